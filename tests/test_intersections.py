"""Real plane intersections (paper eq. 1-6) against exact synthetic truth.

Planes are fitted to the pixels of each true plane id of frames rendered by
`planeslam.sim.render.render_frame` (Kinect-like noise), so these tests exercise
the intersection stage independently of the segmentation stage.
`segmentation_from_render` and `visible_fraction` are reused by test_objects.py.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.errors import ConfigError, GeometryError
from planeslam.core.geometry import invert_pose, plane_line, transform_plane, transform_points
from planeslam.frontend.config import IntersectionConfig
from planeslam.frontend.intersections import candidate_pairs, find_intersections, intersection_lines
from planeslam.frontend.types import Plane, Segmentation
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import SCENES, Box, Panel, Structure, look_at, make_scene

pytestmark = pytest.mark.unit

CAMERA = CameraConfig()


# --------------------------------------------------------------------------- helpers


def erode_labels(labels: np.ndarray, r: int) -> np.ndarray:
    """Unlabel pixels within `r` px (4 directions) of another label: seams like a segmenter's."""
    out = labels.copy()
    if r <= 0:
        return out
    H, W = labels.shape
    for dy, dx in ((r, 0), (-r, 0), (0, r), (0, -r)):
        shifted = np.full_like(labels, -2)
        shifted[max(-dy, 0) : H - max(dy, 0), max(-dx, 0) : W - max(dx, 0)] = labels[
            max(dy, 0) : H - max(-dy, 0), max(dx, 0) : W - max(-dx, 0)
        ]
        out[shifted != labels] = -1
    return out


def plane_from_points(pid: int, pts: np.ndarray, rays: np.ndarray, depth: np.ndarray) -> Plane:
    """Least-squares plane of (K, 3) camera-frame points, normal toward the camera."""
    c = pts.mean(axis=0)
    X = pts - c
    S = X.T @ X
    _, V = np.linalg.eigh(S)
    n = V[:, 0]
    d = -float(n @ c)
    if d < 0:
        n, d = -n, -d
    area = float(np.sum(depth**2 / (CAMERA.fx * CAMERA.fy * np.abs(rays @ n))))
    e1 = V[:, 2]
    e2 = np.cross(n, e1)
    a, b = X @ e1, X @ e2
    box = np.array([[a.min(), b.min()], [a.max(), b.min()], [a.max(), b.max()], [a.min(), b.max()]])
    return Plane(
        id=pid,
        normal=n,
        d=d,
        points=pts,
        centroid=c,
        covariance=np.eye(3) * 1e-6,
        scatter=S,
        num_points=len(pts),
        area_m2=area,
        outline=c + box @ np.stack([e1, e2]),
    )


def segmentation_from_render(
    plane_id: np.ndarray, depth_m: np.ndarray, min_points: int = 400, erode_px: int = 0
) -> tuple[Segmentation, list[int]]:
    """Planes fitted to each true plane id's valid pixels -> (Segmentation, scene id per plane)."""
    rays = PixelRays.for_camera(CAMERA).rays
    depth = depth_m.astype(np.float64)
    ids = erode_labels(np.where(depth > 0, plane_id, -1), erode_px)
    labels = np.full(ids.shape, -1, dtype=np.int32)
    planes: list[Plane] = []
    scene_ids: list[int] = []
    for sid in np.unique(ids[ids >= 0]):
        mask = ids == sid
        if np.count_nonzero(mask) < min_points:
            continue
        pts = depth[mask][:, None] * rays[mask]
        labels[mask] = len(planes)
        planes.append(plane_from_points(len(planes), pts, rays[mask], depth[mask]))
        scene_ids.append(int(sid))
    return Segmentation(planes=planes, labels=labels), scene_ids


@functools.lru_cache(maxsize=32)
def rendered(scene_name: str, frame: int, noise: bool = True):
    """(scene, T_world_cam, RenderedFrame) of a named scene's frame, seeded by the frame index."""
    scene, traj = SCENES[scene_name](None, None)
    T = traj.T_world_cam[frame]
    return scene, T, render_frame(scene, T, CAMERA, np.random.default_rng(frame), noise=noise)


