"""`planeslam bench speed`: the front end and the whole system, timed in one sitting and
normalised by a fixed reference workload, so two runs made in different hours (or on a
machine shared with other jobs) compare.

Each of `repeats` rounds times, for every dataset (a TUM folder such as 7-Scenes, and
the built-in synthetic scene):
- front end: `FrontEnd.process` on frames held in memory (reading excluded), one
  untimed warm-up frame first;
- whole system: `run_frames` on a fresh `SLAM` (what `planeslam run` does, outputs
  not written): frames read one ahead on a second thread, the backend in its worker
  process, the final optimisation included, start-up excluded;
and the reference workload before the first run and after every run: each run's
reference time is the mean of the two timed around it (the load of the minute).

Figures per workload, each the median over the rounds:
- fps = frames / seconds;
- ms/frame = 1000 seconds / frames;
- ref units/frame = (seconds / frames) / (the run's reference seconds): the cost of a
  frame in reference workloads; it moves with the code, much less with the hour;
- CPU ms/frame = 1000 CPU seconds / frames: user + system time of this process (all its
  threads) and, for the whole system, of the backend worker process; on a machine
  shared with other jobs it counts the work done, not the wait for a core.

The reference workload is pure numpy and OpenCV, fixed in size and seed, with the
pipeline's mix (PNG decoding, image-sized float32 arithmetic, per-cell reductions,
sorting and counting, contours, and many small-array calls from Python); it takes
about 1 s on one core of a quiet 2-core machine and never changes with planeslam's code.
"""

from __future__ import annotations

import logging
import os
import platform
import statistics
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from planeslam import __version__
from planeslam.app.bench import aligned_rows, synthetic_dataset
from planeslam.config import ConfigLayer, PlaneSlamConfig, open_configured, resolve_config
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.native_tuning import single_native_threads

if TYPE_CHECKING:
    from planeslam.io.sequence import RgbdDataset

log = logging.getLogger(__name__)

FRONT_END = "front end"
WHOLE_SYSTEM = "whole system"
DEFAULT_DATASET = Path("../shared/data/7scenes_redkitchen_1000f")
"""Timed when no dataset is given and it exists (relative to the working directory)."""
MAX_PRELOADED = 100
"""Most distinct frames the front-end timing holds in memory (cycled beyond)."""
REFERENCE_ROUNDS = 5
"""Repetitions of the reference's basic block (fixed: about 1 s in all)."""

MARKDOWN_COLUMNS = (
    "date (UTC)",
    "commit",
    "command",
    "machine",
    "load before",
    "load after",
    "workload",
    "dataset",
    "frames",
    "fps",
    "ms/frame",
    "reference s",
    "ref units/frame",
    "CPU ms/frame",
)
"""Columns of `SpeedResult.to_markdown`; fps, ms/frame, reference s, ref units/frame and
CPU ms/frame are medians over the rounds."""


# ----------------------------------------------------------------------------------------
# The reference workload.


