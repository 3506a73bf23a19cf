"""Compiled (numba) per-plane work of the segmentation's plane records
(`segment_common.build_plane`): the outline's vertices met with the plane, and the noise
of 1/z about the plane for the rounding gate. Conventions as `kernels` (cache=True, no
fast-math; `kernels.warm_up` loads these too through `warm_up_plane_kernels`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from planeslam.frontend.fused import fma as _fma


@njit(cache=True, nogil=True)
def outline_points_kernel(
    poly: np.ndarray,
    u0: int,
    v0: int,
    small_shape: tuple[int, int],
    stride: int,
    rays: np.ndarray,
    normal: np.ndarray,
    d: float,
) -> np.ndarray:
    """Polygon vertices poly (M, 2) int (u, v) on the strided label grid, offset by its
    box corner (u0, v0) -> (M, 3) float64 points [m, camera frame] on the plane
    n . x + d = 0: each vertex scaled to full-image pixels (every `stride`-th; the grid's
    last row / column (`small_shape` (rows, cols)) to the image border), its z=1 ray
    (`rays` (H, W, 3) float64) met with the plane; a ray within 1e-9 of parallel to it
    meets it at -d / -1e-9. As numpy's `rays @ normal` (OpenBLAS's dgemv) and after."""
    height, width = rays.shape[0], rays.shape[1]
    last_v, last_u = small_shape[0] - 1, small_shape[1] - 1
    out = np.empty((poly.shape[0], 3))
    for m in range(poly.shape[0]):
        u, v = poly[m, 0] + u0, poly[m, 1] + v0
        u = width - 1 if u == last_u else min(max(stride * u, 0), width - 1)
        v = height - 1 if v == last_v else min(max(stride * v, 0), height - 1)
        r0, r1, r2 = rays[v, u, 0], rays[v, u, 1], rays[v, u, 2]
        # dgemv_t's order for rows of three: fma(r2, n2, fma(r0, n0, r1 n1))
        along: float = _fma(r2, normal[2], _fma(r0, normal[0], r1 * normal[1]))  # type: ignore[call-arg]
        if not abs(along) > 1e-9:
            along = -1e-9
        scale = -d / along
        out[m, 0] = r0 * scale
        out[m, 1] = r1 * scale
        out[m, 2] = r2 * scale
    return out


@njit(cache=True, nogil=True)
def inverse_depth_noise_kernel(
    xyz: np.ndarray, normal: np.ndarray, d: float, step: float, sample: int
) -> float:
    """Noise of 1/z about the plane (normal (3,), d [m]) before a rounding of `step`
    [1/m], in steps, from every max(1, K // sample)-th of the points xyz (3, K) [m]:
    `quantised_fit.inverse_depth_residual_steps` on them, in one pass (summed in order,
    not pairwise: equal to it within about 1e-12 relative, not bit for bit)."""
    k = xyz.shape[1]
    s = max(1, k // sample)
    n0, n1, n2 = normal[0], normal[1], normal[2]
    total = 0.0
    count = 0
    for i in range(0, k, s):
        z = xyz[2, i]
        r = 1.0 / z + (xyz[0, i] * n0 + xyz[1, i] * n1 + z * n2) / (z * d)
        total += r * r
        count += 1
    variance = total / count - step * step / 12.0
    return np.sqrt(max(variance, 0.0)) / step


def warm_up_plane_kernels() -> None:
    """Compile (or load from numba's cache) both kernels for the argument types
    `build_plane` passes, on tiny inputs (`kernels.warm_up` calls it)."""
    n = 2
    points = np.ones((3, 2 * n))[:, :n].T  # a plane's points: a view of segmentation's buffer
    # A plane's normal: an eigenvector (a column view of eigh's result) or a fresh array.
    poly, rays = np.ones((3, 2), np.int32), np.ones((n, n, 3))  # approxPolyDP's int32
    for unit in (np.eye(3)[:, 2], np.array([0.0, 0.0, 1.0])):
        for vertices in (poly, poly.astype(np.int64)):  # int64: the boxPoints fallback
            outline_points_kernel(vertices, 0, 0, (n, n), 1, rays, unit, 1.0)
        inverse_depth_noise_kernel(points.T, unit, 1.0, 0.01, 8)
