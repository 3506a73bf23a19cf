"""Compiled (numba) cell-grid work of the organised segmentation (`organized`): the
smallest eigenvector of many symmetric 3x3 matrices (cells' and candidate planes'
scatters), the links between neighbouring cells and their components, the sums of cell
groups, and the CAPE-style region growing with its refits. Conventions as `kernels`
(cache=True, no fast-math; `kernels.warm_up` loads these too through
`warm_up_cell_kernels`); `tests/test_kernels.py` holds each to the numpy and scipy code
it replaced.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planeslam.frontend.plane_kernels import plane_of_moments


@njit(cache=True, nogil=True)
def smallest_eigh3_kernel(scatter: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form eigen-analysis of symmetric 3x3 matrices (C, 3, 3) float64 (the
    trigonometric solution of the characteristic cubic).

    Returns (smallest eigenvalue (C,), middle eigenvalue (C,), unit eigenvector of the
    smallest (C, 3)): the longest of the cross products of the rows of (A - lam_min I)
    (the first on ties). A row with no well-defined smallest eigenvector (isotropic or
    rank <= 1) gets a zero vector."""
    n = scatter.shape[0]
    lam_min = np.empty(n)
    lam_mid = np.empty(n)
    vec = np.zeros((n, 3))
    rows = np.empty((3, 3))
    for c in range(n):
        a = scatter[c]
        a00, a11, a22 = a[0, 0], a[1, 1], a[2, 2]
        a01, a02, a12 = a[0, 1], a[0, 2], a[1, 2]
        q = (a00 + a11 + a22) / 3.0
        b00, b11, b22 = a00 - q, a11 - q, a22 - q
        p1 = a01 * a01 + a02 * a02 + a12 * a12
        p = math.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
        safe_p = p if p > 0 else 1.0
        det_b = (
            b00 * (b11 * b22 - a12 * a12)
            - a01 * (a01 * b22 - a12 * a02)
            + a02 * (a01 * a12 - b11 * a02)
        )
        r = min(max(det_b / (2.0 * safe_p**3), -1.0), 1.0)
        phi = math.acos(r) / 3.0
        high = q + 2.0 * p * math.cos(phi)
        low = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
        lam_min[c] = low
        lam_mid[c] = 3.0 * q - high - low
        # Rows of (A - lam_min I) span the plane orthogonal to the eigenvector: cross them.
        rows[0, 0], rows[0, 1], rows[0, 2] = a00 - low, a01, a02
        rows[1, 0], rows[1, 1], rows[1, 2] = a01, a11 - low, a12
        rows[2, 0], rows[2, 1], rows[2, 2] = a02, a12, a22 - low
        best = -1.0
        for i, j in ((0, 1), (0, 2), (1, 2)):
            u, v = rows[i], rows[j]
            c0 = u[1] * v[2] - u[2] * v[1]
            c1 = u[2] * v[0] - u[0] * v[2]
            c2 = u[0] * v[1] - u[1] * v[0]
            norm2 = c0 * c0 + c1 * c1 + c2 * c2
            if norm2 > best:
                best = norm2
                vec[c, 0], vec[c, 1], vec[c, 2] = c0, c1, c2
        if best > 0:
            vec[c] /= math.sqrt(best)
        else:
            vec[c] = 0.0
    return lam_min, lam_mid, vec


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
def _region_plane(
    cells: np.ndarray, n_cells: int, count: np.ndarray, mean: np.ndarray, scatter: np.ndarray
) -> tuple[bool, float, np.ndarray, np.ndarray, np.ndarray, float]:
    """Merged moments of cells[:n_cells] and their least-squares plane (`merge_moments` and
    `plane_from_moments`) -> (ok, points, centroid (3,), scatter (3, 3), normal (3,) toward
    the camera, d); ok False when the points are (nearly) collinear."""
    total = 0.0
    centroid = np.zeros(3)
    for k in range(n_cells):
        c = cells[k]
        total += count[c]
        for i in range(3):
            centroid[i] += count[c] * mean[c, i]
    centroid /= total
    merged = np.zeros((3, 3))
    for k in range(n_cells):
        c = cells[k]
        for i in range(3):
            for j in range(3):
                merged[i, j] += scatter[c, i, j] + count[c] * (mean[c, i] - centroid[i]) * (
                    mean[c, j] - centroid[j]
                )
    ok, normal, d, _ = plane_of_moments(centroid, merged)
    return ok, total, centroid, merged, normal, d