def reference_workload() -> float:
    """Run the fixed reference workload once (single-threaded numpy and OpenCV) -> its
    wall-clock seconds. Same inputs (seed 0) and same work on every call."""
    import cv2

    rng = np.random.default_rng(0)
    h, w = 480, 640
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = 1.0 + 0.002 * u + 0.001 * v + rng.normal(0.0, 0.005, (h, w)).astype(np.float32)
    depth[100:200, 300:420] += 0.5
    ok, png = cv2.imencode(".png", (depth * 1000).astype(np.uint16))
    assert ok
    rays = np.dstack([(u - 320) / 585.0, (v - 240) / 585.0, np.ones_like(u)]).astype(np.float32)
    small = rng.normal(size=(256, 3, 3))
    small = small @ small.transpose(0, 2, 1)
    with single_native_threads():
        t0 = time.perf_counter()
        total = 0.0
        for _ in range(REFERENCE_ROUNDS):
            decoded = [cv2.imdecode(png, cv2.IMREAD_UNCHANGED) for _ in range(8)]  # the reader
            z = np.asarray(decoded[-1], dtype=np.float32) / 1000.0
            for _ in range(6):  # back-projection and per-cell moments
                _, zc = cv2.threshold(z, 6.0, 0.0, cv2.THRESH_TOZERO_INV)
                cloud = cv2.multiply(rays, cv2.merge([zc, zc, zc]))
                cells = cloud.reshape(30, 16, 40, 16, 3).transpose(0, 2, 1, 3, 4)
                cells = cells.reshape(1200, 256, 3)
                mean = cells.mean(axis=1)
                centred = cells - mean[:, None, :]
                scatter = np.einsum("cpi,cpj->cij", centred, centred)
                total += float(np.linalg.eigvalsh(scatter.astype(np.float64))[:, 0].sum())
            for _ in range(4):  # sorting and counting labels
                labels = (zc * 7).astype(np.int32).ravel()
                order = np.argsort(labels, kind="stable")
                counts = np.bincount(labels[order])
                total += float(counts.max())
            for _ in range(4):  # masks and contours
                mask = (zc > 1.6).astype(np.uint8)
                opened = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
                contours, _ = cv2.findContours(opened, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
                total += len(contours)
            for k in range(1500):  # small-array calls from Python (tracking, the map)
                s = small[k % 256]
                n = np.linalg.eigh(s)[1][:, 0]
                total += float(n @ s @ n) + float(np.linalg.norm(np.cross(n, s[0])))
        seconds = time.perf_counter() - t0
    if not np.isfinite(total):  # keeps the work from being optimised away, in spirit
        raise ArithmeticError("reference workload produced a non-finite checksum")
    return seconds


# ----------------------------------------------------------------------------------------
# Results.


@dataclass(frozen=True)
class WorkloadTiming:
    """One workload (front end or whole system on one dataset) timed in every round."""

    kind: str
    """FRONT_END or WHOLE_SYSTEM."""
    dataset: str
    """Dataset folder name."""
    frames: int
    """Frames per round."""
    seconds: tuple[float, ...]
    """Wall-clock seconds of each round."""
    reference_s: tuple[float, ...]
    """The reference workload's seconds around each round's run (mean of the two)."""
    cpu_s: tuple[float, ...]
    """CPU seconds (user + system) of each round's run, the backend worker's included."""

    @property
    def fps_runs(self) -> tuple[float, ...]:
        return tuple(self.frames / s for s in self.seconds)

    @property
    def fps(self) -> float:
        """Median frames per second."""
        return statistics.median(self.fps_runs)

    @property
    def ms_per_frame(self) -> float:
        """Median milliseconds per frame."""
        return statistics.median(1e3 * s / self.frames for s in self.seconds)

    @property
    def ref_units_per_frame(self) -> float:
        """Median over rounds of (seconds / frames) / reference seconds."""
        return statistics.median(
            s / self.frames / r for s, r in zip(self.seconds, self.reference_s, strict=True)
        )

    @property
    def cpu_ms_per_frame(self) -> float:
        """Median CPU milliseconds per frame."""
        return statistics.median(1e3 * c / self.frames for c in self.cpu_s)

    @property
    def label(self) -> str:
        return f"{self.kind} {self.dataset}"


@dataclass(frozen=True)
class MachineInfo:
    """Where and when a benchmark ran."""

    cpu_model: str
    cores: int
    """Cores this process may run on."""
    date_utc: str
    """ISO 8601 start time, UTC, minutes."""
    commit: str
    """Short git commit of the planeslam code measured ('-dirty' with local edits)."""
    load_before: tuple[float, float, float]
    """os.getloadavg() (1, 5, 15 min) before the first round."""
    load_after: tuple[float, float, float]
    """os.getloadavg() after the last round."""

    @property
    def machine(self) -> str:
        return f"{self.cpu_model}, {self.cores} cores"


@dataclass(frozen=True)
class SpeedResult:
    """Figures of one `bench_speed` run."""

    command: str
    """The command line ('' from Python)."""
    machine: MachineInfo
    repeats: int
    reference_s: tuple[float, ...]
    """Every timing of the reference workload (1 + one per run), in order."""
    workloads: tuple[WorkloadTiming, ...]

    def ratios(self) -> dict[str, float]:
        """Dataset -> whole-system fps / front-end fps (medians)."""
        out = {}
        for w in self.workloads:
            if w.kind != WHOLE_SYSTEM:
                continue
            fe = [f for f in self.workloads if f.kind == FRONT_END and f.dataset == w.dataset]
            if fe:
                out[w.dataset] = w.fps / fe[0].fps
        return out

    def to_text(self) -> str:
        """A readable table: one row per workload."""
        m = self.machine
        head = [
            f"planeslam bench speed: rounds: {self.repeats} in one sitting, commit {m.commit}, "
            f"{m.date_utc} UTC",
            f"machine: {m.machine}; load average before {_load(m.load_before)}, "
            f"after {_load(m.load_after)}",
            f"reference workload: median {statistics.median(self.reference_s):.3f} s "
            f"(runs {' '.join(f'{r:.3f}' for r in self.reference_s)})",
        ]
        rows = [
            [
                "workload",
                "frames",
                "fps",
                "fps per round",
                "ms/frame",
                "ref units/frame",
                "CPU ms/frame",
            ]
        ]
        for w in self.workloads:
            rows.append(
                [
                    w.label,
                    str(w.frames),
                    f"{w.fps:.1f}",
                    " ".join(f"{f:.1f}" for f in w.fps_runs),
                    f"{w.ms_per_frame:.1f}",
                    f"{w.ref_units_per_frame:.4f}",
                    f"{w.cpu_ms_per_frame:.1f}",
                ]
            )
        lines = aligned_rows(rows)
        ratios = ", ".join(f"{k} {v:.2f}" for k, v in self.ratios().items())
        foot = [
            "fps, ms/frame, ref units/frame, CPU ms/frame: medians over the rounds; ref "
            "units/frame = (seconds per frame) / (the reference seconds around the run), lower "
            "is faster; CPU ms/frame: this process's and the backend worker's CPU time.",
        ]
        if ratios:
            foot.append(f"whole system fps / front end fps: {ratios}")
        return "\n".join(head + lines + foot)

    def markdown_rows(self) -> list[list[str]]:
        """The rows of `to_markdown`, one per workload, cells as `MARKDOWN_COLUMNS`."""
        m = self.machine
        command = f"`{self.command}`" if self.command else "(from Python)"
        return [
            [
                m.date_utc,
                m.commit,
                command,
                m.machine,
                _load(m.load_before),
                _load(m.load_after),
                w.kind,
                w.dataset,
                str(w.frames),
                f"{w.fps:.2f}",
                f"{w.ms_per_frame:.2f}",
                f"{statistics.median(w.reference_s):.3f}",
                f"{w.ref_units_per_frame:.5f}",
                f"{w.cpu_ms_per_frame:.2f}",
            ]
            for w in self.workloads
        ]

    def to_markdown(self, header: bool = True) -> str:
        """A markdown table (with its header row when `header`), one row per workload."""
        lines = []
        if header:
            lines.append(_md_row(MARKDOWN_COLUMNS))
            lines.append(_md_row(["---"] * len(MARKDOWN_COLUMNS)))
        lines.extend(_md_row(r) for r in self.markdown_rows())
        return "\n".join(lines) + "\n"


def _load(load: Sequence[float]) -> str:
    return " ".join(f"{x:.2f}" for x in load)


def _md_row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def append_markdown(result: SpeedResult, path: str | Path) -> Path:
    """Append `result`'s table to `path`: its rows only when the file already ends with a
    table of the same columns (one table grows run after run), else a new table."""
    path = Path(path)
    text = path.read_text(encoding="utf-8") if path.is_file() else ""
    lines = [line for line in text.splitlines() if line.strip()]
    continues = (
        bool(lines) and lines[-1].startswith("|") and _md_row(MARKDOWN_COLUMNS) in text.splitlines()
    )
    with path.open("a", encoding="utf-8") as f:
        if text and not text.endswith("\n"):
            f.write("\n")
        if not continues and text:
            f.write("\n")
        f.write(result.to_markdown(header=not continues))
    return path


# ----------------------------------------------------------------------------------------
# The benchmark.


def machine_now(load_before: tuple[float, float, float], started_utc: str) -> MachineInfo:
    """MachineInfo with the code's commit and the load now as 'after'."""
    return MachineInfo(
        cpu_model=cpu_model(),
        cores=len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else os.cpu_count() or 1,
        date_utc=started_utc,
        commit=code_commit(),
        load_before=load_before,
        load_after=load_average(),
    )


def cpu_model() -> str:
    """The processor's model name (Linux /proc/cpuinfo, else the platform's)."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def load_average() -> tuple[float, float, float]:
    """The 1, 5 and 15 minute load averages (NaN where the system has none)."""
    try:
        return os.getloadavg()
    except OSError:
        return (float("nan"),) * 3


def code_commit() -> str:
    """Short commit of the git checkout planeslam is imported from, '-dirty' when tracked
    files differ from it; the package version when it is not a git checkout."""
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=here,
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "."],
            cwd=here.parent,
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"v{__version__}"
    return commit + ("-dirty" if dirty else "")


@dataclass(frozen=True)
class _Source:
    """One dataset of the benchmark, opened and configured."""

    name: str
    folder: Path
    config: PlaneSlamConfig
    dataset: RgbdDataset
    indices: list[int]


def _open_source(
    folder: Path, frames: int, config: str | Path | None, overrides: Sequence[str | ConfigLayer]
) -> _Source:
    from planeslam.slam import frame_indices

    cfg = resolve_config(folder, config, None, overrides)
    dataset, cfg = open_configured(folder, cfg)
    if len(dataset) == 0:
        raise DatasetFormatError(f"{folder}: no frames")
    indices = frame_indices(len(dataset), frames, 1)
    return _Source(folder.name, folder, cfg, dataset, indices)


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process (`time.process_time`: all its threads, to
    the nanosecond; `os.times` counts in 10 ms ticks, which a short run can stay under) and
    of its finished (waited-for) children."""
    t = os.times()
    return time.process_time() + t.children_user + t.children_system


def _time_front_end(source: _Source) -> tuple[float, int, float]:
    """FrontEnd.process over the source's frames (preloaded, at most MAX_PRELOADED distinct
    ones, cycled) -> (seconds, frames, CPU seconds)."""
    from planeslam.frontend.pipeline import FrontEnd

    n = len(source.indices)
    distinct = min(n, MAX_PRELOADED)
    pick = np.linspace(0, n - 1, distinct).round().astype(int)
    loaded = [source.dataset[source.indices[int(i)]] for i in pick]
    front_end = FrontEnd(source.config, seed=0)
    with single_native_threads():
        front_end.process(loaded[0].depth_m, loaded[0].timestamp)
        cpu0, t0 = _cpu_seconds(), time.perf_counter()
        for k in range(n):
            frame = loaded[k % distinct]
            front_end.process(frame.depth_m, frame.timestamp)
        seconds, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
    return seconds, n, cpu


def _time_whole_system(source: _Source) -> tuple[float, int, float]:
    """`run_frames` (reading on its thread, backend, final optimisation) on a fresh SLAM
    over the source's frames -> (seconds, frames processed, CPU seconds: this process's
    during the run and the backend worker's whole life, start-up included)."""
    from planeslam.slam import run_frames, slam_for_dataset

    children0 = os.times()
    slam = slam_for_dataset(source.config, source.dataset, source.indices[0])
    with slam:
        cpu0 = _cpu_seconds()
        summary = run_frames(slam, source.dataset, source.indices)
        cpu = _cpu_seconds() - cpu0
    children = os.times()  # the worker, waited for when the SLAM closed
    cpu += children.children_user + children.children_system
    cpu -= children0.children_user + children0.children_system
    return summary.seconds, summary.frames, cpu


def bench_speed(
    dataset_dirs: Sequence[str | Path] = (),
    frames: int = 300,
    repeats: int = 3,
    synthetic: bool = True,
    config: str | Path | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
    cache_dir: str | Path | None = None,
    command: str = "",
    progress: bool = False,
) -> SpeedResult:
    """Time the front end and the whole system on each dataset folder (its first `frames`
    frames) and, with `synthetic`, on the built-in synthetic scene (rendered once into
    `cache_dir`), `repeats` rounds in one sitting, with the reference workload before the
    first run and after every run. See the module docstring for the figures."""

    if frames < 1:
        raise ConfigError(f"bench speed: --frames must be >= 1, got {frames}")
    if repeats < 1:
        raise ConfigError(f"bench speed: --repeats must be >= 1, got {repeats}")
    folders = [Path(d) for d in dataset_dirs]
    if synthetic:
        folders.append(synthetic_dataset(None if cache_dir is None else Path(cache_dir)))
    if not folders:
        raise ConfigError(
            "bench speed: no dataset to time (give a folder or keep the synthetic scene)"
        )
    sources = [_open_source(f, frames, config, overrides) for f in folders]
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M")
    load_before = load_average()
    reference = [reference_workload()]
    # (kind, dataset) -> per round: (seconds, frames, CPU seconds, reference around the run)
    raw: dict[tuple[str, str], list[tuple[float, int, float, float]]] = {}
    for r in range(repeats):
        for source in sources:
            for kind, timer in ((FRONT_END, _time_front_end), (WHOLE_SYSTEM, _time_whole_system)):
                if progress:
                    log.info("round %d/%d: %s %s", r + 1, repeats, kind, source.name)
                seconds, frames_done, cpu = timer(source)
                reference.append(reference_workload())
                around = 0.5 * (reference[-2] + reference[-1])
                raw.setdefault((kind, source.name), []).append((seconds, frames_done, cpu, around))
    workloads = []
    for (kind, name), runs in raw.items():
        counts = {run[1] for run in runs}
        if len(counts) != 1:
            raise DatasetFormatError(f"{name}: rounds processed different frame counts {counts}")
        run_s, cpu_s, around_s = (tuple(run[i] for run in runs) for i in (0, 2, 3))
        workloads.append(WorkloadTiming(kind, name, counts.pop(), run_s, around_s, cpu_s))
    return SpeedResult(
        command=command,
        machine=machine_now(load_before, started),
        repeats=repeats,
        reference_s=tuple(reference),
        workloads=tuple(workloads),
    )
