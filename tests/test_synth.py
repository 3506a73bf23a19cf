"""Synthetic scenes: exact ray casting, the Kinect noise model, truth, and the TUM writer."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import assert_pose_close

from planeslam.config import load_camera_yaml, resolve_config
from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.geometry import pose_from_quat
from planeslam.io.dataset import TumDataset
from planeslam.sim.noise import KinectNoise
from planeslam.sim.render import plane_in_camera, render_frame
from planeslam.sim.scenes import SCENES, get_scene, look_at, make_scene
from planeslam.sim.sequence import TRUTH_SCHEMA, load_truth, synthesize

pytestmark = pytest.mark.unit

SMALL = CameraConfig(fx=131.25, fy=131.25, cx=79.5, cy=59.5, width=160, height=120)
HALF = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


def _world_points(frame, camera: CameraConfig) -> np.ndarray:
    """(H, W, 3) world points of a frame's measured depth."""
    pts_cam = frame.depth_m.astype(np.float64)[..., None] * PixelRays.for_camera(camera).rays
    T = frame.T_world_cam
    return pts_cam @ T[:3, :3].T + T[:3, 3]


def _oracle_plane_ids(scene, T_world_cam, camera, pixels_vu):
    """Brute force: nearest plane hit by each pixel's ray, testing every plane (N, P)."""
    v, u = pixels_vu
    rays_cam = np.stack(
        [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(len(u))], axis=1
    )
    rays = rays_cam @ T_world_cam[:3, :3].T
    eye = T_world_cam[:3, 3]
    N = np.stack([p.normal for p in scene.planes])
    D = np.array([p.d for p in scene.planes])
    denom = rays @ N.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(N @ eye + D)[None, :] / denom
    hits = eye[None, None, :] + t[..., None] * rays[:, None, :]
    inside = np.ones_like(t, dtype=bool)
    for k in range(2):
        axes = np.stack([p.axes[k] for p in scene.planes])
        centres = np.stack([p.centre for p in scene.planes])
        half = np.array([p.half_size_m[k] for p in scene.planes])
        local = np.einsum("npj,pj->np", hits - centres[None], axes)
        inside &= np.abs(local) <= half + 1e-9
    facing = np.array([p.two_sided for p in scene.planes])[None, :] | (denom < 0)
    t = np.where(inside & facing & (t > 0), t, np.inf)
    best = np.argmin(t, axis=1)
    return np.where(np.isfinite(t.min(axis=1)), best, -1), t.min(axis=1)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_noise_free_render_is_exact(name: str) -> None:
    scene, traj = get_scene(name, frames=5, rng=np.random.default_rng(3))
    for T in traj.T_world_cam[[0, 3]]:
        frame = render_frame(scene, T, SMALL, np.random.default_rng(0), noise=False)
        valid = frame.depth_m > 0
        assert valid.mean() > 0.5
        pts = _world_points(frame, SMALL)[valid]
        ids = frame.plane_id[valid]
        assert np.all(ids >= 0)
        N = np.stack([p.normal for p in scene.planes])
        D = np.array([p.d for p in scene.planes])
        residual = np.abs(np.einsum("ij,ij->i", pts, N[ids]) + D[ids])
        assert residual.max() < 1e-6, f"{name}: point-to-plane residual {residual.max():.2e} m"
        # The same in the camera frame, with normals oriented toward the sensor.
        pts_cam = frame.depth_m.astype(np.float64)[..., None] * PixelRays.for_camera(SMALL).rays
        for k in np.unique(ids):
            n_cam, d_cam = plane_in_camera(scene.planes[k], T)
            assert d_cam > 0
            on_k = pts_cam[valid & (frame.plane_id == k)]
            assert np.abs(on_k @ n_cam + d_cam).max() < 1e-6
        # Every labelled pixel is the nearest plane hit (independent brute force).
        vv, uu = np.nonzero(np.ones(frame.plane_id.shape, dtype=bool))
        oracle, t_min = _oracle_plane_ids(scene, T, SMALL, (vv[::7], uu[::7]))
        labels = frame.plane_id[vv[::7], uu[::7]]
        agree = oracle == labels
        # Ties only at shared edges (both planes give the same depth).
        same_depth = np.isclose(frame.depth_true_m[vv[::7], uu[::7]], t_min, atol=1e-9)
        assert np.all(agree | same_depth)
        assert agree.mean() > 0.99


