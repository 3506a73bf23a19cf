"""The renderer's second depth model ('disparity', structured light) against its own
definition, the scene options (camera height, field of view, texture) that give an
independent rendering of the paper's box-in-a-room experiment, and the front end and
SLAM on those renderings."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.config import from_mapping
from planeslam.core.errors import ConfigError
from planeslam.core.geometry import invert_pose
from planeslam.eval.suite import SequenceSpec, load_suite, sequence_root
from planeslam.sim.noise import NOISE_MODELS, DisparityNoise, KinectNoise, noise_model_of
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import (
    Box,
    Scene,
    SceneOptions,
    Texture,
    get_scene,
    look_at,
    make_scene,
)
from planeslam.sim.sequence import (
    SynthOptions,
    camera_with_hfov,
    load_truth,
    render_sequence,
    synthesize,
)

pytestmark = pytest.mark.unit

HALF = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
MODEL = DisparityNoise()

INDEPENDENT = SynthOptions(
    noise_model="disparity",
    hfov_deg=57.0,
    scene=SceneOptions(
        camera_height_m=0.7,
        target_height_m=0.15,
        start_azimuth_deg=0.0,
        texture=Texture(seed=7, brightness=(0.25, 0.75)),
    ),
    label="independent",
)
"""The independent rendering of the paper's experiment, as in configs/suite.yaml."""

SUITE_YAML = Path(__file__).resolve().parents[1] / "configs" / "suite.yaml"


def _wall_frame(seed: int, model: str | DisparityNoise = "disparity"):
    """A 6 x 6 m room's +x wall seen obliquely from 1.7-3.6 m (HALF camera): (scene, frame,
    mask of wall pixels)."""
    room = Box("room", np.array((0.0, 0.0, 1.5)), np.array((6.0, 6.0, 3.0)), kind="room")
    scene = make_scene("wall", (room,), texture=Texture(seed=4, brightness=(0.7, 0.7)))
    T = look_at(np.array([[1.0, -0.5, 1.5]]), np.array([[3.0, 0.8, 1.4]]))[0]
    frame = render_frame(scene, T, HALF, np.random.default_rng(seed), noise_model=model)
    wall = frame.plane_id == scene.plane_by_name("room.wall_+x").id
    return scene, frame, wall


