"""Overlay drawing and `planeslam frame` (process_frame) on synthetic frames with exact truth."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from conftest import shared_sequence
from scipy import ndimage

from planeslam.app.frame import process_frame
from planeslam.app.overlay import (
    CONCAVE_RGB,
    CONVEX_RGB,
    CORNER_RGB,
    PLANE_ALPHA,
    draw_overlay,
    format_size,
    project_points,
    write_png,
)
from planeslam.config import PlaneSlamConfig
from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.frontend.pipeline import FrontEnd
from planeslam.sim.sequence import synthesize

pytestmark = pytest.mark.unit

SMALL = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


def _empty_observation(camera: CameraConfig, corners=(), edges=(), planes=(), objects=()):
    """A duck-typed FrameObservation with no plane pixels (only what draw_overlay reads)."""
    return SimpleNamespace(
        segmentation=SimpleNamespace(
            planes=list(planes), labels=np.full((camera.height, camera.width), -1, np.int32)
        ),
        structure=SimpleNamespace(
            edges=list(edges), corners=list(corners), objects=list(objects), reason=""
        ),
        stage_ms={},
        reason="",
    )


def _near(image: np.ndarray, u: int, v: int, rgb: tuple[int, int, int], tol: float = 30) -> bool:
    """Some pixel of the 3x3 neighbourhood of (u, v) is within tol of colour rgb
    (anti-aliased lines blend their centre pixel slightly)."""
    patch = image[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3).astype(float)
    return bool(np.linalg.norm(patch - np.asarray(rgb, float), axis=1).min() < tol)


def test_project_points_pinhole_and_behind_camera():
    pts = np.array([[0.2, -0.1, 2.0], [0.0, 0.0, 1.0], [0.1, 0.1, -1.0]])
    uv, ok = project_points(pts, SMALL)
    np.testing.assert_allclose(uv[0], [159.5 + 262.5 * 0.1, 119.5 - 262.5 * 0.05])
    np.testing.assert_allclose(uv[1], [159.5, 119.5])
    assert ok.tolist() == [True, True, False]
    assert np.isnan(uv[2]).all()


def test_corner_edges_and_label_drawn_at_projected_pixels(rng):
    rgb = rng.integers(0, 256, (SMALL.height, SMALL.width, 3), dtype=np.uint8)
    corner = np.array([0.3, -0.2, 2.5])
    convex = SimpleNamespace(segment=np.array([[-0.6, 0.3, 2.0], [-0.2, 0.3, 2.0]]), convex=True)
    concave = SimpleNamespace(segment=np.array([[0.2, 0.5, 2.0], [0.6, 0.5, 2.0]]), convex=False)
    obs = _empty_observation(
        SMALL, corners=[SimpleNamespace(point=corner)], edges=[convex, concave]
    )
    out = draw_overlay(rgb, obs, SMALL, legend=False)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    uv, _ = project_points(corner[None], SMALL)
    u, v = np.rint(uv[0]).astype(int)
    assert (u, v) == (191, 98)
    assert _near(out, u, v, CORNER_RGB)
    # Edge midpoints carry the edge colours (concave is dashed: its first dash covers 0-10 px).
    uv, _ = project_points(convex.segment.mean(axis=0)[None], SMALL)
    cu, cv_ = np.rint(uv[0]).astype(int)
    assert _near(out, cu, cv_, CONVEX_RGB)
    uv, _ = project_points(concave.segment[:1] + [0.01, 0.0, 0.0], SMALL)
    su, sv = np.rint(uv[0]).astype(int)
    assert _near(out, su, sv, CONCAVE_RGB)
    assert not _near(out, su, sv, CONVEX_RGB) and not _near(out, cu, cv_, CONCAVE_RGB)
    # Far from everything drawn, the image is untouched.
    drawn = np.any(out != rgb, axis=2)
    assert not drawn[:60, :100].any() and not drawn[200:, 250:].any()
    assert drawn.sum() < 0.05 * drawn.size


def test_object_label_near_planes_centroid(rng):
    rgb = np.full((SMALL.height, SMALL.width, 3), 90, np.uint8)
    planes = [
        SimpleNamespace(id=0, centroid=np.array([0.0, 0.0, 2.0])),
        SimpleNamespace(id=1, centroid=np.array([0.4, 0.0, 2.0])),
    ]
    obj = SimpleNamespace(cls="box", planes=(0, 1), size_m=(0.19, 0.38, 0.29))
    out = draw_overlay(rgb, _empty_observation(SMALL, planes=planes, objects=[obj]), SMALL, False)
    changed = np.argwhere(np.any(out != rgb, axis=2))
    uv, _ = project_points(np.array([[0.2, 0.0, 2.0]]), SMALL)
    assert len(changed) > 100
    u, v = uv[0]
    assert abs(changed[:, 1].mean() - u) < 6.0  # centred horizontally
    assert v - 30 < changed[:, 0].min() and changed[:, 0].max() <= v  # just above
    assert format_size(obj.size_m) == "0.38x0.29x0.19 m"


def _wall_left_half(camera: CameraConfig) -> np.ndarray:
    """Depth of a slanted wall n = (0.3, 0, -1)/|.|, 2 m ahead, on the left half only."""
    rays = PixelRays.for_camera(camera).rays
    n = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])
    d = 2.0 * abs(n[2])
    depth = (d / -(rays @ n)).astype(np.float32)
    depth[:, camera.width // 2 :] = 0.0
    return depth


def test_overlay_tints_planes_and_keeps_the_rest(rng):
    cfg = PlaneSlamConfig(camera=SMALL)
    obs = FrontEnd(cfg).process(_wall_left_half(SMALL))
    labels = obs.segmentation.labels
    assert len(obs.segmentation.planes) == 1
    rgb = rng.integers(0, 256, (SMALL.height, SMALL.width, 3), dtype=np.uint8)
    out = draw_overlay(rgb, obs, SMALL)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    inside = ndimage.binary_erosion(labels >= 0, iterations=4)
    assert inside.sum() > 0.3 * labels.size
    diff = np.abs(out.astype(int) - rgb.astype(int)).sum(axis=2)
    # The tint moves each pixel PLANE_ALPHA of the way to the palette colour.
    expected = PLANE_ALPHA * np.abs(np.array([31, 119, 180]) - rgb.astype(int)).sum(axis=2)
    np.testing.assert_allclose(np.median(diff[inside]), np.median(expected[inside]), rtol=0.1)
    far = ~ndimage.binary_dilation(labels >= 0, iterations=4)
    far[:40] = False  # the summary banner (two lines at 320 px)
    assert far.sum() > 0.3 * labels.size
    assert (diff[far] == 0).all()


def test_empty_frame_gets_a_reason_banner():
    cfg = PlaneSlamConfig(camera=SMALL)
    obs = FrontEnd(cfg).process(np.zeros((SMALL.height, SMALL.width), np.float32))
    assert obs.reason and not obs.segmentation.planes
    rgb = np.full((SMALL.height, SMALL.width, 3), 200, np.uint8)
    out = draw_overlay(rgb, obs, SMALL, legend=False)
    changed = np.any(out != rgb, axis=2)
    assert changed[:12].mean() > 0.5  # darkened band with the text
    assert not changed[60:].any()


def test_bad_image_is_rejected(tmp_path):
    with pytest.raises(DatasetFormatError, match="uint8"):
        draw_overlay(np.zeros((4, 4), np.uint8), _empty_observation(SMALL), SMALL)
    with pytest.raises(DatasetFormatError, match="RGB"):
        write_png(tmp_path / "x.png", np.zeros((4, 4, 3), np.float32))


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synth") / "box"
    synthesize("box_room_circle", folder, frames=2, seed=3, camera=SMALL)
    return folder


def test_process_frame_writes_frame_json_and_overlay(tiny_dataset, tmp_path):
    result = process_frame(tiny_dataset, 1, out_dir=tmp_path / "f")
    assert result.frame_json.is_file() and result.overlay_png.is_file()
    assert result.config_yaml.is_file()
    data = json.loads(result.frame_json.read_text())
    assert data["schema"] == "planeslam.map/1"
    assert data["frame"] == "camera" and data["index"] == 1
    assert len(data["planes"]) >= 3
    for p in data["planes"]:
        assert set(p) >= {"id", "normal", "d", "area_m2", "outline"}
        assert abs(np.linalg.norm(p["normal"]) - 1) < 1e-9 and p["d"] > 0
        assert np.asarray(p["outline"]).shape[1] == 3
    for e in data["edges"]:
        assert set(e) >= {"planes", "length_m", "segment", "convex"}
        assert np.asarray(e["segment"]).shape == (2, 3)
    for c in data["corners"]:
        assert len(c["planes"]) == 3 and len(c["point"]) == 3
    for o in data["objects"]:
        assert set(o) >= {"id", "class", "planes", "size_m"}
        assert o["size_m"] == sorted(o["size_m"], reverse=True)
    image = cv2.imread(str(result.overlay_png), cv2.IMREAD_UNCHANGED)
    assert image.shape == (SMALL.height, SMALL.width, 3)
    text = result.summary()
    assert f"{len(data['planes'])} planes" in text and "ms" in text


@pytest.mark.parametrize("index", [2, -1, 99])
def test_process_frame_index_out_of_range(tiny_dataset, tmp_path, index):
    with pytest.raises((DatasetFormatError, ConfigError)) as info:
        process_frame(tiny_dataset, index, out_dir=tmp_path)
    message = str(info.value)
    assert "\n" not in message
    assert str(tiny_dataset) in message and "0..1" in message and str(index) in message


@pytest.mark.data
def test_process_frame_on_7scenes(tmp_path):
    folder = shared_sequence("7scenes_redkitchen_1000f")
    result = process_frame(folder, 0, out_dir=tmp_path)
    assert len(result.observation.segmentation.planes) >= 3
    image = cv2.imread(str(result.overlay_png))
    assert image is not None and image.shape == (480, 640, 3)


def test_process_frame_camera_override(tiny_dataset, tmp_path):
    """--camera overrides the dataset's camera.yaml (here: same focal, principal point moved)."""
    result = process_frame(tiny_dataset, 0, camera="262.5,262.5,150.0,110.0", out_dir=tmp_path)
    text = result.config_yaml.read_text()
    assert "cx: 150.0" in text and "cy: 110.0" in text
    with pytest.raises(ConfigError, match="fx,fy,cx,cy"):
        process_frame(tiny_dataset, 0, camera="1,2", out_dir=tmp_path)