def test_render_is_deterministic_and_seeded() -> None:
    scene, traj = get_scene("room_boxes_loop", frames=4, rng=np.random.default_rng(0))
    a = render_frame(scene, traj.T_world_cam[1], SMALL, np.random.default_rng(7))
    b = render_frame(scene, traj.T_world_cam[1], SMALL, np.random.default_rng(7))
    c = render_frame(scene, traj.T_world_cam[1], SMALL, np.random.default_rng(8))
    assert a.depth_m.dtype == np.float32 and a.rgb.dtype == np.uint8
    assert a.plane_id.dtype == np.int32
    assert a.depth_m.tobytes() == b.depth_m.tobytes()
    assert a.rgb.tobytes() == b.rgb.tobytes()
    assert np.array_equal(a.plane_id, c.plane_id)
    assert not np.array_equal(a.depth_m, c.depth_m)
    assert not np.array_equal(a.rgb, c.rgb)


def test_noisy_depth_follows_the_kinect_model() -> None:
    scene, traj = get_scene("room_boxes_loop", frames=6, rng=np.random.default_rng(0))
    model = KinectNoise()
    rng = np.random.default_rng(11)
    res, bound, sig, zs, inc, meas, hit = [], [], [], [], [], [], []
    for T in traj.T_world_cam[:5]:
        f = render_frame(scene, T, HALF, rng)
        valid = f.depth_m > 0
        z = f.depth_true_m[valid]
        s = model.depth_sigma(z, f.incidence_rad[valid])
        step = model.quantisation_step(z * 1.05, HALF.fx)
        res.append(f.depth_m[valid] - z)
        bound.append(3 * s + step / 2)
        sig.append(np.sqrt(s**2 + step**2 / 12))
        zs.append(f.depth_m[f.depth_m > 0])
        inc.append(f.incidence_rad[f.plane_id >= 0])
        meas.append(f.depth_m[f.plane_id >= 0] > 0)
        hit.append(f.plane_id >= 0)
    res, bound, sig = np.concatenate(res), np.concatenate(bound), np.concatenate(sig)
    assert np.mean(np.abs(res) <= bound) > 0.99
    normalised = res / sig
    assert abs(normalised.mean()) < 0.1
    assert 0.85 < normalised.std() < 1.15  # the noise is there, at the modelled level
    zs = np.concatenate(zs)
    assert zs.min() >= model.min_range_m and zs.max() <= model.max_range_m
    inc, meas = np.concatenate(inc), np.concatenate(meas)
    assert not np.any(meas[inc > np.deg2rad(model.grazing_full_deg)])
    # Dropouts are a minority of the pixels that see a surface.
    assert 0.9 < meas.mean() < 0.999


def test_box_room_circle_sees_the_box_faces() -> None:
    scene, traj = get_scene("box_room_circle")
    assert len(traj) == 24
    assert np.allclose(np.diff(traj.timestamps), 1.0)
    box = scene.object_by_name("box")
    top = scene.plane_by_name("box.top").id
    sides = [i for i in box.plane_ids if i != top]
    rng = np.random.default_rng(5)
    three = 0
    for T in traj.T_world_cam:
        assert np.isclose(np.linalg.norm(T[:2, 3]), 0.7)
        f = render_frame(scene, T, HALF, rng)
        measured = f.plane_id[f.depth_m > 0]
        side_px = sorted((int(np.sum(measured == k)) for k in sides), reverse=True)
        assert int(np.sum(measured == top)) > 500 and side_px[0] > 500
        three += side_px[1] >= 75  # 300 pixels at 640x480
        # Walls and the floor are in view too.
        walls = {scene.planes[k].name for k in np.unique(f.plane_id[f.depth_m > 0])}
        assert "room.floor" in walls and sum(w.startswith("room.wall") for w in walls) >= 2
    # On a 0.7 m circle around a 0.38 x 0.29 m box, one side face is edge-on
    # within 12-16 deg of the box axes, so not all 24 views can show two sides.
    assert three >= 14