def _neighbourhood_disparity(d_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max true disparity over each pixel's 3 x 3 neighbourhood (edge-padded),
    computed with shifts (independently of the model's morphology)."""
    pad = np.pad(d_true, 1, mode="edge")
    H, W = d_true.shape
    shifted = np.stack([pad[i : i + H, j : j + W] for i in range(3) for j in range(3)])
    return shifted.min(axis=0), shifted.max(axis=0)


# ----------------------------------------------------------------------------- the model


def test_noise_models_by_name_and_bad_names() -> None:
    assert set(NOISE_MODELS) == {"kinect", "disparity", "tof"}
    assert isinstance(noise_model_of("disparity"), DisparityNoise)
    assert isinstance(noise_model_of(None), KinectNoise)
    custom = DisparityNoise(flying_prob=0.0)
    assert noise_model_of(custom) is custom
    with pytest.raises(ConfigError, match="'sonar'.*kinect, disparity, tof"):
        noise_model_of("sonar")
    with pytest.raises(ConfigError, match="dropout_signal_low"):
        DisparityNoise(dropout_signal_low=0.2, dropout_signal_high=0.1)
    with pytest.raises(ConfigError, match="focal_px"):
        DisparityNoise(focal_px=0.0)


def test_disparity_render_is_seeded() -> None:
    scene, traj = get_scene("box_room_circle", frames=4)
    a, b, c = (
        render_frame(scene, traj.T_world_cam[1], HALF, np.random.default_rng(s), noise_model=m)
        for s, m in ((3, "disparity"), (3, "disparity"), (4, "disparity"))
    )
    assert a.depth_m.tobytes() == b.depth_m.tobytes() and a.rgb.tobytes() == b.rgb.tobytes()
    assert not np.array_equal(a.depth_m, c.depth_m)
    k = render_frame(scene, traj.T_world_cam[1], HALF, np.random.default_rng(3))
    assert np.array_equal(a.plane_id, k.plane_id) and not np.array_equal(a.depth_m, k.depth_m)


def test_depth_lies_on_disparity_levels() -> None:
    """Every measured depth is F b / (k / 8) for an integer k; a histogram of a slanted
    wall's depth in 1 mm bins is empty between those levels, which are z^2 / (8 F b) apart."""
    _, frame, wall = _wall_frame(1)
    z = frame.depth_m[wall & (frame.depth_m > 0)].astype(np.float64)
    assert z.size > 50000 and z.min() < 2.0 and z.max() > 3.4
    k = MODEL.fb_px_m / z / MODEL.disparity_step_px
    assert np.abs(k - np.rint(k)).max() < 1e-3  # float32 depth: about 1e-5 here
    lo, hi = 2.4, 2.6
    counts, edges = np.histogram(z, bins=np.arange(lo, hi + 1e-9, 0.001))
    levels = MODEL.depth_levels(lo, hi)
    assert 10 <= len(levels) <= 14  # steps of 13-16 mm here
    occupied = edges[:-1][counts > 0] + 0.0005
    assert np.count_nonzero(counts) == len(levels)  # one full bin per level, 188 empty
    assert np.abs(occupied[:, None] - levels[None, :]).min(axis=1).max() <= 0.0005 + 1e-9
    np.testing.assert_allclose(np.diff(levels), MODEL.quantisation_step(levels[:-1]), rtol=0.02)
    # The Kinect model on the same wall quantises with the colour camera's fx (262.5 px
    # here), so its levels are other ones.
    _, kin, _ = _wall_frame(1, "kinect")
    zk = kin.depth_m[wall & (kin.depth_m > 0)].astype(np.float64)
    kk = MODEL.fb_px_m / zk / MODEL.disparity_step_px
    assert np.mean(np.abs(kk - np.rint(kk)) < 1e-3) < 0.1


def test_disparity_noise_level_and_spatial_correlation() -> None:
    """Away from edges the disparity error has the model's sigma (white, correlated and
    quantisation together) and neighbouring pixels err together, as a Gaussian-blurred
    field predicts; the Kinect model's errors are independent per pixel."""
    _, frame, wall = _wall_frame(2)
    valid = wall & (frame.depth_m > 0)
    d_meas = np.where(valid, MODEL.fb_px_m / np.where(valid, frame.depth_m, 1.0), np.nan)
    r = d_meas - MODEL.true_disparity(frame.depth_true_m)
    sigma = np.sqrt(
        MODEL.sigma_white_px**2 + MODEL.sigma_correlated_px**2 + MODEL.disparity_step_px**2 / 12
    )
    assert abs(np.nanmean(r)) < 0.01
    assert np.nanstd(r) == pytest.approx(sigma, rel=0.05)  # measured 0.0812 vs 0.0806 px

    def lag_correlation(res: np.ndarray, lag: int) -> float:
        a, b = res[:, :-lag], res[:, lag:]
        ok = np.isfinite(a) & np.isfinite(b)
        return float(np.corrcoef(a[ok], b[ok])[0, 1])

    for lag in (1, 5):
        expected = (
            MODEL.sigma_correlated_px**2 * np.exp(-(lag**2) / (4 * MODEL.correlation_px**2))
        ) / sigma**2
        assert lag_correlation(r, lag) == pytest.approx(expected, abs=0.05)  # 0.54, 0.28
    _, kin, _ = _wall_frame(2, "kinect")
    rk = np.where(wall & (kin.depth_m > 0), kin.depth_m - kin.depth_true_m, np.nan)
    assert abs(lag_correlation(rk, 1)) < 0.05


def test_flying_pixels_only_at_depth_edges() -> None:
    """Depths far from the true surface (beyond 6 sigma plus a step) occur only within a
    pixel of a depth edge (a neighbour's true disparity more than edge_jump_px away) and
    lie between the two sides' depths; about half of the measured edge pixels fly
    (flying_prob 0.5, times the chance that the mix leaves the noise band)."""
    scene, traj = get_scene("box_room_circle")
    tol = 6 * np.hypot(MODEL.sigma_white_px, MODEL.sigma_correlated_px) + MODEL.disparity_step_px
    off_total = band_total = 0
    for k in (2, 5, 16):
        frame = render_frame(
            scene, traj.T_world_cam[k], HALF, np.random.default_rng(k), noise_model=MODEL
        )
        valid = frame.depth_m > 0
        d_true = MODEL.true_disparity(frame.depth_true_m)
        d_meas = np.where(valid, MODEL.fb_px_m / np.where(valid, frame.depth_m, 1.0), 0.0)
        lo, hi = _neighbourhood_disparity(d_true)
        band = np.maximum(hi - d_true, d_true - lo) > MODEL.edge_jump_px
        off = valid & (np.abs(d_meas - d_true) > tol)
        assert not np.any(off & ~band), "a pixel far from its surface away from any edge"
        assert np.all((d_meas[off] >= lo[off] - tol) & (d_meas[off] <= hi[off] + tol))
        off_total += int(off.sum())
        band_total += int((band & valid).sum())
    assert off_total > 500
    assert 0.35 < off_total / band_total < 0.6  # measured 0.49
    # Without flying pixels nothing is off the surface.
    still = DisparityNoise(flying_prob=0.0)
    frame = render_frame(
        scene, traj.T_world_cam[2], HALF, np.random.default_rng(0), noise_model=still
    )
    valid = frame.depth_m > 0
    d_meas = np.where(valid, still.fb_px_m / np.where(valid, frame.depth_m, 1.0), 0.0)
    assert not np.any(valid & (np.abs(d_meas - still.true_disparity(frame.depth_true_m)) > tol))


def _projector_oracle(scene, T_world_cam, camera, depth_true_m, baseline_m) -> np.ndarray:
    """(H, W) bool by brute force: the segment from the projector (camera frame
    (baseline, 0, 0)) to the pixel's surface point crosses another plane first."""
    rays = PixelRays.for_camera(camera).rays
    X = depth_true_m[..., None] * rays  # (H, W, 3) camera frame
    P = np.array([baseline_m, 0.0, 0.0])
    T_cam_world = invert_pose(T_world_cam)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    blocked = np.zeros(depth_true_m.shape, dtype=bool)
    direction = X - P
    for plane in scene.planes:
        n = R @ plane.normal
        c = R @ plane.centre + t
        axes = plane.axes @ R.T
        denom = direction @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((c - P) @ n) / denom
        hit_pt = P + s[..., None] * direction
        local = (hit_pt - c) @ axes.T
        inside = np.all(np.abs(local) <= plane.half_size_m + 1e-9, axis=-1)
        blocked |= inside & (s > 1e-6) & (s < 1 - 1e-4)
    return blocked & (depth_true_m > 0)


def test_projector_shadows_match_a_brute_force_oracle() -> None:
    """Pixels the projector cannot see (beside the box's silhouettes) have no depth; the
    row-wise rule agrees with casting the projector's rays through the scene."""
    scene, traj = get_scene("box_room_circle")
    for k in (0, 3):
        T = traj.T_world_cam[k]
        frame = render_frame(scene, T, HALF, np.random.default_rng(k), noise_model=MODEL)
        shadow = MODEL.shadowed(frame.depth_true_m, HALF)
        oracle = _projector_oracle(scene, T, HALF, frame.depth_true_m, MODEL.baseline_m)
        assert oracle.sum() > 300  # a band beside the box, a few to 15 px wide here
        # The rule sees the occluder's edge at its first pixel centre, not where it is.
        # A band may end one pixel early or late, and a band thinner than a pixel next to a
        # silhouette may be missed, never more.
        differ = shadow != oracle
        assert differ.mean() < 1e-3, (int(shadow.sum()), int(oracle.sum()))
        either = shadow | oracle
        beside = np.zeros_like(oracle)
        beside[:, 1:] |= either[:, :-1]
        beside[:, :-1] |= either[:, 1:]
        z = frame.depth_true_m
        beside[:, :-1] |= z[:, 1:] < z[:, :-1] - 0.005  # left of a nearer surface
        assert np.all(beside[differ])
        assert not np.any(frame.depth_m[shadow] > 0)
        # The projector sits to the right: shadows fall on the far side left of the box.
        box = np.isin(frame.plane_id, scene.object_by_name("box").plane_ids)
        cols = np.nonzero(shadow.any(axis=0))[0]
        assert cols.max() < np.nonzero(box.any(axis=0))[0].max()


def _albedo_ladder_room() -> Scene:
    """A 7 x 7 x 3 m room whose walls go from very dark to bright (mean albedo 0.06,
    0.12, 0.2, 0.8; floor 0.7, ceiling 0.5)."""
    room = Box("room", np.array((0.0, 0.0, 1.5)), np.array((7.0, 7.0, 3.0)), kind="room")
    scene = make_scene("ladder", (room,), texture=Texture(seed=5))
    grey = {"wall_+x": 0.06, "wall_-x": 0.12, "wall_+y": 0.2, "wall_-y": 0.8, "floor": 0.7}
    planes = tuple(
        replace(p, albedo_rgb=np.full(3, grey.get(p.name.split(".")[1], 0.5))) for p in scene.planes
    )
    return replace(scene, planes=planes)


def test_dropouts_rise_with_incidence_and_darkness() -> None:
    """Dropout rates per bin of incidence (bright surfaces) and of reflectance (surfaces
    faced within 45 deg) match the model's probability, linear in rho cos(theta), and rise
    with incidence and with darkness."""
    scene = _albedo_ladder_room()
    eyes = np.array(
        [[0.0, 2.5, 0.3], [0.0, 1.5, 1.6], [1.5, 0.0, 1.5], [-1.5, 0.3, 1.5], [0.2, 1.5, 1.5]]
    )
    targets = np.array(
        [[0.0, -3.5, 0.25], [0.0, -0.5, 0.0], [3.5, 0.0, 1.4], [-3.5, 0.3, 1.4], [0.2, 3.5, 1.5]]
    )
    dropped, p_model, inc, rho = [], [], [], []
    rng = np.random.default_rng(6)
    for T in look_at(eyes, targets):
        f = render_frame(scene, T, HALF, rng, noise_model=MODEL)
        near_edge, _ = MODEL.flying_candidates(f.depth_true_m)
        keep = (f.depth_true_m > 0.6) & (f.depth_true_m < 4.0) & ~near_edge
        keep &= ~MODEL.shadowed(f.depth_true_m, HALF)
        p = MODEL.dropout_probability(f.reflectance, f.incidence_rad)
        p = 1 - (1 - p) * (1 - MODEL.random_dropout_prob)
        dropped.append(f.depth_m[keep] == 0)
        p_model.append(p[keep])
        inc.append(np.degrees(f.incidence_rad[keep]))
        rho.append(f.reflectance[keep])
    drop, pm = np.concatenate(dropped), np.concatenate(p_model)
    deg, refl = np.concatenate(inc), np.concatenate(rho)

    def rates(bins: list[np.ndarray]) -> list[float]:
        """Empirical dropout rate per bin, each checked against the model's mean."""
        out = []
        for m in bins:
            n = int(m.sum())
            assert n > 1500, [int(b.sum()) for b in bins]
            emp, exp = float(drop[m].mean()), float(pm[m].mean())
            assert abs(emp - exp) < 0.01 + 4 * np.sqrt(max(exp * (1 - exp), 1e-3) / n)
            out.append(emp)
        return out

    bright = refl > 0.35
    angle_bins = ((0, 60), (60, 72), (72, 78), (78, 82), (82, 88))
    emp = rates([bright & (deg >= a) & (deg < b) for a, b in angle_bins])
    assert emp[0] < 0.01 and emp[-1] > 0.6  # measured 0.001 0.001 0.066 0.373 0.806
    assert all(b > a + 0.05 for a, b in zip(emp[1:], emp[2:], strict=False))
    facing = deg < 45
    dark_bins = ((0.0, 0.05), (0.05, 0.08), (0.08, 0.11), (0.11, 0.2), (0.3, 1.0))
    emp = rates([facing & (refl >= a) & (refl < b) for a, b in dark_bins])
    assert emp[0] > 0.8 and emp[-1] < 0.01  # measured 0.987 0.777 0.419 0.044 0.001
    assert all(a > b + 0.03 for a, b in zip(emp, emp[1:], strict=False))


# ------------------------------------------------------------- scene options, synth options


def test_scene_options_move_the_camera_not_the_scene() -> None:
    default, traj0 = get_scene("box_room_circle")
    scene, traj = get_scene("box_room_circle", options=INDEPENDENT.scene)
    assert [(p.name, p.d) for p in scene.planes] == [(p.name, p.d) for p in default.planes]
    assert len(scene.edges) == len(default.edges) and len(scene.corners) == len(default.corners)
    eye = traj.positions
    np.testing.assert_allclose(eye[:, 2], 0.7)
    np.testing.assert_allclose(np.linalg.norm(eye[:, :2], axis=1), 0.7)
    np.testing.assert_allclose(eye[0], [0.7, 0.0, 0.7], atol=1e-12)  # azimuth 0
    np.testing.assert_allclose(np.degrees(np.arctan2(eye[1, 1], eye[1, 0])), 15.0)
    # Looking at the point 0.15 m above the floor's centre.
    view = traj.T_world_cam[:, :3, 2]
    to_target = np.array([0.0, 0.0, 0.15]) - eye
    to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ij,ij->i", view, to_target), 1.0)
    assert np.allclose(traj0.positions[:, 2], 0.5)
    # The other scenes take height and look-at height, not a start azimuth.
    _, zig = get_scene("zigzag_panels", 3, options=SceneOptions(camera_height_m=1.6))
    np.testing.assert_allclose(zig.positions[:, 2], 1.6, atol=0.03)  # plus hand-shake
    with pytest.raises(ConfigError, match="zigzag_panels.*start_azimuth_deg"):
        get_scene("zigzag_panels", 3, options=SceneOptions(start_azimuth_deg=10.0))
    with pytest.raises(ConfigError, match="camera_height_m"):
        SceneOptions(camera_height_m=-1.0)


def test_texture_ranges_and_default_appearance() -> None:
    """The default Texture draws what the scenes always had (mean albedo 0.6); another
    brightness range changes only the brightness, a seed changes everything."""
    scene, _ = get_scene("room_boxes_loop", frames=2)
    assert all(abs(p.albedo_rgb.mean() - 0.6) < 1e-12 for p in scene.planes)
    boxes = scene.boxes
    dim = make_scene("x", boxes, texture=Texture(seed=2, brightness=(0.1, 0.3)))
    same = make_scene("x", boxes, texture=2)
    other = make_scene("x", boxes, texture=Texture(seed=3))
    for p, q, r, s in zip(scene.planes, dim.planes, same.planes, other.planes, strict=True):
        assert np.array_equal(p.albedo_rgb, r.albedo_rgb) and p.texture_salt == r.texture_salt
        assert q.texture_cell_m == p.texture_cell_m and q.texture_salt == p.texture_salt
        assert s.texture_salt != p.texture_salt
    means = np.array([q.albedo_rgb.mean() for q in dim.planes])
    assert means.max() < 0.35 and np.ptp(means) > 0.1
    with pytest.raises(ConfigError, match="brightness"):
        Texture(brightness=(0.5, 0.2))
    with pytest.raises(ConfigError, match="cell_m"):
        Texture(cell_m=(0.0, 0.02))


def test_camera_with_hfov() -> None:
    cam = camera_with_hfov(57.0)
    assert cam.width == 640 and cam.fx == cam.fy
    assert np.degrees(2 * np.arctan(cam.width / 2 / cam.fx)) == pytest.approx(57.0)
    assert (cam.cx, cam.cy) == (319.5, 239.5)
    small = camera_with_hfov(90.0, HALF)
    assert small.fx == pytest.approx(160.0) and small.depth_scale == HALF.depth_scale
    with pytest.raises(ConfigError, match="field of view"):
        camera_with_hfov(180.0)


def test_independent_first_frame_sees_floor_back_wall_and_two_box_faces() -> None:
    """The independent rendering's first frame, as in the issue: floor, back wall, the
    box's top and one side; no other surface, so no trihedral corner is in view."""
    scene, traj = get_scene("box_room_circle", options=INDEPENDENT.scene)
    camera = INDEPENDENT.camera()
    f = render_frame(
        scene, traj.T_world_cam[0], camera, np.random.default_rng(0), noise_model="disparity"
    )
    ids, counts = np.unique(f.plane_id[f.depth_m > 0], return_counts=True)
    seen = {scene.planes[i].name: int(n) for i, n in zip(ids, counts, strict=True)}
    assert set(seen) == {"room.floor", "room.wall_-x", "box.top", "box.side_+x"}, seen
    assert min(seen.values()) > 10000
    visible = set(seen)
    for c in scene.corners:
        assert not {scene.planes[i].name for i in c.plane_ids} <= visible


def test_synth_options_from_yaml_and_their_tag() -> None:
    text = """
noise_model: disparity
hfov_deg: 57
scene: {camera_height_m: 0.7, start_azimuth_deg: 0, texture: {seed: 7, brightness: [0.25, 0.75]}}
"""
    opts = from_mapping(SynthOptions, yaml.safe_load(text), "test.yaml")
    assert opts.scene.texture == Texture(seed=7, brightness=(0.25, 0.75))
    assert opts.tag == "disparity-fov57-h0.7-az0-tex7-b0.25-0.75"
    assert SynthOptions().tag == "" and SynthOptions(noise_model="disparity").tag == "disparity"
    assert INDEPENDENT.tag == "independent"
    assert opts.camera().fx == pytest.approx(camera_with_hfov(57.0).fx)
    with pytest.raises(ConfigError, match="unknown key.*valid keys: noise_model"):
        from_mapping(SynthOptions, {"noise": "disparity"}, "test.yaml")
    with pytest.raises(
        ConfigError, match=r"noise_model must be one of \['kinect', 'disparity', 'tof'\]"
    ):
        from_mapping(SynthOptions, {"noise_model": "sonar"}, "test.yaml")
    with pytest.raises(ConfigError, match="label"):
        SynthOptions(label="a b")


def test_suite_sequences_with_synth_options(tmp_path: Path) -> None:
    suite = tmp_path / "suite.yaml"
    suite.write_text(
        "methods: [isam2]\nsequences:\n"
        "  - scene: box_room_circle\n"
        "  - scene: box_room_circle\n    synth: {noise_model: disparity}\n"
        "  - scene: box_room_circle\n    synth: {label: indep, hfov_deg: 57}\n"
    )
    config, _ = load_suite(suite)
    names = [s.name for s in config.sequences]
    assert names == ["box_room_circle", "box_room_circle/disparity", "box_room_circle/indep"]
    roots = [sequence_root(s, tmp_path, tmp_path / "out").name for s in config.sequences]
    assert roots == ["box_room_circle", "box_room_circle_disparity", "box_room_circle_indep"]
    suite.write_text(
        "methods: [isam2]\nsequences:\n  - path: somewhere\n    synth: {noise_model: disparity}\n"
    )
    with pytest.raises(ConfigError, match=r"sequences\[0\].synth applies to a 'scene' only"):
        load_suite(suite)


def test_default_suite_has_the_independent_rendering() -> None:
    """configs/suite.yaml runs box_room_circle as it is, with the disparity model, and as
    the independent rendering (the options above), side by side."""
    config, _ = load_suite(SUITE_YAML)
    box = [s for s in config.sequences if s.scene == "box_room_circle"]
    assert [s.synth for s in box] == [
        SynthOptions(),
        SynthOptions(noise_model="disparity"),
        INDEPENDENT,
    ]
    assert SequenceSpec(scene="box_room_circle", synth=INDEPENDENT).name in [s.name for s in box]


@pytest.mark.integration
def test_synth_command_writes_the_rendering_it_was_asked_for(tmp_path: Path) -> None:
    from planeslam.app.cli import main

    out = tmp_path / "seq"
    code = main(
        ["synth", "box_room_circle", str(out), "--frames", "2", "--noise-model", "disparity",
         "--hfov", "57", "--camera-height", "0.7", "--look-height", "0.15",
         "--start-azimuth", "0", "--texture-seed", "7", "--texture-brightness", "0.25,0.75"]
    )  # fmt: skip
    assert code == 0
    truth = load_truth(out)
    assert truth["rendering"]["noise_model"] == "disparity"
    assert truth["rendering"]["noise_constants"]["focal_px"] == MODEL.focal_px
    assert truth["rendering"]["scene_options"]["camera_height_m"] == 0.7
    assert truth["camera"]["fx"] == pytest.approx(INDEPENDENT.camera().fx)
    np.testing.assert_allclose(np.asarray(truth["trajectory"])[0, 1:4], [0.7, 0.0, 0.7], atol=1e-9)
    # The same through the library, frame for frame.
    again = render_sequence("box_room_circle", tmp_path / "lib", INDEPENDENT, frames=2)
    assert [p.read_bytes() for p in again.depth_paths] == [
        (out / "depth" / p.name).read_bytes() for p in again.depth_paths
    ]
    # A brightness range needs the texture's seed: a one-line error, exit code 2.
    bad = ["synth", "box_room_circle", str(tmp_path / "x"), "--texture-brightness", "0.2,0.4"]
    assert main(bad) == 2


def test_written_depth_keeps_the_disparity_levels(tmp_path: Path) -> None:
    """After the 16-bit PNG (0.2 mm per unit) the depth still sits on the levels."""
    result = synthesize(
        "box_room_circle", tmp_path / "seq", frames=2, camera=HALF, noise_model="disparity"
    )
    from planeslam.io.dataset import TumDataset

    data = TumDataset(result.out_dir, HALF)
    for frame in data:
        z = frame.depth_m[frame.depth_m > 0].astype(np.float64)
        k = MODEL.fb_px_m / z / MODEL.disparity_step_px
        level = MODEL.fb_px_m / (np.rint(k) * MODEL.disparity_step_px)
        assert np.abs(z - level).max() <= 0.5 / HALF.depth_scale + 1e-6
    with pytest.raises(ConfigError, match="depth_scale"):
        synthesize("box_room_circle", tmp_path / "bad", frames=1, noise_model="disparity",
                   camera=CameraConfig(depth_scale=20000.0))  # fmt: skip
    assert json.loads(result.truth_path.read_text())["rendering"]["noise"] is True


# --------------------------------------------------------- the front end and SLAM on them

THREE_FACE_FRAMES = (2, 3, 8, 9, 14, 15, 20, 21)
"""box_room_circle frames showing the box top and two sides (as in test_frontend.py)."""


@pytest.mark.integration
def test_front_end_finds_box_and_room_in_disparity_frames() -> None:
    """Per frame, with the disparity model: the box in every three-face frame, sized
    within 1.5 cm each (measured over 10 seeds: 78 of 80 frames within 7.5 mm, the worst
    2.2 cm, one side lengthened by flying pixels) and within 3 mm as the median of the
    eight (measured at most 2.4 mm over 5 seeds); the room in at least 6 of them (6-8);
    every trihedral corner within 5 mm of a true one (at most 1.7 mm)."""
    from planeslam.config import PlaneSlamConfig
    from planeslam.core.geometry import transform_points
    from planeslam.frontend.pipeline import FrontEnd

    config = PlaneSlamConfig()
    front = FrontEnd(config)
    scene, traj = get_scene("box_room_circle")
    true_box = np.array(scene.object_by_name("box").size_m)
    sizes, rooms = [], 0
    for k in THREE_FACE_FRAMES:
        T = traj.T_world_cam[k]
        frame = render_frame(
            scene, T, config.camera, np.random.default_rng([0, k]), noise_model="disparity"
        )
        st = front.process(frame.depth_m).structure
        boxes = [o for o in st.objects if o.cls == "box"]
        assert len(boxes) == 1, (k, [(o.cls, o.size_m) for o in st.objects])
        sizes.append(sorted(boxes[0].size_m, reverse=True))
        rooms += any(o.cls == "room" for o in st.objects)
        corners_cam = transform_points(invert_pose(T), np.stack([c.point for c in scene.corners]))
        for c in st.corners:
            assert np.linalg.norm(corners_cam - c.point, axis=1).min() < 0.005, k
    err = np.array(sizes) - true_box
    assert np.abs(err).max() < 0.015, np.round(err, 4)
    assert np.abs(np.median(np.array(sizes), axis=0) - true_box).max() < 0.003
    assert rooms >= 6


def _slam_on(root: Path):
    """Full SLAM (iSAM2) from the true first pose -> (summary, ATE [m], abs size errors by
    class [m])."""
    from planeslam.config import resolve_config
    from planeslam.eval.object_sizes import object_size_errors
    from planeslam.eval.trajectory_metrics import evaluate_trajectory
    from planeslam.io.dataset import TumDataset
    from planeslam.slam import SLAM, run_frames

    cfg = resolve_config(root)
    data = TumDataset(root, cfg.camera, cfg.dataset)
    with SLAM(cfg, "isam2", T_world_first=data.groundtruth_pose(data.timestamps[0])) as slam:
        summary = run_frames(slam, data, list(range(len(data))))
    errors = object_size_errors(slam.map.to_dict()["objects"], load_truth(root))
    by_class = {e["class"]: np.asarray(e["abs_error_m"]) for e in errors}
    assert data.groundtruth is not None
    ate = evaluate_trajectory(data.groundtruth, slam.trajectory(), 0.02, 1.0).ate_rmse_m
    return summary, ate, by_class


@pytest.mark.integration
@pytest.mark.slow
def test_slam_on_the_disparity_rendering(tmp_path: Path) -> None:
    """box_room_circle with the disparity model and the scene's own camera: every frame
    tracked; measured over seeds 0-4: ATE 0.7-1.4 mm, box within 3.0 mm, room within
    2.5 mm (the Kinect model: 0.1 mm, 2.8 mm, 0.1 mm)."""
    root = render_sequence("box_room_circle", tmp_path / "seq", SynthOptions("disparity")).out_dir
    summary, ate, sizes = _slam_on(root)
    assert summary.lost_frames == 0
    assert ate < 0.003
    assert sizes["box"].max() < 0.006 and sizes["room"].max() < 0.006


@pytest.mark.integration
@pytest.mark.slow
def test_slam_on_the_independent_rendering_reaches_the_issue_target(tmp_path: Path) -> None:
    """The issue's target on the independent rendering: all 24 poses tracked, box sizes
    within 1 cm, room within 2 cm. At commit 19577cf every frame after the first was lost
    ('plane pose degenerate_rotation'); the ATE bound is the one test_slam.py sets for the
    scene's own rendering."""
    root = render_sequence("box_room_circle", tmp_path / "seq", INDEPENDENT).out_dir
    summary, ate, sizes = _slam_on(root)
    assert summary.lost_frames == 0
    assert ate < 0.01
    assert sizes["box"].max() < 0.01 and sizes["room"].max() < 0.02
