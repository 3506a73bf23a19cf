"""Map segments: tracking that restarts after a loss instead of staying lost.

When a frame cannot be placed in the map, a `Segment` starts at it: later frames are
tracked in the segment's own frame (the camera frame of its first frame) against its
most recent keyframe (planes, corners, edges and keypoints, the same estimator as in the
map, and its dense fallbacks against the previous frame), while every frame is also
tried against the whole map. A frame that tracks in the segment and is placed in the map
near the map's prediction or by keypoints joins them; a frame placed by a whole-map
relocalisation joins them only when a second one puts the segment at the same place
(`PlacementVote`: a symmetric scene offers places a half-turn off). T_world_seg follows from
the joining frame's two poses, and every frame of the segment gets its world pose
through it (the orchestrator re-anchors them on the joining frame, so later
optimisation moves them too).
A segment frame that the segment cannot track either starts a new segment; frames of a
segment that never joins stay lost, unless the segment has tracked more frames than the
map holds: then it replaces the map (`planeslam.slam.system.SLAM` starts a new map at
the segment's latest frame, the segment's first frame where the old map predicted it).
The old map becomes a `DroppedMap`: its frames have no pose until a keyframe of the new
map relocalises in it, twice at one place, and then rejoin through that keyframe. (ORB-SLAM
resets a map lost within its first keyframes; ORB-SLAM3's atlas keeps the old map and
merges it when a place is recognised. Here the old map's frames come back, its
landmarks do not.)

Nothing of a segment enters the map or the factor graph before it joins: the map stays
one consistent world, and a joined segment's frames hang on the joining keyframe.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.geometry import invert_pose
from planeslam.core.types import TrackingPath
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.keypoints import Keypoints
from planeslam.tracking.tracker import Tracker, TrackResult
from planeslam.tracking.views import FrameView, MapView, frame_as_map

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation


class PlacementVote:
    """Where whole-map relocalisations put a set of frames, T_world_set (4, 4). One is not
    enough (a symmetric scene offers places a half-turn off): a placement counts when the
    next one puts the set within `fast_max_jump_m` / `fast_max_jump_deg` of it."""

    def __init__(self, config: TrackingConfig) -> None:
        self.config = config
        self.candidate: np.ndarray | None = None
        """(4, 4) the last placement, awaiting the next."""

    def confirms(self, T_world_set: np.ndarray) -> bool:
        """Whether T_world_set (4, 4) agrees with the last placement; it becomes the
        candidate either way."""
        previous, self.candidate = self.candidate, T_world_set
        if previous is None:
            return False
        meters, degrees = pose_difference(previous, T_world_set)
        return meters <= self.config.fast_max_jump_m and degrees <= self.config.fast_max_jump_deg


class Segment:
    """Frames tracked since a loss, in the camera frame of the segment's first frame."""

    def __init__(
        self,
        index: int,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        depth_m: np.ndarray | None,
        config: TrackingConfig,
        camera: CameraConfig | None,
        sensor: DepthNoiseConfig | None,
        seed: int = 0,
        result: TrackResult | None = None,
        odometry=None,
    ) -> None:
        """Start at frame `index` (its observation, colour and (H, W) depth [m]); `result`
        the map tracker's (lost) result for it, whose keypoints are reused and whose pose
        (the map's prediction) is `T_world_seg_guess`; `odometry` the map tracker's
        `odometry.RgbdOdometry` (stateless), so planes that fix only some directions are
        completed as in the map."""
        self.config = config
        self.first = index
        self.tracker = Tracker(config, odometry, camera, sensor, seed, empty_map_starts=False)
        self.poses: dict[int, np.ndarray] = {index: np.eye(4)}
        """Frame index -> T_seg_cam (4, 4) of every frame the segment tracked."""
        self._view = frame_as_map(FrameView.of(observation, camera), np.eye(4))
        self._last = np.eye(4)
        self.velocity = np.eye(4)
        """The last motion T_prev_cur (4, 4) tracked in the segment."""
        self._last_keyframe = np.eye(4)
        self.placements = PlacementVote(config)
        """Where relocalised frames put the segment in the map (T_world_seg)."""
        self.T_world_seg_guess = np.eye(4) if result is None else result.T_world_cam
        """(4, 4) where the map predicted the segment's first frame: its place, should the
        segment replace the map."""
        keypoints = result.keypoints if result is not None else None
        self.tracker.add_keyframe(index, np.eye(4), rgb, observation.cloud, keypoints)
        self.tracker.start(observation, np.eye(4), rgb, depth_m)

    def confirms(self, T_world_cam: np.ndarray, T_seg_cam: np.ndarray) -> bool:
        """Whether a relocalised frame's pose T_world_cam (4, 4), tracked at T_seg_cam (4, 4)
        in the segment, puts the segment where an earlier relocalised frame did
        (`PlacementVote`)."""
        return self.placements.confirms(T_world_cam @ invert_pose(T_seg_cam))

    def track(
        self,
        index: int,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        depth_m: np.ndarray | None,
    ) -> np.ndarray | None:
        """T_seg_cam (4, 4) of frame `index` in the segment, or None when the segment
        cannot track it. A frame far enough from the last keyframe becomes one."""
        result = self.tracker.track(
            observation, self._view, self._last @ self.velocity, rgb, depth_m
        )
        if result.lost:  # a dense fallback's pose counts: the segment only chains motions
            return None
        T = result.T_world_cam
        self.velocity = invert_pose(self._last) @ T
        self._last = T
        self.poses[index] = T
        meters, degrees = pose_difference(self._last_keyframe, T)
        if meters >= self.config.segment_keyframe_m or degrees >= self.config.segment_keyframe_deg:
            self._view = frame_as_map(FrameView.of(observation, self.tracker.camera), T)
            self._last_keyframe = T
            self.tracker.add_keyframe(index, T, rgb, observation.cloud, result.keypoints)
        return T


