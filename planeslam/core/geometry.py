"""Rigid-body and plane geometry shared by every stage.

Poses are 4x4 homogeneous matrices named by their frames: `T_world_cam`
maps camera-frame points to the world frame. Planes are (n, d) with
n . x + d = 0 and |n| = 1.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.core.errors import GeometryError, PlaneSlamError


def pose_from_quat(t_xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(3,) translation [m] + (4,) quaternion xyzw -> (4, 4) pose.

    Batched: (N, 3), (N, 4) -> (N, 4, 4)."""
    t_xyz = np.asarray(t_xyz, dtype=np.float64)
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    batch = t_xyz.ndim == 2
    t2, q2 = np.atleast_2d(t_xyz), np.atleast_2d(quat_xyzw)
    T = np.tile(np.eye(4), (len(t2), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(q2).as_matrix()
    T[:, :3, 3] = t2
    return T if batch else T[0]


def quat_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) or (N, 4, 4) pose -> translation (.., 3) and quaternion xyzw (.., 4), qw >= 0."""
    T = np.asarray(T, dtype=np.float64)
    q = Rotation.from_matrix(T[..., :3, :3]).as_quat()
    q = np.where(q[..., 3:4] < 0, -q, q)
    return T[..., :3, 3].copy(), q


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4, 4) or (N, 4, 4), without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def as_pose(T: Any, name: str, error: type[PlaneSlamError] = GeometryError) -> np.ndarray:
    """T (a (4, 4) array, or a gtsam.Pose3 or anything else with a `matrix()` method) as a
    (4, 4) float64 array, or `error` naming `name` when it has another shape or non-finite
    values (the one check every module applies to a pose argument). gtsam is not imported."""
    if not isinstance(T, np.ndarray) and callable(getattr(T, "matrix", None)):
        T = T.matrix()  # gtsam.Pose3 (duck-typed: core does not import gtsam)
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise error(
            f"{name} is a {type(T).__name__}, expected a (4, 4) pose array or a gtsam.Pose3"
        ) from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise error(f"{name} has shape {T.shape} or non-finite values, expected (4, 4)")
    return T


ROTATION_TOLERANCE = 1e-4
"""Largest |R R^T - I| entry a pose argument may have; within it the rotation is projected
back onto SO(3). TUM's 4-decimal quaternions give about 5e-5."""


def rigid_pose(
    T: Any,
    name: str,
    error: type[PlaneSlamError] = GeometryError,
    tolerance: float = ROTATION_TOLERANCE,
) -> np.ndarray:
    """T as `as_pose` takes it -> (4, 4) float64 rigid transform, its rotation re-orthonormalised
    (`orthonormalize_pose`); `error` naming `name` when the rotation block is more than
    `tolerance` from a rotation (|R R^T - I| entries, det R > 0) or the last row is not
    (0, 0, 0, 1)."""
    T = as_pose(T, name, error)
    R = T[:3, :3]
    off = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if off > tolerance or np.linalg.det(R) <= 0:
        raise error(
            f"{name}'s rotation block is {off:.1e} from orthonormal (det {np.linalg.det(R):.3f}), "
            f"expected a rotation within {tolerance:g}"
        )
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-12):
        raise error(f"{name}'s last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    return orthonormalize_pose(T)


def orthonormalize_pose(T: np.ndarray) -> np.ndarray:
    """(4, 4) or (N, 4, 4) pose with its rotation projected onto SO(3) (nearest rotation by
    SVD): chained products and solvers drift off orthonormality by ~1e-12 per step."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    D = np.ones(T.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    T[..., :3, :3] = U @ (D[..., :, None] * Vt)
    return T


def transform_points(T_b_a: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame a to frame b with the (4, 4) pose T_b_a."""
    return points_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]


def transform_plane(T_b_a: np.ndarray, n_a: np.ndarray, d_a: float) -> tuple[np.ndarray, float]:
    """Express plane (n_a, d_a) of frame a in frame b: n_b = R n_a, d_b = d_a - n_b . t."""
    n_b = T_b_a[:3, :3] @ n_a
    return n_b, float(d_a - n_b @ T_b_a[:3, 3])


def orient_plane_toward(n: np.ndarray, d: float, viewpoint: np.ndarray) -> tuple[np.ndarray, float]:
    """Flip (n, d) so the viewpoint lies on the positive side (n . viewpoint + d > 0).

    In the camera frame the viewpoint is the origin, so this makes d > 0.
    """
    if float(n @ viewpoint + d) < 0:
        return -n, -d
    return n, d


def rotation_angle(R: np.ndarray) -> float:
    """Angle [rad] of a (3, 3) rotation, robust near 0 and pi (atan2 of its sine and
    cosine; arccos of the trace alone resolves no better than about 2e-8 rad near 0)."""
    sin = 0.5 * math.hypot(R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1])
    return math.atan2(sin, 0.5 * (float(np.trace(R)) - 1.0))


