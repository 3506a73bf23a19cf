"""Full SLAM, frame by frame: front end -> tracking against the map -> map / backend.

Two backends share the front end, the tracking and the plane-object map:

Every mapped frame (a keyframe) is merged into the plane-object map, then handed to a
`planeslam.backend.base.Backend`:

- `merge`: the paper's system (Section 4.4). Every tracked frame is a keyframe, merged
  into the map (plane statistics refit, longest edges kept, objects re-aggregated);
  poses are never revised.
- `isam2` (default): keyframes go to a GTSAM iSAM2 graph (odometry between keyframes,
  plane and corner landmarks whose identities are the map's plane and corner ids), which
  runs in a child process (`planeslam.backend.worker`) while tracking goes on.

A keyframe's update is applied `lag_frames` frames later (or at the next keyframe): the
keyframe takes its optimised pose, the planes and corners it saw move onto their
landmarks, and the pose tracked since moves by the keyframe's correction; map planes that
came to lie on one segment then merge (`Map.merge_same_segments`), and the next keyframe
takes those joins to the graph. Every frame's pose is re-anchored on the final pose of
its anchor: the keyframe nearest to it in pose (on a revisit, the keyframe made there
before rather than the last one, which may be hundreds of frames back).

`SLAM.process(depth_m, timestamp, rgb)` needs no dataset folder (live cameras, other
sources); `run_frames` drives it over an `RgbdDataset` (folder or bag). Poses are
T_world_cam (4, 4). The first frame's pose fixes the world frame (`run.start_pose`): the
identity (the first camera's frame), or its ground-truth pose when one is known
(`T_world_first`; `slam_for_dataset` reads it from the dataset).
A `SLAM` is a context manager: leaving the block (or dropping the object) stops its
backend process.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import logging
import time
import weakref
from collections.abc import Callable, Iterable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planeslam.backend.base import (
    Backend,
    BackendKind,
    BackendResult,
    KeyframeInput,
    KeyframeUpdate,
)
from planeslam.backend.factory import create_backend
from planeslam.backend.keyframes import nearest_keyframe
from planeslam.config import PlaneSlamConfig
from planeslam.core.errors import ConfigError, DatasetFormatError, FrameReadError, PlaneSlamError
from planeslam.core.frame_checks import check_depth_units, check_rgb, clean_depth
from planeslam.core.geometry import (
    as_pose,
    compose_covariance,
    invert_pose,
    orthonormalize_pose,
    transform_points,
)
from planeslam.core.native_tuning import single_native_threads
from planeslam.core.types import LoopConstraint, RelativePose, TrackingPath
from planeslam.frontend.pipeline import FrameObservation, FrontEnd
from planeslam.io.dataset import Frame
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.config import MapConfig
from planeslam.mapping.sparse_cloud import FusedCloudSize
from planeslam.mapping.world_map import Map
from planeslam.tracking.estimator import PoseConstraints
from planeslam.tracking.final_poses import FrameTerms, final_poses
from planeslam.tracking.glitches import PoseGlitches, find_pose_glitches, reestimate_glitches
from planeslam.tracking.keypoints import Keypoints
from planeslam.tracking.loops import LoopOutcome, LoopSearch
from planeslam.tracking.odometry import RgbdOdometry
from planeslam.tracking.segments import Segment
from planeslam.tracking.tracker import MapView, Tracker, TrackResult

logger = logging.getLogger(__name__)

SPARSE_STRIDE = 8
"""Every SPARSE_STRIDE-th pixel (each direction) off all planes goes to the sparse cloud."""

POINT_BYTES = 15
"""Bytes per point of the point cloud the map stands in for: float32 x, y, z + uint8 r, g, b."""

FUSED_VOXEL_M = 0.01
"""Voxel of the fused point cloud the map is compared with [m]."""

FUSED_STRIDE = 2
"""Keyframes' pixels (every FUSED_STRIDE-th in each direction) fill the fused cloud: a
lower bound of the cloud of all frames at full resolution (neighbouring frames and
pixels mostly fall in the same 1 cm voxels), so the memory ratio errs low."""


@dataclass(frozen=True)
class _PendingKeyframe:
    """The keyframe whose backend update is not applied yet, and the map ids it saw. One
    at most: a keyframe merged into the map before the previous one's correction would
    stay uncorrected there."""

    index: int
    plane_ids: tuple[int, ...]
    corner_ids: tuple[int, ...]


@dataclass(frozen=True)
class FrameResult:
    """What SLAM made of one frame."""

    index: int
    """Position of the frame in the processed sequence (0, 1, ...)."""
    timestamp: float
    """[s]"""
    T_world_cam: np.ndarray
    """(4, 4) pose estimated online (before later optimisation)."""
    path: TrackingPath
    """How the pose was found."""
    reason: str
    """Why tracking needed a fallback or lost the frame; '' otherwise."""
    keyframe: bool
    """Whether the frame went into the map (merge) or the graph (isam2)."""
    observation: FrameObservation = field(repr=False)
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Wall-clock ms per stage: the front end's, then tracking, map, backend."""
    rgb: np.ndarray | None = field(default=None, repr=False)
    """(H, W, 3) uint8 colour image as given to `process` (not copied), or None."""
    constraints: PoseConstraints | None = None
    """Which degrees of freedom the planes fixed and what fixed the rest (None: first or
    lost frame)."""
    anchor: int | None = None
    """The keyframe (its `index`) whose final pose this frame's pose follows in
    `SLAM.trajectory`: the frame itself if a keyframe, else the keyframe nearest in pose
    (None: lost before any keyframe)."""
    pose_covariance: np.ndarray | None = None
    """(6, 6) covariance of `T_world_cam` in its tangent space (gtsam's Pose3 order,
    rotation [rad^2] first, then translation [m^2]): a keyframe's backend marginal once
    its update is in, else the latest keyframe marginal moved to this frame with one
    tracking step's noise (the backend's `odometry_sigma_*`). None without a graph
    (merge backend), before the first update, and for lost frames."""

    @property
    def lost(self) -> bool:
        return self.path is TrackingPath.LOST

    def to_record(self) -> dict[str, Any]:
        """One line of frames.jsonl."""
        return {
            "index": self.index,
            "timestamp": self.timestamp,
            "path": self.path.value,
            "reason": self.reason,
            "keyframe": self.keyframe,
            "planes": len(self.observation.segmentation.planes),
            "corners": len(self.observation.structure.corners),
            "frontend_reason": self.observation.reason,
            "stage_ms": {k: round(v, 3) for k, v in self.stage_ms.items()},
            "constraints": None if self.constraints is None else self.constraints.to_record(),
            "anchor": self.anchor,
        }


