"""Closed-form registration from plane and point correspondences, and ICP refinement.

The paper's map merging (Section 4.4) estimates the motion between two
frames from plane-to-plane correspondences in closed form (no motion model,
no iterations, Section 2.2) and refines it with ICP. This module gives

- `pose_from_planes`: rotation from normals (weighted Wahba/Kabsch by SVD),
  translation from offsets (linear least squares);
- `pose_from_points`: Kabsch/Umeyama without scale, e.g. on corner points;
- `pose_from_planes_and_points`: both kinds of correspondence in one
  covariance-weighted closed-form solve (the paper leaves the combination
  open, Section 5);
- `refine_icp`: Open3D point-to-plane (or point-to-point) ICP.

Conventions: planes (n, d) with n . x + d = 0, |n| = 1. Every solver returns
`T_dst_src` (4, 4) with x_dst = R x_src + t, so a plane maps as
n_dst = R n_src, d_dst = d_src - n_dst . t (`geometry.transform_plane`).

Observability. Each solver reports, for rotation and for translation, the
smallest eigenvalue of the information matrix divided by its trace (0 when
a direction is not constrained at all, 1/3 for perfectly spread data) and
lists the unobservable directions as unit vectors in the dst frame. Those
directions take their value from the optional prior pose (identity when
none is given), so the result never contains NaN and a caller can fill the
gap from odometry. The noise amplification along the weakest direction is
about 1 / sqrt(N * observability).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

from planeslam.core.errors import GeometryError
from planeslam.core.geometry import (
    as_pose,
    axis_angle_rotation,
    cross,
    rotation_between,
    skew,
)

logger = logging.getLogger(__name__)

DEFAULT_MIN_OBSERVABILITY = 1e-3
"""Directions whose information / trace ratio is below this are unobservable."""


class RegistrationStatus(enum.Enum):
    """Outcome of a closed-form registration."""

    OK = "ok"
    """Rotation and translation fully observable."""
    DEGENERATE_TRANSLATION = "degenerate_translation"
    """Rotation observable; translation lacks 1-3 directions (taken from the prior)."""
    DEGENERATE_ROTATION = "degenerate_rotation"
    """Rotation lacks an axis (and translation usually directions too); taken from the prior."""
    TOO_FEW = "too_few"
    """No usable correspondence (empty input or all weights zero); T is the prior."""


@dataclass(frozen=True)
class RegistrationResult:
    """Closed-form pose estimate with its observability and residuals."""

    T: np.ndarray
    """(4, 4) T_dst_src: maps src-frame points to the dst frame."""
    status: RegistrationStatus
    rotation_observability: float
    """Smallest eigenvalue / trace of the rotation information matrix, in [0, 1/3]."""
    translation_observability: float
    """Smallest eigenvalue / trace of the translation information matrix, in [0, 1/3]."""
    unobservable_rotation_axes: np.ndarray = field(repr=False)
    """(K, 3) unit rotation axes, dst frame, about which rotation came from the prior."""
    unobservable_translation_dirs: np.ndarray = field(repr=False)
    """(K, 3) unit directions, dst frame, along which translation came from the prior."""
    plane_angle_residual_rad: np.ndarray = field(repr=False)
    """(N,) angle between R n_src and n_dst per plane correspondence [rad]."""
    plane_offset_residual_m: np.ndarray = field(repr=False)
    """(N,) transformed src offset minus dst offset per plane correspondence [m]."""
    point_residual_m: np.ndarray = field(repr=False)
    """(P,) distance |R p_src + t - p_dst| per point correspondence [m]."""

    @property
    def ok(self) -> bool:
        """True when the whole pose was observable."""
        return self.status is RegistrationStatus.OK


class IcpResult(NamedTuple):
    """ICP outcome; unpacks as (T, fitness, inlier_rmse)."""

    T: np.ndarray
    """(4, 4) refined T_target_source."""
    fitness: float
    """Fraction of (down-sampled) source points with a target point within max distance."""
    inlier_rmse: float
    """RMSE of the inlier correspondences [m]."""


# ----------------------------------------------------------------------------- validation


def _as_vectors(name: str, a: np.ndarray, n: int | None = None) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
        want = f"({n}, 3)" if n is not None else "(N, 3)"
        raise GeometryError(f"{name} has shape {a.shape}, expected {want}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} contains non-finite values")
    return a


def _as_scalars(name: str, a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n,):
        raise GeometryError(f"{name} has shape {a.shape}, expected ({n},)")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} contains non-finite values")
    return a


def _as_weights(name: str, w: np.ndarray | None, n: int) -> np.ndarray:
    if w is None:
        return np.ones(n)
    w = _as_scalars(name, w, n)
    if np.any(w < 0):
        raise GeometryError(f"{name} has negative entries; expected weights >= 0")
    return w


def _unit_normals(name: str, n: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(n, axis=1)
    if np.any(norm < 1e-9):
        raise GeometryError(f"{name} contains a zero-length normal; expected unit normals")
    return n / norm[:, None]


def _as_prior(T_prior: np.ndarray | None) -> np.ndarray:
    return np.eye(4) if T_prior is None else as_pose(T_prior, "T_prior")


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise GeometryError(f"{name} = {value}, expected a positive finite number")
    return value


# ----------------------------------------------------------------------------- rotation solve


def _wahba(H: np.ndarray, R_prior: np.ndarray, min_obs: float):
    """Rotation maximising trace(R^T H) for H = sum w dst src^T, with observability.

    For noise-free data the singular values s1 >= s2 >= s3 of H are the
    eigenvalues of the weighted src scatter S, and the rotation information
    matrix is trace(S) I - S, with eigenvalues s2+s3 (about the dominant
    direction u1), s1+s3, s1+s2. Only the axis u1 can become unobservable
    (all data parallel), or all three (no spread at all).
    """
    U, s, Vt = np.linalg.svd(H)
    total = float(s.sum())
    if total <= 1e-300:
        return R_prior.copy(), 0.0, np.eye(3)
    obs = float((s[1] + s[2]) / (2.0 * total))
    if obs >= min_obs:
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
        return U @ D @ Vt, obs, np.zeros((0, 3))
    # All data along one direction: a_src -> a_dst fixed, the angle about it from the prior.
    a_src, a_dst = Vt[0], U[:, 0]
    R_min = rotation_between(a_src, a_dst)
    M = R_prior.T @ R_min
    # trace(M Rot(a, th)) = cos th (tr M - a'Ma) + sin th tr(M [a]x) + a'Ma
    theta = float(np.arctan2(np.trace(M @ skew(a_src)), np.trace(M) - a_src @ M @ a_src))
    return R_min @ axis_angle_rotation(a_src, theta), obs, a_dst[None, :]


def _solve_translation(A: np.ndarray, b: np.ndarray, t_prior: np.ndarray, min_obs: float):
    """Least-squares t from normal equations A t = b; weak eigen-directions from the prior."""
    lam, V = np.linalg.eigh(A)
    total = float(lam.sum())
    ratio = lam / total if total > 1e-300 else np.zeros(3)
    good = ratio >= min_obs
    Vg, Vb = V[:, good], V[:, ~good]
    t = Vg @ ((Vg.T @ b) / lam[good]) + Vb @ (Vb.T @ t_prior)
    return t, float(max(ratio.min(), 0.0)), Vb.T.copy()


# ----------------------------------------------------------------------------- core solver


def _residuals(T, n_src, d_src, n_dst, d_dst, p_src, p_dst) -> dict[str, np.ndarray]:
    """Per-correspondence residuals of T_dst_src, as RegistrationResult fields."""
    R, t = T[:3, :3], T[:3, 3]
    m = n_src @ R.T
    sine = np.linalg.norm(cross(m, n_dst), axis=1)
    return {
        "plane_angle_residual_rad": np.arctan2(sine, np.einsum("ij,ij->i", m, n_dst)),
        "plane_offset_residual_m": (d_src - m @ t) - d_dst,
        "point_residual_m": np.linalg.norm(p_src @ R.T + t - p_dst, axis=1),
    }


def _solve(
    n_src: np.ndarray,
    d_src: np.ndarray,
    n_dst: np.ndarray,
    d_dst: np.ndarray,
    w_normal: np.ndarray,
    w_offset: np.ndarray,
    p_src: np.ndarray,
    p_dst: np.ndarray,
    w_point: np.ndarray,
    T_prior: np.ndarray,
    min_obs: float,
) -> RegistrationResult:
    R_prior, t_prior = T_prior[:3, :3], T_prior[:3, 3]
    if w_normal.sum() + w_offset.sum() + w_point.sum() <= 0:
        logger.debug("registration: no usable correspondence, returning the prior")
        return RegistrationResult(
            T=T_prior.copy(),
            status=RegistrationStatus.TOO_FEW,
            rotation_observability=0.0,
            translation_observability=0.0,
            unobservable_rotation_axes=np.eye(3),
            unobservable_translation_dirs=np.eye(3),
            **_residuals(T_prior, n_src, d_src, n_dst, d_dst, p_src, p_dst),
        )

    # Rotation: one weighted Wahba problem over normals and centred points.
    H = np.einsum("i,ij,ik->jk", w_normal, n_dst, n_src)
    wp = float(w_point.sum())
    if wp > 0:
        c_src = w_point @ p_src / wp
        c_dst = w_point @ p_dst / wp
        H += np.einsum("i,ij,ik->jk", w_point, p_dst - c_dst, p_src - c_src)
    R, rot_obs, rot_axes = _wahba(H, R_prior, min_obs)

    # Translation: offsets give m . t = d_src - d_dst with m = R n_src; points give
    # t = p_dst - R p_src. Normal equations of the weighted sum of both.
    m = n_src @ R.T
    A = np.einsum("i,ij,ik->jk", w_offset, m, m) + wp * np.eye(3)
    b = (w_offset * (d_src - d_dst)) @ m
    if wp > 0:
        b += w_point @ (p_dst - p_src @ R.T)
    t, trans_obs, trans_dirs = _solve_translation(A, b, t_prior, min_obs)

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    if len(rot_axes):
        status = RegistrationStatus.DEGENERATE_ROTATION
    elif len(trans_dirs):
        status = RegistrationStatus.DEGENERATE_TRANSLATION
    else:
        status = RegistrationStatus.OK
    if status is not RegistrationStatus.OK:
        logger.debug(
            "registration %s: rotation obs %.2e, translation obs %.2e",
            status.value,
            rot_obs,
            trans_obs,
        )
    return RegistrationResult(
        T=T,
        status=status,
        rotation_observability=rot_obs,
        translation_observability=trans_obs,
        unobservable_rotation_axes=rot_axes,
        unobservable_translation_dirs=trans_dirs,
        **_residuals(T, n_src, d_src, n_dst, d_dst, p_src, p_dst),
    )


_NO_POINTS = np.zeros((0, 3))


def _check_planes(n_src, d_src, n_dst, d_dst):
    n_src = _unit_normals("n_src", _as_vectors("n_src", n_src))
    N = len(n_src)
    n_dst = _unit_normals("n_dst", _as_vectors("n_dst", n_dst, N))
    return n_src, _as_scalars("d_src", d_src, N), n_dst, _as_scalars("d_dst", d_dst, N)


def _check_points(src, dst):
    src = _as_vectors("src points", src)
    return src, _as_vectors("dst points", dst, len(src))


# ----------------------------------------------------------------------------- public API


def pose_from_planes(
    n_src: np.ndarray,
    d_src: np.ndarray,
    n_dst: np.ndarray,
    d_dst: np.ndarray,
    weights: np.ndarray | None = None,
    T_prior: np.ndarray | None = None,
    min_observability: float = DEFAULT_MIN_OBSERVABILITY,
) -> RegistrationResult:
    """T_dst_src from N plane correspondences (src plane i is dst plane i), closed form.

    n_src, n_dst: (N, 3) unit normals; d_src, d_dst: (N,) offsets [m];
    weights: (N,) >= 0 (e.g. inverse variances), default ones. Rotation:
    argmax_R sum w_i n_dst_i . R n_src_i by SVD (needs 2 non-parallel normals).
    Translation: least squares of (R n_src_i) . t = d_src_i - d_dst_i (needs 3
    linearly independent normals). Unobservable rotation axes / translation
    directions take their values from T_prior ((4, 4) T_dst_src guess,
    default identity) and are listed in the result.
    """
    n_src, d_src, n_dst, d_dst = _check_planes(n_src, d_src, n_dst, d_dst)
    w = _as_weights("weights", weights, len(n_src))
    return _solve(
        n_src,
        d_src,
        n_dst,
        d_dst,
        w,
        w,
        _NO_POINTS,
        _NO_POINTS,
        np.zeros(0),
        _as_prior(T_prior),
        float(min_observability),
    )


def pose_from_points(
    src: np.ndarray,
    dst: np.ndarray,
    weights: np.ndarray | None = None,
    T_prior: np.ndarray | None = None,
    min_observability: float = DEFAULT_MIN_OBSERVABILITY,
) -> RegistrationResult:
    """T_dst_src from N point correspondences, (N, 3) each [m]: weighted Kabsch, no scale.

    Rotation needs 3 non-collinear points; for collinear points the rotation
    about the line comes from T_prior (default identity), status
    DEGENERATE_ROTATION. The translation is always observable (N >= 1).
    """
    src, dst = _check_points(src, dst)
    w = _as_weights("weights", weights, len(src))
    zn, zd = np.zeros((0, 3)), np.zeros(0)
    return _solve(zn, zd, zn, zd, zd, zd, src, dst, w, _as_prior(T_prior), float(min_observability))


def pose_from_planes_and_points(
    n_src: np.ndarray,
    d_src: np.ndarray,
    n_dst: np.ndarray,
    d_dst: np.ndarray,
    points_src: np.ndarray,
    points_dst: np.ndarray,
    sigma_angle_rad: float = np.radians(1.0),
    sigma_offset_m: float = 0.01,
    sigma_point_m: float = 0.02,
    plane_weights: np.ndarray | None = None,
    point_weights: np.ndarray | None = None,
    T_prior: np.ndarray | None = None,
    min_observability: float = DEFAULT_MIN_OBSERVABILITY,
) -> RegistrationResult:
    """T_dst_src from plane and point (e.g. corner) correspondences together, closed form.

    Planes as in `pose_from_planes` ((N, 3), (N,)), points (P, 3) [m]. The
    joint cost is

        E(R, t) = sum_i w_i |R n_src_i - n_dst_i|^2 / sigma_angle^2
                + sum_i w_i (d_src_i - (R n_src_i) . t - d_dst_i)^2 / sigma_offset^2
                + sum_j v_j |R p_src_j + t - p_dst_j|^2 / sigma_point^2

    (w = plane_weights, v = point_weights, default ones). It is solved in
    two closed-form steps, exact for noise-free data and the usual
    decoupling otherwise: (1) R by one SVD of the weighted Wahba problem
    over normals and weighted-centred points, i.e. the translation-free
    parts of the first and third terms; (2) t by one 3x3 linear solve of the
    second and third terms given R. Points make translation observable where
    planes leave it free (a corridor: floor + two parallel walls), normals
    make rotation observable where points are collinear.
    """
    n_src, d_src, n_dst, d_dst = _check_planes(n_src, d_src, n_dst, d_dst)
    p_src, p_dst = _check_points(points_src, points_dst)
    w = _as_weights("plane_weights", plane_weights, len(n_src))
    v = _as_weights("point_weights", point_weights, len(p_src))
    s_a = _positive("sigma_angle_rad", sigma_angle_rad)
    s_d = _positive("sigma_offset_m", sigma_offset_m)
    s_p = _positive("sigma_point_m", sigma_point_m)
    return _solve(
        n_src,
        d_src,
        n_dst,
        d_dst,
        w / s_a**2,
        w / s_d**2,
        p_src,
        p_dst,
        v / s_p**2,
        _as_prior(T_prior),
        float(min_observability),
    )


def refine_icp(
    source_points: np.ndarray,
    target_points: np.ndarray,
    T_init: np.ndarray,
    max_distance_m: float,
    voxel_m: float,
    method: Literal["point_to_plane", "point_to_point"] = "point_to_plane",
    max_iterations: int = 30,
    normal_radius_m: float | None = None,
) -> IcpResult:
    """Refine T_target_source (4, 4) by Open3D ICP on (N, 3) / (M, 3) clouds [m].

    Both clouds are voxel-down-sampled with `voxel_m` (<= 0: not at all);
    point-to-plane uses target normals estimated within `normal_radius_m`
    (default 2 voxels, or max_distance_m without down-sampling; at most 30
    neighbours): keep it above the cloud's point spacing. `max_distance_m`
    is the correspondence gate.
    Returns the refined pose, the inlier fraction and the inlier RMSE [m].
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = _as_vectors("source_points", source_points)
    tgt = _as_vectors("target_points", target_points)
    T_init = as_pose(T_init, "T_init")
    max_distance_m = _positive("max_distance_m", max_distance_m)
    if method not in ("point_to_plane", "point_to_point"):
        raise GeometryError(
            f"ICP method {method!r} unknown; expected point_to_plane or point_to_point"
        )
    if len(src) < 3 or len(tgt) < 3:
        raise GeometryError(f"ICP needs >= 3 points per cloud, got {len(src)} and {len(tgt)}")

    def cloud(points: np.ndarray):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        return pc.voxel_down_sample(voxel_m) if voxel_m > 0 else pc

    pc_src, pc_tgt = cloud(src), cloud(tgt)
    if method == "point_to_plane":
        radius = normal_radius_m or (2.0 * voxel_m if voxel_m > 0 else max_distance_m)
        pc_tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        estimation: reg.TransformationEstimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint()
    result = reg.registration_icp(
        pc_src,
        pc_tgt,
        max_distance_m,
        T_init,
        estimation,
        reg.ICPConvergenceCriteria(max_iteration=int(max_iterations)),
    )
    T = np.array(result.transformation, dtype=np.float64)
    logger.debug(
        "ICP %s: %d -> %d points, fitness %.3f, rmse %.4f m",
        method,
        len(pc_src.points),
        len(pc_tgt.points),
        result.fitness,
        result.inlier_rmse,
    )
    return IcpResult(T=T, fitness=float(result.fitness), inlier_rmse=float(result.inlier_rmse))