def pose_distances(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translations [m] and rotation angles [deg] between poses T_a (..., 4, 4) and T_b
    (..., 4, 4), broadcast (one T_b against K poses T_a, or K pairs): shape (...)."""
    metres = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    cos = (np.einsum("...ij,...ij->...", T_a[..., :3, :3], T_b[..., :3, :3]) - 1.0) / 2.0
    return metres, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))  # trace(R_a^T R_b)


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [rad] between two vectors, robust near 0 and pi."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b))


def intersect_three_planes(
    normals: np.ndarray, offsets: np.ndarray, min_sin: float = 0.2
) -> np.ndarray:
    """Point common to three planes, (3, 3) normals and (3,) offsets -> (3,).

    Raises GeometryError when the triple is ill-conditioned: the absolute
    determinant of the unit normals (the volume they span, 1 for orthogonal
    planes) is below `min_sin`.
    """
    det = float(np.linalg.det(normals))
    if abs(det) < min_sin:
        raise GeometryError(f"planes nearly share a direction (|det| = {abs(det):.3f} < {min_sin})")
    return np.linalg.solve(normals, -np.asarray(offsets, dtype=np.float64))


def plane_line(
    n1: np.ndarray, d1: float, n2: np.ndarray, d2: float, min_sin: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Intersection line of two planes: (point (3,), unit direction (3,)).

    The point is the one closest to the origin. Raises GeometryError when the
    planes are nearly parallel (sin of their angle below `min_sin`).
    """
    direction = np.cross(n1, n2)
    s = float(np.linalg.norm(direction))
    if s < min_sin:
        raise GeometryError(f"planes are nearly parallel (sin = {s:.3f} < {min_sin})")
    direction = direction / s
    A = np.stack([n1, n2, direction])
    point = np.linalg.solve(A, np.array([-d1, -d2, 0.0]))
    return point, direction


def unit(v: np.ndarray) -> np.ndarray:
    """v / |v| for a non-zero (3,) vector."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def tangent_basis(normal: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the tangent plane of the unit sphere at `normal` (3,).

    Same construction as GTSAM `Unit3::basis()`: b1 = normalize(n x a) with `a` the
    coordinate axis least aligned with n (ties to the lower axis), b2 = n x b1.
    """
    nx, ny, nz = (float(v) for v in normal)
    mx, my, mz = abs(nx), abs(ny), abs(nz)
    # n x a for a = e_x, e_y, e_z
    if mx <= my and mx <= mz:
        b1 = (0.0, nz, -ny)
    elif my <= mx and my <= mz:
        b1 = (-nz, 0.0, nx)
    else:
        b1 = (ny, -nx, 0.0)
    inv = 1.0 / math.sqrt(b1[0] ** 2 + b1[1] ** 2 + b1[2] ** 2)
    b1x, b1y, b1z = b1[0] * inv, b1[1] * inv, b1[2] * inv
    b2 = (ny * b1z - nz * b1y, nz * b1x - nx * b1z, nx * b1y - ny * b1x)
    return np.array([[b1x, b2[0]], [b1y, b2[1]], [b1z, b2[2]]])


def plane_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal in-plane axes u, v (u x v = n) for the unit normal n (3,);
    the rows of `tangent_basis(n)`."""
    return tangent_basis(n).T


def pose_adjoint(T: np.ndarray) -> np.ndarray:
    """(6, 6) adjoint of the (4, 4) pose T in gtsam's Pose3 tangent order (rotation first,
    then translation): [[R, 0], [t^ R, R]], so that T Exp(xi) = Exp(Ad_T xi) T."""
    R, t = T[:3, :3], T[:3, 3]
    adjoint = np.zeros((6, 6))
    adjoint[:3, :3] = adjoint[3:, 3:] = R
    adjoint[3:, :3] = skew(t) @ R
    return adjoint


def compose_covariance(cov_a_b: np.ndarray, T_b_c: np.ndarray, cov_b_c: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of T_a_c = T_a_b T_b_c from independent (6, 6) covariances of
    T_a_b and T_b_c, each in its pose's own tangent space (gtsam's right perturbation,
    rotation first): Ad(T_b_c^-1) cov_a_b Ad(T_b_c^-1)^T + cov_b_c."""
    adjoint = pose_adjoint(invert_pose(T_b_c))
    return adjoint @ cov_a_b @ adjoint.T + cov_b_c


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for (..., 3) arrays, broadcast: `np.cross`'s result bit for bit (the same
    products and differences) without its axis handling, which makes np.cross take
    about 15 us on small arrays; tracking calls it thousands of times per second."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


