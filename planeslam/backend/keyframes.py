"""The keyframe rule of the factor-graph backend."""

from __future__ import annotations

import math

import numpy as np

from planeslam.backend.config import BackendConfig
from planeslam.core.geometry import as_pose, invert_pose


def is_keyframe(
    config: BackendConfig,
    T_last_kf: np.ndarray,
    T_now: np.ndarray,
    frames_since: int,
    new_planes: int = 0,
) -> bool:
    """Whether a frame at T_now (4, 4) becomes a keyframe after the one at T_last_kf (4, 4).

    True when it moved at least `keyframe_min_translation_m`, turned at least
    `keyframe_min_rotation_deg`, is `keyframe_max_frames` frames after it, or sees at least
    `keyframe_new_planes` planes the map does not have yet.
    """
    T_rel = invert_pose(as_pose(T_last_kf, "T_last_kf")) @ as_pose(T_now, "T_now")
    cos = np.clip((np.trace(T_rel[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return bool(
        frames_since >= config.keyframe_max_frames
        or new_planes >= config.keyframe_new_planes
        or np.linalg.norm(T_rel[:3, 3]) >= config.keyframe_min_translation_m
        or math.degrees(math.acos(cos)) >= config.keyframe_min_rotation_deg
    )
