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
landmarks, and the pose tracked since moves by the keyframe's correction. Every frame's
pose is re-anchored on its final keyframe pose.

`SLAM.process(depth_m, timestamp, rgb)` needs no dataset folder (live cameras, other
sources); `run_frames` drives it over a `TumDataset`. Poses are T_world_cam (4, 4); the
world frame is the first camera's unless `T_world_first` is given. A `SLAM` is a context
manager: leaving the block (or dropping the object) stops its backend process.
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planeslam.backend.base import (
    Backend,
    BackendKind,
    BackendResult,
    KeyframeInput,
    KeyframeUpdate,
    create_backend,
)
from planeslam.config import PlaneSlamConfig
from planeslam.core.errors import ConfigError, DatasetFormatError, PlaneSlamError
from planeslam.core.geometry import invert_pose, orthonormalize_pose, transform_points
from planeslam.core.native_tuning import single_native_threads
from planeslam.core.types import TrackingPath
from planeslam.frontend.pipeline import FrameObservation, FrontEnd
from planeslam.io.dataset import Frame, TumDataset
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.world_map import Map
from planeslam.tracking.odometry import RgbdOdometry
from planeslam.tracking.tracker import MapView, Tracker, TrackResult

logger = logging.getLogger(__name__)

BACKENDS = tuple(k.value for k in BackendKind)

SPARSE_STRIDE = 8
"""Every SPARSE_STRIDE-th pixel (each direction) off all planes goes to the sparse cloud."""

POINT_BYTES = 15
"""Bytes per point of the point cloud the map stands in for: float32 x, y, z + uint8 r, g, b."""


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
        }


