"""Association gates from the caller's pose uncertainty.

A plane or corner observed in the camera frame is moved into the world by the predicted
pose T_world_cam; an error xi = (omega [rad], v [m]) of that pose, in gtsam's Pose3
tangent space (right perturbation T Exp(xi), rotation first, as
`gtsam.Marginals.marginalCovariance` orders a Pose3's covariance), moves it by, to first
order:

    normal  n_world:  R (omega x n_cam)                      angle |omega x n_cam|
    offset  d_world:  -(n_cam x R^T t) . omega - n_cam . v   (t: the camera's position)
    corner  p_world:  R (omega x p_cam + v)

The offset's rotation term is the lever arm of the world origin: d is measured there.
`pose_gate_sigmas` propagates a (6, 6) covariance through these Jacobians; `PlaneLandmarks`
adds k of the resulting sigmas to its fixed gates in quadrature.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from planeslam.core.errors import AssociationError
from planeslam.core.geometry import as_pose


@dataclass(frozen=True)
class PoseGateSigmas:
    """One standard deviation of each observation moved to the world by an uncertain pose."""

    angle_rad: np.ndarray
    """(N,) per plane: of its normal's direction, in the worst direction [rad]."""
    offset_m: np.ndarray
    """(N,) per plane: of its world offset d [m]."""
    corner_m: np.ndarray
    """(K,) per corner: of its world position, in the worst direction [m]."""


def pose_covariance_matrix(pose_covariance: Any, pose_key: int | None = None) -> np.ndarray:
    """A (6, 6) Pose3 covariance (rotation [rad] first, then translation [m]) from a matrix,
    or from a `gtsam.Marginals` and the key of the pose (`pose_key`); AssociationError when
    it is not finite, symmetric and positive semi-definite."""
    if hasattr(pose_covariance, "marginalCovariance"):
        if pose_key is None:
            raise AssociationError(
                "pose_covariance is a gtsam.Marginals: give pose_key, the key of the pose "
                "whose marginal covariance gates the association"
            )
        try:
            pose_covariance = pose_covariance.marginalCovariance(pose_key)
        except (RuntimeError, IndexError, KeyError) as exc:  # gtsam: the key is not there
            message = " ".join(str(exc).split())[:120]
            raise AssociationError(
                f"no marginal covariance for key {pose_key}: {message}"
            ) from None
    try:
        cov = np.asarray(pose_covariance, dtype=np.float64)
    except (TypeError, ValueError):
        cov = np.zeros(0)
    scale = float(np.max(np.abs(cov))) if cov.size and np.all(np.isfinite(cov)) else 0.0
    if (
        cov.shape != (6, 6)
        or not np.all(np.isfinite(cov))
        or not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12 * max(scale, 1e-300))
        or np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() < -1e-9 * max(scale, 1e-300)
    ):
        raise AssociationError(
            f"pose_covariance of shape {cov.shape}: expected a finite symmetric positive "
            "semi-definite (6, 6) matrix, rotation [rad] first then translation [m] (as "
            "gtsam.Marginals.marginalCovariance gives for a Pose3)"
        )
    return 0.5 * (cov + cov.T)


def _worst_sigma(J: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """sqrt of the largest eigenvalue of J cov J^T, for (..., 3, 6) Jacobians J."""
    spread = np.einsum("...ij,jk,...lk->...il", J, cov, J)
    return np.sqrt(np.clip(np.linalg.eigvalsh(spread)[..., -1], 0.0, None))


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """(N, 3) vectors -> (N, 3, 3) cross-product matrices."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def pose_gate_sigmas(
    T_world_cam: Any,
    pose_covariance: np.ndarray,
    n_cam: np.ndarray,
    p_cam: np.ndarray,
) -> PoseGateSigmas:
    """Sigmas of observed planes (unit normals n_cam (N, 3)) and corners (p_cam (K, 3) [m]),
    camera frame, moved into the world by T_world_cam ((4, 4) or gtsam.Pose3) whose
    error has the (6, 6) covariance `pose_covariance` (see the module docstring)."""
    T = as_pose(T_world_cam, "T_world_cam_pred", AssociationError)
    cov = pose_covariance_matrix(pose_covariance)
    n = np.asarray(n_cam, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(p_cam, dtype=np.float64).reshape(-1, 3)
    zeros = np.zeros((len(n), 3, 3))
    # normal: d(n_world) = -R [n]x omega; the angle is its norm, so R drops out
    J_normal = np.concatenate([-_skew_rows(n), zeros], axis=-1)
    t_cam = T[:3, :3].T @ T[:3, 3]  # the camera's position, in camera axes
    J_offset = -np.concatenate([np.cross(n, t_cam), n], axis=-1)  # (N, 6)
    offset = np.sqrt(np.clip(np.einsum("ni,ij,nj->n", J_offset, cov, J_offset), 0.0, None))
    J_corner = np.concatenate([-_skew_rows(p), np.broadcast_to(np.eye(3), (len(p), 3, 3))], -1)
    return PoseGateSigmas(
        angle_rad=_worst_sigma(J_normal, cov),
        offset_m=offset,
        corner_m=_worst_sigma(J_corner, cov),
    )


__all__ = ["PoseGateSigmas", "pose_covariance_matrix", "pose_gate_sigmas"]
