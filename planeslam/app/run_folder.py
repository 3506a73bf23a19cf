"""A finished run's output folder read back for `planeslam view` and `planeslam mesh`:
run.json (the dataset), config.yaml, trajectory.txt (final poses), frames.jsonl."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.config import PlaneSlamConfig, load_config
from planeslam.core.camera import CameraConfig
from planeslam.core.config import from_mapping, read_yaml
from planeslam.core.errors import DatasetFormatError, EvaluationError
from planeslam.eval.report import FRAMES_JSONL, TRAJECTORY_TXT, read_frame_records
from planeslam.eval.run_info import read_run_info
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import Frame, associate_timestamps
from planeslam.io.sequence import RgbdDataset, open_dataset
from planeslam.io.trajectory import Trajectory, read_tum

STAMP_TOLERANCE_S = 1e-4
"""Frames of the run and of the dataset are matched by time stamp within this [s]
(trajectory.txt keeps microseconds)."""


@dataclass(frozen=True)
class RunFrame:
    """One processed frame of a run: its record, dataset index and final pose."""

    record: dict[str, Any] = field(repr=False)
    """Its frames.jsonl record (index, timestamp, path, reason, keyframe, stage_ms)."""
    dataset_index: int
    T_world_cam: np.ndarray | None = field(repr=False)
    """(4, 4) final pose from trajectory.txt; None when the run wrote none for it."""

    @property
    def keyframe(self) -> bool:
        return bool(self.record.get("keyframe"))


@dataclass(frozen=True)
class RunFolder:
    """A run folder with its dataset opened."""

    run_dir: Path
    dataset: RgbdDataset
    trajectory: Trajectory
    """Final poses (trajectory.txt)."""
    frames: list[RunFrame] = field(repr=False)

    @property
    def camera(self) -> CameraConfig:
        """The camera of the run's config.yaml (a bag's camera_info applied)."""
        return self.dataset.camera

    def config(self) -> PlaneSlamConfig:
        """The whole resolved config the run saved (config.yaml); ConfigError when it has
        keys this version does not know (the camera and dataset sections alone are read
        by `open_run`, so a mesh needs no more)."""
        return load_config(self.run_dir / "config.yaml")

    def read(self, frames: Sequence[RunFrame]) -> Iterator[tuple[RunFrame, Frame]]:
        """The dataset's images of `frames`, one at a time."""
        for f in frames:
            yield f, self.dataset[f.dataset_index]


def open_run(run_dir: str | Path, dataset: str | Path | None = None) -> RunFolder:
    """Read a `planeslam run` output folder and open its dataset (`dataset` overrides the
    path in run.json, e.g. after moving either). EvaluationError / DatasetFormatError
    naming the file for a missing or malformed part."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise EvaluationError(f"{run_dir}: run folder not found")
    info = read_run_info(run_dir)
    for name in ("config.yaml", TRAJECTORY_TXT, FRAMES_JSONL):
        if not (run_dir / name).is_file():
            raise EvaluationError(f"{run_dir / name}: not found (written by `planeslam run`)")
    saved = read_yaml(run_dir / "config.yaml")
    where = str(run_dir / "config.yaml")
    if not isinstance(saved, dict):
        raise EvaluationError(f"{where}: expected a mapping of config sections")
    camera = from_mapping(CameraConfig, saved.get("camera"), where, "camera")
    dataset_config = from_mapping(DatasetConfig, saved.get("dataset"), where, "dataset")
    root = Path(dataset) if dataset is not None else Path(info.dataset)
    if not root.exists():
        raise DatasetFormatError(
            f"{root}: dataset folder of the run not found; pass --dataset DIR where it is now"
        )
    data = open_dataset(root, camera, dataset_config)
    trajectory = read_tum(run_dir / TRAJECTORY_TXT)
    records = read_frame_records(run_dir / FRAMES_JSONL)
    stamps = np.array([float(r.get("timestamp", np.nan)) for r in records])
    in_data: dict[int, int] = {}
    if len(stamps):
        in_data = dict(associate_timestamps(stamps, data.timestamps, STAMP_TOLERANCE_S))
    missing = [i for i in range(len(records)) if i not in in_data]
    if missing:
        raise DatasetFormatError(
            f"{run_dir / FRAMES_JSONL}: frame {records[missing[0]]['index']} "
            f"(t = {stamps[missing[0]]}) is not a frame of {root} ({len(missing)} such "
            "frames); wrong --dataset?"
        )
    in_traj: dict[int, int] = {}
    if len(trajectory) and len(stamps):
        in_traj = dict(associate_timestamps(stamps, trajectory.timestamps, STAMP_TOLERANCE_S))
    frames = [
        RunFrame(
            record=r,
            dataset_index=in_data[i],
            T_world_cam=trajectory.T_world_cam[in_traj[i]] if i in in_traj else None,
        )
        for i, r in enumerate(records)
    ]
    return RunFolder(run_dir, data, trajectory, frames)
