"""Plane observation: a camera-frame plane measurement of a world-frame plane landmark.

Error (3,), identical to gtsam's `OrientedPlane3Factor`:

    pi_cam = pi_world.transform(T_world_cam)           # n_cam = R^T n_world,
                                                       # d_cam = n_world . t + d_world
    e = pi_cam.errorVector(z_cam)
      = (B(n_cam)^T n_z,  d_cam - d_z)                 # B: Unit3 tangent basis at n_cam

The first two components are the measured normal projected onto the tangent
plane of the predicted normal [rad, small-angle], the third the offset error
[m]. Keys: (pose T_world_cam: Pose3, plane landmark in the world frame:
OrientedPlane3). The noise is the (3, 3) covariance of the plane fit in
OrientedPlane3 local coordinates (`segmentation.Plane.covariance`): (xi, d) with the
measured normal n + B xi. Mind the signs: the normal part of gtsam's error is
measured - predicted, the offset part predicted - measured, so the fit covariance's
normal/offset cross terms change sign in error coordinates (`error_covariance`). Passing
the fit covariance unconverted biases the optimum wherever the cross terms matter
(planes whose centroid is far from the optical axis): on the synthetic box-in-a-room it
tripled the ATE.
"""

from __future__ import annotations

import gtsam
import numpy as np

from planeslam.core.errors import GeometryError

from ._noise import distinct_keys, gaussian_noise, robust_noise

_ERROR_SIGNS = np.array([1.0, 1.0, -1.0])


def error_covariance(fit_covariance: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of the factor's error from the (3, 3) plane-fit covariance in
    (xi [rad], d [m]) coordinates: the normal/offset cross terms change sign."""
    cov = np.asarray(fit_covariance, dtype=np.float64)
    return cov * np.outer(_ERROR_SIGNS, _ERROR_SIGNS)


def _noise_model(noise: np.ndarray | gtsam.noiseModel.Gaussian) -> gtsam.noiseModel.Gaussian:
    if isinstance(noise, gtsam.noiseModel.Base):
        return gaussian_noise(noise, 3)
    return gaussian_noise(error_covariance(noise), 3)


def plane_factor(
    measured_cam: np.ndarray | gtsam.OrientedPlane3,
    noise: np.ndarray | gtsam.noiseModel.Gaussian,
    pose_key: int,
    plane_key: int,
) -> gtsam.OrientedPlane3Factor:
    """Built-in plane observation factor (Gaussian noise only).

    measured_cam: (4,) [n_x, n_y, n_z, d] in the camera frame, normal toward the camera
    (d > 0), or an OrientedPlane3; noise: the (3, 3) plane-fit covariance in (xi, d)
    coordinates (converted by `error_covariance`), or a Gaussian model of the error itself.
    """
    z_cam = measured_plane(measured_cam)
    keys = distinct_keys(pose_key, plane_key)
    return gtsam.OrientedPlane3Factor(z_cam.planeCoefficients(), _noise_model(noise), *keys)


def robust_plane_factor(
    measured_cam: np.ndarray | gtsam.OrientedPlane3,
    noise: np.ndarray | gtsam.noiseModel.Gaussian,
    pose_key: int,
    plane_key: int,
    loss: str = "huber",
    k: float | None = None,
) -> gtsam.CustomFactor:
    """Plane observation with a robust loss: the built-in factor's error and Jacobians.

    loss: 'huber' or 'cauchy'; k: threshold in whitened units (default 1.345 for
    Huber, 2.3849 for Cauchy). Other arguments as `plane_factor`.
    """
    z_cam = measured_plane(measured_cam)
    pose_key, plane_key = distinct_keys(pose_key, plane_key)
    model = robust_noise(_noise_model(noise), loss, k)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        T_world_cam = values.atPose3(pose_key)
        plane_world = values.atOrientedPlane3(plane_key)
        if H is None:
            return plane_world.transform(T_world_cam).errorVector(z_cam)
        pred_H_plane = np.zeros((3, 3), order="F")
        pred_H_pose = np.zeros((3, 6), order="F")
        err_H_pred = np.zeros((3, 3), order="F")
        plane_cam = plane_world.transform(T_world_cam, pred_H_plane, pred_H_pose)
        err = plane_cam.errorVector(z_cam, err_H_pred)
        H[0] = err_H_pred @ pred_H_pose
        H[1] = err_H_pred @ pred_H_plane
        return err

    return gtsam.CustomFactor(model, [pose_key, plane_key], error)


def measured_plane(measured_cam: np.ndarray | gtsam.OrientedPlane3) -> gtsam.OrientedPlane3:
    """(4,) plane or OrientedPlane3 -> OrientedPlane3 with unit normal and d > 0.

    A non-unit normal is rescaled with its offset (OrientedPlane3's own constructor
    would normalise n but keep d). A plane with d <= 0 faces away from the camera:
    orient it first (`planeslam.core.geometry.orient_plane_toward`), since a flipped normal
    gives zero normal error and a wrong offset error.
    """
    if isinstance(measured_cam, gtsam.OrientedPlane3):
        coeffs = measured_cam.planeCoefficients()
    else:
        coeffs = np.asarray(measured_cam, dtype=np.float64)
        if coeffs.shape != (4,) or not np.all(np.isfinite(coeffs)):
            raise GeometryError(
                f"measured plane of shape {coeffs.shape}: expected finite (4,) [n, d]"
            )
    norm = float(np.linalg.norm(coeffs[:3]))
    if norm < 1e-9:
        raise GeometryError(f"measured plane {coeffs}: normal has zero length")
    coeffs = coeffs / norm
    if coeffs[3] <= 0.0:
        raise GeometryError(
            f"measured plane {coeffs}: expected d > 0 (normal toward the camera); orient it first"
        )
    return gtsam.OrientedPlane3(coeffs)
