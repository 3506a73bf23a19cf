"""An iSAM2 that survives an indeterminate system: the recovery path for landmark factors
added to a caller's graph (and the one `planeslam.backend.isam2` takes).

gtsam raises a RuntimeError ("Indeterminant linear system ... near variable K") when an
update leaves a variable unconstrained: a pose seen through fewer than three independent
planes and no odometry, a landmark tied by too little. iSAM2 is not exception safe: after
the error its Bayes tree may hold part of the failed update. `RecoveringISAM2.update`
therefore rebuilds the smoother from the factors committed before and the last estimate,
and retries the update with fewer of the landmark factors of `AddedFactors`:

1. without the factors of the variable the message names (unless it is one of the
   caller's own new variables);
2. without the factors of every new landmark;
3. without any landmark factor;

and raises GeometryError when even the caller's own factors fail (give every pose an
odometry factor or a prior). New landmarks left out are forgotten by the `PlaneLandmarks`
(a later frame creates them again), which then takes the new estimate.

With an ISAM2 of your own the same path, by hand: catch the RuntimeError of
`isam.update`; make a new ISAM2 and update it with every factor committed before and the
last estimate; `landmarks.forget(added.new_planes, added.new_corners)`; update again with
your own factors and values only.

The smoother keeps a Python handle on its linearisation point: pybind11 otherwise copies
the whole estimate into every call of a Python factor (see `planeslam.factors.landmarks`).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass

import gtsam

from planeslam.core.errors import ConfigError, GeometryError

from .landmarks import AddedFactors, PlaneLandmarks

logger = logging.getLogger(__name__)

_KEY_IN_MESSAGE = re.compile(r"near variable\s+(\d+)")


@dataclass(frozen=True)
class UpdateOutcome:
    """What one `RecoveringISAM2.update` committed and what it left out."""

    factors: tuple[gtsam.NonlinearFactor, ...]
    """Factors committed: the caller's, then the landmark factors kept."""
    failures: int
    """Indeterminate updates caught and recovered from (0: the first try went through)."""
    dropped_factors: int
    """Landmark factors left out."""
    dropped_planes: tuple[int, ...]
    """New plane landmarks left out (and forgotten by the `PlaneLandmarks`)."""
    dropped_corners: tuple[int, ...]
    """New corner landmarks left out (and forgotten)."""


def new_isam2(params: gtsam.ISAM2Params) -> tuple[gtsam.ISAM2, gtsam.Values]:
    """An ISAM2 and a Python handle on its linearisation point, to be kept as long as it.

    pybind11 copies a C++ `const Values&` into a new Python object for every call of a
    Python factor (`CustomFactor`) unless a Python object for that very Values exists:
    without the handle each robust plane, corner and structural factor copies the whole
    estimate each time iSAM2 linearises it, which made updates O(map size) per factor.
    """
    isam = gtsam.ISAM2(params)
    return isam, isam.getLinearizationPoint()


