"""Shared by the scripts that watch a run from inside: their arguments and the truth
(`watched_run`: dense_choices.py, plane_pairs.py), which frame is being processed and the
true step it makes (dense_choices.py, dense_landing.py, sweep_timing.py); a stage's CPU
time over a whole run timed as `planeslam bench speed` times it (fused_cloud_cpu.py,
map_merge_cpu.py); the modules that call `convex_hull_2d` (map_merge_cpu.py,
hull_timing.py); the first frames of a sequence (`first_frames`: open3d_threads.py,
tensor_odometry.py); the timing scripts' dataset (`timed_source`: fused_cloud_cpu.py,
map_merge_cpu.py through `time_whole_run`, front_end_process.py, front_end_stages.py,
front_end_diff.py, whole_system_threads.py)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import planeslam.mapping.seating as seating
import planeslam.slam.system as system
import planeslam.tracking.association as association
from planeslam.config import open_configured, resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.geometry import invert_pose
from planeslam.io.dataset import Frame
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import read_tum
from planeslam.tracking.hypotheses import pose_difference

SEVEN_SCENES = "../shared/data/7scenes_redkitchen_1000f"
"""The default sequence of the timing scripts (beside the checkout)."""

HULL_CALLERS = (seating, association)
"""The modules whose `convex_hull_2d` a run calls: the map merge's outlines and plane
association's overlap. Replace it on each to watch every hull."""


class WatchedRun(NamedTuple):
    """A watched run's arguments, SEQUENCE OUT [FRAMES] [INDICES], and its truth."""

    sequence: str
    out: str
    frames: int | None
    """The first FRAMES frames (None: all)."""
    indices: set[int] | None
    """The frames to show (None: every one)."""
    truth: list[np.ndarray]
    """(4, 4) true T_world_cam per frame, from SEQUENCE's groundtruth.txt."""

    def shown(self, frame: int) -> bool:
        return self.indices is None or frame in self.indices


def watched_run(argv: Sequence[str]) -> WatchedRun:
    """argv's SEQUENCE OUT [FRAMES] [INDICES (comma-separated)] and SEQUENCE's truth (one
    pose per frame, as `planeslam synth` writes)."""
    sequence, out = argv[1], argv[2]
    return WatchedRun(
        sequence,
        out,
        int(argv[3]) if len(argv) > 3 else None,
        {int(i) for i in argv[4].split(",")} if len(argv) > 4 else None,
        list(read_tum(f"{sequence}/groundtruth.txt").T_world_cam),
    )


def first_frames(
    argv: Sequence[str], default_count: int
) -> tuple[RgbdDataset, CameraConfig, list[Frame]]:
    """argv's [DATASET] [PAIRS] (default SEVEN_SCENES and `default_count`): the dataset
    (read with its guessed config), its camera and its first PAIRS + 1 frames."""
    path = Path(argv[1] if len(argv) > 1 else SEVEN_SCENES)
    count = int(argv[2]) if len(argv) > 2 else default_count
    dataset, config = open_configured(path, resolve_config(path))
    return dataset, config.camera, [dataset[i] for i in range(count + 1)]


def count_frames() -> dict[str, int]:
    """Wraps `SLAM.process` to count the frames of the run; the returned dict's "frame" is
    the index of the frame being processed (-1 before the first)."""
    current = {"frame": -1}
    process = system.SLAM.process

    def counting(self, *args, **kwargs):
        current["frame"] += 1
        return process(self, *args, **kwargs)

    system.SLAM.process = counting
    return current


def step(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(4, 4) the motion from T_from to T_to, in T_from's camera frame."""
    return invert_pose(T_from) @ T_to


def step_error_m(truth: list[np.ndarray], i: int, T_previous: np.ndarray, T: np.ndarray) -> float:
    """Error [m] of T (4, 4) as frame i's step from T_previous (4, 4), against the true step
    between the (4, 4) poses truth[i - 1] and truth[i]."""
    return pose_difference(step(truth[i - 1], truth[i]), step(T_previous, T))[0]


def thread_cpu(
    function: Callable[..., Any],
    spent: dict[str, float],
    figure: str,
    calls: dict[str, int] | None = None,
    wall: dict[str, float] | None = None,
):
    """`function` wrapped to add the CPU time of its calling thread (`time.thread_time`)
    to spent[figure] [s], with `calls` 1 to calls[figure] per call, and with `wall` its
    wall-clock time to wall[figure] [s]."""

    def wrapper(*args, **kwargs):
        start, start_wall = time.thread_time(), time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            spent[figure] += time.thread_time() - start
            if calls is not None:
                calls[figure] += 1
            if wall is not None:
                wall[figure] += time.perf_counter() - start_wall

    return wrapper


def timed_source(argv: Sequence[str], default_frames: int):
    """argv's [DATASET] [FRAMES] (default the 7-Scenes clip beside the checkout and
    `default_frames`) opened as `planeslam bench speed` opens a dataset (its `_Source`)."""
    from planeslam.app.bench_speed import _open_source

    dataset = Path(argv[1] if len(argv) > 1 else SEVEN_SCENES)
    frames = int(argv[2]) if len(argv) > 2 else default_frames
    return _open_source(dataset, frames, None, ())


def time_whole_run(argv: Sequence[str], default_frames: int) -> tuple[float, int, float]:
    """The whole system on argv's [DATASET] [FRAMES] (`timed_source`), timed as `planeslam
    bench speed` times it: (wall seconds, frames, CPU seconds of this process and the
    backend worker)."""
    from planeslam.app.bench_speed import _time_whole_system

    return _time_whole_system(timed_source(argv, default_frames))
