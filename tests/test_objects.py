"""Plane graph, trihedral angles, objects, classes and sizes (paper 4.2-4.3)."""

from __future__ import annotations

import json

import networkx as nx
import numpy as np
import pytest
from test_intersections import (
    BOX_FRAMES,
    _wedge,
    plane_from_points,
    rendered,
    segmentation_from_render,
)

from planeslam.core.errors import ConfigError
from planeslam.core.geometry import invert_pose, transform_points
from planeslam.core.types import GravitySource
from planeslam.frontend.config import ObjectConfig
from planeslam.frontend.intersections import Edge
from planeslam.frontend.objects import (
    DEFAULT_PATTERNS,
    MAP_SCHEMA,
    ObjectPattern,
    build_structure,
    classify_object,
    measure_size,
    to_map_dict,
)
from planeslam.frontend.plane_graph import (
    aggregate_corners,
    build_plane_graph,
    estimate_gravity,
    find_corners,
    find_triangles,
    plane_orientation,
    snap_edges_to_corners,
)
from planeslam.frontend.types import Plane, Segmentation

pytestmark = pytest.mark.unit

UP = np.array([0.0, -1.0, 0.0])


# --------------------------------------------------------------------------- graph pieces


def test_triangles_match_networkx_simple_cycles(rng):
    for _ in range(20):
        g = nx.gnp_random_graph(12, 0.35, seed=int(rng.integers(1 << 30)))
        expected = sorted(tuple(sorted(c)) for c in nx.simple_cycles(g, length_bound=3))
        assert find_triangles(g) == expected
    assert find_triangles(nx.Graph()) == []


def test_aggregation_example_of_the_paper():
    """Sec. 4.2: 2-3-7, 2-9-7, 2-6-3, 3-7-5, 2-9-6, 5-9-7 form one object."""
    paper = [(2, 3, 7), (2, 9, 7), (2, 6, 3), (3, 7, 5), (2, 9, 6), (5, 9, 7)]
    others = [(2, 20, 21), (30, 31, 32), (31, 32, 33)]  # shares only plane 2 / its own edge
    groups = aggregate_corners(paper + others)
    assert groups == [[0, 1, 2, 3, 4, 5], [6], [7, 8]]
    assert aggregate_corners([]) == []


def test_plane_orientation():
    assert plane_orientation(np.array([0.0, -1.0, 0.0]), UP, 15.0) == ("horizontal", "up")
    assert plane_orientation(np.array([0.0, 1.0, 0.0]), UP, 15.0) == ("horizontal", "down")
    assert plane_orientation(np.array([0.0, 0.0, -1.0]), UP, 15.0) == ("vertical", "")
    tilted = np.array([0.0, -np.cos(0.6), -np.sin(0.6)])  # 34 deg off up
    assert plane_orientation(tilted, UP, 15.0) == ("slanted", "")


