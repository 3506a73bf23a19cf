"""Open3D RGB-D odometry between two frames: the point-based fallback of tracking and the
baseline a user would otherwise pick (`planeslam.eval.baselines`)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from planeslam.core.camera import CameraConfig


def open3d_intrinsic(camera: CameraConfig) -> o3d.camera.PinholeCameraIntrinsic:
    """Open3D pinhole intrinsics of our camera (distortion is not modelled by Open3D)."""
    return o3d.camera.PinholeCameraIntrinsic(
        camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    )


def rgbd_image(
    rgb: np.ndarray, depth_m: np.ndarray, depth_trunc_m: float
) -> o3d.geometry.RGBDImage:
    """Open3D RGBDImage (intensity + depth [m], 0 beyond `depth_trunc_m`) from an (H, W, 3)
    uint8 RGB image and an (H, W) depth image in metres."""
    # Open3D's stubs type the buffer argument too narrowly for numpy arrays.
    color = o3d.geometry.Image(np.ascontiguousarray(rgb, dtype=np.uint8))  # type: ignore[call-overload]
    depth = o3d.geometry.Image(np.ascontiguousarray(depth_m, dtype=np.float32))  # type: ignore[call-overload]
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, depth, depth_scale=1.0, depth_trunc=depth_trunc_m, convert_rgb_to_intensity=True
    )


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


class RgbdOdometry:
    """Frame-to-frame Open3D RGB-D odometry (hybrid photometric + geometric Jacobian)."""

    def __init__(
        self, camera: CameraConfig, depth_trunc_m: float = 4.0, depth_diff_max_m: float = 0.03
    ) -> None:
        self.intrinsic = open3d_intrinsic(camera)
        self.depth_trunc_m = depth_trunc_m
        self.option = o3d.pipelines.odometry.OdometryOption(
            depth_diff_max=depth_diff_max_m, depth_min=0.0, depth_max=depth_trunc_m
        )
        self.jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def image(self, rgb: np.ndarray, depth_m: np.ndarray) -> o3d.geometry.RGBDImage:
        """The RGBDImage this odometry compares (see `rgbd_image`)."""
        return rgbd_image(rgb, depth_m, self.depth_trunc_m)

    def motion(
        self,
        current: o3d.geometry.RGBDImage,
        previous: o3d.geometry.RGBDImage,
        T_prev_cur_init: np.ndarray | None = None,
    ) -> np.ndarray | None:
        """(4, 4) T_prev_cur mapping current-camera points into the previous camera frame,
        or None when the registration failed (see `registration_ok`)."""
        init = np.eye(4) if T_prev_cur_init is None else np.asarray(T_prev_cur_init, float)
        ok, T, info = o3d.pipelines.odometry.compute_rgbd_odometry(
            current, previous, self.intrinsic, init, self.jacobian, self.option
        )
        T = np.asarray(T, dtype=np.float64)
        return T if registration_ok(ok, T, np.asarray(info)) else None
