"""Compiled (numba) per-plane work of the segmentation's plane records
(`segment_common.build_planes`): every plane's least-squares fit and covariance in one
pass (`plane_of_moments`, also the region growing's refit in `cell_kernels`), the
outline's vertices met with the plane, and the noise of 1/z about the plane for the
rounding gate. Conventions as `kernels` (cache=True, no fast-math; `kernels.warm_up`
loads these too through `warm_up_plane_kernels`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from planeslam.frontend.fused import fma as _fma

FIT_OK, FIT_TOO_FEW_POINTS, FIT_COLLINEAR = 0, 1, 2
"""`plane_fits_kernel`'s status per plane: fit; fewer than 4 points (no covariance);
points (nearly) collinear."""


@njit(cache=True, nogil=True)
def _tangent_basis(n0: float, n1: float, n2: float) -> np.ndarray:
    """`core.geometry.tangent_basis` (GTSAM's `Unit3::basis()`), compiled: (3, 2)."""
    m0, m1, m2 = abs(n0), abs(n1), abs(n2)
    if m0 <= m1 and m0 <= m2:
        b0, b1, b2 = 0.0, n2, -n1
    elif m1 <= m0 and m1 <= m2:
        b0, b1, b2 = -n2, 0.0, n0
    else:
        b0, b1, b2 = n1, -n0, 0.0
    inv = 1.0 / np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    b0, b1, b2 = b0 * inv, b1 * inv, b2 * inv
    basis = np.empty((3, 2))
    basis[0, 0], basis[1, 0], basis[2, 0] = b0, b1, b2
    basis[0, 1] = n1 * b2 - n2 * b1
    basis[1, 1] = n2 * b0 - n0 * b2
    basis[2, 1] = n0 * b1 - n1 * b0
    return basis


@njit(cache=True, nogil=True)
def plane_of_moments(
    centroid: np.ndarray, scatter: np.ndarray
) -> tuple[bool, np.ndarray, float, float]:
    """`core.plane_fit.plane_from_moments`, compiled: the least-squares plane of points with
    this centroid (3,) [m] and scatter (3, 3) [m^2] -> (ok: False when the points are
    (nearly) collinear, unit normal toward the camera (3,), d [m], residual sum of squares
    [m^2])."""
    eigval, eigvec = np.linalg.eigh(scatter)
    normal = np.ascontiguousarray(eigvec[:, 0])
    d = -(normal[0] * centroid[0] + normal[1] * centroid[1] + normal[2] * centroid[2])
    if d < 0:
        normal, d = -normal, -d
    return eigval[1] > 1e-12 * max(eigval[2], 1e-300), normal, d, max(eigval[0], 0.0)


@njit(cache=True, nogil=True)
def plane_fits_kernel(xyz: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, ...]:
    """The least-squares plane of each segment of the points xyz (3, N) float64 [m, camera
    frame]; segment r is columns bounds[r]:bounds[r + 1] (bounds (R + 1,) int).

    Returns count (R,) int64, centroid (R, 3) [m], scatter (R, 3, 3) [m^2] (centred
    products, two passes in float64), normal (R, 3) unit toward the camera, d (R,) [m],
    rss (R,) [m^2] (the smallest eigenvalue of the scatter), covariance (R, 3, 3) in
    OrientedPlane3 local coordinates (`core.plane_fit.plane_covariance`'s formula),
    cubes (R,) the sum of z^3 [m^3] (the area's), and status (R,) int64 (`FIT_OK`,
    `FIT_TOO_FEW_POINTS`, `FIT_COLLINEAR`; the other outputs of such a row are
    undefined)."""
    n_planes = bounds.shape[0] - 1
    count = np.zeros(n_planes, np.int64)
    centroid = np.zeros((n_planes, 3))
    scatter = np.zeros((n_planes, 3, 3))
    normal = np.zeros((n_planes, 3))
    d = np.zeros(n_planes)
    rss = np.zeros(n_planes)
    covariance = np.zeros((n_planes, 3, 3))
    cubes = np.zeros(n_planes)
    status = np.full(n_planes, FIT_OK, np.int64)
    for r in range(n_planes):
        a, b = bounds[r], bounds[r + 1]
        k = b - a
        count[r] = k
        if k <= 3:
            status[r] = FIT_TOO_FEW_POINTS
            continue
        sx = sy = sz = 0.0
        for i in range(a, b):
            sx += xyz[0, i]
            sy += xyz[1, i]
            sz += xyz[2, i]
        cx, cy, cz = sx / k, sy / k, sz / k
        xx = xy = xz = yy = yz = zz = z3 = 0.0
        for i in range(a, b):
            dx, dy, dz = xyz[0, i] - cx, xyz[1, i] - cy, xyz[2, i] - cz
            xx += dx * dx
            xy += dx * dy
            xz += dx * dz
            yy += dy * dy
            yz += dy * dz
            zz += dz * dz
            z = xyz[2, i]
            z3 += z * z * z
        s = scatter[r]
        s[0, 0], s[0, 1], s[0, 2] = xx, xy, xz
        s[1, 0], s[1, 1], s[1, 2] = xy, yy, yz
        s[2, 0], s[2, 1], s[2, 2] = xz, yz, zz
        centroid[r, 0], centroid[r, 1], centroid[r, 2] = cx, cy, cz
        cubes[r] = z3
        ok, unit, offset, residual = plane_of_moments(centroid[r], s)
        if not ok:
            status[r] = FIT_COLLINEAR
            continue
        normal[r], d[r], rss[r] = unit, offset, residual
        n0, n1, n2 = unit[0], unit[1], unit[2]
        # plane_covariance: (rss / (k - 3)) [[M^-1, -M^-1 u], [-u^T M^-1, 1/k + u^T M^-1 u]]
        basis = _tangent_basis(n0, n1, n2)
        m = basis.T @ s @ basis
        u0 = basis[0, 0] * cx + basis[1, 0] * cy + basis[2, 0] * cz
        u1 = basis[0, 1] * cx + basis[1, 1] * cy + basis[2, 1] * cz
        det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
        if not det > 0:
            status[r] = FIT_COLLINEAR
            continue
        i00, i01, i10, i11 = m[1, 1] / det, -m[0, 1] / det, -m[1, 0] / det, m[0, 0] / det
        w0, w1 = i00 * u0 + i01 * u1, i10 * u0 + i11 * u1
        scale = rss[r] / (k - 3)
        c = covariance[r]
        c[0, 0], c[0, 1], c[1, 0], c[1, 1] = scale * i00, scale * i01, scale * i10, scale * i11
        c[0, 2], c[1, 2] = -scale * w0, -scale * w1
        c[2, 0], c[2, 1] = -scale * w0, -scale * w1
        c[2, 2] = scale * (1.0 / k + u0 * w0 + u1 * w1)
    return count, centroid, scatter, normal, d, rss, covariance, cubes, status


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
    """Compile (or load from numba's cache) these kernels for the argument types
    `build_planes` passes, on tiny inputs (`kernels.warm_up` calls it)."""
    n = 2
    plane_fits_kernel(np.ones((3, n)), np.array([0, n], np.int64))  # plane_of_moments too
    points = np.ones((3, 2 * n))[:, :n].T  # a plane's points: a view of segmentation's buffer
    # A plane's normal: an eigenvector (a column view of eigh's result) or a fresh array.
    poly, rays = np.ones((3, 2), np.int32), np.ones((n, n, 3))  # approxPolyDP's int32
    for unit in (np.eye(3)[:, 2], np.array([0.0, 0.0, 1.0])):
        for vertices in (poly, poly.astype(np.int64)):  # int64: the boxPoints fallback
            outline_points_kernel(vertices, 0, 0, (n, n), 1, rays, unit, 1.0)
        inverse_depth_noise_kernel(points.T, unit, 1.0, 0.01, 8)
