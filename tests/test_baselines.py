"""Open3D RGB-D odometry baseline: failure handling on blank frames, accuracy on TUM fr1/xyz."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_sequence

from planeslam.config import resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError, EvaluationError
from planeslam.eval.baselines import run_open3d_odometry
from planeslam.eval.suite import (
    SequenceSpec,
    SuiteConfig,
    SuiteResult,
    SuiteRow,
    load_suite,
    run_suite,
    to_markdown,
    write_csv,
)
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import Frame, TumDataset
from planeslam.io.trajectory import Trajectory
from planeslam.tracking.odometry import registration_ok

pytestmark = pytest.mark.integration  # open3d odometry on real data, the baseline suite in workers


@dataclass
class BlankDataset:
    """Stands in for TumDataset: frames with no valid depth, so every registration fails."""

    n: int
    camera: CameraConfig = CameraConfig(width=80, height=60, fx=60.0, fy=60.0, cx=39.5, cy=29.5)
    config: DatasetConfig = DatasetConfig()
    groundtruth: Trajectory | None = None
    groundtruth_pose = TumDataset.groundtruth_pose

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, index: int) -> Frame:
        h, w = self.camera.height, self.camera.width
        return Frame(
            index=index,
            timestamp=10.0 + index / 30.0,
            rgb=np.zeros((h, w, 3), np.uint8),
            depth_m=np.zeros((h, w), np.float32),
        )


def test_failed_registrations_are_counted_and_extrapolated() -> None:
    T_world_first = np.eye(4)
    T_world_first[:3, 3] = [1.0, 2.0, 3.0]
    gt = Trajectory(np.array([10.0]), T_world_first[None])
    seen: list[float] = []
    result = run_open3d_odometry(
        BlankDataset(n=7, groundtruth=gt), every=2, on_pose=lambda t, T: seen.append(t)
    )  # type: ignore[arg-type]
    assert result.frames == 4 and result.lost_frames == 3
    np.testing.assert_allclose(result.trajectory.timestamps, 10.0 + np.array([0, 2, 4, 6]) / 30.0)
    assert seen == list(result.trajectory.timestamps)
    # no motion was ever estimated: constant velocity from rest keeps the first pose
    np.testing.assert_allclose(result.trajectory.T_world_cam, np.repeat(T_world_first[None], 4, 0))
    assert set(result.frame_timings[1]) == {"read", "rgbd_image", "odometry"}


def test_bad_arguments() -> None:
    with pytest.raises(EvaluationError, match="every"):
        run_open3d_odometry(BlankDataset(n=3), every=0)  # type: ignore[arg-type]
    with pytest.raises(EvaluationError, match="max_frames"):
        run_open3d_odometry(BlankDataset(n=3), max_frames=0)  # type: ignore[arg-type]


@pytest.mark.data
@pytest.mark.slow
def test_open3d_odometry_on_tum_fr1_xyz() -> None:
    path = shared_sequence("tum_fr1_xyz_10f")
    cfg = resolve_config(path)
    dataset = TumDataset(path, cfg.camera, cfg.dataset)
    result = run_open3d_odometry(dataset)
    assert result.frames == 10 and result.lost_frames == 0
    gt = dataset.groundtruth
    assert gt is not None
    # Chained from the first ground-truth pose: the first pose is exact, and the
    # unaligned end point lands near the true one (11 cm of motion in 0.3 s).
    np.testing.assert_allclose(result.trajectory.T_world_cam[0], gt.T_world_cam[0], atol=1e-12)
    end_error_m = np.linalg.norm(result.trajectory.positions[-1] - gt.positions[-1])
    assert end_error_m < 0.02
    ev = evaluate_trajectory(gt, result.trajectory)
    assert ev.pairs == 10
    # measured 0.0044 m; motion chained in the wrong direction gives 0.034 m
    assert ev.ate_rmse_m < 0.012
    # one thread per native pool: a second run gives the same bits
    again = run_open3d_odometry(dataset)
    assert np.array_equal(again.trajectory.T_world_cam, result.trajectory.T_world_cam)


def test_registration_ok_rejects_open3d_false_successes() -> None:
    info = np.diag([2e4, 3e4, 8e4, 2e5, 6e5, 6e5])
    assert registration_ok(True, np.eye(4), info)
    assert not registration_ok(False, np.eye(4), info)
    assert not registration_ok(True, np.full((4, 4), np.nan), np.zeros((6, 6)))  # blank depth
    assert not registration_ok(True, np.eye(4), np.zeros((6, 6)))
    assert not registration_ok(True, np.eye(4), np.diag([0.0, 1, 1, 1, 1, 1]))  # unconstrained


class BlankOneFrame:
    """A real dataset with the depth of one frame removed."""

    groundtruth_pose = TumDataset.groundtruth_pose

    def __init__(self, dataset: TumDataset, blank: int) -> None:
        self.dataset, self.blank = dataset, blank
        self.camera, self.config, self.groundtruth = (
            dataset.camera,
            dataset.config,
            dataset.groundtruth,
        )

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> Frame:
        frame = self.dataset[index]
        if index == self.blank:
            frame = Frame(frame.index, frame.timestamp, frame.rgb, np.zeros_like(frame.depth_m))
        return frame


@pytest.mark.data
def test_lost_frame_repeats_the_previous_motion() -> None:
    path = shared_sequence("tum_fr1_xyz_10f")
    cfg = resolve_config(path)
    dataset = BlankOneFrame(TumDataset(path, cfg.camera, cfg.dataset), blank=2)
    result = run_open3d_odometry(dataset, max_frames=3)  # type: ignore[arg-type]
    assert result.lost_frames == 1
    T = result.trajectory.T_world_cam
    motion_01 = np.linalg.inv(T[0]) @ T[1]
    assert np.linalg.norm(motion_01[:3, 3]) > 1e-3  # the camera does move between 0 and 1
    np.testing.assert_allclose(np.linalg.inv(T[1]) @ T[2], motion_01, atol=1e-9)


# --- benchmark suite ---------------------------------------------------------------------------


def test_load_suite_rejects_unknown_keys_and_methods(tmp_path: Path) -> None:
    good = tmp_path / "suite.yaml"
    good.write_text("sequences:\n  - {path: seq_a, max_frames: 5}\nmethods: [open3d_odometry]\n")
    config, base = load_suite(good)
    assert config.sequences == (SequenceSpec(path="seq_a", max_frames=5),) and base == tmp_path
    (tmp_path / "typo.yaml").write_text("sequences: [{path: a}]\njbos: 2\n")
    with pytest.raises(ConfigError, match="unknown key.*jbos.*valid keys: sequences, methods"):
        load_suite(tmp_path / "typo.yaml")
    (tmp_path / "method.yaml").write_text("sequences: [{path: a}]\nmethods: [orbslam]\n")
    with pytest.raises(ConfigError, match="unknown method.*orbslam.*open3d_odometry"):
        load_suite(tmp_path / "method.yaml")


def test_suite_tables(tmp_path: Path) -> None:
    result = SuiteResult(
        rows=[
            SuiteRow("fr1_xyz", "open3d_odometry", ate_rmse_m=0.0044, fps=3.5, lost_frames=0),
            SuiteRow("missing", "open3d_odometry", error="DatasetFormatError: x | y"),
        ]
    )
    table = to_markdown(result).splitlines()
    assert table[0].startswith("| sequence | method | ATE RMSE [m] |")
    assert "| fr1_xyz | open3d_odometry | 0.0044 | - |" in table[2]
    assert table[3].endswith("| DatasetFormatError: x / y |")  # a '|' cannot break the table
    rows = write_csv(result, tmp_path / "suite.csv").read_text()
    assert rows.splitlines()[1].startswith("fr1_xyz,open3d_odometry,0.0044,")
    assert len(result.failed) == 1


@pytest.mark.data
@pytest.mark.slow
def test_suite_runs_jobs_in_workers_and_reports_failures(tmp_path: Path) -> None:
    folder = shared_sequence("tum_fr1_xyz_10f")
    config = SuiteConfig(
        sequences=(
            SequenceSpec(path=str(folder), max_frames=4),
            SequenceSpec(path="no_such_sequence"),
        ),
        jobs=2,
    )
    seen: list[SuiteRow] = []
    result = run_suite(config, base_dir=tmp_path, out_dir=tmp_path / "out", on_row=seen.append)
    ok, failed = result.rows
    assert len(seen) == 2
    assert ok.error is None and ok.frames == 4 and ok.fps is not None and ok.fps > 0
    assert ok.ate_rmse_m is not None and ok.ate_rmse_m < 0.012
    assert (tmp_path / "out" / folder.name / "open3d_odometry" / "metrics.json").is_file()
    assert failed.error is not None and "no_such_sequence: dataset not found" in failed.error
    assert failed.ate_rmse_m is None