class RecoveringISAM2:
    """iSAM2 over a caller's factors and our landmark factors, rebuilt and retried with fewer
    landmark factors when an update is indeterminate (see the module docstring)."""

    def __init__(self, params: gtsam.ISAM2Params | None = None, extra_updates: int = 0) -> None:
        """`extra_updates`: relinearising `ISAM2.update()` calls after each update."""
        if (
            isinstance(extra_updates, bool)
            or int(extra_updates) != extra_updates
            or extra_updates < 0
        ):
            raise ConfigError(f"extra_updates={extra_updates!r}: expected an integer >= 0")
        self.params = params if params is not None else gtsam.ISAM2Params()
        self.extra_updates = int(extra_updates)
        self.graph = gtsam.NonlinearFactorGraph()
        """Every factor committed so far (what a rebuild starts from)."""
        self._estimate = gtsam.Values()
        self._isam: gtsam.ISAM2 | None = None  # made on the first update
        self._theta: gtsam.Values | None = None
        self.failures = 0
        """Indeterminate updates caught so far."""

    @property
    def isam(self) -> gtsam.ISAM2:
        """The current ISAM2 (e.g. for `marginalCovariance`); a rebuild replaces it."""
        if self._isam is None:
            self.rebuild()
        assert self._isam is not None, "rebuild makes the smoother"
        return self._isam

    @property
    def estimate(self) -> gtsam.Values:
        """The estimate after the last update (not a copy)."""
        return self._estimate

    def set_estimate(self, estimate: gtsam.Values) -> None:
        """Replace the estimate (e.g. with a batch optimisation's result over `graph`); the
        smoother is rebuilt from it on the next update."""
        self._estimate = estimate
        self._isam = self._theta = None

    def restart(self, graph: gtsam.NonlinearFactorGraph, estimate: gtsam.Values) -> None:
        """Hold only `graph` at `estimate` from now on (a fresh iSAM2 over them, e.g. a
        sliding window of a larger graph). RuntimeError, with the smoother as it was,
        when `graph` is indeterminate."""
        previous = (self.graph, self._estimate)
        self.graph, self._estimate = graph, estimate
        try:
            self.rebuild()
        except RuntimeError:
            self.graph, self._estimate = previous
            self.rebuild()
            raise

    def relinearise(self, iterations: int) -> None:
        """`iterations` more `ISAM2.update()` calls (relinearising what moved), then take the
        estimate: after a `restart` from an estimate far from the optimum."""
        isam = self.isam
        for _ in range(iterations):
            isam.update()
        self._estimate = isam.calculateEstimate()

    def rebuild(self) -> None:
        """A fresh iSAM2 from the committed factors, linearised at the last estimate."""
        self._isam, self._theta = new_isam2(self.params)
        if self.graph.size():
            self._isam.update(self.graph, self._estimate)

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        added: AddedFactors | None = None,
        landmarks: PlaneLandmarks | None = None,
    ) -> UpdateOutcome:
        """Commit the caller's new factors `graph` and values `values` with the landmark
        factors and new landmark values of `added` (made by `PlaneLandmarks.add_observations`
        into a graph and values of their own, not into `graph` / `values`). On an
        indeterminate system, rebuild and retry with fewer landmark factors. `landmarks`:
        the table that made `added`; it forgets the new landmarks left out and takes the
        new estimate. GeometryError when the caller's own factors are indeterminate."""
        if self._isam is None:
            self.rebuild()
        own = [graph.at(i) for i in range(graph.size())]
        own_keys = set(values.keys())
        ours = list(added.factors) if added is not None else []
        new_keys = set(added.new_keys) if added is not None else set()
        dropped: set[int] = set()
        failures = 0
        level = 0  # 0: drop the named keys, 1: all new landmarks, 2: all landmark factors
        message = ""
        while True:
            kept = [f for f in ours if not _left_out(set(f.keys()), level, dropped, new_keys)]
            used = {k for f in own + kept for k in f.keys()}
            floating = sorted(own_keys - used)
            if failures and floating:  # iSAM2 would take them, unconstrained
                names = ", ".join(gtsam.DefaultKeyFormatter(k) for k in floating)
                raise GeometryError(
                    f"iSAM2 update indeterminate, and without the landmark factors {names} "
                    "has no factor: give every new pose an odometry factor or a prior "
                    f"({message[:200]})"
                )
            update_graph = gtsam.NonlinearFactorGraph()
            for factor in own + kept:
                update_graph.add(factor)
            update_values = gtsam.Values(values)
            if added is not None:
                ours_used = gtsam.Values(added.values)
                for key in added.new_keys:
                    if ours_used.exists(key) and (key not in used or update_values.exists(key)):
                        ours_used.erase(key)
                update_values.insert(ours_used)
            isam = self._isam
            assert isam is not None, "rebuild makes the smoother"
            try:
                isam.update(update_graph, update_values)
                for _ in range(self.extra_updates):
                    isam.update()
            except RuntimeError as exc:
                failures += 1
                self.failures += 1
                message = " ".join(str(exc).split())
                match = _KEY_IN_MESSAGE.search(message)
                bad = int(match.group(1)) if match else None
                logger.warning("iSAM2 update failed (%s); rebuilding and retrying", message[:120])
                self.rebuild()
                if level == 0 and bad is not None and bad not in own_keys and bad not in dropped:
                    dropped.add(bad)
                elif level < 2 and ours:
                    level += 1
                else:
                    raise GeometryError(
                        "iSAM2 cannot take the update even without its landmark factors: "
                        "give every new pose an odometry factor or a prior "
                        f"({message[:200]})"
                    ) from None
                continue
            self._estimate = isam.calculateEstimate()
            for factor in own + kept:
                self.graph.add(factor)
            lost_planes: tuple[int, ...] = ()
            lost_corners: tuple[int, ...] = ()
            if added is not None and landmarks is not None:
                lost = {k for k in added.new_keys if k not in used}
                keys = landmarks.keys
                lost_planes = tuple(j for j in added.new_planes if keys.plane(j) in lost)
                lost_corners = tuple(c for c in added.new_corners if keys.corner(c) in lost)
                if lost_planes or lost_corners:
                    landmarks.forget(lost_planes, lost_corners)
                    logger.warning(
                        "dropped %d new plane and %d new corner landmarks",
                        len(lost_planes),
                        len(lost_corners),
                    )
                landmarks.update_estimates(self._estimate)
            return UpdateOutcome(
                factors=tuple(own + kept),
                failures=failures,
                dropped_factors=len(ours) - len(kept),
                dropped_planes=lost_planes,
                dropped_corners=lost_corners,
            )


def _left_out(keys: set[int], level: int, dropped: set[int], new_keys: set[int]) -> bool:
    """Whether a landmark factor on `keys` stays out at this retry level."""
    return level >= 2 or bool(keys & dropped) or (level >= 1 and bool(keys & new_keys))


__all__ = ["RecoveringISAM2", "UpdateOutcome", "new_isam2"]
