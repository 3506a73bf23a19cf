"""Planes from depth whose inverse is quantised: the maximum-likelihood fit for far planes.

A Kinect-like sensor measures disparity and rounds it, so 1/z takes values on a grid of
step `s` (Kinect v1: a 1/8 px disparity step at 580 px x 7.5 cm, 0.00285 1/m, measured
on 7-Scenes, TUM fr1 and ICL-NUIM alike): the depth step z^2 s is 10 cm at 5.7 m. Where
the per-pixel noise before the rounding is small against the step, a far wall's pixels
sit on two or three depth levels, and a least-squares plane through them is biased by a
part of a step that changes with the view (ICL-NUIM's far walls: 1-2 cm under the true
poses). With Gaussian noise sigma in 1/z before the rounding the rounding bias of a mean
is at most (s / pi) exp(-2 pi^2 sigma^2 / s^2) (Sheppard; negligible once sigma > s / 2).

`fit_quantised_plane` fits w = 1/z = a . beta, a = (x/z, y/z, 1) (a plane
n . p + d = 0 is linear in inverse depth: beta = -n / d), by maximum likelihood of each
pixel's interval [w - s/2, w + s/2] under N(a . beta, sigma^2), with sigma estimated
too (interval-censored regression; Newton's method on the exact gradient and Hessian).
`quantisation_bias_m` says when it is worth it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import log_ndtr, ndtr

from planeslam.core.errors import GeometryError

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


@dataclass(frozen=True)
class QuantisedPlaneFit:
    """A plane n . p + d = 0 (camera frame, n toward the camera, d > 0) fitted to
    quantised inverse depth, and the noise before the rounding."""

    normal: np.ndarray
    """(3,) unit normal."""
    d: float
    """Offset [m]."""
    sigma_steps: float
    """Noise of 1/z before the rounding, in quantisation steps."""


def inverse_depth_residual_steps(
    points: np.ndarray, normal: np.ndarray, d: float, step: float
) -> float:
    """Noise of 1/z about the plane (n, d) before a rounding of `step` [1/m], in steps
    (`_noise_steps`). points: (K, 3) camera frame [m], z > 0. Includes the plane's misfit:
    an overestimate."""
    z = points[:, 2]
    return _noise_steps(1.0 / z + (points @ normal) / (z * d), step)


def _noise_steps(residual: np.ndarray, step: float) -> float:
    """Noise before a rounding of `step` behind 1/z residuals (K,) [1/m], in steps:
    sqrt(max(mean squared residual - step^2 / 12, 0)) / step (Sheppard's correction)."""
    variance = float(residual @ residual) / len(residual) - step * step / 12.0
    return float(np.sqrt(max(variance, 0.0))) / step


def quantisation_bias_m(depth_m: float, step: float, sigma_steps: float) -> float:
    """Largest rounding bias [m] of a mean depth near depth_m [m] when 1/z is rounded to
    `step` [1/m] after Gaussian noise of `sigma_steps` steps: z^2 (s / pi) exp(-2 pi^2 sigma^2)."""
    return depth_m * depth_m * step / np.pi * float(np.exp(-2.0 * np.pi**2 * sigma_steps**2))


def fit_quantised_plane(
    points: np.ndarray, step: float, max_points: int = 4096
) -> QuantisedPlaneFit:
    """Maximum-likelihood plane of points (K, 3) [m, camera frame, z > 0] whose 1/z is
    rounded to multiples of `step` [1/m]. At most `max_points` evenly spread points are
    used (with 2,048 some ICL-NUIM walls' likelihood peaked at a spuriously small noise, cm
    off the fit on all points). Raises GeometryError for fewer than 4 points or a fit that
    does not converge."""
    if len(points) < 4:
        raise GeometryError(f"a quantised plane fit needs at least 4 points, got {len(points)}")
    if len(points) > max_points:
        points = points[np.linspace(0, len(points) - 1, max_points).astype(np.intp)]
    z = points[:, 2]
    rays = np.stack([points[:, 0] / z, points[:, 1] / z, np.ones_like(z)], axis=1)
    w = 1.0 / z
    beta0, *_ = np.linalg.lstsq(rays, w, rcond=None)
    residual = w - rays @ beta0
    # Parameters theta = ((beta - beta0) / step (3,), log(sigma / step)): all of order 1.
    scaled = rays * step
    half = 0.5 * step
    upper = np.triu_indices(3)
    products = scaled[:, upper[0]] * scaled[:, upper[1]]  # (K, 6): the Gram matrix's terms

    def log_likelihood(theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        r = residual - scaled @ theta[:3]
        ll, g_r, g_t, h_rr, h_rt, h_tt = _interval_terms(r, half, step * np.exp(theta[3]))
        # d r / d theta[:3] = -scaled; theta[3] is log sigma itself.
        grad = np.concatenate([-(scaled.T @ g_r), [g_t.sum()]])
        hess = np.empty((4, 4))
        hess[upper] = products.T @ h_rr
        hess[upper[1], upper[0]] = hess[upper]
        hess[:3, 3] = hess[3, :3] = -(scaled.T @ h_rt)
        hess[3, 3] = h_tt.sum()
        return float(ll.sum()), grad, hess

    theta = np.array([0.0, 0.0, 0.0, np.log(max(_noise_steps(residual, step), 0.1))])
    theta = _newton_ascent(log_likelihood, theta)
    beta = beta0 + step * theta[:3]
    norm = float(np.linalg.norm(beta))
    if not norm > 0:
        raise GeometryError("the quantised plane fit passes through the camera centre")
    return QuantisedPlaneFit(normal=-beta / norm, d=1.0 / norm, sigma_steps=float(np.exp(theta[3])))


def _newton_ascent(
    log_likelihood: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]],
    theta: np.ndarray,
    tolerance: float = 1e-2,
    max_iterations: int = 30,
    max_step: float = 1.0,
) -> np.ndarray:
    """Maximise a smooth function (value, gradient, Hessian) of a few parameters from
    `theta` by Newton steps, the Hessian's eigenvalues of the wrong sign (where the function
    is not concave) replaced by a small share of the largest, each step at most `max_step`
    in every parameter and halved until the value does not decrease; until a step is below
    `tolerance` in every parameter. (SciPy's trust-region Newton evaluates as often, plus
    about 2 ms per fit of its own: more than the likelihood costs.) Raises GeometryError
    when it does not converge."""
    value, grad, hess = log_likelihood(theta)
    for _ in range(max_iterations):
        curvature, axes = np.linalg.eigh(-hess)
        floor = 1e-3 * max(float(np.abs(curvature).max()), 1e-300)
        step = axes @ ((axes.T @ grad) / np.maximum(curvature, floor))
        step *= min(1.0, max_step / max(float(np.abs(step).max()), 1e-300))
        for _ in range(20):
            trial = log_likelihood(theta + step)
            if trial[0] >= value:
                break
            step = 0.5 * step
        else:
            break  # no ascent along a millionth of the step: at the maximum to rounding
        theta = theta + step
        value, grad, hess = trial
        if np.max(np.abs(step)) < tolerance:
            return theta
    if not np.all(np.isfinite(theta)) or np.max(np.abs(grad)) > 1e3 * tolerance * len(grad):
        raise GeometryError(f"the quantised plane fit did not converge (gradient {grad})")
    return theta