def _plane(pid: int, normal, d: float, area: float = 1.0) -> Plane:
    """A plane record without real inliers (graph-level tests only)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    pts = np.tile(-d * n, (3, 1))
    return Plane(
        id=pid, normal=n, d=d, points=pts, centroid=pts[0], covariance=np.eye(3),
        scatter=np.eye(3), num_points=3, area_m2=area, outline=pts,
    )  # fmt: skip


def test_gravity_estimate():
    pitch = np.deg2rad(33.0)  # camera looking 33 deg down at a floor 0.5 m below
    floor_n = np.array([0.0, -np.cos(pitch), -np.sin(pitch)])
    wall_n = np.array([0.0, -np.sin(pitch), -np.cos(pitch)])
    gravity = estimate_gravity([_plane(0, wall_n, 2.0, 5.0), _plane(1, floor_n, 0.5, 2.0)])
    np.testing.assert_allclose(gravity.up_cam, floor_n)
    assert (gravity.source, gravity.plane_id) == (GravitySource.PLANE, 1)
    assert not gravity.source.is_fallback
    ceiling = estimate_gravity([_plane(0, [0.0, 1.0, -0.1], 1.0)])  # up = -normal
    assert ceiling.up_cam[1] < -0.99 and ceiling.plane_id == 0
    fallback = estimate_gravity([_plane(0, wall_n, 2.0)])
    np.testing.assert_allclose(fallback.up_cam, UP)
    assert (fallback.source, fallback.plane_id) == (GravitySource.CAMERA, None)
    assert fallback.source.is_fallback and str(fallback.source).startswith("camera")


def _edge(i: int, j: int, a, b, convex: bool) -> Edge:
    seg = np.array([a, b], dtype=np.float64)
    return Edge((i, j), seg, float(np.linalg.norm(seg[1] - seg[0])), 0.0, np.pi / 2, convex, 100)


def _box_graph(convex: bool = True, up=UP, size=(0.4, 0.3, 0.2)) -> nx.Graph:
    """Corner of three axis-aligned planes (camera frame, y down) at point c: a box's
    top + side + front (convex) or a room's floor + wall + back wall (concave),
    with edges of lengths `size` along x, y, z."""
    lx, ly, lz = size
    ex, ey, ez = np.eye(3)
    if convex:
        c = np.array([0.3, 0.3, 2.0])
        normals = [-ey, -ex, -ez]
        ends = [c + lz * ez, c + lx * ex, c + ly * ey]
    else:
        c = np.array([-0.3, 0.3, 2.0])
        normals = [-ey, ex, -ez]
        ends = [c - lz * ez, c + lx * ex, c - ly * ey]
    planes = [_plane(k, n, float(-n @ c)) for k, n in enumerate(normals)]
    edges = [_edge(0, 1, c, ends[0], convex), _edge(0, 2, c, ends[1], convex),
             _edge(1, 2, c, ends[2], convex)]  # fmt: skip
    return build_plane_graph(planes, edges, up, 15.0)


def test_corner_point_and_virtual_corners():
    g = _box_graph()
    (corner,) = find_corners(g, min_det=0.2, tol_m=0.05)
    assert corner.planes == (0, 1, 2)
    np.testing.assert_allclose(corner.point, [0.3, 0.3, 2.0], atol=1e-9)
    assert corner.convex_edges == 3
    # Move one edge 0.3 m away from the corner: the triple is a virtual corner.
    seg = g.edges[0, 2]["segment"]
    g.edges[0, 2]["segment"] = seg + np.array([0.3, 0.0, 0.0])
    assert find_corners(g, tol_m=0.05) == []
    assert len(find_corners(g, tol_m=0.5)) == 1


def test_edge_ends_snap_to_their_corner():
    """Ends within corner_tol_m of a corner move onto it (overshoot and shortfall);
    an end far from it (a T-junction) stays."""
    g = _box_graph(size=(0.4, 0.3, 0.2))
    c = np.array([0.3, 0.3, 2.0])
    ex, ey, ez = np.eye(3)
    edges = [
        _edge(0, 1, c - 0.02 * ez, c + 0.2 * ez, True),  # 2 cm past the corner
        _edge(0, 2, c + 0.03 * ex, c + 0.4 * ex, True),  # stops 3 cm short of it
        _edge(1, 2, c + 0.1 * ey, c + 0.3 * ey, True),  # 10 cm away: T-junction, kept
    ]
    for e in edges:
        g.edges[e.planes]["segment"] = e.segment
    (corner,) = find_corners(g, tol_m=0.12)
    snapped = snap_edges_to_corners(g, [corner], edges, tol_m=0.05)
    assert [e.length_m for e in snapped] == pytest.approx([0.2, 0.4, 0.2])
    np.testing.assert_allclose(snapped[0].segment[0], c, atol=1e-9)
    np.testing.assert_allclose(snapped[1].segment[0], c, atol=1e-9)
    np.testing.assert_allclose(snapped[2].segment, edges[2].segment)
    assert g.edges[0, 1]["length_m"] == pytest.approx(0.2)
    np.testing.assert_allclose(g.edges[0, 2]["segment"], snapped[1].segment)


def test_ill_conditioned_triple_is_not_a_corner():
    planes = [_plane(0, [0, -1, 0], 1.0), _plane(1, [0, -1, -0.1], 1.0), _plane(2, [-1, 0, 0], 1.0)]
    z = np.zeros(3)
    edges = [_edge(0, 1, z, z + 1, True), _edge(0, 2, z, z + 1, True), _edge(1, 2, z, z + 1, True)]
    g = build_plane_graph(planes, edges, UP, 15.0)
    assert find_corners(g, min_det=0.2, tol_m=10.0) == []


# --------------------------------------------------------------------------- classification


def test_patterns_box_room_structure_unknown():
    assert classify_object(_box_graph(convex=True))[0] == "box"
    assert classify_object(_box_graph(convex=False))[0] == "room"
    mixed = _box_graph(convex=False)
    mixed.edges[1, 2]["convex"] = True  # a floor with two panels meeting in a convex edge
    assert classify_object(mixed)[0] == "structure"
    # Convex corner whose planes are all slanted (camera up mistaken): no pattern.
    slanted = _box_graph(up=np.array([1.0, -1.0, 1.0]) / np.sqrt(3))
    assert classify_object(slanted)[0] == "unknown"


def test_first_matching_pattern_wins_and_table_is_extendable():
    g = _box_graph(convex=True)
    g.add_node(3, normal=np.array([0.0, -1.0, 0.0]), d=0.5, area_m2=4.0,
               orientation="horizontal", facing="up")  # fmt: skip
    g.add_edge(3, 1, convex=False, length_m=0.3, segment=np.zeros((2, 3)))
    g.add_edge(3, 2, convex=False, length_m=0.4, segment=np.zeros((2, 3)))
    assert classify_object(g)[0] == "box"  # box and structure both match
    assert classify_object(g, DEFAULT_PATTERNS[::-1])[0] == "structure"
    two_floors = ObjectPattern(
        "table_on_floor",
        nodes=({"orientation": "horizontal"}, {"orientation": "horizontal"}),
        edges=(),
    )
    assert classify_object(g, (two_floors,) + DEFAULT_PATTERNS)[0] == "table_on_floor"
    assert classify_object(g, (two_floors,))[0] == "table_on_floor"


def test_measure_size_from_edges_and_parallel_planes():
    g = _box_graph(size=(0.4, 0.3, 0.2))
    assert measure_size(g, {0, 1, 2}, {0, 1, 2}, 20.0) == pytest.approx((0.4, 0.3, 0.2))
    # A parallel opposite face 0.5 m away bounds that dimension when larger than its edge.
    g.add_node(3, normal=np.array([0.0, 0.0, 1.0]), d=-2.5, area_m2=1.0,
               orientation="vertical", facing="")  # fmt: skip  # the face z = 2.5
    assert measure_size(g, {0, 1, 2, 3}, {0, 1, 2, 3}, 20.0) == pytest.approx((0.5, 0.4, 0.3))


BAD_OBJECT_CONFIGS = [
    {"gravity_up_cam": (0.0, 1.0)},
    {"gravity_up_cam": (0.0, 0.0, 0.0)},
    {"orientation_tol_deg": 0.0},
    {"corner_min_det": 0.0},
    {"corner_tol_m": -1.0},
]


@pytest.mark.parametrize("bad", BAD_OBJECT_CONFIGS)
def test_object_config_rejects_bad_values(bad):
    with pytest.raises(ConfigError):
        ObjectConfig(**bad)


# --------------------------------------------------------------------------- whole frames


def _names(scene, sids, ids):
    return sorted(scene.planes[sids[k]].name for k in ids)


@pytest.mark.parametrize("frame_index", BOX_FRAMES)
def test_box_in_room_frame(frame_index):
    scene, T, frame = rendered("box_room_circle", frame_index)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    st = build_structure(seg)
    assert st.reason == ""
    assert st.gravity_source is GravitySource.PLANE
    floor = st.gravity_plane_id
    assert floor is not None and _names(scene, sids, [floor]) == ["room.floor"]
    up_true = invert_pose(T)[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(st.gravity_up_cam @ up_true)) < 1.0

    boxes = [o for o in st.objects if o.cls == "box"]
    rooms = [o for o in st.objects if o.cls == "room"]
    assert len(boxes) == 1 and len(rooms) == 1, [(o.cls, o.planes) for o in st.objects]
    box_planes = _names(scene, sids, boxes[0].planes)
    assert "box.top" in box_planes and "room.floor" in box_planes  # floor joins via its corner
    np.testing.assert_allclose(boxes[0].size_m, (0.38, 0.29, 0.19), atol=0.01)
    assert "room.floor" in _names(scene, sids, rooms[0].planes)

    # Corners: every one is a true corner within 2 cm; convexity patterns as expected.
    truth = {c.plane_ids: transform_points(invert_pose(T), c.point[None])[0] for c in scene.corners}
    patterns = {}
    for c in st.corners:
        key = tuple(sorted(sids[k] for k in c.planes))
        assert key in truth
        assert np.linalg.norm(c.point - truth[key]) < 0.02, _names(scene, sids, c.planes)
        patterns[tuple(_names(scene, sids, c.planes))] = c.convex_edges
    top = [k for k in patterns if "box.top" in k]
    assert len(top) == 1 and patterns[top[0]] == 3
    assert all(v == 0 for k, v in patterns.items() if all(n.startswith("room.") for n in k))
    assert all(v == 1 for k, v in patterns.items() if "room.floor" in k and "box.top" not in k
               and any(n.startswith("box.") for n in k))  # fmt: skip


def test_room_corner_alone_is_a_room():
    scene, T, frame = rendered("box_room_circle", 9)
    keep = [p.id for p in scene.planes if p.name.startswith("room.")]
    plane_id = np.where(np.isin(frame.plane_id, keep), frame.plane_id, -1)
    seg, sids = segmentation_from_render(plane_id, frame.depth_m)
    st = build_structure(seg)
    assert [o.cls for o in st.objects] == ["room"]
    assert st.corners[0].convex_edges == 0
    assert all(not e.convex for e in st.edges)


def test_given_gravity_is_used():
    scene, T, frame = rendered("box_room_circle", 3)
    seg, _ = segmentation_from_render(frame.plane_id, frame.depth_m)
    up_true = invert_pose(T)[:3, :3] @ np.array([0.0, 0.0, 1.0])
    st = build_structure(seg, object_config=ObjectConfig(gravity_up_cam=tuple(up_true * 2.0)))
    assert st.gravity_source is GravitySource.CONFIG and st.gravity_plane_id is None
    np.testing.assert_allclose(st.gravity_up_cam, up_true)
    assert sorted(o.cls for o in st.objects) == ["box", "room"]
    # A wrong up (camera z) turns walls horizontal: no box or room pattern matches.
    st = build_structure(seg, object_config=ObjectConfig(gravity_up_cam=(0.0, 0.0, -1.0)))
    assert "box" not in [o.cls for o in st.objects]


def test_zigzag_panels_are_a_structure():
    scene, T, frame = rendered("zigzag_panels", 40)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    st = build_structure(seg)
    (obj,) = [o for o in st.objects if any("zigzag" in n for n in _names(scene, sids, o.planes))]
    assert obj.cls == "structure"
    truth = scene.object_by_name("zigzag").size_m
    assert obj.size_m[1] == pytest.approx(truth[1], abs=0.03)  # panel height 0.8 m
    assert obj.size_m[0] == pytest.approx(truth[0], abs=0.2)  # along the zig-zag


def test_several_boxes_in_a_room():
    scene, T, frame = rendered("room_boxes_loop", 0)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    st = build_structure(seg)
    boxes = [o for o in st.objects if o.cls == "box"]
    assert boxes
    for o in boxes:
        owners = {scene.planes[sids[k]].object_id for k in o.planes if
                  not scene.planes[sids[k]].name.startswith("room.")}  # fmt: skip
        assert len(owners) == 1
        truth = scene.objects[owners.pop()].size_m
        np.testing.assert_allclose(o.size_m, truth, atol=0.015)


# --------------------------------------------------------------------------- bad input, schema


def test_degenerate_frames_have_reasons(rng):
    seg, _ = _wedge(90.0, True, rng)
    empty = Segmentation(planes=[], labels=np.full((4, 4), -1, dtype=np.int32))
    one = Segmentation(planes=seg.planes[:1], labels=np.where(seg.labels == 0, 0, -1))
    p = seg.planes[0]
    shifted = Plane(**{**p.__dict__, "id": 1, "d": p.d + 0.3, "points": p.points - 0.3 * p.normal})
    parallel = Segmentation(planes=[p, shifted], labels=seg.labels)
    cases = {"no planes": empty, "only one plane": one, "nearly parallel": parallel,
             "no trihedral corner": seg}  # fmt: skip
    for words, s in cases.items():
        st = build_structure(s)
        assert words in st.reason
        assert st.objects == [] and st.corners == []
        json.dumps(to_map_dict(s, st))
    assert len(build_structure(seg).edges) == 1


def test_map_dict_schema_and_plain_types():
    scene, T, frame = rendered("box_room_circle", 15)
    seg, _ = segmentation_from_render(frame.plane_id, frame.depth_m)
    st = build_structure(seg)
    data = to_map_dict(seg, st)
    text = json.dumps(data)  # no numpy scalars or arrays anywhere
    assert json.loads(text) == data
    assert data["schema"] == MAP_SCHEMA
    assert set(data) == {"schema", "planes", "edges", "corners", "objects"}
    assert set(data["planes"][0]) == {"id", "normal", "d", "area_m2", "outline"}
    assert set(data["edges"][0]) == {"planes", "length_m", "segment", "convex"}
    assert set(data["corners"][0]) == {"planes", "point"}
    assert set(data["objects"][0]) == {"id", "class", "planes", "size_m"}
    assert len(data["planes"]) == len(seg.planes)
    for o in data["objects"]:
        assert o["size_m"] == sorted(o["size_m"], reverse=True)
    assert np.array(data["edges"][0]["segment"]).shape == (2, 3)


def test_structure_stages_each_lap_once_and_repeat_exactly():
    """The four stages report one lap each (the front end times them with it; timing
    itself is `planeslam bench`'s job) and give the same structure on every call."""
    scene, T, frame = rendered("box_room_circle", 9)
    seg, _ = segmentation_from_render(frame.plane_id, frame.depth_m)
    laps: list[int] = []
    first = to_map_dict(seg, build_structure(seg, lap=lambda: laps.append(1)))
    assert len(laps) == 4
    assert {o["class"] for o in first["objects"]} >= {"box"}
    for _ in range(3):
        assert to_map_dict(seg, build_structure(seg)) == first


def test_plane_from_points_helper_is_exact(rng):
    """The test helper itself: exact plane from noise-free points, normal toward the camera."""
    pts = np.column_stack([rng.uniform(-1, 1, 500), np.full(500, 0.7), rng.uniform(1, 3, 500)])
    p = plane_from_points(0, pts, pts / pts[:, 2:3], pts[:, 2])
    np.testing.assert_allclose(p.normal, [0.0, -1.0, 0.0], atol=1e-9)
    assert p.d == pytest.approx(0.7)


def _room_graph(with_ceiling: bool):
    """Floor z = 0 (normal up), walls x = 0 and y = 0, optionally a ceiling z = 2.5;
    vertical corner edge seen only up to 0.3 m (a low camera)."""
    import networkx as nx

    g = nx.Graph()
    g.add_node(0, normal=np.array([0.0, 0.0, 1.0]), d=0.0)
    g.add_node(1, normal=np.array([1.0, 0.0, 0.0]), d=0.0)
    g.add_node(2, normal=np.array([0.0, 1.0, 0.0]), d=0.0)

    def edge(a, b, p, q):
        seg = np.array([p, q], dtype=float)
        g.add_edge(a, b, segment=seg, length_m=float(np.linalg.norm(seg[1] - seg[0])))

    edge(0, 1, [0, 0, 0], [0, 3.5, 0])
    edge(0, 2, [0, 0, 0], [4.0, 0, 0])
    edge(1, 2, [0, 0, 0], [0, 0, 0.3])
    if with_ceiling:
        g.add_node(3, normal=np.array([0.0, 0.0, -1.0]), d=2.5)
        edge(3, 1, [0, 0, 2.5], [0, 3.5, 2.5])
    return g


@pytest.mark.parametrize(
    ("with_ceiling", "expected"), [(False, (4.0, 3.5)), (True, (4.0, 3.5, 2.5))]
)
def test_room_height_only_when_floor_and_ceiling_bound_it(with_ceiling, expected) -> None:
    from planeslam.frontend.objects import measure_size

    g = _room_graph(with_ceiling)
    planes = set(g.nodes)
    up = np.array([0.0, 0.0, 1.0])
    size = measure_size(g, planes, planes, 10.0, up, height_needs_bound=True)
    np.testing.assert_allclose(size, expected, atol=1e-9)
    # Without the rule the visible 0.3 m of the vertical edge would pass for the height.
    assert measure_size(g, planes, planes, 10.0)[-1] == pytest.approx(
        0.3 if not with_ceiling else 2.5
    )