class SLAM:
    """RGB-D SLAM with a plane-object map; feed it frames with `process`."""

    def __init__(
        self,
        config: PlaneSlamConfig,
        backend: BackendKind | str | None = None,
        T_world_first: np.ndarray | Any | None = None,
        seed: int | None = None,
        map: Map | None = None,
        localize: bool = False,
    ) -> None:
        """`backend` and `seed` default to the config's `run` section. `T_world_first`
        ((4, 4) array or gtsam.Pose3): the first frame's ground-truth pose, taken with
        `run.start_pose: groundtruth` (None: the identity); ConfigError with 'identity'.
        `map` (e.g. `Map.load(path)`): track in this map instead of starting an empty one;
        the first frame is placed in it by relocalisation (T_world_first only breaks ties)
        and frames are lost until one is. With `localize` the map is not changed (no
        merging, no backend keyframes); without it, it is extended as usual."""
        if localize and map is None:
            raise ConfigError("localize needs a map to localise in (map=Map.load(path))")
        self.config = config
        self.front_end = FrontEnd(config, seed=config.run.seed if seed is None else seed)
        odometry = RgbdOdometry(config.camera) if config.tracking.rgbd_odometry else None
        self.tracker = Tracker(
            config.tracking, odometry, config.camera, config.sensor, config.run.seed
        )
        self.backend: Backend = create_backend(backend or config.run.backend, config.backend)
        self._in_given_map = map is not None
        self.map = (
            map
            if map is not None
            else Map(map_config_for(config.map, self.backend), config.objects)
        )
        self.map.sensor = config.sensor  # also a given map's: it merges this run's frames
        self.localize = localize
        """Track in `map` without changing it."""
        if self._in_given_map:
            self.tracker.expect_jump()
        self._stop_backend = weakref.finalize(self, self.backend.close)
        """Stops the backend process when the SLAM is closed, finished or dropped."""
        self._finished = False
        self._T_world_first = _first_pose(config, T_world_first)
        self._stamps: list[float] = []
        self._anchor: list[int] = []
        """Per frame: the keyframe (frame index) its pose is expressed against."""
        self._T_anchor_cam: list[np.ndarray] = []
        """Per frame: pose relative to its anchor keyframe's online pose."""
        self._keyframe_online: dict[int, np.ndarray] = {}
        """Keyframe pose when it was added (tracked, or optimised by its own update)."""
        self._keyframe_array: np.ndarray | None = None
        """`_keyframe_online` as one (K, 4, 4) array, rebuilt after a change."""
        self._map_view: tuple[int, MapView] | None = None
        """(map revision, its view) of the last `map_view`."""
        self._keyframe_final: dict[int, np.ndarray] = {}
        """Keyframe pose after the last optimisation (`finish`); the online one until then."""
        self._frame_terms: dict[int, FrameTerms] = {}
        """Per tracked frame between keyframes: the planes and corners its pose rests on, for
        its re-estimate against the final map (`tracking.final_poses`)."""
        self.final_poses: dict[str, float] = {}
        """After `finish`: frames between keyframes re-estimated against the final map
        ('reestimated'), left at their anchored pose ('kept') and the wall-clock 'ms'."""
        self.settled_glitches: dict[str, Any] = {}
        """After `finish` (`tracking.settle_glitches`): the final trajectory's pose glitches
        ('found', their 'found_timestamps' [s]), those re-estimated from their neighbours'
        path ('re_estimated') and those left out as lost ('left_out')."""
        self._last_keyframe: int | None = None
        self._merged_frames: dict[int, int] = {}
        """Map merge number (`MapPlane.seen_in`) -> the frame index merged."""
        self._odometry_since_keyframe: RelativePose | None = None
        """The caller's odometry composed since the last keyframe (None: not given for
        every frame since)."""
        self._last_covariance: tuple[int, np.ndarray] | None = None
        """(keyframe index, (6, 6) marginal covariance) of the latest backend update that
        had one."""
        self._velocity = np.eye(4)
        """Last motion T_prev_cur of tracked frames (constant-velocity prediction)."""
        self._last_tracked: np.ndarray | None = None
        self._tracked: list[bool] = []
        """Per frame: whether it has a pose (False: lost, or in a segment not joined yet)."""
        self._segment: Segment | None = None
        """The segment tracking since the last loss, until it joins the map."""
        self._pending: _PendingKeyframe | None = None
        self._joined_planes: list[tuple[int, int]] = []
        """(absorbed, surviving) map plane ids joined since the last keyframe went to the
        backend, which ties them in the graph with the next one."""
        self._loop_search: LoopSearch | None = None
        """Each keyframe's loop search, beside tracking (`KeyframeLoops.search`), when loops
        are on and the backend takes them."""
        loops = self.tracker.loops
        if self.backend.takes_loops and config.tracking.loops.enabled and loops is not None:
            self._loop_search = LoopSearch(loops.search)
            weakref.finalize(self, self._loop_search.close)  # dropped without close
        self.loops: list[tuple[int, int]] = []
        """(keyframe, older keyframe) frame indices of every loop constraint sent to the
        backend."""
        self.loop_search_ms: list[float] = []
        """Per collected loop search: its wall-clock time on the search's thread [ms]."""
        self.backend_result: BackendResult | None = None
        """What the backend reported at `finish`: update times, failures, factors."""
        self.pointcloud_bytes = 0
        """Bytes of all processed frames' clouds merged (valid depth x POINT_BYTES): the
        paper's comparison."""
        self.fused_cloud = FusedCloudSize(FUSED_VOXEL_M)
        """The keyframes' clouds fused with their tracked poses, 1 cm voxels."""

    # -------------------------------------------------------------------------- lifecycle

    @property
    def backend_name(self) -> str:
        return self.backend.kind.value

    def __enter__(self) -> SLAM:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the backend without optimising (an interrupted run); idempotent. The SLAM
        takes no more frames; its map and trajectory so far stay readable."""
        self._finished = True
        if self._loop_search is not None:
            self._loop_search.close()
        self._stop_backend()

    # -------------------------------------------------------------------------- state

    @property
    def frames(self) -> int:
        return len(self._stamps)

    def predicted_pose(self) -> np.ndarray:
        """(4, 4) T_world_cam of the next frame under constant velocity."""
        if self._last_tracked is None:
            return self._T_world_first
        return self._last_tracked @ self._velocity

    def map_view(self) -> MapView:
        """The map's planes, corners, edges and objects for tracking (world frame), rebuilt
        only after the map changed (most frames are not keyframes)."""
        if self._map_view is None or self._map_view[0] != self.map.revision:
            self._map_view = (self.map.revision, map_view(self.map))
        return self._map_view[1]

    def _is_keyframe(self, T_world_cam: np.ndarray, new_planes: int) -> bool:
        if self._last_keyframe is None:
            return True
        since = self.frames - self._last_keyframe
        return self.backend.is_keyframe(self._keyframe_poses(), T_world_cam, since, new_planes)

    def _keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) online keyframe poses, increasing frame index (the last one last)."""
        if self._keyframe_array is None:
            self._keyframe_array = np.asarray(list(self._keyframe_online.values()))
        return self._keyframe_array

    def _set_keyframe_online(self, index: int, T_world_cam: np.ndarray) -> None:
        self._keyframe_online[index] = T_world_cam
        self._keyframe_array = None

    # -------------------------------------------------------------------------- frames

    def process(
        self,
        depth_m: np.ndarray,
        timestamp: float,
        rgb: np.ndarray | None = None,
        odometry: RelativePose | tuple[Any, np.ndarray] | None = None,
    ) -> FrameResult:
        """Process one frame: (H, W) float depth [m] (0, NaN and +-inf = invalid), its
        timestamp [s] (after the previous frame's), and optionally (H, W, 3) uint8 RGB (for
        the RGB-D odometry fallback and map colours) and the caller's odometry (wheel, IMU,
        VIO): (T_prev_cur (4, 4) or gtsam.Pose3, the motion since the previous frame in
        its camera frame; information (6, 6), rotation first) or a `RelativePose`. The
        odometry predicts the pose for tracking (instead of constant velocity) and, composed
        from keyframe to keyframe, becomes a between factor in the iSAM2 graph.
        Raises PlaneSlamError, changing nothing, after `finish` or `close`, and
        DatasetFormatError, changing nothing, for a bad frame: another shape or dtype,
        depth that cannot be metres (raw sensor values, millimetres: the message names the
        likely depth_scale), greyscale or RGBA colour, a timestamp not after the last;
        GeometryError, changing nothing, for odometry that is not a rigid T_prev_cur with
        a symmetric positive definite information."""
        if self._finished:
            raise PlaneSlamError(
                "this SLAM has finished (finish or close was called); create a new one"
            )
        cam = self.config.camera
        depth_m = clean_depth(depth_m, (cam.height, cam.width), depth_scale=cam.depth_scale)
        max_range_m = self.config.segmentation.max_depth_m
        check_depth_units(depth_m, "depth_m", max_range_m, camera_depth_scale=cam.depth_scale)
        if rgb is not None:
            rgb = check_rgb(rgb, depth_m.shape)
        timestamp = self._check_timestamp(timestamp)
        step = None if odometry is None else RelativePose.from_odometry(odometry)
        index = self.frames
        observation = self.front_end.process(depth_m, timestamp)
        stage_ms = dict(observation.stage_ms)

        if self._pending and index - self._pending.index >= self.backend.lag_frames:
            t0 = time.perf_counter()
            self._apply_update(self.backend.collect())
            stage_ms["backend"] = 1e3 * (time.perf_counter() - t0)

        t0 = time.perf_counter()
        T_pred = self.predicted_pose()
        if step is not None and self._last_tracked is not None and self._tracked[-1]:
            T_pred = self._last_tracked @ step.T_a_b
        self._odometry_since_keyframe = (
            None
            if step is None or self._odometry_since_keyframe is None
            else self._odometry_since_keyframe.then(step)
        )
        valid = np.count_nonzero(depth_m > 0)  # clean_depth set NaN and +-inf to 0
        if not valid:  # a blind sensor: nothing to track with, and no segment starts on it
            track = TrackResult(T_pred, TrackingPath.LOST, "no valid depth: no plane or point")
        elif self._last_tracked is None and not self._in_given_map:  # the first frame seen
            track = TrackResult(self._T_world_first, TrackingPath.FIRST, "first frame")
            self.tracker.start(observation, self._T_world_first, rgb, depth_m)
        else:
            track = self.tracker.track(
                observation, self.map_view(), T_pred, rgb, depth_m, self._last_tracked
            )
        joined = None
        if valid and (self._segment is not None or (track.lost and self.config.tracking.segments)):
            track, joined = self._segment_step(index, observation, rgb, depth_m, track)
        T_world_cam = orthonormalize_pose(track.T_world_cam)
        stage_ms["tracking"] = 1e3 * (time.perf_counter() - t0)

        keyframe = track.path.maps and self._is_keyframe(T_world_cam, track.new_planes)
        if keyframe:
            keypoints = track.keypoints
            if not self.localize:  # a localising run keeps keyframes for tracking only
                T_world_cam = self._add_keyframe(
                    index, timestamp, observation, track, rgb, stage_ms, keypoints
                )
            self.tracker.add_keyframe(index, T_world_cam, rgb, observation.cloud, keypoints)
        self._remember(index, timestamp, T_world_cam, keyframe, track.lost)
        if track.terms is not None and not (keyframe or track.lost):
            self._frame_terms[index] = track.terms
        if joined is not None:
            self._join(index, joined)
        self.pointcloud_bytes += POINT_BYTES * int(valid)
        if track.lost:
            logger.info("frame %d (%.3f s) lost: %s", index, timestamp, track.reason)
        return FrameResult(
            index=index,
            timestamp=float(timestamp),
            T_world_cam=T_world_cam,
            path=track.path,
            reason=track.reason,
            keyframe=keyframe,
            observation=observation,
            stage_ms=stage_ms,
            rgb=rgb,
            constraints=track.constraints,
            anchor=self._anchor[-1] if self._anchor[-1] >= 0 else None,
            pose_covariance=None if track.lost else self._pose_covariance(T_world_cam),
        )

    def map_record(self) -> dict[str, Any]:
        """map.json: `Map.to_dict` (schema 'planeslam.map/1', world frame, n . x + d = 0)
        plus this run's keyframes ('keyframes': frame index, timestamp [s], the map merge
        number or None, T_world_cam (4, 4) rows, final when `finish` ran) and, per plane,
        the frame indices of the merges of this run that saw it ('seen_in_frames';
        'seen_in' counts merges)."""
        data = self.map.to_dict()
        for plane in data["planes"]:
            merges = plane["seen_in"]
            plane["seen_in_frames"] = sorted(
                self._merged_frames[m] for m in merges if m in self._merged_frames
            )
        merge_of = {k: m for m, k in self._merged_frames.items()}
        data["keyframes"] = [
            {
                "index": k,
                "timestamp": self._stamps[k],
                "merge": merge_of.get(k),
                "T_world_cam": np.asarray(T, dtype=np.float64).tolist(),
            }
            for k, T in sorted(self._keyframe_final.items())
        ]
        return data

    def _pose_covariance(self, T_world_cam: np.ndarray) -> np.ndarray | None:
        """(6, 6) covariance of a frame at T_world_cam: the latest keyframe marginal the
        backend returned, moved to the frame (exactly the marginal when the frame is that
        keyframe) with one tracking step's noise otherwise; None before any."""
        if self._last_covariance is None:
            return None
        index, cov = self._last_covariance
        T_key_cam = invert_pose(self._keyframe_online[index]) @ T_world_cam
        if np.allclose(T_key_cam, np.eye(4), atol=1e-12):
            return cov.copy()
        cfg = self.config.backend
        sigmas = np.repeat([cfg.odometry_sigma_rot_rad, cfg.odometry_sigma_trans_m], 3)
        return compose_covariance(cov, T_key_cam, np.diag(sigmas**2))

    def _check_timestamp(self, timestamp: float) -> float:
        """`timestamp` [s] as a float: a finite number after the previous frame's."""
        try:
            t = float(timestamp)
        except (TypeError, ValueError):
            raise DatasetFormatError(
                f"timestamp {timestamp!r} is not a number of seconds"
            ) from None
        if not np.isfinite(t):
            raise DatasetFormatError(f"timestamp {timestamp!r} is not a finite number of seconds")
        if self._stamps and not t > self._stamps[-1]:
            raise DatasetFormatError(
                f"timestamp {t:.6f} s is not after the previous frame's {self._stamps[-1]:.6f} s "
                "(frames must come in increasing time order)"
            )
        return t

    def _segment_step(
        self,
        index: int,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        depth_m: np.ndarray,
        track: TrackResult,
    ) -> tuple[TrackResult, Segment | None]:
        """Segments (`planeslam.tracking.segments`): a lost frame starts one; while one is
        open, every frame is tracked in it too. Returns the frame's result (its reason says
        which segment holds a lost frame) and the segment it joins to the map, if any."""
        tracking = self.config.tracking
        segment = self._segment
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
            self._segment = None
            return track, segment
        if not track.lost:
            self._segment = None
            return track, None
        if T_seg is None:  # the segment lost it too (or there is none): one starts here
            seed = self.config.run.seed + index
            self._segment = Segment(
                index,
                observation,
                rgb,
                depth_m,
                tracking,
                self.config.camera,
                self.config.sensor,
                seed,
                track,
                self.tracker.odometry,
            )
            note = "a new segment starts here"
        else:
            assert segment is not None
            note = f"tracked in the segment since frame {segment.first}, not joined yet"
        return dataclasses.replace(track, reason=f"{track.reason}; {note}"), None

    def _join(self, index: int, segment: Segment) -> None:
        """Frame `index` relocalised in the map and tracked in `segment`: every frame of the
        segment gets a pose, anchored where frame `index` is (so later corrections move
        them with it)."""
        anchor, T_anchor_join = self._anchor[index], self._T_anchor_cam[index]
        T_join_seg = invert_pose(segment.poses[index])
        for k, T_seg_cam in segment.poses.items():
            if k < index:
                self._anchor[k] = anchor
                self._T_anchor_cam[k] = T_anchor_join @ T_join_seg @ T_seg_cam
                self._tracked[k] = True
        logger.info(
            "segment of frames %d-%d joined the map at frame %d (%d frames tracked in it)",
            segment.first,
            index - 1,
            index,
            len(segment.poses) - 1,
        )

    def _add_keyframe(
        self,
        index: int,
        timestamp: float,
        observation: FrameObservation,
        track: TrackResult,
        rgb: np.ndarray | None,
        stage_ms: dict[str, float],
        keypoints: Keypoints | None,
    ) -> np.ndarray:
        """Merge the frame into the map and hand it to the backend (after applying the
        previous keyframe's update if it is still pending) with the previous keyframe's
        loop constraint, if its search found one, and start this keyframe's loop search
        on the loop search's thread (`KeyframeLoops.search`: from its `keypoints`, or
        detected in `rgb`). Returns the frame's pose: corrected by that update, or with
        `lag_frames` 0 the backend's own."""
        T_world_cam = track.T_world_cam
        moved: tuple[int, ...] = ()
        if self._pending:
            t0 = time.perf_counter()
            moved = self._pending.plane_ids
            correction = self._apply_update(self.backend.collect(), merge_segments=False)
            T_world_cam = orthonormalize_pose(correction @ T_world_cam)
            stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        loops: tuple[LoopConstraint, ...] = ()
        if self._loop_search is not None:
            t0 = time.perf_counter()
            loops = self._collect_loop()
            cloud = observation.cloud
            images = None if rgb is None or cloud is None else (rgb, cloud)
            assert self.tracker.loops is not None  # with the loop search
            query = self.tracker.loops.query(index, observation, T_world_cam, keypoints, images)
            if query is not None:
                self._loop_search.submit(query)
            stage_ms["loops"] = 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        self._merged_frames[self.map.frames_merged] = index
        merged = self.map.merge(
            observation,
            T_world_cam,
            track.plane_pairs,
            track.corner_pairs,
            reaggregate=self.backend.objects_every_keyframe,
        )
        self._merge_same_segments(moved)  # after the frame's pairs, which may name them
        self._add_sparse_points(observation, T_world_cam, rgb)
        self._add_to_fused_cloud(observation, T_world_cam)
        stage_ms["map"] = 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        T_prev_cam = None  # measured motion since the last keyframe
        relocalised = False  # ... or none: placed by a whole-map search, or frames lost since
        if self._last_keyframe is not None:
            T_prev_cam = invert_pose(self._keyframe_online[self._last_keyframe]) @ T_world_cam
            relocalised = track.path is TrackingPath.RELOCALISED or not all(
                self._tracked[self._last_keyframe + 1 :]
            )
        self.backend.submit(
            KeyframeInput(
                index=index,
                timestamp=float(timestamp),
                T_world_cam=T_world_cam,
                measurements=observation.measurements(),
                plane_ids=merged.planes,
                corner_ids=merged.corners,
                T_prev_cam=T_prev_cam,
                odometry=self._odometry_since_keyframe if T_prev_cam is not None else None,
                joined_planes=tuple(self._joined_planes),
                loops=loops,
                relocalised=relocalised,
            )
        )
        self._joined_planes = []
        self._set_keyframe_online(index, T_world_cam)
        self._pending = _PendingKeyframe(
            index, tuple(merged.planes.values()), tuple(merged.corners.values())
        )
        if self.backend.lag_frames == 0:
            self._apply_update(self.backend.collect(), move_last_tracked=False)
            T_world_cam = self._keyframe_online[index]
        stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        return T_world_cam

    def _collect_loop(self) -> tuple[LoopConstraint, ...]:
        """The previous keyframe's loop search (`_take_loop_search`), timed; its loop
        constraint (if any) is returned and counted in `loops`."""
        outcome = self._take_loop_search()
        if outcome is None:
            return ()
        self.loop_search_ms.append(outcome.search_ms)
        if outcome.loop is None:
            return ()
        self.loops.append((outcome.loop.index, outcome.loop.old_index))
        return (outcome.loop,)

    def _take_loop_search(self) -> LoopOutcome | None:
        """The pending loop search's outcome (waiting for it), its keypoints given to the
        keypoint map; None when none is pending."""
        assert self._loop_search is not None
        outcome = self._loop_search.collect()
        if outcome is not None:
            assert self.tracker.loops is not None  # with the loop search
            self.tracker.loops.take_keypoints(outcome)
        return outcome

    def _apply_update(
        self, update: KeyframeUpdate, move_last_tracked: bool = True, merge_segments: bool = True
    ) -> np.ndarray:
        """The pending keyframe's update: its pose becomes the optimised one, and the planes
        and corners it saw move onto their landmarks (tracking uses them next; the whole
        map and its objects are rebuilt in `finish`); with `merge_segments`, those planes
        then merge with map planes they came to share a segment with
        (`Map.merge_same_segments`). Returns the correction (4, 4)
        T_optimised @ T_online^-1, which also moves the last tracked pose (frames since the
        keyframe were tracked in the uncorrected map) unless told not to."""
        pending = self._pending
        assert pending is not None and update.index == pending.index, (
            "backend updates come back in submission order"
        )
        self._pending = None
        correction = update.T_world_cam @ invert_pose(self._keyframe_online[pending.index])
        self._set_keyframe_online(pending.index, update.T_world_cam)
        self.tracker.move_keyframe(pending.index, update.T_world_cam)
        self.tracker.correct_previous(correction)
        self._keyframe_final[pending.index] = update.T_world_cam
        if update.covariance is not None:
            self._last_covariance = (pending.index, update.covariance)
        self.map.apply_estimates(
            update.planes, update.corners, pending.plane_ids, pending.corner_ids, reaggregate=False
        )
        if merge_segments:
            self._merge_same_segments(pending.plane_ids)
        if move_last_tracked and self._last_tracked is not None:
            self._last_tracked = orthonormalize_pose(correction @ self._last_tracked)
        return correction

    def _merge_same_segments(self, plane_ids: Iterable[int]) -> None:
        """`Map.merge_same_segments` on `plane_ids`; the joins go to the backend with the
        next keyframe."""
        absorbed = self.map.merge_same_segments(plane_ids)
        self._joined_planes.extend(sorted(absorbed.items()))

    @property
    def fused_cloud_bytes(self) -> int:
        """Bytes of the fused 1 cm point cloud (`POINT_BYTES` per occupied voxel)."""
        return POINT_BYTES * self.fused_cloud.voxels

    def _add_to_fused_cloud(self, observation: FrameObservation, T_world_cam: np.ndarray) -> None:
        if observation.cloud is None:
            return
        xyz = observation.cloud[::FUSED_STRIDE, ::FUSED_STRIDE].reshape(-1, 3)
        self.fused_cloud.add(xyz[xyz[:, 2] > 0], T_world_cam.copy())  # a new array: kept as is

    def _add_sparse_points(self, observation, T_world_cam, rgb) -> None:
        """Non-planar points of the frame (label -1), subsampled, into the map's sparse cloud."""
        s = SPARSE_STRIDE
        xyz = observation.cloud[::s, ::s]
        off_plane = observation.segmentation.labels[::s, ::s] < 0
        keep = off_plane & (xyz[..., 2] > 0) & np.all(np.isfinite(xyz), axis=-1)
        points = transform_points(T_world_cam, xyz[keep].astype(np.float64))
        colors = None if rgb is None else np.asarray(rgb)[::s, ::s][keep]
        self.map.add_sparse_points(points, colors)

    def _remember(self, index, timestamp, T_world_cam, keyframe, lost) -> None:
        if not lost:
            if self._last_tracked is not None:
                gap = self._tracked and not self._tracked[-1]  # no velocity across lost frames
                self._velocity = np.eye(4) if gap else invert_pose(self._last_tracked) @ T_world_cam
            self._last_tracked = T_world_cam
        self._tracked.append(not lost)
        if keyframe:  # the first frame always is one, so every frame has an anchor
            self._last_keyframe = index
            self._odometry_since_keyframe = RelativePose.identity()
            self._set_keyframe_online(index, T_world_cam)
            self._keyframe_final[index] = T_world_cam
        anchor = self._anchor_of(T_world_cam, keyframe, lost)
        assert anchor is not None or lost, "the first tracked frame is always a keyframe"
        self._stamps.append(float(timestamp))
        self._anchor.append(-1 if anchor is None else anchor)  # -1: lost before any keyframe
        T_anchor = np.eye(4) if anchor is None else self._keyframe_online[anchor]
        self._T_anchor_cam.append(invert_pose(T_anchor) @ T_world_cam)

    def _anchor_of(self, T_world_cam: np.ndarray, keyframe: bool, lost: bool) -> int | None:
        """The keyframe (frame index) whose final pose a frame's pose at T_world_cam (4, 4)
        will follow: a keyframe itself, a tracked frame the keyframe nearest in pose
        (`nearest_keyframe`), a lost frame the last keyframe; None before any keyframe."""
        if keyframe or lost or len(self._keyframe_online) < 2:
            return self._last_keyframe
        indices = list(self._keyframe_online)
        return indices[nearest_keyframe(self.config.backend, self._keyframe_poses(), T_world_cam)]

    def finish(self) -> float:
        """End of the sequence: the backend's final optimisation (iSAM2: a batch over the
        whole graph, `backend.final_iterations`), every keyframe pose taken from its result
        and the whole map (planes, corners, then objects) rebuilt from the final
        landmarks, then the frames between keyframes re-estimated against it
        (`tracking.final_poses`); the backend then stops and the SLAM takes no more frames.
        Returns the wall-clock ms."""
        if self._finished:
            raise PlaneSlamError("this SLAM has finished (finish or close was called)")
        start = time.perf_counter()
        self._finished = True
        self._pending = None  # the final state below supersedes its update
        if self._loop_search is not None:  # the last keyframe's: its keypoints only, no
            self._take_loop_search()  # later keyframe takes its loop
            self._loop_search.close()
        try:
            result = self.backend.finish()
        finally:
            self._stop_backend()
        self._keyframe_final.update(result.keyframe_poses)
        for index, T_world_cam in result.keyframe_poses.items():
            self.tracker.move_keyframe(index, T_world_cam)  # keypoints follow the final map
        if not self.localize:
            self.map.apply_estimates(result.planes, result.corners)
        terms, self._frame_terms = self._frame_terms, {}
        self._reestimate_frames(terms)
        self._settle_glitches(terms)
        self.backend_result = result
        return 1e3 * (time.perf_counter() - start)

    def _reestimate_frames(self, terms: Mapping[int, FrameTerms]) -> None:
        """Each tracked frame between keyframes re-estimated against the final map from the
        planes and corners it was tracked with (`terms`, by frame; `tracking.final_poses`);
        a frame the map does not fix keeps its pose anchored on its keyframe."""
        if not self.config.tracking.final_poses:
            return
        start = time.perf_counter()
        frames = {
            k: (frame_terms, self._keyframe_final[self._anchor[k]] @ self._T_anchor_cam[k])
            for k, frame_terms in terms.items()
        }
        cfg = self.config.tracking
        found = final_poses(
            frames,
            self.map_view(),
            self.tracker.refine_settings,
            self.tracker.thresholds,
            cfg.sigma_point_m,
            cfg.final_max_step_m,
            cfg.final_max_step_deg,
        )
        for k, T_world_cam in found.items():
            self._set_final_pose(k, T_world_cam)
        self.final_poses = {
            "reestimated": len(found),
            "kept": len(frames) - len(found),
            "ms": 1e3 * (time.perf_counter() - start),
        }
        logger.info(
            "final map: %d of %d frames between keyframes re-estimated in %.0f ms",
            len(found),
            len(frames),
            self.final_poses["ms"],
        )

    def _set_final_pose(self, index: int, T_world_cam: np.ndarray) -> None:
        """Frame `index` takes T_world_cam (4, 4) in the final map, kept relative to its
        anchor keyframe's final pose."""
        self._T_anchor_cam[index] = invert_pose(self._keyframe_final[self._anchor[index]]) @ (
            T_world_cam
        )

    def _settle_glitches(self, terms: Mapping[int, FrameTerms]) -> None:
        """The final trajectory's pose glitches (`tracking.settle_glitches`): each frame with
        `terms` (by frame) that they fix from the pose its good neighbours put it at takes
        that estimate; the others are left out as lost."""
        cfg = self.config.tracking
        if not cfg.settle_glitches:
            return
        trajectory = self.trajectory()
        found = self.pose_glitches(trajectory)
        frames = [k for k, tracked in enumerate(self._tracked) if tracked]  # row -> frame
        poses = reestimate_glitches(
            trajectory,
            found.rows.tolist(),
            {int(r): terms[frames[r]] for r in found.rows if frames[r] in terms},
            self.map_view(),
            self.tracker.refine_settings,
            self.tracker.thresholds,
            cfg.sigma_point_m,
            found.max_span_s,
            cfg.fast_max_jump_m,
            cfg.fast_max_jump_deg,
        )
        for row in found.rows.tolist():
            if row in poses:
                self._set_final_pose(frames[row], poses[row])
            else:
                self._tracked[frames[row]] = False
        self.settled_glitches = {
            "found": len(found),
            "found_timestamps": [round(float(t), 6) for t in found.timestamps],
            "re_estimated": len(poses),
            "left_out": len(found) - len(poses),
        }
        if len(found):
            logger.info(
                "final trajectory: %d pose glitches, %d re-estimated, %d left out",
                len(found),
                len(poses),
                len(found) - len(poses),
            )

    # -------------------------------------------------------------------------- results

    def pose_glitches(self, trajectory: Trajectory | None = None) -> PoseGlitches:
        """The glitches of `trajectory` (default: this run's) under tracking's jump limits:
        poses beyond `fast_max_jump_*` off the path of the frames within 2 `fast_max_gap_s`
        around them (`tracking.glitches.find_pose_glitches`)."""
        cfg = self.config.tracking
        return find_pose_glitches(
            self.trajectory() if trajectory is None else trajectory,
            2.0 * cfg.fast_max_gap_s,
            cfg.fast_max_jump_m,
            cfg.fast_max_jump_deg,
        )

    @property
    def tracked_frames(self) -> int:
        """Frames with a pose (every processed frame but the lost ones)."""
        return int(sum(self._tracked))

    def trajectory(self) -> Trajectory:
        """Every tracked frame's pose, each re-anchored on its optimised keyframe; lost
        frames are left out (as ORB-SLAM does)."""
        rows = [k for k, tracked in enumerate(self._tracked) if tracked]
        poses = [self._keyframe_final[self._anchor[k]] @ self._T_anchor_cam[k] for k in rows]
        return Trajectory(
            timestamps=np.asarray(self._stamps, dtype=np.float64)[rows],
            T_world_cam=np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
        )


