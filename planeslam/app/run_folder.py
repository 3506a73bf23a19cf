"""A run's output folder: claimed by a run (`claim_run_folder`: a lock, the previous run's
files moved aside), and read back when finished for `planeslam view` and `planeslam mesh`
(`open_run`: run.json (the dataset), config.yaml, trajectory.txt (final poses),
frames.jsonl)."""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.config import PlaneSlamConfig, load_config
from planeslam.core.camera import CameraConfig
from planeslam.core.config import from_mapping, read_yaml
from planeslam.core.errors import DatasetFormatError, EvaluationError, OutputFolderError
from planeslam.core.safe_files import FolderLock, resolve_path
from planeslam.eval.report import (
    ATE_PNG,
    EVAL_JSON,
    FRAMES_JSONL,
    MAP_JSON,
    MAP_PNG,
    METRICS_JSON,
    REPORT_HTML,
    TIMELINE_PNG,
    TRAJECTORY_PNG,
    TRAJECTORY_TXT,
    read_frame_records,
)
from planeslam.eval.run_info import RUN_JSON, read_run_info
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import Frame, associate_timestamps
from planeslam.io.sequence import RgbdDataset, open_dataset
from planeslam.io.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

RUN_OUTPUTS = (
    "config.yaml",
    RUN_JSON,
    TRAJECTORY_TXT,
    FRAMES_JSONL,
    MAP_JSON,
    "map_planes.ply",
    "map_points.ply",
    METRICS_JSON,
    EVAL_JSON,
    TRAJECTORY_PNG,
    ATE_PNG,
    MAP_PNG,
    TIMELINE_PNG,
    REPORT_HTML,
    "groundtruth.txt",
    "mesh.ply",
    "run.rrd",
)
"""Every file a run (and `planeslam mesh` / `view` after it) writes into its folder."""

PREVIOUS_PREFIX = "previous-"


def default_out_dir(dataset: str | Path) -> Path:
    """out/<name> from the dataset's resolved path ('..' and '.' name their folder)."""
    return Path("out") / (resolve_path(dataset).name or "dataset")


@contextmanager
def claim_run_folder(out: str | Path, inputs: Sequence[Path] = ()) -> Iterator[Path | None]:
    """Own `out` for a run: hold its lock (`FolderLock`: OutputFolderError naming the live
    run that holds it) and move a previous run's files (`RUN_OUTPUTS`, links moved as links)
    into `out`/previous-<UTC time>/, so a folder never mixes two runs. Other files, and
    `inputs` the run still reads (a dataset's groundtruth.txt when `out` is the dataset
    folder), are left alone. Yields where the old files went (None: there were none)."""
    out = Path(out)
    with FolderLock(out):
        yield _move_previous(out, {resolve_path(p) for p in inputs})


def _move_previous(out: Path, keep: set[Path]) -> Path | None:
    found = [
        name
        for name in RUN_OUTPUTS
        if os.path.lexists(out / name) and resolve_path(out / name) not in keep
    ]
    if not found:
        return None
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    aside = out / f"{PREVIOUS_PREFIX}{stamp}"
    for k in itertools.count(1):
        try:
            aside.mkdir()
            break
        except FileExistsError:
            aside = out / f"{PREVIOUS_PREFIX}{stamp}-{k}"
    for name in found:
        os.rename(out / name, aside / name)
    log.info("%s: the previous run's files moved to %s", out, aside)
    return aside


def check_empty_folder(folder: str | Path, overwrite: bool) -> None:
    """OutputFolderError unless `folder` is absent or empty, or `overwrite` is given."""
    folder = Path(folder)
    if overwrite or not folder.exists():
        return
    if not folder.is_dir():
        raise OutputFolderError(f"{folder}: exists and is not a folder")
    if any(folder.iterdir()):
        raise OutputFolderError(
            f"{folder}: folder is not empty; choose another or pass --overwrite"
        )


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
