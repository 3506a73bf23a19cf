"""Shared plane geometry: the 2-D convex hull that outlines and map planes are built on."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from planeslam.core.geometry import (
    clip_convex_polygon,
    convex_hull_2d,
    convex_polygon_gap,
    polygon_area,
)

pytestmark = pytest.mark.unit


def test_the_hull_is_qhulls_counter_clockwise_ring_of_the_same_points() -> None:
    """Seeded point sets of 3-300 points, far from the origin and of many sizes: the same
    vertices as scipy's Qhull, rows of the input, turning counter-clockwise."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        k = int(rng.integers(3, 300))
        points = rng.normal(size=(k, 2)) * rng.uniform(0.01, 5.0) + rng.normal(size=2) * 3.0
        ring = convex_hull_2d(points)
        qhull = ConvexHull(points)
        expected = points[qhull.vertices]
        assert {tuple(p) for p in ring} == {tuple(p) for p in expected}
        assert len(ring) == len(expected)
        edges = np.roll(ring, -1, axis=0) - ring
        following = np.roll(edges, -1, axis=0)
        turns = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
        assert np.all(turns > 0)
        assert polygon_area(ring) == pytest.approx(qhull.volume, rel=1e-12)


def test_points_on_a_hull_edge_are_not_vertices() -> None:
    """A pixel grid's border points between its corners lie on the hull's edges."""
    grid = np.stack(np.meshgrid(np.arange(10.0), np.arange(5.0)), axis=-1).reshape(-1, 2)
    ring = convex_hull_2d(0.01 * grid + 2.0)
    assert {tuple(np.round(p, 9)) for p in ring} == {
        (2.0, 2.0),
        (2.09, 2.0),
        (2.09, 2.04),
        (2.0, 2.04),
    }


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((0, 2)),
        np.array([[0.0, 0.0], [1.0, 1.0]]),
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]),
        np.full((5, 2), 1.5),
    ],
    ids=["empty", "two points", "collinear", "coincident"],
)
def test_points_that_span_no_area_have_no_hull(points: np.ndarray) -> None:
    assert convex_hull_2d(points).shape == (0, 2)


def test_the_gap_is_zero_exactly_where_the_polygons_clip_to_something() -> None:
    """`convex_polygon_gap`'s overlap test (separating edges) against Sutherland-Hodgman
    clipping, on 500 seeded pairs of hulls, overlapping, apart and nested."""
    rng = np.random.default_rng(11)
    overlapping = 0
    for _ in range(500):
        a = convex_hull_2d(rng.normal(size=(int(rng.integers(3, 16)), 2)))
        b = convex_hull_2d(
            rng.normal(size=(int(rng.integers(3, 16)), 2)) * rng.uniform(0.05, 1.0)
            + rng.normal(size=2) * 2.0
        )
        clipped = len(clip_convex_polygon(a, b)) > 0
        gap = convex_polygon_gap(a, b)
        assert (gap == 0.0) == clipped and gap >= 0.0
        overlapping += clipped
    assert 100 < overlapping < 400


def test_cross_is_numpys_bit_for_bit() -> None:
    from planeslam.core.geometry import cross

    rng = np.random.default_rng(5)
    for shape_a, shape_b in (
        ((3,), (3,)),
        ((7, 3), (7, 3)),
        ((4, 1, 2, 3), (5, 1, 3)),
        ((6, 3), (3,)),
    ):
        a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
        assert np.array_equal(cross(a, b), np.cross(a, b))
