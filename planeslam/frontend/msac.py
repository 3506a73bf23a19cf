"""The paper's plane segmentation (paper step 2): M-estimator sample consensus (MSAC),
plane by plane on a random subsample of the organised cloud.

`MsacSegmenter(config, sensor).segment(cloud, rays, rng)`; `segmentation.make_segmenter`
picks it for `segmentation.method: msac`. Thresholds are multiples of the `sensor`
depth noise sigma(z) = a + b z^2; keys are those of `segmentation.msac` unless they are
`segmentation`'s own. Planes are in the camera frame with their normal toward the
camera (d > 0); `Plane.area_m2`, `outline` and `covariance`: see `segment_common`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.errors import GeometryError
from planeslam.core.plane_fit import moments_of, plane_from_moments
from planeslam.frontend.config import SegmentationConfig
from planeslam.frontend.segment_common import (
    OUTLINE_STRIDE,
    PixelGrid,
    build_planes,
    checked_cloud,
    empty_segmentation,
    finish,
    no_valid_reason,
    pixel_grid,
)
from planeslam.frontend.types import Segmentation


@dataclass(frozen=True)
class MsacSegmenter:
    """The paper's MSAC method; a `Segmenter`. Reads `config.msac` and the keys both
    methods share."""

    config: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(method="msac"))
    sensor: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise sigma(z) the thresholds are multiples of."""

    def segment(
        self,
        cloud: np.ndarray,
        camera_or_rays: CameraConfig | PixelRays,
        rng: np.random.Generator | None = None,
        depth_m: np.ndarray | None = None,
    ) -> Segmentation:
        """See `types.Segmenter.segment`; `rng` defaults to one seeded with 0."""
        grid = pixel_grid(camera_or_rays)
        cloud = checked_cloud(cloud, grid)
        rng = rng if rng is not None else np.random.default_rng(0)
        return _segment_msac(cloud, grid, self.config, self.sensor, rng, depth_m)


def _nearest_label(e: np.ndarray) -> np.ndarray:
    """(N, H, W) normalised distances -> (H, W) int32 index of the nearest with e < 1, or -1."""
    best = np.argmin(e, axis=0).astype(np.int32)
    best[np.take_along_axis(e, best[None], axis=0)[0] >= 1.0] = -1
    return best


def _small_pieces(mask: np.ndarray, min_pixels: float) -> np.ndarray:
    """(H, W) bool: pixels of `mask` in 4-connected pieces smaller than min_pixels."""
    _, pieces, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] < min_pixels
    small[0] = False  # background
    return small[pieces]


