"""Compiled (numba) loops of the front end's per-pixel work: back-projection, the
organised segmentation's pixel assignment and the gathering of each plane's inliers.

Each kernel does in one pass over the pixels what numpy did in several passes and
temporary arrays, with the same float32 operations in the same order (no fast-math,
so no fused multiply-adds): the results are identical to the numpy code they
replace, bit for bit. Compiled once per machine (`cache=True` keeps the machine code
beside the module, or in numba's user cache when that is not writable).
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
def _rms2_to_plane(
    scatter: np.ndarray, mean: np.ndarray, count: np.ndarray, c: int, normal: np.ndarray, d: float
) -> float:
    """Mean squared distance [m^2] of cell c's points (its moments) to the plane (normal, d)."""
    quad = 0.0
    for i in range(3):
        for j in range(3):
            quad += normal[i] * scatter[c, i, j] * normal[j]
    off = normal[0] * mean[c, 0] + normal[1] * mean[c, 1] + normal[2] * mean[c, 2] + d
    return quad / max(count[c], 1) + off * off


@njit(cache=True, nogil=True)
def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True, nogil=True)
def _component_labels(parent: np.ndarray) -> np.ndarray:
    """(N,) component label of each node of a union-find forest, numbered in the order of
    each component's first node (as scipy's connected_components)."""
    n = len(parent)
    comp = np.full(n, -1, dtype=np.int64)
    label_of_root = np.full(n, -1, dtype=np.int64)
    labels = 0
    for i in range(n):
        root = _find(parent, i)
        if label_of_root[root] < 0:
            label_of_root[root] = labels
            labels += 1
        comp[i] = label_of_root[root]
    return comp


@njit(cache=True, nogil=True)
def link_cells_kernel(
    rows: int,
    cols: int,
    planar: np.ndarray,
    normal: np.ndarray,
    d: np.ndarray,
    mean: np.ndarray,
    scatter: np.ndarray,
    count: np.ndarray,
    sigma: np.ndarray,
    tilt_var: np.ndarray,
    min_angle_rad: float,
    k2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Links between 4-neighbour planar cells of a rows x cols grid that fit each other's
    planes: normals within max(min_angle_rad, 3 sigma of both cells' tilt noise), at most
    45 deg, and each cell's RMS distance to the other's plane within sqrt(k2) sigma.

    Per-cell inputs (C,): planar, d, count, sigma [m], tilt_var [rad^2]; normal, mean
    (C, 3); scatter (C, 3, 3). Returns (connected component per cell (C,), numbered in
    the order of each component's first cell as scipy's connected_components does;
    links per cell (C,))."""
    n = rows * cols
    parent = np.arange(n)
    degree = np.zeros(n, dtype=np.int64)
    quarter = np.pi / 4.0
    for a in range(n):
        if not planar[a]:
            continue
        r, c = a // cols, a % cols
        for step in range(2):
            if step == 0:
                if c + 1 >= cols:
                    continue
                b = a + 1
            else:
                if r + 1 >= rows:
                    continue
                b = a + cols
            if not planar[b]:
                continue
            angle = min(max(3.0 * np.sqrt(tilt_var[a] + tilt_var[b]), min_angle_rad), quarter)
            dot = normal[a, 0] * normal[b, 0] + normal[a, 1] * normal[b, 1]
            dot += normal[a, 2] * normal[b, 2]
            if not dot >= np.cos(angle):
                continue
            if not _rms2_to_plane(scatter, mean, count, b, normal[a], d[a]) <= k2 * sigma[b] ** 2:
                continue
            if not _rms2_to_plane(scatter, mean, count, a, normal[b], d[b]) <= k2 * sigma[a] ** 2:
                continue
            degree[a] += 1
            degree[b] += 1
            ra, rb = _find(parent, a), _find(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    return _component_labels(parent), degree


@njit(cache=True, nogil=True)
def group_sums_kernel(
    group: np.ndarray, count: np.ndarray, mean: np.ndarray, scatter: np.ndarray, n_groups: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw moments of cell groups: group (C,) index per cell (-1 for none), count (C,),
    mean (C, 3) [m], scatter (C, 3, 3) [m^2] -> (points (G,), first moments (G, 3) [m],
    second moments about the origin (G, 3, 3) [m^2]), float64, summed in cell order (as
    numpy.bincount does)."""
    total = np.zeros(n_groups)
    first = np.zeros((n_groups, 3))
    second = np.zeros((n_groups, 3, 3))
    for c in range(len(group)):
        g = group[c]
        if g < 0:
            continue
        w = float(count[c])
        total[g] += w
        for i in range(3):
            first[g, i] += w * mean[c, i]
        for i in range(3):
            for j in range(i, 3):
                second[g, i, j] += scatter[c, i, j] + w * mean[c, i] * mean[c, j]
    for g in range(n_groups):
        for i in range(3):
            for j in range(i):
                second[g, i, j] = second[g, j, i]
    return total, first, second


@njit(cache=True, nogil=True)
def dense_components_kernel(linked: np.ndarray) -> np.ndarray:
    """Connected components of the undirected graph of an (N, N) bool matrix (an edge where
    linked[i, j] or linked[j, i]) -> (N,) labels numbered in the order of each component's
    first node (as scipy's connected_components)."""
    n = linked.shape[0]
    parent = np.arange(n)
    for i in range(n):
        for j in range(n):
            if linked[i, j]:
                ra, rb = _find(parent, i), _find(parent, j)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    return _component_labels(parent)


@njit(cache=True, nogil=True)
def flood_fill_kernel(fit: np.ndarray, rows: int, cols: int, seed: int) -> np.ndarray:
    """Cells 4-connected to `seed` through `fit` (rows * cols,) bool (seed included, whatever
    its own flag) -> their indices, ascending."""
    n = rows * cols
    seen = np.zeros(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    seen[seed] = True
    stack[0] = seed
    top = 1
    found = 1
    while top > 0:
        top -= 1
        a = stack[top]
        r, c = a // cols, a % cols
        for k in range(4):
            if k == 0:
                if c == 0:
                    continue
                b = a - 1
            elif k == 1:
                if c + 1 >= cols:
                    continue
                b = a + 1
            elif k == 2:
                if r == 0:
                    continue
                b = a - cols
            else:
                if r + 1 >= rows:
                    continue
                b = a + cols
            if fit[b] and not seen[b]:
                seen[b] = True
                stack[top] = b
                top += 1
                found += 1
    out = np.empty(found, dtype=np.int64)
    k = 0
    for a in range(n):
        if seen[a]:
            out[k] = a
            k += 1
    return out


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
    planar = np.ones(n, np.bool_)
    normal, mean, scatter = np.ones((n, 3)), np.ones((n, 3)), np.ones((n, 3, 3))
    count, vec = np.ones(n, np.int64), np.ones(n)
    link_cells_kernel(1, n, planar, normal, vec, mean, scatter, count, vec, vec, 0.1, 1.0)
    group_sums_kernel(np.zeros(n, np.int64), count, mean, scatter, 1)
    dense_components_kernel(np.ones((n, n), np.bool_))
    flood_fill_kernel(planar, 1, n, 0)
    _WARM = True
