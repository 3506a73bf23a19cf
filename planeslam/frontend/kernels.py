"""Compiled (numba) loops of the front end's per-pixel work: back-projection, the
organised segmentation's pixel assignment and the gathering of each plane's inliers,
the real intersections' search for edge points, and the voxel keys of a keyframe's
sampled points (the fused-cloud figure, `mapping.sparse_cloud.FusedCloudSize`).

Each kernel does in one pass over the pixels what numpy did in several passes and
temporary arrays, with the same float32 operations in the same order (no fast-math,
so no fused multiply-adds the compiler chooses): the results are identical to the
numpy code they replace, bit for bit. The one deliberate fused multiply-add is
`_dot3`, which computes a 3-vector dot product as OpenBLAS's dgemm kernels do on
every x86-64 CPU with FMA (Haswell and later, Zen): the intersections' `matrix @
points` products and the keyframe points moved by their pose, reproduced bit for bit
without BLAS. Compiled once per machine (`cache=True` keeps the machine code beside the
module, or in numba's user cache when that is not writable).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planeslam.frontend.cell_kernels import warm_up_cell_kernels
from planeslam.frontend.fused import fma as _fma
from planeslam.frontend.plane_kernels import warm_up_plane_kernels


@njit(cache=True, nogil=True)
def back_project_kernel(depth: np.ndarray, rays: np.ndarray, limit: np.float32) -> np.ndarray:
    """(H, W) float32 depth [m], (H, W, 3) float32 z=1 rays, float32 limit [m] -> (H, W, 3)
    float32 points; a depth that is NaN, <= 0 or > limit gives (0, 0, 0)."""
    height, width = depth.shape
    out = np.empty((height, width, 3), dtype=np.float32)
    zero = np.float32(0.0)
    for v in range(height):
        for u in range(width):
            z = depth[v, u]
            if not (z > zero and z <= limit):
                z = zero
            out[v, u, 0] = rays[v, u, 0] * z
            out[v, u, 1] = rays[v, u, 1] * z
            out[v, u, 2] = rays[v, u, 2] * z
    return out


@njit(cache=True, nogil=True)
def assign_pixels_kernel(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    valid: np.ndarray,
    candidates: np.ndarray,
    ncand: np.ndarray,
    normals: np.ndarray,
    ds: np.ndarray,
    ka: np.float32,
    kb: np.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel labels of the organised segmentation (its step 5), cell-major.

    x, y, z (C, P) float32 [m], valid (C, P) bool; candidates (C, K) int candidate
    planes of each cell, valid ones first, ncand (C,) how many; normals (R, 3) and ds
    (R,) float32 planes. A pixel is an inlier of plane i when |n.p + d| <= ka + kb z^2;
    with several candidates the smallest |n.p + d| / (ka + kb z^2) wins (the first on a
    tie). Returns labels (C, P) int32 (-1 for none) and inliers per plane (R,) int64."""
    cells, npix = x.shape
    labels = np.full((cells, npix), -1, dtype=np.int32)
    counts = np.zeros(len(ds), dtype=np.int64)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for c in range(cells):
        k = ncand[c]
        if k == 0:
            continue
        if k == 1:
            i = candidates[c, 0]
            n0, n1, n2, d = normals[i, 0], normals[i, 1], normals[i, 2], ds[i]
            for p in range(npix):
                if not valid[c, p]:
                    continue
                zz = z[c, p]
                tol = zz * zz
                tol = tol * kb
                tol = tol + ka
                r = x[c, p] * n0
                r = r + y[c, p] * n1
                r = r + zz * n2
                r = r + d
                if abs(r) <= tol:
                    labels[c, p] = i
                    counts[i] += 1
            continue
        for p in range(npix):
            zz = z[c, p]
            tol = zz * zz
            tol = tol * kb
            tol = tol + ka
            if not valid[c, p]:
                tol = -one  # never better (as the numpy code: e = -|r| < 0)
            best = one
            best_label = -1
            for s in range(k):
                i = candidates[c, s]
                r = x[c, p] * normals[i, 0]
                r = r + y[c, p] * normals[i, 1]
                r = r + zz * normals[i, 2]
                r = r + ds[i]
                e = abs(r) / tol
                if e <= best and e >= zero:
                    best = e
                    best_label = i
            if best_label >= 0:
                labels[c, p] = best_label
                counts[best_label] += 1
    return labels, counts


