"""The world map: exact merging from sufficient statistics, edges, corners, objects,
persistence, backend updates, PLY export, memory, and the paper's box-in-a-room run."""

from __future__ import annotations

import json
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from planeslam.core.errors import AssociationError, ConfigError, MapError
from planeslam.core.geometry import invert_pose, pose_from_quat, transform_points
from planeslam.core.plane_fit import moments_of, plane_from_moments
from planeslam.core.types import GravitySource
from planeslam.frontend.intersections import Edge
from planeslam.frontend.objects import FrameStructure
from planeslam.frontend.pipeline import FrameObservation
from planeslam.frontend.plane_graph import Corner
from planeslam.frontend.types import Plane, Segmentation
from planeslam.mapping.config import MapConfig
from planeslam.mapping.gravity import UpOrigin, UpSource
from planeslam.mapping.seating import hull_on_plane, seat_segments
from planeslam.mapping.world_map import Map
from planeslam.sim.scenes import get_scene

pytestmark = pytest.mark.unit

UP = np.array([0.0, 0.0, 1.0])


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    q = rng.normal(size=4)
    return pose_from_quat(rng.normal(scale=scale, size=3), q / np.linalg.norm(q))


def make_plane(
    pid: int,
    points_cam: np.ndarray,
    outline_cam: np.ndarray | None = None,
    orient: np.ndarray | None = None,
) -> Plane:
    """A front-end-like Plane fitted on (K, 3) camera-frame points; the normal faces the
    camera, or points like `orient` (3,) when given (a synthetic scene's visible side)."""
    count, centroid, scatter = moments_of(points_cam)
    n, d, _ = plane_from_moments(centroid, scatter)
    if orient is not None and n @ orient < 0:
        n, d = -n, -d
    if outline_cam is None:
        outline_cam, area = hull_on_plane(points_cam, n, d)
    else:
        area = hull_on_plane(outline_cam, n, d)[1]
    return Plane(
        id=pid,
        normal=n,
        d=d,
        points=points_cam,
        centroid=centroid,
        covariance=np.eye(3),
        scatter=scatter,
        num_points=count,
        area_m2=area,
        outline=outline_cam,
    )


def observation(
    planes: list[Plane],
    edges: list[Edge] = (),  # type: ignore[assignment]
    corners: list[Corner] = (),  # type: ignore[assignment]
    up_cam: np.ndarray | None = None,
    timestamp: float = 0.0,
    gravity_source: GravitySource = GravitySource.PLANE,
) -> FrameObservation:
    structure = FrameStructure(
        edges=list(edges),
        graph=nx.Graph(),
        corners=list(corners),
        objects=[],
        gravity_up_cam=np.array([0.0, -1.0, 0.0]) if up_cam is None else up_cam,
        gravity_source=gravity_source,
    )
    seg = Segmentation(planes=planes, labels=np.zeros((1, 1), dtype=np.int32))
    return FrameObservation(timestamp, seg, structure, {})


def rect_points(corner: np.ndarray, u: np.ndarray, v: np.ndarray, n: int = 12) -> np.ndarray:
    """(n*n, 3) grid over the parallelogram corner + s u + t v, s, t in [0, 1]."""
    s, t = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    return corner + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v


def scene_observation(
    plane_ids: list[int], T_world_cam: np.ndarray, scene_name: str = "box_room_circle"
) -> tuple[FrameObservation, list[int]]:
    """An exact observation of some planes of a synthetic scene (with their edges and
    corners among them) in the camera frame T_world_cam; returns it and the scene ids of
    its planes in order."""
    scene, _ = get_scene(scene_name, 1, np.random.default_rng(0))
    T_cam_world = invert_pose(T_world_cam)
    index = {pid: k for k, pid in enumerate(plane_ids)}
    planes = []
    for pid in plane_ids:
        sp = scene.planes[pid]
        poly = sp.polygon
        pts = rect_points(poly[0], poly[1] - poly[0], poly[3] - poly[0])
        plane = make_plane(
            index[pid], transform_points(T_cam_world, pts), orient=T_cam_world[:3, :3] @ sp.normal
        )
        planes.append(plane)
    object_of = {p.id: p.object_id for p in scene.planes}
    box = scene.object_by_name("box").id
    edges = []
    for e in scene.edges:
        if all(p in index for p in e.plane_ids):
            i, j = sorted(index[p] for p in e.plane_ids)
            convex = all(object_of[p] == box for p in e.plane_ids)
            edges.append(
                Edge(
                    planes=(i, j),
                    segment=transform_points(T_cam_world, e.segment),
                    length_m=e.length_m,
                    length_eq6_m=e.length_m,
                    angle_rad=np.pi / 2,
                    convex=convex,
                    num_points=100,
                )
            )
    corners = []
    for c in scene.corners:
        if all(p in index for p in c.plane_ids):
            tri = tuple(sorted(index[p] for p in c.plane_ids))
            convex = sum(
                all(object_of[p] == box for p in pair)
                for pair in (
                    (c.plane_ids[0], c.plane_ids[1]),
                    (c.plane_ids[0], c.plane_ids[2]),
                    (c.plane_ids[1], c.plane_ids[2]),
                )
            )
            corners.append(
                Corner(
                    planes=tri,
                    point=transform_points(T_cam_world, c.point[None])[0],
                    convex_edges=int(convex),
                )
            )
    up_cam = T_cam_world[:3, :3] @ UP
    return observation(planes, edges, corners, up_cam), plane_ids


