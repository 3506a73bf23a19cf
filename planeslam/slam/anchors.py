"""Every frame's pose anchored on a keyframe, so that optimisation moves it with that keyframe.

A frame's pose is kept as T_anchor_cam (4, 4): the pose relative to its anchor keyframe's
online pose when it was tracked. The anchor is the frame itself for a keyframe, the
keyframe nearest in pose for a tracked frame (on a revisit, the keyframe made there
before rather than the last one), and the last keyframe for a lost frame. A keyframe has
two poses: online (as tracked, then as its own backend update optimised it) and final
(after the last optimisation; the online one until then). A frame's final pose is its
anchor's final pose @ T_anchor_cam; at the end, the frames between keyframes are
re-estimated against the final map (`final_poses`). Poses are T_world_cam (4, 4) [m];
frames are indexed 0, 1, ... in the order they were processed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from planeslam.backend.config import BackendConfig
from planeslam.backend.keyframes import nearest_keyframe
from planeslam.core.geometry import invert_pose
from planeslam.io.trajectory import Trajectory
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.estimator import ConstraintThresholds, EstimatorSettings
from planeslam.tracking.final_poses import FrameTerms, final_poses
from planeslam.tracking.glitches import PoseGlitches, find_pose_glitches
from planeslam.tracking.views import MapView

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FinalMap:
    """What the frames' final poses are estimated against when a run finishes."""

    view: MapView
    """The final map's planes and corners (world frame)."""
    settings: EstimatorSettings
    """Tracking's refinement settings (`Tracker.refine_settings`)."""
    thresholds: ConstraintThresholds
    """When a direction counts as fixed (`Tracker.thresholds`)."""
    config: TrackingConfig
    """`final_poses` and the corner noise."""


