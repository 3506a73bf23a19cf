"""Point-based baseline: Open3D RGB-D odometry, frame to frame, as a user would run it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from planeslam.camera import CameraConfig
from planeslam.dataset import Frame, TumDataset
from planeslam.errors import EvaluationError
from planeslam.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BaselineResult:
    """Trajectory and cost of one baseline run."""

    trajectory: Trajectory
    """Estimated T_world_cam per processed frame (frame timestamps)."""
    frames: int
    """Frames processed."""
    seconds: float
    """Wall-clock time of processing, frame reading included, set-up excluded [s]."""
    lost_frames: int
    """Frames whose registration failed (their motion was extrapolated)."""
    frame_timings: list[dict[str, float]] = field(default_factory=list, repr=False)
    """Per frame {stage: ms}: 'read', 'rgbd_image', 'odometry'."""


def open3d_intrinsic(camera: CameraConfig) -> o3d.camera.PinholeCameraIntrinsic:
    """Open3D pinhole intrinsics of our camera (distortion is not modelled by Open3D)."""
    return o3d.camera.PinholeCameraIntrinsic(
        camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    )


def rgbd_image(frame: Frame, depth_trunc_m: float) -> o3d.geometry.RGBDImage:
    """Open3D RGBDImage (intensity + depth in metres, 0 beyond `depth_trunc_m`) of a Frame."""
    color = o3d.geometry.Image(np.ascontiguousarray(frame.rgb, dtype=np.uint8))
    depth = o3d.geometry.Image(np.ascontiguousarray(frame.depth_m, dtype=np.float32))
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, depth, depth_scale=1.0, depth_trunc=depth_trunc_m, convert_rgb_to_intensity=True
    )


def initial_pose(dataset: TumDataset, timestamp: float) -> np.ndarray:
    """(4, 4) ground-truth T_world_cam nearest to `timestamp` within the dataset's association
    window, else the identity."""
    gt = dataset.groundtruth
    if gt is None or len(gt) == 0:
        return np.eye(4)
    k = int(np.argmin(np.abs(gt.timestamps - timestamp)))
    if abs(gt.timestamps[k] - timestamp) > dataset.config.max_time_difference_s:
        log.info("no ground-truth pose near %.3f s: the baseline starts at the identity", timestamp)
        return np.eye(4)
    return np.array(gt.T_world_cam[k], dtype=np.float64)


def registration_ok(success: bool, T: np.ndarray, information: np.ndarray) -> bool:
    """Whether an Open3D odometry result can be used.

    Open3D reports success with an identity or NaN motion and a zero (6, 6) information
    matrix when no pixel has a correspondence (blank depth), so its flag alone is not enough:
    also require a finite motion and an information matrix of full rank.
    """
    if not success or not np.all(np.isfinite(T)) or not np.all(np.isfinite(information)):
        return False
    eig = np.linalg.eigvalsh(0.5 * (information + information.T))
    return bool(eig[-1] > 0 and eig[0] > 1e-9 * eig[-1])


def run_open3d_odometry(
    dataset: TumDataset,
    max_frames: int | None = None,
    every: int = 1,
    on_pose: Callable[[float, np.ndarray], None] | None = None,
    depth_trunc_m: float = 4.0,
    depth_diff_max_m: float = 0.03,
) -> BaselineResult:
    """Frame-to-frame Open3D RGB-D odometry (hybrid photometric + geometric Jacobian).

    Uses every `every`-th frame, at most `max_frames` of them; each frame is registered to
    the previous processed one from an identity guess and the relative motions are chained
    from the first ground-truth pose (identity without ground truth). A failed registration
    repeats the previous relative motion (constant velocity; identity for the first) and
    counts as lost (see `registration_ok`). `on_pose(timestamp, T_world_cam)` is called for
    every pose as it is estimated (e.g. `TumWriter.write`).
    """
    if every < 1:
        raise EvaluationError(f"every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise EvaluationError(f"max_frames must be >= 1, got {max_frames}")
    indices = list(range(0, len(dataset), every))[:max_frames]
    intrinsic = open3d_intrinsic(dataset.camera)
    option = o3d.pipelines.odometry.OdometryOption(
        depth_diff_max=depth_diff_max_m, depth_min=0.0, depth_max=depth_trunc_m
    )
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    stamps: list[float] = []
    poses: list[np.ndarray] = []
    timings: list[dict[str, float]] = []
    lost = 0
    previous: o3d.geometry.RGBDImage | None = None
    T_prev_cur_last = np.eye(4)
    start = time.perf_counter()
    for index in indices:
        t0 = time.perf_counter()
        frame = dataset[index]
        t1 = time.perf_counter()
        current = rgbd_image(frame, depth_trunc_m)
        t2 = time.perf_counter()
        if previous is None:
            T_world_cam = initial_pose(dataset, frame.timestamp)
        else:
            # source = current, target = previous: the result maps current-camera points
            # into the previous camera frame, i.e. T_prev_cur.
            ok, T_prev_cur, info = o3d.pipelines.odometry.compute_rgbd_odometry(
                current, previous, intrinsic, np.eye(4), jacobian, option
            )
            if not registration_ok(ok, T_prev_cur, info):
                lost += 1
                log.warning(
                    "frame %d (%.3f s): odometry failed, extrapolating", index, frame.timestamp
                )
                T_prev_cur = T_prev_cur_last
            T_prev_cur_last = np.asarray(T_prev_cur, dtype=np.float64)
            T_world_cam = poses[-1] @ T_prev_cur_last
        t3 = time.perf_counter()
        previous = current
        stamps.append(frame.timestamp)
        poses.append(T_world_cam)
        timings.append(
            {"read": 1e3 * (t1 - t0), "rgbd_image": 1e3 * (t2 - t1), "odometry": 1e3 * (t3 - t2)}
        )
        if on_pose is not None:
            on_pose(frame.timestamp, T_world_cam)
    seconds = time.perf_counter() - start
    log.info("open3d odometry: %d frames in %.2f s, %d lost", len(poses), seconds, lost)
    trajectory = Trajectory(
        timestamps=np.asarray(stamps, dtype=np.float64),
        T_world_cam=np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
    )
    return BaselineResult(
        trajectory=trajectory,
        frames=len(poses),
        seconds=seconds,
        lost_frames=lost,
        frame_timings=timings,
    )
