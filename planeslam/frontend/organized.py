"""Organised plane segmentation (paper step 2, the default method): cell-wise plane fits
on the image grid merged into planes, in the spirit of PEAC/CAPE.

`OrganizedSegmenter(config, sensor).segment(cloud, rays)` finds the planes of one
organised cloud (`cloud.organized_cloud`); `segmentation.make_segmenter` picks it
for `segmentation.method: organized`. Every plane is expressed in the camera frame
with its normal toward the camera (d > 0).

Depth noise model (Kinect-like, the `sensor` section): sigma(z) = a + b z^2 [m]
(`sensor.sigma_a_m`, `sensor.sigma_b_per_m`); every distance threshold is a
multiple of sigma at the depth where it is applied. Keys below are those of
`segmentation.organized` unless they are `segmentation`'s own.

Step by step:
1. the image is cut into square cells of `cell_size_px` (stored cell-major,
   (cells, pixels per cell)); each cell's moments give a least-squares plane
   (batched, closed-form 3x3 eigen-solver). A cell is planar when enough of
   its pixels are valid and its RMS residual is below
   `cell_max_rms_sigmas` sigma(z).
2. neighbouring planar cells are linked when each fits the other's plane
   (RMS of the cell's points to the other plane, computed exactly from its
   moments, below `merge_max_rms_sigmas` sigma) and their normals differ by less
   than `merge_max_angle_deg`; connected components of these links are
   candidate planes.
3. each candidate is refit on its merged moments and every cell is checked
   against the candidate's plane; a candidate whose cells do not fit (a curved
   surface chained together) is re-grown from seeds cell by cell against the
   growing region's plane (CAPE-style region growing).
4. with `merge_coplanar`, regions that are the same plane (their moments fit
   each other's plane) are merged even when they do not touch in the image
   (a wall split by an occluder is one plane).
5. pixels: in cells surrounded by cells of the same plane, each valid pixel
   within `segmentation.pixel_max_distance_sigmas` sigma(z) of that plane is an
   inlier; in border and rejected cells next to planes, each pixel goes to the
   nearest candidate plane of its 3x3 cell neighbourhood within that distance. (A 5x5
   neighbourhood recovers the last pixels of a face seen as a thin wedge, but
   also lets planes claim pixels across depth edges, which hurt tracking; the
   edge ends it would fix are recovered by snapping edges to corners instead.)
6. planes with fewer than `segmentation.min_plane_points` inliers are dropped; the
   rest are refit on their pixel inliers and numbered by decreasing size. All
   planes' inliers are gathered into one (3, N) float64 buffer, grouped by
   plane; `Plane.points` is a (K, 3) transposed view of its slice (no copy).

With `pixel_stride` k > 1 the steps run on every k-th pixel of every k-th row
(cells of `cell_size_px` / k strided pixels) and each label covers its k x k block.
`Plane.area_m2`, `outline` and `covariance`: see `segment_common`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.plane_fit import merge_moments, plane_from_moments
from planeslam.frontend.cell_kernels import (
    dense_components_kernel,
    group_sums_kernel,
    grow_regions_kernel,
    link_cells_kernel,
    smallest_eigh3_kernel,
)
from planeslam.frontend.config import SegmentationConfig
from planeslam.frontend.kernels import (
    assign_pixels_kernel,
    cells_from_cloud_kernel,
    gather_planes_kernel,
)
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

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OrganizedSegmenter:
    """The organised (cell-grid) method; a `Segmenter`. Reads `config.organized` and the
    keys both methods share."""

    config: SegmentationConfig = field(default_factory=SegmentationConfig)
    sensor: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise sigma(z) the thresholds are multiples of."""

    def segment(
        self,
        cloud: np.ndarray,
        camera_or_rays: CameraConfig | PixelRays,
        rng: np.random.Generator | None = None,
        depth_m: np.ndarray | None = None,
    ) -> Segmentation:
        """See `types.Segmenter.segment`; deterministic (`rng` is unused)."""
        cfg = self.config
        pixels = pixel_grid(camera_or_rays)
        cloud = checked_cloud(cloud, pixels)
        k = cfg.organized.pixel_stride
        if k == 1:
            grid = _cell_grid(pixels, cfg.organized.cell_size_px)
            return _segment_organized(cloud, grid, cfg, self.sensor, depth_m)
        sub_cfg = replace(
            cfg,
            min_plane_points=max(3, -(-cfg.min_plane_points // (k * k))),
            organized=replace(
                cfg.organized, cell_size_px=cfg.organized.cell_size_px // k, pixel_stride=1
            ),
        )
        sub_pixels = pixel_grid(_strided_rays(camera_or_rays, pixels, k))
        sub_grid = _cell_grid(sub_pixels, sub_cfg.organized.cell_size_px)
        outline_stride = -(-OUTLINE_STRIDE // k)  # about OUTLINE_STRIDE full-image pixels
        seg = _segment_organized(
            cloud[::k, ::k], sub_grid, sub_cfg, self.sensor, depth_m, outline_stride
        )
        labels = np.repeat(np.repeat(seg.labels, k, axis=0), k, axis=1)
        return replace(seg, labels=np.ascontiguousarray(labels[: pixels.height, : pixels.width]))


# ----------------------------------------------------------------------------------------
# Camera geometry in cell-major layout, cached per camera and cell size.


@dataclass(frozen=True, eq=False)
class _CellGrid:
    """A camera's pixel rays in cell-major layout."""

    pixels: PixelGrid
    cell: int
    rows: int
    cols: int
    rx: np.ndarray  # (C, P) float32 x of the z=1 rays, cell-major, zero in padding
    ry: np.ndarray  # (C, P) float32 y of the z=1 rays

    @property
    def height(self) -> int:
        return self.pixels.height

    @property
    def width(self) -> int:
        return self.pixels.width

    @property
    def padded(self) -> bool:
        return self.rows * self.cell != self.height or self.cols * self.cell != self.width

    def to_cells(self, image: np.ndarray) -> np.ndarray:
        """(H, W) -> (C, P) cell-major copy (cells row by row, pixels row by row in a cell)."""
        c = self.cell
        if self.padded:
            full = np.zeros((self.rows * c, self.cols * c), dtype=image.dtype)
            full[: self.height, : self.width] = image
            image = full
        blocks = image.reshape(self.rows, c, self.cols, c).transpose(0, 2, 1, 3)
        return blocks.reshape(self.rows * self.cols, c * c)

    def to_image(self, cells: np.ndarray) -> np.ndarray:
        """(C, P) cell-major -> (H, W) contiguous image."""
        c = self.cell
        image = cells.reshape(self.rows, self.cols, c, c).transpose(0, 2, 1, 3)
        image = image.reshape(self.rows * c, self.cols * c)
        return np.ascontiguousarray(image[: self.height, : self.width])


_CELL_GRIDS: dict[tuple[int, int], tuple[PixelGrid, _CellGrid]] = {}


def _cell_grid(pixels: PixelGrid, cell: int) -> _CellGrid:
    """The cached `_CellGrid` of a camera's `PixelGrid` for this cell size."""
    key = (id(pixels), cell)
    hit = _CELL_GRIDS.get(key)
    if hit is not None and hit[0] is pixels:
        return hit[1]
    grid = _CellGrid(
        pixels=pixels,
        cell=cell,
        rows=-(-pixels.height // cell),
        cols=-(-pixels.width // cell),
        rx=np.empty(0),
        ry=np.empty(0),
    )
    for name, axis in (("rx", 0), ("ry", 1)):
        image = np.ascontiguousarray(pixels.rays[:, :, axis], dtype=np.float32)
        object.__setattr__(grid, name, grid.to_cells(image))
    if len(_CELL_GRIDS) >= 8:
        _CELL_GRIDS.clear()
    _CELL_GRIDS[key] = (pixels, grid)  # holding `pixels` keeps its id unique
    return grid


_STRIDED_RAYS: dict[tuple[int, int], tuple[object, PixelRays]] = {}


def _strided_rays(camera_or_rays: CameraConfig | PixelRays, pixels: PixelGrid, k: int) -> PixelRays:
    """The rays of every k-th pixel of every k-th row, one PixelRays per camera (cached)."""
    key = (id(camera_or_rays), k)
    hit = _STRIDED_RAYS.get(key)
    if hit is not None and hit[0] is camera_or_rays:
        return hit[1]
    if len(_STRIDED_RAYS) >= 8:
        _STRIDED_RAYS.clear()
    rays = PixelRays(rays=np.ascontiguousarray(pixels.rays[::k, ::k]))
    _STRIDED_RAYS[key] = (camera_or_rays, rays)
    return rays


# ----------------------------------------------------------------------------------------
# Cells, regions and pixels.


@dataclass
class _Cells:
    """Per-cell moments and plane fits (C cells), float64."""

    count: np.ndarray  # (C,) valid pixels
    mean: np.ndarray  # (C, 3)
    scatter: np.ndarray  # (C, 3, 3)
    normal: np.ndarray  # (C, 3) toward the camera
    d: np.ndarray  # (C,)
    sigma: np.ndarray  # (C,) noise at the cell's mean depth
    planar: np.ndarray  # (C,) bool
    tilt_var: np.ndarray  # (C,) variance of the normal's tilt from noise sigma [rad^2]


def _cell_fits(x, y, z, valid, cfg: SegmentationConfig, noise: DepthNoiseConfig) -> _Cells:
    """Moments and least-squares planes of every cell: x, y, z, valid (C, P)."""
    count = np.count_nonzero(valid, axis=1)
    usable = count >= cfg.organized.min_cell_valid_fraction * x.shape[1]
    n_safe = np.maximum(count, 1).astype(np.float32)
    mean32 = np.stack([x.sum(1), y.sum(1), z.sum(1)], axis=1) / n_safe[:, None]
    # Centre before the products: float32 cannot hold x^2 sums to noise precision.
    # Invalid pixels are (0, 0, 0), so each adds exactly mean_a * mean_b to the sum of
    # products: subtract that instead of masking (exact for full cells, within a few
    # % of the residual scatter for half-empty ones; exact float64 sums were tried and
    # moved the shared rows: docs/speed.md, "Exact cell moments").
    dx = x - mean32[:, 0:1]
    dy = y - mean32[:, 1:2]
    dz = z - mean32[:, 2:3]
    n_invalid = (x.shape[1] - count).astype(np.float64)
    m64 = mean32.astype(np.float64)
    sums = [
        np.einsum("ij,ij->i", dd[a], dd[b]).astype(np.float64) - n_invalid * m64[:, a] * m64[:, b]
        for dd in ((dx, dy, dz),)
        for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    ]
    sxx, sxy, sxz, syy, syz, szz = sums
    scatter = np.stack(
        [np.stack([sxx, sxy, sxz], 1), np.stack([sxy, syy, syz], 1), np.stack([sxz, syz, szz], 1)],
        axis=1,
    )
    mean = mean32.astype(np.float64)
    lam_min, lam_mid, normal = smallest_eigh3_kernel(scatter)
    d = -np.einsum("ij,ij->i", normal, mean)
    flip = d < 0
    normal[flip] *= -1.0
    d[flip] *= -1.0
    sigma = noise.sigma_m(mean[:, 2])
    rms2 = np.maximum(lam_min, 0.0) / np.maximum(count, 1)
    # d / |mean| is the cosine of the incidence angle at the cell
    cos_inc = d / np.maximum(np.linalg.norm(mean, axis=1), 1e-9)
    planar = (
        usable
        & (rms2 <= (cfg.organized.cell_max_rms_sigmas * sigma) ** 2)
        & (cos_inc >= math.cos(math.radians(cfg.max_incidence_deg)))
    )
    # least-squares slope variance along the cell's shorter in-plane axis
    tilt_var = sigma**2 / np.maximum(lam_mid, 1e-12)
    return _Cells(count, mean, scatter, normal, d, sigma, planar, tilt_var)


def _cos_tolerance(tilt_var: np.ndarray, cfg: SegmentationConfig) -> np.ndarray:
    """Cosine of the largest normal angle accepted between cells or cell and plane:
    merge_max_angle_deg, widened to 3 standard deviations of the cells' normal noise
    (far cells are only a few cm wide), at most 45 deg."""
    angle = np.clip(
        3.0 * np.sqrt(tilt_var), math.radians(cfg.organized.merge_max_angle_deg), math.pi / 4
    )
    return np.cos(angle)


def _rms2_to_plane(cells: _Cells, idx: np.ndarray, normal: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Mean squared distance of the points of cells `idx` (K,) to planes (K, 3)/(K,) or (3,)/()."""
    n = np.broadcast_to(normal, (len(idx), 3))
    quad = np.einsum("ki,kij,kj->k", n, cells.scatter[idx], n)
    off = np.einsum("ki,ki->k", n, cells.mean[idx]) + d
    return quad / np.maximum(cells.count[idx], 1) + off * off


@dataclass
class _Region:
    cells: np.ndarray  # cell indices
    count: int
    centroid: np.ndarray
    scatter: np.ndarray
    normal: np.ndarray
    d: float


def _link_cells(cells: _Cells, rows: int, cols: int, cfg: SegmentationConfig):
    """Links between 4-neighbour planar cells that fit each other's planes (normals within
    `_cos_tolerance`, each cell within merge_max_rms_sigmas of the other's plane).

    Returns (component label per cell (C,), links per cell (C,))."""
    return link_cells_kernel(
        rows,
        cols,
        cells.planar,
        cells.normal,
        cells.d,
        cells.mean,
        cells.scatter,
        cells.count,
        cells.sigma,
        cells.tilt_var,
        math.radians(cfg.organized.merge_max_angle_deg),
        float(cfg.organized.merge_max_rms_sigmas**2),
    )


def _grow_regions(
    cells: _Cells,
    member: np.ndarray,
    degree: np.ndarray,
    rows: int,
    cols: int,
    min_px: float,
    cfg: SegmentationConfig,
) -> list[_Region]:
    """Seeded region growing inside the cells `member` (K,) (CAPE-style): a region grows
    over the connected cells that fit its current plane, refit after each growth
    (`cell_kernels.grow_regions_kernel`)."""
    idx, bounds, count, centroid, scatter, normal, d = grow_regions_kernel(
        member,
        degree,
        rows,
        cols,
        cells.count,
        cells.mean,
        cells.scatter,
        cells.normal,
        cells.sigma,
        cells.tilt_var,
        min_px,
        math.radians(cfg.organized.merge_max_angle_deg),
        float(cfg.organized.merge_max_rms_sigmas**2),
    )
    return [
        _Region(
            idx[bounds[i] : bounds[i + 1]], int(count[i]), centroid[i], scatter[i], normal[i], d[i]
        )
        for i in range(len(count))
    ]


def _group_planes(cells: _Cells, group: np.ndarray, n_groups: int):
    """Merged moments and planes of cell groups, all groups at once.

    group: (C,) group index per cell, -1 for none. Returns (count (G,), centroid (G, 3),
    scatter (G, 3, 3), normal (G, 3) toward the camera, d (G,))."""
    count, first, second = group_sums_kernel(
        group, cells.count, cells.mean, cells.scatter, n_groups
    )
    safe = np.maximum(count, 1.0)
    centroid = first / safe[:, None]
    scatter = second - safe[:, None, None] * centroid[:, :, None] * centroid[:, None, :]
    _, _, normal = smallest_eigh3_kernel(scatter)
    d = -np.einsum("gi,gi->g", normal, centroid)
    flip = d < 0
    normal[flip] *= -1.0
    d[flip] *= -1.0
    return count, centroid, scatter, normal, d


def _find_regions(
    cells: _Cells, rows: int, cols: int, cfg: SegmentationConfig, noise: DepthNoiseConfig
) -> list[_Region]:
    """Steps 2-4 of the module docstring: planar regions of cells."""
    comp, degree = _link_cells(cells, rows, cols, cfg)
    min_px = 0.5 * cfg.min_plane_points
    planar_px = np.bincount(comp, weights=cells.count * cells.planar)
    big = np.flatnonzero(planar_px >= min_px)
    regions: list[_Region] = []
    if len(big) == 0:
        return regions
    # Candidate planes = big components of linked cells, fit and checked all at once.
    group_of = np.full(len(planar_px), -1)
    group_of[big] = np.arange(len(big))
    group = np.where(cells.planar, group_of[comp], -1)
    _, _, _, normal, d = _group_planes(cells, group, len(big))
    member = np.flatnonzero(group >= 0)
    g = group[member]
    cos_max = _cos_tolerance(cells.tilt_var[member], cfg)
    rms2 = _rms2_to_plane(cells, member, normal[g], d[g])
    rms_fits = rms2 <= (cfg.organized.merge_max_rms_sigmas * cells.sigma[member]) ** 2
    fits = rms_fits & (np.einsum("ki,ki->k", cells.normal[member], normal[g]) >= cos_max)
    # Chaining shows as cells off the merged plane; far cells' normals are too noisy
    # (depth quantisation) to judge a candidate by, so they only drop single cells.
    fit_fraction = np.bincount(g, weights=rms_fits, minlength=len(big)) / np.bincount(
        g, minlength=len(big)
    )
    good = fit_fraction >= 0.9
    # Good candidates: refit on the cells that fit (a few stragglers leave).
    kept = np.full(len(group), -1)
    keep = fits & good[g]
    kept[member[keep]] = g[keep]
    count, centroid, scatter, normal, d = _group_planes(cells, kept, len(big))
    order = np.argsort(kept, kind="stable")
    bounds = np.searchsorted(kept[order], np.arange(len(big) + 1))
    for i in np.flatnonzero(good & (count >= min_px)):
        if np.abs(normal[i]).sum() == 0:
            continue
        idx = order[bounds[i] : bounds[i + 1]]
        regions.append(_Region(idx, int(count[i]), centroid[i], scatter[i], normal[i], d[i]))
    # Chained candidates (a curved surface, a shallow bend): CAPE-style region growing.
    all_order = np.argsort(group, kind="stable")
    all_bounds = np.searchsorted(group[all_order], np.arange(len(big) + 1))
    for i in np.flatnonzero(~good):
        idx = all_order[all_bounds[i] : all_bounds[i + 1]]
        regions.extend(_grow_regions(cells, idx, degree, rows, cols, min_px, cfg))
    if cfg.organized.merge_coplanar and len(regions) > 1:
        regions = _merge_coplanar(regions, cfg, noise)
    return regions


def _merge_coplanar(
    regions: list[_Region], cfg: SegmentationConfig, noise: DepthNoiseConfig
) -> list[_Region]:
    """Merge regions whose points fit each other's plane (moments test, both ways)."""
    n = np.stack([r.normal for r in regions])
    d = np.array([r.d for r in regions])
    c = np.stack([r.centroid for r in regions])
    s = np.stack([r.scatter for r in regions])
    cnt = np.array([r.count for r in regions], dtype=np.float64)
    # rms2[i, j]: mean squared distance of region j's points to plane i
    quad = np.einsum("ia,jab,ib->ij", n, s, n) / cnt[None, :]
    off = n @ c.T + d[:, None]
    rms2 = quad + off * off
    sigma = noise.sigma_m(c[:, 2])
    fits = rms2 <= (cfg.organized.merge_max_rms_sigmas * sigma[None, :]) ** 2
    same = fits & fits.T & (n @ n.T >= math.cos(math.radians(cfg.organized.coplanar_max_angle_deg)))
    comp = dense_components_kernel(same)
    ncomp = int(comp.max()) + 1
    if ncomp == len(regions):
        return regions
    merged = []
    for k in range(ncomp):
        group = np.flatnonzero(comp == k)
        if len(group) == 1:
            merged.append(regions[group[0]])
            continue
        cells_idx = np.concatenate([regions[g].cells for g in group])
        count, centroid, scatter = merge_moments(cnt[group], c[group], s[group])
        normal, dd, _ = plane_from_moments(centroid, scatter)
        merged.append(_Region(cells_idx, count, centroid, scatter, normal, dd))
    return merged


def _neighbour_labels(cell_label: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """(C, 9) labels of each cell's 3x3 neighbourhood (-1 outside the grid); [:, 4] is own."""
    padded = np.full((rows + 2, cols + 2), -1, dtype=cell_label.dtype)
    padded[1:-1, 1:-1] = cell_label.reshape(rows, cols)
    shifts = [padded[i : i + rows, j : j + cols] for i in range(3) for j in range(3)]
    return np.stack(shifts, axis=-1).reshape(rows * cols, 9)


@dataclass
class _PixelLabels:
    """Pixel labels in cell-major layout and inliers per plane."""

    labels: np.ndarray  # (C, P) int32, -1 for no plane
    counts: np.ndarray  # (R,) inlier pixels per plane
    single: np.ndarray  # (C,) bool: the cell has exactly one candidate plane


def _assign_pixels(x, y, z, valid, cand, normals, ds, cfg, noise) -> _PixelLabels:
    """Step 5 of the module docstring. x, y, z, valid: (C, P) cell-major; cand (C, K)
    candidate labels (-1 for none); normals (R, 3), ds (R,) float32.

    A pixel is an inlier of a candidate plane when |n . p + d| <= k sigma(z); with
    several candidates (cells touching two planes) the nearest in units of sigma wins
    (`kernels.assign_pixels_kernel`).
    """
    ka = np.float32(cfg.pixel_max_distance_sigmas * noise.sigma_a_m)
    kb = np.float32(cfg.pixel_max_distance_sigmas * noise.sigma_b_per_m)
    # Unique candidate labels per cell, valid ones first.
    cu = -np.sort(-cand, axis=1)
    cu[:, 1:][cu[:, 1:] == cu[:, :-1]] = -1
    cu = -np.sort(-cu, axis=1)
    ncand = (cu >= 0).sum(axis=1)
    cu = np.ascontiguousarray(cu[:, : max(int(ncand.max()), 1)])
    labels, counts = assign_pixels_kernel(x, y, z, valid, cu, ncand, normals, ds, ka, kb)
    return _PixelLabels(labels, counts, ncand == 1)


def _segment_organized(
    cloud: np.ndarray,
    grid: _CellGrid,
    cfg: SegmentationConfig,
    noise: DepthNoiseConfig,
    depth_m: np.ndarray | None,
    outline_stride: int = OUTLINE_STRIDE,
) -> Segmentation:
    t0 = time.perf_counter()
    # Points beyond max_depth_m (a cloud made with a larger one) are invalid too.
    limit = np.float32(cfg.max_depth_m)
    x, y, z, valid = cells_from_cloud_kernel(
        cloud, grid.rows, grid.cols, grid.cell, grid.rx, grid.ry, limit
    )
    if not valid.any():
        return empty_segmentation(
            grid.height, grid.width, no_valid_reason(depth_m, cfg.max_depth_m)
        )
    t1 = time.perf_counter()
    cells = _cell_fits(x, y, z, valid, cfg, noise)
    t2 = time.perf_counter()
    regions = _find_regions(cells, grid.rows, grid.cols, cfg, noise)
    t3 = time.perf_counter()
    if not regions:
        return empty_segmentation(
            grid.height, grid.width, f"no plane with at least {cfg.min_plane_points} points"
        )
    regions.sort(key=lambda r: -r.count)
    cell_label = np.full(grid.rows * grid.cols, -1, dtype=np.int32)
    for i, region in enumerate(regions):
        cell_label[region.cells] = i
    normals = np.stack([r.normal for r in regions]).astype(np.float32)
    ds = np.array([r.d for r in regions], dtype=np.float32)
    cand = _neighbour_labels(cell_label, grid.rows, grid.cols)
    px = _assign_pixels(x, y, z, valid, cand, normals, ds, cfg, noise)
    t4 = time.perf_counter()
    order = np.argsort(-px.counts, kind="stable")
    order = order[px.counts[order] >= cfg.min_plane_points]
    if len(order) == 0:
        return empty_segmentation(
            grid.height, grid.width, f"no plane with at least {cfg.min_plane_points} points"
        )
    remap = np.full(len(regions) + 1, -1, dtype=np.int32)
    remap[order + 1] = np.arange(len(order), dtype=np.int32)
    # Inlier pixels of all planes, grouped by new plane id, in one (3, N) float64
    # buffer (rows contiguous); labels renumbered in place.
    xyz, bounds = gather_planes_kernel(x, y, z, px.labels, px.single, remap, len(order))
    labels_img = grid.to_image(px.labels)
    lab_small = labels_img[::outline_stride, ::outline_stride]
    boxes = ndimage.find_objects(lab_small + 1, max_label=len(order))
    planes = build_planes(
        xyz,
        bounds,
        lab_small,
        boxes,
        grid.pixels,
        cfg.outline_epsilon_px,
        outline_stride,
        noise,
    )
    t5 = time.perf_counter()
    log.debug(
        "organized segmentation: cloud %.2f ms, cells %.2f ms, regions %.2f ms, "
        "pixels %.2f ms, planes %.2f ms; %d planes",
        *(1e3 * v for v in (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)),
        len(planes),
    )
    return finish(planes, labels_img)
