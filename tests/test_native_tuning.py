"""The native pools `single_native_threads` narrows, and what that buys: a dense
fallback (Open3D's RGB-D odometry) that gives the same bits every time."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from planeslam.core.camera import CameraConfig
from planeslam.core.native_tuning import single_native_threads
from planeslam.tracking.odometry import RgbdOdometry

pytestmark = pytest.mark.unit


def test_one_thread_inside_the_block_and_the_previous_settings_after() -> None:
    o3d.utility.set_max_threads(2)
    cv2.setNumThreads(2)
    try:
        with single_native_threads():
            assert o3d.utility.get_max_threads() == 1
            assert cv2.getNumThreads() == 1
        assert o3d.utility.get_max_threads() == 2
        assert cv2.getNumThreads() == 2
    finally:
        o3d.utility.set_max_threads(0)


def _textured_wall(camera: CameraConfig, shift_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 seeded blurred texture moved `shift_px` to the right and the (H, W)
    depth [m] of a wall tilted about the vertical axis, 1.2-1.8 m away."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (camera.height, camera.width + 40)), (0, 0), 3)
    grey = texture[:, 20 - shift_px : 20 - shift_px + camera.width]
    rgb = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    depth = np.tile(np.linspace(1.2, 1.8, camera.width, dtype=np.float32), (camera.height, 1))
    return rgb, depth


def test_rgbd_odometry_repeats_bit_for_bit_on_one_thread() -> None:
    camera = CameraConfig(width=160, height=120, fx=120.0, fy=120.0, cx=80.0, cy=60.0)
    odometry = RgbdOdometry(camera)
    previous = odometry.image(*_textured_wall(camera, 0))
    current = odometry.image(*_textured_wall(camera, 2))
    with single_native_threads():
        motions = [odometry.motion(current, previous) for _ in range(8)]
    assert motions[0] is not None
    assert np.abs(motions[0][:3, 3]).max() > 1e-3  # it found the shift
    for T in motions[1:]:
        assert T is not None and np.array_equal(T, motions[0])
