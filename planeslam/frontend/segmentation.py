"""Plane segmentation of one organised point cloud (paper step 2).

`segment_planes(depth)` = `cloud.organized_cloud` + `segment_cloud(cloud)`; the
front end calls the two separately (its `cloud` and `planes` stages).
Two methods: `organized` (default; cell-wise fits on
the image grid merged into planes, in the spirit of PEAC/CAPE) and `msac`
(the paper's M-estimator sample consensus, plane by plane on a subsample).
Every plane is expressed in the camera frame with its normal toward the
camera (d > 0).

Depth noise model (Kinect-like, both methods): sigma(z) = a + b z^2 [m]
(`depth_sigma_a_m`, `depth_sigma_b_per_m`); every distance threshold is a
multiple of sigma at the depth where it is applied.

`organized`, step by step:
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
   within `pixel_max_distance_sigmas` sigma(z) of that plane is an inlier; in
   border and rejected cells next to planes, each pixel goes to the nearest
   candidate plane of its 3x3 cell neighbourhood within that distance. (A 5x5
   neighbourhood recovers the last pixels of a face seen as a thin wedge, but
   also lets planes claim pixels across depth edges, which hurt tracking; the
   edge ends it would fix are recovered by snapping edges to corners instead.)
6. planes with fewer than `min_plane_points` inliers are dropped; the rest
   are refit on their pixel inliers and numbered by decreasing size. All
   planes' inliers are gathered into one (3, N) float64 buffer, grouped by
   plane; `Plane.points` is a (K, 3) transposed view of its slice (no copy).

`Plane.area_m2` is the sum of per-pixel footprints on the plane,
z^2 / (fx fy |n . r|) = z^3 / (fx fy d) per inlier (r the pixel's z=1 ray).
`Plane.outline` is the outer contour of the largest connected piece of the
plane's pixel mask, traced on every 3rd pixel (cv2.findContours + cv2.approxPolyDP with
`outline_epsilon_px`), its vertices' rays intersected with the plane.
`Plane.covariance` comes from the least-squares fit (see `plane_fit`), in the
tangent basis of `plane_fit.tangent_basis` (= gtsam.Unit3(n).basis()).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.errors import ConfigError, GeometryError
from planeslam.core.plane_fit import (
    merge_moments,
    moments_of,
    moments_of_columns,
    plane_covariance,
    plane_from_moments,
    smallest_eigh3,
)
from planeslam.frontend.cloud import back_project
from planeslam.frontend.config import SegmentationConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plane:
    """One plane found in one frame, camera frame, n . x + d = 0, d > 0."""

    id: int
    """Index in `Segmentation.planes` and the value of its pixels in `Segmentation.labels`."""
    normal: np.ndarray
    """(3,) unit normal pointing toward the camera."""
    d: float
    """Offset [m] (distance from the camera centre to the plane)."""
    points: np.ndarray = field(repr=False)
    """(K, 3) float64 inlier points [m]."""
    centroid: np.ndarray
    """(3,) mean of the inliers [m]."""
    covariance: np.ndarray = field(repr=False)
    """(3, 3) covariance of the fit in OrientedPlane3 local coordinates
    (2 tangent-space normal components [rad], then d [m])."""
    scatter: np.ndarray = field(repr=False)
    """(3, 3) sum of outer products of centred inliers [m^2]: with `centroid` and
    `num_points` these are the sufficient statistics to refit or merge planes."""
    num_points: int
    """Number of inliers."""
    area_m2: float
    """Area of the plane's visible region [m^2]."""
    outline: np.ndarray = field(repr=False)
    """(M, 3) closed polygon on the plane bounding its region [m] (M >= 3)."""


@dataclass(frozen=True)
class Segmentation:
    """The planes of one frame and which pixels belong to them."""

    planes: list[Plane]
    labels: np.ndarray = field(repr=False)
    """(H, W) int32: plane id per pixel, -1 for pixels on no plane."""
    reason: str = ""
    """Why the result is empty or partial (no valid depth, ...); '' when all went well."""


# ----------------------------------------------------------------------------------------
# Camera geometry in cell-major layout, cached per camera.