def _segment_msac(
    cloud: np.ndarray,
    grid: PixelGrid,
    cfg: SegmentationConfig,
    noise: DepthNoiseConfig,
    rng: np.random.Generator,
    depth_m: np.ndarray | None,
) -> Segmentation:
    """Plane by plane MSAC (Torr & Zisserman truncated quadratic cost) on a subsample.

    Each round: draw `msac.hypotheses` triplets at once (first point from the
    remaining subsample, the two others among valid pixels within
    `msac.local_radius_px`), score them all on `msac.score_points` remaining points
    with sum(min(r^2 / T(z)^2, 1)), T(z) = `pixel_max_distance_sigmas` sigma(z),
    refit the best by least squares on its inliers (twice), remove them; stop when
    too few points remain or the best plane is too small. Then every valid pixel
    goes to its nearest plane within T(z); connected pieces of a plane smaller
    than min_plane_points / 2 (bands where a plane crosses other surfaces) go to
    their next nearest plane or to none; planes are refit on their pixels.
    """
    z = cloud[..., 2]
    valid = (z > 0) & (z <= cfg.max_depth_m)
    valid_idx = np.flatnonzero(valid)
    if len(valid_idx) == 0:
        return empty_segmentation(
            grid.height, grid.width, no_valid_reason(depth_m, cfg.max_depth_m)
        )
    x, y, z = (np.where(valid, cloud[..., k], np.float32(0.0)) for k in range(3))
    xyz_flat = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)  # (H*W, 3) float32
    k = cfg.pixel_max_distance_sigmas
    n_sub = min(cfg.msac.sample_points, len(valid_idx))
    sub = rng.choice(valid_idx, size=n_sub, replace=False)
    pts = xyz_flat[sub].astype(np.float64)
    thr = k * noise.sigma_m(pts[:, 2])
    scale = len(valid_idx) / n_sub
    min_sub = cfg.min_plane_points / scale
    width, height = grid.width, grid.height
    radius = cfg.msac.local_radius_px
    cos_inc = math.cos(math.radians(cfg.max_incidence_deg))
    remaining = np.ones(n_sub, dtype=bool)
    found_n: list[np.ndarray] = []
    found_d: list[float] = []
    for _ in range(cfg.msac.max_planes):
        rem = np.flatnonzero(remaining)
        if len(rem) < max(min_sub, 3):
            break
        hyp = cfg.msac.hypotheses
        first = rem[rng.integers(len(rem), size=hyp)]
        v1, u1 = np.divmod(sub[first], width)
        offsets = rng.integers(-radius, radius + 1, size=(hyp, 2, 2))
        v23 = np.clip(v1[:, None] + offsets[:, :, 0], 0, height - 1)
        u23 = np.clip(u1[:, None] + offsets[:, :, 1], 0, width - 1)
        pix23 = v23 * width + u23
        ok = valid.ravel()[pix23].all(axis=1)
        p1 = pts[first]
        p23 = xyz_flat[pix23].astype(np.float64)
        if found_n:
            # the 2nd and 3rd points must not lie on a plane already extracted
            fn = np.stack(found_n)
            dist = np.abs(p23 @ fn.T + np.array(found_d))
            near = dist < (k * noise.sigma_m(p23[:, :, 2]))[..., None]
            ok &= ~near.any(axis=(1, 2))
        normal = np.cross(p23[:, 0] - p1, p23[:, 1] - p1)
        norm = np.linalg.norm(normal, axis=1)
        ok &= norm > 1e-9
        if not ok.any():
            continue
        normal = normal[ok] / norm[ok, None]
        d = -np.einsum("ij,ij->i", normal, p1[ok])
        # planes seen edge-on (through the camera centre) fit any line of pixels
        grazing = np.abs(d) < cos_inc * np.linalg.norm(p1[ok], axis=1)
        if grazing.all():
            continue
        normal, d = normal[~grazing], d[~grazing]
        score_idx = rem[rng.integers(len(rem), size=min(cfg.msac.score_points, len(rem)))]
        r = (pts[score_idx] @ normal.T + d) / thr[score_idx, None]
        cost = np.minimum(r * r, 1.0).sum(axis=0)
        best = int(np.argmin(cost))
        n_best, d_best = normal[best], float(d[best])
        inl = rem
        for _ in range(3):
            inl = rem[np.abs(pts[rem] @ n_best + d_best) < thr[rem]]
            if len(inl) < 3:
                break
            try:
                n_best, d_best, _ = plane_from_moments(*moments_of(pts[inl])[1:])
            except GeometryError:
                break
        if len(inl) < min_sub:
            break
        if abs(d_best) < cos_inc * np.linalg.norm(pts[inl].mean(axis=0)):
            remaining[inl] = False  # an edge-on plane: drop its points, keep searching
            continue
        found_n.append(n_best)
        found_d.append(d_best)
        remaining[inl] = False
    if not found_n:
        return empty_segmentation(
            grid.height, grid.width, f"no plane with at least {cfg.min_plane_points} points"
        )
    # Every valid pixel to its nearest plane within T(z) (normalised distance e < 1).
    inv_tol = (1.0 / (k * noise.sigma_m(z))).astype(np.float32)
    e = np.empty((len(found_n), *z.shape), dtype=np.float32)
    for i, (n, d) in enumerate(zip(found_n, found_d, strict=True)):
        n32 = n.astype(np.float32)
        e[i] = np.abs(x * n32[0] + y * n32[1] + z * n32[2] + np.float32(d)) * inv_tol
    e[:, ~valid] = np.inf
    labels = _nearest_label(e)
    # A plane fit through a cluttered remainder also collects thin bands where it
    # crosses other surfaces: such small pieces go to their next nearest plane.
    for i in range(len(found_n)):
        e[i][_small_pieces(labels == i, 0.5 * cfg.min_plane_points)] = np.inf
    labels = _nearest_label(e)
    for i in range(len(found_n)):
        labels[_small_pieces(labels == i, 0.5 * cfg.min_plane_points)] = -1
    counts = np.bincount(labels.ravel() + 1, minlength=len(found_n) + 1)[1:]
    order = np.argsort(-counts, kind="stable")
    order = order[counts[order] >= cfg.min_plane_points]
    if len(order) == 0:
        return empty_segmentation(
            grid.height, grid.width, f"no plane with at least {cfg.min_plane_points} points"
        )
    remap = np.full(len(found_n) + 1, -1, dtype=np.int32)
    remap[order + 1] = np.arange(len(order), dtype=np.int32)
    labels = remap[labels + 1]
    lab_small = labels[::OUTLINE_STRIDE, ::OUTLINE_STRIDE]
    boxes = ndimage.find_objects(lab_small + 1, max_label=len(order))
    # Inliers of all planes grouped by plane id (raster order within each), in one
    # (3, N) float64 buffer; pixels on no plane (-1) sort first and are left out.
    pix = np.argsort(labels.ravel(), kind="stable")
    bounds = np.searchsorted(labels.ravel()[pix], np.arange(len(order) + 1))
    pix = pix[bounds[0] :]
    xyz = np.stack([c.ravel()[pix] for c in (x, y, z)]).astype(np.float64)
    planes = build_planes(
        xyz,
        bounds - bounds[0],
        lab_small,
        boxes,
        grid,
        cfg.outline_epsilon_px,
        OUTLINE_STRIDE,
        noise,
    )
    return finish(planes, labels)
