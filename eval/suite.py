"""Benchmark suite: every (sequence, method) pair as one job, one table.

A suite YAML lists sequences (dataset folders or ROS bags with an optional config preset)
and method names; each method is looked up in `METHODS` and returns a trajectory and run
metrics. Jobs run in this process, in worker processes, or on a Dask cluster
(`planeslam.eval.executors`); every row records when its job ran, so the table says how
many jobs shared the machine. A run that fails is reported with its one-line error and
never stops the others.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np

from planeslam.config import resolve_config
from planeslam.core.bounded_parse import read_json_file
from planeslam.core.config import from_mapping, read_yaml
from planeslam.core.errors import ConfigError, DatasetFormatError, EvaluationError
from planeslam.core.safe_files import atomic_output
from planeslam.io.sequence import RgbdDataset, open_dataset
from planeslam.io.trajectory import Trajectory, write_tum
from planeslam.sim.sequence import SynthOptions

from .executors import Job, run_here, run_in_processes, run_on_dask
from .metrics import RunMetrics, run_metrics, slam_run_metrics, write_metrics
from .object_sizes import mean_object_size_error, object_size_errors
from .trajectory_metrics import evaluate_trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SequenceSpec:
    """One dataset of the suite."""

    path: str = ""
    """Dataset folder (TUM layout) or ROS bag; relative paths are relative to the suite
    file."""
    scene: str | None = None
    """Instead of `path`: a synthetic scene (`planeslam synth`), rendered once into the
    suite's output folder (data/<scene>) with seed 0."""
    config: str | None = None
    """Preset name or YAML file; default: guessed from the folder name."""
    max_frames: int | None = None
    """Process at most this many frames (all when unset)."""
    every: int = 1
    """Use every `every`-th frame (keyframes far apart)."""
    optional: bool = False
    """Skip the sequence (with a note) when its folder does not exist, e.g. shared data."""
    synth: SynthOptions = field(default_factory=SynthOptions)
    """With `scene`: how to render it (depth noise model, field of view, camera height,
    texture; `planeslam.sim.render.SynthOptions`), into data/<scene>_<tag>."""

    @property
    def name(self) -> str:
        """Row label: the folder name (or scene, with '/<tag>' of a non-default rendering),
        with '/every<K>' when subsampled."""
        base = self.scene or Path(self.path).name
        base = f"{base}/{self.synth.tag}" if self.scene and self.synth.tag else base
        return base if self.every == 1 else f"{base}/every{self.every}"


@dataclass(frozen=True)
class SuiteConfig:
    """What a suite runs."""

    sequences: tuple[SequenceSpec, ...] = ()
    """Datasets to run every method on."""
    methods: tuple[str, ...] = ("open3d_odometry",)
    """Method names (keys of `planeslam.eval.suite.METHODS`)."""
    jobs: int | None = None
    """Runs at once, in worker processes; default 1, in this process: each run has the
    machine to itself, so its fps mean something (the iSAM2 backend takes the second
    core). More finish sooner but share the cores. With the dask executor and no
    scheduler: the LocalCluster's workers (default: one per core)."""
    executor: Literal["local", "dask"] = "local"
    """Where jobs run: 'local' (this machine: this process, or `jobs` worker processes) or
    'dask' (a Dask distributed cluster: `scheduler`, or a LocalCluster on this machine)."""
    scheduler: str | None = None
    """Dask scheduler address ('tcp://host:8786'); None: a LocalCluster on this machine."""
    max_time_difference_s: float = 0.02
    """Pose association window of the evaluation [s]."""
    rpe_delta_s: float = 1.0
    """RPE span [s]."""


@dataclass(frozen=True)
class MethodResult:
    """What a method returns for one sequence."""

    trajectory: Trajectory
    """Estimated T_world_cam per processed frame."""
    metrics: RunMetrics
    """Speed, memory and map size of the run."""
    objects: list[dict[str, Any]] | None = None
    """Estimated objects in the map schema, when the method builds objects."""


Method = Callable[[RgbdDataset, SequenceSpec], MethodResult]
METHODS: dict[str, Method] = {}
"""Method name -> callable(dataset, sequence spec) -> MethodResult."""


