"""Trajectory evaluation against the evo CLI, error cases, plots, report, metrics, object sizes."""

from __future__ import annotations

import base64
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planeslam.core.errors import EvaluationError
from planeslam.eval.metrics import (
    RunMetrics,
    memory_ratio,
    peak_rss_mb,
    read_metrics,
    run_metrics,
    stage_medians,
    write_metrics,
)
from planeslam.eval.object_sizes import (
    mean_object_size_error,
    object_size_errors,
    object_size_errors_from_files,
)
from planeslam.eval.plots import view_axes
from planeslam.eval.report import evaluate_to_folder, write_evaluation, write_report
from planeslam.eval.trajectory_metrics import (
    EVAL_KEYS,
    evaluate_trajectory,
    format_table,
)
from planeslam.io.trajectory import Trajectory, write_tum

pytestmark = pytest.mark.unit

BIN = Path(sys.executable).parent
RATE_HZ = 30.0
T0 = 1305031102.0


def circle_trajectory(n: int = 150, rate_hz: float = RATE_HZ) -> Trajectory:
    """Camera on a wavy circle of radius 1 m, turning with it; T_world_cam at `rate_hz`."""
    theta = 2 * np.pi * np.arange(n) / n
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([np.cos(theta), np.sin(theta), 0.3 * np.sin(2 * theta)], axis=1)
    angles = np.stack([theta, 0.2 * np.sin(theta), 0.1 * np.cos(3 * theta)], axis=1)
    T[:, :3, :3] = Rotation.from_euler("zyx", angles).as_matrix()
    return Trajectory(timestamps=T0 + np.arange(n) / rate_hz, T_world_cam=T)


def noisy(
    traj: Trajectory, rng: np.random.Generator, sigma_m: float, sigma_rad: float
) -> Trajectory:
    T = traj.T_world_cam.copy()
    T[:, :3, 3] += rng.normal(0.0, sigma_m, (len(traj), 3))
    T[:, :3, :3] = (
        Rotation.from_rotvec(rng.normal(0.0, sigma_rad, (len(traj), 3))).as_matrix() @ T[:, :3, :3]
    )
    return Trajectory(timestamps=traj.timestamps.copy(), T_world_cam=T)


def random_rigid(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-5.0, 5.0, 3)
    return T


@pytest.fixture
def tum_pair(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, Path]:
    """Ground truth and a noisy estimate in another world frame, timestamps offset by 13 ms
    (beyond evo's default 0.01 s window, within ours), a fifth of the estimate's poses dropped
    (so the association has work to do)."""
    gt = circle_trajectory()
    est = noisy(gt, rng, sigma_m=0.01, sigma_rad=0.01)
    keep = np.sort(rng.choice(len(est), size=120, replace=False))
    T_other_world = random_rigid(rng)
    est = Trajectory(est.timestamps[keep] + 0.013, T_other_world @ est.T_world_cam[keep])
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    return tmp_path / "gt.txt", tmp_path / "est.txt"


def run_evo(tool: str, gt: Path, est: Path, out_zip: Path, *extra: str) -> dict:
    """Run an evo CLI tool with -a and the TUM window; return (stats, np_arrays) of its result."""
    from evo.tools import file_interface

    env = dict(os.environ, HOME=str(out_zip.parent), MPLBACKEND="Agg")  # evo writes ~/.evo
    cmd = [str(BIN / tool), "tum", str(gt), str(est), "-a", "--t_max_diff", "0.02"]
    cmd += [*extra, "--save_results", str(out_zip), "--no_warnings", "--silent"]
    subprocess.run(cmd, check=True, env=env, capture_output=True, timeout=120)
    result = file_interface.load_res_file(out_zip, load_trajectories=False)
    return {"stats": result.stats, "arrays": result.np_arrays}


@pytest.mark.integration
def test_ate_equals_evo_ape_cli(tum_pair: tuple[Path, Path], tmp_path: Path) -> None:
    gt, est = tum_pair
    ours = evaluate_trajectory(gt, est)
    evo = run_evo("evo_ape", gt, est, tmp_path / "ape.zip")
    assert ours.pairs == 120 == evo["arrays"]["error_array"].size
    assert ours.ate_rmse_m == pytest.approx(evo["stats"]["rmse"], abs=1e-9)
    assert ours.ate_mean_m == pytest.approx(evo["stats"]["mean"], abs=1e-9)
    assert ours.ate_median_m == pytest.approx(evo["stats"]["median"], abs=1e-9)
    assert ours.ate_max_m == pytest.approx(evo["stats"]["max"], abs=1e-9)
    np.testing.assert_allclose(ours.ate_errors_m, evo["arrays"]["error_array"], atol=1e-9)
    # 1 cm noise per axis: the aligned error is about sqrt(3) cm, far from 0.
    assert 0.012 < ours.ate_rmse_m < 0.022