class SLAM:
    """RGB-D SLAM with a plane-object map; feed it frames with `process`."""

    def __init__(
        self,
        config: PlaneSlamConfig,
        backend: BackendKind | str | None = None,
        T_world_first: np.ndarray | None = None,
        seed: int | None = None,
    ) -> None:
        """`backend` and `seed` default to the config's `run` section."""
        self.config = config
        self.front_end = FrontEnd(config, seed=config.run.seed if seed is None else seed)
        odometry = RgbdOdometry(config.camera) if config.tracking.rgbd_odometry else None
        self.tracker = Tracker(config.tracking, odometry)
        self.map = Map(config.map, config.objects)
        self.backend: Backend = create_backend(backend or config.run.backend, config.backend)
        self._stop_backend = weakref.finalize(self, self.backend.close)
        """Stops the backend process when the SLAM is closed, finished or dropped."""
        self._finished = False
        self._T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first)
        self._stamps: list[float] = []
        self._anchor: list[int] = []
        """Per frame: the keyframe (frame index) its pose is expressed against."""
        self._T_anchor_cam: list[np.ndarray] = []
        """Per frame: pose relative to its anchor keyframe's online pose."""
        self._keyframe_online: dict[int, np.ndarray] = {}
        """Keyframe pose when it was added (tracked, or optimised by its own update)."""
        self._keyframe_final: dict[int, np.ndarray] = {}
        """Keyframe pose after the last optimisation (`finish`); the online one until then."""
        self._last_keyframe: int | None = None
        self._velocity = np.eye(4)
        """Last motion T_prev_cur of tracked frames (constant-velocity prediction)."""
        self._last_tracked: np.ndarray | None = None
        self._pending: _PendingKeyframe | None = None
        self.backend_result: BackendResult | None = None
        """What the backend reported at `finish`: update times, failures, factors."""
        self.pointcloud_bytes = 0
        """Bytes of the point cloud of every processed frame (valid depth x POINT_BYTES)."""

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
        return len(self._stamps)

    def predicted_pose(self) -> np.ndarray:
        """(4, 4) T_world_cam of the next frame under constant velocity."""
        if self._last_tracked is None:
            return self._T_world_first
        return self._last_tracked @ self._velocity

    def map_view(self) -> MapView:
        """The map's planes and corners for tracking (world frame)."""
        ids, normals, d = self.map.plane_arrays()
        corner_ids, corner_planes, corner_points = self.map.corner_arrays()
        corners, planes = self.map.corners, self.map.planes
        convex = np.array([corners[int(c)].convex_edges for c in corner_ids], dtype=np.int64)
        area = np.array([planes[int(i)].area_m2 for i in ids], dtype=np.float64)
        return MapView(ids, normals, d, corner_ids, corner_planes, corner_points, convex, area)

    def _is_keyframe(self, T_world_cam: np.ndarray, new_planes: int) -> bool:
        if self._last_keyframe is None:
            return True
        T_kf = self._keyframe_online[self._last_keyframe]
        since = self.frames - self._last_keyframe
        return self.backend.is_keyframe(T_kf, T_world_cam, since, new_planes)

    # -------------------------------------------------------------------------- frames

    def process(
        self, depth_m: np.ndarray, timestamp: float, rgb: np.ndarray | None = None
    ) -> FrameResult:
        """Process one frame: (H, W) depth [m] (0 = invalid), its timestamp [s], and
        optionally (H, W, 3) uint8 RGB (for the RGB-D odometry fallback and map colours).
        Raises PlaneSlamError, changing nothing, after `finish` or `close`."""
        if self._finished:
            raise PlaneSlamError(
                "this SLAM has finished (finish or close was called); create a new one"
            )
        depth_m = np.asarray(depth_m)
        cam = self.config.camera
        if depth_m.shape != (cam.height, cam.width):
            raise DatasetFormatError(
                f"depth image is {depth_m.shape}, the camera config says "
                f"({cam.height}, {cam.width})"
            )
        if rgb is not None and np.asarray(rgb).shape[:2] != depth_m.shape:
            raise DatasetFormatError(
                f"colour image is {np.asarray(rgb).shape}, depth is {depth_m.shape}"
            )
        index = self.frames
        observation = self.front_end.process(depth_m, timestamp)
        stage_ms = dict(observation.stage_ms)

        if self._pending and index - self._pending.index >= self.backend.lag_frames:
            t0 = time.perf_counter()
            self._apply_update(self.backend.collect())
            stage_ms["backend"] = 1e3 * (time.perf_counter() - t0)

        t0 = time.perf_counter()
        T_pred = self.predicted_pose()
        if index == 0:
            track = TrackResult(self._T_world_first, TrackingPath.FIRST, "first frame")
        else:
            track = self.tracker.track(observation, self.map_view(), T_pred, rgb, depth_m)
        T_world_cam = orthonormalize_pose(track.T_world_cam)
        stage_ms["tracking"] = 1e3 * (time.perf_counter() - t0)

        keyframe = track.path.maps and self._is_keyframe(T_world_cam, track.new_planes)
        if keyframe:
            T_world_cam = self._add_keyframe(index, timestamp, observation, track, rgb, stage_ms)
        self._remember(index, timestamp, T_world_cam, keyframe, track.lost)
        valid = np.count_nonzero(np.isfinite(depth_m) & (depth_m > 0))
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
        if self._pending:
            t0 = time.perf_counter()
            correction = self._apply_update(self.backend.collect())
            T_world_cam = orthonormalize_pose(correction @ T_world_cam)
            stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        merged = self.map.merge(
            observation,
            T_world_cam,
            track.plane_pairs,
            track.corner_pairs,
            reaggregate=self.backend.objects_every_keyframe,
        )
        self._add_sparse_points(observation, T_world_cam, rgb)
        stage_ms["map"] = 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        T_prev_cam = None  # measured motion since the last keyframe
        if self._last_keyframe is not None:
            T_prev_cam = invert_pose(self._keyframe_online[self._last_keyframe]) @ T_world_cam
        self.backend.submit(
            KeyframeInput(
                index=index,
                timestamp=float(timestamp),
                T_world_cam=T_world_cam,
                measurements=observation.measurements(),
                plane_ids=merged.planes,
                corner_ids=merged.corners,
                T_prev_cam=T_prev_cam,
            )
        )
        self._keyframe_online[index] = T_world_cam
        self._pending = _PendingKeyframe(
            index, tuple(merged.planes.values()), tuple(merged.corners.values())
        )
        if self.backend.lag_frames == 0:
            self._apply_update(self.backend.collect(), move_last_tracked=False)
            T_world_cam = self._keyframe_online[index]
        stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        return T_world_cam

    def _apply_update(self, update: KeyframeUpdate, move_last_tracked: bool = True) -> np.ndarray:
        """The pending keyframe's update: its pose becomes the optimised one, and the planes
        and corners it saw move onto their landmarks (tracking uses them next; the whole
        map and its objects are rebuilt in `finish`). Returns the correction (4, 4)
        T_optimised @ T_online^-1, which also moves the last tracked pose (frames since the
        keyframe were tracked in the uncorrected map) unless told not to."""
        pending = self._pending
        assert pending is not None and update.index == pending.index, (
            "backend updates come back in submission order"
        )
        self._pending = None
        correction = update.T_world_cam @ invert_pose(self._keyframe_online[pending.index])
        self._keyframe_online[pending.index] = update.T_world_cam
        self._keyframe_final[pending.index] = update.T_world_cam
        self.map.apply_estimates(
            update.planes, update.corners, pending.plane_ids, pending.corner_ids, reaggregate=False
        )
        if move_last_tracked and self._last_tracked is not None:
            self._last_tracked = orthonormalize_pose(correction @ self._last_tracked)
        return correction

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
                self._velocity = invert_pose(self._last_tracked) @ T_world_cam
            self._last_tracked = T_world_cam
        if keyframe:  # the first frame always is one, so every frame has an anchor
            self._last_keyframe = index
            self._keyframe_online[index] = self._keyframe_final[index] = T_world_cam
        anchor = self._last_keyframe
        assert anchor is not None, "the first frame is always a keyframe"
        self._stamps.append(float(timestamp))
        self._anchor.append(anchor)
        self._T_anchor_cam.append(invert_pose(self._keyframe_online[anchor]) @ T_world_cam)

    def finish(self) -> float:
        """End of the sequence: the backend's final optimisation (iSAM2: a batch over the
        whole graph, `backend.final_iterations`), every keyframe pose taken from its result
        and the whole map (planes, corners, then objects) rebuilt from the final
        landmarks; the backend then stops and the SLAM takes no more frames.
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
        self._keyframe_final.update(result.keyframe_poses)
        self.map.apply_estimates(result.planes, result.corners)
        self.backend_result = result
        return 1e3 * (time.perf_counter() - start)

    # -------------------------------------------------------------------------- results

    def trajectory(self) -> Trajectory:
        """Every processed frame's pose, each re-anchored on its optimised keyframe."""
        poses = [
            self._keyframe_final[a] @ T
            for a, T in zip(self._anchor, self._T_anchor_cam, strict=True)
        ]
        return Trajectory(
            timestamps=np.asarray(self._stamps, dtype=np.float64),
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


def frame_indices(num_frames: int, max_frames: int | None, every: int) -> list[int]:
    """Every `every`-th frame index, at most `max_frames` of them."""
    if every < 1:
        raise ConfigError(f"every must be >= 1 (take every n-th frame), got {every}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"max_frames must be >= 1 or None, got {max_frames}")
    return list(range(0, num_frames, every))[:max_frames]


def slam_for_dataset(
    config: PlaneSlamConfig,
    dataset: TumDataset,
    first_index: int,
    backend: BackendKind | str | None = None,
    seed: int | None = None,
) -> SLAM:
    """A SLAM whose world frame is the dataset's ground-truth frame: it starts at the
    ground-truth pose of frame `first_index` (the identity without ground truth), so the
    estimates and the truth can be compared pose by pose."""
    T_world_first = dataset.groundtruth_pose(dataset.timestamps[first_index])
    return SLAM(config, backend, T_world_first=T_world_first, seed=seed)


def _read(dataset: TumDataset, index: int) -> tuple[Frame, float]:
    t0 = time.perf_counter()
    frame = dataset[index]
    return frame, 1e3 * (time.perf_counter() - t0)


def run_frames(
    slam: SLAM,
    dataset: TumDataset,
    indices: Iterable[int],
    on_result: Callable[[FrameResult], None] | None = None,
) -> RunSummary:
    """Feed `dataset[i]` for i in `indices` to `slam`; `on_result` sees every FrameResult as
    it comes (write it out there: an interrupted run then keeps what it did). The next
    frame is read on a second thread while this one is processed; the 'read' stage is the
    reader's time, which overlaps processing."""
    timings: list[dict[str, float]] = []
    paths: dict[str, int] = {}
    lost = keyframes = 0
    indices = list(indices)
    start = time.perf_counter()
    # Frames are read (PNG decoding releases the GIL) one ahead on a second thread.
    try:
        with (
            single_native_threads(),
            concurrent.futures.ThreadPoolExecutor(max_workers=1) as reader,
        ):
            upcoming = [reader.submit(_read, dataset, indices[0])] if indices else []
            for k in range(len(indices)):
                frame, read_ms = upcoming.pop().result()
                if k + 1 < len(indices):
                    upcoming.append(reader.submit(_read, dataset, indices[k + 1]))
                result = slam.process(frame.depth_m, frame.timestamp, frame.rgb)
                timings.append({"read": read_ms, **result.stage_ms})
                paths[result.path.value] = paths.get(result.path.value, 0) + 1
                lost += result.lost
                keyframes += result.keyframe
                if on_result is not None:
                    on_result(result)
        finish_ms = slam.finish()
    except BaseException:  # interrupted or failed: stop the backend, keep the map as it is
        slam.close()
        raise
    return RunSummary(
        frames=len(timings),
        seconds=time.perf_counter() - start,
        lost_frames=lost,
        keyframes=keyframes,
        paths=paths,
        frame_timings=timings,
        finish_ms=finish_ms,
    )
