"""`planeslam bench long`: cost, map size and memory over long sequences that revisit.

A long sequence is a real or synthetic one replayed in passes, forward then backward
then forward again, so the camera keeps coming back to the places it has mapped. The
replay is a new dataset folder of list files pointing (through symlinks) at the source's
images, with new timestamps every 1/rate seconds and the ground truth replayed at them;
nothing is copied. The run reports per block of frames: fps, the backend's update time,
the map's landmarks and both processes' resident memory, then the ATE of the whole run
and of each pass (one alignment over the whole run: a revisit that drifts from the first
pass shows as a larger error in its pass). Run with several seeds, it also reports the
median and range of the ATE and of the plane growth over them (`seeds_summary`).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.app.progress import progress_bar
from planeslam.config import ConfigLayer, resolve_config
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.geometry import pose_distances
from planeslam.core.resources import rss_mb
from planeslam.core.safe_files import write_text_atomic
from planeslam.eval.trajectory_metrics import TrajectoryEvaluation, evaluate_trajectory
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import Trajectory, format_tum_row, read_tum
from planeslam.io.tum_text import row_error, tum_rows
from planeslam.slam import SLAM, FrameResult, run_frames, slam_for_dataset

log = logging.getLogger(__name__)


def pass_order(num_frames: int, passes: int) -> list[int]:
    """Source frame indices of `passes` passes over 0..num_frames-1, forward then backward
    and so on; a turn does not repeat its end frame."""
    if num_frames < 2 or passes < 1:
        raise ConfigError(f"a replay needs >= 2 frames and >= 1 pass, got {num_frames}, {passes}")
    order = list(range(num_frames))
    forward = True
    for _ in range(passes - 1):
        forward = not forward
        turn = list(range(num_frames - 2, -1, -1)) if not forward else list(range(1, num_frames))
        order += turn
    return order


def replay_sequence(source: Path, target: Path, passes: int, rate_hz: float = 30.0) -> Path:
    """Write `target` as `passes` forward-backward passes over the TUM folder `source` (with
    associations.txt and groundtruth.txt): rgb/ and depth/ are symlinks to the source's,
    list files and ground truth are new (timestamps k / rate_hz). Returns `target`."""
    source, target = Path(source).resolve(), Path(target)
    expected = "t_rgb rgb_path t_depth depth_path"
    assoc = source / "associations.txt"
    frames = []
    for lineno, fields in tum_rows(assoc, "associations", expected):
        if len(fields) < 4:
            raise row_error(assoc, lineno, f"'{expected}'", fields)
        frames.append((float(fields[0]), fields[1], fields[3]))
    truth = read_tum(source / "groundtruth.txt")
    truth_of = [truth.pose_near(t_src, 0.02) for t_src, _, _ in frames]  # per source frame
    order = pass_order(len(frames), passes)
    target.mkdir(parents=True, exist_ok=True)
    for folder in ("rgb", "depth"):
        link = target / folder
        if not link.exists():
            os.symlink(source / folder, link, target_is_directory=True)
    camera = source / "camera.yaml"
    if camera.is_file() and not (target / "camera.yaml").exists():
        os.symlink(camera, target / "camera.yaml")
    stamps = np.arange(len(order)) / rate_hz
    names = ("rgb.txt", "depth.txt", "associations.txt", "groundtruth.txt")
    lines: dict[str, list[str]] = {name: [] for name in names}
    for t, k in zip(stamps, order, strict=True):
        _, rgb, depth = frames[k]
        lines["rgb.txt"].append(f"{t:.6f} {rgb}")
        lines["depth.txt"].append(f"{t:.6f} {depth}")
        lines["associations.txt"].append(f"{t:.6f} {rgb} {t:.6f} {depth}")
        pose = truth_of[k]
        if pose is not None:
            lines["groundtruth.txt"].append(format_tum_row(t, pose))
    header = f"# replay of {source}: {passes} passes, {len(order)} frames at {rate_hz} Hz\n"
    for name, rows in lines.items():
        write_text_atomic(target / name, header + "\n".join(rows) + "\n")
    return target


@dataclass
class Block:
    """Figures of one block of consecutive frames."""

    first: int
    frames: int = 0
    seconds: float = 0.0
    keyframes: int = 0
    update_ms: list[float] = field(default_factory=list)
    map_planes: int = 0
    rss_main_mb: float = 0.0
    rss_backend_mb: float = 0.0

    def row(self) -> dict[str, Any]:
        return {
            "frames": f"{self.first}-{self.first + self.frames - 1}",
            "fps": self.frames / self.seconds if self.seconds else 0.0,
            "keyframes": self.keyframes,
            "update_ms_median": float(np.median(self.update_ms)) if self.update_ms else 0.0,
            "update_ms_p95": float(np.percentile(self.update_ms, 95)) if self.update_ms else 0.0,
            "map_planes": self.map_planes,
            "rss_main_mb": self.rss_main_mb,
            "rss_backend_mb": self.rss_backend_mb,
        }


@dataclass(frozen=True)
class LongRunResult:
    name: str
    blocks: list[dict[str, Any]]
    planes_per_pass: list[int]
    ate_rmse_m: float | None
    frames: int
    seconds: float
    ate_per_pass_m: list[float] = field(default_factory=list)
    """ATE RMSE of each pass's frames under the whole run's alignment [m]."""
    seed: int = 0
    """`run.seed` of the run (the front end's and the keypoint RANSAC's random generator)."""
    revisit_offsets: list[tuple[float, float]] = field(default_factory=list)
    """Per pass after the first: median translation [m] and rotation [deg] between a frame's
    estimated pose and the first pass's estimate of the same image (`revisit_offsets`)."""
    glitches_per_pass: list[int] = field(default_factory=list)
    """Pose glitches (`planeslam.tracking.glitches`) of the final trajectory in each pass."""

    @property
    def fps(self) -> float:
        """Frames per second over the run (frames and the final batch)."""
        return self.frames / self.seconds if self.seconds else 0.0

    @property
    def plane_growth(self) -> float | None:
        """Plane landmarks after the last pass over those after the first (None without a
        first pass's count)."""
        counts = self.planes_per_pass
        return counts[-1] / counts[0] if counts and counts[0] else None

    def to_text(self) -> str:
        head = (
            "| frames | fps | keyframes | iSAM2 update median / p95 [ms] | plane landmarks "
            "| RSS main / backend [MiB] |"
        )
        lines = [f"**{self.name}** (seed {self.seed})", "", head, "|---|---|---|---|---|---|"]
        for b in self.blocks:
            lines.append(
                f"| {b['frames']} | {b['fps']:.1f} | {b['keyframes']} | "
                f"{b['update_ms_median']:.0f} / {b['update_ms_p95']:.0f} | {b['map_planes']} | "
                f"{b['rss_main_mb']:.0f} / {b['rss_backend_mb']:.0f} |"
            )
        ate = "-" if self.ate_rmse_m is None else f"{100 * self.ate_rmse_m:.2f} cm"
        if self.ate_per_pass_m:
            ate += " (per pass " + " / ".join(f"{100 * e:.2f}" for e in self.ate_per_pass_m) + ")"
        passes = ", ".join(str(n) for n in self.planes_per_pass)
        lines += [
            "",
            f"{self.frames} frames in {self.seconds:.0f} s ({self.fps:.1f} fps); "
            f"plane landmarks after each pass: {passes}; ATE {ate}",
        ]
        if self.revisit_offsets:
            metres = " / ".join(f"{100 * m:.2f}" for m, _ in self.revisit_offsets)
            degrees = " / ".join(f"{deg:.2f}" for _, deg in self.revisit_offsets)
            lines.append(
                "the same image's pose against its first-pass pose, median per later pass: "
                f"{metres} cm, {degrees} deg"
            )
        if self.glitches_per_pass:
            counts = " / ".join(str(n) for n in self.glitches_per_pass)
            lines.append(f"pose glitches found per pass (without the truth): {counts}")
        return "\n".join(lines)


