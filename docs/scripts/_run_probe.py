"""Shared by the scripts that watch a run from inside (dense_choices.py, dense_landing.py,
sweep_timing.py): which frame is being processed, and the true step it makes."""

from __future__ import annotations

import numpy as np

import planeslam.slam.system as system
from planeslam.core.geometry import invert_pose
from planeslam.tracking.hypotheses import pose_difference


def count_frames() -> dict[str, int]:
    """Wraps `SLAM.process` to count the frames of the run; the returned dict's "frame" is
    the index of the frame being processed (-1 before the first)."""
    current = {"frame": -1}
    process = system.SLAM.process

    def counting(self, *args, **kwargs):
        current["frame"] += 1
        return process(self, *args, **kwargs)

    system.SLAM.process = counting
    return current


def step(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(4, 4) the motion from T_from to T_to, in T_from's camera frame."""
    return invert_pose(T_from) @ T_to


def step_error_m(truth: list[np.ndarray], i: int, T_previous: np.ndarray, T: np.ndarray) -> float:
    """Error [m] of T (4, 4) as frame i's step from T_previous (4, 4), against the true step
    between the (4, 4) poses truth[i - 1] and truth[i]."""
    return pose_difference(step(truth[i - 1], truth[i]), step(T_previous, T))[0]