def register_method(name: str) -> Callable[[Method], Method]:
    """Decorator adding a method to `METHODS` under `name`."""

    def add(fn: Method) -> Method:
        METHODS[name] = fn
        return fn

    return add


@register_method("open3d_odometry")
def _open3d_odometry(dataset: RgbdDataset, spec: SequenceSpec) -> MethodResult:
    from .baselines import run_open3d_odometry

    result = run_open3d_odometry(dataset, max_frames=spec.max_frames, every=spec.every)
    metrics = run_metrics(
        frames=result.frames,
        seconds=result.seconds,
        frame_timings=result.frame_timings,
        lost_frames=result.lost_frames,
    )
    return MethodResult(trajectory=result.trajectory, metrics=metrics)


def _slam_method(backend: str) -> Method:
    def run(dataset: RgbdDataset, spec: SequenceSpec) -> MethodResult:
        from planeslam.slam import frame_indices, run_frames, slam_for_dataset

        config = resolve_config(dataset.root, spec.config)
        config = dataclasses.replace(config, camera=dataset.camera)  # a bag's camera_info
        indices = frame_indices(len(dataset), spec.max_frames, spec.every)
        with slam_for_dataset(config, dataset, indices[0], backend) as slam:
            summary = run_frames(slam, dataset, indices)
        metrics = slam_run_metrics(slam, summary)
        objects = slam.map.to_dict()["objects"]
        return MethodResult(trajectory=slam.trajectory(), metrics=metrics, objects=objects)

    return run


register_method("merge")(_slam_method("merge"))
register_method("isam2")(_slam_method("isam2"))


@dataclass(frozen=True)
class SuiteRow:
    """One (sequence, method) result; figures are None when the run failed or lacks them."""

    sequence: str
    method: str
    ate_rmse_m: float | None = None
    rpe_trans_m_per_s: float | None = None
    rpe_rot_deg_per_s: float | None = None
    fps: float | None = None
    memory_ratio: float | None = None
    object_size_error_m: float | None = None
    frames: int | None = None
    lost_frames: int | None = None
    seconds: float | None = None
    """Wall-clock time of the whole job, loading and evaluation included [s]."""
    error: str | None = None
    """One-line reason when the run failed."""
    executor: str | None = None
    """Where the job ran: 'local' or 'dask'."""
    jobs_at_once: int | None = None
    """Most jobs of the suite running at one time while this one ran (itself included)."""
    started_at: float | None = None
    """Wall-clock start of the job [s since the epoch, the worker's clock]."""
    finished_at: float | None = None
    """Wall-clock end of the job [s since the epoch, the worker's clock]."""


@dataclass(frozen=True)
class SuiteResult:
    rows: list[SuiteRow] = field(default_factory=list)
    executor: str = "local"
    """Where the jobs ran: 'local' or 'dask'."""

    @property
    def failed(self) -> list[SuiteRow]:
        return [r for r in self.rows if r.error is not None]

    @property
    def most_jobs_at_once(self) -> int:
        """Most jobs that ran at one time (1 when they ran one after the other)."""
        return max((r.jobs_at_once or 1 for r in self.rows), default=1)


def load_suite(path: str | Path) -> tuple[SuiteConfig, Path]:
    """Read a suite YAML -> (config, folder relative sequence paths resolve against)."""
    path = Path(path)
    config = from_mapping(SuiteConfig, read_yaml(path), str(path))
    unknown = [m for m in config.methods if m not in METHODS]
    if unknown:
        raise ConfigError(
            f"{path}: unknown method(s) {', '.join(unknown)}; methods: {', '.join(METHODS)}"
        )
    if not config.sequences:
        raise ConfigError(f"{path}: 'sequences' is empty (expected a list of {{path: ...}})")
    for k, spec in enumerate(config.sequences):
        if bool(spec.path) == (spec.scene is not None):
            raise ConfigError(f"{path}: sequences[{k}] needs exactly one of 'path' or 'scene'")
        if spec.every < 1:
            raise ConfigError(f"{path}: sequences[{k}].every must be >= 1, got {spec.every}")
        if spec.scene is None and spec.synth != SynthOptions():
            raise ConfigError(f"{path}: sequences[{k}].synth applies to a 'scene' only")
    return config, path.parent