# ----------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("voxel_m", 0.0),
        ("sparse_max_points", -1),
        ("merge_max_angle_deg", 0.0),
        ("min_observations", 0),
        ("derive_corners", "yes"),
    ],
)
def test_config_rejects_bad_values_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=f"map.{key}"):
        MapConfig(**{key: value})


# ----------------------------------------------------------------------------- planes


def test_merging_two_views_equals_the_fit_on_the_union_of_points(rng):
    """Two noisy patches of one world plane seen from two poses: the map plane is exactly
    the least-squares plane of all points stacked in the world frame."""
    n_true = np.array([0.3, -0.2, 0.93])
    n_true /= np.linalg.norm(n_true)
    axes = np.linalg.svd(n_true[None])[2][1:]
    base = -0.8 * n_true
    a = base + rng.uniform(-1, 0.3, (400, 2)) @ axes + rng.normal(0, 0.004, (400, 1)) * n_true
    b = base + rng.uniform(-0.2, 1, (300, 2)) @ axes + rng.normal(0, 0.004, (300, 1)) * n_true
    T1, T2 = random_pose(rng), random_pose(rng)
    # both cameras on the visible side of the plane (n . eye + d > 0)
    T1[:3, 3] = base + 1.5 * n_true + rng.normal(0, 0.3, 3)
    T2[:3, 3] = base + 1.2 * n_true + rng.normal(0, 0.3, 3)
    m = Map()
    first = m.merge(observation([make_plane(0, transform_points(invert_pose(T1), a))]), T1)
    pid = first.planes[0]
    n_before = m.planes[pid].normal.copy()
    m.merge(observation([make_plane(0, transform_points(invert_pose(T2), b))]), T2, [(0, pid)])
    count, c, S = moments_of(np.concatenate([a, b]))
    n, d, _ = plane_from_moments(c, S)
    if n @ n_before < 0:
        n, d = -n, -d
    p = m.planes[pid]
    assert len(m.planes) == 1 and p.observations == 2 and p.num_points == count == 700
    np.testing.assert_allclose(p.centroid, c, atol=1e-9)
    np.testing.assert_allclose(p.scatter, S, atol=1e-9)
    np.testing.assert_allclose(p.normal, n, atol=1e-9)
    assert p.d == pytest.approx(d, abs=1e-9)


def test_merged_outline_is_the_hull_of_both_outlines_on_the_plane(rng):
    T1, T2 = random_pose(rng), random_pose(rng)
    T1[:3, 3], T2[:3, 3] = [0.5, 0.5, 1.5], [1.0, 0.3, 2.0]  # above the plane z = 0
    u, v = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    a = rect_points(np.zeros(3), u, v)  # [0, 1] x [0, 1] on z = 0
    b = rect_points(np.array([0.5, 0.2, 0.0]), 1.5 * u, 0.8 * v)  # [0.5, 2] x [0.2, 1]
    m = Map()
    pid = m.merge(observation([make_plane(0, transform_points(invert_pose(T1), a))]), T1).planes[0]
    m.merge(observation([make_plane(0, transform_points(invert_pose(T2), b))]), T2, [(0, pid)])
    p = m.planes[pid]
    # hull of the union: (0,0) (1,0) (2,0.2) (2,1) (0,1)
    expected = np.array([[0, 0], [1, 0], [2, 0.2], [2, 1], [0, 1]], dtype=np.float64)
    assert p.area_m2 == pytest.approx(2.0 - 0.5 * 1.0 * 0.2, abs=1e-9)
    assert p.outline.shape == (5, 3)
    np.testing.assert_allclose(np.abs(p.outline[:, 2]), 0.0, atol=1e-9)
    got = {tuple(np.round(x, 9)) for x in p.outline[:, :2]}
    assert got == {tuple(np.round(x, 9)) for x in expected}