def visible_fraction(segment_world: np.ndarray, T_world_cam: np.ndarray, frame, ids) -> np.ndarray:
    """Per-sample visibility (200 samples) of a true world segment: inside the image,
    not occluded and on one of the planes `ids`. `fully_visible` ignores the 1.5 %
    at each end, whose pixels may round onto a neighbouring surface."""
    T_cam_world = invert_pose(T_world_cam)
    s = np.linspace(0.0, 1.0, 200)[:, None]
    pts = transform_points(
        T_cam_world, segment_world[0] + s * (segment_world[1] - segment_world[0])
    )
    z = np.maximum(pts[:, 2], 1e-6)
    u = np.round(CAMERA.fx * pts[:, 0] / z + CAMERA.cx).astype(int)
    v = np.round(CAMERA.fy * pts[:, 1] / z + CAMERA.cy).astype(int)
    ok = (pts[:, 2] > 0.1) & (u >= 2) & (u < CAMERA.width - 2) & (v >= 2) & (v < CAMERA.height - 2)
    vis = np.zeros(len(pts), dtype=bool)
    vis[ok] = np.isin(frame.plane_id[v[ok], u[ok]], ids) & (
        np.abs(frame.depth_true_m[v[ok], u[ok]] - pts[ok, 2]) < 0.02
    )
    return vis


def matched_edges(scene, T_world_cam, frame, seg, sids, edges):
    """[(true edge, found edge or None, visible samples (200,) bool, true segment in camera)]
    for the true edges whose two planes were both segmented."""
    found = {tuple(sorted((sids[e.planes[0]], sids[e.planes[1]]))): e for e in edges}
    T_cam_world = invert_pose(T_world_cam)
    out = []
    for te in scene.edges:
        if not set(te.plane_ids) <= set(sids):
            continue
        vis = visible_fraction(te.segment, T_world_cam, frame, list(te.plane_ids))
        out.append((te, found.get(te.plane_ids), vis, transform_points(T_cam_world, te.segment)))
    return out


def fully_visible(vis: np.ndarray) -> bool:
    return bool(vis[3:-3].all())


def is_box_edge(scene, te) -> bool:
    return all(scene.planes[k].name.startswith("box.") for k in te.plane_ids)


def segment_error(found: np.ndarray, truth: np.ndarray) -> float:
    """Largest end-point distance [m] of two (2, 3) segments, whichever order."""
    direct = np.linalg.norm(found - truth, axis=1).max()
    flipped = np.linalg.norm(found[::-1] - truth, axis=1).max()
    return float(min(direct, flipped))


BOX_FRAMES = (3, 9, 15, 21)
"""box_room_circle frames that see the box top and two sides, none at grazing incidence."""


# --------------------------------------------------------------------------- unit tests


def test_candidate_pairs_touching_regions_only():
    labels = np.full((60, 80), -1, dtype=np.int32)
    labels[:, :30] = 0
    labels[:, 33:50] = 1  # 3 px seam to plane 0
    labels[:20, 70:] = 2  # far from both
    labels[40:, 50:] = 3  # touches plane 1 directly
    pairs = candidate_pairs(labels, adjacency_px=8, stride=2, min_contact_px=3)
    assert pairs.tolist() == [[0, 1], [1, 3]]
    assert candidate_pairs(labels, adjacency_px=2, stride=1, min_contact_px=3).tolist() == [[1, 3]]


def test_candidate_pairs_degenerate_images():
    assert candidate_pairs(np.full((10, 10), -1, dtype=np.int32)).shape == (0, 2)
    assert candidate_pairs(np.zeros((10, 10), dtype=np.int32)).shape == (0, 2)
    with pytest.raises(GeometryError, match="labels"):
        candidate_pairs(np.zeros(10, dtype=np.int32))


