"""A camera's odometry read from a file: the motion between two frames, with its noise.

The file is a TUM trajectory (`timestamp tx ty tz qx qy qz qw`, `read_tum`) of the
camera's odometry poses T_odom_cam: wheel odometry, an IMU or another visual odometry,
moved to the camera frame (a robot base's poses composed with the base-to-camera
transform). Only the motion between two times is used, so the odometry's own world frame
and drift do not matter. `SLAM.process(odometry=...)` takes each step: it predicts the
pose for tracking (filling the directions the planes leave free) and becomes a between
factor in the iSAM2 graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planeslam.core.errors import DatasetFormatError
from planeslam.core.geometry import invert_pose
from planeslam.core.types import RelativePose
from planeslam.io.trajectory import Trajectory, read_tum


@dataclass(frozen=True)
class OdometryFile:
    """Odometry poses and the noise of one step between two frames."""

    path: Path
    trajectory: Trajectory
    """The camera's odometry poses T_odom_cam (their world frame is arbitrary)."""
    sigma_m: float
    """Standard deviation of one step's translation, per axis [m]."""
    sigma_deg: float
    """Standard deviation of one step's rotation, per axis [deg]."""

    @classmethod
    def load(cls, path: str | Path, sigma_m: float = 0.02, sigma_deg: float = 1.0) -> OdometryFile:
        """Read a TUM file (DatasetFormatError naming the file and line on a bad row);
        ValueError for sigmas that are not positive."""
        if not (sigma_m > 0 and sigma_deg > 0):
            raise ValueError(
                f"odometry sigmas must be > 0, got {sigma_m} m and {sigma_deg} deg per step"
            )
        return cls(Path(path), read_tum(path), float(sigma_m), float(sigma_deg))

    def check_covers(self, timestamps: np.ndarray) -> None:
        """DatasetFormatError when the odometry's time span holds none of the frames'
        (N,) timestamps [s] (another clock, another sequence)."""
        t = self.trajectory.timestamps
        inside = (timestamps >= t[0]) & (timestamps <= t[-1])
        if not np.any(inside):
            raise DatasetFormatError(
                f"{self.path}: odometry spans {t[0]:.3f}-{t[-1]:.3f} s, the frames "
                f"{timestamps.min():.3f}-{timestamps.max():.3f} s: expected odometry on the "
                "frames' clock"
            )

    def step(self, t_prev: float, t_cur: float) -> RelativePose | None:
        """The camera's motion T_prev_cur from `t_prev` to `t_cur` [s] with its covariance
        (rotation first, gtsam's order), or None when either time is outside the file's."""
        T_prev = self.trajectory.interpolated(t_prev)
        T_cur = self.trajectory.interpolated(t_cur)
        if T_prev is None or T_cur is None:
            return None
        variances = [np.radians(self.sigma_deg) ** 2] * 3 + [self.sigma_m**2] * 3
        return RelativePose(invert_pose(T_prev) @ T_cur, np.diag(variances))
