"""A sensor's depth noise from the planes it sees: the axial sigma(z) = a + b z^2 and the
step of its quantised inverse depth (`DepthNoiseConfig`), the model the segmentation's
gates and the plane factors' correlated depth noise follow.

1. Every frame is segmented (`FrontEnd`); each pixel of a plane seen within
   `max_incidence_deg` of its normal gives its depth residual r = z - z_plane along its
   ray (z_plane = -d / (n . ray), camera frame) at the plane's depth z_plane (at grazing
   incidence a sensor's error grows beyond its axial sigma: Nguyen et al. 2012).
2. The quantisation step s of 1/z [1/m] is the lattice spacing of the frames' distinct
   inverse depths; when they lie on no lattice (depth not quantised, or rounded again to
   millimetres as OpenNI and TUM's PNGs do) the configured step is kept.
3. a and b maximise the Gaussian likelihood of the residuals with variance
   (a + b z^2)^2 + (z^2 s)^2 / 12 (axial noise plus the rounding of 1/z), the residuals
   beyond 3.5 sigma (border pixels, clutter) left out and the fit repeated.
4. The segmentation's inlier gates scale with the model, so the frames are segmented
   again with the fitted model (`iterations`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import GeometryError
from planeslam.frontend.config import FrontEndConfig, FrontEndSettings
from planeslam.frontend.pipeline import FrontEnd

MAX_PIXELS = 200_000
"""Residuals the likelihood is evaluated on (a seeded subsample beyond that)."""
TRIM_SIGMAS = 3.5
"""Residuals beyond this many model sigmas are left out of the next fit."""


@dataclass(frozen=True)
class DepthNoiseFit:
    """A fitted depth noise model and the residuals it was fitted to."""

    sensor: DepthNoiseConfig
    """sigma_a_m, sigma_b_per_m and inverse_depth_step_per_m fitted."""
    step_found: bool
    """Whether the 1/z step was found in the frames (else the configured one is kept)."""
    depth_m: np.ndarray
    """(B,) centres of the depth bins of the summary [m]."""
    sigma_m: np.ndarray
    """(B,) robust sigma (1.4826 MAD) of the residuals in each bin [m]."""
    pixels: np.ndarray
    """(B,) residuals in each bin."""
    planes: int
    """Plane segments the residuals came from (last iteration)."""
    frames: int
    """Frames used."""


def plane_residuals(
    depths_m: Sequence[np.ndarray],
    front_end: FrontEnd,
    min_pixels: int = 500,
    max_incidence_deg: float = 45.0,
) -> tuple[np.ndarray, np.ndarray, int]:
    """((N,) plane depth z_plane [m], (N,) depth residual z - z_plane [m], planes) of the
    pixels of every plane of at least `min_pixels` pixels in the (H, W) depth images whose
    ray meets the plane within `max_incidence_deg` of its normal."""
    cos_max = math.cos(math.radians(max_incidence_deg))
    z_planes, residuals, planes = [], [], 0
    for depth_m in depths_m:
        observation = front_end.process(depth_m)
        segmentation, cloud = observation.segmentation, observation.cloud
        if cloud is None:
            continue
        for k, plane in enumerate(segmentation.planes):
            mask = segmentation.labels == k
            if np.count_nonzero(mask) < min_pixels:
                continue
            xyz = cloud[mask].astype(np.float64)
            xyz = xyz[xyz[:, 2] > 0]
            ray = xyz / xyz[:, 2:3]
            n_dot_ray = ray @ np.asarray(plane.normal, dtype=np.float64)
            z_plane = -float(plane.d) / n_dot_ray
            keep = (z_plane > 0) & (np.abs(n_dot_ray) >= cos_max * np.linalg.norm(ray, axis=1))
            if np.count_nonzero(keep) < min_pixels:
                continue
            z_planes.append(z_plane[keep])
            residuals.append(xyz[keep, 2] - z_plane[keep])
            planes += 1
    if not planes:
        raise GeometryError("no plane of enough pixels in the frames: nothing to calibrate on")
    return np.concatenate(z_planes), np.concatenate(residuals), planes


def inverse_depth_step(depths_m: Sequence[np.ndarray], tolerance: float = 0.1) -> float | None:
    """The spacing s [1/m] of the lattice the valid pixels' 1/z lie on (the smallest
    spacing between distinct values, refined as their median), or None when fewer than
    80 % of the spacings are within `tolerance` s of a whole multiple of it."""
    inverse = np.concatenate([1.0 / d[d > 0].astype(np.float64) for d in depths_m])
    levels = np.unique(np.round(inverse, 9))
    gaps = np.diff(levels)
    gaps = gaps[gaps > 0]
    if len(gaps) < 10:
        return None
    smallest = float(np.percentile(gaps, 5))
    step = float(np.median(gaps[gaps < 1.5 * smallest]))
    multiples = gaps / step
    on_lattice = np.abs(multiples - np.rint(multiples)) <= tolerance
    return step if np.mean(on_lattice) >= 0.8 else None


def fit_sigma(
    z_m: np.ndarray, residual_m: np.ndarray, step_per_m: float, rng: np.random.Generator
) -> tuple[float, float]:
    """(a [m], b [1/m]) of sigma(z) = a + b z^2 maximising the likelihood of the (N,)
    residuals at depths (N,) z_m [m] (module docstring, step 3)."""
    if len(z_m) > MAX_PIXELS:
        pick = rng.choice(len(z_m), MAX_PIXELS, replace=False)
        z_m, residual_m = z_m[pick], residual_m[pick]
    r = residual_m - np.median(residual_m)
    quantisation_var = (z_m**2 * step_per_m) ** 2 / 12.0
    z2 = z_m**2
    keep = np.ones(len(r), dtype=bool)
    start = max(1.4826 * float(np.median(np.abs(r))), 1e-4)
    params = np.log([start / 2, start / 2])
    for _ in range(3):
        zk, rk, qk = z2[keep], r[keep], quantisation_var[keep]

        def negative_log_likelihood(log_ab: np.ndarray, zk=zk, rk=rk, qk=qk) -> float:
            a, b = np.exp(log_ab)
            var = (a + b * zk) ** 2 + qk
            return float(np.sum(np.log(var) + rk**2 / var))

        params = minimize(negative_log_likelihood, params, method="Nelder-Mead").x
        a, b = np.exp(params)
        keep = np.abs(r) <= TRIM_SIGMAS * np.sqrt((a + b * z2) ** 2 + quantisation_var)
    a, b = np.exp(params)
    return float(a), float(b)


def fit_depth_noise(
    depths_m: Sequence[np.ndarray],
    config: FrontEndSettings,
    iterations: int = 2,
    seed: int = 0,
) -> DepthNoiseFit:
    """The depth noise model of the sensor that took the (H, W) depth images `depths_m`
    [m] (0 = invalid), segmented with `config` (its camera; its sensor model to start
    with, then the fitted one). GeometryError when the frames show no plane."""
    if not depths_m:
        raise GeometryError("no frames to calibrate on")
    rng = np.random.default_rng(seed)
    found = inverse_depth_step(depths_m)
    sensor = config.sensor
    step = sensor.inverse_depth_step_per_m if found is None else found
    for _ in range(max(1, int(iterations))):
        settings = FrontEndConfig(
            config.camera, sensor, config.segmentation, config.intersections, config.objects
        )
        front_end = FrontEnd(settings, seed=seed)
        z, residual, planes = plane_residuals(depths_m, front_end)
        a, b = fit_sigma(z, residual, step, rng)
        sensor = DepthNoiseConfig(sigma_a_m=a, sigma_b_per_m=b, inverse_depth_step_per_m=step)
    edges = np.arange(math.floor(z.min() * 4) / 4, z.max() + 0.25, 0.25)
    bins = np.digitize(z, edges) - 1
    centres, sigmas, counts = [], [], []
    for k in range(len(edges) - 1):
        in_bin = residual[bins == k]
        if len(in_bin) >= 100:
            centres.append(0.5 * (edges[k] + edges[k + 1]))
            sigmas.append(1.4826 * float(np.median(np.abs(in_bin - np.median(in_bin)))))
            counts.append(len(in_bin))
    return DepthNoiseFit(
        sensor=sensor,
        step_found=found is not None,
        depth_m=np.array(centres),
        sigma_m=np.array(sigmas),
        pixels=np.array(counts, dtype=np.int64),
        planes=planes,
        frames=len(depths_m),
    )
