"""SLAM over a dataset: the frames to take (`frame_indices`), a SLAM starting where the
dataset says (`slam_for_dataset`) and the loop that feeds it (`run_frames`)."""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import time
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager

from planeslam.backend.base import BackendKind
from planeslam.config import PlaneSlamConfig
from planeslam.core.errors import ConfigError, DatasetFormatError, FrameReadError
from planeslam.core.native_tuning import single_native_threads
from planeslam.core.types import RelativePose
from planeslam.io.dataset import Frame
from planeslam.io.sequence import RgbdDataset
from planeslam.slam.records import FrameResult, RunSummary, RunTally
from planeslam.slam.system import SLAM

logger = logging.getLogger(__name__)


def frame_indices(num_frames: int, max_frames: int | None, every: int) -> list[int]:
    """Every `every`-th frame index, at most `max_frames` of them."""
    if every < 1:
        raise ConfigError(f"every must be >= 1 (take every n-th frame), got {every}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"max_frames must be >= 1 or None, got {max_frames}")
    return list(range(0, num_frames, every))[:max_frames]


def slam_for_dataset(
    config: PlaneSlamConfig,
    dataset: RgbdDataset,
    first_index: int,
    backend: BackendKind | str | None = None,
    seed: int | None = None,
) -> SLAM:
    """A SLAM starting at frame `first_index` as `run.start_pose` says: 'groundtruth' at its
    ground-truth pose (the identity without ground truth), so the estimates and the truth
    share the world frame and compare pose by pose; 'identity' at the identity."""
    T_world_first = None
    if config.run.start_pose == "groundtruth":
        T_world_first = dataset.groundtruth_pose(dataset.timestamps[first_index])
    known = T_world_first is not None and dataset.groundtruth is not None
    logger.info(
        "start pose (run.start_pose %s): %s",
        config.run.start_pose,
        "the first frame's ground truth" if known else "the identity",
    )
    return SLAM(config, backend, T_world_first=T_world_first, seed=seed)


def _read(dataset: RgbdDataset, index: int) -> tuple[Frame, float]:
    t0 = time.perf_counter()
    frame = dataset[index]
    return frame, 1e3 * (time.perf_counter() - t0)


def run_frames(
    slam: SLAM,
    dataset: RgbdDataset,
    indices: Iterable[int],
    on_result: Callable[[FrameResult], None] | None = None,
    tally: RunTally | None = None,
    guard: Callable[[], AbstractContextManager[object]] | None = None,
    odometry: Callable[[float, float], RelativePose | None] | None = None,
) -> RunSummary:
    """Feed `dataset[i]` for i in `indices` to `slam`; `on_result` sees every FrameResult as
    it comes (write it out there: an interrupted run then keeps what it did), `tally` (when
    given) the counts so far. Each frame is processed, counted and passed to `on_result`
    inside `guard()` when given (an application's deferral of Ctrl-C: a frame is then
    wholly done and reported, or not begun). The next frame is read on a second thread
    while this one is processed; the 'read' stage is the reader's time, which overlaps
    processing. A frame whose image cannot be read (FrameReadError) is skipped with a
    warning; DatasetFormatError when no frame can be read. `odometry(t_prev, t_cur)`, when
    given, is the camera's measured motion since the previous processed frame (None where
    it has none; `planeslam.io.odometry.OdometryFile.step`)."""
    tally = RunTally() if tally is None else tally
    tally.start = time.perf_counter()
    indices = list(indices)
    previous_stamp: float | None = None
    # Frames are read (PNG decoding releases the GIL) one ahead on a second thread.
    try:
        with (
            single_native_threads(),
            concurrent.futures.ThreadPoolExecutor(max_workers=1) as reader,
        ):
            upcoming = [reader.submit(_read, dataset, indices[0])] if indices else []
            for k in range(len(indices)):
                future = upcoming.pop()
                if k + 1 < len(indices):
                    upcoming.append(reader.submit(_read, dataset, indices[k + 1]))
                try:
                    frame, read_ms = future.result()
                except FrameReadError as exc:
                    tally.skipped_frames += 1
                    logger.warning("frame %d skipped: %s", indices[k], exc)
                    continue
                step = None
                if odometry is not None and previous_stamp is not None:
                    step = odometry(previous_stamp, frame.timestamp)
                previous_stamp = frame.timestamp
                with guard() if guard is not None else contextlib.nullcontext():
                    result = slam.process(frame.depth_m, frame.timestamp, frame.rgb, step)
                    tally.add(result, read_ms)
                    if on_result is not None:
                        on_result(result)
        if indices and not tally.frame_timings:
            raise DatasetFormatError(
                f"{dataset.root}: none of the {len(indices)} frames could be read "
                "(each was skipped: its images are missing or cannot be decoded)"
            )
        tally.finish_ms = slam.finish()
    except BaseException:  # interrupted or failed: stop the backend, keep the map as it is
        slam.close()
        raise
    return tally.summary()
