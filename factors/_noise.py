"""Validation of noise arguments shared by the factor modules (private)."""

from __future__ import annotations

import math

import gtsam
import numpy as np

from planeslam.core.errors import ConfigError, GeometryError

_ROBUST_DEFAULT_K = {"huber": 1.345, "cauchy": 2.3849}  # 95 % efficiency under Gaussian noise


def gaussian_noise(
    noise: np.ndarray | gtsam.noiseModel.Gaussian, dim: int
) -> gtsam.noiseModel.Gaussian:
    """A (dim, dim) covariance or a Gaussian noise model of dimension `dim` -> Gaussian model."""
    if isinstance(noise, gtsam.noiseModel.Gaussian):
        if noise.dim() != dim:
            raise ConfigError(f"noise model of dimension {noise.dim()}: expected {dim}")
        return noise
    if isinstance(noise, gtsam.noiseModel.Base):
        raise ConfigError(
            f"noise model {type(noise).__name__}: expected a Gaussian model or a covariance "
            "(robust losses are chosen with the factory's `loss` argument)"
        )
    cov = np.asarray(noise, dtype=np.float64)
    if cov.shape != (dim, dim) or not np.all(np.isfinite(cov)):
        raise GeometryError(f"covariance of shape {cov.shape}: expected a finite ({dim}, {dim})")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-15):
        raise GeometryError("covariance is not symmetric: expected a symmetric matrix")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise GeometryError(
            f"covariance with eigenvalues {np.linalg.eigvalsh(cov)}: expected positive definite"
        ) from None
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def isotropic_noise(sigma: float, dim: int) -> gtsam.noiseModel.Isotropic:
    """Isotropic model with standard deviation `sigma` > 0 (units of the error)."""
    if not (isinstance(sigma, (int, float, np.floating)) and math.isfinite(sigma) and sigma > 0):
        raise ConfigError(f"sigma={sigma!r}: expected a finite positive number")
    return gtsam.noiseModel.Isotropic.Sigma(dim, float(sigma))


def robust_noise(
    base: gtsam.noiseModel.Gaussian, loss: str, k: float | None
) -> gtsam.noiseModel.Robust:
    """Wrap `base` in a Huber or Cauchy M-estimator with threshold `k` (whitened units)."""
    if loss not in _ROBUST_DEFAULT_K:
        raise ConfigError(f"robust loss {loss!r}: expected one of {sorted(_ROBUST_DEFAULT_K)}")
    k = _ROBUST_DEFAULT_K[loss] if k is None else k
    if not (isinstance(k, (int, float, np.floating)) and math.isfinite(k) and k > 0):
        raise ConfigError(f"robust threshold k={k!r}: expected a finite positive number")
    estimator = gtsam.noiseModel.mEstimator
    m = estimator.Huber.Create(float(k)) if loss == "huber" else estimator.Cauchy.Create(float(k))
    return gtsam.noiseModel.Robust.Create(m, base)


def distinct_keys(*keys: int) -> tuple[int, ...]:
    """Check that a factor's keys are distinct integers."""
    if len(set(keys)) != len(keys):
        raise ConfigError(f"factor keys {keys}: expected distinct keys")
    return tuple(int(k) for k in keys)
