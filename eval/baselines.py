"""Point-based baseline: Open3D RGB-D odometry, frame to frame, as a user would run it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from planeslam.core.errors import EvaluationError
from planeslam.core.native_tuning import single_native_threads
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import Trajectory
from planeslam.tracking.odometry import RgbdOdometry

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


def run_open3d_odometry(
    dataset: RgbdDataset,
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
    every pose as it is estimated (e.g. `TumWriter.write`). Native pools run one thread
    each, as in a planeslam run, so a run's figures repeat (`single_native_threads`).
    """
    if every < 1:
        raise EvaluationError(f"every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise EvaluationError(f"max_frames must be >= 1, got {max_frames}")
    indices = list(range(0, len(dataset), every))[:max_frames]
    odometry = RgbdOdometry(dataset.camera, depth_trunc_m, depth_diff_max_m)
    with single_native_threads():
        return _chain_motions(dataset, indices, odometry, on_pose)


def _chain_motions(
    dataset: RgbdDataset,
    indices: list[int],
    odometry: RgbdOdometry,
    on_pose: Callable[[float, np.ndarray], None] | None,
) -> BaselineResult:
    """`run_open3d_odometry`'s loop over the frames `indices` of `dataset`."""
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    timings: list[dict[str, float]] = []
    lost = 0
    previous = None
    T_prev_cur_last = np.eye(4)
    start = time.perf_counter()
    for index in indices:
        t0 = time.perf_counter()
        frame = dataset[index]
        t1 = time.perf_counter()
        current = odometry.image(frame.rgb, frame.depth_m)
        t2 = time.perf_counter()
        if previous is None:
            T_world_cam = dataset.groundtruth_pose(frame.timestamp)
        else:
            # source = current, target = previous: the result maps current-camera points
            # into the previous camera frame, i.e. T_prev_cur.
            T_prev_cur = odometry.motion(current, previous)
            if T_prev_cur is None:
                lost += 1
                log.warning(
                    "frame %d (%.3f s): odometry failed, extrapolating", index, frame.timestamp
                )
                T_prev_cur = T_prev_cur_last
            T_prev_cur_last = T_prev_cur
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
