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
its anchor (`planeslam.slam.anchors`): the keyframe nearest to it in pose (on a revisit,
the keyframe made there before rather than the last one, which may be hundreds of frames
back).

`SLAM.process(depth_m, timestamp, rgb)` needs no dataset folder (live cameras, other
sources); `run_frames` drives it over an `RgbdDataset` (folder or bag). Poses are
T_world_cam (4, 4). The first frame's pose fixes the world frame (`run.start_pose`): the
identity (the first camera's frame), or its ground-truth pose when one is known
(`T_world_first`; `slam_for_dataset` reads it from the dataset). When a segment of
frames tracked since a loss (`planeslam.tracking.segments`) has tracked more frames than
the map holds and never joined it, the segment replaces the map, its first frame placed
where the map predicted it; the dropped map's frames have no pose until a keyframe of the
new map relocalises in the dropped one (twice at one place), and then rejoin.
A `SLAM` is a context manager: leaving the block (or dropping the object) stops its
backend process.
"""

from __future__ import annotations

import logging
import time
import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from planeslam.backend.base import (
    Backend,
    BackendKind,
    BackendResult,
    KeyframeInput,
    KeyframeUpdate,
)
from planeslam.backend.factory import create_backend, map_config_for
from planeslam.config import PlaneSlamConfig
from planeslam.core.errors import ConfigError, DatasetFormatError, PlaneSlamError
from planeslam.core.frame_checks import check_depth_units, check_rgb, clean_depth
from planeslam.core.geometry import (
    as_pose,
    compose_covariance,
    invert_pose,
    orthonormalize_pose,
    transform_points,
)
from planeslam.core.types import RelativePose, TrackingPath
from planeslam.frontend.pipeline import FrameObservation, FrontEnd
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.sparse_cloud import FusedCloudSize
from planeslam.mapping.world_map import Map
from planeslam.slam.anchors import AnchoredPoses, FinalMap
from planeslam.slam.map_view import map_view
from planeslam.slam.records import FrameResult
from planeslam.tracking.glitches import PoseGlitches
from planeslam.tracking.odometry import RgbdOdometry
from planeslam.tracking.segments import DroppedMap, Segment, Segments
from planeslam.tracking.tracker import FrameView, MapView, Tracker, TrackResult

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
        every_keyframe_keypoints: bool = False,
    ) -> None:
        """`backend` and `seed` default to the config's `run` section. `T_world_first`
        ((4, 4) array or gtsam.Pose3): the first frame's ground-truth pose, taken with
        `run.start_pose: groundtruth` (None: the identity); ConfigError with 'identity'.
        `map` (e.g. `Map.load(path)`): track in this map instead of starting an empty one;
        the first frame is placed in it by relocalisation (T_world_first only breaks ties)
        and frames are lost until one is. With `localize` the map is not changed (no
        merging, no backend keyframes); without it, it is extended as usual. With
        `every_keyframe_keypoints`, every keyframe's keypoints are detected, so frames can
        later relocalise by keypoints anywhere in the map (a map made to relocalise in;
        one detection per keyframe); without, only where a frame needed them."""
        if localize and map is None:
            raise ConfigError("localize needs a map to localise in (map=Map.load(path))")
        self.config = config
        self.front_end = FrontEnd(config, seed=config.run.seed if seed is None else seed)
        self._backend_kind = backend or config.run.backend
        self._every_keyframe_keypoints = every_keyframe_keypoints
        self._in_given_map = map is not None
        self.localize = localize
        """Track in `map` without changing it."""
        self._finished = False
        self._T_world_first = _first_pose(config, T_world_first)
        self.poses = AnchoredPoses(config.backend)
        """Every frame's pose on its anchor keyframe, and the keyframes' poses."""
        self.final_poses: dict[str, float] = {}
        """After `finish`: frames between keyframes re-estimated against the final map
        ('reestimated'), left at their anchored pose ('kept') and the wall-clock 'ms'."""
        self.backend_result: BackendResult | None = None
        """What the backend reported at `finish`: update times, failures, factors."""
        self.pointcloud_bytes = 0
        """Bytes of all processed frames' clouds merged (valid depth x POINT_BYTES): the
        paper's comparison."""
        self._dropped: list[DroppedMap] = []
        """Maps that segments outgrew, whose frames rejoin when keyframes relocalise there."""
        self._start_map(map)

    def _start_map(self, given: Map | None = None) -> None:
        """A map (`given`, or an empty one) with its own tracker, backend process and
        segments: at the start, and again when a segment outgrows the map
        (`_segment_outgrowing_the_map`)."""
        config = self.config
        odometry = RgbdOdometry(config.camera) if config.tracking.rgbd_odometry else None
        self.tracker = Tracker(
            config.tracking,
            odometry,
            config.camera,
            config.sensor,
            config.run.seed,
            every_keyframe_keypoints=self._every_keyframe_keypoints,
        )
        self.backend: Backend = create_backend(self._backend_kind, config.backend)
        self.map = (
            given
            if given is not None
            else Map(map_config_for(config.map, self.backend), config.objects)
        )
        self.map.sensor = config.sensor  # also a given map's: it merges this run's frames
        if given is not None:
            self.tracker.expect_jump()
        self._stop_backend = weakref.finalize(self, self.backend.close)
        """Stops the backend process when the SLAM is closed, finished or dropped."""
        self._map_view: tuple[int, MapView] | None = None
        """(map revision, its view) of the last `map_view`."""
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
        self.segments = Segments(
            self.tracker, config.tracking, config.camera, config.sensor, config.run.seed
        )
        """The segment tracking since the last loss, until it joins the map."""
        self._pending: _PendingKeyframe | None = None
        self._joined_planes: list[tuple[int, int]] = []
        """(absorbed, surviving) map plane ids joined since the last keyframe went to the
        backend, which ties them in the graph with the next one."""
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
        self._stop_backend()

    # -------------------------------------------------------------------------- state

    @property
    def frames(self) -> int:
        return len(self.poses)

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
        if self.poses.last_keyframe is None:
            return True
        since = self.frames - self.poses.last_keyframe
        return self.backend.is_keyframe(self.poses.keyframe_poses(), T_world_cam, since, new_planes)

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
        if step is not None and self._last_tracked is not None and self.poses.is_tracked(-1):
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
        if valid and (
            self.segments.open is not None or (track.lost and self.config.tracking.segments)
        ):
            track, joined = self.segments.step(index, observation, rgb, depth_m, track)
            outgrowing = self._segment_outgrowing_the_map(index) if track.lost else None
            if outgrowing is not None:
                track = self._restart_from(index, outgrowing, observation, rgb, depth_m, track)
                joined = outgrowing
        T_world_cam = orthonormalize_pose(track.T_world_cam)
        stage_ms["tracking"] = 1e3 * (time.perf_counter() - t0)

        keyframe = track.path.maps and self._is_keyframe(T_world_cam, track.new_planes)
        if keyframe:
            if not self.localize:  # a localising run keeps keyframes for tracking only
                T_world_cam = self._add_keyframe(
                    index, timestamp, observation, track, rgb, stage_ms
                )
            self.tracker.add_keyframe(index, T_world_cam, rgb, observation.cloud, track.keypoints)
        self._remember(timestamp, T_world_cam, keyframe, track)
        if joined is not None:
            self._join(index, joined)
        if keyframe and self._dropped:
            self._rejoin_dropped(index, observation, rgb, T_world_cam, track)
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
            anchor=self.poses.anchor(index),
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
                "timestamp": self.poses.timestamps[k],
                "merge": merge_of.get(k),
                "T_world_cam": np.asarray(T, dtype=np.float64).tolist(),
            }
            for k, T in self.poses.final_keyframes()
        ]
        return data

    def _pose_covariance(self, T_world_cam: np.ndarray) -> np.ndarray | None:
        """(6, 6) covariance of a frame at T_world_cam: the latest keyframe marginal the
        backend returned, moved to the frame (exactly the marginal when the frame is that
        keyframe) with one tracking step's noise otherwise; None before any."""
        if self._last_covariance is None:
            return None
        index, cov = self._last_covariance
        T_key_cam = invert_pose(self.poses.online(index)) @ T_world_cam
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
        stamps = self.poses.timestamps
        if stamps and not t > stamps[-1]:
            raise DatasetFormatError(
                f"timestamp {t:.6f} s is not after the previous frame's {stamps[-1]:.6f} s "
                "(frames must come in increasing time order)"
            )
        return t

    def _segment_outgrowing_the_map(self, index: int) -> Segment | None:
        """The open segment if it tracked frame `index` and has tracked more frames than
        the map holds: it replaces the map, so the run keeps the larger of the two. A loss
        right after the first frames (a large first step) otherwise leaves every later
        frame lost when nothing relocalises in the few views of the map; ORB-SLAM likewise
        resets a map lost within its first keyframes. A given map is never replaced."""
        segment = self.segments.open
        outgrows = (
            segment is not None
            and index in segment.poses
            and not self._in_given_map
            and len(segment.poses) > self.poses.tracked_frames
        )
        return segment if outgrows else None

    def _restart_from(
        self,
        index: int,
        segment: Segment,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        depth_m: np.ndarray,
        track: TrackResult,
    ) -> TrackResult:
        """A new map (tracker, backend, segments) starts at frame `index`, at `segment`'s
        pose of it, the segment's first frame where the old map predicted it. The old map's
        frames lose their poses until a keyframe relocalises in it (`DroppedMap`). Returns
        frame `index`'s result; the caller joins the segment at it."""
        dropped = DroppedMap(self.tracker, self.map_view(), self.poses.forget_keyframes())
        if dropped.poses:  # a map with no tracked frame has nothing to bring back
            self._dropped.append(dropped)
        self._stop_backend()
        self._start_map()
        T_world_cam = segment.T_world_seg_guess @ segment.poses[index]
        self._velocity = segment.velocity
        self.tracker.start(observation, T_world_cam, rgb, depth_m)
        note = (
            f"the segment since frame {segment.first} ({len(segment.poses)} frames) outgrew "
            f"the map ({len(dropped.poses)} frames tracked), which it never joined: "
            "a new map starts from it"
        )
        logger.info("frame %d: %s", index, note)
        return TrackResult(T_world_cam, TrackingPath.FIRST, f"{track.reason}; {note}")

    def _rejoin_dropped(
        self,
        index: int,
        observation: FrameObservation,
        rgb: np.ndarray | None,
        T_world_cam: np.ndarray,
        track: TrackResult,
    ) -> None:
        """Keyframe `index` at T_world_cam (4, 4) tried in each dropped map: one that places
        it (confirmed by an earlier keyframe) gives its frames poses again, anchored on it.
        Its keypoints are detected here, once, when tracking did not need them."""
        frame = FrameView.of(observation, self.config.camera)
        keypoints = track.keypoints
        keypoint_map, cloud = self.tracker.keypoint_map, observation.cloud
        if keypoints is None and keypoint_map is not None and rgb is not None and cloud is not None:
            keypoints = keypoint_map.detector.detect(rgb, cloud)
        for dropped in list(self._dropped):
            T_old_cam = dropped.place(frame, T_world_cam, keypoints)
            if T_old_cam is None:
                continue
            self.poses.join(index, {**dropped.poses, index: T_old_cam})
            self._dropped.remove(dropped)
            rejoined = len(dropped.poses)
            logger.info("frame %d relocalised in a dropped map: %d frames rejoin", index, rejoined)

    def _join(self, index: int, segment: Segment) -> None:
        """Frame `index` relocalised in the map and tracked in `segment`: every frame of the
        segment gets a pose, anchored where frame `index` is (so later corrections move
        them with it)."""
        self.poses.join(index, segment.poses)
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
    ) -> np.ndarray:
        """Merge the frame into the map and hand it to the backend (after applying the
        previous keyframe's update if it is still pending). Returns the frame's pose:
        corrected by that update, or with `lag_frames` 0 the backend's own."""
        T_world_cam = track.T_world_cam
        moved: tuple[int, ...] = ()
        if self._pending:
            t0 = time.perf_counter()
            moved = self._pending.plane_ids
            correction = self._apply_update(self.backend.collect(), merge_segments=False)
            T_world_cam = orthonormalize_pose(correction @ T_world_cam)
            stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
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
        last = self.poses.last_keyframe
        if last is not None:
            T_prev_cam = invert_pose(self.poses.online(last)) @ T_world_cam
            lost_since = not self.poses.tracked_since(last)
            relocalised = track.path is TrackingPath.RELOCALISED or lost_since
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
                relocalised=relocalised,
            )
        )
        self._joined_planes = []
        self.poses.set_online(index, T_world_cam)
        self._pending = _PendingKeyframe(
            index, tuple(merged.planes.values()), tuple(merged.corners.values())
        )
        if self.backend.lag_frames == 0:
            self._apply_update(self.backend.collect(), move_last_tracked=False)
            T_world_cam = self.poses.online(index)
        stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        return T_world_cam

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
        correction = self.poses.optimised(pending.index, update.T_world_cam)
        self.tracker.move_keyframe(pending.index, update.T_world_cam)
        self.tracker.correct_previous(correction)
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
        # sampled on the fused cloud's worker; the cloud is never written after the front end
        self.fused_cloud.add_sampled(observation.cloud, FUSED_STRIDE, T_world_cam.copy())

    def _add_sparse_points(self, observation, T_world_cam, rgb) -> None:
        """Non-planar points of the frame (label -1), subsampled, into the map's sparse cloud."""
        s = SPARSE_STRIDE
        xyz = observation.cloud[::s, ::s]
        off_plane = observation.segmentation.labels[::s, ::s] < 0
        keep = off_plane & (xyz[..., 2] > 0) & np.all(np.isfinite(xyz), axis=-1)
        points = transform_points(T_world_cam, xyz[keep].astype(np.float64))
        colors = None if rgb is None else np.asarray(rgb)[::s, ::s][keep]
        self.map.add_sparse_points(points, colors)

    def _remember(
        self,
        timestamp: float,
        T_world_cam: np.ndarray,
        keyframe: bool,
        track: TrackResult,
    ) -> None:
        if not track.lost:
            if self._last_tracked is not None:
                gap = not self.poses.is_tracked(-1)  # no velocity across lost frames
                self._velocity = np.eye(4) if gap else invert_pose(self._last_tracked) @ T_world_cam
            self._last_tracked = T_world_cam
        if keyframe:
            self._odometry_since_keyframe = RelativePose.identity()
        self.poses.add(timestamp, T_world_cam, keyframe, track.lost, track.terms)

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
        try:
            result = self.backend.finish()
        finally:
            self._stop_backend()
        self.poses.set_final(result.keyframe_poses)
        for index, T_world_cam in result.keyframe_poses.items():
            self.tracker.move_keyframe(index, T_world_cam)  # keypoints follow the final map
        if not self.localize:
            self.map.apply_estimates(result.planes, result.corners)
        cfg = self.config.tracking
        if cfg.final_poses:
            final = FinalMap(
                self.map_view(), self.tracker.refine_settings, self.tracker.thresholds, cfg
            )
            self.final_poses = self.poses.reestimate(final)
        self.backend_result = result
        for dropped in self._dropped:  # said, not only counted among the lost frames
            logger.warning(
                "frames %d-%d (%d tracked) have no pose: frames tracked after a loss "
                "outgrew their map, and no later keyframe relocalised in it",
                min(dropped.poses),
                max(dropped.poses),
                len(dropped.poses),
            )
        return 1e3 * (time.perf_counter() - start)

    # -------------------------------------------------------------------------- results

    def pose_glitches(self, trajectory: Trajectory | None = None) -> PoseGlitches:
        """The glitches of `trajectory` (default: this run's) under tracking's jump limits:
        poses beyond `fast_max_jump_*` off the path of the frames within 2 `fast_max_gap_s`
        around them (`tracking.glitches.find_pose_glitches`)."""
        return self.poses.glitches(self.config.tracking, trajectory)

    @property
    def tracked_frames(self) -> int:
        """Frames with a pose (every processed frame but the lost ones)."""
        return self.poses.tracked_frames

    def trajectory(self) -> Trajectory:
        """Every tracked frame's pose, each re-anchored on its optimised keyframe; lost
        frames are left out (as ORB-SLAM does)."""
        return self.poses.trajectory()


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
