"""The sliding window of the iSAM2 backend: the recent keyframes in iSAM2, the rest held fixed.

On the five-pass 7-Scenes replay the whole graph in iSAM2 cost 1.5 s per keyframe by the
fifth pass: each revisit keyframe observes old landmarks, so each update re-eliminates
about a third of a dense graph. With a window, iSAM2 holds only the last keyframes, the
landmarks they observe and the factors among them; every other variable is held at its
last estimate, as ORB-SLAM's local bundle adjustment holds the keyframes outside its
covisible set. A factor between a window variable and a held one enters as its
linearisation with the held variable's columns dropped (conditioning on the held value):
per window variable one `gtsam.LinearContainerFactor` sums them. So the window keeps what
the map outside it says about its landmarks and its first pose (through the odometry from
the keyframe before it), and the update cost depends on the window, not on the map.
`FactorHistory` keeps every factor and the estimate of every variable, for the final
batch optimisation over the whole graph.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence, Set

import gtsam
import numpy as np

from planeslam.factors.config import LandmarkKeys


class FactorHistory:
    """Every committed factor, the factors of each variable and the estimate of every variable."""

    def __init__(self, keys: LandmarkKeys) -> None:
        self.keys = keys
        self.graph = gtsam.NonlinearFactorGraph()
        """Every committed factor (the whole graph, for the final batch optimisation)."""
        self.estimate = gtsam.Values()
        """The last estimate of every variable (the window's variables from the smoother)."""
        self._factors: list[gtsam.NonlinearFactor] = []  # `graph`'s, as the objects added
        self._factors_of: dict[int, list[int]] = defaultdict(list)

    def add(self, factors: Iterable[gtsam.NonlinearFactor]) -> None:
        """Commit factors (in order)."""
        for factor in factors:
            position = len(self._factors)
            self.graph.add(factor)
            self._factors.append(factor)
            for key in factor.keys():
                self._factors_of[key].append(position)

    def remove(self, factors: Iterable[gtsam.NonlinearFactor]) -> int:
        """Take committed factors out (the very objects given to `add`); returns how many."""
        gone = {id(f) for f in factors}
        kept = [f for f in self._factors if id(f) not in gone]
        removed = len(self._factors) - len(kept)
        if removed:
            self.graph = gtsam.NonlinearFactorGraph()
            self._factors = []
            self._factors_of = defaultdict(list)
            self.add(kept)
        return removed

    def copy_graph(self) -> gtsam.NonlinearFactorGraph:
        """A new graph of every committed factor."""
        graph = gtsam.NonlinearFactorGraph()
        for factor in self._factors:
            graph.add(factor)
        return graph

    def take_estimate(self, values: gtsam.Values) -> None:
        """Take newer values of some variables (new ones inserted)."""
        self.estimate.insert_or_assign(values)

    def factors_of(self, keys: Iterable[int]) -> list[gtsam.NonlinearFactor]:
        """The committed factors on any of `keys`, each once, in commit order."""
        positions = sorted({p for key in keys for p in self._factors_of.get(key, ())})
        return [self._factors[p] for p in positions]

    def neighbours(self, keys: Iterable[int]) -> set[int]:
        """The variables that share a factor with any of `keys` (and `keys`)."""
        return {k for factor in self.factors_of(keys) for k in factor.keys()}

    def dim(self, key: int) -> int:
        """Tangent dimension of a variable: 6 for a pose, 3 for a plane or a corner."""
        return 6 if chr(gtsam.Symbol(key).chr()) == self.keys.pose_char else 3

    def values_of(self, keys: Iterable[int]) -> gtsam.Values:
        """The estimate of `keys` as a new Values."""
        out = gtsam.Values()
        for key in keys:
            char = chr(gtsam.Symbol(key).chr())
            if char == self.keys.pose_char:
                out.insert(key, self.estimate.atPose3(key))
            elif char == self.keys.plane_char:
                out.insert(key, self.estimate.atOrientedPlane3(key))
            else:
                out.insert(key, self.estimate.atPoint3(key))
        return out

    def conditioned(
        self, factors: Sequence[gtsam.NonlinearFactor], free: set[int]
    ) -> list[gtsam.LinearContainerFactor]:
        """The factors' information on the `free` variables with every other variable held
        at its estimate: each factor linearised at the estimate (whitened, robust weights
        applied), the held variables' columns dropped, and the rows summed (QR) per free
        variable into one `LinearContainerFactor` linearised at the estimate. Each factor
        must have exactly one free variable."""
        rows: dict[int, list[np.ndarray]] = defaultdict(list)
        for factor in factors:
            mine = [k for k in factor.keys() if k in free]
            if len(mine) != 1:
                raise ValueError(
                    f"FactorHistory.conditioned: a factor on {len(mine)} free variables "
                    "(expected 1)"
                )
            jacobian = gtsam.JacobianFactor(factor.linearize(self.estimate))
            A, b = jacobian.jacobian()
            start = 0
            for key in jacobian.keys():
                if key == mine[0]:
                    rows[key].append(np.column_stack([A[:, start : start + self.dim(key)], b]))
                start += self.dim(key)
        out = []
        for key, blocks in rows.items():
            n = self.dim(key)
            # [R d] of the stacked [A b]; rows past n would hold only the residual's norm.
            R = np.linalg.qr(np.vstack(blocks))[1][:n]
            linear = gtsam.JacobianFactor(
                key, R[:, :n], R[:, n], gtsam.noiseModel.Unit.Create(R.shape[0])
            )
            out.append(gtsam.LinearContainerFactor(linear, self.values_of([key])))
        return out


def split_factors(
    factors: Iterable[gtsam.NonlinearFactor], free: Set[int], inside: Set[int] = frozenset()
) -> tuple[list[gtsam.NonlinearFactor], list[gtsam.NonlinearFactor]]:
    """Split the factors of variables entering the window (`free`) into those the window
    holds as they are (every key free) and those to condition on the held variables
    (`FactorHistory.conditioned`). Factors on a variable already `inside` the window are
    left out: the window took their information when that variable entered it."""
    whole: list[gtsam.NonlinearFactor] = []
    conditioned: list[gtsam.NonlinearFactor] = []
    for factor in factors:
        keys = set(factor.keys())
        if keys & inside:
            continue
        (whole if keys <= free else conditioned).append(factor)
    return whole, conditioned
