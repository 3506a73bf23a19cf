"""Simulated camera odometry (a robot's wheels, an IMU) from a synthetic sequence's truth.

Each step between two consecutive truth poses gets independent Gaussian noise (rotation
vector and translation, per axis, in the step's frame), and the noisy steps are composed
from the identity: the odometry drifts like a random walk, as wheel odometry does. Written
as odometry.txt beside a rendered sequence, it is what `planeslam run --odometry` reads.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.core.geometry import invert_pose
from planeslam.io.trajectory import Trajectory


def noisy_odometry(truth: Trajectory, sigma_m: float, sigma_deg: float, seed: int) -> Trajectory:
    """Odometry poses T_odom_cam (N, 4, 4) at the truth's (N,) timestamps: its steps, each
    moved by noise of `sigma_m` [m] and `sigma_deg` [deg] per axis, drawn from `seed`."""
    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], len(truth), axis=0)
    for k in range(1, len(truth)):
        noise = np.eye(4)
        noise[:3, :3] = Rotation.from_rotvec(
            np.radians(sigma_deg) * rng.standard_normal(3)
        ).as_matrix()
        noise[:3, 3] = sigma_m * rng.standard_normal(3)
        step = invert_pose(truth.T_world_cam[k - 1]) @ truth.T_world_cam[k]
        poses[k] = poses[k - 1] @ step @ noise
    return Trajectory(truth.timestamps.copy(), poses)
