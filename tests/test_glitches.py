"""Pose glitches: poses that jump off the frames around them and back, and their settling
(`planeslam.tracking.glitches`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planeslam.eval.metrics import read_metrics, run_metrics, write_metrics
from planeslam.io.trajectory import Trajectory
from planeslam.tracking.glitches import find_pose_glitches

pytestmark = pytest.mark.unit


def _orbit(frames: int = 90, rate_hz: float = 30.0, seed: int = 0) -> Trajectory:
    """A camera on a 0.7 m circle at 0.5 m/s, turning with it, with 2 mm / 0.1 deg of
    seeded jitter (about what good tracking leaves)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate_hz
    phase = 0.5 * t / 0.7
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 0, 3] = 0.7 * np.cos(phase) + rng.normal(0, 0.002, frames)
    poses[:, 1, 3] = 0.7 * np.sin(phase) + rng.normal(0, 0.002, frames)
    turn = np.column_stack([np.zeros(frames), np.zeros(frames), phase])
    turn += rng.normal(0, np.radians(0.1), (frames, 3))
    poses[:, :3, :3] = Rotation.from_rotvec(turn).as_matrix()
    return Trajectory(timestamps=t, T_world_cam=poses)


def test_smooth_motion_has_no_glitches_and_the_ends_are_not_judged() -> None:
    found = find_pose_glitches(_orbit())
    assert len(found) == 0
    assert found.judged == 90 - 2  # the first and the last pose have no neighbour on one side


@pytest.mark.parametrize("frames", [(40,), (40, 41)])
def test_a_jump_of_one_or_two_frames_is_found_and_its_neighbours_are_not(frames) -> None:
    trajectory = _orbit()
    for k in frames:
        trajectory.T_world_cam[k, 2, 3] += 0.12  # 12 cm off and back, as 7-Scenes' frame 750
    found = find_pose_glitches(trajectory)
    np.testing.assert_allclose(found.timestamps, trajectory.timestamps[list(frames)])


def test_two_jumps_one_frame_apart_are_both_found_and_the_frame_between_is_not() -> None:
    """7-Scenes' frames 491 and 493: each hid the other, since the line from one glitch's
    neighbour to the other glitch passes near it."""
    trajectory = _orbit()
    for k in (40, 42):
        trajectory.T_world_cam[k, 2, 3] += 0.07
    found = find_pose_glitches(trajectory)
    np.testing.assert_allclose(found.timestamps, trajectory.timestamps[[40, 42]])


def test_three_frames_off_together_are_not_taken_for_two_glitches() -> None:
    trajectory = _orbit()
    trajectory.T_world_cam[40:43, 2, 3] += 0.07  # a stretch, not two glitches around a good pose
    assert len(find_pose_glitches(trajectory)) == 0  # longer than the two frames judged together


def test_a_turn_off_the_slerp_is_found() -> None:
    trajectory = _orbit()
    spin = Rotation.from_rotvec([np.radians(5.0), 0.0, 0.0]).as_matrix()
    trajectory.T_world_cam[30, :3, :3] = trajectory.T_world_cam[30, :3, :3] @ spin
    found = find_pose_glitches(trajectory)
    np.testing.assert_allclose(found.timestamps, [trajectory.timestamps[30]])
    assert len(find_pose_glitches(trajectory, min_jump_deg=6.0)) == 0


def test_frames_far_apart_are_not_judged() -> None:
    trajectory = _orbit(frames=30, rate_hz=1.5)  # every 20th frame of a 30 Hz sequence
    trajectory.T_world_cam[10, 2, 3] += 0.5
    found = find_pose_glitches(trajectory)
    assert found.judged == 0 and len(found) == 0
    assert len(find_pose_glitches(Trajectory(np.zeros(0), np.zeros((0, 4, 4))))) == 0


def test_metrics_json_keeps_the_glitches(tmp_path) -> None:
    trajectory = _orbit()
    trajectory.T_world_cam[50, 0, 3] += 0.08
    glitches = find_pose_glitches(trajectory)
    metrics = run_metrics(frames=90, seconds=3.0, pose_glitches=glitches)
    back = read_metrics(write_metrics(metrics, tmp_path / "metrics.json"))
    assert back.pose_glitches["count"] == 1 and back.pose_glitches["judged"] == 88
    assert back.pose_glitches["timestamps"] == [round(float(trajectory.timestamps[50]), 6)]


def test_evaluation_marks_the_glitches_it_finds(tmp_path) -> None:
    from planeslam.eval.report import evaluate_to_folder
    from planeslam.io.trajectory import write_tum

    truth = _orbit()
    estimate = _orbit(seed=1)
    estimate.T_world_cam[60, 2, 3] += 0.10
    gt_path, est_path = tmp_path / "groundtruth.txt", tmp_path / "run" / "trajectory.txt"
    est_path.parent.mkdir()
    write_tum(gt_path, truth)
    write_tum(est_path, estimate)
    run = evaluate_to_folder(gt_path, est_path)
    assert run.evaluation.ate_max_m == pytest.approx(0.10, abs=0.01)  # the glitch's error
    assert (tmp_path / "run" / "ate_over_time.png").stat().st_size > 0
