"""Full SLAM on synthetic sequences with exact truth: both backends, the outputs of
`planeslam run`, interruption, far-apart keyframes, and the frame-by-frame API."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_pose_close

from planeslam.app.runner import run_sequence
from planeslam.config import PlaneSlamConfig, resolve_config
from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import Trajectory, read_tum
from planeslam.mapping.world_map import Map
from planeslam.sim.sequence import synthesize
from planeslam.slam import SLAM, run_frames

pytestmark = pytest.mark.integration  # full SLAM runs, `planeslam run`


@pytest.fixture(scope="module")
def box_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper's experiment: a box in a room seen from a circle of 24 poses."""
    return synthesize("box_room_circle", tmp_path_factory.mktemp("brc") / "seq", seed=3).out_dir


@pytest.fixture(scope="module")
def loop(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A room with boxes walked around in a closed loop, 60 frames."""
    root = tmp_path_factory.mktemp("loop") / "seq"
    return synthesize("room_boxes_loop", root, frames=60, seed=4).out_dir


def run(root: Path, backend: str, every: int = 1):
    cfg = resolve_config(root)
    dataset = TumDataset(root, cfg.camera, cfg.dataset)
    indices = list(range(0, len(dataset), every))
    slam = SLAM(cfg, backend, T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    summary = run_frames(slam, dataset, indices)
    ev = evaluate_trajectory(dataset.groundtruth, slam.trajectory(), 0.02, 1.0)
    return slam, summary, ev


def true_sizes(root: Path) -> dict[str, list[float]]:
    truth = json.loads((root / "truth.json").read_text())
    return {o["class"]: o["size_m"] for o in truth["objects"]}


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["merge", "isam2"])
def test_box_room_circle_poses_and_objects(box_room: Path, backend: str) -> None:
    slam, summary, ev = run(box_room, backend)
    assert summary.lost_frames == 0, summary.paths
    assert ev.ate_rmse_m < 0.01
    classes = [o.cls for o in slam.map.objects]
    assert "box" in classes and "room" in classes
    box = next(o for o in slam.map.objects if o.cls == "box")
    assert np.max(np.abs(np.array(box.size_m) - true_sizes(box_room)["box"])) < 0.02


@pytest.mark.slow
def test_isam2_beats_merge_on_the_loop(loop: Path) -> None:
    """Measured: iSAM2 0.62 mm, merge 6.6 mm (loops of seeds 5 and 6: 0.51 / 4.9 mm and
    0.42 / 6.9 mm); half of merge's error leaves a wide margin and still fails a backend
    that only matches the merge."""
    _, _, merge = run(loop, "merge")
    _, summary, isam2 = run(loop, "isam2")
    assert summary.lost_frames == 0
    assert isam2.ate_rmse_m < 0.01
    assert isam2.ate_rmse_m < 0.5 * merge.ate_rmse_m, (isam2.ate_rmse_m, merge.ate_rmse_m)


@pytest.mark.slow
def test_keyframes_far_apart_still_track(loop: Path) -> None:
    """Every 4th frame of the 60-frame loop (15 keyframes around the room, as every 20th of
    the default 300): planes and corners need no small-motion assumption. Its steps (about
    30 cm and 24 deg in 0.13 s) are faster than any plausible motion, so a relocalisation
    is not taken on one frame: the second frame waits in a segment for a second one, and
    every frame has its pose at the end."""
    slam, summary, ev = run(loop, "merge", every=4)
    assert summary.lost_frames <= 1, summary.paths
    assert slam.tracked_frames == 15
    assert ev.ate_rmse_m < 0.02


def test_run_writes_every_output(box_room: Path, tmp_path: Path) -> None:
    result = run_sequence(box_room, tmp_path / "out", backend="merge", max_frames=6)
    out = result.out_dir
    for name in ("config.yaml", "run.json", "trajectory.txt", "frames.jsonl", "map.json",
                 "map_planes.ply", "map_points.ply", "metrics.json", "eval.json", "report.html",
                 "trajectory.png", "map.png", "frame_errors.csv"):  # fmt: skip
        assert (out / name).is_file(), name
    assert len(read_tum(out / "trajectory.txt")) == 6
    errors = (out / "frame_errors.csv").read_text().splitlines()  # a header, a row a frame
    assert len(errors) == 7 and errors[1].split(",")[5:7] == ["0", "first"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["map_bytes"] > 0
    assert metrics["memory_ratio"] >= 100
    assert set(metrics["map_bytes_breakdown"]) >= {"planes", "edges", "corners", "objects"}
    records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["index"] for r in records] == list(range(6))
    reloaded = json.loads(json.dumps(Map.load(out / "map.json").to_dict()))
    written = json.loads((out / "map.json").read_text())
    assert len(written.pop("keyframes")) == 6  # the run's, beside the map (SLAM.map_record)
    assert [p.pop("seen_in_frames") for p in written["planes"]]
    assert reloaded == written


def test_interrupted_run_keeps_its_outputs(
    box_room: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = {"n": 0}
    original = SLAM.process

    def interrupt_after_three(self, *args, **kwargs):
        if calls["n"] == 3:
            raise KeyboardInterrupt
        calls["n"] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(SLAM, "process", interrupt_after_three)
    with pytest.raises(KeyboardInterrupt):
        run_sequence(box_room, tmp_path / "out", backend="merge", max_frames=6)
    out = tmp_path / "out"
    assert len(read_tum(out / "trajectory.txt")) == 3
    assert (out / "map.json").is_file() and (out / "metrics.json").is_file()


def test_process_needs_no_dataset(box_room: Path) -> None:
    cfg = resolve_config(box_room)
    dataset = TumDataset(box_room, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "merge")
    first = slam.process(dataset[0].depth_m, 0.0)
    second = slam.process(dataset[1].depth_m, 1.0, dataset[1].rgb)
    assert first.keyframe and first.path == "first"
    assert not second.lost
    assert len(slam.trajectory()) == 2
    with pytest.raises(DatasetFormatError, match=r"depth_m has shape \(10, 10\), expected"):
        slam.process(np.zeros((10, 10), np.float32), 2.0)


def test_unknown_backend_and_bad_every(box_room: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="backend 'gtsam' unknown"):
        SLAM(resolve_config(box_room), "gtsam")
    with pytest.raises(ConfigError, match="every must be >= 1"):
        run_sequence(box_room, tmp_path, every=0)


def static_ate_m(root: Path, estimate: Trajectory) -> float:
    """ATE of a camera that never moves (every pose = the estimate's first) at the
    estimate's timestamps, evaluated as the run is. evo's Umeyama alignment refuses one
    repeated position, so the positions get 1 um of random spread (changes the score by
    < 1e-6 m)."""
    T = np.repeat(estimate.T_world_cam[:1], len(estimate), axis=0)
    T[:, :3, 3] += np.random.default_rng(0).normal(0.0, 1e-6, (len(T), 3))
    static = Trajectory(timestamps=estimate.timestamps, T_world_cam=T)
    max_dt = resolve_config(root).dataset.max_time_difference_s
    return evaluate_trajectory(root / "groundtruth.txt", static, max_dt).ate_rmse_m


@pytest.mark.data
@pytest.mark.parametrize("clip", ["tum_fr1_xyz_10f", "tum_fr1_desk_9f"])
def test_run_on_a_short_real_clip(clip: str, tmp_path: Path) -> None:
    """TUM fr1/xyz (10 frames) and fr1/desk (9 frames), 0.3 s each: tracked on planes,
    evaluated; too short for RPE, which the summary says instead of failing.

    On clips this short a camera that never moves already scores ~3.5 cm ATE (the camera
    moves a few cm), so the run must beat that by far. Measured (merge): xyz 9.6 mm vs
    static 34.4 mm, desk 10.5 mm vs static 35.7 mm."""
    from conftest import shared_sequence

    root = shared_sequence(clip)
    result = run_sequence(root, tmp_path, backend="merge")
    assert result.summary.lost_frames == 0
    assert result.evaluation is not None
    ate = result.evaluation.evaluation.ate_rmse_m
    static = static_ate_m(root, read_tum(tmp_path / "trajectory.txt"))
    assert static > 0.03  # the clips do move: the check below has teeth
    assert ate < 0.025 and ate < 0.5 * static, (ate, static)
    assert "RPE not computed" in result.text()


def test_a_given_map_merges_with_the_runs_sensor_model(tmp_path: Path) -> None:
    """map.json does not keep the depth noise model: the run that extends a loaded map
    gives it its own (the consolidation gate of the frames it merges)."""
    Map().save(tmp_path / "map.json")
    sensor = DepthNoiseConfig(sigma_a_m=0.004, sigma_b_per_m=0.006)
    cfg = dataclasses.replace(PlaneSlamConfig(), sensor=sensor)
    loaded = Map.load(tmp_path / "map.json")
    assert loaded.sensor == DepthNoiseConfig()
    with SLAM(cfg, "merge", map=loaded) as slam:
        assert slam.map is loaded and slam.map.sensor == sensor


@pytest.mark.slow
def test_the_dense_fallbacks_register_against_the_corrected_previous_pose(loop: Path) -> None:
    """The backend's corrections move the tracker's last frame too: after each frame, the
    pose the RGB-D odometry and ICP fallbacks start from is the frame's own final pose,
    not the one it had before a keyframe's update moved the map."""
    cfg = resolve_config(loop)
    dataset = TumDataset(loop, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    for i in range(40):
        frame = dataset[i]
        tracked = slam.process(frame.depth_m, frame.timestamp, frame.rgb)
        assert not tracked.lost
        previous = slam.tracker.previous_pose
        if i > 0:  # the first frame starts the map without tracking
            assert previous is not None
            assert_pose_close(previous, tracked.T_world_cam, 1e-9, 1e-9)


def test_a_revisit_follows_the_keyframe_made_at_that_place(loop: Path) -> None:
    """Frames 0-15 of the loop, then back to 0: the way back makes no keyframes (nothing
    new), and each frame's pose follows the keyframe of its own place (`anchor`, the
    nearest in pose), not the last keyframe, many frames back by then."""
    cfg = resolve_config(loop)
    dataset = TumDataset(loop, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    order = list(range(16)) + list(range(14, -1, -1))
    results = []
    for k, i in enumerate(order):
        frame = dataset[i]  # views 6 deg apart: 2 a second (a turn at 30 Hz would be a glitch)
        results.append(slam.process(frame.depth_m, k / 2.0, frame.rgb))
    slam.finish()
    first_visit = {i: k for k, i in reversed(list(enumerate(order)))}
    assert all(r.keyframe and r.anchor == r.index for r in results[:16])
    back = results[16:]
    assert not any(r.keyframe for r in back)
    assert [r.anchor for r in back] == [first_visit[i] for i in order[16:]]
    poses = slam.trajectory().T_world_cam
    for k in range(16, len(order)):  # the same image: the same final pose
        assert_pose_close(poses[k], poses[first_visit[order[k]]], 0.01, 0.5)


def test_a_keyframe_after_lost_frames_goes_to_the_backend_as_relocalised(loop: Path) -> None:
    """A blind frame (no valid depth) is lost; the next keyframe's motion from the previous
    keyframe is then no measurement, so it reaches the backend marked `relocalised` (a weak
    link there, not a confident odometry factor); every other keyframe is not, and the run
    keeps its poses."""
    cfg = resolve_config(loop)
    dataset = TumDataset(loop, cfg.camera, cfg.dataset)
    slam = SLAM(cfg, "isam2", T_world_first=dataset.groundtruth_pose(dataset.timestamps[0]))
    submitted = []
    submit = slam.backend.submit

    def record(keyframe):
        submitted.append((keyframe.index, keyframe.relocalised))
        submit(keyframe)

    slam.backend.submit = record  # type: ignore[method-assign]
    blind = 12
    for i in range(30):
        frame = dataset[i]
        depth = np.zeros_like(frame.depth_m) if i == blind else frame.depth_m
        result = slam.process(depth, frame.timestamp, frame.rgb)
        assert result.lost == (i == blind), (i, result.reason)
    slam.finish()
    marked = [index for index, relocalised in submitted if relocalised]
    first_after = min(index for index, _ in submitted if index > blind)
    assert marked == [first_after], submitted
    ev = evaluate_trajectory(dataset.groundtruth, slam.trajectory(), 0.02, 1.0)
    assert ev.ate_rmse_m < 0.01, ev.ate_rmse_m