def skew(a: np.ndarray) -> np.ndarray:
    """(3, 3) cross-product matrix of a (3,): skew(a) @ b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def axis_angle_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by `angle_rad` about the unit `axis` (3,) (Rodrigues)."""
    K = skew(axis)
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest (3, 3) rotation taking unit vector a (3,) to unit vector b (3,); for
    opposite vectors, a half turn about an axis perpendicular to a."""
    c = float(a @ b)
    if c < -1.0 + 1e-12:
        return axis_angle_rotation(plane_basis(unit(a))[0], np.pi)
    K = skew(cross(a, b))
    return np.eye(3) + K + (K @ K) / (1.0 + c)


def point_segment_distance(point: np.ndarray, segment: np.ndarray) -> float:
    """Distance [m] from a (3,) point to the (2, 3) segment (a degenerate one is a point)."""
    a, b = segment
    ab = b - a
    denom = float(ab @ ab)
    s = 0.0 if denom == 0 else float(np.clip((point - a) @ ab / denom, 0.0, 1.0))
    return float(np.linalg.norm(a + s * ab - point))


def convex_hull_2d(points_uv: np.ndarray) -> np.ndarray:
    """Counter-clockwise hull vertices (H, 2) of (K, 2) points, rows of `points_uv`; (0, 2)
    when they span no area (fewer than 3, collinear or coincident, to float32 precision).
    OpenCV's hull decides on float32 coordinates about the first point (a few microseconds
    where Qhull's set-up takes about a hundred): a point within about 1e-7 of the points'
    extent of the hull's edge may be a vertex or not."""
    import cv2  # here, not at the top: the backend worker process imports no OpenCV

    points = np.asarray(points_uv, dtype=np.float64)
    if len(points) < 3:
        return np.zeros((0, 2))
    local = (points - points[0]).astype(np.float32)
    index = cv2.convexHull(local, clockwise=False, returnPoints=False)[:, 0]
    extent = float(np.abs(local).max())
    if len(index) < 3 or cv2.contourArea(local[index]) <= 1e-6 * extent * extent:
        return np.zeros((0, 2))
    return points[index]


def polygon_area(polygon_uv: np.ndarray) -> float:
    """Shoelace area of a simple (K, 2) polygon (0 for K < 3)."""
    if len(polygon_uv) < 3:
        return 0.0
    x, y = polygon_uv[:, 0], polygon_uv[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def clip_convex_polygon(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: convex (K, 2) subject clipped by a counter-clockwise convex (H, 2).

    Each clip edge is one vectorised pass over the subject's edges; every
    subject edge emits [crossing point if it crosses, end point if inside].
    """
    out = subject
    for c1, c2 in zip(clip, np.roll(clip, -1, axis=0), strict=True):
        if len(out) == 0:
            break
        edge = c2 - c1
        side = edge[0] * (out[:, 1] - c1[1]) - edge[1] * (out[:, 0] - c1[0])  # >= 0: inside
        start, end = out, np.roll(out, -1, axis=0)
        s_side, e_side = side, np.roll(side, -1)
        s_in, e_in = s_side >= 0, e_side >= 0
        crosses = s_in != e_in
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(crosses, s_side / (s_side - e_side), 0.0)
        crossing = start + frac[:, None] * (end - start)
        slots = np.stack([crossing, end], axis=1)  # (K, 2 slots, 2)
        keep = np.stack([crosses, e_in], axis=1)
        out = slots[keep]
    return out


def convex_polygon_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two counter-clockwise convex polygons (K, 2), (L, 2) [m]: 0 when
    they overlap or touch, else the smallest distance between their boundaries."""
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    if not (_outside_an_edge(a, b) or _outside_an_edge(b, a)):
        return 0.0
    return min(_points_to_ring(a, b), _points_to_ring(b, a))


def _outside_an_edge(points: np.ndarray, ring: np.ndarray) -> bool:
    """Whether all the (P, 2) points lie strictly outside one edge line of the
    counter-clockwise convex (R, 2) ring. Two convex polygons are disjoint exactly when
    this holds one way or the other (the separating axis theorem)."""
    start = ring
    edge = np.roll(ring, -1, axis=0) - start  # (R, 2)
    rel = points[None, :, :] - start[:, None, :]  # (R, P, 2)
    side = edge[:, None, 0] * rel[..., 1] - edge[:, None, 1] * rel[..., 0]  # >= 0: inside
    return bool((side < 0).all(axis=1).any())


def _points_to_ring(points: np.ndarray, ring: np.ndarray) -> float:
    """Smallest distance from the (P, 2) points to the edges of the closed (R, 2) ring."""
    start, end = ring, np.roll(ring, -1, axis=0)
    edge = end - start  # (R, 2)
    rel = points[:, None, :] - start[None, :, :]  # (P, R, 2)
    length2 = np.maximum(np.einsum("rk,rk->r", edge, edge), 1e-24)
    s = np.clip(np.einsum("prk,rk->pr", rel, edge) / length2, 0.0, 1.0)
    closest = start[None] + s[..., None] * edge[None]
    return float(np.sqrt(np.min(np.sum((points[:, None, :] - closest) ** 2, axis=-1))))
