"""The paper's frame-by-frame merging (Section 4.4) as a backend.

The orchestrator merges every mapped frame into the plane-object map before handing it
to a backend; for the paper's system that merge is all there is. So every mapped frame is
a keyframe, each update confirms the tracked pose and moves no landmark, objects are
re-aggregated at every merge, and `finish` revises nothing.
"""

from __future__ import annotations

import numpy as np

from planeslam.backend.base import BackendKind, BackendResult, KeyframeInput, KeyframeUpdate
from planeslam.core.errors import PlaneSlamError


class MergeBackend:
    """`Backend` of the paper's system: poses are never revised."""

    kind = BackendKind.MERGE
    lag_frames = 0
    objects_every_keyframe = True
    takes_loops = False
    map_cull_single_view_after = 0
    map_merge_segments = False

    def __init__(self) -> None:
        self._poses: dict[int, np.ndarray] = {}
        self._pending: list[KeyframeInput] = []
        self._finished = False

    def is_keyframe(
        self, T_keyframes: np.ndarray, T_now: np.ndarray, frames_since: int, new_planes: int
    ) -> bool:
        return True

    def submit(self, keyframe: KeyframeInput) -> None:
        if self._finished:
            raise PlaneSlamError("the merge backend has finished; create a new SLAM")
        self._poses[keyframe.index] = keyframe.T_world_cam
        self._pending.append(keyframe)

    def collect(self) -> KeyframeUpdate:
        if not self._pending:
            raise PlaneSlamError("MergeBackend.collect: no keyframe was submitted")
        keyframe = self._pending.pop(0)
        return KeyframeUpdate(keyframe.index, keyframe.T_world_cam, {}, {}, update_ms=0.0)

    def finish(self) -> BackendResult:
        self._finished = True
        self._pending.clear()
        return BackendResult(keyframe_poses=dict(self._poses))

    def close(self) -> None:
        self._finished = True
        self._pending.clear()
