"""The keyframe rule of the factor-graph backend."""

from __future__ import annotations

import numpy as np

from planeslam.backend.config import BackendConfig
from planeslam.core.geometry import as_pose, pose_distances


def is_keyframe(
    config: BackendConfig,
    T_last_kf: np.ndarray,
    T_now: np.ndarray,
    frames_since: int,
    new_planes: int = 0,
    T_keyframes: np.ndarray | None = None,
) -> bool:
    """Whether a frame at T_now (4, 4) becomes a keyframe after the one at T_last_kf (4, 4).

    True when it sees at least `keyframe_new_planes` planes the map does not have yet, or
    when it moved at least `keyframe_min_translation_m`, turned at least
    `keyframe_min_rotation_deg`, or is `keyframe_max_frames` frames after the last one;
    with `keyframe_skip_revisits`, not then when it is that close to any earlier keyframe
    of `T_keyframes` (K, 4, 4): a revisit that sees nothing new adds nothing to the graph.
    """
    if new_planes >= config.keyframe_new_planes:
        return True
    if not (
        frames_since >= config.keyframe_max_frames
        or _moved(config, as_pose(T_last_kf, "T_last_kf"), as_pose(T_now, "T_now"))
    ):
        return False
    if not config.keyframe_skip_revisits or T_keyframes is None or not len(T_keyframes):
        return True
    return not _near_any(config, np.asarray(T_keyframes, dtype=np.float64), T_now)


def _moved(config: BackendConfig, T_a: np.ndarray, T_b: np.ndarray) -> bool:
    metres, degrees = pose_distances(T_a, T_b)
    return bool(
        metres >= config.keyframe_min_translation_m or degrees >= config.keyframe_min_rotation_deg
    )


def _near_any(config: BackendConfig, T_keyframes: np.ndarray, T_now: np.ndarray) -> bool:
    """Whether T_now is within the translation and rotation thresholds of a keyframe."""
    metres, degrees = pose_distances(T_keyframes, T_now)
    return bool(
        np.any(
            (metres < config.keyframe_min_translation_m)
            & (degrees < config.keyframe_min_rotation_deg)
        )
    )


def nearest_keyframe(config: BackendConfig, T_keyframes: np.ndarray, T_now: np.ndarray) -> int:
    """Row of `T_keyframes` (K, 4, 4), K >= 1, nearest to T_now (4, 4): the smallest sum of
    the translation over `keyframe_min_translation_m` and the rotation angle over
    `keyframe_min_rotation_deg` (so one keyframe spacing counts one in either)."""
    metres, degrees = pose_distances(T_keyframes, T_now)
    score = metres / config.keyframe_min_translation_m + degrees / config.keyframe_min_rotation_deg
    return int(np.argmin(score))
