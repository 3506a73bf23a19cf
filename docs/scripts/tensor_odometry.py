"""Open3D's tensor RGB-D odometry against the legacy one the dense fallback calls, on one
thread (docs/speed.md, "What is left toward 2x").

    python docs/scripts/tensor_odometry.py [DATASET] [PAIRS]

On the first PAIRS (default 30) consecutive pairs of DATASET (default
../shared/data/7scenes_redkitchen_1000f, which has ground truth): CPU ms per call of
`RgbdOdometry.motion` (legacy `compute_rgbd_odometry`, hybrid term, 20/10/5 iterations)
and of `open3d.t.pipelines.odometry.rgbd_odometry_multi_scale` (hybrid, the same
iterations, depth up to 4 m), three rounds each; then the median error of each one's
translation against the true step [cm].
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np
import open3d as o3d
from _run_probe import first_frames, step

from planeslam.tracking.odometry import RgbdOdometry

o3d.utility.set_max_threads(1)
dataset, camera, frames = first_frames(sys.argv, 30)
count = len(frames) - 1
legacy = RgbdOdometry(camera)
legacy_images = [legacy.image(f.rgb, f.depth_m) for f in frames]
tensor_images = [
    o3d.t.geometry.RGBDImage(
        o3d.t.geometry.Image(np.ascontiguousarray(f.rgb)),
        o3d.t.geometry.Image(np.ascontiguousarray(f.depth_m, dtype=np.float32)),
    )
    for f in frames
]
K = o3d.core.Tensor.from_numpy(
    np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
)
criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(k) for k in (20, 10, 5)]


def tensor_motion(i: int) -> np.ndarray:
    """(4, 4) T_prev_cur of pair i by the tensor odometry."""
    result = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
        tensor_images[i + 1],
        tensor_images[i],
        K,
        o3d.core.Tensor.from_numpy(np.eye(4)),
        1.0,
        4.0,
        criteria,
        o3d.t.pipelines.odometry.Method.Hybrid,
    )
    return result.transformation.numpy()


def legacy_motion(i: int) -> np.ndarray | None:
    return legacy.motion(legacy_images[i + 1], legacy_images[i])


print(f"{dataset.root.name}: {count} pairs, one thread")
for name, motion in (("legacy", legacy_motion), ("tensor", tensor_motion)):
    rounds, motions = [], []
    for _ in range(3):
        start = time.process_time()
        motions = [motion(i) for i in range(count)]
        rounds.append(1e3 * (time.process_time() - start) / count)
    errors = []
    for i, T in enumerate(motions):
        if T is None:
            continue
        T_a = dataset.groundtruth_pose(frames[i].timestamp)
        T_b = dataset.groundtruth_pose(frames[i + 1].timestamp)
        assert T_a is not None and T_b is not None, "needs ground truth"
        errors.append(float(np.linalg.norm(T[:3, 3] - step(T_a, T_b)[:3, 3])))
    print(
        f"  {name}: {', '.join(f'{r:.1f}' for r in rounds)} ms CPU per call "
        f"(median {statistics.median(rounds):.1f}); median step error "
        f"{100 * statistics.median(errors):.2f} cm over {len(errors)} pairs"
    )
