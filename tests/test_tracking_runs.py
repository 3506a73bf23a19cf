"""Tracking on whole sequences: wide baselines, a second depth model with another camera,
a jump into unmapped space bridged by a segment, a one-view map replaced by a segment
that outgrew it, localisation in a saved map, keypoints
that agree on no pose not stopping the dense fallback, and honest output when frames are
lost (left out of trajectory.txt, counted, no ATE without enough)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_sequence

from planeslam.app.runner import run_sequence
from planeslam.config import load_config, resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.geometry import angle_between
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import Trajectory, read_tum
from planeslam.mapping.world_map import Map
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import SceneOptions, room_boxes_loop
from planeslam.sim.sequence import synthesize
from planeslam.slam import SLAM, FrameResult, run_frames
from planeslam.tracking.segments import Segment

pytestmark = pytest.mark.integration  # tracking on rendered and real sequences, whole runs


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N,) translation errors [m] of (N, 4, 4) poses against (N, 4, 4) truth (no alignment:
    the runs start at the true first pose)."""
    return np.linalg.norm(estimated[:, :3, 3] - truth[:, :3, 3], axis=1)


@pytest.mark.slow
def test_narrow_view_with_the_disparity_depth_model_tracks_every_frame(tmp_path: Path) -> None:
    """The paper's circle seen by another camera (0.7 m high, fx 600: a narrower view that
    often holds the floor, one wall and two box faces, no trihedral corner) with the
    Kinect-like disparity model (quantisation, flying pixels, dropout): before keypoints
    and prior-free hypotheses 23 of the 24 frames were lost. Measured: 24 of 24, ATE
    7 mm, box within 1.2 cm."""
    seq = synthesize(
        "box_room_circle",
        tmp_path / "seq",
        seed=3,
        noise_model="disparity",
        camera=CameraConfig(fx=600.0, fy=600.0),
        scene_options=SceneOptions(camera_height_m=0.7),
    ).out_dir
    cfg = resolve_config(seq)
    dataset = TumDataset(seq, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    summary = run_frames(slam, dataset, range(len(dataset)))
    assert slam.tracked_frames == 24, summary.paths
    ev = evaluate_trajectory(dataset.groundtruth, slam.trajectory(), 0.02, 1.0)
    assert ev.ate_rmse_m < 0.02
    box = [o for o in slam.map.objects if o.cls == "box"]
    assert box and np.max(np.abs(np.array(box[0].size_m) - [0.38, 0.29, 0.19])) < 0.02


@pytest.mark.slow
def test_a_segment_bridges_a_jump_into_unmapped_space() -> None:
    """Frames 0-8 of a 60-frame loop, then a jump to frame 25: the view holds nothing the
    map can place (the plane fit to the stale prediction and the dense fallbacks are
    refused), so a segment tracks frames 25-33 on its own. Having tracked more frames than
    the 9-frame map, it replaces the map at frame 34 (its first frame where the old map
    predicted it); at frame 48 and again at 49 the new map's keyframes relocalise in the
    dropped map, whose 9 frames then rejoin. Every frame ends up with a pose, all within
    3 cm after alignment (measured 0.6 cm); without segments the 23 frames stay lost. (A
    relocalisation from four of the frame's eight planes once joined it 1.7 m off:
    plane-only relocalisation now needs most of the frame's planes.)"""
    cfg = load_config("synthetic")
    scene, path = room_boxes_loop(frames=60)
    rng = np.random.default_rng(1)
    order = list(range(9)) + list(range(25, 60))
    frames = [render_frame(scene, path.T_world_cam[i], cfg.camera, rng) for i in order]
    truth = Trajectory(np.arange(len(order), dtype=float), path.T_world_cam[order])
    for segments, tracked in ((True, len(order)), (False, None)):
        config = dataclasses.replace(
            cfg, tracking=dataclasses.replace(cfg.tracking, segments=segments)
        )
        slam = SLAM(config, "merge", T_world_first=truth.T_world_cam[0])
        lost_online = sum(
            slam.process(f.depth_m, float(k), f.rgb).lost for k, f in enumerate(frames)
        )
        slam.finish()
        if tracked is None:
            assert slam.tracked_frames == len(order) - lost_online <= len(order) - 10
            continue
        assert lost_online >= 9  # the jump was real: these were lost when processed ...
        assert slam.tracked_frames == tracked  # ... and have poses after the joins
        assert evaluate_trajectory(truth, slam.trajectory(), 0.02, 1.0).ate_max_m < 0.03


@pytest.mark.slow
def test_a_segment_replaces_a_map_of_one_view_it_cannot_join(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The first frame sees the far side of a room (frame 30 of a 60-frame loop), the next
    ones the start of the loop: nothing places them in the one-view map of the first, so
    they were all lost (a segment tracked them but never joined). Now the segment replaces
    that map when it has tracked more frames than it: every frame but the first has a
    pose (measured ATE 1.4 cm, the merge backend's drift), and the run says which frames
    of the dropped map have none."""
    cfg = load_config("synthetic")
    scene, path = room_boxes_loop(frames=60)
    rng = np.random.default_rng(1)
    order = [30, *range(12)]
    frames = [render_frame(scene, path.T_world_cam[i], cfg.camera, rng) for i in order]
    slam = SLAM(cfg, "merge")
    results = [slam.process(f.depth_m, float(k), f.rgb) for k, f in enumerate(frames)]
    slam.finish()
    assert results[1].lost  # the first step is not trackable from the first view
    assert results[2].path == "first" and "a new map starts" in results[2].reason
    trajectory = slam.trajectory()
    assert trajectory.timestamps.tolist() == [float(k) for k in range(1, len(order))]
    truth = Trajectory(np.arange(len(order), dtype=float), path.T_world_cam[order])
    assert evaluate_trajectory(truth, trajectory, 0.02, 1.0).ate_rmse_m < 0.03
    assert "frames 0-0 (1 tracked) have no pose" in caplog.text


@pytest.mark.slow
def test_localise_in_a_saved_map_without_changing_it(tmp_path: Path) -> None:
    """The map of a loop around a room with four boxes, saved and loaded; frames of the
    loop between those that made it are placed in it with no ground truth and no prior (the
    first by whole-map relocalisation), then tracked; with `localize` the map stays exactly
    as loaded, without it it grows. (The paper's box room would not do: a square room and
    a box look the same turned by 180 deg, and relocalisation refuses to choose.)"""
    cfg = load_config("synthetic")
    scene, path = room_boxes_loop(frames=60)
    rng = np.random.default_rng(3)
    slam = SLAM(cfg, "merge", T_world_first=path.T_world_cam[0])
    for k in range(0, 60, 2):
        f = render_frame(scene, path.T_world_cam[k], cfg.camera, rng)
        slam.process(f.depth_m, k / 30.0, f.rgb)
    slam.finish()
    slam.map.save(tmp_path / "map.json")
    order = list(range(31, 60, 4))
    frames = [render_frame(scene, path.T_world_cam[k], cfg.camera, rng) for k in order]
    before = json.dumps(Map.load(tmp_path / "map.json").to_dict())
    for localize in (True, False):
        slam = SLAM(cfg, "merge", map=Map.load(tmp_path / "map.json"), localize=localize)
        results = [
            slam.process(f.depth_m, k / 30.0, f.rgb) for k, f in zip(order, frames, strict=True)
        ]
        slam.finish()
        assert results[0].path == "relocalised"
        assert slam.tracked_frames == len(frames)
        poses = slam.trajectory().T_world_cam
        # within the saved map's own accuracy (the merge backend's, about 1 cm here)
        assert np.max(pose_errors(poses, path.T_world_cam[order])) < 0.03
        assert (json.dumps(slam.map.to_dict()) == before) is localize


def blank_depth(seq: Path, indices: list[int]) -> None:
    """Overwrite the depth images of frames `indices` with 'no measurement' (0)."""
    names = sorted((seq / "depth").glob("*.png"), key=lambda p: float(p.stem))
    for k in indices:
        cv2.imwrite(str(names[k]), np.zeros((480, 640), np.uint16))


def test_lost_frames_are_left_out_and_counted(tmp_path: Path) -> None:
    seq = synthesize("box_room_circle", tmp_path / "seq", frames=24, seed=3).out_dir
    blank_depth(seq, [3])
    result = run_sequence(seq, tmp_path / "out", backend="merge", max_frames=6)
    out = result.out_dir
    rows = read_tum(out / "trajectory.txt")
    assert len(rows) == 5 and 3.0 not in rows.timestamps
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["lost_frames"] == 1 and metrics["tracked_fraction"] == pytest.approx(5 / 6)
    assert json.loads((out / "eval.json").read_text())["tracked_fraction"] == pytest.approx(5 / 6)
    assert "over 5 poses (83.3% of the frames tracked)" in result.text()
    records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert records[3]["path"] == "lost" and records[3]["constraints"] is None
    assert records[1]["constraints"]["planes"] == {"rotation": 3, "translation": 3}


def test_a_run_that_tracks_too_little_says_why_there_is_no_ate(tmp_path: Path) -> None:
    seq = synthesize("box_room_circle", tmp_path / "seq", frames=24, seed=3).out_dir
    blank_depth(seq, [1, 2, 3])
    result = run_sequence(seq, tmp_path / "out", backend="merge", max_frames=4)
    assert result.evaluation is None
    assert any(w.startswith("no ATE (1 of 4 frames tracked)") for w in result.warnings)
    assert "no ATE (1 of 4 frames tracked)" in result.text()
    assert len(read_tum(result.out_dir / "trajectory.txt")) == 1
    assert (result.out_dir / "metrics.json").is_file()


@pytest.mark.data
@pytest.mark.slow
def test_7scenes_every_20th_frame(tmp_path: Path) -> None:
    """7-Scenes RedKitchen at 0.67 s between frames (every 20th of 1000, 10-20 cm and up to
    14 deg apart). Before: ATE 3.35-6.1 m, 31 of 50 frames on RGB-D odometry. Measured:
    all 50 tracked, ATE 3.4-4.2 cm (the ground truth's own consistency with the depth is
    about 2 cm and 1 deg per step here)."""
    result = run_sequence(shared_sequence("7scenes_redkitchen_1000f"), tmp_path, every=20)
    assert result.metrics.tracked_fraction is not None and result.metrics.tracked_fraction >= 0.95
    assert result.evaluation is not None
    assert result.evaluation.evaluation.ate_rmse_m <= 0.05
    assert result.evaluation.evaluation.pairs == 50


@pytest.mark.data
@pytest.mark.slow
def test_a_picture_does_not_take_its_walls_landmark_on_icl_nuim() -> None:
    """ICL-NUIM frame 62 is the first to see a picture hanging 3.5 cm in front of the side
    wall. Counting pairs first, the picture (the lower weighted cost) took the wall's
    landmark and the wall became a second landmark 2.3 cm from the first (ATE 1.57 cm);
    the wall's contest is now decided by what leaving each out loses
    (`tracking.weigh_unpaired_min_area_m2`: the wall is 8-9 m^2), so the map holds the wall
    once (0.66 cm). Fails with `weigh_unpaired_min_area_m2: null`."""
    folder = shared_sequence("iclnuim_of_kt0")
    cfg = resolve_config(folder)
    dataset = TumDataset(folder, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    try:
        for k in range(72):
            frame = dataset[k]
            slam.process(frame.depth_m, frame.timestamp, frame.rgb)
    finally:
        slam.finish()
    walls = [p for p in slam.map.planes.values() if p.area_m2 >= 1.0]
    copies = [
        (a.id, b.id)
        for i, a in enumerate(walls)
        for b in walls[i + 1 :]
        if angle_between(a.normal, b.normal) < np.radians(1.0) and abs(a.d - b.d) < 0.05
    ]
    assert len(walls) >= 4 and copies == [], copies


@pytest.mark.data
def test_the_first_frame_is_the_dense_fallbacks_previous_frame() -> None:
    """ICL-NUIM with planes only up to 3 m: a frame holds the floor and one wall, so the
    plane pose cannot fix the translation and the second frame needs RGB-D odometry against
    the first. The first frame (of the run, and of a segment) is not tracked, and it used
    not to be kept as the previous frame: all 100 later frames were lost, each starting a
    segment whose next frame failed the same way. Measured: the 11 frames all tracked."""
    folder = shared_sequence("iclnuim_of_kt0")
    cfg = resolve_config(folder, overrides=["segmentation.max_depth_m=3.0"])
    dataset = TumDataset(folder, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "merge")
    results = [
        slam.process(dataset[k].depth_m, dataset.timestamps[k], dataset[k].rgb) for k in range(11)
    ]
    slam.finish()
    assert np.allclose(results[0].T_world_cam, np.eye(4))
    assert not any(r.lost for r in results), [r.reason for r in results]
    assert "odometry" in results[1].path  # the plane pose alone could not do it
    assert slam.tracked_frames == 11
    first, second = results[0].observation, results[1].observation
    rgb, depth = dataset[0].rgb, dataset[0].depth_m
    odometry = slam.tracker.odometry
    segment = Segment(0, first, rgb, depth, cfg.tracking, cfg.camera, cfg.sensor, 0, None, odometry)
    T_seg_cam = segment.track(1, second, dataset[1].rgb, dataset[1].depth_m)
    assert T_seg_cam is not None  # a segment's second frame: the same fallback
    assert np.linalg.norm(T_seg_cam[:3, 3] - results[1].T_world_cam[:3, 3]) < 0.01


@pytest.mark.data
def test_keypoints_that_agree_on_no_pose_still_let_the_dense_fallback_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The issue-40 office loop: a repetitive texture's many matches agreed on no pose,
    that was taken as a jump, so the dense fallback never ran and tracking gave up (the code
    of 6bf4a8b^ loses frames 1-3 here: "the frame's keypoints contradict the recent
    keyframes (a jump?)"). Here every frame's keypoints get 60 matches with random map
    points, on ICL-NUIM with planes up to 3 m, where the plane pose leaves the translation
    free: each frame is still tracked by the dense fallback, where the run with the true
    matches places it."""
    from planeslam.tracking.keypoints import KeypointMap, Keypoints, PointMatches

    folder = shared_sequence("iclnuim_of_kt0")
    cfg = resolve_config(folder, overrides=["segmentation.max_depth_m=3.0"])
    dataset = TumDataset(folder, cfg.camera, cfg.dataset)

    def run() -> list[FrameResult]:
        slam = SLAM(cfg, "merge")
        results = [
            slam.process(dataset[k].depth_m, dataset.timestamps[k], dataset[k].rgb)
            for k in range(4)
        ]
        slam.finish()
        return results

    reference = run()
    rng = np.random.default_rng(0)

    def random_matches(
        self: KeypointMap, keypoints: Keypoints, indices: list[int], *args: object
    ) -> PointMatches:
        n = 60  # a keypoint may match several points, as a repetitive texture's do
        return PointMatches(
            observed=rng.integers(0, len(keypoints), n),
            points_world=rng.uniform(-2.0, 2.0, (n, 3)),
            covariances_world=np.broadcast_to(1e-4 * np.eye(3), (n, 3, 3)).copy(),
            keyframes=np.full(n, indices[-1] if indices else 0, np.int64),
        )

    monkeypatch.setattr(KeypointMap, "matches", random_matches)
    results = run()
    disagreeing = [r for r in results[1:] if "60 point matches agree on no pose" in r.reason]
    assert len(disagreeing) == 3, [r.reason for r in results]
    assert all("odometry" in r.path or "icp" in r.path for r in disagreeing)
    for ours, theirs in zip(results, reference, strict=True):
        assert np.linalg.norm(ours.T_world_cam[:3, 3] - theirs.T_world_cam[:3, 3]) < 0.01