@pytest.mark.integration
@pytest.mark.parametrize(
    ("relation", "field"),
    [("trans_part", "rpe_trans_m_per_s"), ("angle_deg", "rpe_rot_deg_per_s")],
)
def test_rpe_equals_evo_rpe_cli(
    tum_pair: tuple[Path, Path], tmp_path: Path, relation: str, field: str
) -> None:
    gt, est = tum_pair
    ours = evaluate_trajectory(gt, est, rpe_delta_s=1.0)
    assert ours.rpe_delta_frames == 30  # 1 s at 30 Hz
    assert ours.rpe_delta_s == pytest.approx(1.0, abs=1e-3)
    evo = run_evo(
        "evo_rpe", gt, est, tmp_path / "rpe.zip",
        "--pose_relation", relation, "--delta", "30", "--delta_unit", "f", "--all_pairs",
    )  # fmt: skip
    assert getattr(ours, field) == pytest.approx(evo["stats"]["rmse"], abs=1e-9)
    assert getattr(ours, field) > 1e-3  # noise is there, the comparison is not 0 == 0


def test_rigid_motion_of_ground_truth_has_zero_error(rng: np.random.Generator) -> None:
    gt = circle_trajectory()
    for _ in range(3):
        moved = Trajectory(gt.timestamps.copy(), random_rigid(rng) @ gt.T_world_cam)
        ev = evaluate_trajectory(gt, moved)
        assert ev.ate_rmse_m < 1e-9 and ev.ate_max_m < 1e-9
        assert ev.rpe_trans_m_per_s is not None and ev.rpe_trans_m_per_s < 1e-9
        assert ev.rpe_rot_deg_per_s is not None and ev.rpe_rot_deg_per_s < 1e-6
        np.testing.assert_allclose(ev.T_world_est_aligned, ev.T_world_gt, atol=1e-9)


def test_to_dict_has_exactly_the_eval_json_keys(tum_pair: tuple[Path, Path]) -> None:
    ev = evaluate_trajectory(*tum_pair)
    data = json.loads(json.dumps(ev.to_dict()))
    assert list(data) == list(EVAL_KEYS)
    assert data["pairs"] == 120
    assert "ATE RMSE" in format_table(ev)


def test_short_sequence_has_no_rpe(rng: np.random.Generator) -> None:
    gt = circle_trajectory(n=10)  # 0.3 s, shorter than the 1 s RPE delta
    ev = evaluate_trajectory(gt, noisy(gt, rng, 0.01, 0.0))
    assert ev.rpe_trans_m_per_s is None and ev.rpe_rot_deg_per_s is None
    assert ev.rpe_delta_frames == 0
    assert ev.to_dict()["rpe_trans_m_per_s"] is None
    assert ev.ate_rmse_m > 1e-3


# --- clear errors ------------------------------------------------------------------------------


def test_empty_file_is_named(tmp_path: Path) -> None:
    write_tum(tmp_path / "gt.txt", circle_trajectory())
    (tmp_path / "est.txt").write_text("# timestamp tx ty tz qx qy qz qw\n\n")
    with pytest.raises(EvaluationError, match=r"estimate: .*est\.txt: no poses"):
        evaluate_trajectory(tmp_path / "gt.txt", tmp_path / "est.txt")


def test_missing_file_is_named(tmp_path: Path) -> None:
    write_tum(tmp_path / "est.txt", circle_trajectory())
    with pytest.raises(EvaluationError, match=r"ground truth: .*nothere\.txt: .*not found"):
        evaluate_trajectory(tmp_path / "nothere.txt", tmp_path / "est.txt")


