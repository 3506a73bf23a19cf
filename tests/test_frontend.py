"""The whole per-frame front end with the REAL segmenter on rendered frames with exact
truth (Kinect-like noise seeded per frame), its stage timing, and bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from test_intersections import (
    fully_visible,
    matched_edges,
    rendered,
    segment_error,
)
from test_segmentation import _check_against_truth

from planeslam.config import PlaneSlamConfig
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import GeometryError
from planeslam.core.geometry import invert_pose, transform_points
from planeslam.frontend.pipeline import STAGES, FrameObservation, FrontEnd

pytestmark = pytest.mark.unit

CONFIG = PlaneSlamConfig()
assert CONFIG.camera == CameraConfig()  # the renders use the default 640 x 480 camera

THREE_FACE_FRAMES = (2, 3, 8, 9, 14, 15, 20, 21)
"""box_room_circle frames whose truth shows the box top and two sides, each with at
least 5000 valid pixels (the other frames see two faces or a grazing sliver)."""

BOX_TRUE = (0.38, 0.29, 0.19)


def _front_end() -> FrontEnd:
    return FrontEnd(CONFIG)


def _scene_ids(obs: FrameObservation, frame) -> list[int]:
    """Scene plane id covering most of each found plane's pixels."""
    truth = np.where(frame.depth_m > 0, frame.plane_id, -1)
    out = []
    for p in obs.segmentation.planes:
        ids, n = np.unique(truth[obs.segmentation.labels == p.id], return_counts=True)
        out.append(int(ids[np.argmax(n)]))
    return out


@pytest.mark.integration
def test_truth_frames_see_three_box_faces():
    """The frame list above agrees with the renderer's truth."""
    for k in range(24):
        scene, _, frame = rendered("box_room_circle", k)
        valid = frame.depth_m > 0
        faces = [np.sum(valid & (frame.plane_id == i)) for i, p in enumerate(scene.planes)
                 if p.name.startswith("box.")]  # fmt: skip
        assert (sum(n >= 5000 for n in faces) >= 3) == (k in THREE_FACE_FRAMES), k


@pytest.mark.integration
@pytest.mark.parametrize(
    ("frame_index", "stride"), [(k, 2) for k in THREE_FACE_FRAMES[1::2]] + [(9, 1), (20, 1)]
)
def test_box_and_room_with_the_real_segmenter(frame_index, stride):
    """Every pixel (stride 1) or every 2nd pixel of every 2nd row (the default)."""
    scene, T, frame = rendered("box_room_circle", frame_index)
    organized = dataclasses.replace(CONFIG.segmentation.organized, pixel_stride=stride)
    cfg = dataclasses.replace(
        CONFIG, segmentation=dataclasses.replace(CONFIG.segmentation, organized=organized)
    )
    obs = FrontEnd(cfg).process(frame.depth_m, 1.5)
    assert tuple(obs.stage_ms) == STAGES and all(v >= 0 for v in obs.stage_ms.values())
    assert obs.reason == ""
    # planes: each true plane once, within 1 deg and 1 cm, none split or merged
    assert _check_against_truth(obs.segmentation, scene, T, frame) >= 5
    sids = _scene_ids(obs, frame)
    names = [scene.planes[s].name for s in sids]
    st = obs.structure
    boxes = [o for o in st.objects if o.cls == "box"]
    assert len(boxes) == 1, [(o.cls, o.planes) for o in st.objects]
    assert {"box.top"} <= {names[k] for k in boxes[0].planes}
    np.testing.assert_allclose(boxes[0].size_m, BOX_TRUE, atol=0.01)
    rooms = [o for o in st.objects if o.cls == "room"]
    assert len(rooms) == 1 and "room.floor" in {names[k] for k in rooms[0].planes}
    # corners: true corners within 2 cm
    T_cam_world = invert_pose(T)
    truth = {c.plane_ids: transform_points(T_cam_world, c.point[None])[0] for c in scene.corners}
    assert len(st.corners) >= 2
    for c in st.corners:
        key = tuple(sorted(sids[k] for k in c.planes))
        assert key in truth, [names[k] for k in c.planes]
        assert np.linalg.norm(c.point - truth[key]) < 0.02, [names[k] for k in c.planes]
    # edges: fully visible ones within 2 cm in length and end points
    matches = matched_edges(scene, T, frame, obs.segmentation, sids, st.edges)
    full = [(te, e, seg) for te, e, vis, seg in matches if fully_visible(vis)]
    assert len(full) >= 3
    for te, e, seg_cam in full:
        label = [scene.planes[k].name for k in te.plane_ids]
        assert e is not None, f"missed the fully visible edge {label}"
        assert abs(e.length_m - te.length_m) < 0.02, (label, e.length_m, te.length_m)
        assert segment_error(e.segment, seg_cam) < 0.02, label


