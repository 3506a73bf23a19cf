"""Corner observation: a trihedral corner measured in the camera frame.

Error (3,) [m]:

    e = T_world_cam^-1 * p_world - p_cam_measured      (Pose3.transformTo)

Keys: (pose T_world_cam: Pose3, corner landmark p_world: Point3). Jacobians come
from `Pose3.transformTo`: w.r.t. the pose's local coordinates (rotation first,
then translation, body frame) and w.r.t. the point. gtsam's Python wrapper has
no `PoseToPointFactor`; the test uses `ReferenceFrameFactorPoint3Pose3` on the
inverse pose as the oracle.
"""

from __future__ import annotations

import gtsam
import numpy as np

from planeslam.core.errors import ConfigError, GeometryError

from ._noise import distinct_keys, gaussian_noise


def corner_factor(
    measured_cam: np.ndarray,
    noise: np.ndarray | gtsam.noiseModel.Gaussian | gtsam.noiseModel.Robust,
    pose_key: int,
    corner_key: int,
) -> gtsam.CustomFactor:
    """Corner point measured in the camera frame against a world-frame Point3 landmark.

    measured_cam: (3,) corner in the camera frame [m]; noise: (3, 3) covariance [m^2],
    a Gaussian noise model, or a 3-D `noiseModel.Robust` (a CustomFactor takes any).
    """
    p_cam = np.array(measured_cam, dtype=np.float64)
    if p_cam.shape != (3,) or not np.all(np.isfinite(p_cam)):
        raise GeometryError(f"measured corner of shape {p_cam.shape}: expected finite (3,)")
    pose_key, corner_key = distinct_keys(pose_key, corner_key)
    model: gtsam.noiseModel.Base
    if isinstance(noise, gtsam.noiseModel.Robust):
        if noise.dim() != 3:
            raise ConfigError(f"noise model of dimension {noise.dim()}: expected 3")
        model = noise
    else:
        model = gaussian_noise(noise, 3)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        T_world_cam = values.atPose3(pose_key)
        p_world = values.atPoint3(corner_key)
        if H is None:
            return T_world_cam.transformTo(p_world) - p_cam
        H_pose = np.zeros((3, 6), order="F")
        H_point = np.zeros((3, 3), order="F")
        err = T_world_cam.transformTo(p_world, H_pose, H_point) - p_cam
        H[0] = H_pose
        H[1] = H_point
        return err

    return gtsam.CustomFactor(model, [pose_key, corner_key], error)