class AnchoredPoses:
    """The frames' timestamps, whether each has a pose, and each pose on its anchor."""

    def __init__(self, config: BackendConfig) -> None:
        """`config`: the keyframe spacing that measures which keyframe is nearest in pose
        (`nearest_keyframe`)."""
        self._config = config
        self.timestamps: list[float] = []
        """Per frame [s]."""
        self.last_keyframe: int | None = None
        self._tracked: list[bool] = []
        """Per frame: whether it has a pose (False: lost, or in a segment not joined yet)."""
        self._anchor: list[int] = []
        """Per frame: the keyframe (frame index) its pose is expressed against (-1: none)."""
        self._T_anchor_cam: list[np.ndarray] = []
        """Per frame: pose relative to its anchor keyframe's online pose."""
        self._online: dict[int, np.ndarray] = {}
        """Keyframe pose when it was added (tracked, or optimised by its own update)."""
        self._online_array: np.ndarray | None = None
        """`_online` as one (K, 4, 4) array, rebuilt after a change."""
        self._final: dict[int, np.ndarray] = {}
        """Keyframe pose after the last optimisation (`set_final`); the online one until then."""
        self._terms: dict[int, FrameTerms] = {}
        """Per tracked frame between keyframes: the planes and corners its pose rests on, for
        its re-estimate against the final map (`tracking.final_poses`)."""

    def __len__(self) -> int:
        return len(self.timestamps)

    # ---------------------------------------------------------------------- keyframes

    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) online keyframe poses, increasing frame index (the last one last)."""
        if self._online_array is None:
            self._online_array = np.asarray(list(self._online.values()))
        return self._online_array

    def online(self, index: int) -> np.ndarray:
        """(4, 4) online pose of keyframe `index`."""
        return self._online[index]

    def set_online(self, index: int, T_world_cam: np.ndarray) -> None:
        self._online[index] = T_world_cam
        self._online_array = None

    def optimised(self, index: int, T_world_cam: np.ndarray) -> np.ndarray:
        """Keyframe `index` takes its optimised pose T_world_cam (4, 4), online and final.
        Returns the correction (4, 4) T_optimised @ T_online^-1."""
        correction = T_world_cam @ invert_pose(self._online[index])
        self.set_online(index, T_world_cam)
        self._final[index] = T_world_cam
        return correction

    def set_final(self, keyframe_poses: Mapping[int, np.ndarray]) -> None:
        """The final optimisation's {keyframe index: T_world_cam (4, 4)}."""
        self._final.update(keyframe_poses)

    def final_keyframes(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe index, final T_world_cam (4, 4)), increasing index."""
        return sorted(self._final.items())

    # ---------------------------------------------------------------------- frames

    def add(
        self,
        timestamp: float,
        T_world_cam: np.ndarray,
        keyframe: bool,
        lost: bool,
        terms: FrameTerms | None = None,
    ) -> None:
        """The next frame at T_world_cam (4, 4), anchored (module docstring); a keyframe
        becomes its own anchor. `terms`: what a tracked frame between keyframes rests on."""
        index = len(self)
        self._tracked.append(not lost)
        if keyframe:  # the first frame always is one, so every frame has an anchor
            self.last_keyframe = index
            self.set_online(index, T_world_cam)
            self._final[index] = T_world_cam
        anchor = self._anchor_of(T_world_cam, keyframe, lost)
        assert anchor is not None or lost, "the first tracked frame is always a keyframe"
        self.timestamps.append(float(timestamp))
        self._anchor.append(-1 if anchor is None else anchor)  # -1: lost before any keyframe
        T_anchor = np.eye(4) if anchor is None else self._online[anchor]
        self._T_anchor_cam.append(invert_pose(T_anchor) @ T_world_cam)
        if terms is not None and not (keyframe or lost):
            self._terms[index] = terms

    def _anchor_of(self, T_world_cam: np.ndarray, keyframe: bool, lost: bool) -> int | None:
        """The anchor of a frame at T_world_cam (4, 4) (module docstring); None before any
        keyframe."""
        if keyframe or lost or len(self._online) < 2:
            return self.last_keyframe
        indices = list(self._online)
        return indices[nearest_keyframe(self._config, self.keyframe_poses(), T_world_cam)]

    def anchor(self, index: int) -> int | None:
        """The keyframe (frame index) whose final pose frame `index` follows; None: lost
        before any keyframe."""
        return self._anchor[index] if self._anchor[index] >= 0 else None

    def is_tracked(self, index: int) -> bool:
        return self._tracked[index]

    def tracked_since(self, index: int) -> bool:
        """Whether every frame after frame `index` has a pose."""
        return all(self._tracked[index + 1 :])

    @property
    def tracked_frames(self) -> int:
        """Frames with a pose."""
        return int(sum(self._tracked))

    def join(self, index: int, T_seg_cam: Mapping[int, np.ndarray]) -> None:
        """Frame `index`, placed in the map, joins a segment whose poses are `T_seg_cam`
        ({frame: (4, 4) in the segment's frame}, `index` included): its earlier frames get
        a pose, anchored where frame `index` is (so later corrections move them with it)."""
        anchor, T_anchor_join = self._anchor[index], self._T_anchor_cam[index]
        T_join_seg = invert_pose(T_seg_cam[index])
        for k, T in T_seg_cam.items():
            if k < index:
                self._anchor[k] = anchor
                self._T_anchor_cam[k] = T_anchor_join @ T_join_seg @ T
                self._tracked[k] = True

    def forget_keyframes(self) -> dict[int, np.ndarray]:
        """The map was dropped (a segment replaced it): no keyframe is left, and no frame
        so far has a pose until it joins the next map. Returns {frame: T_world_cam (4, 4)}
        of the frames that had one, in the dropped map's world frame."""
        poses = {k: self.final_pose(k) for k, tracked in enumerate(self._tracked) if tracked}
        self.last_keyframe = None
        self._tracked = [False] * len(self._tracked)
        self._anchor = [-1] * len(self._anchor)
        self._online.clear()
        self._online_array = None
        self._final.clear()
        self._terms.clear()
        return poses

    # ---------------------------------------------------------------------- final poses

    def final_pose(self, index: int) -> np.ndarray:
        """(4, 4) T_world_cam of frame `index` on its anchor's final pose."""
        return self._final[self._anchor[index]] @ self._T_anchor_cam[index]

    def set_final_pose(self, index: int, T_world_cam: np.ndarray) -> None:
        """Frame `index` takes T_world_cam (4, 4) in the final map, kept relative to its
        anchor keyframe's final pose."""
        self._T_anchor_cam[index] = invert_pose(self._final[self._anchor[index]]) @ T_world_cam

    def trajectory(self) -> Trajectory:
        """Every tracked frame's final pose; lost frames are left out (as ORB-SLAM does)."""
        rows = [k for k, tracked in enumerate(self._tracked) if tracked]
        poses = [self.final_pose(k) for k in rows]
        return Trajectory(
            timestamps=np.asarray(self.timestamps, dtype=np.float64)[rows],
            T_world_cam=np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
        )

    def glitches(
        self, config: TrackingConfig, trajectory: Trajectory | None = None
    ) -> PoseGlitches:
        """The glitches of `trajectory` (default: this one's) under `config`'s jump limits:
        poses beyond `fast_max_jump_*` off the path of the frames within 2 `fast_max_gap_s`
        [s] around them (`find_pose_glitches`)."""
        return find_pose_glitches(
            self.trajectory() if trajectory is None else trajectory,
            2.0 * config.fast_max_gap_s,
            config.fast_max_jump_m,
            config.fast_max_jump_deg,
        )

    def reestimate(self, final: FinalMap) -> dict[str, float]:
        """After the final optimisation (`set_final`): each frame between keyframes
        re-estimated against `final` (`tracking.final_poses`); a frame the map does not fix
        keeps its anchored pose. Returns the counts ('reestimated', 'kept') and the
        wall-clock 'ms'."""
        start = time.perf_counter()
        terms, self._terms = self._terms, {}
        frames = {k: (frame_terms, self.final_pose(k)) for k, frame_terms in terms.items()}
        config = final.config
        found = final_poses(
            frames,
            final.view,
            final.settings,
            final.thresholds,
            config.sigma_point_m,
        )
        for k, T_world_cam in found.items():
            self.set_final_pose(k, T_world_cam)
        summary = {
            "reestimated": len(found),
            "kept": len(frames) - len(found),
            "ms": 1e3 * (time.perf_counter() - start),
        }
        logger.info(
            "final map: %d of %d frames between keyframes re-estimated in %.0f ms",
            len(found),
            len(frames),
            summary["ms"],
        )
        return summary
