"""Organised point cloud from a depth image (paper step 1).

The cloud keeps the image layout: `points[v, u]` is the camera-frame point of
pixel (u, v) in metres (x right, y down, z forward). Invalid pixels (depth 0,
negative, NaN, inf or beyond `max_depth_m`) are all-zero points, so the cloud
is NaN-free and `points[..., 2] > 0` is exactly the validity mask
(`valid_mask` returns it).
"""

from __future__ import annotations

from typing import overload

import numpy as np

from planeslam.core.camera import PixelRays
from planeslam.core.errors import GeometryError
from planeslam.frontend.kernels import back_project_kernel

_RAYS32_CACHE: dict[int, tuple[PixelRays, np.ndarray]] = {}


def rays_float32(rays: PixelRays) -> np.ndarray:
    """(H, W, 3) float32 copy of `rays.rays`, made once per PixelRays object and cached."""
    hit = _RAYS32_CACHE.get(id(rays))
    if hit is not None and hit[0] is rays:
        return hit[1]
    if len(_RAYS32_CACHE) >= 8:
        _RAYS32_CACHE.clear()
    value = np.ascontiguousarray(rays.rays, dtype=np.float32)
    _RAYS32_CACHE[id(rays)] = (rays, value)  # holding `rays` keeps its id unique
    return value


def check_depth_shape(depth_m: np.ndarray, shape: tuple[int, int]) -> None:
    """Raise GeometryError unless `depth_m` is a 2-D image of `shape` (H, W)."""
    if np.ndim(depth_m) != 2 or tuple(np.shape(depth_m)) != tuple(shape):
        raise GeometryError(
            f"depth image has shape {tuple(np.shape(depth_m))}, the camera rays are "
            f"{shape[0]}x{shape[1]} (H, W): use the camera config of this sensor"
        )


def valid_mask(depth_m: np.ndarray, max_depth_m: float = np.inf) -> np.ndarray:
    """(H, W) bool: depth is finite, > 0 and <= max_depth_m [m] (NaN compares False)."""
    depth = np.asarray(depth_m)
    return (depth > 0) & (depth <= max_depth_m) & (depth < np.inf)


def organized_cloud(
    depth_m: np.ndarray, rays: PixelRays, max_depth_m: float = np.inf
) -> np.ndarray:
    """Back-project a depth image: (H, W) metres -> (H, W, 3) float32 camera-frame points [m].

    Invalid pixels (see module docstring) become (0, 0, 0). `rays` comes from
    `PixelRays.for_camera(camera)`, computed once per camera.
    """
    return back_project(depth_m, rays_float32(rays), max_depth_m)


def back_project(
    depth_m: np.ndarray, rays32: np.ndarray, max_depth_m: float = np.inf
) -> np.ndarray:
    """`organized_cloud` with the (H, W, 3) float32 z=1 rays given directly -> (H, W, 3)
    float32 C-contiguous camera-frame points [m], invalid pixels (0, 0, 0)."""
    check_depth_shape(depth_m, rays32.shape[:2])
    depth = np.ascontiguousarray(depth_m, dtype=np.float32)
    # float32 as the comparison with a float32 image would be (cv2.threshold did so)
    limit = np.float32(min(float(max_depth_m), float(np.finfo(np.float32).max)))
    rays = rays32 if rays32.flags.c_contiguous else np.ascontiguousarray(rays32)
    return back_project_kernel(depth, rays, limit)


@overload
def sampled_points(cloud: np.ndarray, stride: int) -> tuple[np.ndarray, None]: ...
@overload
def sampled_points(
    cloud: np.ndarray, stride: int, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray]: ...
@overload
def sampled_points(
    cloud: np.ndarray, stride: int, values: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]: ...
def sampled_points(
    cloud: np.ndarray, stride: int, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The valid points (z > 0, finite) among every `stride`-th pixel in each direction of
    an organised cloud (H, W, 3) -> (N, 3), and the same pixels of `values` (H, W) -> (N,)
    (None without)."""
    xyz = cloud[::stride, ::stride].reshape(-1, 3)
    keep = (xyz[:, 2] > 0) & np.all(np.isfinite(xyz), axis=1)
    picked = None if values is None else values[::stride, ::stride].reshape(-1)[keep]
    return xyz[keep], picked