def test_bad_pairs_and_poses_are_refused(rng):
    m = Map()
    obs = observation(
        [make_plane(0, rect_points(np.array([0, 0, 2.0]), np.eye(3)[0], np.eye(3)[1]))]
    )
    m.merge(obs, np.eye(4))
    with pytest.raises(AssociationError, match="no map plane with id 7"):
        m.merge(obs, np.eye(4), [(0, 7)])
    with pytest.raises(AssociationError, match="observed index 3"):
        m.merge(obs, np.eye(4), [(3, 0)])
    with pytest.raises(MapError, match="T_world_cam"):
        m.merge(obs, np.eye(3))
    assert len(m.planes) == 1


def test_new_plane_ids_are_monotonic_and_pairs_beyond_the_gate_make_new_planes():
    obs = observation(
        [make_plane(0, rect_points(np.array([0, 0, 2.0]), np.eye(3)[0], np.eye(3)[1]))]
    )
    m = Map(MapConfig(merge_max_angle_deg=10, consolidate=False))  # same plane, new ids
    assert m.merge(obs, np.eye(4)).planes == {0: 0}
    T = np.eye(4)
    T[:3, :3] = pose_from_quat(np.zeros(3), [np.sin(0.2), 0, 0, np.cos(0.2)])[:3, :3]  # 23 deg
    assert m.merge(obs, T, [(0, 0)]).planes == {0: 1}
    assert m.merge(obs, np.eye(4)).planes == {0: 2}
    assert list(m.plane_ids()) == [0, 1, 2]


# ----------------------------------------------------------------------------- edges, corners


def three_planes_observation(length_m: float, corner_shift: np.ndarray) -> FrameObservation:
    """Floor z=0, walls x=0 and y=0 seen from a camera at the world point (1, 1, 1) (T = I
    after the caller's pose), an edge floor-wall x of `length_m`, and one corner."""
    g = np.linspace(0.05, 1, 8)
    uu, vv = (a.reshape(-1) for a in np.meshgrid(g, g))
    floor = np.stack([uu, vv, 0 * uu], 1)
    wall_x = np.stack([0 * uu, uu, vv], 1)
    wall_y = np.stack([uu, 0 * uu, vv], 1)
    planes = [make_plane(k, p) for k, p in enumerate((floor, wall_x, wall_y))]
    edges = [
        Edge(
            (0, 1),
            np.array([[0, 0, 0], [0, length_m, 0.0]]),
            length_m,
            length_m,
            np.pi / 2,
            False,
            50,
        ),
        Edge((0, 2), np.array([[0, 0, 0], [1, 0, 0.0]]), 1.0, 1.0, np.pi / 2, False, 50),
        Edge((1, 2), np.array([[0, 0, 0], [0, 0, 1.0]]), 1.0, 1.0, np.pi / 2, False, 50),
    ]
    corners = [Corner((0, 1, 2), corner_shift, 0)]
    return observation(planes, edges, corners, up_cam=UP)


def test_edges_keep_the_longest_length_and_its_segment():
    m = Map()
    m.merge(three_planes_observation(0.5, np.zeros(3)), np.eye(4))
    pairs = [(0, 0), (1, 1), (2, 2)]
    m.merge(three_planes_observation(0.8, np.zeros(3)), np.eye(4), pairs)
    m.merge(three_planes_observation(0.6, np.zeros(3)), np.eye(4), pairs)
    e = m.edges[(0, 1)]
    assert e.length_m == 0.8 and e.observations == 3 and not e.convex
    np.testing.assert_allclose(np.linalg.norm(e.segment[1] - e.segment[0]), 0.8, atol=1e-12)
    np.testing.assert_allclose(e.segment, [[0, 0, 0], [0, 0.8, 0]], atol=1e-9)
    assert len(m.edges) == 3


def test_corners_average_their_points_count_weighted():
    m = Map()
    shifts = [np.array([0.01, 0, 0]), np.array([0, 0.03, 0]), np.array([0, 0, -0.02])]
    m.merge(three_planes_observation(1.0, shifts[0]), np.eye(4))
    pairs = [(0, 0), (1, 1), (2, 2)]
    m.merge(three_planes_observation(1.0, shifts[1]), np.eye(4), pairs, [(0, 0)])
    # not paired by the caller, but its three planes are those of corner 0: averaged too
    m.merge(three_planes_observation(1.0, shifts[2]), np.eye(4), pairs)
    assert list(m.corners) == [0]
    c = m.corners[0]
    assert c.observations == 3 and c.planes == (0, 1, 2)
    np.testing.assert_allclose(c.point, np.mean(shifts, axis=0), atol=1e-15)
    ids, rows, points = m.corner_arrays()
    assert ids.tolist() == [0] and rows.tolist() == [[0, 1, 2]]