def sequence_root(spec: SequenceSpec, base_dir: str | Path, out_dir: str | Path | None) -> Path:
    """The dataset folder of a sequence: its path, or data/<scene> under the output folder."""
    if spec.scene is not None:
        tag = spec.synth.tag
        return Path(out_dir or ".") / "data" / (f"{spec.scene}_{tag}" if tag else spec.scene)
    return Path(base_dir) / spec.path


def render_scenes(config: SuiteConfig, out_dir: str | Path) -> None:
    """Render the synthetic scenes of a suite into out_dir/data once (seed 0), before the
    workers start, so that no two workers render the same scene."""
    from planeslam.sim.sequence import render_sequence

    for spec in config.sequences:
        if spec.scene is not None:
            root = sequence_root(spec, ".", out_dir)
            if not (root / "truth.json").is_file():
                log.info("rendering %s into %s", spec.scene, root)
                render_sequence(spec.scene, root, spec.synth, seed=0)


def run_job(
    spec: SequenceSpec,
    method: str,
    base_dir: str,
    out_dir: str | None,
    max_time_difference_s: float,
    rpe_delta_s: float,
) -> SuiteRow:
    """Run one method on one sequence and evaluate it; any exception becomes `error`."""
    started_at = time.time()
    start = time.perf_counter()
    root = sequence_root(spec, base_dir, out_dir)
    try:
        cfg = resolve_config(root, spec.config)
        dataset = open_dataset(root, cfg.camera, cfg.dataset)
        result = METHODS[method](dataset, spec)
        row: dict[str, Any] = {
            "fps": result.metrics.fps,
            "memory_ratio": result.metrics.memory_ratio,
            "frames": result.metrics.frames,
            "lost_frames": result.metrics.lost_frames,
        }
        if out_dir is not None:
            run_dir = Path(out_dir) / spec.name.replace("/", "_") / method
            write_tum(run_dir / "trajectory.txt", result.trajectory)
            write_metrics(result.metrics, run_dir / "metrics.json")
        if dataset.groundtruth is None:
            raise EvaluationError(f"{root}: no ground truth to evaluate against")
        ev = evaluate_trajectory(
            dataset.groundtruth, result.trajectory, max_time_difference_s, rpe_delta_s
        )
        row.update(
            ate_rmse_m=ev.ate_rmse_m,
            rpe_trans_m_per_s=ev.rpe_trans_m_per_s,
            rpe_rot_deg_per_s=ev.rpe_rot_deg_per_s,
        )
        truth_path = root / "truth.json"
        if result.objects is not None and truth_path.is_file():
            truth = read_json_file(truth_path, DatasetFormatError, what="truth file")
            row["object_size_error_m"] = mean_object_size_error(
                object_size_errors(result.objects, truth)
            )
    except Exception as exc:  # noqa: BLE001 - a failing job is reported, the suite goes on
        message = str(exc).splitlines()[0] if str(exc) else ""
        log.warning("%s / %s failed: %s: %s", spec.name, method, type(exc).__name__, message)
        row = {"error": f"{type(exc).__name__}: {message}"}
    return SuiteRow(
        sequence=spec.name,
        method=method,
        seconds=time.perf_counter() - start,
        started_at=started_at,
        finished_at=time.time(),
        **row,
    )


def jobs_at_once(rows: list[SuiteRow]) -> list[int | None]:
    """Per row, the most rows whose [started_at, finished_at) overlapped at one instant of
    its own run (itself included); None for a row without times."""
    timed = [r for r in rows if r.started_at is not None and r.finished_at is not None]
    starts = np.array([r.started_at for r in timed], dtype=np.float64)
    ends = np.array([r.finished_at for r in timed], dtype=np.float64)
    # The number of running jobs rises only at starts, so it peaks at one: count there.
    running = ((starts[None, :] <= starts[:, None]) & (ends[None, :] > starts[:, None])).sum(1)
    result: list[int | None] = []
    for r in rows:
        if r.started_at is None or r.finished_at is None:
            result.append(None)
            continue
        inside = (starts >= r.started_at) & (starts < r.finished_at)
        inside |= starts == r.started_at
        result.append(int(running[inside].max()))
    return result