def test_room_loop_closes_and_always_sees_three_directions() -> None:
    scene, traj = get_scene("room_boxes_loop", frames=300, rng=np.random.default_rng(1))
    assert len(traj) == 300 and np.allclose(np.diff(traj.timestamps), 1 / 30)
    assert_pose_close(traj.T_world_cam[-1], traj.T_world_cam[0], 1e-9, 1e-4)
    steps = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert steps.max() < 0.05 and steps.min() > 0.005
    for T in traj.T_world_cam[::25]:
        f = render_frame(scene, T, SMALL, np.random.default_rng(0))
        ids, counts = np.unique(f.plane_id[f.depth_m > 0], return_counts=True)
        normals = np.stack([scene.planes[k].normal for k in ids[counts > 100]])
        assert np.linalg.svd(normals, compute_uv=False)[2] > 0.3
    # Fewer frames: the same closed path, sampled more sparsely.
    short = get_scene("room_boxes_loop", frames=7, rng=np.random.default_rng(1))[1]
    longer = get_scene("room_boxes_loop", frames=13, rng=np.random.default_rng(1))[1]
    for i in range(7):
        assert_pose_close(short.T_world_cam[i], longer.T_world_cam[2 * i], 1e-9, 1e-4)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_truth_is_geometrically_consistent(name: str) -> None:
    scene, _ = get_scene(name, frames=2)
    for p in scene.planes:
        assert np.isclose(np.linalg.norm(p.normal), 1.0)
        assert np.allclose(p.polygon @ p.normal + p.d, 0.0, atol=1e-12)
    for e in scene.edges:
        for k in e.plane_ids:
            p = scene.planes[k]
            assert np.allclose(e.segment @ p.normal + p.d, 0.0, atol=1e-9)
        assert e.length_m > 0.01
    for c in scene.corners:
        for k in c.plane_ids:
            p = scene.planes[k]
            assert abs(c.point @ p.normal + p.d) < 1e-9
    room = scene.object_by_name("room")
    assert room.object_class == "room"
    for obj in scene.objects:
        assert list(obj.size_m) == sorted(obj.size_m, reverse=True) or obj.object_class == "room"
        if obj.object_class == "box":
            # A box on the floor: 8 edges of its own and 4 with the floor, all of its size.
            own = [e for e in scene.edges if set(e.plane_ids) <= set(obj.plane_ids)]
            lengths = sorted(round(e.length_m, 9) for e in own)
            sx, sy, sz = next(b for b in scene.boxes if b.name == obj.name).size_m
            assert lengths == sorted(round(v, 9) for v in [sz] * 4 + [sx] * 2 + [sy] * 2)
            assert sorted(obj.size_m) == pytest.approx(sorted([sx, sy, sz]), abs=1e-12)


def test_box_room_circle_truth_matches_the_paper() -> None:
    scene, _ = get_scene("box_room_circle")
    assert scene.object_by_name("box").size_m == pytest.approx((0.38, 0.29, 0.19), abs=1e-12)
    assert scene.object_by_name("room").size_m[:2] == pytest.approx((1.88, 1.88), abs=1e-12)
    # 12 room edges + 8 box edges + 4 box-floor edges; 8 room + 4 top + 4 floor corners.
    assert len(scene.edges) == 24 and len(scene.corners) == 16


def test_zigzag_truth_has_panel_edges() -> None:
    scene, traj = get_scene("zigzag_panels")
    assert len(traj) == 150
    zig = scene.object_by_name("zigzag")
    floor = scene.plane_by_name("room.floor").id
    panel_panel = [e for e in scene.edges if set(e.plane_ids) <= set(zig.plane_ids)]
    panel_floor = [
        e for e in scene.edges if floor in e.plane_ids and set(e.plane_ids) & set(zig.plane_ids)
    ]
    assert len(panel_panel) == 3 and len(panel_floor) == 4
    assert all(np.isclose(e.length_m, 0.8) for e in panel_panel)
    assert all(np.isclose(e.length_m, 1.0) for e in panel_floor)
    assert (
        sum(floor in c.plane_ids for c in scene.corners if set(c.plane_ids) & set(zig.plane_ids))
        == 3
    )


def test_synthesize_writes_a_tum_folder(tmp_path) -> None:
    out = tmp_path / "seq"
    result = synthesize("box_room_circle", out, frames=3, seed=4, camera=SMALL)
    assert result.num_frames == 3 and result.scene_name == "box_room_circle"
    cfg = resolve_config(out)
    assert cfg.camera == SMALL == load_camera_yaml(out / "camera.yaml")
    data = TumDataset(out, cfg.camera, cfg.dataset)
    assert len(data) == 3
    truth = load_truth(out / "truth.json")
    assert truth["schema"] == TRUTH_SCHEMA and truth["seed"] == 4
    traj = np.asarray(truth["trajectory"])
    assert data.groundtruth is not None
    assert np.allclose(data.groundtruth.timestamps, traj[:, 0], atol=1e-6)
    assert np.allclose(data.timestamps, traj[:, 0], atol=1e-6)
    T_truth = pose_from_quat(traj[:, 1:4], traj[:, 4:8])
    scene, _ = get_scene("box_room_circle", frames=3)
    model = KinectNoise()
    for i, frame in enumerate(data):
        assert_pose_close(data.groundtruth.T_world_cam[i], T_truth[i], 1e-8, 1e-4)
        clean = render_frame(scene, T_truth[i], SMALL, np.random.default_rng(0), noise=False)
        assert np.array_equal(frame.rgb.shape, clean.rgb.shape)
        valid = frame.depth_m > 0
        z = clean.depth_true_m[valid]
        bound = 3 * model.depth_sigma(z, clean.incidence_rad[valid])
        bound += model.quantisation_step(1.05 * z, SMALL.fx) / 2 + 1 / SMALL.depth_scale
        assert np.mean(np.abs(frame.depth_m[valid] - z) <= bound) > 0.99
    # Same seed, same bytes; truth planes as written are the scene's.
    again = synthesize("box_room_circle", tmp_path / "again", frames=3, seed=4, camera=SMALL)
    for p, q in zip(
        result.depth_paths + result.rgb_paths, again.depth_paths + again.rgb_paths, strict=True
    ):
        assert p.read_bytes() == q.read_bytes()
    planes = {p["name"]: p for p in truth["planes"]}
    floor = scene.plane_by_name("room.floor")
    assert np.allclose(planes["room.floor"]["normal"], floor.normal)
    assert [o["class"] for o in truth["objects"]] == ["room", "box"]