def test_intersection_lines_agree_with_geometry(rng):
    n = rng.normal(size=(20, 2, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    d = rng.uniform(0.2, 3.0, size=(20, 2))
    p0, u = intersection_lines(n[:, 0], d[:, 0], n[:, 1], d[:, 1])
    for k in range(20):
        q0, q = plane_line(n[k, 0], d[k, 0], n[k, 1], d[k, 1], min_sin=1e-3)
        np.testing.assert_allclose(p0[k], q0, atol=1e-9)
        np.testing.assert_allclose(u[k], q, atol=1e-9)


@pytest.mark.parametrize("bad", [{"d_thresh_m": 0}, {"d_min_m": 0.05}, {"min_angle_deg": 95},
                                 {"label_stride": 0}, {"extent_trim_points": -1}])  # fmt: skip
def test_config_rejects_bad_values(bad):
    with pytest.raises(ConfigError):
        IntersectionConfig(**bad)


def _wedge(angle_deg: float, convex: bool, rng: np.random.Generator, noise_m: float = 0.002):
    """Two 0.4 x 0.3 m half-planes meeting along a vertical line 1.5 m ahead.

    The wedge opens by `angle_deg`; convex: its apex points at the camera (a box
    edge), else away (a room corner). Returns a Segmentation (labels only mark
    the two regions as touching) and the true edge length."""
    half = np.deg2rad(angle_deg) / 2
    apex = np.array([0.0, 0.0, 1.5])
    sign = 1.0 if convex else -1.0  # convex: faces recede from the apex
    planes = []
    for k, side in enumerate((-1.0, 1.0)):
        # In-plane direction from the line into the region (x-z plane), and the line (y).
        w = np.array([side * np.sin(half), 0.0, sign * np.cos(half)])
        a = rng.uniform(0.0, 0.4, 6000)
        b = rng.uniform(-0.15, 0.15, 6000)
        pts = apex + a[:, None] * w + b[:, None] * np.array([0.0, 1.0, 0.0])
        n = np.cross(w, [0.0, 1.0, 0.0])
        n /= np.linalg.norm(n)
        pts = pts + rng.normal(0.0, noise_m, len(pts))[:, None] * n
        rays = pts / pts[:, 2:3]
        planes.append(plane_from_points(k, pts, rays, pts[:, 2]))
    labels = np.full((40, 40), -1, dtype=np.int32)
    labels[:, :20] = 0
    labels[:, 20:] = 1
    return Segmentation(planes=planes, labels=labels), 0.3


@pytest.mark.parametrize("angle_deg", [60.0, 90.0, 120.0])
@pytest.mark.parametrize("convex", [True, False])
def test_wedge_convexity_angle_and_length(angle_deg, convex, rng):
    seg, length = _wedge(angle_deg, convex, rng)
    edges = find_intersections(seg)
    assert len(edges) == 1
    e = edges[0]
    assert e.planes == (0, 1)
    assert e.convex is convex
    assert e.angle_rad == pytest.approx(np.deg2rad(angle_deg), abs=np.deg2rad(1.0))
    assert e.length_m == pytest.approx(length, abs=0.01)
    line_pts = e.segment - np.array([0.0, 0.0, 1.5])
    assert np.abs(line_pts[:, [0, 2]]).max() < 0.005  # on the true line x = 0, z = 1.5


def test_degenerate_frames_give_no_edges(rng):
    seg, _ = _wedge(90.0, True, rng)
    empty = Segmentation(planes=[], labels=np.full((4, 4), -1, dtype=np.int32))
    one = Segmentation(planes=seg.planes[:1], labels=np.where(seg.labels == 0, 0, -1))
    assert find_intersections(empty) == []
    assert find_intersections(one) == []
    # Two parallel planes side by side in the image: never intersected.
    p = seg.planes[0]
    shifted = Plane(**{**p.__dict__, "id": 1, "d": p.d + 0.3, "points": p.points - 0.3 * p.normal})
    parallel = Segmentation(planes=[p, shifted], labels=seg.labels)
    assert find_intersections(parallel) == []


def test_bleeding_band_does_not_stretch_the_edge(rng):
    """A box side (vertical, 0.3 m wide) on a floor 0.9 m ahead; the segmenter gave the
    side some floor pixels along the line where the side's plane meets the floor,
    0.1 m beyond the side's end. They fit both planes, so the side's extent ignores
    them (extent_min_sigmas); without that rule the edge overshoots by 0.1 m."""
    n = 8000
    floor = np.column_stack([rng.uniform(-0.4, 0.4, n), np.full(n, 0.3), rng.uniform(0.7, 1.3, n)])
    side = np.column_stack(
        [rng.uniform(-0.15, 0.15, n), rng.uniform(0.1, 0.3, n), np.full(n, 0.9)]
    )  # the face z = 0.9, from the floor (y = 0.3) up to y = 0.1
    band = np.column_stack(
        [rng.uniform(0.15, 0.25, 300), np.full(300, 0.3), 0.9 + rng.uniform(-0.003, 0.003, 300)]
    )  # floor pixels beyond the side's end, within 3 sigma of its plane
    sigma = 0.0012 + 0.0019 * 0.81
    floor[:, 1] += rng.normal(0.0, sigma, n)
    side[:, 2] += rng.normal(0.0, sigma, n)
    band[:, 1] += rng.normal(0.0, sigma, 300)
    side = np.concatenate([side, band])
    planes = [plane_from_points(k, p, p / p[:, 2:3], p[:, 2]) for k, p in enumerate((floor, side))]
    labels = np.full((40, 40), -1, dtype=np.int32)
    labels[20:], labels[:20] = 0, 1
    seg = Segmentation(planes=planes, labels=labels)
    (edge,) = find_intersections(seg)
    assert edge.length_m == pytest.approx(0.30, abs=0.01)
    assert np.sort(edge.segment[:, 0]) == pytest.approx([-0.15, 0.15], abs=0.01)
    (loose,) = find_intersections(seg, IntersectionConfig(extent_min_sigmas=0.0))
    assert loose.length_m == pytest.approx(0.40, abs=0.01)
    # sigma(z) is the sensor's: a model 10x noisier hides the band inside 3 sigma
    (noisy,) = find_intersections(seg, sensor=DepthNoiseConfig(0.012, 0.019))
    assert noisy.length_m == pytest.approx(0.40, abs=0.01)


def test_d_min_literal_reading_drops_points_near_the_line(rng):
    seg, _ = _wedge(90.0, True, rng)
    (full,) = find_intersections(seg)
    (cut,) = find_intersections(seg, IntersectionConfig(d_min_m=0.01))
    assert cut.num_points < 0.7 * full.num_points
    assert cut.length_m == pytest.approx(full.length_m, abs=0.01)


# --------------------------------------------------------------------------- synthetic scenes


@pytest.mark.parametrize("frame_index", BOX_FRAMES)
def test_box_room_edges_against_truth(frame_index):
    scene, T, frame = rendered("box_room_circle", frame_index)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    edges = find_intersections(seg)
    matches = matched_edges(scene, T, frame, seg, sids, edges)
    truth_pairs = {te.plane_ids for te in scene.edges}
    # Every edge found is a true edge (no pair touching only in the image).
    for e in edges:
        assert tuple(sorted((sids[e.planes[0]], sids[e.planes[1]]))) in truth_pairs
    full = [(te, e, seg_cam) for te, e, vis, seg_cam in matches if fully_visible(vis)]
    assert len(full) >= 3, "the view should show at least three whole box edges"
    for te, e, seg_cam in full:
        names = [scene.planes[k].name for k in te.plane_ids]
        assert e is not None, f"missed the fully visible edge {names}"
        assert abs(e.length_m - te.length_m) < 0.02, (names, e.length_m, te.length_m)
        assert segment_error(e.segment, seg_cam) < 0.02, names
    for te, e, _, _ in matches:
        if e is not None:
            assert e.convex is is_box_edge(scene, te), [scene.planes[k].name for k in te.plane_ids]
            assert e.angle_rad == pytest.approx(np.pi / 2, abs=np.deg2rad(2.0))


def test_partly_visible_room_edges_match_their_visible_part():
    scene, T, frame = rendered("box_room_circle", 3)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    matches = matched_edges(scene, T, frame, seg, sids, find_intersections(seg))
    checked = 0
    for te, e, vis, _ in matches:
        if is_box_edge(scene, te) or vis.mean() < 0.2:
            continue
        assert e is not None
        idx = np.flatnonzero(vis)
        # Visible part: between the first and last visible samples (occluders inside count).
        visible_len = te.length_m * (idx[-1] - idx[0]) / (len(vis) - 1)
        assert abs(e.length_m - visible_len) < 0.03, (te.plane_ids, e.length_m, visible_len)
        assert e.convex is False
        checked += 1
    assert checked >= 2


def test_robust_extent_beats_eq6():
    """The documented choice: the trimmed overlap extent is closer to the truth than eq. 6."""
    err_robust, err_eq6 = [], []
    for k in BOX_FRAMES:
        scene, T, frame = rendered("box_room_circle", k)
        seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
        for te, e, vis, _ in matched_edges(scene, T, frame, seg, sids, find_intersections(seg)):
            if fully_visible(vis) and e is not None:
                err_robust.append(e.length_m - te.length_m)
                err_eq6.append(e.length_eq6_m - te.length_m)
    rms_robust = float(np.sqrt(np.mean(np.square(err_robust))))
    rms_eq6 = float(np.sqrt(np.mean(np.square(err_eq6))))
    assert len(err_robust) >= 8
    assert rms_robust < 0.006
    assert rms_robust < rms_eq6


def test_seams_between_regions_are_bridged():
    """A segmentation that leaves 2-px unlabelled seams still yields the box edges."""
    scene, T, frame = rendered("box_room_circle", 9)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m, erode_px=2)
    matches = matched_edges(scene, T, frame, seg, sids, find_intersections(seg))
    full = [(te, e) for te, e, vis, _ in matches if fully_visible(vis)]
    assert len(full) >= 3
    for te, e in full:
        assert e is not None
        assert abs(e.length_m - te.length_m) < 0.03


def test_point_cap_keeps_lengths():
    scene, T, frame = rendered("box_room_circle", 15)
    seg, _ = segmentation_from_render(frame.plane_id, frame.depth_m)
    capped = {e.planes: e for e in find_intersections(seg)}
    full = {
        e.planes: e for e in find_intersections(seg, IntersectionConfig(max_points_per_plane=0))
    }
    assert capped.keys() == full.keys()
    for key, e in capped.items():
        assert abs(e.length_m - full[key].length_m) < 0.01
        assert e.convex == full[key].convex


def test_touching_in_image_but_apart_in_space():
    """A panel floating 0.3 m above the floor touches it in the image, not in space."""
    room = Box("room", (0.0, 0.0, 1.5), (6.0, 6.0, 3.0), kind="room")
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # faces -y
    panel = Panel("panel", (0.0, 0.0, 0.8), (1.0, 1.0), R)
    scene = make_scene("floating", (room,), (Structure("s", (panel,)),))
    T = look_at(np.array([0.0, -2.0, 1.2]), np.array([0.0, 0.0, 0.5]))[0]
    frame = render_frame(scene, T, CAMERA, np.random.default_rng(0))
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    floor = sids.index(scene.plane_by_name("room.floor").id)
    pan = sids.index(scene.plane_by_name("s.panel").id)
    pairs = candidate_pairs(seg.labels).tolist()
    assert sorted((floor, pan)) in pairs  # adjacent in the image
    assert all(set(e.planes) != {floor, pan} for e in find_intersections(seg))


def test_plane_ids_are_camera_frame_consistent():
    """Edges lie on both planes they join (camera frame, metres)."""
    scene, T, frame = rendered("box_room_circle", 21)
    seg, sids = segmentation_from_render(frame.plane_id, frame.depth_m)
    T_cam_world = invert_pose(T)
    for e in find_intersections(seg):
        for k in e.planes:
            n, d = transform_plane(
                T_cam_world, scene.planes[sids[k]].normal, scene.planes[sids[k]].d
            )
            assert np.abs(e.segment @ n + d).max() < 0.01