@np.errstate(over="ignore", invalid="ignore")  # a trial step the line search rejects
def _interval_terms(r: np.ndarray, half: float, sigma: float) -> tuple[np.ndarray, ...]:
    """Per-point log P(r - half < e < r + half), e ~ N(0, sigma^2), and its derivatives:
    (log L, d/dr, d/dlog sigma, d2/dr2, d2/dr dlog sigma, d2/dlog sigma2), each (K,).

    Evaluated at -|r| (L is even in r; in the lower tail the difference of normal CDFs
    keeps its relative precision), the odd derivatives' signs restored after; beyond
    about 37 sigma, where the CDFs underflow, through their logarithms."""
    sign = np.where(r > 0, -1.0, 1.0)
    ra = -np.abs(r)
    u = (ra + half) / sigma
    lo = (ra - half) / sigma
    mass = ndtr(u) - ndtr(lo)
    far = ~(mass > 1e-250)
    log_mass = np.log(np.where(far, 1.0, mass))
    if far.any():
        log_u = log_ndtr(u[far])
        log_mass[far] = log_u + np.log1p(-np.exp(log_ndtr(lo[far]) - log_u))
    u2, lo2 = u * u, lo * lo
    a_u = np.exp(-0.5 * u2 - _LOG_SQRT_2PI - log_mass)
    a_l = np.exp(-0.5 * lo2 - _LOG_SQRT_2PI - log_mass)
    g_r = (a_u - a_l) / sigma
    g_t = lo * a_l - u * a_u
    h_rr = g_t / (sigma * sigma) - g_r * g_r
    h_rt = (u2 * a_u - lo2 * a_l) / sigma - g_r - g_r * g_t
    h_tt = -g_t - (u2 * u * a_u - lo2 * lo * a_l) - g_t * g_t
    return log_mass, sign * g_r, g_t, h_rr, sign * h_rt, h_tt