@pytest.mark.integration
@pytest.mark.slow
def test_demo_figure_box_found_and_sized():
    """All 24 frames of the demo scene: the box is found, classed 'box' and sized
    within 1 cm in every three-face frame (8 of 24; a few others add a box from a
    grazing sliver of a third face); the median size over all frames where a box is
    found is within 1 cm (before: 8/24 frames, 0.413 x 0.329 x 0.193 m, none within
    1 cm)."""
    front = _front_end()
    found, sizes = [], []
    rooms = 0
    for k in range(24):
        _, _, frame = rendered("box_room_circle", k)
        obs = front.process(frame.depth_m)
        boxes = [o for o in obs.structure.objects if o.cls == "box"]
        rooms += any(o.cls == "room" for o in obs.structure.objects)
        if boxes:
            found.append(k)
            sizes.append(boxes[0].size_m)
            if k in THREE_FACE_FRAMES:
                np.testing.assert_allclose(boxes[0].size_m, BOX_TRUE, atol=0.01, err_msg=str(k))
    assert set(THREE_FACE_FRAMES) <= set(found)
    np.testing.assert_allclose(np.median(sizes, axis=0), BOX_TRUE, atol=0.01)
    assert rooms >= 20


def test_observation_keeps_the_cloud_and_serialises():
    _, _, frame = rendered("box_room_circle", 9)
    obs = _front_end().process(frame.depth_m, 2.0)
    assert obs.cloud.shape == (480, 640, 3) and obs.cloud.dtype == np.float32
    valid = frame.depth_m > 0
    np.testing.assert_allclose(obs.cloud[..., 2][valid], frame.depth_m[valid], rtol=1e-6)
    assert np.all(obs.cloud[~valid] == 0.0)
    p = obs.segmentation.planes[0]  # its points are points of the cloud
    assert np.isin(p.points[:50, 2].astype(np.float32), obs.cloud[..., 2]).all()
    data = json.loads(json.dumps(obs.to_dict()))
    assert data["stage_ms"].keys() == set(STAGES) and data["reason"] == ""
    assert data["timestamp"] == 2.0


# --------------------------------------------------------------------------- bad input


def _wall(depth_m: float = 2.0) -> np.ndarray:
    return np.full((480, 640), depth_m, dtype=np.float32)


BAD_DEPTHS = {
    "zeros": (lambda: np.zeros((480, 640), np.float32), "no valid depth"),
    "nan": (lambda: np.full((480, 640), np.nan, np.float32), "NaN or infinite"),
    "inf": (lambda: np.full((480, 640), np.inf, np.float32), "NaN or infinite"),
    "negative": (lambda: -_wall(), "<= 0"),
    "absurd_far": (lambda: _wall(1e6), "beyond max_depth_m"),
}


@pytest.mark.parametrize("case", sorted(BAD_DEPTHS))
def test_frames_without_valid_depth_give_a_reason(case):
    make, words = BAD_DEPTHS[case]
    obs = _front_end().process(make())
    assert words in obs.reason
    assert obs.segmentation.planes == [] and obs.structure.objects == []
    assert tuple(obs.stage_ms) == STAGES
    json.dumps(obs.to_dict())


def test_one_plane_only(rng):
    depth = _wall() + rng.normal(0.0, 0.003, (480, 640)).astype(np.float32)
    obs = _front_end().process(depth)
    assert len(obs.segmentation.planes) == 1
    assert "only one plane" in obs.reason
    assert obs.structure.edges == [] and obs.structure.objects == []


def test_no_planes(rng):
    depth = rng.uniform(0.5, 4.0, (480, 640)).astype(np.float32)  # no surface at all
    obs = _front_end().process(depth)
    assert obs.segmentation.planes == []
    assert "no plane" in obs.reason and "no planes in the frame" in obs.structure.reason


def test_mixed_garbage_depth_keeps_the_good_part(rng):
    """NaN, inf, negative and 1e6 m pixels sprinkled over a real frame: they are
    invalid pixels, the planes are still found."""
    _, _, frame = rendered("box_room_circle", 9)
    depth = frame.depth_m.copy()
    idx = rng.choice(depth.size, size=depth.size // 20, replace=False)
    depth.ravel()[idx] = rng.choice([np.nan, np.inf, -1.0, 1e6], size=len(idx))
    with np.errstate(all="raise"):  # no numpy warning escapes either
        obs = _front_end().process(depth)
    assert obs.segmentation.reason == ""
    assert len(obs.segmentation.planes) >= 5
    assert np.all(np.isfinite(obs.cloud))
    assert any(o.cls == "box" for o in obs.structure.objects)


def test_wrong_shape_is_a_geometry_error():
    with pytest.raises(GeometryError, match="shape"):
        _front_end().process(np.ones((48, 64), np.float32))
