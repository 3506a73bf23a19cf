"""What motion between two frames tracking believes without more evidence.

`near`: a pose the fast path takes on the planes' word (within its correction of the
prediction, or between close frames within its jump limit). `plausible`: a motion a
hand-held or robot-borne camera makes in the time between two frames; a pose beyond it
is not taken on one frame's evidence (a symmetric scene offers places a half-turn off).

Every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

import numpy as np

from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.hypotheses import pose_difference

MAX_SPEED_M_S = 0.6
"""Fastest plausible camera motion between two frames [m/s] (a walking robot, a hand)."""
MAX_TURN_DEG_S = 60.0
"""Fastest plausible camera turn between two frames [deg/s]."""


def near(
    cfg: TrackingConfig,
    T: np.ndarray,
    T_pred: np.ndarray,
    close_frames: bool = False,
    T_last: np.ndarray | None = None,
) -> bool:
    """Whether T (4, 4) is within the fast path's correction of the prediction, or with
    `close_frames` (at most `fast_max_gap_s` apart) within its jump limit of the
    prediction or of the last frame's pose T_last (4, 4): the constant-velocity
    prediction overshoots when the camera stops or turns back, the last pose does not."""
    meters, degrees = pose_difference(T_pred, T)
    if meters <= cfg.fast_max_correction_m and degrees <= cfg.fast_max_correction_deg:
        return True
    if not close_frames:
        return False
    jumps = [(meters, degrees)] + ([] if T_last is None else [pose_difference(T_last, T)])
    return any(m <= cfg.fast_max_jump_m and d <= cfg.fast_max_jump_deg for m, d in jumps)


def plausible(
    cfg: TrackingConfig,
    T: np.ndarray,
    T_last: np.ndarray | None,
    gap_s: float,
    correction: bool = False,
) -> bool:
    """Whether a motion from T_last (4, 4) to T (4, 4) in `gap_s` seconds is one a
    hand-held or robot-borne camera makes: within the fast path's jump limit, or within
    MAX_SPEED_M_S and MAX_TURN_DEG_S over the gap (True without a last pose or time).
    With `correction`, the fast path's correction (`fast_max_correction_*`) is allowed on
    top: T is an estimate of this frame that may also correct the last pose's drift."""
    if T_last is None or not np.isfinite(gap_s):  # no last pose or time: no bound
        return True
    meters, degrees = pose_difference(T_last, T)
    extra_m = cfg.fast_max_correction_m if correction else 0.0
    extra_deg = cfg.fast_max_correction_deg if correction else 0.0
    return meters <= max(cfg.fast_max_jump_m, MAX_SPEED_M_S * gap_s) + extra_m and (
        degrees <= max(cfg.fast_max_jump_deg, MAX_TURN_DEG_S * gap_s) + extra_deg
    )