def test_gravity_comes_from_a_plane_based_estimate_and_follows_the_merged_floor():
    tilt = np.array([0.0, np.sin(0.08), np.cos(0.08)])  # 4.6 deg off the floor normal
    fallback = three_planes_observation(1.0, np.zeros(3))
    fallback = observation(
        fallback.segmentation.planes,
        fallback.structure.edges,
        up_cam=np.array([1.0, 0, 0]),
        timestamp=1.0,
        gravity_source=GravitySource.CAMERA,
    )
    m = Map()
    m.merge(fallback, np.eye(4))
    assert m.gravity_source == UpSource(UpOrigin.FRAME_FALLBACK, 1.0)
    assert str(m.gravity_source) == "frame 1.0 (fallback)"
    planar = three_planes_observation(1.0, np.zeros(3))
    planar = observation(planar.segmentation.planes, up_cam=tilt, timestamp=2.0)
    m.merge(planar, np.eye(4), [(0, 0), (1, 1), (2, 2)])
    assert m.gravity_source == UpSource(UpOrigin.FRAME, 2.0)
    assert str(m.gravity_source) == "frame 2.0"
    np.testing.assert_allclose(m.gravity_up, UP, atol=1e-12)  # snapped to the floor's normal
    m.set_gravity(tilt)
    m.reaggregate()
    np.testing.assert_allclose(m.gravity_up, tilt, atol=1e-15)  # a set up is kept
    assert m.gravity_source == UpSource(UpOrigin.SET)


@pytest.mark.parametrize(
    ("text", "origin", "timestamp"),
    [
        ("", UpOrigin.UNKNOWN, None),
        ("set", UpOrigin.SET, None),
        ("frame 1305031102.175304", UpOrigin.FRAME, 1305031102.175304),
        ("frame 7", UpOrigin.FRAME, 7),
        ("frame 1.0 (fallback)", UpOrigin.FRAME_FALLBACK, 1.0),
    ],
)
def test_up_source_text_round_trips(text, origin, timestamp):
    source = UpSource.parse(text)
    assert source == UpSource(origin, timestamp) and str(source) == text


def test_up_source_reads_free_text_as_set_and_checks_its_timestamp():
    assert UpSource.parse("camera -y (no horizontal-looking plane)") == UpSource(UpOrigin.SET)
    assert UpSource.parse("frame x") == UpSource(UpOrigin.SET)
    with pytest.raises(MapError, match="timestamp"):
        UpSource(UpOrigin.FRAME)
    with pytest.raises(MapError, match="timestamp"):
        UpSource(UpOrigin.SET, 1.0)


def test_a_loaded_fallback_up_is_still_replaced_by_a_plane_based_frame(tmp_path):
    base = three_planes_observation(1.0, np.zeros(3))
    m = Map()
    m.merge(
        observation(
            base.segmentation.planes,
            up_cam=np.array([1.0, 0, 0]),
            timestamp=1.0,
            gravity_source=GravitySource.CAMERA,
        ),
        np.eye(4),
    )
    data = m.to_dict()
    assert data["gravity_source"] == "frame 1.0 (fallback)"  # readable in map.json
    loaded = Map.load(m.save(tmp_path / "map.json"))
    assert loaded.gravity_source == UpSource(UpOrigin.FRAME_FALLBACK, 1.0)
    planar = observation(base.segmentation.planes, up_cam=UP, timestamp=2.0)
    loaded.merge(planar, np.eye(4), [(0, 0), (1, 1), (2, 2)])
    assert str(loaded.gravity_source) == "frame 2.0"
    np.testing.assert_allclose(loaded.gravity_up, UP, atol=1e-12)


# ----------------------------------------------------------------------------- objects


BOX_ROOM_VIEWS = (
    # (scene plane ids seen, pose seed): together they cover every plane, edge and corner
    ([5, 0, 2, 6, 8, 10, 4], 1),
    ([5, 1, 3, 7, 9, 10, 4], 2),
    ([5, 0, 3, 6, 9, 10], 3),
    ([5, 1, 2, 7, 8, 10, 4], 4),
)


def merge_scene_views(
    m: Map, rng_seed: int = 7, views: int = len(BOX_ROOM_VIEWS)
) -> dict[int, int]:
    """Merge exact views of box_room_circle from random poses; scene id -> map id."""
    rng = np.random.default_rng(rng_seed)
    scene_to_map: dict[int, int] = {}
    for ids, _ in BOX_ROOM_VIEWS[:views]:
        T = random_pose(rng, scale=0.5)
        obs, order = scene_observation(ids, T)
        pairs = [(k, scene_to_map[s]) for k, s in enumerate(order) if s in scene_to_map]
        got = m.merge(obs, T, pairs)
        scene_to_map.update({s: got.planes[k] for k, s in enumerate(order)})
    return scene_to_map