@njit(cache=True, nogil=True)
def gather_planes_kernel(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    labels: np.ndarray,
    single: np.ndarray,
    remap: np.ndarray,
    n_planes: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Renumber labels (C, P) in place by `remap` (old label + 1 -> new, -1 to drop) and
    gather every plane's inliers into one (3, N) float64 buffer, grouped by new label.

    Within a plane: first the pixels of cells with one candidate (`single` (C,) bool),
    then those of cells with several, each part in cell order and pixel order within
    a cell. Returns (xyz (3, N), bounds (n_planes + 1,): plane i is xyz[:, b[i]:b[i+1]])."""
    cells, npix = labels.shape
    n_single = np.zeros(n_planes, dtype=np.int64)
    n_multi = np.zeros(n_planes, dtype=np.int64)
    for c in range(cells):
        for p in range(npix):
            new = remap[labels[c, p] + 1]
            labels[c, p] = new
            if new >= 0:
                if single[c]:
                    n_single[new] += 1
                else:
                    n_multi[new] += 1
    bounds = np.zeros(n_planes + 1, dtype=np.int64)
    for i in range(n_planes):
        bounds[i + 1] = bounds[i] + n_single[i] + n_multi[i]
    at_single = bounds[:-1].copy()
    at_multi = bounds[:-1] + n_single
    xyz = np.empty((3, bounds[n_planes]), dtype=np.float64)
    for c in range(cells):
        at = at_single if single[c] else at_multi
        for p in range(npix):
            i = labels[c, p]
            if i >= 0:
                k = at[i]
                xyz[0, k] = x[c, p]
                xyz[1, k] = y[c, p]
                xyz[2, k] = z[c, p]
                at[i] = k + 1
    return xyz, bounds


@njit(cache=True, nogil=True)
def cells_from_cloud_kernel(
    cloud: np.ndarray, rows: int, cols: int, cell: int, rx: np.ndarray, ry: np.ndarray, limit: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An (H, W, 3) float32 organised cloud in cell-major layout: cells of cell x cell
    pixels, rows x cols of them (zero padding past the image), pixels row by row in a cell.

    rx, ry (C, P) float32: the z=1 rays in that layout; limit: the float32 max depth [m].
    Returns x, y, z (C, P) float32 [m] (x = z rx, y = z ry) and valid (C, P) bool
    (0 < z <= limit). When some z exceeds limit every invalid pixel's z is set to 0."""
    height, width = cloud.shape[0], cloud.shape[1]
    npix = cell * cell
    cells = rows * cols
    zero = np.float32(0.0)
    any_far = False
    for v in range(height):
        for u in range(width):
            if cloud[v, u, 2] > limit:
                any_far = True
    x = np.empty((cells, npix), dtype=np.float32)
    y = np.empty((cells, npix), dtype=np.float32)
    z = np.empty((cells, npix), dtype=np.float32)
    valid = np.empty((cells, npix), dtype=np.bool_)
    for r in range(rows):
        for c in range(cols):
            k = r * cols + c
            for i in range(cell):
                v = r * cell + i
                for j in range(cell):
                    u = c * cell + j
                    p = i * cell + j
                    zz = cloud[v, u, 2] if v < height and u < width else zero
                    ok = zz > zero and not zz > limit
                    if any_far and not ok:
                        zz = zero
                    z[k, p] = zz
                    valid[k, p] = ok
                    x[k, p] = zz * rx[k, p]
                    y[k, p] = zz * ry[k, p]
    return x, y, z, valid


@njit(cache=True, nogil=True)
def _dot3(a0: float, a1: float, a2: float, x: float, y: float, z: float) -> float:
    """(a0, a1, a2) . (x, y, z) as OpenBLAS's dgemm accumulates the three products:
    fma(a2, z, fma(a1, y, a0 x)) (bit for bit `(rows @ points)[r, k]`)."""
    return _fma(a2, z, _fma(a1, y, a0 * x))  # type: ignore[call-arg]  # (typingctx is numba's)


@njit(cache=True, nogil=True)
def sampled_voxel_keys_kernel(
    cloud: np.ndarray, stride: int, T: np.ndarray, voxel_m: float, key_bits: int
) -> np.ndarray:
    """Packed voxel keys (N,) int64 of the valid points (z > 0, all finite) among every
    `stride`-th pixel in each direction of the (H, W, 3) float32 camera-frame cloud [m],
    moved to the world by T (4, 4): floor(p / voxel_m) per axis, each offset by
    2^(key_bits - 1) and packed x, y, z from the high bits; points whose key reaches
    beyond +-2^(key_bits - 1) are left out. Bit for bit what `sampled_points`,
    `transform_points` (OpenBLAS's dgemm order, `_dot3`), floor and packing give."""
    height, width = cloud.shape[0], cloud.shape[1]
    offset = 1 << (key_bits - 1)
    out = np.empty(((height + stride - 1) // stride) * ((width + stride - 1) // stride), np.int64)
    n = 0
    for v in range(0, height, stride):
        for u in range(0, width, stride):
            x, y, z = float(cloud[v, u, 0]), float(cloud[v, u, 1]), float(cloud[v, u, 2])
            if not (z > 0.0 and np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                continue
            packed = 0
            inside = True
            for r in range(3):
                w = _dot3(T[r, 0], T[r, 1], T[r, 2], x, y, z) + T[r, 3]
                if not np.isfinite(w):
                    inside = False
                    break
                key = np.floor(w / voxel_m)
                if not abs(key) < offset:
                    inside = False
                    break
                packed = (packed << key_bits) | (int(key) + offset)
            if inside:
                out[n] = packed
                n += 1
    return out[:n]


@njit(cache=True, nogil=True)
def band_points_kernel(
    points: np.ndarray,
    stride: int,
    normals: np.ndarray,
    ds: np.ndarray,
    dirs: np.ndarray,
    groups: np.ndarray,
    d_thresh: float,
    d_min: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge points of one plane near each of its D partner planes (paper eq. 3 and 5).

    points (K, 3) float64 inliers [m], of which every `stride`-th (0, stride, ...) is
    tested; partner r: unit normal normals[r] (3,), offset ds[r] [m], the pair's line
    direction dirs[r] (3,) and group id groups[r]. A point is an edge point of partner
    r when d_min <= |n_r . p + d_r| < d_thresh [m]. Returns, partner by partner and in
    point order within a partner: group ids (M,), signed distances n_r . p + d_r (M,)
    [m], line coordinates t = u_r . p (M,) [m] and the points (M, 3) [m]."""
    count = (len(points) + stride - 1) // stride
    size = len(ds) * count
    group = np.empty(size, dtype=np.int64)
    signed = np.empty(size)
    t = np.empty(size)
    xyz = np.empty((size, 3))
    m = 0
    for r in range(len(ds)):
        n0, n1, n2, d = normals[r, 0], normals[r, 1], normals[r, 2], ds[r]
        u0, u1, u2 = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        for k in range(0, len(points), stride):
            x, y, z = points[k, 0], points[k, 1], points[k, 2]
            s = _dot3(n0, n1, n2, x, y, z) + d
            if abs(s) < d_thresh and abs(s) >= d_min:
                group[m] = groups[r]
                signed[m] = s
                t[m] = _dot3(u0, u1, u2, x, y, z)
                xyz[m, 0] = x
                xyz[m, 1] = y
                xyz[m, 2] = z
                m += 1
    return group[:m].copy(), signed[:m].copy(), t[:m].copy(), xyz[:m].copy()


@njit(cache=True, nogil=True)
def contact_counts_kernel(grid: np.ndarray, k: int) -> np.ndarray:
    """Contacts between the labelled regions of an (H, W) int label grid (-1 for none):
    pixel pairs k apart horizontally or vertically with two different labels lo < hi ->
    (n, n) int64 counts at [lo, hi], n = the largest label + 1 (0 for an empty grid)."""
    height, width = grid.shape
    n = 0
    for v in range(height):
        for u in range(width):
            n = max(n, grid[v, u] + 1)
    counts = np.zeros((n, n), dtype=np.int64)
    for v in range(height):
        for u in range(width):
            a = grid[v, u]
            # The neighbours k to the right and k below; past the border, a itself (no contact).
            right = grid[v, u + k] if u + k < width else a
            below = grid[v + k, u] if v + k < height else a
            for b in (right, below):
                lo, hi = min(a, b), max(a, b)
                if lo >= 0 and lo != hi:
                    counts[lo, hi] += 1
    return counts


@njit(cache=True, nogil=True)
def _extent(t: np.ndarray, start: int, count: int, trim: int) -> tuple[float, float]:
    """Trimmed extent [lo, hi] [m] of the `count` sorted coordinates t[start:start+count]:
    at most `trim` (and 1 %) dropped at each end, each end pushed out by (trimmed + 1) mean
    spacings; (0, 0) for no points."""
    k = min(trim, count // 100)
    lo = t[start + k] if count > 0 else 0.0
    hi = t[start + count - 1 - k] if count > 0 else 0.0
    spacing = (hi - lo) / max(count - 1 - 2 * k, 1)
    return lo - (k + 1) * spacing, hi + (k + 1) * spacing


@njit(cache=True, nogil=True)
def edge_extents_kernel(
    key: np.ndarray,
    group: np.ndarray,
    t: np.ndarray,
    signed: np.ndarray,
    core: np.ndarray,
    xyz: np.ndarray,
    stride: np.ndarray,
    width: float,
    trim: int,
    min_points: int,
    min_length: float,
    diag_pad2: float,
    ends: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Extent, convexity, support and eq. 6 length of every plane pair from its edge points
    (the steps after eq. 3 and 5 in `intersections`' module docstring).

    The K edge points of all G = 2P groups (group 2p: pair p's plane A's points near plane
    B, 2p + 1 the reverse), sorted by key = group * width + t: group (K,) int64, t (K,)
    coordinate along the pair's line [m], signed (K,) distance to the other plane [m],
    core (K,) bool (far enough from the other plane to count for the extent), xyz (K, 3)
    [m]; stride (G,) subsampling of each group's plane. A side's extent is `_extent` of its
    core points where they are enough (min_points at full resolution and a quarter of
    the side), else of all its points; the edge is the overlap of both sides' extents
    (the union for a convex edge). Eq. 6: the farthest pair among the `ends` extreme
    points of each side at each end of the raw common extent, minus diag_pad2 =
    (2 d_thresh)^2. Returns per pair (P,): lo, hi [m] along the line, valid, convex,
    support (edge points within the extent, full-resolution count), eq. 6 length [m];
    and per group (G,) the side: mean signed distance within the edge's extent [m]."""
    n_groups = len(stride)
    n_pairs = n_groups // 2
    n = len(t)
    cnt = np.zeros(n_groups, dtype=np.int64)
    cnt_core = np.zeros(n_groups, dtype=np.int64)
    t_core = np.empty(n)
    m = 0
    for i in range(n):
        cnt[group[i]] += 1
        if core[i]:
            cnt_core[group[i]] += 1
            t_core[m] = t[i]
            m += 1
    start = np.zeros(n_groups, dtype=np.int64)
    start_core = np.zeros(n_groups, dtype=np.int64)
    for g in range(1, n_groups):
        start[g] = start[g - 1] + cnt[g - 1]
        start_core[g] = start_core[g - 1] + cnt_core[g - 1]
    lo_g, hi_g = np.empty(n_groups), np.empty(n_groups)
    rlo_g, rhi_g = np.zeros(n_groups), np.zeros(n_groups)
    for g in range(n_groups):
        c = cnt_core[g]
        if c * stride[g] >= min_points and c >= 0.25 * cnt[g]:
            lo_g[g], hi_g[g] = _extent(t_core, start_core[g], c, trim)
        else:
            lo_g[g], hi_g[g] = _extent(t, start[g], cnt[g], trim)
        if cnt[g] > 0:
            rlo_g[g], rhi_g[g] = t[start[g]], t[start[g] + cnt[g] - 1]

    lo, hi = np.empty(n_pairs), np.empty(n_pairs)
    valid = np.zeros(n_pairs, dtype=np.bool_)
    convex = np.zeros(n_pairs, dtype=np.bool_)
    support = np.zeros(n_pairs)
    eq6 = np.zeros(n_pairs)
    side = np.zeros(n_groups)
    first = np.empty(2, dtype=np.int64)
    stop = np.empty(2, dtype=np.int64)
    cand = np.empty((2, 2 * ends), dtype=np.int64)  # (low end, high end) x (side, rank)
    for p in range(n_pairs):
        a, b = 2 * p, 2 * p + 1
        lo[p] = lo_g[a] if lo_g[a] >= lo_g[b] else lo_g[b]
        hi[p] = hi_g[a] if hi_g[a] <= hi_g[b] else hi_g[b]
        valid[p] = min(cnt[a] * stride[a], cnt[b] * stride[b]) >= min_points and (
            hi[p] - lo[p] >= min_length
        )
        for g in (a, b):
            total, inside = 0.0, 0.0
            for i in range(start[g], start[g] + cnt[g]):
                if t[i] >= lo[p] and t[i] <= hi[p]:
                    total += signed[i]
                    inside += 1.0
                    support[p] += stride[g]
            side[g] = total / max(inside, 1.0)
        convex[p] = side[a] + side[b] < 0
        if valid[p] and convex[p] and min(cnt[a], cnt[b]) > 0:
            lo[p], hi[p] = min(lo_g[a], lo_g[b]), max(hi_g[a], hi_g[b])

        if n == 0:
            continue
        rlo = max(rlo_g[a], rlo_g[b])
        rhi = min(rhi_g[a], rhi_g[b])
        for s, g in enumerate((a, b)):
            first[s] = np.searchsorted(key, g * width + rlo, side="left")
            stop[s] = np.searchsorted(key, g * width + rhi, side="right")
            for o in range(ends):
                low = min(first[s] + o, max(stop[s] - 1, first[s]))
                high = max(stop[s] - 1 - o, first[s])
                cand[0, s * ends + o] = min(max(low, 0), n - 1)
                cand[1, s * ends + o] = min(max(high, 0), n - 1)
        best = 0.0
        for c0 in range(2 * ends):
            if stop[c0 // ends] <= first[c0 // ends]:
                continue
            i = cand[0, c0]
            for c1 in range(2 * ends):
                if stop[c1 // ends] <= first[c1 // ends]:
                    continue
                j = cand[1, c1]
                dx, dy, dz = xyz[i, 0] - xyz[j, 0], xyz[i, 1] - xyz[j, 1], xyz[i, 2] - xyz[j, 2]
                diag2 = (dx * dx + dz * dz) + dy * dy  # the order numpy's einsum sums them
                best = max(best, diag2)
        eq6[p] = np.sqrt(max(best - diag_pad2, 0.0))
    return lo, hi, valid, convex, support, eq6, side


_WARM = False


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel for the argument types the front
    end passes, on tiny inputs; once per process. The first run on a machine compiles for
    some seconds; later processes load the cached machine code in well under a second."""
    global _WARM
    if _WARM:
        return
    f32, n = np.float32, 2
    img = np.ones((n, n), f32)
    back_project_kernel(img, np.ones((n, n, 3), f32), f32(6.0))
    rx = np.zeros((1, n * n), f32)
    strided = np.ones((2 * n, 2 * n, 3), f32)[::2, ::2]  # segment()'s pixel_stride > 1
    cells_from_cloud_kernel(strided, 1, 1, n, rx, rx, f32(6.0))
    x, y, z, valid = cells_from_cloud_kernel(np.ones((n, n, 3), f32), 1, 1, n, rx, rx, f32(6.0))
    cand = np.zeros((1, 2), np.int32)
    ncand = np.ones(1, np.int64)
    normals, ds = np.ones((1, 3), f32), np.ones(1, f32)
    labels, _ = assign_pixels_kernel(x, y, z, valid, cand, ncand, normals, ds, f32(1.0), f32(0.0))
    remap = np.array([-1, 0], np.int32)
    gather_planes_kernel(x, y, z, labels, np.ones(1, np.bool_), remap, 1)
    normal = np.ones((n, 3))
    count, vec = np.ones(n, np.int64), np.ones(n)
    points = np.ones((3, 2 * n))[:, :n].T  # a plane's points: a view of segmentation's buffer
    band_points_kernel(points, 1, normal, vec, normal, count, 0.02, 0.0)
    contact_counts_kernel(np.zeros((2 * n, 2 * n), np.int32)[::2, ::2], 1)
    key, flag = np.arange(n, dtype=np.float64), np.ones(n, np.bool_)
    edge_extents_kernel(key, count - 1, key, key, flag, normal, vec, 1.0, 3, 1, 0.01, 0.0, 8)
    sampled_voxel_keys_kernel(np.ones((n, n, 3), f32), 2, np.eye(4), 0.01, 21)  # fused cloud
    warm_up_plane_kernels()
    warm_up_cell_kernels()
    _WARM = True
