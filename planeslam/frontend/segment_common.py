"""What both segmentation methods share: the camera's pixel geometry (cached per camera),
empty results and their reasons, and the plane record built from a plane's inliers
(refit, covariance, area, outline).

`Plane.area_m2` is the sum of per-pixel footprints on the plane,
z^2 / (fx fy |n . r|) = z^3 / (fx fy d) per inlier (r the pixel's z=1 ray).
`Plane.outline` is the outer contour of the largest connected piece of the
plane's pixel mask, traced on every 3rd pixel (cv2.findContours + cv2.approxPolyDP with
`outline_epsilon_px`), its vertices' rays intersected with the plane.
`Plane.covariance` comes from the least-squares fit (see `plane_fit`), in the
tangent basis of `plane_fit.tangent_basis` (= gtsam.Unit3(n).basis()).
A plane whose least-squares offset the sensor's 1/z rounding could bias by more than
twice the fit's own offset sigma (far walls where the noise does not dither the rounding) takes
the maximum-likelihood fit of `core.quantised_fit` instead; its covariance is the same
formula about the new plane, and its centroid and scatter are moved to refit to it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.errors import ConfigError, GeometryError
from planeslam.core.plane_fit import plane_covariance
from planeslam.core.quantised_fit import (
    fit_quantised_plane,
    inverse_depth_residual_steps,
    quantisation_bias_m,
)
from planeslam.frontend.plane_kernels import (
    FIT_OK,
    inverse_depth_noise_kernel,
    outline_points_kernel,
    plane_fits_kernel,
)
from planeslam.frontend.types import Plane, Segmentation

log = logging.getLogger(__name__)

DEFAULT_SENSOR = DepthNoiseConfig()
"""The sensor `build_planes` assumes when its caller names none (its 1/z step)."""

OUTLINE_STRIDE = 3
"""Outlines are traced on every 3rd pixel of every 3rd row (full-image pixels)."""


@dataclass(frozen=True, eq=False)
class PixelGrid:
    """Pixel rays of one camera and what the segmenters derive from them."""

    height: int
    width: int
    rays: np.ndarray  # (H, W, 3) float64 z=1 rays
    rays32: np.ndarray  # (H, W, 3) float32 z=1 rays (back-projection)
    fx: float
    fy: float


_GRID_CACHE: dict[tuple, tuple[object, PixelGrid]] = {}


def pixel_grid(camera_or_rays: CameraConfig | PixelRays) -> PixelGrid:
    """The cached `PixelGrid` of a camera (or of a PixelRays object)."""
    if isinstance(camera_or_rays, CameraConfig):
        key: tuple = ("camera", camera_or_rays)
    elif isinstance(camera_or_rays, PixelRays):
        key = ("rays", id(camera_or_rays))
    else:
        raise ConfigError(
            f"segment_planes needs a CameraConfig or PixelRays, got {type(camera_or_rays).__name__}"
        )
    hit = _GRID_CACHE.get(key)
    if hit is not None and (key[0] == "camera" or hit[0] is camera_or_rays):
        return hit[1]
    if isinstance(camera_or_rays, CameraConfig):
        rays = PixelRays.for_camera(camera_or_rays).rays
        fx, fy = float(camera_or_rays.fx), float(camera_or_rays.fy)
    else:
        rays = np.asarray(camera_or_rays.rays, dtype=np.float64)
        if rays.ndim != 3 or rays.shape[2] != 3 or min(rays.shape[:2]) < 2:
            raise GeometryError(f"PixelRays.rays must be (H, W, 3), got shape {rays.shape}")
        fx = 1.0 / float(np.median(np.diff(rays[:, :, 0], axis=1)))
        fy = 1.0 / float(np.median(np.diff(rays[:, :, 1], axis=0)))
    height, width = rays.shape[:2]
    grid = PixelGrid(
        height=height,
        width=width,
        rays=rays,
        rays32=np.ascontiguousarray(rays, dtype=np.float32),
        fx=fx,
        fy=fy,
    )
    if len(_GRID_CACHE) >= 8:
        _GRID_CACHE.clear()
    _GRID_CACHE[key] = (camera_or_rays, grid)  # holding the object keeps its id unique
    return grid


def checked_cloud(cloud: np.ndarray, grid: PixelGrid) -> np.ndarray:
    """The (H, W, 3) float32 organised cloud, or GeometryError when it does not fit the camera."""
    if np.shape(cloud) != (grid.height, grid.width, 3):
        raise GeometryError(
            f"organised cloud has shape {tuple(np.shape(cloud))}, expected "
            f"({grid.height}, {grid.width}, 3) for this camera: use cloud.organized_cloud"
        )
    return np.asarray(cloud, dtype=np.float32)


def empty_segmentation(height: int, width: int, reason: str) -> Segmentation:
    """No planes, all (H, W) labels -1, and why."""
    log.debug("segmentation empty: %s", reason)
    return Segmentation(
        planes=[], labels=np.full((height, width), -1, dtype=np.int32), reason=reason
    )


def no_valid_reason(depth: np.ndarray | None, max_depth_m: float) -> str:
    """Why a frame has no valid depth, from its depth image when known."""
    if depth is None:
        return f"no valid depth: no point with 0 < z <= max_depth_m={max_depth_m} m"
    depth = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(depth)
    if not finite.any():
        return "no valid depth: every pixel is NaN or infinite"
    if not (depth[finite] > 0).any():
        return "no valid depth: every finite pixel is <= 0"
    return f"no valid depth: every positive pixel is beyond max_depth_m={max_depth_m} m"


def finish(planes: list[Plane], labels_img: np.ndarray) -> Segmentation:
    """Renumber if a degenerate plane was skipped (ids stay 0..N-1 by decreasing size)."""
    if all(p.id == i for i, p in enumerate(planes)):
        return Segmentation(planes=planes, labels=labels_img)
    remap = np.full(int(labels_img.max()) + 2, -1, dtype=np.int32)
    fixed = []
    for i, p in enumerate(planes):
        remap[p.id + 1] = i
        fixed.append(Plane(**{**p.__dict__, "id": i}))
    return Segmentation(planes=fixed, labels=remap[labels_img + 1])


def build_planes(
    xyz: np.ndarray,
    bounds: np.ndarray,
    labels_small: np.ndarray,
    boxes: Sequence[tuple[slice, slice] | None],
    grid: PixelGrid,
    outline_epsilon_px: float,
    outline_stride: int = OUTLINE_STRIDE,
    sensor: DepthNoiseConfig = DEFAULT_SENSOR,
) -> list[Plane]:
    """The plane records of one frame: plane i's inliers are the columns
    bounds[i]:bounds[i + 1] of xyz (3, N) float64 [m] (rows contiguous); each is refit
    (all at once, `plane_fits_kernel`), given covariance, area and outline, and its
    `Plane.points` is the (K, 3) transposed view of its columns.

    `labels_small` is the label image strided by `outline_stride`, `boxes[i]` the
    (rows, cols) slices bounding plane i in it (None: not in it). `sensor` gives the
    1/z quantisation step. Planes whose points are degenerate (fewer than 4, collinear)
    are left out."""
    bounds = np.asarray(bounds, dtype=np.int64)
    count, centroid, scatter, normal, d, _, covariance, cubes, status = plane_fits_kernel(
        xyz, bounds
    )
    step = sensor.inverse_depth_step_per_m
    planes = []
    for i in range(len(bounds) - 1):
        if status[i] != FIT_OK:
            log.debug("plane %d skipped: %d points, degenerate (status %d)", i, count[i], status[i])
            continue
        points = xyz[:, bounds[i] : bounds[i + 1]]
        n, offset, mean, spread, cov = (
            normal[i],
            float(d[i]),
            centroid[i],
            scatter[i],
            covariance[i],
        )
        if step > 0 and _rounding_could_bias(points, n, offset, mean, cov, step):
            try:
                n, offset, mean, spread, cov = _quantised_refit(
                    points, int(count[i]), mean, spread, step
                )
            except GeometryError as exc:
                log.debug("plane %d keeps its least-squares fit: %s", i, exc)
        try:
            outline = _outline(
                i, n, offset, labels_small, boxes[i], grid, outline_epsilon_px, outline_stride
            )
        except GeometryError as exc:
            log.debug("plane %d skipped: %s", i, exc)
            continue
        planes.append(
            Plane(
                id=i,
                normal=n,
                d=offset,
                points=points.T,
                centroid=mean,
                covariance=cov,
                scatter=spread,
                num_points=int(count[i]),
                area_m2=float(cubes[i]) / (grid.fx * grid.fy * offset),
                outline=outline,
            )
        )
    return planes


def _rounding_could_bias(
    xyz: np.ndarray,
    normal: np.ndarray,
    d: float,
    centroid: np.ndarray,
    covariance: np.ndarray,
    step: float,
    sample: int = 4096,
) -> bool:
    """Whether the 1/z rounding (`step` [1/m]) could bias the least-squares plane (normal,
    d) of the points xyz (3, K) by more than twice its own offset sigma (significant at 2
    sigma): the noise about it, from up to `sample` evenly spread points, is too small to
    dither the rounding at the centroid's depth.

    The noise comes from a compiled pass, equal to numpy's to about 1e-12; where the bias
    is within 1e-6 (relative) of the threshold, the numpy computation decides, so the
    answer is always numpy's."""
    threshold = 2.0 * np.sqrt(covariance[2, 2])
    sigma_steps = inverse_depth_noise_kernel(xyz, normal, d, step, sample)
    bias = quantisation_bias_m(float(centroid[2]), step, sigma_steps)
    if abs(bias - threshold) > 1e-6 * threshold:
        return bool(bias > threshold)
    points = xyz[:, :: max(1, xyz.shape[1] // sample)].T
    sigma_steps = inverse_depth_residual_steps(points, normal, d, step)
    return bool(quantisation_bias_m(float(centroid[2]), step, sigma_steps) > threshold)


def _quantised_refit(
    xyz: np.ndarray, count: int, centroid: np.ndarray, scatter: np.ndarray, step: float
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """(normal, d, centroid, scatter, covariance) of the maximum-likelihood plane of xyz
    (3, K) under the 1/z rounding `step`: its moments moved onto it (`_moments_on_plane`),
    the covariance the least-squares formula about it. Raises GeometryError when the fit
    does not converge (the caller keeps least squares)."""
    fit = fit_quantised_plane(xyz.T, step)
    centroid, scatter = _moments_on_plane(count, centroid, scatter, fit.normal, fit.d)
    rss = float(fit.normal @ scatter @ fit.normal)
    covariance = plane_covariance(fit.normal, centroid, scatter, count, rss)
    return fit.normal, fit.d, centroid, scatter, covariance


def _moments_on_plane(
    count: int, centroid: np.ndarray, scatter: np.ndarray, normal: np.ndarray, d: float
) -> tuple[np.ndarray, np.ndarray]:
    """Moments of `count` points (centroid (3,), scatter (3, 3)) moved so that they refit to
    the plane (normal, d): the centroid onto it along the normal, the scatter's spread in
    the plane kept and along the normal replaced by the squared distances to the plane,
    cross terms dropped. The plane's covariance is the same from either; merges of moments
    (the map, segment merges) then start from the refit plane, not from least squares."""
    along = np.outer(normal, normal)
    in_plane = np.eye(3) - along
    offset = float(normal @ centroid) + d
    moved = centroid - offset * normal
    off_plane = float(normal @ scatter @ normal) + count * offset * offset
    return moved, in_plane @ scatter @ in_plane + off_plane * along


def _outline(
    plane_id: int,
    normal: np.ndarray,
    d: float,
    labels_small: np.ndarray,
    box: tuple[slice, slice] | None,
    grid: PixelGrid,
    epsilon_px: float,
    stride: int,
) -> np.ndarray:
    """(M, 3) outline on the plane: outer contour of the largest piece of its mask.

    The contour is traced on every `stride`-th pixel of every such row
    (`labels_small`): cheap, and finer than the polygon tolerance
    `epsilon_px` needs. `box`: (rows, cols) slices of `labels_small`."""
    s = stride
    if box is None:
        raise GeometryError(f"plane {plane_id} has no pixel on the outline grid")
    v0, u0 = box[0].start, box[1].start
    mask = (labels_small[box] == plane_id).view(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        raise GeometryError(f"plane {plane_id} has no pixels in its bounding box {box}")
    contour = contours[0] if len(contours) == 1 else max(contours, key=cv2.contourArea)
    poly = cv2.approxPolyDP(contour, epsilon_px / s, True)
    poly = poly.reshape(-1, 2)
    if len(poly) < 3:
        poly = np.round(cv2.boxPoints(cv2.minAreaRect(contour))).astype(np.int64)
    return outline_points_kernel(poly, u0, v0, labels_small.shape, s, grid.rays, normal, d)