def test_box_room_truth_gives_a_box_and_a_room_of_the_true_sizes():
    m = Map()
    scene_to_map = merge_scene_views(m)
    assert np.allclose(m.gravity_up, UP, atol=1e-12)
    assert len(m.planes) == 11
    by_class = {o.cls: o for o in m.objects}
    assert sorted(by_class) == ["box", "room"]
    np.testing.assert_allclose(by_class["box"].size_m, (0.38, 0.29, 0.19), atol=1e-9)
    np.testing.assert_allclose(by_class["room"].size_m, (1.88, 1.88, 1.10), atol=1e-9)
    box_planes = {scene_to_map[s] for s in (6, 7, 8, 9, 10)}
    assert box_planes <= set(by_class["box"].planes)
    room_planes = {scene_to_map[s] for s in range(6)}
    assert set(by_class["room"].planes) == room_planes
    assert len(m.corners) == 8 + 8  # room corners, 4 box top corners and 4 on the floor


def test_min_observations_leaves_rarely_seen_planes_out_of_objects():
    # two views: only the floor, the ceiling and the box top are seen twice
    once, twice = Map(), Map(MapConfig(min_observations=2))
    merge_scene_views(once, views=2)
    merge_scene_views(twice, views=2)
    assert {o.cls for o in once.objects} == {"box", "room"}  # two disjoint halves of each
    assert twice.objects == [] and len(twice.planes) == len(once.planes) == 11
    assert sorted(twice.graph().nodes) == sorted(
        p.id for p in twice.planes.values() if p.observations >= 2
    )


# ----------------------------------------------------------------------------- persistence


def assert_maps_equal(a: Map, b: Map) -> None:
    assert list(a.planes) == list(b.planes)
    for pid, p in a.planes.items():
        q = b.planes[pid]
        for name in ("normal", "centroid", "scatter", "outline"):
            assert np.array_equal(getattr(p, name), getattr(q, name)), (pid, name)
        assert (p.d, p.num_points, p.area_m2, p.observations) == (
            q.d,
            q.num_points,
            q.area_m2,
            q.observations,
        )
    assert list(a.edges) == list(b.edges)
    for key, e in a.edges.items():
        f = b.edges[key]
        assert np.array_equal(e.segment, f.segment)
        assert (e.length_m, e.angle_rad, e.convex, e.observations) == (
            f.length_m,
            f.angle_rad,
            f.convex,
            f.observations,
        )
    assert list(a.corners) == list(b.corners)
    for cid, c in a.corners.items():
        k = b.corners[cid]
        assert np.array_equal(c.point, k.point)
        assert (c.planes, c.convex_edges, c.observations) == (
            k.planes,
            k.convex_edges,
            k.observations,
        )
    assert a.objects == b.objects
    assert np.array_equal(a.gravity_up, b.gravity_up)
    assert np.array_equal(a.sparse_points, b.sparse_points)
    assert np.array_equal(a.sparse_colors, b.sparse_colors)
    assert a.config == b.config and a.object_config == b.object_config


def test_save_load_round_trip_is_exact_and_merging_continues_identically(tmp_path, rng):
    m = Map(MapConfig(voxel_m=0.1))
    merge_scene_views(m)
    m.add_sparse_points(
        rng.uniform(-1, 1, (500, 3)), rng.integers(0, 256, (500, 3), dtype=np.uint8)
    )
    path = m.save(tmp_path / "out" / "map.json")
    loaded = Map.load(path)
    assert_maps_equal(m, loaded)
    assert loaded.gravity_source == m.gravity_source
    assert loaded.save(tmp_path / "again.json").read_bytes() == path.read_bytes()
    assert not list((tmp_path / "out").glob(".*tmp"))  # the temp file was replaced
    # ids continue where they stopped, in both
    obs = observation(
        [make_plane(0, rect_points(np.array([0, 0, 2.0]), np.eye(3)[0], np.eye(3)[1]))]
    )
    assert m.merge(obs, np.eye(4)).planes == loaded.merge(obs, np.eye(4)).planes == {0: 11}
    assert_maps_equal(m, loaded)


@pytest.mark.parametrize("schema", ["planeslam.map/999", None])
def test_unknown_or_missing_schema_is_refused_naming_file_and_version(tmp_path, schema):
    path = tmp_path / "map.json"
    data = Map().to_dict()
    if schema is None:
        del data["schema"]
    else:
        data["schema"] = schema
    path.write_text(json.dumps(data))
    with pytest.raises(MapError) as info:
        Map.load(path)
    msg = str(info.value)
    assert str(path) in msg and repr(schema) in msg and "planeslam.map/1" in msg
    assert "\n" not in msg


def test_missing_file_is_a_map_error(tmp_path):
    with pytest.raises(MapError, match="not found"):
        Map.load(tmp_path / "nope.json")


