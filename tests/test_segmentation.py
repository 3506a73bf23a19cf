"""Plane segmentation (paper step 2): accuracy on synthetic frames with exact truth,
plane statistics and covariance, bad input, and the real 7-Scenes frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.errors import ConfigError, GeometryError
from planeslam.core.geometry import tangent_basis
from planeslam.core.plane_fit import (
    correlated_depth_sigmas,
    merge_moments,
    moments_of,
    patch_covariance,
    plane_covariance,
    plane_from_moments,
)
from planeslam.frontend.cell_kernels import smallest_eigh3_kernel
from planeslam.frontend.cloud import organized_cloud
from planeslam.frontend.config import MsacConfig, OrganizedConfig, SegmentationConfig
from planeslam.frontend.msac import MsacSegmenter
from planeslam.frontend.organized import OrganizedSegmenter
from planeslam.frontend.segmentation import make_segmenter, segment_cloud, segment_planes
from planeslam.frontend.types import Segmentation, Segmenter
from planeslam.sim.render import plane_in_camera, render_frame
from planeslam.sim.scenes import get_scene
from tests.conftest import shared_sequence

pytestmark = pytest.mark.unit

CAMERA = CameraConfig()  # 640 x 480, f = 525
RAYS = PixelRays.for_camera(CAMERA)
ORGANIZED = SegmentationConfig()
MSAC = SegmentationConfig(method="msac")


def _organized(**changes) -> SegmentationConfig:
    """The default config with `changes` to its `organized` section."""
    return dataclasses.replace(ORGANIZED, organized=OrganizedConfig(**changes))


def _render(scene_name: str, frame: int, seed: int):
    scene, trajectory = get_scene(scene_name)
    T_world_cam = trajectory.T_world_cam[frame]
    rendered = render_frame(scene, T_world_cam, CAMERA, np.random.default_rng(seed), noise=True)
    return scene, T_world_cam, rendered


def _check_against_truth(seg: Segmentation, scene, T_world_cam, rendered, max_z: float = 3.0):
    """Every true plane with >= 3000 valid pixels, mean depth <= max_z, is found once,
    within 1 deg and 1 cm, and no found plane covers two true planes."""
    truth = np.where(rendered.depth_m > 0, rendered.plane_id, -1)
    ids, counts = np.unique(truth[truth >= 0], return_counts=True)
    checked = 0
    for true_id, count in zip(ids, counts, strict=True):
        pixels = truth == true_id
        if count < 3000 or rendered.depth_m[pixels].mean() > max_z:
            continue
        name = scene.planes[true_id].name
        labels, hits = np.unique(seg.labels[pixels], return_counts=True)
        hits, labels = hits[labels >= 0], labels[labels >= 0]
        assert len(labels), f"{name} ({count} px) not found"
        assert np.sum(hits > 0.1 * count) == 1, f"{name} split into planes {labels} ({hits} px)"
        assert hits.max() > 0.8 * count, f"{name}: only {hits.max()} of {count} px labelled"
        plane = seg.planes[int(labels[np.argmax(hits)])]
        n_true, d_true = plane_in_camera(scene.planes[true_id], T_world_cam)
        angle = np.degrees(np.arccos(min(1.0, float(plane.normal @ n_true))))
        assert angle < 1.0, f"{name}: normal off by {angle:.2f} deg"
        assert abs(plane.d - d_true) < 0.01, f"{name}: d {plane.d:.4f} m, truth {d_true:.4f} m"
        checked += 1
    for plane in seg.planes:
        covered, n = np.unique(truth[seg.labels == plane.id], return_counts=True)
        major = covered[(covered >= 0) & (n > 0.1 * n.sum())]
        assert len(major) <= 1, f"plane {plane.id} merges true planes {major}"
    return checked


def _check_plane_fields(seg: Segmentation, stride: int = 1) -> None:
    """Plane records are consistent; with `pixel_stride` k each fitted pixel labels its
    k x k block (640 x 480 divides by k = 2)."""
    assert seg.labels.dtype == np.int32 and seg.labels.shape == (CAMERA.height, CAMERA.width)
    sizes = [p.num_points for p in seg.planes]
    assert sizes == sorted(sizes, reverse=True)
    assert [p.id for p in seg.planes] == list(range(len(seg.planes)))
    labelled = np.bincount(seg.labels[seg.labels >= 0], minlength=len(sizes))
    assert np.array_equal(labelled, stride**2 * np.array(sizes, dtype=np.int64))
    for p in seg.planes:
        assert p.d > 0 and abs(np.linalg.norm(p.normal) - 1) < 1e-9
        assert p.points.shape == (p.num_points, 3) and p.points.dtype == np.float64
        count, centroid, scatter = moments_of(p.points)
        np.testing.assert_allclose(centroid, p.centroid, atol=1e-9)
        np.testing.assert_allclose(scatter, p.scatter, rtol=1e-6, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(p.covariance) > 0)
        assert p.outline.shape[1] == 3 and len(p.outline) >= 3
        np.testing.assert_allclose(p.outline @ p.normal + p.d, 0.0, atol=1e-9)
        assert p.area_m2 > 0


@pytest.mark.integration
@pytest.mark.parametrize(
    ("scene_name", "frame"),
    [
        ("box_room_circle", 0),
        ("box_room_circle", 9),
        ("room_boxes_loop", 59),
        ("room_boxes_loop", 179),
        ("zigzag_panels", 29),
        ("zigzag_panels", 89),
    ],
)
@pytest.mark.parametrize("stride", [1, 2])
def test_organized_matches_truth(scene_name, frame, stride):
    scene, T_world_cam, rendered = _render(scene_name, frame, seed=frame + 1)
    cfg = _organized(pixel_stride=stride)
    seg = segment_planes(rendered.depth_m, RAYS, cfg)
    assert seg.reason == ""
    assert _check_against_truth(seg, scene, T_world_cam, rendered) >= 3
    _check_plane_fields(seg, stride)


@pytest.mark.integration
@pytest.mark.parametrize(("scene_name", "frame"), [("box_room_circle", 4), ("zigzag_panels", 59)])
def test_msac_matches_truth(scene_name, frame):
    scene, T_world_cam, rendered = _render(scene_name, frame, seed=frame + 1)
    seg = segment_planes(rendered.depth_m, RAYS, MSAC, rng=np.random.default_rng(3))
    assert _check_against_truth(seg, scene, T_world_cam, rendered) >= 3
    _check_plane_fields(seg)


@pytest.mark.slow  # two MSAC runs on a full frame
def test_msac_is_reproducible_with_a_seed():
    _, _, rendered = _render("box_room_circle", 13, seed=5)
    a = segment_planes(rendered.depth_m, RAYS, MSAC, rng=np.random.default_rng(7))
    b = segment_planes(rendered.depth_m, CAMERA, MSAC, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(a.labels, b.labels)


def test_camera_and_rays_give_the_same_result():
    _, _, rendered = _render("room_boxes_loop", 0, seed=2)
    a = segment_planes(rendered.depth_m, RAYS, ORGANIZED)
    b = segment_planes(rendered.depth_m, CAMERA, ORGANIZED)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.planes[0].area_m2 == pytest.approx(b.planes[0].area_m2, rel=1e-6)


# ------------------------------------------------------------------ analytic scenes


def _analytic_depth(planes, rng, noise=True):
    """Nearest intersection of each pixel ray with planes [(n, d, mask (H, W) or None)],
    plus Kinect-like noise sigma = 0.0012 + 0.0019 z^2 (seeded)."""
    depth = np.full((CAMERA.height, CAMERA.width), np.inf)
    for n, d, mask in planes:
        along = RAYS.rays @ np.asarray(n, dtype=np.float64)
        with np.errstate(divide="ignore"):
            z = np.where(along < 0, -d / along, np.inf)
        if mask is not None:
            z = np.where(mask, z, np.inf)
        depth = np.minimum(depth, z)
    depth[~np.isfinite(depth)] = 0.0
    if noise:
        depth += (0.0012 + 0.0019 * depth**2) * rng.standard_normal(depth.shape) * (depth > 0)
    return depth.astype(np.float32)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_area_and_outline_of_a_frontal_wall():
    depth = _analytic_depth([((0, 0, -1), 2.0, None)], None, noise=False)
    seg = segment_planes(depth, RAYS, ORGANIZED)
    assert len(seg.planes) == 1
    wall = seg.planes[0]
    expected = (CAMERA.width * 2.0 / CAMERA.fx) * (CAMERA.height * 2.0 / CAMERA.fy)
    assert wall.area_m2 == pytest.approx(expected, rel=1e-4)
    # outline polygon (pixel centres of the border) spans the image less one pixel
    x, y = wall.outline[:, 0], wall.outline[:, 1]
    polygon_area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    inner = ((CAMERA.width - 1) * 2.0 / CAMERA.fx) * ((CAMERA.height - 1) * 2.0 / CAMERA.fy)
    assert polygon_area == pytest.approx(inner, rel=0.01)


@pytest.mark.parametrize("merge", [True, False])
def test_wall_split_by_an_occluder(merge, rng):
    """A tilted wall behind a pole: one plane when coplanar regions merge, else two."""
    u = np.broadcast_to(np.arange(CAMERA.width), (CAMERA.height, CAMERA.width))
    wall_n = _unit([0.3, -0.1, -1.0])
    pole = (u >= 290) & (u < 340)
    depth = _analytic_depth([(wall_n, 2.5, None), ((0, 0, -1), 1.2, pole)], rng)
    cfg = _organized(merge_coplanar=merge)
    seg = segment_planes(depth, RAYS, cfg)
    walls = [p for p in seg.planes if abs(p.d - 2.5) < 0.02]
    assert len(walls) == (1 if merge else 2)
    for wall in walls:
        assert np.degrees(np.arccos(min(1.0, wall.normal @ wall_n))) < 0.5
    poles = [p for p in seg.planes if abs(p.d - 1.2) < 0.01]
    assert len(poles) == 1 and poles[0].normal[2] < -0.999


def test_two_planes_meeting_at_a_shallow_angle_stay_apart(rng):
    """A 160 deg dihedral (20 deg bend) at 1.5 m: two planes, not one."""
    v = np.broadcast_to(np.arange(CAMERA.height)[:, None], (CAMERA.height, CAMERA.width))
    n_a = _unit([0.0, 0.0, -1.0])
    n_b = _unit([0.0, np.sin(np.radians(20)), -np.cos(np.radians(20))])
    # plane B shares the line z = 1.5, y = 0 with A
    depth = _analytic_depth(
        [(n_a, 1.5, v < 240), (n_b, 1.5 * np.cos(np.radians(20)), v >= 240)], rng
    )
    seg = segment_planes(depth, RAYS, ORGANIZED)
    assert len(seg.planes) == 2
    for truth in (n_a, n_b):
        assert max(p.normal @ truth for p in seg.planes) > np.cos(np.radians(1.0))


# ------------------------------------------------------------------ plane statistics


def test_tangent_basis_matches_gtsam_unit3(rng):
    gtsam = pytest.importorskip("gtsam")
    for n in [*rng.normal(size=(50, 3)), (0, 0, -1.0), (1, 1, 0.0), (0, -1, 1.0)]:
        n = _unit(n)
        np.testing.assert_allclose(tangent_basis(n), gtsam.Unit3(n).basis(), atol=1e-12)


def test_smallest_eigh3_kernel_matches_numpy(rng):
    a = rng.normal(size=(200, 3, 3))
    s = a @ a.transpose(0, 2, 1)
    s[:50, :, 2] *= 1e-3  # flat ones, as plane cells are
    s = 0.5 * (s + s.transpose(0, 2, 1))
    lam_min, lam_mid, vec = smallest_eigh3_kernel(s)
    ref_val, ref_vec = np.linalg.eigh(s)
    np.testing.assert_allclose(lam_min, ref_val[:, 0], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(lam_mid, ref_val[:, 1], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum("ki,ki->k", vec, ref_vec[:, :, 0])), 1.0, atol=1e-6)


def test_merge_moments_is_exact(rng):
    pts = rng.normal(size=(300, 3)) * [1.0, 0.5, 0.01] + [0.2, -0.1, 2.0]
    parts = np.split(pts, [50, 170])
    stats = [moments_of(p) for p in parts]
    count, centroid, scatter = merge_moments(
        np.array([s[0] for s in stats]),
        np.stack([s[1] for s in stats]),
        np.stack([s[2] for s in stats]),
    )
    ref = moments_of(pts)
    assert count == ref[0]
    np.testing.assert_allclose(centroid, ref[1], atol=1e-12)
    np.testing.assert_allclose(scatter, ref[2], atol=1e-9)


def test_fit_covariance_matches_monte_carlo(rng):
    """Spread of (tangent-space normal error, d error) over noisy fits of one patch
    agrees with `plane_covariance` within 15 %."""
    n_true = _unit([0.2, -0.3, -0.9])
    d_true = 1.8
    basis = tangent_basis(n_true)
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 20), np.linspace(-0.2, 0.2, 15))
    plane_pts = -d_true * n_true + u.reshape(-1, 1) * basis[:, 0] + v.reshape(-1, 1) * basis[:, 1]
    plane_pts += np.array([0.4, 0.1, 0.0]) - n_true * (n_true @ [0.4, 0.1, 0.0])
    sigma = 0.004
    errors, predicted = [], []
    for _ in range(2000):
        pts = plane_pts + sigma * rng.standard_normal((len(plane_pts), 1)) * n_true
        count, centroid, scatter = moments_of(pts)
        n, d, rss = plane_from_moments(centroid, scatter)
        xi = basis.T @ n / (n @ n_true)  # local coordinates of n around n_true
        errors.append([xi[0], xi[1], d - d_true])
        predicted.append(plane_covariance(n, centroid, scatter, count, rss))
    empirical = np.cov(np.array(errors).T)
    model = np.mean(predicted, axis=0)
    np.testing.assert_allclose(np.diag(empirical), np.diag(model), rtol=0.15)
    corr = empirical[0, 2] / np.sqrt(empirical[0, 0] * empirical[2, 2])
    corr_model = model[0, 2] / np.sqrt(model[0, 0] * model[2, 2])
    assert corr == pytest.approx(corr_model, abs=0.1)


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize("method", ["organized", "msac"])
@pytest.mark.parametrize("value", [0.0, np.nan, np.inf, -1.0, 50.0])
def test_frame_without_valid_depth_gives_empty_result(method, value):
    depth = np.full((CAMERA.height, CAMERA.width), value, dtype=np.float32)
    seg = segment_planes(depth, RAYS, SegmentationConfig(method=method))
    assert seg.planes == [] and "no valid depth" in seg.reason
    assert np.all(seg.labels == -1) and seg.labels.dtype == np.int32


def test_frame_without_planes_gives_empty_result(rng):
    depth = rng.uniform(1.0, 3.0, (CAMERA.height, CAMERA.width)).astype(np.float32)
    for cfg in (ORGANIZED, MSAC):
        seg = segment_planes(depth, RAYS, cfg, rng=np.random.default_rng(0))
        assert seg.planes == [] and "no plane" in seg.reason


def test_wrong_depth_shape_names_the_shapes():
    with pytest.raises(GeometryError, match=r"\(240, 320\).*480x640"):
        segment_planes(np.ones((240, 320), np.float32), RAYS)


def test_bad_camera_argument_and_config():
    with pytest.raises(ConfigError, match="CameraConfig or PixelRays"):
        segment_planes(np.ones((480, 640), np.float32), np.ones((480, 640, 3)))
    with pytest.raises(ConfigError, match="organized.cell_size_px"):
        OrganizedConfig(cell_size_px=0)
    with pytest.raises(ConfigError, match="organized.pixel_stride"):
        OrganizedConfig(pixel_stride=5)
    with pytest.raises(ConfigError, match="multiple of"):
        OrganizedConfig(cell_size_px=15, pixel_stride=2)
    with pytest.raises(ConfigError, match="msac.hypotheses"):
        MsacConfig(hypotheses=0)
    with pytest.raises(ConfigError, match="segmentation.min_plane_points"):
        SegmentationConfig(min_plane_points=0)
    with pytest.raises(ConfigError, match="method"):
        SegmentationConfig(method="ransac")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="sensor.sigma_a_m"):
        DepthNoiseConfig(sigma_a_m=0.0)
    with pytest.raises(ConfigError, match="sensor.sigma_b_per_m"):
        DepthNoiseConfig(sigma_b_per_m=-1e-3)


@pytest.mark.parametrize(
    ("method", "kind"),
    [
        ("organized", OrganizedSegmenter),
        pytest.param("msac", MsacSegmenter, marks=pytest.mark.slow),  # MSAC: seconds a frame
    ],
)
def test_factory_picks_the_method_and_entry_points_agree(method, kind):
    """`make_segmenter` gives a `Segmenter` of the configured method, and
    `segment_planes` = `organized_cloud` + `segment_cloud` = the segmenter itself."""
    _, _, rendered = _render("box_room_circle", 4, seed=5)
    cfg = SegmentationConfig(method=method)
    segmenter: Segmenter = make_segmenter(cfg)
    assert type(segmenter) is kind
    cloud = organized_cloud(rendered.depth_m, RAYS, cfg.max_depth_m)
    a = segmenter.segment(cloud, RAYS, np.random.default_rng(3), rendered.depth_m)
    b = segment_cloud(cloud, RAYS, cfg, np.random.default_rng(3), depth_m=rendered.depth_m)
    c = segment_planes(rendered.depth_m, RAYS, cfg, rng=np.random.default_rng(3))
    assert len(a.planes) >= 3
    for other in (b, c):
        np.testing.assert_array_equal(a.labels, other.labels)
        assert [p.d for p in a.planes] == [p.d for p in other.planes]


def test_depth_noise_scales_the_inlier_band():
    """The thresholds are multiples of the sensor's sigma(z): with a 10x noisier sensor
    model the wall takes in a strip 5 cm off it that the default leaves out."""
    u = np.broadcast_to(np.arange(CAMERA.width), (CAMERA.height, CAMERA.width))
    depth = _analytic_depth([((0, 0, -1), 2.0, None)], None, noise=False)
    depth[:, u[0] >= 600] += 0.05  # a 5 cm step along the right border
    right = np.s_[:, 600:]
    default = segment_planes(depth, RAYS, ORGANIZED)
    noisy = segment_planes(
        depth, RAYS, ORGANIZED, sensor=DepthNoiseConfig(sigma_a_m=0.012, sigma_b_per_m=0.019)
    )
    assert np.all(default.labels[right] != default.labels[240, 100])
    assert np.all(noisy.labels[right] == noisy.labels[240, 100])
    assert DepthNoiseConfig().sigma_m(2.0) == pytest.approx(0.0012 + 0.0019 * 4.0)


# ------------------------------------------------------------------ real data


@pytest.mark.data
def test_redkitchen_frame0_big_planes():
    from planeslam.config import resolve_config
    from planeslam.io.dataset import TumDataset

    root = shared_sequence("7scenes_redkitchen_1000f")
    cfg = resolve_config(root)
    depth = TumDataset(root, cfg.camera)[0].depth_m
    rays = PixelRays.for_camera(cfg.camera)
    organized = segment_planes(depth, rays, cfg.segmentation, sensor=cfg.sensor)
    msac_cfg = dataclasses.replace(cfg.segmentation, method="msac")
    msac = segment_planes(depth, rays, msac_cfg, rng=np.random.default_rng(0), sensor=cfg.sensor)
    # table top, floor, cupboard fronts (left and back): four planes above 25000 px
    assert sum(np.sum(organized.labels == p.id) > 25000 for p in organized.planes) >= 4
    # inlier RMS < 1.5 cm; beyond 2.5 m the Kinect noise itself (sigma(2.6 m) = 1.4 cm)
    # sets the bound: there 1.25 sigma at the centroid (inliers lie within 3 sigma(z),
    # and sigma grows as z^2 across the plane)
    for p in organized.planes:
        rms = np.sqrt(np.mean((p.points @ p.normal + p.d) ** 2))
        bound = 0.015 if p.centroid[2] < 2.5 else 1.25 * cfg.sensor.sigma_m(p.centroid[2])
        assert rms < bound, f"plane {p.id} ({p.num_points} px) inlier RMS {rms:.4f} m"
    for p in msac.planes[:4]:
        rms = np.sqrt(np.mean((p.points @ p.normal + p.d) ** 2))
        assert rms < 0.015, f"msac plane {p.id} inlier RMS {rms:.4f} m"
    a, b = organized.planes[0], msac.planes[0]
    assert np.degrees(np.arccos(min(1.0, a.normal @ b.normal))) < 3.0
    assert abs(a.d - b.d) < 0.03
    overlap = np.sum((organized.labels == 0) & (msac.labels == 0))
    assert overlap > 0.7 * min(np.sum(organized.labels == 0), b.num_points)


def test_patch_covariance_carries_the_tilt_about_the_centroid_to_the_offset() -> None:
    """Tilting a patch about its centroid c by a small angle a along the tangent b moves
    d = -n . c by -a b . c: the covariance's (normal, offset) block has that slope."""
    sensor = DepthNoiseConfig()
    n = np.array([0.3, -0.2, -0.9])
    n /= np.linalg.norm(n)
    c = np.array([1.2, -0.4, 2.5])  # off the optical axis
    tilt, offset = correlated_depth_sigmas(sensor, c[2], 0.04)
    assert offset == pytest.approx(sensor.sigma_m(2.5))
    assert tilt == pytest.approx(offset / 0.1)
    cov = patch_covariance(sensor, n, c, 0.04)
    B = tangent_basis(n)
    a = 1e-6
    n_tilted = n + a * B[:, 0]
    n_tilted /= np.linalg.norm(n_tilted)
    slope = (-(n_tilted @ c) - -(n @ c)) / a  # d(d) / d(tangent 0)
    np.testing.assert_allclose(cov[2, 0] / cov[0, 0], slope, rtol=1e-4)
    np.testing.assert_allclose(cov[2, 2], offset**2 + tilt**2 * np.sum((B.T @ c) ** 2))
    on_axis = patch_covariance(sensor, np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 2.5]), 0.04)
    np.testing.assert_allclose(on_axis, np.diag([tilt**2, tilt**2, offset**2]))