@dataclass(frozen=True)
class RunSummary:
    """Counts and timings of `run_frames`."""

    frames: int
    seconds: float
    """Wall-clock seconds of processing (frame reading included, start-up excluded)."""
    lost_frames: int
    keyframes: int
    paths: dict[str, int]
    """Tracking path -> number of frames."""
    frame_timings: list[dict[str, float]] = field(repr=False)
    """Per frame {stage: ms}."""
    finish_ms: float = 0.0
    """`SLAM.finish` (final batch optimisation), included in `seconds`."""
    skipped_frames: int = 0
    """Frames left out because an image could not be read (FrameReadError)."""


@dataclass
class RunTally:
    """What `run_frames` has done so far. A caller that passes its own keeps the counts of
    a run that is interrupted or fails: `summary()` then describes the frames until then."""

    start: float = field(default_factory=time.perf_counter)
    """`time.perf_counter()` when processing started."""
    frame_timings: list[dict[str, float]] = field(default_factory=list)
    """Per processed frame {stage: ms}, 'read' first."""
    paths: dict[str, int] = field(default_factory=dict)
    lost_frames: int = 0
    keyframes: int = 0
    skipped_frames: int = 0
    finish_ms: float = 0.0

    def add(self, result: FrameResult, read_ms: float) -> None:
        self.frame_timings.append({"read": read_ms, **result.stage_ms})
        self.paths[result.path.value] = self.paths.get(result.path.value, 0) + 1
        self.lost_frames += result.lost
        self.keyframes += result.keyframe

    def summary(self) -> RunSummary:
        """The counts, with the seconds since `start`."""
        return RunSummary(
            frames=len(self.frame_timings),
            seconds=time.perf_counter() - self.start,
            lost_frames=self.lost_frames,
            keyframes=self.keyframes,
            paths=dict(self.paths),
            frame_timings=list(self.frame_timings),
            finish_ms=self.finish_ms,
            skipped_frames=self.skipped_frames,
        )