# ----------------------------------------------------------------------------- backend


def test_update_geometry_moves_outlines_edges_and_corners_onto_the_new_planes():
    m = Map()
    scene_to_map = merge_scene_views(m)
    wall = scene_to_map[0]  # room.wall_+x: n = (-1, 0, 0), d = 0.94
    n_new = np.array([-1.0, 0.02, 0.01])
    n_new /= np.linalg.norm(n_new)
    before = {k: e.length_m for k, e in m.edges.items()}
    m.update_geometry({wall: (-n_new, -0.95)}, {})  # given flipped: re-oriented to the map's
    p = m.planes[wall]
    np.testing.assert_allclose(p.normal, n_new, atol=1e-15)
    assert p.d == pytest.approx(0.95, abs=1e-15)
    np.testing.assert_allclose(p.outline @ p.normal + p.d, 0.0, atol=1e-12)
    assert p.centroid @ p.normal + p.d == pytest.approx(0.0, abs=1e-12)
    smallest = np.linalg.eigh(p.scatter)[1][:, 0]  # the scatter turned with the plane
    assert abs(smallest @ n_new) == pytest.approx(1.0, abs=1e-12)
    for key, e in m.edges.items():
        assert e.length_m == before[key]
        if wall in key:
            for pid in key:
                q = m.planes[pid]
                np.testing.assert_allclose(e.segment @ q.normal + q.d, 0.0, atol=1e-12)
    for c in m.corners.values():
        if wall in c.planes:
            for pid in c.planes:
                q = m.planes[pid]
                assert c.point @ q.normal + q.d == pytest.approx(0.0, abs=1e-12)
    cid = next(iter(m.corners))
    m.update_geometry({}, {cid: np.array([1.0, 2.0, 3.0])})
    assert m.corners[cid].point.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(MapError, match="no map plane with id 99"):
        m.update_geometry({99: (n_new, 1.0)}, {})


# ----------------------------------------------------------------------------- sparse, ply, memory


def test_sparse_cloud_averages_per_voxel_and_keeps_the_best_supported_when_capped():
    m = Map(MapConfig(voxel_m=1.0, sparse_max_points=2))
    m.add_sparse_points(np.array([[0.2, 0.2, 0.2], [0.4, 0.6, 0.8], [5.5, 0.5, 0.5]]))
    m.add_sparse_points(
        np.array([[0.6, 0.4, 0.2], [-0.5, 0.5, 0.5], [5.5, 0.5, 0.5], [np.nan, 0, 0]]),
        np.array([[0, 0, 0], [10, 20, 30], [0, 0, 0], [0, 0, 0]], dtype=np.uint8),
    )
    # voxel (0,0,0): 3 points, (5,0,0): 2 points, (-1,0,0): 1 point -> dropped by the cap
    pts = m.sparse_points
    assert len(pts) == 2
    np.testing.assert_allclose(pts[0], [0.4, 0.4, 0.4], atol=1e-15)
    np.testing.assert_allclose(pts[1], [5.5, 0.5, 0.5], atol=1e-15)
    assert m.sparse_colors[0].tolist() == [107, 107, 107]  # (160 + 160 + 0) / 3
    with pytest.raises(MapError, match=r"\(N, 3\)"):
        m.add_sparse_points(np.zeros((3, 2)))


def test_ply_files_are_readable_by_open3d_and_survive_cleaning(tmp_path, rng):
    """map_planes.ply is a mesh whose every vertex is on a face (cleaning keeps it whole),
    coloured by object; map_points.ply is the sparse cloud alone."""
    o3d = pytest.importorskip("open3d")
    m = Map()
    scene_to_map = merge_scene_views(m)
    m.add_sparse_points(rng.uniform(-1, 1, (200, 3)) * [0.9, 0.9, 0.5] + [0, 0, 0.55])
    mesh = o3d.io.read_triangle_mesh(str(m.write_planes_ply(tmp_path / "map_planes.ply")))
    ring_sizes = [len(p.outline) for p in m.planes.values()]
    assert len(mesh.vertices) == sum(ring_sizes) + len(ring_sizes)
    assert len(mesh.triangles) == sum(ring_sizes)
    cleaned = o3d.geometry.TriangleMesh(mesh).remove_unreferenced_vertices()
    assert len(cleaned.vertices) == len(mesh.vertices)
    colors = np.asarray(mesh.vertex_colors)
    first = np.cumsum([0] + [r + 1 for r in ring_sizes])[:-1]
    plane_colors = {pid: colors[first[k]] for k, pid in enumerate(m.planes)}
    box = [plane_colors[scene_to_map[s]] for s in (6, 7, 8, 9, 10)]
    room = [plane_colors[scene_to_map[s]] for s in range(6)]  # floor goes to the room
    assert all(np.allclose(c, box[0]) for c in box) and all(np.allclose(c, room[0]) for c in room)
    assert not np.allclose(box[0], room[0])
    np.testing.assert_allclose(np.asarray(mesh.vertices), m.plane_mesh().vertices, atol=1e-6)
    faces = ply_faces(tmp_path / "map_planes.ply", len(mesh.vertices))
    np.testing.assert_array_equal(faces["v"], np.asarray(mesh.triangles))
    assert faces["plane_id"].tolist() == [
        pid for pid, r in zip(m.planes, ring_sizes, strict=True) for _ in range(r)
    ]
    owner = {o.cls: o.id for o in m.objects}
    face_object = dict(zip(faces["plane_id"].tolist(), faces["object_id"].tolist(), strict=True))
    assert {face_object[scene_to_map[s]] for s in (6, 7, 8, 9, 10)} == {owner["box"]}
    assert {face_object[scene_to_map[s]] for s in range(6)} == {owner["room"]}
    cloud = o3d.io.read_point_cloud(str(m.write_points_ply(tmp_path / "map_points.ply")))
    np.testing.assert_allclose(np.asarray(cloud.points), m.sparse_points, atol=1e-6)
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, m.sparse_colors, atol=0.5)