@dataclass(frozen=True, eq=False)
class _Grid:
    """Pixel rays of one camera, in image layout and in cell-major layout."""

    height: int
    width: int
    cell: int
    rows: int
    cols: int
    rx_img: np.ndarray  # (H, W) float32 x of the z=1 rays
    ry_img: np.ndarray  # (H, W) float32 y of the z=1 rays
    rays: np.ndarray  # (H, W, 3) float64 z=1 rays
    rays32: np.ndarray  # (H, W, 3) float32 z=1 rays (back-projection)
    rx: np.ndarray  # (C, P) float32, cell-major, zero in padding
    ry: np.ndarray  # (C, P) float32
    fx: float
    fy: float

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


_GRID_CACHE: dict[tuple, tuple[object, _Grid]] = {}


def _grid_for(camera_or_rays: CameraConfig | PixelRays, cell: int) -> _Grid:
    """The cached `_Grid` of a camera (or of a PixelRays object) for this cell size."""
    if isinstance(camera_or_rays, CameraConfig):
        key: tuple = ("camera", camera_or_rays, cell)
    elif isinstance(camera_or_rays, PixelRays):
        key = ("rays", id(camera_or_rays), cell)
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
    grid = _Grid(
        height=height,
        width=width,
        cell=cell,
        rows=-(-height // cell),
        cols=-(-width // cell),
        rx_img=np.ascontiguousarray(rays[:, :, 0], dtype=np.float32),
        ry_img=np.ascontiguousarray(rays[:, :, 1], dtype=np.float32),
        rays=rays,
        rays32=np.ascontiguousarray(rays, dtype=np.float32),
        rx=np.empty(0),
        ry=np.empty(0),
        fx=fx,
        fy=fy,
    )
    object.__setattr__(grid, "rx", grid.to_cells(grid.rx_img))
    object.__setattr__(grid, "ry", grid.to_cells(grid.ry_img))
    if len(_GRID_CACHE) >= 8:
        _GRID_CACHE.clear()
    _GRID_CACHE[key] = (camera_or_rays, grid)  # holding the object keeps its id unique
    return grid


# ----------------------------------------------------------------------------------------
# Public entry point.


def segment_planes(
    depth_m: np.ndarray,
    camera_or_rays: CameraConfig | PixelRays,
    config: SegmentationConfig | None = None,
    rng: np.random.Generator | None = None,
) -> Segmentation:
    """Find the planes of one depth image (paper step 2).

    depth_m: (H, W) depth along the optical axis [m]; 0, negative, NaN, inf and
    values beyond `config.max_depth_m` are invalid. camera_or_rays: the camera
    (rays cached per camera) or its precomputed `PixelRays`. rng: used by
    'msac' only (default: seeded with 0). Returns planes in the camera frame,
    ids 0..N-1 by decreasing number of inliers, and the (H, W) int32 label
    image. A frame without valid depth or without planes gives an empty
    result with `reason` set. Raises GeometryError when the depth shape does
    not match the camera. Same as `organized_cloud` then `segment_cloud`.
    """
    cfg = config or SegmentationConfig()
    grid = _grid_for(camera_or_rays, cfg.cell_size_px)
    cloud = back_project(depth_m, grid.rays32, cfg.max_depth_m)
    return segment_cloud(cloud, camera_or_rays, cfg, rng, depth_m=depth_m)


def segment_cloud(
    cloud: np.ndarray,
    camera_or_rays: CameraConfig | PixelRays,
    config: SegmentationConfig | None = None,
    rng: np.random.Generator | None = None,
    depth_m: np.ndarray | None = None,
) -> Segmentation:
    """`segment_planes` on a precomputed organised cloud (the front end's `cloud` stage).

    cloud: (H, W, 3) float32 camera-frame points [m] from `cloud.organized_cloud`
    (invalid pixels all zero; z > 0 is the validity mask); points beyond
    `config.max_depth_m` are ignored. depth_m: the (H, W) depth image it came
    from, used only to say why a frame has no valid depth (NaN, <= 0, too far).
    """
    cfg = config or SegmentationConfig()
    grid = _grid_for(camera_or_rays, cfg.cell_size_px)
    if np.shape(cloud) != (grid.height, grid.width, 3):
        raise GeometryError(
            f"organised cloud has shape {tuple(np.shape(cloud))}, expected "
            f"({grid.height}, {grid.width}, 3) for this camera: use cloud.organized_cloud"
        )
    cloud = np.asarray(cloud, dtype=np.float32)
    if cfg.method == "msac":
        rng = rng if rng is not None else np.random.default_rng(0)
        return _segment_msac(cloud, grid, cfg, rng, depth_m)
    k = cfg.pixel_stride
    if k == 1:
        return _segment_organized(cloud, grid, cfg, depth_m)
    sub_cfg = replace(
        cfg,
        cell_size_px=cfg.cell_size_px // k,
        min_plane_points=max(3, -(-cfg.min_plane_points // (k * k))),
        pixel_stride=1,
    )
    sub_grid = _grid_for(_strided_rays(camera_or_rays, grid, k), sub_cfg.cell_size_px)
    outline_stride = -(-_OUTLINE_STRIDE // k)  # about _OUTLINE_STRIDE full-image pixels
    seg = _segment_organized(cloud[::k, ::k], sub_grid, sub_cfg, depth_m, outline_stride)
    labels = np.repeat(np.repeat(seg.labels, k, axis=0), k, axis=1)
    return replace(seg, labels=np.ascontiguousarray(labels[: grid.height, : grid.width]))


_STRIDED_RAYS: dict[tuple[int, int], tuple[object, PixelRays]] = {}


def _strided_rays(camera_or_rays: CameraConfig | PixelRays, grid: _Grid, k: int) -> PixelRays:
    """The rays of every k-th pixel of every k-th row, one PixelRays per camera (cached)."""
    key = (id(camera_or_rays), k)
    hit = _STRIDED_RAYS.get(key)
    if hit is not None and hit[0] is camera_or_rays:
        return hit[1]
    if len(_STRIDED_RAYS) >= 8:
        _STRIDED_RAYS.clear()
    rays = PixelRays(rays=np.ascontiguousarray(grid.rays[::k, ::k]))
    _STRIDED_RAYS[key] = (camera_or_rays, rays)
    return rays


def _empty(grid: _Grid, reason: str) -> Segmentation:
    log.debug("segmentation empty: %s", reason)
    return Segmentation(
        planes=[], labels=np.full((grid.height, grid.width), -1, dtype=np.int32), reason=reason
    )


def _no_valid_reason(depth: np.ndarray | None, cfg: SegmentationConfig) -> str:
    if depth is None:
        return f"no valid depth: no point with 0 < z <= max_depth_m={cfg.max_depth_m} m"
    depth = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(depth)
    if not finite.any():
        return "no valid depth: every pixel is NaN or infinite"
    if not (depth[finite] > 0).any():
        return "no valid depth: every finite pixel is <= 0"
    return f"no valid depth: every positive pixel is beyond max_depth_m={cfg.max_depth_m} m"


# ----------------------------------------------------------------------------------------
# Organized (cell grid) method.


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


def _cell_fits(x, y, z, valid, cfg: SegmentationConfig) -> _Cells:
    """Moments and least-squares planes of every cell: x, y, z, valid (C, P)."""
    count = np.count_nonzero(valid, axis=1)
    usable = count >= cfg.min_cell_valid_fraction * x.shape[1]
    n_safe = np.maximum(count, 1).astype(np.float32)
    mean32 = np.stack([x.sum(1), y.sum(1), z.sum(1)], axis=1) / n_safe[:, None]
    # Centre before the products: float32 cannot hold x^2 sums to noise precision.
    # Invalid pixels are (0, 0, 0), so each adds exactly mean_a * mean_b to the sum of
    # products: subtract that instead of masking (exact for full cells, within a few
    # % of the residual scatter for half-empty ones).
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
    lam_min, lam_mid, normal = smallest_eigh3(scatter)
    d = -np.einsum("ij,ij->i", normal, mean)
    flip = d < 0
    normal[flip] *= -1.0
    d[flip] *= -1.0
    sigma = cfg.sigma_m(mean[:, 2])
    rms2 = np.maximum(lam_min, 0.0) / np.maximum(count, 1)
    # d / |mean| is the cosine of the incidence angle at the cell
    cos_inc = d / np.maximum(np.linalg.norm(mean, axis=1), 1e-9)
    planar = (
        usable
        & (rms2 <= (cfg.cell_max_rms_sigmas * sigma) ** 2)
        & (cos_inc >= math.cos(math.radians(cfg.max_incidence_deg)))
    )
    # least-squares slope variance along the cell's shorter in-plane axis
    tilt_var = sigma**2 / np.maximum(lam_mid, 1e-12)
    return _Cells(count, mean, scatter, normal, d, sigma, planar, tilt_var)


def _cos_tolerance(tilt_var: np.ndarray, cfg: SegmentationConfig) -> np.ndarray:
    """Cosine of the largest normal angle accepted between cells or cell and plane:
    merge_max_angle_deg, widened to 3 standard deviations of the cells' normal noise
    (far cells are only a few cm wide), at most 45 deg."""
    angle = np.clip(3.0 * np.sqrt(tilt_var), math.radians(cfg.merge_max_angle_deg), math.pi / 4)
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


def _region_of(cells: _Cells, idx: np.ndarray) -> _Region | None:
    count, centroid, scatter = merge_moments(cells.count[idx], cells.mean[idx], cells.scatter[idx])
    try:
        normal, d, _ = plane_from_moments(centroid, scatter)
    except GeometryError:
        return None
    return _Region(idx, count, centroid, scatter, normal, d)


def _fitting(
    cells: _Cells, idx: np.ndarray, region: _Region, cfg: SegmentationConfig
) -> np.ndarray:
    """(K,) bool: cells `idx` fit the region's plane (RMS and angle tests)."""
    rms2 = _rms2_to_plane(cells, idx, region.normal, np.float64(region.d))
    cos_max = _cos_tolerance(cells.tilt_var[idx], cfg)
    return (rms2 <= (cfg.merge_max_rms_sigmas * cells.sigma[idx]) ** 2) & (
        cells.normal[idx] @ region.normal >= cos_max
    )


def _link_cells(cells: _Cells, rows: int, cols: int, cfg: SegmentationConfig):
    """Links between 4-neighbour planar cells that fit each other's planes.

    Returns (component label per cell (C,), links per cell (C,))."""
    grid = np.arange(rows * cols).reshape(rows, cols)
    a = np.concatenate([grid[:, :-1].ravel(), grid[:-1, :].ravel()])
    b = np.concatenate([grid[:, 1:].ravel(), grid[1:, :].ravel()])
    both = cells.planar[a] & cells.planar[b]
    a, b = a[both], b[both]
    cos_max = _cos_tolerance(cells.tilt_var[a] + cells.tilt_var[b], cfg)
    ok = np.einsum("ki,ki->k", cells.normal[a], cells.normal[b]) >= cos_max
    a, b = a[ok], b[ok]
    k2 = cfg.merge_max_rms_sigmas**2
    ok = (_rms2_to_plane(cells, b, cells.normal[a], cells.d[a]) <= k2 * cells.sigma[b] ** 2) & (
        _rms2_to_plane(cells, a, cells.normal[b], cells.d[b]) <= k2 * cells.sigma[a] ** 2
    )
    a, b = a[ok], b[ok]
    n = rows * cols
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    degree = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    return comp, degree


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
    over the connected cells that fit its current plane, refit after each growth."""
    remaining = np.zeros(rows * cols, dtype=bool)
    remaining[member] = True
    regions: list[_Region] = []
    for _ in range(64):
        cand = np.flatnonzero(remaining)
        if cells.count[cand].sum() < min_px:
            break
        seed = int(cand[np.argmax(degree[cand])])
        region = _region_of(cells, np.array([seed]))
        grown = np.array([seed])
        for _ in range(4):
            if region is None:
                break
            fit = np.zeros(rows * cols, dtype=bool)
            fit[cand] = _fitting(cells, cand, region, cfg)
            fit[seed] = True
            comp, _ = ndimage.label(fit.reshape(rows, cols))
            new = np.flatnonzero(comp.ravel() == comp.ravel()[seed])
            if len(new) == len(grown):
                break
            grown = new
            region = _region_of(cells, grown)
        remaining[grown] = False
        if region is not None and region.count >= min_px:
            regions.append(region)
    return regions


def _group_planes(cells: _Cells, group: np.ndarray, n_groups: int):
    """Merged moments and planes of cell groups, all groups at once.

    group: (C,) group index per cell, -1 for none. Returns (count (G,), centroid (G, 3),
    scatter (G, 3, 3), normal (G, 3) toward the camera, d (G,))."""
    member = group >= 0
    g = group[member]
    w = cells.count[member].astype(np.float64)
    mean = cells.mean[member]
    count = np.bincount(g, weights=w, minlength=n_groups)
    first = np.stack(
        [np.bincount(g, weights=w * mean[:, i], minlength=n_groups) for i in range(3)], 1
    )
    raw = cells.scatter[member] + w[:, None, None] * mean[:, :, None] * mean[:, None, :]
    second = np.empty((n_groups, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            second[:, i, j] = second[:, j, i] = np.bincount(
                g, weights=raw[:, i, j], minlength=n_groups
            )
    safe = np.maximum(count, 1.0)
    centroid = first / safe[:, None]
    scatter = second - safe[:, None, None] * centroid[:, :, None] * centroid[:, None, :]
    _, _, normal = smallest_eigh3(scatter)
    d = -np.einsum("gi,gi->g", normal, centroid)
    flip = d < 0
    normal[flip] *= -1.0
    d[flip] *= -1.0
    return count, centroid, scatter, normal, d


def _find_regions(cells: _Cells, rows: int, cols: int, cfg: SegmentationConfig) -> list[_Region]:
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
    rms_fits = rms2 <= (cfg.merge_max_rms_sigmas * cells.sigma[member]) ** 2
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
    if cfg.merge_coplanar and len(regions) > 1:
        regions = _merge_coplanar(regions, cfg)
    return regions


def _merge_coplanar(regions: list[_Region], cfg: SegmentationConfig) -> list[_Region]:
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
    sigma = cfg.sigma_m(c[:, 2])
    fits = rms2 <= (cfg.merge_max_rms_sigmas * sigma[None, :]) ** 2
    same = fits & fits.T & (n @ n.T >= math.cos(math.radians(cfg.coplanar_max_angle_deg)))
    ncomp, comp = connected_components(same, directed=False)
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
    """Pixel labels in a permuted cell layout: first the cells whose only candidate is
    plane i (rows starts[i]:starts[i+1]), then the cells with several candidates."""

    perm: np.ndarray  # (C',) cell index of each row
    starts: np.ndarray  # (R + 1,) row bounds of each plane's single-candidate cells
    x: np.ndarray  # (C', P) float32 [m]
    y: np.ndarray
    z: np.ndarray
    labels: np.ndarray  # (C', P) int32, -1 for no plane
    counts: np.ndarray  # (R,) inlier pixels per plane


def _assign_pixels(x, y, z, valid, cand, normals, ds, cfg) -> _PixelLabels:
    """Step 5 of the module docstring. x, y, z, valid: (C, P) cell-major; cand (C, K)
    candidate labels (-1 for none).

    A pixel is an inlier of a candidate plane when |n . p + d| <= k sigma(z); with
    several candidates (cells touching two planes) the nearest in units of sigma wins.
    """
    n_regions = len(ds)
    ka = np.float32(cfg.pixel_max_distance_sigmas * cfg.depth_sigma_a_m)
    kb = np.float32(cfg.pixel_max_distance_sigmas * cfg.depth_sigma_b_per_m)
    # Unique candidate labels per cell, valid ones first.
    cu = -np.sort(-cand, axis=1)
    cu[:, 1:][cu[:, 1:] == cu[:, :-1]] = -1
    cu = -np.sort(-cu, axis=1)
    ncand = (cu >= 0).sum(axis=1)
    cu = cu[:, : max(int(ncand.max()), 1)]
    single = np.flatnonzero(ncand == 1)
    single = single[np.argsort(cu[single, 0], kind="stable")]
    starts = np.searchsorted(cu[single, 0], np.arange(n_regions + 1))
    multi = np.flatnonzero(ncand > 1)
    perm = np.concatenate([single, multi])
    xp, yp, zp, vp = x[perm], y[perm], z[perm], valid[perm]
    # |r| <= k sigma(z)  <=>  |r| / (ka + kb z^2) <= 1; tol holds the denominator.
    tol = zp * zp
    tol *= kb
    tol += ka
    tol[~vp] = -1.0  # invalid pixels fit no plane
    labels = np.full(xp.shape, -1, dtype=np.int32)
    counts = np.zeros(n_regions, dtype=np.int64)
    for i in range(n_regions):
        a, b = starts[i], starts[i + 1]
        if a == b:
            continue
        n = normals[i]
        r = xp[a:b] * n[0]
        r += yp[a:b] * n[1]
        r += zp[a:b] * n[2]
        r += ds[i]
        ok = np.abs(r, out=r) <= tol[a:b]
        np.copyto(labels[a:b], np.int32(i), where=ok)
        counts[i] = np.count_nonzero(ok)
    nb = len(single)
    if len(multi):
        cb = cu[multi]
        xb, yb, zb, tb = xp[nb:], yp[nb:], zp[nb:], tol[nb:]
        best = np.full(xb.shape, np.float32(1.0))
        best_label = np.full(xb.shape, -1, dtype=np.int32)

        def residual(ls: np.ndarray) -> np.ndarray:
            ls_safe = np.maximum(ls, 0)
            n = normals[ls_safe]
            r = xb * n[:, 0:1]
            r += yb * n[:, 1:2]
            r += zb * n[:, 2:3]
            r += ds[ls_safe][:, None]
            r = np.abs(r, out=r)
            r /= tb  # invalid pixels: tb = -1, never better
            return r

        for slot in range(cb.shape[1]):
            ls = cb[:, slot]
            e = residual(ls)
            better = (e <= best) & (e >= 0) & (ls >= 0)[:, None]
            np.copyto(best, e, where=better)
            np.copyto(best_label, ls[:, None], where=better)
        labels[nb:] = best_label
        counts += np.bincount(best_label.ravel() + 1, minlength=n_regions + 1)[1:]
    return _PixelLabels(perm, starts, xp, yp, zp, labels, counts)


def _segment_organized(
    cloud: np.ndarray,
    grid: _Grid,
    cfg: SegmentationConfig,
    depth_m: np.ndarray | None,
    outline_stride: int = 3,
) -> Segmentation:
    t0 = time.perf_counter()
    z = grid.to_cells(cloud[..., 2])
    valid = z > 0
    far = z > cfg.max_depth_m
    if far.any():  # a cloud made with a larger max_depth_m
        valid &= ~far
        z = np.where(valid, z, np.float32(0.0))
    if not valid.any():
        return _empty(grid, _no_valid_reason(depth_m, cfg))
    x = z * grid.rx
    y = z * grid.ry
    t1 = time.perf_counter()
    cells = _cell_fits(x, y, z, valid, cfg)
    t2 = time.perf_counter()
    regions = _find_regions(cells, grid.rows, grid.cols, cfg)
    t3 = time.perf_counter()
    if not regions:
        return _empty(grid, f"no plane with at least {cfg.min_plane_points} points")
    regions.sort(key=lambda r: -r.count)
    cell_label = np.full(grid.rows * grid.cols, -1, dtype=np.int32)
    for i, region in enumerate(regions):
        cell_label[region.cells] = i
    normals = np.stack([r.normal for r in regions]).astype(np.float32)
    ds = np.array([r.d for r in regions], dtype=np.float32)
    cand = _neighbour_labels(cell_label, grid.rows, grid.cols)
    px = _assign_pixels(x, y, z, valid, cand, normals, ds, cfg)
    t4 = time.perf_counter()
    order = np.argsort(-px.counts, kind="stable")
    order = order[px.counts[order] >= cfg.min_plane_points]
    if len(order) == 0:
        return _empty(grid, f"no plane with at least {cfg.min_plane_points} points")
    n_old = len(regions)
    remap = np.full(n_old + 1, -1, dtype=np.int32)
    remap[order + 1] = np.arange(len(order), dtype=np.int32)
    labels = px.labels
    if len(order) != n_old or np.any(order != np.arange(n_old)):
        labels = remap[labels + 1]
    cell_labels = np.full((grid.rows * grid.cols, grid.cell**2), -1, dtype=np.int32)
    cell_labels[px.perm] = labels
    labels_img = grid.to_image(cell_labels)
    # Inlier pixels of all planes, grouped by new plane id, in one (3, N) float64
    # buffer: single-candidate rows are already grouped by region (boolean masks
    # of contiguous blocks), pixels of multi-candidate rows are sorted by label.
    psz = grid.cell**2
    nb = px.starts[-1]
    flat = labels.reshape(-1)
    single_ok = flat[: nb * psz] >= 0
    multi_flat = flat[nb * psz :]
    multi_sel = np.flatnonzero(multi_flat >= 0)
    multi_lab = multi_flat[multi_sel]
    multi_sel = multi_sel[np.argsort(multi_lab.astype(np.int16), kind="stable")] + nb * psz
    multi_lo = np.searchsorted(np.sort(multi_lab), np.arange(len(order) + 1))
    blocks = [(px.starts[o] * psz, px.starts[o + 1] * psz) for o in order]
    n_single = [np.count_nonzero(single_ok[a:b]) for a, b in blocks]
    n_multi = np.diff(multi_lo)
    bounds = np.concatenate([[0], np.cumsum(np.add(n_single, n_multi))])
    xyz = np.empty((3, bounds[-1]))  # float64 rows: contiguous per-plane columns
    for k, coord in enumerate((px.x, px.y, px.z)):
        flat_k = coord.reshape(-1)
        for i, (a, b) in enumerate(blocks):
            lo, mid = bounds[i], bounds[i] + n_single[i]
            xyz[k, lo:mid] = flat_k[a:b][single_ok[a:b]]
            xyz[k, mid : bounds[i + 1]] = flat_k[multi_sel[multi_lo[i] : multi_lo[i + 1]]]
    lab_small = labels_img[::outline_stride, ::outline_stride]
    boxes = ndimage.find_objects(lab_small + 1, max_label=len(order))
    planes = []
    for new_id in range(len(order)):
        a, b = bounds[new_id], bounds[new_id + 1]
        box = boxes[new_id]
        plane = _build_plane(new_id, xyz[:, a:b], lab_small, box, grid, cfg, outline_stride)
        if plane is not None:
            planes.append(plane)
    t5 = time.perf_counter()
    log.debug(
        "organized segmentation: cloud %.2f ms, cells %.2f ms, regions %.2f ms, "
        "pixels %.2f ms, planes %.2f ms; %d planes",
        *(1e3 * v for v in (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)),
        len(planes),
    )
    return _finish(planes, labels_img)


def _finish(planes: list[Plane], labels_img: np.ndarray) -> Segmentation:
    """Renumber if a degenerate plane was skipped (ids stay 0..N-1 by decreasing size)."""
    if all(p.id == i for i, p in enumerate(planes)):
        return Segmentation(planes=planes, labels=labels_img)
    remap = np.full(int(labels_img.max()) + 2, -1, dtype=np.int32)
    fixed = []
    for i, p in enumerate(planes):
        remap[p.id + 1] = i
        fixed.append(Plane(**{**p.__dict__, "id": i}))
    return Segmentation(planes=fixed, labels=remap[labels_img + 1])


# ----------------------------------------------------------------------------------------
# Plane outputs shared by both methods.


def _build_plane(
    plane_id: int,
    xyz: np.ndarray,
    labels_small: np.ndarray,
    box: tuple[slice, slice] | None,
    grid: _Grid,
    cfg: SegmentationConfig,
    outline_stride: int = 3,
) -> Plane | None:
    """Refit a plane on its inliers `xyz` (3, K) float64 (rows contiguous) and derive
    covariance, area, outline; `Plane.points` is the (K, 3) transposed view of `xyz`.

    `labels_small` is the label image strided by `outline_stride`, `box` the
    (rows, cols) slices bounding the plane in it (None: not in it). None when the
    points are degenerate (collinear)."""
    try:
        count, centroid, scatter = moments_of_columns(xyz[0], xyz[1], xyz[2])
        normal, d, rss = plane_from_moments(centroid, scatter)
        covariance = plane_covariance(normal, centroid, scatter, count, rss)
        outline = _outline(plane_id, normal, d, labels_small, box, grid, cfg, outline_stride)
    except GeometryError as exc:
        log.debug("plane %d skipped: %s", plane_id, exc)
        return None
    z = xyz[2]
    area = float((z * z) @ z) / (grid.fx * grid.fy * d)
    return Plane(
        id=plane_id,
        normal=normal,
        d=d,
        points=xyz.T,
        centroid=centroid,
        covariance=covariance,
        scatter=scatter,
        num_points=count,
        area_m2=area,
        outline=outline,
    )


_OUTLINE_STRIDE = 3


def _outline(
    plane_id, normal, d, labels_small, box, grid: _Grid, cfg, stride: int = 3
) -> np.ndarray:
    """(M, 3) outline on the plane: outer contour of the largest piece of its mask.

    The contour is traced on every `stride`-th pixel of every such row
    (`labels_small`): cheap, and finer than the polygon tolerance
    `outline_epsilon_px` needs. `box`: (rows, cols) slices of `labels_small`."""
    s = stride
    if box is None:
        raise GeometryError(f"plane {plane_id} has no pixel on the outline grid")
    v0, u0 = box[0].start, box[1].start
    mask = (labels_small[box] == plane_id).view(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        raise GeometryError(f"plane {plane_id} has no pixels in its bounding box {box}")
    contour = max(contours, key=cv2.contourArea)
    poly = cv2.approxPolyDP(contour, cfg.outline_epsilon_px / s, True)
    poly = poly.reshape(-1, 2)
    if len(poly) < 3:
        poly = np.round(cv2.boxPoints(cv2.minAreaRect(contour))).astype(np.int64)
    u, v = poly[:, 0] + u0, poly[:, 1] + v0
    # A region on the last sampled row / column reaches the image border.
    last_v, last_u = labels_small.shape[0] - 1, labels_small.shape[1] - 1
    u = np.where(u == last_u, grid.width - 1, np.clip(s * u, 0, grid.width - 1))
    v = np.where(v == last_v, grid.height - 1, np.clip(s * v, 0, grid.height - 1))
    rays = grid.rays[v, u]
    along = rays @ normal
    along = np.where(np.abs(along) > 1e-9, along, -1e-9)
    return rays * (-d / along)[:, None]


# ----------------------------------------------------------------------------------------
# MSAC (the paper's method).


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
    grid: _Grid,
    cfg: SegmentationConfig,
    rng: np.random.Generator,
    depth_m: np.ndarray | None,
) -> Segmentation:
    """Plane by plane MSAC (Torr & Zisserman truncated quadratic cost) on a subsample.

    Each round: draw `msac_hypotheses` triplets at once (first point from the
    remaining subsample, the two others among valid pixels within
    `msac_local_radius_px`), score them all on `msac_score_points` remaining points
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
        return _empty(grid, _no_valid_reason(depth_m, cfg))
    x, y, z = (np.where(valid, cloud[..., k], np.float32(0.0)) for k in range(3))
    xyz_flat = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)  # (H*W, 3) float32
    k = cfg.pixel_max_distance_sigmas
    n_sub = min(cfg.msac_sample_points, len(valid_idx))
    sub = rng.choice(valid_idx, size=n_sub, replace=False)
    pts = xyz_flat[sub].astype(np.float64)
    thr = k * cfg.sigma_m(pts[:, 2])
    scale = len(valid_idx) / n_sub
    min_sub = cfg.min_plane_points / scale
    width, height = grid.width, grid.height
    radius = cfg.msac_local_radius_px
    cos_inc = math.cos(math.radians(cfg.max_incidence_deg))
    remaining = np.ones(n_sub, dtype=bool)
    found_n: list[np.ndarray] = []
    found_d: list[float] = []
    for _ in range(cfg.max_planes):
        rem = np.flatnonzero(remaining)
        if len(rem) < max(min_sub, 3):
            break
        hyp = cfg.msac_hypotheses
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
            near = dist < (k * cfg.sigma_m(p23[:, :, 2]))[..., None]
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
        score_idx = rem[rng.integers(len(rem), size=min(cfg.msac_score_points, len(rem)))]
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
        return _empty(grid, f"no plane with at least {cfg.min_plane_points} points")
    # Every valid pixel to its nearest plane within T(z) (normalised distance e < 1).
    inv_tol = (1.0 / (k * cfg.sigma_m(z))).astype(np.float32)
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
        return _empty(grid, f"no plane with at least {cfg.min_plane_points} points")
    remap = np.full(len(found_n) + 1, -1, dtype=np.int32)
    remap[order + 1] = np.arange(len(order), dtype=np.int32)
    labels = remap[labels + 1]
    planes = []
    lab_small = labels[::_OUTLINE_STRIDE, ::_OUTLINE_STRIDE]
    boxes = ndimage.find_objects(lab_small + 1, max_label=len(order))
    for new_id in range(len(order)):
        pix = np.flatnonzero(labels == new_id)
        xyz = np.stack([c.ravel()[pix] for c in (x, y, z)]).astype(np.float64)
        plane = _build_plane(new_id, xyz, lab_small, boxes[new_id], grid, cfg, _OUTLINE_STRIDE)
        if plane is not None:
            planes.append(plane)
    return _finish(planes, labels)
