"""Structural regularity between two plane landmarks (world frame) meeting at a real edge.

Orthogonality, error (1,) [~rad near 90 deg]:

    e = n_a . n_b                                   (= cos of the angle between normals)

Parallelism, error (2,) [~rad near 0 or 180 deg]:

    e = B(n_a)^T n_b                                (|e| = sin of the angle)

One plane seen as two landmarks, error (3,) [rad, rad, m]:

    e = OrientedPlane3.errorVector(a, b)            (normal difference in the tangent
                                                     plane of n_a, then d_b - d_a)

the tie that joins two landmarks the map found to be one plane segment.

B(n_a) is the (3, 2) Unit3 tangent basis at n_a (`Unit3.errorVector`), so e is n_b
projected onto the tangent plane of n_a. |e| vanishes both when the normals agree
and when they are opposite (two walls facing each other), and flipping n_b only
flips the sign of e, leaving the cost and the normal equations unchanged: no sign
has to be chosen, and an optimiser started within 90 deg of either stays in that
basin. Keys: two OrientedPlane3 landmarks; Jacobians are w.r.t. each plane's 3-D
local coordinates (the offset column is zero). The sigma is isotropic because B
is only defined up to a rotation about n_a.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from planeslam.core.errors import ConfigError, GeometryError

from ._noise import distinct_keys, isotropic_noise, robust_noise


def _normal_pair_factor(
    key_a: int, key_b: int, sigma: float, relation: str, dim: int
) -> gtsam.CustomFactor:
    """CustomFactor on two plane landmarks whose error is `Unit3.<relation>` of their
    normals ('dot': (1,), 'errorVector': (2,)), chained through `OrientedPlane3.normal`."""
    key_a, key_b = distinct_keys(key_a, key_b)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        plane_a = values.atOrientedPlane3(key_a)
        plane_b = values.atOrientedPlane3(key_b)
        if H is None:
            return np.atleast_1d(getattr(plane_a.normal(), relation)(plane_b.normal()))
        na_H_a = np.zeros((2, 3), order="F")
        nb_H_b = np.zeros((2, 3), order="F")
        e_H_na = np.zeros((dim, 2), order="F")
        e_H_nb = np.zeros((dim, 2), order="F")
        na, nb = plane_a.normal(na_H_a), plane_b.normal(nb_H_b)
        e = getattr(na, relation)(nb, e_H_na, e_H_nb)
        H[0] = e_H_na @ na_H_a
        H[1] = e_H_nb @ nb_H_b
        return np.atleast_1d(e)

    return gtsam.CustomFactor(isotropic_noise(sigma, dim), [key_a, key_b], error)


def orthogonal_planes_factor(key_a: int, key_b: int, sigma: float) -> gtsam.CustomFactor:
    """Planes `key_a` and `key_b` are perpendicular; sigma [rad] on n_a . n_b."""
    return _normal_pair_factor(key_a, key_b, sigma, "dot", 1)


def parallel_planes_factor(key_a: int, key_b: int, sigma: float) -> gtsam.CustomFactor:
    """Planes `key_a` and `key_b` are parallel (normals agreeing or opposite); sigma [rad]."""
    return _normal_pair_factor(key_a, key_b, sigma, "errorVector", 2)


def same_plane_factor(
    key_a: int, key_b: int, sigma_rad: float, sigma_m: float, loss: str | None = "huber"
) -> gtsam.CustomFactor:
    """Plane landmarks `key_a` and `key_b` are one plane (normals agreeing, same offset):
    sigmas of each normal component [rad] and of the offset [m]; `loss` 'huber' or
    'cauchy' makes it robust (a wrong tie then gives way), None keeps it Gaussian."""
    key_a, key_b = distinct_keys(key_a, key_b)
    for name, value in (("sigma_rad", sigma_rad), ("sigma_m", sigma_m)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ConfigError(f"same_plane_factor {name}={value!r}: expected a finite number > 0")
    gaussian = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([sigma_rad, sigma_rad, sigma_m], dtype=np.float64)
    )
    noise = gaussian if loss is None else robust_noise(gaussian, loss, None)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        plane_a = values.atOrientedPlane3(key_a)
        plane_b = values.atOrientedPlane3(key_b)
        if H is None:
            return np.asarray(plane_a.errorVector(plane_b))
        H_a = np.zeros((3, 3), order="F")
        H_b = np.zeros((3, 3), order="F")
        e = plane_a.errorVector(plane_b, H_a, H_b)
        H[0], H[1] = H_a, H_b
        return np.asarray(e)

    return gtsam.CustomFactor(noise, [key_a, key_b], error)


def structural_factor(
    key_a: int, key_b: int, measured_angle_rad: float, tolerance_rad: float, sigma: float
) -> gtsam.CustomFactor | None:
    """Orthogonality or parallelism factor when the measured angle is close to it, else None.

    measured_angle_rad: angle in [0, pi] between the two landmark normals (world
    frame, `planeslam.core.geometry.angle_between(n_a, n_b)`; not the dihedral angle
    between plane regions, which ignores the normals' signs). Orthogonal when
    |angle - pi/2| < tolerance_rad; parallel when angle < tolerance_rad (normals
    agree) or angle > pi - tolerance_rad (normals opposite; the parallel error
    needs no sign, see the module docstring). tolerance_rad in (0, pi/4); sigma [rad].
    """
    angle = float(measured_angle_rad)
    if not (math.isfinite(angle) and -1e-9 <= angle <= math.pi + 1e-9):
        raise GeometryError(f"angle between normals {measured_angle_rad!r}: expected [0, pi] rad")
    tol = float(tolerance_rad)
    if not (math.isfinite(tol) and 0.0 < tol < math.pi / 4):
        raise ConfigError(f"structural tolerance {tolerance_rad!r} rad: expected (0, pi/4)")
    if abs(angle - math.pi / 2) < tol:
        return orthogonal_planes_factor(key_a, key_b, sigma)
    if angle < tol or angle > math.pi - tol:
        return parallel_planes_factor(key_a, key_b, sigma)
    return None
