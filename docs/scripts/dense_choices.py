"""What the dense fallback tried and took, frame by frame, against the true step
(docs/experiments.md, "Choosing among the dense fallback's results").

    python docs/scripts/dense_choices.py SEQUENCE OUT [FRAMES] [INDICES]

Runs `planeslam run` on the TUM-layout folder SEQUENCE (with groundtruth.txt, one pose
per frame, as `planeslam synth` writes) into OUT, the first FRAMES frames (default all).
For every frame (or only the comma-separated INDICES) that reaches the dense fallback it
prints the true step, each start and each result as a step from the previous frame's
pose with its error against the true step [cm] and its landing cost
(`sweep.landing_cost`, what chooses among the results), each result's median colour
difference (what chose before), and the result taken. Steps are (x, y, z) [m] in the
previous camera's frame and turns [deg].
"""

from __future__ import annotations

import math
import sys

import numpy as np
from _run_probe import count_frames, step, step_error_m, watched_run

import planeslam.tracking.dense as dense
from planeslam.app.runner import run_sequence
from planeslam.core.geometry import rotation_angle

run = watched_run(sys.argv)
current = count_frames()


def _shown_step(motion: np.ndarray) -> str:
    """A (4, 4) step as its translation [m] and its turn [deg]."""
    turn = math.degrees(rotation_angle(motion[:3, :3]))
    return f"{np.round(motion[:3, 3], 3)} {turn:.1f} deg"


def _described(fallback: dense.DenseFallback, T: np.ndarray) -> str:
    """T (4, 4) as a step from the previous frame's pose, and its error against the truth."""
    i = current["frame"]
    assert fallback.previous_pose is not None
    error_m = step_error_m(run.truth, i, fallback.previous_pose, T)
    return f"{_shown_step(step(fallback.previous_pose, T))} (error {100 * error_m:.1f} cm)"


def _shown() -> bool:
    return run.shown(current["frame"])


def _showing_register(register):
    def wrapper(self, starts, cloud, rgbd, reasons, *args, **kwargs):
        if _shown():
            true_step = step(run.truth[current["frame"] - 1], run.truth[current["frame"]])
            print(f"frame {current['frame']}: true step {_shown_step(true_step)}")
            for T in starts:
                cost = self._landing_cost(cloud, rgbd, T)
                print("  start", _described(self, T), f"landing cost {cost:.4f}")
        taken = register(self, starts, cloud, rgbd, reasons, *args, **kwargs)
        if _shown():
            print("  taken", "nothing" if taken is None else _described(self, taken.T))
        return taken

    return wrapper


def _showing_acceptable(acceptable):
    def wrapper(self, kind, T, cloud, rgbd, *args, **kwargs):
        accepted = acceptable(self, kind, T, cloud, rgbd, *args, **kwargs)
        if _shown():
            measured = self.colour_difference(cloud, rgbd, T)
            median = "-" if measured is None else f"{measured[0]:.3f}"
            print(
                f"    {kind.value}: {_described(self, T)} accepted {accepted}, "
                f"median colour difference {median}, "
                f"landing cost {self._landing_cost(cloud, rgbd, T):.4f}"
            )
        return accepted

    return wrapper


dense.DenseFallback.register = _showing_register(dense.DenseFallback.register)
dense.DenseFallback._acceptable = _showing_acceptable(dense.DenseFallback._acceptable)
run_sequence(run.sequence, run.out, max_frames=run.frames)