def test_synthesize_noise_free_depth_matches_render(tmp_path) -> None:
    out = tmp_path / "clean"
    synthesize("zigzag_panels", out, frames=2, seed=0, camera=SMALL, noise=False)
    cfg = resolve_config(out)
    data = TumDataset(out, cfg.camera)
    truth = load_truth(out)
    scene, _ = get_scene("zigzag_panels", frames=2)
    for frame, row in zip(data, truth["trajectory"], strict=True):
        T = pose_from_quat(np.array(row[1:4]), np.array(row[4:8]))
        clean = render_frame(scene, T, SMALL, np.random.default_rng(0), noise=False)
        # 1e-8 m of pose rounding in groundtruth.txt moves depths by far less than a PNG step.
        assert np.array_equal(frame.depth_m > 0, clean.depth_m > 0)
        assert np.abs(frame.depth_m - clean.depth_m).max() <= 0.5 / SMALL.depth_scale + 1e-5


def test_bad_requests_raise_named_errors(tmp_path) -> None:
    with pytest.raises(ConfigError, match="box_room_circle.*room_boxes_loop.*zigzag_panels"):
        synthesize("no_such_scene", tmp_path / "x")
    with pytest.raises(ConfigError, match="frames"):
        synthesize("box_room_circle", tmp_path / "y", frames=0)
    bad = tmp_path / "truth.json"
    bad.write_text(json.dumps({"schema": "something/else"}))
    with pytest.raises(DatasetFormatError, match="planeslam.truth/1"):
        load_truth(bad)
    with pytest.raises(DatasetFormatError, match="not found"):
        load_truth(tmp_path / "missing.json")


def test_texture_and_depth_move_with_the_scene() -> None:
    """Translating scene and camera together reproduces the frame exactly: texture
    lives in plane coordinates, shading in the (translation-free) world light."""
    scene, traj = get_scene("box_room_circle", frames=4)
    shift = np.array([1.5, -0.7, 0.3])
    moved = make_scene(
        "moved",
        tuple(replace(b, centre=b.centre + shift) for b in scene.boxes),
        texture=1,
    )
    T = traj.T_world_cam[1]
    T_moved = T.copy()
    T_moved[:3, 3] += shift
    f = render_frame(scene, T, SMALL, np.random.default_rng(0), noise=False)
    g = render_frame(moved, T_moved, SMALL, np.random.default_rng(0), noise=False)
    assert np.array_equal(f.plane_id, g.plane_id)
    assert np.allclose(f.depth_m, g.depth_m, atol=1e-5)
    # Pixels whose texture cell is decided by rounding-level differences may differ.
    assert np.mean(np.all(f.rgb == g.rgb, axis=2)) > 0.995
    # And a different pose shows different colours at the same pixels.
    h = render_frame(scene, traj.T_world_cam[2], SMALL, np.random.default_rng(0), noise=False)
    assert np.mean(np.all(f.rgb == h.rgb, axis=2)) < 0.5


def test_grazing_floor_drops_out() -> None:
    scene, _ = get_scene("zigzag_panels", frames=1)
    T = look_at(np.array([[0.0, -3.5, 0.3]]), np.array([[0.0, -1.0, 0.25]]))[0]
    f = render_frame(scene, T, HALF, np.random.default_rng(2))
    floor = (f.plane_id == scene.plane_by_name("room.floor").id) & (f.depth_true_m < 5.0)
    deg = np.degrees(f.incidence_rad)
    measured = f.depth_m > 0
    steep, mid, grazing = floor & (deg < 70), floor & (deg > 77) & (deg < 83), floor & (deg > 85)
    assert steep.sum() > 1000 and mid.sum() > 1000 and grazing.sum() > 1000
    assert measured[steep].mean() > 0.95
    assert 0.2 < measured[mid].mean() < 0.8
    assert not measured[grazing].any()