def map_config_for(config: MapConfig, backend: Backend) -> MapConfig:
    """`config` with the settings it leaves to the backend (null) set to the backend's
    choice (`Backend.map_cull_single_view_after`, `map_merge_segments`)."""
    return dataclasses.replace(
        config,
        cull_single_view_after=(
            backend.map_cull_single_view_after
            if config.cull_single_view_after is None
            else config.cull_single_view_after
        ),
        merge_segments=(
            backend.map_merge_segments if config.merge_segments is None else config.merge_segments
        ),
    )


def map_view(world_map: Map) -> MapView:
    """The planes, corners, edges and objects (with corners) of `world_map` as tracking's
    arrays, world frame."""
    ids, normals, d = world_map.plane_arrays()
    corner_ids, corner_planes, corner_points = world_map.corner_arrays()
    corners, planes = world_map.corners, world_map.planes
    row = {int(pid): k for k, pid in enumerate(ids)}
    edges = list(world_map.edges.values())
    objects = [o for o in world_map.objects if o.corners and all(c in corners for c in o.corners)]
    culled_normals, culled_d, culled_areas = world_map.culled_plane_arrays()
    return MapView(
        ids,
        normals,
        d,
        corner_ids,
        corner_planes,
        corner_points,
        np.array([corners[int(c)].convex_edges for c in corner_ids], dtype=np.int64),
        np.array([planes[int(i)].area_m2 for i in ids], dtype=np.float64),
        edge_planes=np.array([[row[a], row[b]] for a, b in (e.planes for e in edges)])
        .astype(np.int64)
        .reshape(-1, 2),
        edge_segments=np.array([e.segment for e in edges], dtype=np.float64).reshape(-1, 2, 3),
        edge_lengths=np.array([e.length_m for e in edges], dtype=np.float64),
        edge_angles=np.array([e.angle_rad for e in edges], dtype=np.float64),
        edge_convex=np.array([e.convex for e in edges], dtype=bool),
        object_classes=tuple(o.cls for o in objects),
        object_sizes=tuple(tuple(o.size_m) for o in objects),
        object_centres=np.array(
            [np.mean([corners[c].point for c in o.corners], axis=0) for o in objects]
        ).reshape(-1, 3),
        culled_normals=culled_normals,
        culled_d=culled_d,
        culled_areas=culled_areas,
    )


