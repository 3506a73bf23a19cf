"""Map planes that came to lie on one segment merge into one (moments, outline, edges and
corners joined); planes apart, offset or tilted beyond the gates stay separate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from planeslam.core.plane_fit import moments_of, plane_from_moments
from planeslam.frontend.config import ObjectConfig
from planeslam.mapping.config import MapConfig
from planeslam.mapping.contents import MapContents
from planeslam.mapping.records import MapCorner, MapEdge, MapPlane
from planeslam.mapping.seating import hull_on_plane
from planeslam.mapping.segment_merge import merge_same_segments

pytestmark = pytest.mark.unit


def patch(pid: int, corner: list[float], u: list[float], v: list[float], obs: int) -> MapPlane:
    """A map plane of a 21 x 21 grid of points spanning corner + [0, 1] u + [0, 1] v [m],
    normal along u x v."""
    s, t = np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21))
    points = np.asarray(corner) + s.reshape(-1, 1) * u + t.reshape(-1, 1) * np.asarray(v)
    count, centroid, scatter = moments_of(points)
    normal, d, _ = plane_from_moments(centroid, scatter)
    if normal @ np.cross(u, v) < 0:  # facing the side a camera saw it from: u x v
        normal, d = -normal, -d
    outline, area = hull_on_plane(points, normal, d)
    return MapPlane(pid, normal, d, centroid, scatter, count, area, outline, obs)


def edge(a: int, b: int, x0: float, x1: float) -> MapEdge:
    """An edge along the x axis (floor meets the wall y = 0) from x0 to x1 [m]."""
    segment = np.array([[x0, 0.0, 0.0], [x1, 0.0, 0.0]])
    return MapEdge((a, b), segment, x1 - x0, np.pi / 2, False, 2)


def contents_with(*planes: MapPlane) -> MapContents:
    contents = MapContents(MapConfig(), ObjectConfig())
    contents.planes = {p.id: p for p in planes}
    contents.next_plane_id = max(p.id for p in planes) + 1
    return contents


def test_two_patches_of_one_floor_merge_with_their_edges_and_corners() -> None:
    floor = patch(0, [0, 0, 0], [1, 0, 0], [0, 1, 0], obs=5)
    near = patch(1, [1.05, 0, 0.004], [0.6, 0, 0], [0, 1, 0], obs=2)  # 5 cm on, 4 mm up
    wall = patch(2, [0, 0, 0], [0, 0, 1], [1.6, 0, 0], obs=4)  # y = 0, normal +y
    side = patch(3, [0, 0, 0], [0, 1, 0], [0, 0, 1], obs=4)  # x = 0, normal +x
    contents = contents_with(floor, near, wall, side)
    contents.edges = {(0, 2): edge(0, 2, 0.0, 1.0), (1, 2): edge(1, 2, 1.05, 1.65)}
    contents.corners = {
        7: MapCorner(7, (0, 2, 3), np.zeros(3), 0, 3),
        8: MapCorner(8, (1, 2, 3), np.array([0.03, 0.0, 0.0]), 0, 1),  # a stray copy
    }
    assert merge_same_segments(contents, [1]) == {1: 0}  # the plane seen more often stays
    assert sorted(contents.planes) == [0, 2, 3]
    joined = contents.planes[0]
    assert joined.num_points == 2 * 441 and joined.observations == 7
    assert abs(joined.area_m2 - 1.65) < 0.01  # the hull of both outlines
    assert list(contents.edges) == [(0, 2)]
    assert contents.edges[(0, 2)].length_m == 1.0 and contents.edges[(0, 2)].observations == 4
    assert list(contents.corners) == [7]
    np.testing.assert_allclose(contents.corners[7].point, [0.0075, 0.0, 0.0])
    assert contents.corners[7].observations == 4


def test_planes_apart_offset_or_tilted_stay_separate() -> None:
    floor = patch(0, [0, 0, 0], [1, 0, 0], [0, 1, 0], obs=5)
    far = patch(1, [1.5, 0, 0], [1, 0, 0], [0, 1, 0], obs=1)  # 50 cm away on the same plane
    shelf = patch(2, [0, 0, 0.03], [1, 0, 0], [0, 1, 0], obs=1)  # over it, 3 cm up
    tilted = patch(3, [1.05, 0, 0], [1, 0, 0.07], [0, 1, 0], obs=1)  # adjacent, 4 deg
    contents = contents_with(floor, far, shelf, tilted)
    assert merge_same_segments(contents, [0, 1, 2, 3]) == {}
    assert sorted(contents.planes) == [0, 1, 2, 3]
    off = MapContents(MapConfig(merge_segments_max_offset_m=0.05), ObjectConfig())
    off.planes = {p.id: p for p in (floor, shelf)}
    assert merge_same_segments(off, [2]) == {2: 0}  # a wider gate takes the shelf in


def test_planes_seen_apart_in_one_frame_stay_two_segments() -> None:
    # Two segments of one floor that one frame saw apart (left and right of a cupboard)
    # stay two map planes, however close: merged, every later frame would see two planes
    # for one and make the second a new one.
    left = replace(patch(0, [0, 0, 0], [1, 0, 0], [0, 1, 0], obs=2), seen_in=frozenset({3, 4}))
    right = replace(patch(1, [1.05, 0, 0], [0.6, 0, 0], [0, 1, 0], obs=1), seen_in=frozenset({4}))
    contents = contents_with(left, right)
    assert merge_same_segments(contents, [1]) == {}
    assert sorted(contents.planes) == [0, 1]
    contents.planes[1] = replace(right, seen_in=frozenset({5}))  # never seen together
    assert merge_same_segments(contents, [1]) == {1: 0}
    assert contents.planes[0].seen_in == frozenset({3, 4, 5})
