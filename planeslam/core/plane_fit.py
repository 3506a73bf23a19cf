"""Least-squares plane fitting from sufficient statistics, and its covariance.

A set of points is summarised by (count, centroid, scatter), scatter being the
sum of outer products of the centred points. These merge exactly
(`merge_moments`), so planes can be refit from cells or segments without
revisiting their points. The fitted plane is n . x + d = 0 with the unit normal
toward the camera (d > 0 in the camera frame). Its covariance is expressed in
GTSAM `OrientedPlane3` local coordinates: two tangent-space components of the
normal in the basis of `tangent_basis` (identical to `gtsam.Unit3(n).basis()`),
then d.
"""

from __future__ import annotations

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import GeometryError
from planeslam.core.geometry import tangent_basis


def moments_of(points: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """(K, 3) points [m] -> (count, centroid (3,), scatter (3, 3) [m^2]), float64."""
    cols = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    return moments_of_columns(cols[0], cols[1], cols[2])


def moments_of_columns(
    x: np.ndarray, y: np.ndarray, z: np.ndarray
) -> tuple[int, np.ndarray, np.ndarray]:
    """Moments of points given as three contiguous (K,) float64 coordinate arrays [m].

    Uses raw second moments minus K c c^T: exact enough in float64 for room-scale
    coordinates (cancellation costs ~1e-12 of the scatter) and ~10x faster than
    centring a (K, 3) array.
    """
    count = len(x)
    if count == 0:
        raise GeometryError("cannot fit a plane to 0 points")
    cols = (x, y, z)
    centroid = np.array([c.sum() for c in cols]) / count
    raw = np.empty((3, 3))
    for i in range(3):
        for j in range(i, 3):
            raw[i, j] = raw[j, i] = cols[i] @ cols[j]
    return count, centroid, raw - count * np.outer(centroid, centroid)


def merge_moments(
    counts: np.ndarray, centroids: np.ndarray, scatters: np.ndarray
) -> tuple[int, np.ndarray, np.ndarray]:
    """Combine G groups: counts (G,), centroids (G, 3), scatters (G, 3, 3) -> merged
    (count, centroid (3,), scatter (3, 3)), exactly as if fit on all points together."""
    counts = np.asarray(counts, dtype=np.float64)
    total = counts.sum()
    centroid = counts @ centroids / total
    offsets = centroids - centroid
    scatter = scatters.sum(axis=0) + np.einsum("g,gi,gj->ij", counts, offsets, offsets)
    return int(round(total)), centroid, scatter


def plane_from_moments(
    centroid: np.ndarray, scatter: np.ndarray
) -> tuple[np.ndarray, float, float]:
    """Least-squares plane of points with this centroid (3,) and scatter (3, 3).

    Returns (unit normal toward the camera (3,), d [m], residual sum of squares [m^2]).
    Raises GeometryError when the points are (nearly) collinear.
    """
    eigval, eigvec = np.linalg.eigh(scatter)
    if not eigval[1] > 1e-12 * max(eigval[2], 1e-300):
        raise GeometryError(
            f"plane fit is degenerate: points are collinear (scatter eigenvalues {eigval})"
        )
    normal = eigvec[:, 0]
    d = -float(normal @ centroid)
    if d < 0:
        normal, d = -normal, -d
    return normal, d, max(float(eigval[0]), 0.0)


def plane_covariance(
    normal: np.ndarray, centroid: np.ndarray, scatter: np.ndarray, count: int, rss: float
) -> np.ndarray:
    """(3, 3) covariance of a least-squares plane in OrientedPlane3 local coordinates.

    Residual variance rss / (count - 3) times the inverse of the normal-equation
    matrix of r_i = n . p_i + d in the parameters (xi (2,), d), with n perturbed as
    n + B xi, B = `tangent_basis(n)`. With u = B^T centroid and M = B^T scatter B
    this inverse is [[M^-1, -M^-1 u], [-u^T M^-1, 1/count + u^T M^-1 u]].
    Units: rad^2 for the normal block, m^2 for d.
    """
    if count <= 3:
        raise GeometryError(f"plane covariance needs more than 3 points, got {count}")
    basis = tangent_basis(normal)
    m = basis.T @ scatter @ basis
    u = basis.T @ centroid
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    if not det > 0:
        raise GeometryError(f"plane covariance is singular: points are collinear (det {det})")
    m_inv = np.array([[m[1, 1], -m[0, 1]], [-m[1, 0], m[0, 0]]]) / det
    m_inv_u = m_inv @ u
    info_inv = np.empty((3, 3))
    info_inv[:2, :2] = m_inv
    info_inv[:2, 2] = -m_inv_u
    info_inv[2, :2] = -m_inv_u
    info_inv[2, 2] = 1.0 / count + u @ m_inv_u
    return (rss / (count - 3)) * info_inv


def correlated_depth_sigmas(
    sensor: DepthNoiseConfig, depth_m: float, area_m2: float, k: float = 1.0
) -> tuple[float, float]:
    """(tilt [rad], offset [m]) of a plane patch of `area_m2` at `depth_m` from the depth
    error that is correlated across the patch (calibration, quantisation), which a fit
    counting every pixel as independent leaves out: the patch is off by about k sigma(z)
    and tilted by that over its half-width."""
    sigma_z = k * sensor.sigma_m(max(float(depth_m), 0.0))
    half_width = max(0.5 * float(np.sqrt(max(float(area_m2), 0.0))), 0.01)
    return sigma_z / half_width, sigma_z


def patch_covariance(
    sensor: DepthNoiseConfig, normal: np.ndarray, centroid: np.ndarray, area_m2: float
) -> np.ndarray:
    """(3, 3) covariance in OrientedPlane3 local coordinates (camera frame) of a patch's
    correlated depth error (`correlated_depth_sigmas`): the tilt turns the patch about its
    centroid c, which moves the offset d = -n . c at the camera by -(B^T c) . tilt, B the
    normal's tangent basis; the offset error moves it along n."""
    c = np.asarray(centroid, dtype=np.float64)
    tilt, offset = correlated_depth_sigmas(sensor, float(c[2]), area_m2)
    J = np.eye(3)
    J[2, :2] = -(tangent_basis(np.asarray(normal, dtype=np.float64)).T @ c)
    return J @ np.diag([tilt**2, tilt**2, offset**2]) @ J.T
