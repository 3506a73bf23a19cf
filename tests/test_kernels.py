"""The compiled front-end kernels against the numpy and scipy code they replace: the same
results bit for bit (labels, counts, sums, points and their order) on seeded random input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse.csgraph import connected_components

from planeslam.frontend import kernels

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
        assert np.array_equal(kernels.dense_components_kernel(linked), expected)


def test_flood_fill_matches_ndimage_label(rng):
    rows, cols = 9, 13
    for _ in range(20):
        fit = rng.random(rows * cols) < 0.55
        seed = int(rng.integers(rows * cols))
        fit[seed] = True
        comp, _ = ndimage.label(fit.reshape(rows, cols))
        expected = np.flatnonzero(comp.ravel() == comp.ravel()[seed])
        assert np.array_equal(kernels.flood_fill_kernel(fit, rows, cols, seed), expected)


def test_group_sums_match_bincount(rng):
    cells, groups = 50, 4
    group = rng.integers(-1, groups, cells)
    count = rng.integers(0, 256, cells)
    mean = rng.normal(size=(cells, 3))
    a = rng.normal(size=(cells, 3, 3))
    scatter = a @ a.transpose(0, 2, 1)
    total, first, second = kernels.group_sums_kernel(group, count, mean, scatter, groups)
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
    comp, degree = kernels.link_cells_kernel(
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