def seeds_summary(results: Sequence[LongRunResult]) -> str:
    """One line per run (seed, ATE, planes per pass, revisit offsets, fps) and the median
    with the range over the runs: the replay's ATE and plane count move by a few mm and
    tens of planes with the seed, so one seed's figure is one draw."""
    lines = [
        "| seed | ATE [cm] | per pass [cm] | plane landmarks after each pass | last / first "
        "| same image, later passes [cm] | fps |"
    ]
    lines.append("|---|---|---|---|---|---|---|")
    for r in results:
        ate = "-" if r.ate_rmse_m is None else f"{100 * r.ate_rmse_m:.2f}"
        per_pass = " / ".join(f"{100 * e:.2f}" for e in r.ate_per_pass_m) or "-"
        growth = "-" if r.plane_growth is None else f"{r.plane_growth:.2f}x"
        planes = ", ".join(str(n) for n in r.planes_per_pass)
        offsets = " / ".join(f"{100 * m:.2f}" for m, _ in r.revisit_offsets) or "-"
        lines.append(
            f"| {r.seed} | {ate} | {per_pass} | {planes} | {growth} | {offsets} | {r.fps:.1f} |"
        )
    figures = []
    ates = [100 * r.ate_rmse_m for r in results if r.ate_rmse_m is not None]
    if ates:
        figures.append(f"ATE median {np.median(ates):.2f} cm ({min(ates):.2f}-{max(ates):.2f})")
    growths = [r.plane_growth for r in results if r.plane_growth is not None]
    if growths:
        figures.append(
            f"plane landmarks last / first pass median {np.median(growths):.2f}x "
            f"({min(growths):.2f}-{max(growths):.2f})"
        )
    seeds = ", ".join(str(r.seed) for r in results)
    return "\n".join([*lines, "", f"over seeds {seeds}: " + "; ".join(figures)])


