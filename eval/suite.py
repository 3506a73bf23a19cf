"""Benchmark suite: every (sequence, method) pair in its own worker process, one table.

A suite YAML lists sequences (dataset folders with an optional config preset) and method
names; each method is looked up in `METHODS` and returns a trajectory and run metrics.
A run that fails is reported with its one-line error and never stops the others.
"""

from __future__ import annotations

import concurrent.futures
import csv
import json
import logging
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from planeslam.config import resolve_config
from planeslam.core.config import from_mapping, read_yaml
from planeslam.core.errors import ConfigError, EvaluationError
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import Trajectory, write_tum

from .metrics import RunMetrics, run_metrics, slam_run_metrics, write_metrics
from .object_sizes import mean_object_size_error, object_size_errors
from .trajectory_metrics import evaluate_trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SequenceSpec:
    """One dataset of the suite."""

    path: str = ""
    """Dataset folder (TUM layout); relative paths are relative to the suite file."""
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

    @property
    def name(self) -> str:
        """Row label: the folder name (or scene), with '/every<K>' when subsampled."""
        base = self.scene or Path(self.path).name
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
    core). More finish sooner but share the cores."""
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


Method = Callable[[TumDataset, SequenceSpec], MethodResult]
METHODS: dict[str, Method] = {}
"""Method name -> callable(dataset, sequence spec) -> MethodResult."""


def register_method(name: str) -> Callable[[Method], Method]:
    """Decorator adding a method to `METHODS` under `name`."""

    def add(fn: Method) -> Method:
        METHODS[name] = fn
        return fn

    return add


@register_method("open3d_odometry")
def _open3d_odometry(dataset: TumDataset, spec: SequenceSpec) -> MethodResult:
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
    def run(dataset: TumDataset, spec: SequenceSpec) -> MethodResult:
        from planeslam.slam import frame_indices, run_frames, slam_for_dataset

        config = resolve_config(dataset.root, spec.config)
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


@dataclass(frozen=True)
class SuiteResult:
    rows: list[SuiteRow] = field(default_factory=list)

    @property
    def failed(self) -> list[SuiteRow]:
        return [r for r in self.rows if r.error is not None]


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
    return config, path.parent


def sequence_root(spec: SequenceSpec, base_dir: str | Path, out_dir: str | Path | None) -> Path:
    """The dataset folder of a sequence: its path, or data/<scene> under the output folder."""
    if spec.scene is not None:
        return Path(out_dir or ".") / "data" / spec.scene
    return Path(base_dir) / spec.path


def render_scenes(config: SuiteConfig, out_dir: str | Path) -> None:
    """Render the synthetic scenes of a suite into out_dir/data once (seed 0), before the
    workers start, so that no two workers render the same scene."""
    from planeslam.sim.render import synthesize

    for spec in config.sequences:
        if spec.scene is not None:
            root = sequence_root(spec, ".", out_dir)
            if not (root / "truth.json").is_file():
                log.info("rendering %s into %s", spec.scene, root)
                synthesize(spec.scene, root, seed=0)


def run_job(
    spec: SequenceSpec,
    method: str,
    base_dir: str,
    out_dir: str | None,
    max_time_difference_s: float,
    rpe_delta_s: float,
) -> SuiteRow:
    """Run one method on one sequence and evaluate it; any exception becomes `error`."""
    start = time.perf_counter()
    root = sequence_root(spec, base_dir, out_dir)
    try:
        cfg = resolve_config(root, spec.config)
        dataset = TumDataset(root, cfg.camera, cfg.dataset)
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
            raise EvaluationError(f"{root}: no groundtruth.txt to evaluate against")
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
            truth = json.loads(truth_path.read_text(encoding="utf-8"))
            row["object_size_error_m"] = mean_object_size_error(
                object_size_errors(result.objects, truth)
            )
        return SuiteRow(
            sequence=spec.name, method=method, seconds=time.perf_counter() - start, **row
        )
    except Exception as exc:  # noqa: BLE001 - a failing job is reported, the suite goes on
        message = str(exc).splitlines()[0] if str(exc) else ""
        log.warning("%s / %s failed: %s: %s", spec.name, method, type(exc).__name__, message)
        return SuiteRow(
            sequence=spec.name,
            method=method,
            seconds=time.perf_counter() - start,
            error=f"{type(exc).__name__}: {message}",
        )


def run_suite(
    config: SuiteConfig,
    base_dir: str | Path = ".",
    out_dir: str | Path | None = None,
    on_row: Callable[[SuiteRow], None] | None = None,
) -> SuiteResult:
    """Run every (sequence, method) of `config` in worker processes ('spawn', so Open3D and
    OpenMP start clean in each); rows come back in config order. `on_row` sees each row as it
    finishes. With jobs == 1 everything runs in this process."""
    unknown = [m for m in config.methods if m not in METHODS]
    if unknown:
        raise ConfigError(f"unknown method(s) {', '.join(unknown)}; methods: {', '.join(METHODS)}")
    jobs = config.jobs or 1
    if jobs < 1:
        raise ConfigError(f"jobs must be >= 1, got {jobs}")
    tasks = [(spec, method) for spec in config.sequences for method in config.methods]
    args = (
        str(base_dir),
        None if out_dir is None else str(out_dir),
        config.max_time_difference_s,
        config.rpe_delta_s,
    )
    rows: list[SuiteRow | None] = [None] * len(tasks)
    if jobs == 1:
        for k, (spec, method) in enumerate(tasks):
            rows[k] = run_job(spec, method, *args)
            if on_row is not None:
                on_row(rows[k])  # type: ignore[arg-type]
    else:
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            max_workers=min(jobs, len(tasks)), mp_context=context
        ) as pool:
            futures = {
                pool.submit(run_job, spec, method, *args): k
                for k, (spec, method) in enumerate(tasks)
            }
            for future in concurrent.futures.as_completed(futures):
                k = futures[future]
                try:
                    rows[k] = future.result()
                except Exception as exc:  # noqa: BLE001 - a crashed worker is one failed row
                    spec, method = tasks[k]
                    rows[k] = SuiteRow(
                        sequence=spec.name,
                        method=method,
                        error=f"{type(exc).__name__}: worker failed ({exc})",
                    )
                if on_row is not None:
                    on_row(rows[k])  # type: ignore[arg-type]
    return SuiteResult(rows=[r for r in rows if r is not None])


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


def to_markdown(result: SuiteResult) -> str:
    """The suite as a markdown table."""
    head = "| " + " | ".join(title for _, title, _ in _COLUMNS) + " |"
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
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=names)
        writer.writeheader()
        for row in result.rows:
            writer.writerow({k: ("" if v is None else v) for k, v in asdict(row).items()})
    return path
