"""The compiled front-end kernels against the numpy and scipy code they replace: the same
results bit for bit (labels, counts, sums, points and their order) on seeded random input;
the moments and fits summed in another order, within 1e-12 of it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse.csgraph import connected_components

from planeslam.frontend import cell_kernels, kernels, plane_kernels

pytestmark = pytest.mark.unit


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_back_project_matches_numpy(rng):
    depth = rng.uniform(-1.0, 8.0, (12, 16)).astype(np.float32)
    depth[0, :4] = [np.nan, np.inf, -np.inf, 0.0]
    rays = rng.normal(size=(12, 16, 3)).astype(np.float32)
    limit = np.float32(6.0)
    z = np.where((depth > 0) & (depth <= limit), depth, np.float32(0.0))
    expected = z[..., None] * rays
    got = kernels.back_project_kernel(depth, rays, limit)
    assert got.dtype == np.float32 and np.array_equal(got, expected)


def _to_cells(image: np.ndarray, rows: int, cols: int, cell: int) -> np.ndarray:
    full = np.zeros((rows * cell, cols * cell), dtype=image.dtype)
    full[: image.shape[0], : image.shape[1]] = image
    return full.reshape(rows, cell, cols, cell).transpose(0, 2, 1, 3).reshape(rows * cols, -1)


@pytest.mark.parametrize("far", [False, True])
def test_cells_from_cloud_matches_numpy(rng, far):
    rows, cols, cell = 3, 4, 4
    cloud = rng.uniform(-0.5, 5.0, (10, 14, 3)).astype(np.float32)  # padded to 12 x 16
    if far:
        cloud[2, 3, 2] = 9.0
    rx = rng.normal(size=(rows * cols, cell * cell)).astype(np.float32)
    ry = rng.normal(size=rx.shape).astype(np.float32)
    limit = np.float32(6.0)
    z = _to_cells(cloud[..., 2], rows, cols, cell)
    valid = (z > 0) & ~(z > limit)
    if far:
        z = np.where(valid, z, np.float32(0.0))
    x, y, zk, vk = kernels.cells_from_cloud_kernel(cloud, rows, cols, cell, rx, ry, limit)
    assert np.array_equal(vk, valid) and np.array_equal(zk, z)
    assert np.array_equal(x, z * rx) and np.array_equal(y, z * ry)


def _assign_pixels_numpy(x, y, z, valid, cu, ncand, normals, ds, ka, kb):
    """The numpy code the kernel replaced (per pixel, same float32 operations)."""
    labels = np.full(x.shape, -1, dtype=np.int32)
    tol = z * z
    tol *= kb
    tol += ka
    tol[~valid] = -1.0
    for c in range(len(x)):
        best = np.full(x.shape[1], np.float32(1.0))
        for s in range(ncand[c]):
            i = cu[c, s]
            r = x[c] * normals[i, 0]
            r += y[c] * normals[i, 1]
            r += z[c] * normals[i, 2]
            r += ds[i]
            r = np.abs(r)
            if ncand[c] == 1:
                labels[c][r <= tol[c]] = i
                continue
            e = r / tol[c]
            better = (e <= best) & (e >= 0)
            best[better] = e[better]
            labels[c][better] = i
    counts = np.bincount(labels.ravel() + 1, minlength=len(ds) + 1)[1:]
    return labels, counts


def test_assign_pixels_matches_numpy(rng):
    cells, npix, planes = 40, 16, 5
    z = rng.uniform(0.5, 4.0, (cells, npix)).astype(np.float32)
    valid = rng.random((cells, npix)) > 0.1
    z[~valid] = 0.0
    x = (z * rng.normal(0, 0.5, z.shape)).astype(np.float32)
    y = (z * rng.normal(0, 0.5, z.shape)).astype(np.float32)
    normals = rng.normal(size=(planes, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # planes through some of the points, so that pixels fit
    ds = (-(normals[:, 2] * 2.0)).astype(np.float32)
    ncand = rng.integers(0, 4, cells)
    cu = np.full((cells, 3), -1, dtype=np.int32)
    for c in range(cells):
        cu[c, : ncand[c]] = rng.choice(planes, ncand[c], replace=False)
    ka, kb = np.float32(0.5), np.float32(0.1)  # wide tolerances: many inliers and ties
    labels, counts = kernels.assign_pixels_kernel(x, y, z, valid, cu, ncand, normals, ds, ka, kb)
    ref_labels, ref_counts = _assign_pixels_numpy(x, y, z, valid, cu, ncand, normals, ds, ka, kb)
    assert (labels >= 0).sum() > 50
    assert np.array_equal(labels, ref_labels) and np.array_equal(counts, ref_counts)


def test_gather_planes_orders_single_then_multi_candidate_cells(rng):
    cells, npix, old = 6, 4, 3
    x, y, z = (rng.normal(size=(cells, npix)).astype(np.float32) for _ in range(3))
    labels = rng.integers(-1, old, (cells, npix)).astype(np.int32)
    single = np.array([True, False, True, False, True, True])
    remap = np.array([-1, 1, -1, 0], dtype=np.int32)  # old 0 -> 1, old 1 dropped, old 2 -> 0
    expected_labels = remap[labels + 1]
    xyz, bounds = kernels.gather_planes_kernel(x, y, z, labels, single, remap, 2)
    assert np.array_equal(labels, expected_labels)  # renumbered in place
    for new in range(2):
        parts = [np.flatnonzero(np.where(single[:, None], labels, -1).ravel() == new)]
        parts.append(np.flatnonzero(np.where(~single[:, None], labels, -1).ravel() == new))
        idx = np.concatenate(parts)
        expected = np.stack([x.ravel()[idx], y.ravel()[idx], z.ravel()[idx]]).astype(np.float64)
        assert np.array_equal(xyz[:, bounds[new] : bounds[new + 1]], expected)


def test_components_match_scipy(rng):
    for _ in range(20):
        n = int(rng.integers(1, 30))
        linked = rng.random((n, n)) < 2.0 / n
        _, expected = connected_components(linked, directed=False)
        assert np.array_equal(cell_kernels.dense_components_kernel(linked), expected)


def test_flood_fill_matches_ndimage_label(rng):
    rows, cols = 9, 13
    for _ in range(20):
        fit = rng.random(rows * cols) < 0.55
        seed = int(rng.integers(rows * cols))
        fit[seed] = True
        comp, _ = ndimage.label(fit.reshape(rows, cols))
        expected = np.flatnonzero(comp.ravel() == comp.ravel()[seed])
        assert np.array_equal(cell_kernels.flood_fill_kernel(fit, rows, cols, seed), expected)


def test_group_sums_match_bincount(rng):
    cells, groups = 50, 4
    group = rng.integers(-1, groups, cells)
    count = rng.integers(0, 256, cells)
    mean = rng.normal(size=(cells, 3))
    a = rng.normal(size=(cells, 3, 3))
    scatter = a @ a.transpose(0, 2, 1)
    total, first, second = cell_kernels.group_sums_kernel(group, count, mean, scatter, groups)
    member = group >= 0
    g, w, m = group[member], count[member].astype(np.float64), mean[member]
    assert np.array_equal(total, np.bincount(g, weights=w, minlength=groups))
    for i in range(3):
        assert np.array_equal(first[:, i], np.bincount(g, weights=w * m[:, i], minlength=groups))
    raw = scatter[member] + w[:, None, None] * m[:, :, None] * m[:, None, :]
    for i in range(3):
        for j in range(3):
            expected = np.bincount(g, weights=raw[:, min(i, j), max(i, j)], minlength=groups)
            assert np.array_equal(second[:, i, j], expected)


def test_link_cells_components_match_scipy_on_the_links(rng):
    """Cells on a grid, some planar: the kernel's components are those scipy finds on the
    links the kernel reports through its degrees (a chain of identical planes links)."""
    rows, cols = 4, 5
    n = rows * cols
    planar = rng.random(n) < 0.8
    normal = np.tile([0.0, 0.0, -1.0], (n, 1))
    normal[rng.random(n) < 0.3] = [0.0, -1.0, 0.0]  # a second orientation: no link across
    d = np.full(n, 2.0)
    mean = np.zeros((n, 3))
    mean[:, 2] = np.where(normal[:, 2] < 0, 2.0, 0.0)
    mean[:, 1] = np.where(normal[:, 1] < 0, 2.0, 0.0)
    scatter = np.zeros((n, 3, 3))
    count = np.full(n, 100)
    sigma = np.full(n, 0.01)
    tilt = np.full(n, 1e-6)
    comp, degree = cell_kernels.link_cells_kernel(
        rows, cols, planar, normal, d, mean, scatter, count, sigma, tilt, 0.1, 9.0
    )
    grid = np.arange(n).reshape(rows, cols)
    a = np.concatenate([grid[:, :-1].ravel(), grid[:-1, :].ravel()])
    b = np.concatenate([grid[:, 1:].ravel(), grid[1:, :].ravel()])
    ok = planar[a] & planar[b] & (np.einsum("ki,ki->k", normal[a], normal[b]) > 0.9)
    linked = np.zeros((n, n), dtype=bool)
    linked[a[ok], b[ok]] = True
    _, expected = connected_components(linked, directed=False)
    assert np.array_equal(comp, expected)
    assert np.array_equal(degree, linked.sum(0) + linked.sum(1))


# --------------------------------------------------------------------------- intersections


def _band_points_numpy(pts, stride, normals, ds, dirs, groups, d_thresh, d_min):
    """The numpy code `band_points_kernel` replaced: one BLAS (2D, 3) @ (3, K) product."""
    sub = np.ascontiguousarray(pts[::stride].T)
    proj = np.concatenate([normals, dirs]) @ sub
    deg = len(ds)
    signed = proj[:deg] + ds[:, None]
    near = (np.abs(signed) < d_thresh) & (np.abs(signed) >= d_min)
    row, col = np.divmod(np.flatnonzero(near), near.shape[1])
    return groups[row], signed[near], proj[deg:][near], sub[:, col].T


@pytest.mark.parametrize("stride", [1, 3])
def test_band_points_match_the_blas_product(rng, stride):
    """Against numpy's BLAS product, on a transposed view like `Plane.points`: the same
    points, values within 1e-12 (bit for bit where OpenBLAS's dgemm fuses multiply-adds in
    `_dot3`'s order, as on the Intel Xeon it was written on; another CPU's BLAS kernel may
    round its last bit otherwise)."""
    buffer = rng.uniform(-2.0, 2.0, (3, 1200))
    pts = buffer[:, 100:1100].T  # (K, 3), neither C- nor F-contiguous
    normals = rng.normal(size=(4, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    dirs = rng.normal(size=(4, 3))
    ds = rng.uniform(-0.5, 0.5, 4)
    groups = np.array([5, 0, 2, 7], dtype=np.int64)
    for d_min in (0.0, 0.05):
        expected = _band_points_numpy(pts, stride, normals, ds, dirs, groups, 0.3, d_min)
        got = kernels.band_points_kernel(pts, stride, normals, ds, dirs, groups, 0.3, d_min)
        assert len(got[0]) > 50
        assert np.array_equal(expected[0], got[0])  # the same points, in the same order
        for e, g in zip(expected[1:], got[1:], strict=True):
            np.testing.assert_allclose(g, e, rtol=0.0, atol=1e-12)


def _contact_counts_numpy(grid, k):
    """The numpy code `contact_counts_kernel` replaced (bincount of lo * n + hi keys)."""
    n = int(grid.max()) + 1
    keys = []
    for a, b in ((grid[:, :-k], grid[:, k:]), (grid[:-k, :], grid[k:, :])):
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        touch = (lo >= 0) & (lo != hi)
        keys.append(lo[touch].astype(np.int64) * n + hi[touch])
    return np.bincount(np.concatenate(keys), minlength=n * n).reshape(n, n)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_contact_counts_match_bincount(rng, k):
    labels = rng.integers(-1, 6, (24, 32)).astype(np.int32)
    labels[:8, :8] = 2  # a larger region
    grid = labels[::2, ::2]
    assert np.array_equal(kernels.contact_counts_kernel(grid, k), _contact_counts_numpy(grid, k))
    assert kernels.contact_counts_kernel(np.full((4, 4), -1, np.int32), 1).shape == (0, 0)


def _group_starts(counts):
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def _trimmed_extents_numpy(te, cnt, trim):
    start = _group_starts(cnt)
    last = start + np.maximum(cnt, 1) - 1
    k = np.minimum(trim, cnt // 100)
    te_pad = np.append(te, 0.0)
    lo = te_pad[np.where(cnt > 0, start + k, len(te))]
    hi = te_pad[np.where(cnt > 0, last - k, len(te))]
    spacing = (hi - lo) / np.maximum(cnt - 1 - 2 * k, 1)
    return lo - (k + 1) * spacing, hi + (k + 1) * spacing


def _edge_extents_numpy(ge, te, se, core, xyz, stride, trim, min_points, min_length, d_thresh):
    """The numpy code `edge_extents_kernel` replaced (find_intersections after the sort,
    `_trimmed_extents` and `_eq6_lengths`)."""
    ngroups, ends = len(stride), 8
    npairs = ngroups // 2
    pe = ge // 2
    cnt = np.bincount(ge, minlength=ngroups)
    start = _group_starts(cnt)
    last = start + np.maximum(cnt, 1) - 1
    te_pad = np.append(te, 0.0)
    rlo_g = te_pad[np.where(cnt > 0, start, len(te))]
    rhi_g = te_pad[np.where(cnt > 0, last, len(te))]
    lo_g, hi_g = _trimmed_extents_numpy(te, cnt, trim)
    cnt_core = np.bincount(ge[core], minlength=ngroups)
    lo_c, hi_c = _trimmed_extents_numpy(te[core], cnt_core, trim)
    enough = (cnt_core * stride >= min_points) & (cnt_core >= 0.25 * cnt)
    lo_g, hi_g = np.where(enough, lo_c, lo_g), np.where(enough, hi_c, hi_g)
    lo = np.maximum(lo_g[0::2], lo_g[1::2])
    hi = np.minimum(hi_g[0::2], hi_g[1::2])
    support_g = cnt * stride
    valid = (np.minimum(support_g[0::2], support_g[1::2]) >= min_points) & (hi - lo >= min_length)
    in_edge = (te >= lo[pe]) & (te <= hi[pe])
    w = in_edge.astype(np.float64)
    side = np.bincount(ge, weights=se * w, minlength=ngroups) / np.maximum(
        np.bincount(ge, weights=w, minlength=ngroups), 1.0
    )
    convex = side[0::2] + side[1::2] < 0
    support = np.bincount(pe[in_edge], weights=stride[ge[in_edge]], minlength=npairs)
    both = valid & convex & (np.minimum(cnt[0::2], cnt[1::2]) > 0)
    lo = np.where(both, np.minimum(lo_g[0::2], lo_g[1::2]), lo)
    hi = np.where(both, np.maximum(hi_g[0::2], hi_g[1::2]), hi)
    # eq. 6
    rlo = np.repeat(np.maximum(rlo_g[0::2], rlo_g[1::2]), 2)
    rhi = np.repeat(np.minimum(rhi_g[0::2], rhi_g[1::2]), 2)
    width = 2.0 * float(np.max(np.abs(te))) + 1.0
    key = ge * width + te
    groups = np.arange(ngroups)
    first = np.searchsorted(key, groups * width + rlo, side="left")
    stop = np.searchsorted(key, groups * width + rhi, side="right")
    n = np.maximum(stop - first, 0)
    offs = np.arange(ends)
    lo_idx = np.minimum(first[:, None] + offs, np.maximum(stop - 1, first)[:, None])
    hi_idx = np.maximum(stop[:, None] - 1 - offs, first[:, None])
    idx = np.clip(np.concatenate([lo_idx, hi_idx], axis=1), 0, len(te) - 1)
    cand = xyz[idx]
    low = cand[:, :ends].reshape(npairs, 2 * ends, 3)
    high = cand[:, ends:].reshape(npairs, 2 * ends, 3)
    diff = low[:, :, None, :] - high[:, None, :, :]
    diag2 = np.einsum("pabk,pabk->pab", diff, diff).reshape(npairs, -1)
    ok = np.repeat(n > 0, ends).reshape(npairs, 2 * ends)
    pair_ok = ok[:, :, None] & ok[:, None, :]
    diag2 = np.max(np.where(pair_ok.reshape(npairs, -1), diag2, 0.0), axis=1)
    eq6 = np.sqrt(np.maximum(diag2 - 4.0 * d_thresh**2, 0.0))
    return lo, hi, valid, convex, support, eq6, side, key, width


def test_edge_extents_match_numpy(rng):
    """Groups of edge points with pairs of both signs of side, strides, a core mask, empty
    groups and groups of a few points: every output as the numpy code's (flags equal,
    values within 1e-12)."""
    npairs = 40
    sizes = rng.integers(0, 400, 2 * npairs)
    sizes[[3, 10, 11]] = 0
    sizes[[5, 20]] = [1, 2]
    ge = np.repeat(np.arange(2 * npairs), sizes)
    te = rng.uniform(-1.5, 1.5, len(ge)) + rng.uniform(-0.3, 0.3, 2 * npairs)[ge]
    side_sign = rng.choice([-1.0, 1.0], 2 * npairs)
    se = side_sign[ge] * rng.uniform(-0.005, 0.02, len(ge))
    core = rng.random(len(ge)) < 0.7
    core[ge == 7] = False
    xyz = rng.uniform(-2.0, 2.0, (len(ge), 3))
    stride = rng.choice([1.0, 2.0], 2 * npairs)
    width = 2.0 * float(np.max(np.abs(te))) + 1.0
    order = np.argsort(ge * width + te)
    ge, te, se, core, xyz = ge[order], te[order], se[order], core[order], xyz[order]
    *expected, key, width = _edge_extents_numpy(ge, te, se, core, xyz, stride, 3, 20, 0.03, 0.02)
    got = kernels.edge_extents_kernel(
        key, ge, te, se, core, xyz, stride, width, 3, 20, 0.03, 4.0 * 0.02**2, 8
    )
    assert expected[2].any() and not expected[2].all()  # some pairs valid, some not
    assert expected[3].any() and not expected[3].all()  # convex and concave
    for e, g in zip(expected, got, strict=True):
        if e.dtype == bool:
            assert np.array_equal(e, g)
        else:  # bit for bit here; numpy's einsum may sum in another order on another CPU
            np.testing.assert_allclose(g, e, rtol=0.0, atol=1e-12)


def _outline_points_numpy(poly, u0, v0, small_shape, s, rays, normal, d):
    """The numpy code `outline_points_kernel` replaced (end of `segment_common._outline`)."""
    height, width = rays.shape[:2]
    u, v = poly[:, 0] + u0, poly[:, 1] + v0
    last_v, last_u = small_shape[0] - 1, small_shape[1] - 1
    u = np.where(u == last_u, width - 1, np.minimum(np.maximum(s * u, 0), width - 1))
    v = np.where(v == last_v, height - 1, np.minimum(np.maximum(s * v, 0), height - 1))
    r = rays[v, u]
    along = r @ normal
    along = np.where(np.abs(along) > 1e-9, along, -1e-9)
    return r * (-d / along)[:, None]


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_outline_points_match_numpy(rng, dtype):
    """Vertices on the last sampled row / column go to the image border; a ray parallel to
    the plane meets it at -d / -1e-9. Within 1e-12 (bit for bit where OpenBLAS's dgemv
    fuses as the kernel does, as on the Intel Xeon it was written on)."""
    height, width, s = 31, 40, 3
    rays = np.dstack([rng.uniform(-0.6, 0.6, (height, width, 2)), np.ones((height, width))])
    small_shape = (11, 14)  # rays[::3, ::3].shape
    eig = np.linalg.eigh(np.diag([3.0, 1.0, 2.0]) + 0.1)[1]
    for normal in (eig[:, 0], rng.normal(size=3), np.array([1.0, 0.0, 0.0])):
        normal = normal / np.linalg.norm(normal) if normal.flags.owndata else normal
        poly = np.column_stack([rng.integers(0, 9, 20), rng.integers(0, 7, 20)]).astype(dtype)
        poly[:3] = [[8, 0], [0, 6], [8, 6]]  # with (u0, v0) = (5, 4): the last column / row
        rays[12, 15] = [-1.0, 0.5, 0.0]  # perpendicular to the third normal
        poly[3] = [0, 0]
        expected = _outline_points_numpy(poly, 5, 4, small_shape, s, rays, normal, 1.7)
        got = plane_kernels.outline_points_kernel(poly, 5, 4, small_shape, s, rays, normal, 1.7)
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("count", [500, 9000])
def test_inverse_depth_noise_matches_numpy(rng, count):
    """Against `inverse_depth_residual_steps` on every (K // 4096)-th point, within 1e-12."""
    from planeslam.core.quantised_fit import inverse_depth_residual_steps

    normal = np.array([0.1, -0.2, -1.0]) / np.linalg.norm([0.1, -0.2, -1.0])
    d = 3.0
    xy = rng.uniform(-1.0, 1.0, (2, count))
    z = (d + normal[:2] @ xy) / -normal[2] + rng.normal(0.0, 0.004, count)
    buffer = np.ones((3, count + 10))
    buffer[:, :count] = np.vstack([xy, z])
    xyz = buffer[:, :count]  # a view of segmentation's (3, N) buffer
    for step in (0.00285, 0.02):
        expected = inverse_depth_residual_steps(xyz[:, :: max(1, count // 4096)].T, normal, d, step)
        got = plane_kernels.inverse_depth_noise_kernel(xyz, normal, d, step, 4096)
        assert abs(got - expected) <= 1e-12 * max(expected, 1.0)


def test_plane_fits_match_the_single_plane_functions(rng):
    """Each segment's fit, covariance and cubed depths against `moments_of`,
    `plane_from_moments` and `plane_covariance`; degenerate segments flagged."""
    from planeslam.core.plane_fit import moments_of, plane_covariance, plane_from_moments

    segments = []
    for k in (500, 3, 40):
        normal = rng.normal(size=3)
        uv = rng.uniform(-1.0, 1.0, (k, 2))
        basis = np.linalg.svd(normal[None])[2][1:]
        segments.append(
            uv @ basis + 2.0 * normal / np.linalg.norm(normal) + rng.normal(0, 1e-3, (k, 3))
        )
    segments.append(
        np.outer(np.linspace(0.0, 1.0, 20), [1.0, 2.0, 3.0]) + [0.0, 0.0, 2.0]
    )  # a line
    xyz = np.ascontiguousarray(np.concatenate(segments).T)
    bounds = np.cumsum([0] + [len(s) for s in segments])
    count, centroid, scatter, normal, d, rss, cov, cubes, status = plane_fits_kernel_of(xyz, bounds)
    ok, few, line = (
        plane_kernels.FIT_OK,
        plane_kernels.FIT_TOO_FEW_POINTS,
        plane_kernels.FIT_COLLINEAR,
    )
    assert status.tolist() == [ok, few, ok, line] and count.tolist() == [500, 3, 40, 20]
    for i in (0, 2):
        k, c, s = moments_of(segments[i])
        n, off, res = plane_from_moments(c, s)
        np.testing.assert_allclose(centroid[i], c, rtol=1e-12)
        np.testing.assert_allclose(scatter[i], s, rtol=1e-9, atol=1e-12 * np.abs(s).max())
        assert abs(abs(normal[i] @ n) - 1.0) < 1e-12 and np.sign(normal[i] @ n) > 0
        assert abs(d[i] - off) < 1e-12 and abs(rss[i] - res) < 1e-9 * res
        np.testing.assert_allclose(cov[i], plane_covariance(n, c, s, k, res), rtol=1e-7)
        assert abs(cubes[i] - float(np.sum(segments[i][:, 2] ** 3))) < 1e-9 * abs(cubes[i])


def plane_fits_kernel_of(xyz, bounds):
    return plane_kernels.plane_fits_kernel(xyz, np.asarray(bounds, dtype=np.int64))


def _grow_regions_numpy(cells, member, degree, rows, cols, min_px, cfg):
    """The numpy code `grow_regions_kernel` replaced -> [(cells, count, normal, d)]."""
    from planeslam.core.errors import GeometryError
    from planeslam.core.plane_fit import merge_moments, plane_from_moments
    from planeslam.frontend.organized import _cos_tolerance, _rms2_to_plane

    def region_of(idx):
        count, centroid, scatter = merge_moments(
            cells.count[idx], cells.mean[idx], cells.scatter[idx]
        )
        try:
            normal, d, _ = plane_from_moments(centroid, scatter)
        except GeometryError:
            return None
        return idx, count, normal, d

    def fitting(idx, region):
        rms2 = _rms2_to_plane(cells, idx, region[2], np.float64(region[3]))
        cos_max = _cos_tolerance(cells.tilt_var[idx], cfg)
        return (rms2 <= (cfg.organized.merge_max_rms_sigmas * cells.sigma[idx]) ** 2) & (
            cells.normal[idx] @ region[2] >= cos_max
        )

    remaining = np.zeros(rows * cols, dtype=bool)
    remaining[member] = True
    regions = []
    for _ in range(64):
        cand = np.flatnonzero(remaining)
        if cells.count[cand].sum() < min_px:
            break
        seed = int(cand[np.argmax(degree[cand])])
        region = region_of(np.array([seed]))
        grown = np.array([seed])
        for _ in range(4):
            if region is None:
                break
            fit = np.zeros(rows * cols, dtype=bool)
            fit[cand] = fitting(cand, region)
            fit[seed] = True
            new = cell_kernels.flood_fill_kernel(fit, rows, cols, seed)
            if len(new) == len(grown):
                break
            grown = new
            region = region_of(grown)
        remaining[grown] = False
        if region is not None and region[1] >= min_px:
            regions.append(region)
    return regions


def test_grow_regions_matches_numpy():
    """On a frame of a bent wall (cells chain across the bend) and a floor: the same
    regions, cells and counts, planes within 1e-12."""
    from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
    from planeslam.frontend import organized
    from planeslam.frontend.cloud import organized_cloud
    from planeslam.frontend.config import SegmentationConfig

    camera = CameraConfig()
    rays = PixelRays.for_camera(camera)
    u = np.arange(camera.width) / camera.width - 0.5
    depth = np.tile(2.0 + 1.5 * u**2, (camera.height, 1))  # a wall bent about the centre
    v = rays.rays[:, :, 1]
    floor = np.where(v > 0.05, 1.2 / np.maximum(v, 1e-9), np.inf)
    depth = np.minimum(depth, floor) + np.random.default_rng(3).normal(0, 1e-3, depth.shape)
    cfg, noise = SegmentationConfig(), DepthNoiseConfig()
    pixels = organized.pixel_grid(camera)
    grid = organized._cell_grid(pixels, cfg.organized.cell_size_px)
    cloud = organized_cloud(depth.astype(np.float32), rays, cfg.max_depth_m)
    x, y, z, valid = kernels.cells_from_cloud_kernel(
        cloud, grid.rows, grid.cols, grid.cell, grid.rx, grid.ry, np.float32(cfg.max_depth_m)
    )
    cells = organized._cell_fits(x, y, z, valid, cfg, noise)
    _, degree = organized._link_cells(cells, grid.rows, grid.cols, cfg)
    member = np.flatnonzero(cells.planar)
    min_px = 0.5 * cfg.min_plane_points
    expected = _grow_regions_numpy(cells, member, degree, grid.rows, grid.cols, min_px, cfg)
    got = organized._grow_regions(cells, member, degree, grid.rows, grid.cols, min_px, cfg)
    assert len(expected) >= 2 and len(got) == len(expected)
    for region, (idx, count, normal, d) in zip(got, expected, strict=True):
        assert np.array_equal(region.cells, idx) and region.count == count
        np.testing.assert_allclose(region.normal, normal, atol=1e-12)
        assert abs(region.d - d) <= 1e-12