def test_malformed_row_names_file_and_line(tmp_path: Path) -> None:
    write_tum(tmp_path / "gt.txt", circle_trajectory())
    lines = (tmp_path / "gt.txt").read_text().splitlines()
    lines[5] = "1305031102.1 0.1 0.2 oops 0 0 0 1"
    (tmp_path / "est.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(EvaluationError, match=r"est\.txt:6: expected 8 numbers"):
        evaluate_trajectory(tmp_path / "gt.txt", tmp_path / "est.txt")


def test_no_association_reports_ranges_and_gap() -> None:
    gt = circle_trajectory()
    late = Trajectory(gt.timestamps + 100.0, gt.T_world_cam)
    with pytest.raises(EvaluationError) as info:
        evaluate_trajectory(gt, late)
    message = str(info.value)
    assert "\n" not in message
    assert "within 0.02 s" in message
    assert f"{gt.timestamps[0]:.3f}..{gt.timestamps[-1]:.3f}" in message
    assert f"{gt.timestamps[0] + 100:.3f}..{gt.timestamps[-1] + 100:.3f}" in message
    # closest stamps: the estimate's first (T0 + 100) against the ground truth's last.
    assert f"{100.0 - (gt.timestamps[-1] - gt.timestamps[0]):.3f} s apart" in message


def test_too_few_pairs() -> None:
    gt = circle_trajectory()
    est = Trajectory(gt.timestamps[:2].copy(), gt.T_world_cam[:2])
    with pytest.raises(EvaluationError, match=r"only 2 pose\(s\).*at least 3"):
        evaluate_trajectory(gt, est)


def test_degenerate_positions() -> None:
    gt = circle_trajectory()
    still = Trajectory(gt.timestamps.copy(), np.tile(np.eye(4), (len(gt), 1, 1)))
    with pytest.raises(EvaluationError, match="cannot align"):
        evaluate_trajectory(gt, still)


def test_a_camera_turning_in_place_is_evaluated_from_its_first_pose(tmp_path: Path) -> None:
    """Positions that admit no SE(3) alignment (a pure rotation): `planeslam eval` aligns
    the first poses instead (evo's align_origin), says so, and writes it in eval.json; the
    error is then the estimate's offset from the truth relative to its first pose."""
    gt = circle_trajectory()
    turning = gt.T_world_cam.copy()
    turning[:, :3, 3] = [0.5, -1.0, 1.2]  # the camera turns in place
    gt = Trajectory(gt.timestamps, turning)
    T_other_world = np.eye(4)
    T_other_world[:3, 3] = [2.0, 0.0, -1.0]
    est_poses = T_other_world @ turning
    est_poses[60:, :3, 3] += [0.03, 0.0, 0.04]  # a 5 cm jump, kept
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", Trajectory(gt.timestamps.copy(), est_poses))
    with pytest.raises(EvaluationError, match="cannot align"):
        evaluate_trajectory(tmp_path / "gt.txt", tmp_path / "est.txt")
    run = evaluate_to_folder(tmp_path / "gt.txt", tmp_path / "est.txt", tmp_path / "out")
    assert run.evaluation.alignment == "origin"
    assert any("align_origin" in w for w in run.warnings)
    np.testing.assert_allclose(run.evaluation.ate_max_m, 0.05, atol=1e-9)
    np.testing.assert_allclose(run.evaluation.ate_rmse_m, 0.05 * np.sqrt(90 / 150), atol=1e-9)
    data = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert data["alignment"] == "origin"


def test_bad_rpe_delta() -> None:
    gt = circle_trajectory()
    with pytest.raises(EvaluationError, match="rpe_delta_s"):
        evaluate_trajectory(gt, gt, rpe_delta_s=0.0)


# --- plots and report --------------------------------------------------------------------------


def test_view_axes_pick_largest_extents() -> None:
    camera_world = np.stack([np.linspace(0, 3, 10), np.full(10, 0.1), np.linspace(0, 2, 10)], 1)
    assert view_axes(camera_world) == ((0, 2), (0, 1))
    z_up_world = np.stack([np.linspace(0, 1, 10), np.linspace(0, 4, 10), np.zeros(10)], 1)
    assert view_axes(z_up_world) == ((0, 1), (1, 2))


@pytest.mark.integration
def test_write_evaluation_and_report(tum_pair: tuple[Path, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    ev = evaluate_trajectory(*tum_pair)
    paths = write_evaluation(ev, out)
    assert json.loads(paths["eval"].read_text()) == json.loads(json.dumps(ev.to_dict()))
    for key in ("trajectory_plot", "ate_plot"):
        assert paths[key].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert paths[key].stat().st_size > 20_000  # a drawn figure, not an empty canvas
    (out / "overlay.png").write_bytes(paths["ate_plot"].read_bytes())
    write_metrics(
        run_metrics(frames=10, seconds=2.0, frame_timings=[{"seg": 5.0}] * 10), out / "metrics.json"
    )
    page = write_report(out).read_text()
    for name in ("trajectory.png", "ate_over_time.png", "overlay.png"):  # embedded, not linked
        data = base64.b64encode((out / name).read_bytes()).decode("ascii")
        assert f'src="data:image/png;base64,{data}"' in page
    assert str(tmp_path) not in page  # nothing outside the page: it can be moved alone
    assert f"{ev.ate_rmse_m:.4f}" in page
    assert "<th>frames per second</th><td>5.0</td><td>Hz</td>" in page
    assert "<th>seg</th><td>5.0</td><td>ms</td>" in page


def test_frame_errors_show_the_one_wrong_step_beside_its_path(tmp_path: Path) -> None:
    """An exact trajectory with one 10 cm step error at row 60: every later pose is off
    after alignment, but only row 60's step error is, the frames.jsonl beside the estimate
    names its frame and path, and the report lists it first among the largest steps."""
    gt = circle_trajectory(100)
    T = gt.T_world_cam.copy()
    T[60:, 0, 3] += 0.1  # one wrong step: the frames after it follow it
    write_tum(tmp_path / "groundtruth.txt", gt)
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.txt", Trajectory(gt.timestamps, T))
    records = [
        {"index": k, "timestamp": float(t), "path": "icp" if k == 60 else "planes", "reason": ""}
        for k, t in enumerate(gt.timestamps)
    ]
    (run / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    paths = evaluate_to_folder(tmp_path / "groundtruth.txt", run / "trajectory.txt").paths
    with paths["frame_errors"].open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 100 and rows[0]["step_error_m"] == ""
    steps = np.array([float(r["step_error_m"]) for r in rows[1:]])
    assert np.argmax(steps) + 1 == 60 and steps[59] == pytest.approx(0.1, abs=1e-6)
    assert np.max(np.delete(steps, 59)) < 1e-6
    assert rows[60]["frame"] == "60" and rows[60]["path"] == "icp"
    assert float(rows[99]["error_m"]) > 0.01  # the aligned poses all carry it
    page = paths["report"].read_text()  # the largest step errors come first in the report
    largest = page[page.index("Largest step errors") :]
    assert largest.index("<td>60</td><td>icp</td><td>10.0</td>") < largest.index("<td>planes</td>")


def test_report_needs_something_to_show(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match="no eval.json or metrics.json"):
        write_report(tmp_path)


# --- metrics.json ------------------------------------------------------------------------------


def test_stage_medians_and_run_metrics(tmp_path: Path) -> None:
    timings = [{"seg": 10.0, "track": 1.0}, {"seg": 30.0, "track": 3.0}, {"seg": 20.0}]
    assert stage_medians(timings) == {"seg": 20.0, "track": 2.0}
    m = run_metrics(
        frames=3,
        seconds=0.5,
        frame_timings=timings,
        map_bytes=1000,
        pointcloud_bytes=60_000,
        fused_cloud_bytes=12_000,
        lost_frames=1,
    )
    assert m.fps == pytest.approx(6.0)
    assert m.frame_ms_median == pytest.approx(20.0)  # per-frame sums 11, 33, 20
    assert m.memory_ratio == pytest.approx(12.0)  # the headline: against the fused cloud
    assert m.memory_ratio_merged == pytest.approx(60.0)  # the paper's: all clouds merged
    assert list(m.to_dict())[:13] == [
        "frames", "fps", "frame_ms_median", "stage_ms", "peak_rss_mb", "backend_peak_rss_mb",
        "map_bytes", "fused_cloud_bytes", "memory_ratio", "pointcloud_bytes",
        "memory_ratio_merged", "point_bytes", "map_counts",
    ]  # fmt: skip
    assert read_metrics(write_metrics(m, tmp_path / "metrics.json")) == m
    assert memory_ratio(0, 100) is None
    with pytest.raises(EvaluationError):
        memory_ratio(-1, 100)


def test_peak_rss_matches_proc_status() -> None:
    status = Path("/proc/self/status")
    if not status.is_file():
        pytest.skip("no /proc on this platform")
    hwm_kb = next(
        int(line.split()[1]) for line in status.read_text().splitlines() if line.startswith("VmHWM")
    )
    assert peak_rss_mb() == pytest.approx(hwm_kb / 1024.0, rel=0.05)
    assert isinstance(RunMetrics(frames=0, fps=0.0, frame_ms_median=0.0).stage_ms, dict)


# --- object sizes ------------------------------------------------------------------------------

TRUTH = {
    "objects": [
        {"id": 0, "class": "room", "size_m": [1.88, 1.88, 2.5]},
        {"id": 1, "class": "box", "size_m": [0.38, 0.29, 0.19]},
        {"id": 2, "class": "box", "size_m": [0.8, 0.5, 0.4]},
        {"id": 3, "class": "shelf", "size_m": [1.0, 0.3]},
    ]
}


def test_object_size_errors_match_by_class_and_size() -> None:
    estimated = [
        {"id": 7, "class": "box", "planes": [1, 2, 3], "size_m": [0.82, 0.49, 0.37]},
        {"id": 8, "class": "box", "planes": [4, 5, 6], "size_m": [0.37, 0.30, 0.20]},
        {"id": 9, "class": "room", "planes": [7, 8], "size_m": [2.52, 1.9]},  # two walls seen
        {"id": 10, "class": "box", "planes": [9, 10, 11], "size_m": [3.0, 2.0, 1.0]},  # spurious
    ]
    errors = object_size_errors(estimated, TRUTH)
    assert [e["true_id"] for e in errors] == [0, 1, 2, 3]
    room, small, large, shelf = errors
    assert (room["estimated_id"], small["estimated_id"], large["estimated_id"]) == (9, 8, 7)
    assert room["true_size_m"] == [2.5, 1.88, 1.88]  # largest first
    np.testing.assert_allclose(room["abs_error_m"], [0.02, 0.02])  # common leading dimensions
    np.testing.assert_allclose(small["abs_error_m"], [0.01, 0.01, 0.01])
    np.testing.assert_allclose(large["abs_error_m"], [0.02, 0.01, 0.03])
    assert large["mean_abs_error_m"] == pytest.approx(0.02)
    assert shelf["estimated_id"] is None and shelf["mean_abs_error_m"] is None
    assert mean_object_size_error(errors) == pytest.approx((0.02 + 0.01 + 0.02) / 3)
    json.dumps(errors)


def test_object_size_errors_from_files(tmp_path: Path) -> None:
    (tmp_path / "truth.json").write_text(json.dumps(TRUTH))
    (tmp_path / "map.json").write_text(json.dumps({"objects": []}))
    errors = object_size_errors_from_files(tmp_path / "map.json", tmp_path / "truth.json")
    assert all(e["estimated_id"] is None for e in errors)
    (tmp_path / "bad.json").write_text(json.dumps({"objects": [{"id": 1, "class": "box"}]}))
    with pytest.raises(EvaluationError, match="size_m"):
        object_size_errors_from_files(tmp_path / "bad.json", tmp_path / "truth.json")
    with pytest.raises(EvaluationError, match="truth"):
        object_size_errors([], {"planes": []})


@pytest.mark.integration
def test_evaluate_to_folder_adds_object_sizes(tum_pair: tuple[Path, Path], tmp_path: Path) -> None:
    gt, est = tum_pair  # both in tmp_path
    (tmp_path / "truth.json").write_text(json.dumps(TRUTH))
    (tmp_path / "map.json").write_text(
        json.dumps(
            {"objects": [{"id": 5, "class": "box", "planes": [], "size_m": [0.4, 0.3, 0.2]}]}
        )
    )
    run = evaluate_to_folder(gt, est, tmp_path / "out")
    data = json.loads(run.paths["eval"].read_text())
    assert list(data) == [*EVAL_KEYS, "object_size_errors"]
    assert data["object_size_errors"][1]["mean_abs_error_m"] == pytest.approx(
        (0.02 + 0.01 + 0.01) / 3
    )
    assert "Object sizes" in run.paths["report"].read_text()
    with pytest.raises(EvaluationError, match="nothere.json: not found"):
        evaluate_to_folder(gt, est, tmp_path / "out2", truth_json=tmp_path / "nothere.json")