@njit(cache=True, nogil=True)
def grow_regions_kernel(
    member: np.ndarray,
    degree: np.ndarray,
    rows: int,
    cols: int,
    count: np.ndarray,
    mean: np.ndarray,
    scatter: np.ndarray,
    normal: np.ndarray,
    sigma: np.ndarray,
    tilt_var: np.ndarray,
    min_points: float,
    min_angle_rad: float,
    k2: float,
) -> tuple[np.ndarray, ...]:
    """Seeded region growing (CAPE-style) inside the cells `member` (K,) of a rows x cols
    grid: at most 64 times, the remaining cell with most links (`degree` (C,)) seeds a
    region, which grows over the 4-connected remaining cells that fit its plane (RMS
    distance within sqrt(k2) sigma, normal within max(min_angle_rad, 3 sigma of the
    cell's tilt noise), at most 45 deg), refit after each growth, at most 4 times. Stops
    when fewer than `min_points` points remain.

    Per-cell inputs as `link_cells_kernel`. Returns the regions with at least
    `min_points` points: (cells, concatenated, ascending per region; bounds (R + 1,);
    points (R,); centroid (R, 3); scatter (R, 3, 3); normal (R, 3); d (R,))."""
    n = rows * cols
    remaining = np.zeros(n, np.bool_)
    for c in member:
        remaining[c] = True
    quarter = np.pi / 4.0
    cos_max = np.empty(n)
    for c in member:
        cos_max[c] = np.cos(min(max(3.0 * np.sqrt(tilt_var[c]), min_angle_rad), quarter))
    out_cells = np.empty(len(member), np.int64)
    out_bounds = [0]
    out_points, out_d = [0.0], [0.0]
    out_centroid, out_scatter, out_normal = [np.zeros(3)], [np.zeros((3, 3))], [np.zeros(3)]
    fit = np.zeros(n, np.bool_)
    grown = np.empty(n, np.int64)
    for _ in range(64):
        points = 0.0
        seed = -1
        for c in range(n):
            if remaining[c]:
                points += count[c]
                if seed < 0 or degree[c] > degree[seed]:
                    seed = c
        if points < min_points:
            break
        grown[0] = seed
        n_grown = 1
        ok, total, centroid, merged, plane_n, plane_d = _region_plane(
            grown, 1, count, mean, scatter
        )
        for _ in range(4):
            if not ok:
                break
            for c in range(n):
                fit[c] = (
                    remaining[c]
                    and _rms2_to_plane(scatter, mean, count, c, plane_n, plane_d)
                    <= k2 * sigma[c] ** 2
                    and normal[c, 0] * plane_n[0]
                    + normal[c, 1] * plane_n[1]
                    + normal[c, 2] * plane_n[2]
                    >= cos_max[c]
                )
            fit[seed] = True
            new = flood_fill_kernel(fit, rows, cols, seed)
            if len(new) == n_grown:
                break
            n_grown = len(new)
            grown[:n_grown] = new
            ok, total, centroid, merged, plane_n, plane_d = _region_plane(
                grown, n_grown, count, mean, scatter
            )
        for k in range(n_grown):
            remaining[grown[k]] = False
        if ok and total >= min_points:
            start = out_bounds[-1]
            out_cells[start : start + n_grown] = grown[:n_grown]
            out_bounds.append(start + n_grown)
            out_points.append(total)
            out_centroid.append(centroid)
            out_scatter.append(merged)
            out_normal.append(plane_n)
            out_d.append(plane_d)
    n_regions = len(out_bounds) - 1
    centroids = np.empty((n_regions, 3))
    scatters = np.empty((n_regions, 3, 3))
    normals = np.empty((n_regions, 3))
    for r in range(n_regions):
        centroids[r] = out_centroid[r + 1]
        scatters[r] = out_scatter[r + 1]
        normals[r] = out_normal[r + 1]
    return (
        out_cells[: out_bounds[-1]],
        np.array(out_bounds),
        np.array(out_points[1:]),
        centroids,
        scatters,
        normals,
        np.array(out_d[1:]),
    )


def warm_up_cell_kernels() -> None:
    """Compile (or load from numba's cache) these kernels for the argument types
    `organized` passes, on tiny inputs (`kernels.warm_up` calls it)."""
    n = 2
    count, mean, scatter = np.ones(n, np.int64), np.ones((n, 3)), np.ones((n, 3, 3))
    _, vec, normal = smallest_eigh3_kernel(scatter)
    planar = np.ones(n, np.bool_)
    link_cells_kernel(1, n, planar, normal, vec, mean, scatter, count, vec, vec, 0.1, 1.0)
    group_sums_kernel(np.zeros(n, np.int64), count, mean, scatter, 1)
    dense_components_kernel(np.ones((n, n), np.bool_))
    flood_fill_kernel(planar, 1, n, 0)
    member = np.arange(n, dtype=np.int64)
    grow_regions_kernel(member, count, 1, n, count, mean, scatter, normal, vec, vec, 1.0, 0.1, 1.0)