def frame_indices(num_frames: int, max_frames: int | None, every: int) -> list[int]:
    """Every `every`-th frame index, at most `max_frames` of them."""
    if every < 1:
        raise ConfigError(f"every must be >= 1 (take every n-th frame), got {every}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"max_frames must be >= 1 or None, got {max_frames}")
    return list(range(0, num_frames, every))[:max_frames]


def slam_for_dataset(
    config: PlaneSlamConfig,
    dataset: RgbdDataset,
    first_index: int,
    backend: BackendKind | str | None = None,
    seed: int | None = None,
) -> SLAM:
    """A SLAM starting at frame `first_index` as `run.start_pose` says: 'groundtruth' at its
    ground-truth pose (the identity without ground truth), so the estimates and the truth
    share the world frame and compare pose by pose; 'identity' at the identity."""
    T_world_first = None
    if config.run.start_pose == "groundtruth":
        T_world_first = dataset.groundtruth_pose(dataset.timestamps[first_index])
    known = T_world_first is not None and dataset.groundtruth is not None
    logger.info(
        "start pose (run.start_pose %s): %s",
        config.run.start_pose,
        "the first frame's ground truth" if known else "the identity",
    )
    return SLAM(config, backend, T_world_first=T_world_first, seed=seed)


def _first_pose(config: PlaneSlamConfig, T_world_first: np.ndarray | Any | None) -> np.ndarray:
    """The first frame's pose (4, 4) under `run.start_pose`."""
    if T_world_first is None:
        return np.eye(4)
    if config.run.start_pose == "identity":
        raise ConfigError(
            "T_world_first is given but run.start_pose is 'identity': set run.start_pose to "
            "'groundtruth' to start at that pose, or pass no T_world_first"
        )
    return as_pose(T_world_first, "T_world_first", ConfigError)


def _read(dataset: RgbdDataset, index: int) -> tuple[Frame, float]:
    t0 = time.perf_counter()
    frame = dataset[index]
    return frame, 1e3 * (time.perf_counter() - t0)


def run_frames(
    slam: SLAM,
    dataset: RgbdDataset,
    indices: Iterable[int],
    on_result: Callable[[FrameResult], None] | None = None,
    tally: RunTally | None = None,
    guard: Callable[[], AbstractContextManager[object]] | None = None,
) -> RunSummary:
    """Feed `dataset[i]` for i in `indices` to `slam`; `on_result` sees every FrameResult as
    it comes (write it out there: an interrupted run then keeps what it did), `tally` (when
    given) the counts so far. Each frame is processed, counted and passed to `on_result`
    inside `guard()` when given (an application's deferral of Ctrl-C: a frame is then
    wholly done and reported, or not begun). The next frame is read on a second thread
    while this one is processed; the 'read' stage is the reader's time, which overlaps
    processing. A frame whose image cannot be read (FrameReadError) is skipped with a
    warning; DatasetFormatError when no frame can be read."""
    tally = RunTally() if tally is None else tally
    tally.start = time.perf_counter()
    indices = list(indices)
    # Frames are read (PNG decoding releases the GIL) one ahead on a second thread.
    try:
        with (
            single_native_threads(),
            concurrent.futures.ThreadPoolExecutor(max_workers=1) as reader,
        ):
            upcoming = [reader.submit(_read, dataset, indices[0])] if indices else []
            for k in range(len(indices)):
                future = upcoming.pop()
                if k + 1 < len(indices):
                    upcoming.append(reader.submit(_read, dataset, indices[k + 1]))
                try:
                    frame, read_ms = future.result()
                except FrameReadError as exc:
                    tally.skipped_frames += 1
                    logger.warning("frame %d skipped: %s", indices[k], exc)
                    continue
                with guard() if guard is not None else contextlib.nullcontext():
                    result = slam.process(frame.depth_m, frame.timestamp, frame.rgb)
                    tally.add(result, read_ms)
                    if on_result is not None:
                        on_result(result)
        if indices and not tally.frame_timings:
            raise DatasetFormatError(
                f"{dataset.root}: none of the {len(indices)} frames could be read "
                "(each was skipped: its images are missing or cannot be decoded)"
            )
        tally.finish_ms = slam.finish()
    except BaseException:  # interrupted or failed: stop the backend, keep the map as it is
        slam.close()
        raise
    return tally.summary()