def run_long(
    root: Path,
    frames_per_pass: int,
    block: int = 1000,
    config: str | Path | None = None,
    progress: bool = False,
    blocks_path: Path | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
    seed: int = 0,
) -> LongRunResult:
    """SLAM (the config's backend) over a replayed folder, measured block by block.
    `frames_per_pass`: the frames each turn adds (the source's frames - 1, `pass_order`);
    the first pass has one more. `overrides`: 'section.key=value' strings or config layers
    after `config`, then `run.seed` = `seed`. With `blocks_path`, each block's row (with
    its seed) is appended there as a JSON line as soon as the block ends (its iSAM2 update
    times, known only after the final optimisation, are left out), so an interrupted run
    keeps its blocks."""
    cfg = resolve_config(root, config, overrides=[*overrides, f"run.seed={seed}"])
    dataset = TumDataset(root, cfg.camera, cfg.dataset)
    if dataset.groundtruth is None:
        raise DatasetFormatError(f"{root}: no groundtruth.txt")
    blocks: list[Block] = []
    planes_per_pass: list[int] = []
    keyframe_of: list[int] = []  # frame index of each keyframe, in order
    last = 0.0
    with (
        slam_for_dataset(cfg, dataset, 0) as slam,
        progress_bar(len(dataset), root.name, "frame", enabled=progress) as bar,
    ):
        pid = getattr(getattr(slam.backend, "_process", None), "pid", None)

        def on_result(result: FrameResult) -> None:
            nonlocal last
            k = result.index
            if k % block == 0:
                blocks.append(Block(first=k))
            now = time.perf_counter()
            b = blocks[-1]
            b.frames += 1
            b.seconds += now - last
            last = now
            if result.keyframe:
                b.keyframes += 1
                keyframe_of.append(k)
            if k > 0 and k % frames_per_pass == 0:  # the last frame of a pass
                planes_per_pass.append(len(slam.map.planes))
            if (k + 1) % block == 0 or k + 1 == len(dataset):
                b.map_planes = len(slam.map.planes)
                b.rss_main_mb = rss_mb()
                b.rss_backend_mb = rss_mb(pid) if pid else 0.0
                if blocks_path is not None:
                    row = {k: v for k, v in b.row().items() if not k.startswith("update_ms")}
                    row["seed"] = seed
                    with blocks_path.open("a", encoding="utf-8") as f:
                        f.write(json.dumps(row) + "\n")
            bar.step()

        last = time.perf_counter()  # the frames' time, as `planeslam run`: not the start-up
        summary = run_frames(slam, dataset, range(len(dataset)), on_result)
    result = slam.backend_result
    if result is not None:
        for index, ms in zip(keyframe_of, result.update_ms, strict=False):
            blocks[index // block].update_ms.append(ms)
    estimate: Trajectory = slam.trajectory()
    evaluation = evaluate_trajectory(dataset.groundtruth, estimate)
    return LongRunResult(
        name=root.name,
        blocks=[b.row() for b in blocks],
        planes_per_pass=planes_per_pass,
        ate_rmse_m=evaluation.ate_rmse_m,
        frames=summary.frames,
        seconds=summary.seconds,
        ate_per_pass_m=_ate_per_pass(evaluation, dataset.timestamps, frames_per_pass),
        seed=seed,
        revisit_offsets=revisit_offsets(estimate, dataset.timestamps, frames_per_pass),
        glitches_per_pass=_glitches_per_pass(slam, estimate, dataset.timestamps, frames_per_pass),
    )


def _pass_of(stamps: np.ndarray, timestamps: np.ndarray, frames_per_pass: int) -> np.ndarray:
    """(M,) pass of each of `stamps` (M,) [s], frames of the replay's `timestamps` (N,) [s]:
    frame k is in pass max(0, (k - 1) // frames_per_pass) (`pass_order`: the first pass has
    one more frame)."""
    k = np.searchsorted(np.asarray(timestamps), np.asarray(stamps) - 1e-6)
    return np.maximum(0, (k - 1) // frames_per_pass)


def _ate_per_pass(
    evaluation: TrajectoryEvaluation, timestamps: np.ndarray, frames_per_pass: int
) -> list[float]:
    """RMSE [m] of `evaluation`'s aligned errors grouped by pass (`_pass_of`)."""
    passes = _pass_of(evaluation.timestamps, timestamps, frames_per_pass)
    errors = np.asarray(evaluation.ate_errors_m)
    return [float(np.sqrt(np.mean(errors[passes == p] ** 2))) for p in np.unique(passes)]


def _glitches_per_pass(
    slam: SLAM, estimate: Trajectory, timestamps: np.ndarray, frames_per_pass: int
) -> list[int]:
    """The pose glitches of the finished `slam`'s final trajectory `estimate` counted by
    pass (`_pass_of`)."""
    passes = (len(timestamps) - 1) // frames_per_pass if frames_per_pass else 0
    stamps = slam.pose_glitches(estimate).timestamps
    found = _pass_of(np.asarray(stamps, dtype=np.float64), timestamps, frames_per_pass)
    return [int(np.count_nonzero(found == p)) for p in range(max(passes, 1))]


def revisit_offsets(
    estimate: Trajectory, timestamps: np.ndarray, frames_per_pass: int
) -> list[tuple[float, float]]:
    """Per pass after the first, the median translation [m] and rotation [deg] between each
    frame's pose in `estimate` and the first pass's pose of the same source image (replay
    frame k of `timestamps` (N,) [s] shows source image `pass_order(...)[k]`; frames
    missing from `estimate`, lost ones, are left out). A consistent map places an image
    where it placed it before, so this measures revisits without the ground truth's own
    error (7-Scenes' comes from KinectFusion)."""
    timestamps = np.asarray(timestamps, dtype=np.float64)
    passes = (len(timestamps) - 1) // frames_per_pass
    if passes < 2 or not len(estimate):
        return []
    source = np.asarray(pass_order(frames_per_pass + 1, passes))[: len(timestamps)]
    k = np.searchsorted(timestamps, estimate.timestamps - 1e-6)
    known = k < len(timestamps)
    k, poses = k[known], estimate.T_world_cam[known]
    pass_of = np.maximum(0, (k - 1) // frames_per_pass)
    first_row = np.full(frames_per_pass + 1, -1)  # source image -> its first-pass row
    in_first = np.flatnonzero(pass_of == 0)
    first_row[source[k[in_first]]] = in_first
    partner = first_row[source[k]]
    metres, degrees = pose_distances(poses, poses[partner])  # rows without one: dropped
    offsets = []
    for p in range(1, passes):
        rows = (pass_of == p) & (partner >= 0)
        if not rows.any():
            offsets.append((float("nan"), float("nan")))
            continue
        offsets.append((float(np.median(metres[rows])), float(np.median(degrees[rows]))))
    return offsets


def bench_long(
    source: str,
    out_dir: Path,
    passes: int = 5,
    block: int = 1000,
    config: str | Path | None = None,
    progress: bool = False,
    overrides: Sequence[str | ConfigLayer] = (),
    seeds: Sequence[int] = (0,),
) -> list[LongRunResult]:
    """`source`: a TUM folder (with associations.txt and groundtruth.txt) or the name of a
    built-in synthetic scene (rendered into OUT_DIR/data once). Builds the replay of
    `passes` passes in OUT_DIR and runs it once per seed of `seeds` (`run_long`); writes
    OUT_DIR/blocks.jsonl as the blocks end (started afresh) and OUT_DIR/long.md (each run's
    table, then with several seeds `seeds_summary`), rewritten after each run."""
    if not seeds:
        raise ConfigError("bench long: at least one seed")
    from planeslam.sim.scenes import SCENES
    from planeslam.sim.sequence import synthesize

    out_dir = Path(out_dir)
    if source in SCENES:
        folder = out_dir / "data" / source
        if not (folder / "truth.json").is_file():
            synthesize(source, folder, seed=0)
    else:
        folder = Path(source)
        if not folder.is_dir():
            raise DatasetFormatError(
                f"{source}: neither a dataset folder nor a scene ({', '.join(sorted(SCENES))})"
            )
    camera = resolve_config(folder, config, overrides=overrides).camera  # bad keys fail here
    frames_per_pass = len(TumDataset(folder, camera))
    replay = replay_sequence(folder, out_dir / f"{folder.name}_{passes}pass", passes)
    blocks_path = out_dir / "blocks.jsonl"
    blocks_path.unlink(missing_ok=True)
    results: list[LongRunResult] = []
    for seed in seeds:
        results.append(
            run_long(
                replay, frames_per_pass - 1, block, config, progress, blocks_path, overrides, seed
            )
        )
        write_text_atomic(out_dir / "long.md", long_text(results) + "\n")
    return results


def long_text(results: Sequence[LongRunResult]) -> str:
    """Each run's table; with more than one run, then `seeds_summary`."""
    parts = [r.to_text() for r in results]
    if len(results) > 1:
        parts.append(seeds_summary(results))
    return "\n\n".join(parts)