class DroppedMap:
    """A map that a segment outgrew and replaced: its frames' poses in its own world frame
    and what places later frames in it, so that its frames rejoin the run when keyframes
    of the new map relocalise in it (twice at one place: `PlacementVote`)."""

    def __init__(self, tracker: Tracker, view: MapView, poses: dict[int, np.ndarray]) -> None:
        """`tracker`: the dropped map's (its keyframes' keypoints); `view`: its planes and
        corners; `poses`: frame index -> T_old_cam (4, 4) of its tracked frames."""
        self.tracker = tracker
        self.view = view
        self.poses = poses
        self.placements = PlacementVote(tracker.config)
        """Where relocalised keyframes put this map in the new one (T_new_old)."""

    def place(
        self, frame: FrameView, T_world_cam: np.ndarray, keypoints: Keypoints | None
    ) -> np.ndarray | None:
        """T_old_cam (4, 4) of a keyframe (`frame`, its `keypoints`) at T_world_cam (4, 4)
        in the new map when a whole-map relocalisation places it in this map where the
        previous one put this map (its frames then rejoin through it), else None."""
        placed = self.tracker.relocalise(frame, self.view, T_world_cam, keypoints)
        if placed is None or not self.placements.confirms(T_world_cam @ invert_pose(placed.T)):
            return None
        return placed.T


class Segments:
    """The segment open since the last loss, if any, beside the map's tracker: a lost frame
    starts one; while one is open, every frame is tracked in it too, until a frame placed in
    the map joins it (module docstring)."""

    def __init__(
        self,
        tracker: Tracker,
        config: TrackingConfig,
        camera: CameraConfig | None,
        sensor: DepthNoiseConfig | None,
        seed: int = 0,
    ) -> None:
        """`tracker`: the map's; a segment starting at frame k draws from `seed` + k."""
        self.tracker = tracker
        self.config = config
        self.camera = camera
        self.sensor = sensor
        self.seed = seed
        self.open: Segment | None = None
        """The segment tracking since the last loss, until it joins the map."""

    def step(
        self,
        index: int,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        depth_m: np.ndarray,
        track: TrackResult,
    ) -> tuple[TrackResult, Segment | None]:
        """Frame `index` ((H, W) depth [m]) in the open segment, given the map tracker's
        `track` of it. Returns the frame's result (its reason says which segment holds a
        lost frame) and the segment it joins to the map, if any."""
        segment = self.open
        T_seg = segment.track(index, observation, rgb, depth_m) if segment is not None else None
        if not track.lost and segment is not None and T_seg is not None:
            if track.path is TrackingPath.RELOCALISED and not segment.confirms(
                track.T_world_cam, T_seg
            ):
                # One frame's whole-map search does not place a segment (a symmetric scene
                # offers a half-turn-wrong place): the next relocalisation must agree.
                self.tracker.prediction_valid = False
                note = f"relocalised; the segment since frame {segment.first} waits for a second"
                lost = dataclasses.replace(track, path=TrackingPath.LOST)
                return dataclasses.replace(lost, reason=f"{track.reason}; {note}"), None
            self.open = None
            return track, segment
        if not track.lost:
            self.open = None
            return track, None
        if T_seg is None:  # the segment lost it too (or there is none): one starts here
            self.open = Segment(
                index,
                observation,
                rgb,
                depth_m,
                self.config,
                self.camera,
                self.sensor,
                self.seed + index,
                track,
                self.tracker.odometry,
            )
            note = "a new segment starts here"
        else:
            assert segment is not None
            note = f"tracked in the segment since frame {segment.first}, not joined yet"
        return dataclasses.replace(track, reason=f"{track.reason}; {note}"), None
