"""Organised point cloud: back-projection, invalid pixels, shape checks."""

from __future__ import annotations

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.errors import GeometryError
from planeslam.frontend.cloud import organized_cloud, valid_mask

pytestmark = pytest.mark.unit

CAMERA = CameraConfig(fx=500.0, fy=480.0, cx=31.5, cy=23.5, width=64, height=48)


def test_cloud_back_projects_each_pixel(rng):
    depth = rng.uniform(0.5, 4.0, (48, 64)).astype(np.float32)
    cloud = organized_cloud(depth, PixelRays.for_camera(CAMERA))
    assert cloud.shape == (48, 64, 3) and cloud.dtype == np.float32
    v, u = 17, 40
    z = float(depth[v, u])
    expected = [(u - CAMERA.cx) / CAMERA.fx * z, (v - CAMERA.cy) / CAMERA.fy * z, z]
    np.testing.assert_allclose(cloud[v, u], expected, rtol=1e-6)
    # projecting back gives the pixel centres
    uu = cloud[..., 0] / cloud[..., 2] * CAMERA.fx + CAMERA.cx
    np.testing.assert_allclose(uu, np.broadcast_to(np.arange(64), (48, 64)), atol=1e-3)


def test_invalid_depth_gives_zero_points():
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    depth[0, :5] = [0.0, -1.0, np.nan, np.inf, 9.0]
    cloud = organized_cloud(depth, PixelRays.for_camera(CAMERA), max_depth_m=6.0)
    assert np.all(np.isfinite(cloud))
    assert np.all(cloud[0, :5] == 0.0)
    assert np.all(cloud[1:, :, 2] == 2.0)
    np.testing.assert_array_equal(cloud[..., 2] > 0, valid_mask(depth, 6.0))


def test_wrong_shape_names_both_shapes():
    with pytest.raises(GeometryError, match=r"\(48, 63\).*48x64"):
        organized_cloud(np.ones((48, 63), np.float32), PixelRays.for_camera(CAMERA))


@pytest.mark.parametrize("max_depth_m", [6.0, np.inf])
def test_cloud_validity_matches_valid_mask_on_garbage(max_depth_m, rng):
    depth = rng.uniform(-2.0, 9.0, (48, 64)).astype(np.float32)
    flat = depth.ravel()
    idx = rng.choice(flat.size, 600, replace=False)
    flat[idx] = rng.choice([np.nan, np.inf, -np.inf, -0.0, 0.0, 1e6], size=600)
    cloud = organized_cloud(depth, PixelRays.for_camera(CAMERA), max_depth_m=max_depth_m)
    assert np.all(np.isfinite(cloud))
    valid = valid_mask(depth, max_depth_m)
    np.testing.assert_array_equal(cloud[..., 2] > 0, valid)
    np.testing.assert_array_equal(cloud[..., 2][valid], depth[valid])
    assert np.all(cloud[~valid] == 0.0)
