"""Structural regularity between two plane landmarks (world frame) meeting at a real edge.

Orthogonality, error (1,) [~rad near 90 deg]:

    e = n_a . n_b                                   (= cos of the angle between normals)

Parallelism, error (2,) [~rad near 0 or 180 deg]:

    e = B(n_a)^T n_b                                (|e| = sin of the angle)

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

from planeslam.errors import ConfigError, GeometryError

from ._noise import distinct_keys, isotropic_noise


def orthogonal_planes_factor(key_a: int, key_b: int, sigma: float) -> gtsam.CustomFactor:
    """Planes `key_a` and `key_b` are perpendicular; sigma [rad] on n_a . n_b."""
    key_a, key_b = distinct_keys(key_a, key_b)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        plane_a = values.atOrientedPlane3(key_a)
        plane_b = values.atOrientedPlane3(key_b)
        if H is None:
            return np.array([plane_a.normal().dot(plane_b.normal())])
        na_H_a = np.zeros((2, 3), order="F")
        nb_H_b = np.zeros((2, 3), order="F")
        e_H_na = np.zeros((1, 2), order="F")
        e_H_nb = np.zeros((1, 2), order="F")
        e = plane_a.normal(na_H_a).dot(plane_b.normal(nb_H_b), e_H_na, e_H_nb)
        H[0] = e_H_na @ na_H_a
        H[1] = e_H_nb @ nb_H_b
        return np.array([e])

    return gtsam.CustomFactor(isotropic_noise(sigma, 1), [key_a, key_b], error)


def parallel_planes_factor(key_a: int, key_b: int, sigma: float) -> gtsam.CustomFactor:
    """Planes `key_a` and `key_b` are parallel (normals agreeing or opposite); sigma [rad]."""
    key_a, key_b = distinct_keys(key_a, key_b)

    def error(_: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        plane_a = values.atOrientedPlane3(key_a)
        plane_b = values.atOrientedPlane3(key_b)
        if H is None:
            return plane_a.normal().errorVector(plane_b.normal())
        na_H_a = np.zeros((2, 3), order="F")
        nb_H_b = np.zeros((2, 3), order="F")
        e_H_na = np.zeros((2, 2), order="F")
        e_H_nb = np.zeros((2, 2), order="F")
        e = plane_a.normal(na_H_a).errorVector(plane_b.normal(nb_H_b), e_H_na, e_H_nb)
        H[0] = e_H_na @ na_H_a
        H[1] = e_H_nb @ nb_H_b
        return e

    return gtsam.CustomFactor(isotropic_noise(sigma, 2), [key_a, key_b], error)


def structural_factor(
    key_a: int, key_b: int, measured_angle_rad: float, tolerance_rad: float, sigma: float
) -> gtsam.CustomFactor | None:
    """Orthogonality or parallelism factor when the measured angle is close to it, else None.

    measured_angle_rad: angle in [0, pi] between the two landmark normals (world
    frame, `planeslam.geometry.angle_between(n_a, n_b)`; not the dihedral angle
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
