"""Full SLAM, frame by frame: front end -> tracking against the map -> map / backend.

Two backends share the front end, the tracking and the plane-object map:

- `merge`: the paper's system (Section 4.4). Every tracked frame is merged into the map
  (plane statistics refit, longest edges kept, objects re-aggregated); poses are never
  revised.
- `isam2` (default): keyframes go to a GTSAM iSAM2 graph (odometry between keyframes,
  plane and corner landmarks whose identities are the map's plane and corner ids), which
  runs in a child process (`planeslam.backend.worker`) while tracking goes on. A
  keyframe's result is applied `backend.lag_frames` frames later (or at the next
  keyframe): the keyframe takes its optimised pose, the planes and corners it saw move
  onto their landmarks, and the pose tracked since moves by the keyframe's correction.
  Every frame's pose is re-anchored on its optimised keyframe.

`SLAM.process(depth_m, timestamp, rgb)` needs no dataset folder (live cameras, other
sources); `run_frames` drives it over a `TumDataset`. Poses are T_world_cam (4, 4); the
world frame is the first camera's unless `T_world_first` is given.
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from planeslam.backend.isam2 import is_keyframe
from planeslam.config import PlaneSlamConfig
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.geometry import invert_pose, orthonormalize_pose, transform_points
from planeslam.core.native_tuning import single_native_threads
from planeslam.frontend.pipeline import FrameObservation, FrontEnd
from planeslam.io.dataset import Frame, TumDataset
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.map import Map
from planeslam.tracking.odometry import RgbdOdometry
from planeslam.tracking.tracker import MapView, Tracker, TrackResult

if TYPE_CHECKING:
    from planeslam.backend.worker import BackendResult, KeyframeUpdate

logger = logging.getLogger(__name__)

BACKENDS = ("isam2", "merge")

SPARSE_STRIDE = 8
"""Every SPARSE_STRIDE-th pixel (each direction) off all planes goes to the sparse cloud."""

MAPPING_PATHS = ("first", "planes", "relocalised", "planes+odometry")
"""Tracking paths whose poses are accurate enough to be merged into the map or become
keyframes: those fixed by the map's planes and corners, and plane poses completed by RGB-D
odometry (photometric alignment from a good start is sub-millimetre on the synthetic scenes).
Poses that needed ICP, or odometry alone, are tracked but do not write their error into the
map."""

POINT_BYTES = 15
"""Bytes per point of the point cloud the map stands in for: float32 x, y, z + uint8 r, g, b."""


@dataclass(frozen=True)
class FrameResult:
    """What SLAM made of one frame."""

    index: int
    """Position of the frame in the processed sequence (0, 1, ...)."""
    timestamp: float
    """[s]"""
    T_world_cam: np.ndarray
    """(4, 4) pose estimated online (before later optimisation)."""
    path: str
    """How the pose was found (`planeslam.tracking.tracker.PATHS`)."""
    reason: str
    """Why tracking needed a fallback or lost the frame; '' otherwise."""
    keyframe: bool
    """Whether the frame went into the map (merge) or the graph (isam2)."""
    observation: FrameObservation = field(repr=False)
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Wall-clock ms per stage: the front end's, then tracking, map, backend."""

    @property
    def lost(self) -> bool:
        return self.path == "lost"

    def to_record(self) -> dict[str, Any]:
        """One line of frames.jsonl."""
        return {
            "index": self.index,
            "timestamp": self.timestamp,
            "path": self.path,
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
        backend: str = "isam2",
        T_world_first: np.ndarray | None = None,
        seed: int = 0,
    ) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"backend {backend!r} unknown; expected one of {', '.join(BACKENDS)}")
        self.config = config
        self.backend_name = backend
        self.front_end = FrontEnd(config, seed=seed)
        odometry = RgbdOdometry(config.camera) if config.tracking.rgbd_odometry else None
        self.tracker = Tracker(config.tracking, odometry)
        self.map = Map(config.map, config.objects)
        self.backend = None
        if backend == "isam2":
            from planeslam.backend.worker import BackendWorker

            self.backend = BackendWorker(config.backend, inline=not config.backend.run_in_process)
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
        self._pending: tuple[int, list[int], list[int]] | None = None
        """The keyframe in the backend whose result is not applied yet: (frame index, map
        plane ids, map corner ids it saw). One at most: a keyframe merged into the map
        before the previous one's correction would stay uncorrected there."""
        self.backend_result: BackendResult | None = None
        """What the iSAM2 backend reported at `finish`: update times, failures, factors."""
        self.pointcloud_bytes = 0
        """Bytes of the point cloud of every processed frame (valid depth x POINT_BYTES)."""

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
        if self.backend is None:
            return True  # the paper merges every frame
        T_kf = self._keyframe_online[self._last_keyframe]
        since = self.frames - self._last_keyframe
        new_structure = new_planes >= self.config.backend.keyframe_new_planes
        return is_keyframe(self.config.backend, T_kf, T_world_cam, since) or new_structure

    # -------------------------------------------------------------------------- frames

    def process(
        self, depth_m: np.ndarray, timestamp: float, rgb: np.ndarray | None = None
    ) -> FrameResult:
        """Process one frame: (H, W) depth [m] (0 = invalid), its timestamp [s], and
        optionally (H, W, 3) uint8 RGB (for the RGB-D odometry fallback and map colours)."""
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

        if self._pending and index - self._pending[0] >= self.config.backend.lag_frames:
            t0 = time.perf_counter()
            self._apply_update(self.backend.collect())
            stage_ms["backend"] = 1e3 * (time.perf_counter() - t0)

        t0 = time.perf_counter()
        T_pred = self.predicted_pose()
        if index == 0:
            track = TrackResult(self._T_world_first, "first", "first frame")
        else:
            track = self.tracker.track(observation, self.map_view(), T_pred, rgb, depth_m)
        T_world_cam = orthonormalize_pose(track.T_world_cam)
        stage_ms["tracking"] = 1e3 * (time.perf_counter() - t0)

        keyframe = track.path in MAPPING_PATHS and self._is_keyframe(T_world_cam, track.new_planes)
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

    def _add_keyframe(self, index, timestamp, observation, track, rgb, stage_ms) -> np.ndarray:
        """Merge the frame into the map and, with iSAM2, hand it to the smoother (after
        applying the previous keyframe's result if it is still pending). Returns the
        frame's pose: corrected by that result, or with `lag_frames` 0 the optimised one."""
        T_world_cam = track.T_world_cam
        if self._pending:
            t0 = time.perf_counter()
            correction = self._apply_update(self.backend.collect())
            T_world_cam = orthonormalize_pose(correction @ T_world_cam)
            stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        t0 = time.perf_counter()
        planes = self.map.merge(
            observation,
            T_world_cam,
            track.plane_pairs,
            track.corner_pairs,
            reaggregate=self.backend is None,  # with iSAM2, update_geometry re-aggregates
        )
        self._add_sparse_points(observation, T_world_cam, rgb)
        stage_ms["map"] = 1e3 * (time.perf_counter() - t0)
        if self.backend is not None:
            t0 = time.perf_counter()
            corner_ids = self._corner_ids(observation, planes)
            odometry = None  # measured motion since the last keyframe
            if self._last_keyframe is not None:
                odometry = invert_pose(self._keyframe_online[self._last_keyframe]) @ T_world_cam
            self.backend.submit(
                index, timestamp, T_world_cam, observation, planes, corner_ids, odometry
            )
            self._keyframe_online[index] = T_world_cam
            self._pending = (index, list(planes.values()), list(corner_ids.values()))
            if self.config.backend.lag_frames == 0:
                self._apply_update(self.backend.collect(), move_last_tracked=False)
                T_world_cam = self._keyframe_online[index]
            stage_ms["backend"] = stage_ms.get("backend", 0.0) + 1e3 * (time.perf_counter() - t0)
        return T_world_cam

    def _apply_update(self, update: KeyframeUpdate, move_last_tracked: bool = True) -> np.ndarray:
        """The pending keyframe's result: its pose becomes the optimised one, and the planes
        and corners it saw move onto their landmarks (tracking uses them next; the whole
        map and its objects are rebuilt in `finish`). Returns the correction (4, 4)
        T_optimised @ T_online^-1, which also moves the last tracked pose (frames since the
        keyframe were tracked in the uncorrected map) unless told not to."""
        index, plane_ids, corner_ids = self._pending
        self._pending = None
        assert update.index == index, "backend results come back in submission order"
        correction = update.T_world_cam @ invert_pose(self._keyframe_online[index])
        self._keyframe_online[index] = self._keyframe_final[index] = update.T_world_cam
        self._update_map_geometry(
            update.planes, update.corners, plane_ids, corner_ids, reaggregate=False
        )
        if move_last_tracked and self._last_tracked is not None:
            self._last_tracked = orthonormalize_pose(correction @ self._last_tracked)
        return correction

    def _update_map_geometry(
        self,
        plane_estimates: dict[int, tuple[np.ndarray, float]],
        corner_estimates: dict[int, np.ndarray],
        plane_ids: Iterable[int] | None = None,
        corner_ids: Iterable[int] | None = None,
        reaggregate: bool = True,
        min_change: float = 1e-5,
    ) -> None:
        """Move the map's planes and corners (those listed; all when None) onto the
        optimised landmarks that moved by more than `min_change` (rad for normals, m for
        offsets and points), then re-aggregate the objects if asked."""
        current, current_corners = self.map.planes, self.map.corners
        planes, corners = {}, {}
        for pid in plane_estimates if plane_ids is None else plane_ids:
            old, new = current.get(pid), plane_estimates.get(pid)
            if old is None or new is None:
                continue
            n, d = new
            if abs(d - old.d) > min_change or np.max(np.abs(n - old.normal)) > min_change:
                planes[pid] = (n, d)
        for cid in corner_estimates if corner_ids is None else corner_ids:
            old, point = current_corners.get(cid), corner_estimates.get(cid)
            if old is not None and point is not None:
                if np.max(np.abs(point - old.point)) > min_change:
                    corners[cid] = point
        self.map.update_geometry(planes, corners, reaggregate=reaggregate)

    def _corner_ids(self, observation, planes: dict[int, int]) -> dict[int, int]:
        """{observed corner index: map corner id} for corners whose three planes are mapped
        onto the three planes of a map corner (after `Map.merge`)."""
        by_planes = {tuple(sorted(c.planes)): cid for cid, c in self.map.corners.items()}
        ids = {}
        for k, corner in enumerate(observation.structure.corners):
            if not all(i in planes for i in corner.planes):
                continue
            key = tuple(sorted(planes[i] for i in corner.planes))
            if key in by_planes and len(set(key)) == 3:
                ids[k] = by_planes[key]
        return ids

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
        self._stamps.append(float(timestamp))
        self._anchor.append(anchor)
        self._T_anchor_cam.append(invert_pose(self._keyframe_online[anchor]) @ T_world_cam)

    def finish(self) -> float:
        """End of the sequence. With iSAM2: a batch optimisation of the whole graph
        (`backend.final_iterations`, 0 for none), every keyframe pose taken from the result
        and the whole map (planes, corners, then objects) rebuilt from the optimised
        landmarks; the backend then stops (a SLAM takes no frames after `finish`).
        Returns the wall-clock ms."""
        if self.backend is None:
            return 0.0
        start = time.perf_counter()
        self._pending = None  # the final state below supersedes its result
        result = self.backend.finish(self.config.backend.final_iterations)
        for kf, (_, T) in result.keyframe_poses.items():
            self._keyframe_final[kf] = T
        self._update_map_geometry(result.planes, result.corners)
        self.backend_result = result
        return 1e3 * (time.perf_counter() - start)

    def close(self) -> None:
        """Stop the backend without optimising (an interrupted run); idempotent."""
        if self.backend is not None:
            self.backend.close()

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
        raise ConfigError(f"--every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
    return list(range(0, num_frames, every))[:max_frames]


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
            upcoming = reader.submit(_read, dataset, indices[0]) if indices else None
            for k in range(len(indices)):
                frame, read_ms = upcoming.result()
                if k + 1 < len(indices):
                    upcoming = reader.submit(_read, dataset, indices[k + 1])
                result = slam.process(frame.depth_m, frame.timestamp, frame.rgb)
                timings.append({"read": read_ms, **result.stage_ms})
                paths[result.path] = paths.get(result.path, 0) + 1
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