def run_suite(
    config: SuiteConfig,
    base_dir: str | Path = ".",
    out_dir: str | Path | None = None,
    on_row: Callable[[SuiteRow], None] | None = None,
) -> SuiteResult:
    """Run every (sequence, method) of `config` on its executor (`SuiteConfig.executor`);
    rows come back in config order, each with how many jobs ran at once beside it. `on_row`
    sees each row as it finishes. The local executor with jobs == 1 runs everything in this
    process, one job at a time."""
    unknown = [m for m in config.methods if m not in METHODS]
    if unknown:
        raise ConfigError(f"unknown method(s) {', '.join(unknown)}; methods: {', '.join(METHODS)}")
    if config.jobs is not None and config.jobs < 1:
        raise ConfigError(f"jobs must be >= 1, got {config.jobs}")
    if config.executor not in ("local", "dask"):
        raise ConfigError(f"executor must be 'local' or 'dask', got {config.executor!r}")
    if config.scheduler is not None and config.executor != "dask":
        raise ConfigError(f"a scheduler ({config.scheduler}) needs the dask executor")
    tasks = [(spec, method) for spec in config.sequences for method in config.methods]
    args = (
        str(base_dir),
        None if out_dir is None else str(out_dir),
        config.max_time_difference_s,
        config.rpe_delta_s,
    )
    jobs = [Job(run_job, (spec, method, *args)) for spec, method in tasks]
    if config.executor == "dask":
        outcomes = run_on_dask(jobs, config.scheduler, config.jobs)
    elif (config.jobs or 1) == 1:
        outcomes = run_here(jobs)
    else:
        outcomes = run_in_processes(jobs, config.jobs or 1)
    rows: list[SuiteRow | None] = [None] * len(tasks)
    for k, outcome in outcomes:
        if isinstance(outcome, SuiteRow):
            row = outcome
        else:  # the worker died or the cluster lost the job
            spec, method = tasks[k]
            row = SuiteRow(
                sequence=spec.name,
                method=method,
                error=f"{type(outcome).__name__}: worker failed ({outcome})",
            )
        rows[k] = dataclasses.replace(row, executor=config.executor)
        if on_row is not None:
            on_row(rows[k])  # type: ignore[arg-type]
    done = [r for r in rows if r is not None]
    done = [
        dataclasses.replace(r, jobs_at_once=n)
        for r, n in zip(done, jobs_at_once(done), strict=True)
    ]
    return SuiteResult(rows=done, executor=config.executor)


_COLUMNS = (
    ("sequence", "sequence", ""),
    ("method", "method", ""),
    ("ate_rmse_m", "ATE RMSE [m]", ".4f"),
    ("rpe_trans_m_per_s", "RPE [m/s]", ".4f"),
    ("rpe_rot_deg_per_s", "RPE [deg/s]", ".3f"),
    ("fps", "fps", ".2f"),
    ("memory_ratio", "memory ratio", ".1f"),
    ("object_size_error_m", "object size err [m]", ".4f"),
    ("lost_frames", "lost", ""),
    ("error", "error", ""),
)


def _cell(value: Any, spec: str) -> str:
    if value is None:
        return "-"
    return format(value, spec) if spec else str(value)


def timing_title(result: SuiteResult) -> str:
    """The fps column's title: which executor ran the jobs and how many ran at once
    ('fps (local, 1 at a time)', 'fps (dask, up to 2 at once)')."""
    n = result.most_jobs_at_once
    return f"fps ({result.executor}, {'1 at a time' if n == 1 else f'up to {n} at once'})"


def to_markdown(result: SuiteResult) -> str:
    """The suite as a markdown table; the fps column's title says how the jobs ran."""
    titles = [timing_title(result) if key == "fps" else title for key, title, _ in _COLUMNS]
    head = "| " + " | ".join(titles) + " |"
    rule = "|" + "|".join("---" for _ in _COLUMNS) + "|"
    body = [
        "| "
        + " | ".join(_cell(getattr(r, key), spec).replace("|", "/") for key, _, spec in _COLUMNS)
        + " |"
        for r in result.rows
    ]
    return "\n".join([head, rule, *body]) + "\n"


def write_csv(result: SuiteResult, path: str | Path) -> Path:
    """All SuiteRow fields as CSV (empty cells for missing values)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [f.name for f in fields(SuiteRow)]
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=names)
        writer.writeheader()
        for row in result.rows:
            writer.writerow({k: ("" if v is None else v) for k, v in asdict(row).items()})
    return path