def ply_faces(path, vertices: int) -> np.ndarray:
    """The face records of a binary PLY mesh with x y z red green blue vertices, read
    with the face properties its header declares (list uchar int, then ints)."""
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    start = lines.index(next(line for line in lines if line.startswith("element face")))
    names = [line.split()[-1] for line in lines[start + 2 :] if line.startswith("property int")]
    dtype = np.dtype([("n", "u1"), ("v", "<i4", (3,))] + [(n, "<i4") for n in names])
    return np.frombuffer(body[vertices * 15 :], dtype=dtype)


def top_level_value_bytes(text: str) -> dict[str, int]:
    """{key: bytes its value takes in `text`} for the top-level object of a JSON file."""
    decoder = json.JSONDecoder()
    sizes: dict[str, int] = {}
    i = text.index("{") + 1
    while True:
        while text[i] in " \t\r\n,":
            i += 1
        if text[i] == "}":
            return sizes
        key, i = decoder.raw_decode(text, i)
        while text[i] in " \t\r\n:":
            i += 1
        _, end = decoder.raw_decode(text, i)
        sizes[key] = len(text[i:end].encode())
        i = end


def grid_points(n: int, offset: float) -> np.ndarray:
    """`n` points 0.2 m apart on a line, at the centres of voxels of the default 0.05 m."""
    x = 0.2 * np.arange(n) + 0.025
    return np.column_stack([x, np.full(n, offset + 0.025), np.full(n, 3.025)])


def test_memory_bytes_has_every_part_and_sums_to_the_total():
    m = Map()
    merge_scene_views(m)
    m.add_sparse_points(grid_points(100, 0.0))
    for encoding in ("arrays", "json"):
        mem = m.memory_bytes(encoding)
        assert list(mem) == ["planes", "edges", "corners", "objects", "sparse_cloud", "total"]
        assert mem["total"] == sum(v for k, v in mem.items() if k != "total")
        assert all(v > 0 for v in mem.values())


def test_memory_bytes_as_json_are_the_bytes_of_each_part_in_the_saved_file(tmp_path):
    m = Map()
    merge_scene_views(m)
    m.add_sparse_points(grid_points(100, 0.0))
    text = m.save(tmp_path / "map.json").read_text(encoding="utf-8")
    in_file = top_level_value_bytes(text)
    mem = m.memory_bytes("json")
    parts = [k for k in mem if k != "total"]
    assert {k: in_file[k] for k in parts} == {k: mem[k] for k in parts}
    assert mem["total"] < len(text.encode())  # the rest: schema, gravity, config


def test_memory_bytes_in_memory_hold_the_arrays_and_grow_with_the_content():
    """Independent of the per-record layout: each part holds at least the numpy arrays of
    its records, fixed-size records cost the same each, and the sparse cloud grows by
    point (twice the points, twice the bytes), not by re-observation."""
    small, full = Map(), Map()
    merge_scene_views(small, views=1)
    merge_scene_views(full)
    for m in (small, full):
        mem = m.memory_bytes()
        planes = m.planes.values()
        assert mem["planes"] >= sum(
            p.normal.nbytes + p.centroid.nbytes + p.scatter.nbytes + p.outline.nbytes
            for p in planes
        )
        assert mem["edges"] >= sum(e.segment.nbytes for e in m.edges.values())
        assert mem["corners"] >= sum(k.point.nbytes for k in m.corners.values())
    a, b = small.memory_bytes(), full.memory_bytes()
    assert len(small.planes) < len(full.planes)
    assert 0 < len(small.edges) < len(full.edges) and 0 < len(small.corners) < len(full.corners)
    assert a["planes"] < b["planes"] and a["total"] < b["total"]
    # edges and corners are fixed-size records: the same bytes each in both maps
    assert a["edges"] / len(small.edges) == b["edges"] / len(full.edges)
    assert a["corners"] / len(small.corners) == b["corners"] / len(full.corners)

    m = Map()
    m.add_sparse_points(grid_points(100, 0.0))
    one = m.memory_bytes()["sparse_cloud"]
    assert len(m.sparse_points) == 100 and one >= m.sparse_points.nbytes  # float64 positions
    m.add_sparse_points(grid_points(100, 0.0) + 0.001)  # the same 100 voxels again
    assert m.memory_bytes()["sparse_cloud"] == one
    m.add_sparse_points(grid_points(100, 1.0))  # 100 new voxels
    assert len(m.sparse_points) == 200 and m.memory_bytes()["sparse_cloud"] == 2 * one


# ----------------------------------------------------------------------------- the paper's run


@pytest.mark.integration
@pytest.mark.slow
def test_true_pose_merge_of_box_room_circle_sizes_box_and_room(tmp_path):
    """The paper's experiment with the true poses (no tracking): 24 rendered frames
    through the front end, associated with the map and merged."""
    from planeslam.config import resolve_config
    from planeslam.frontend.pipeline import FrontEnd
    from planeslam.io.dataset import TumDataset
    from planeslam.io.trajectory import read_tum
    from planeslam.sim.sequence import load_truth, synthesize
    from planeslam.tracking.association import associate_with_corners

    root = Path(tmp_path) / "brc"
    synthesize("box_room_circle", root, seed=0)
    truth = load_truth(root)
    cfg = resolve_config(root)
    dataset = TumDataset(root, cfg.camera, cfg.dataset)
    front_end = FrontEnd(cfg)
    gt = read_tum(root / "groundtruth.txt")
    m = Map(object_config=cfg.objects)
    valid_points = 0
    for i in range(len(dataset)):
        frame = dataset[i]
        obs = front_end.process(frame.depth_m, frame.timestamp)
        valid_points += int((frame.depth_m > 0).sum())
        T = gt.T_world_cam[i]
        ids, normals, offsets = m.plane_arrays()
        cids, crows, cpoints = m.corner_arrays()
        planes = obs.segmentation.planes
        pairs, cpairs = [], []
        if len(ids):
            a = associate_with_corners(
                normals,
                offsets,
                crows,
                cpoints,
                np.array([p.normal for p in planes]),
                np.array([p.d for p in planes]),
                np.array([c.planes for c in obs.structure.corners]).reshape(-1, 3),
                np.array([c.point for c in obs.structure.corners]).reshape(-1, 3),
                T,
                np.deg2rad(10),
                0.1,
                0.1,
            )
            pairs = [(k, int(ids[j])) for k, j in a.planes]
            cpairs = [(k, int(cids[j])) for k, j in a.corners]
        m.merge(obs, T, pairs, cpairs)
    by_class = {o.cls: o for o in m.objects}
    assert sorted(by_class) == ["box", "room"], m.objects
    true = {o["class"]: np.array(o["size_m"]) for o in truth["objects"]}
    box_err = np.abs(np.array(by_class["box"].size_m) - true["box"])
    assert box_err.mean() < 0.01, by_class["box"].size_m
    # the room's floor plan; its height is not observable (the walls are seen up to ~0.3 m)
    room_err = np.abs(np.array(by_class["room"].size_m[:2]) - true["room"][:2])
    assert room_err.mean() < 0.01, by_class["room"].size_m
    assert valid_points * 15 / m.memory_bytes()["total"] >= 100


def test_seat_segments_puts_segments_on_the_line_and_keeps_parallel_pairs():
    n1 = np.array([[0.0, 0, 1], [0, 0, 1]])
    n2 = np.array([[1.0, 0, 0], [0, 0, -1]])  # second pair parallel
    segs = np.array([[[0.1, 2.0, 0.2], [0.1, 0.0, 0.2]], [[1.0, 1, 1], [2.0, 2, 2]]])
    out = seat_segments(segs, np.array([3.0, 1.0]), n1, np.array([-0.5, 0]), n2, np.array([1.0, 0]))
    # line z = 0.5, x = -1 along -y (like the old segment), centred at the old midpoint's y = 1
    np.testing.assert_allclose(out[0], [[-1, 2.5, 0.5], [-1, -0.5, 0.5]], atol=1e-15)
    assert np.array_equal(out[1], segs[1])
