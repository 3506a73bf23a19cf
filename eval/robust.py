"""The robustness benchmark: procedural sequences split into a tuning and a validation set.

`benchmark_sequences()` is the fixed list: seeds 0..41, the trajectory kind of seed i
is TRAJECTORY_KINDS[i % 7], its texture TEXTURE_KINDS[i % 5] and its depth model
DEPTH_MODELS[i % 3] (the rest of the recipe is drawn from the seed); seeds whose
i // 7 is even are the tuning set, the others the validation set, so each set holds
every trajectory kind three times and every texture and depth model. Tune on the
tuning set; accept or reject a tracking change by the validation set's summary.

Per sequence, planeslam (the configured default backend) and Open3D's RGB-D odometry
run in the same job, one after the other, and each gets (`MethodFigures`):
- tracked fraction: frames with a pose / frames processed (Open3D: frames whose
  registration succeeded; a failed one repeats the last motion);
- ATE RMSE over the tracked frames (evo, SE(3) alignment, `evaluate_trajectory`;
  unaligned where the positions admit no alignment, a camera turning in place: both
  methods start at the true pose);
- false jump: the largest translation error of a frame-to-frame motion,
  |t(inv(dT_true) dT_est)| over consecutive tracked frames: a jump the truth does not
  have (alignment-free);
- relocalisations accepted (frames on the relocalisation path) and wrong ones: the
  pose relocalisation gave, mapped into the truth's frame by the run's ATE alignment,
  more than 10 cm or 5 deg from the truth;
- object size error against the truth's objects (`mean_object_size_error`), and the
  same over the furniture alone (the room left out: a partial view measures it only by
  the walls it saw);
- fps.
Beside them, the sequence's blind frames: frames whose noise-free image does not change
when the camera slides 5 cm along a world axis (`planeslam.sim.observability`), so that
no method reading the images can place them along it; a sequence blind on every frame
(one bare wall filling the view) is out of any such method's reach.
A sequence passes when it tracks >= 98 % of its frames with ATE <= 2 cm and no false
jump over 10 cm; planeslam is ahead of Open3D on it when it tracks at least Open3D's
fraction with a lower ATE.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.config import resolve_config
from planeslam.core.bounded_parse import MAX_JSON_BYTES, load_json, read_text
from planeslam.core.config import ConfigLayer
from planeslam.core.errors import ConfigError, EvaluationError
from planeslam.core.geometry import invert_pose
from planeslam.core.types import TrackingPath
from planeslam.io.sequence import open_dataset
from planeslam.io.trajectory import Trajectory, write_tum
from planeslam.sim.observability import count_blind_frames
from planeslam.sim.procedural import (
    DEPTH_MODELS,
    GENERATOR_VERSION,
    TEXTURE_KINDS,
    TRAJECTORY_KINDS,
    Recipe,
    draw_recipe,
    write_procedural,
)

from .executors import Job, run_here, run_in_processes, run_on_dask
from .object_sizes import mean_object_size_error, object_size_errors
from .report import FRAME_ERRORS_CSV, write_frame_errors
from .trajectory_metrics import TrajectoryEvaluation, evaluate_trajectory

log = logging.getLogger(__name__)

Split = Literal["tuning", "validation"]
SEQUENCE_COUNT = 42
"""Sequences of the benchmark: six of each trajectory kind, three in each set."""
PASS_TRACKED = 0.98
"""A passing sequence tracks at least this fraction of its frames."""
PASS_ATE_M = 0.02
"""... with an ATE of at most this [m] ..."""
PASS_JUMP_M = 0.10
"""... and no false jump over this [m]."""
ROOM_CLASS = "room"
"""The truth's class of the room around the furniture (left out of the furniture size error)."""
WRONG_RELOC_M = 0.10
"""A relocalisation farther than this from the aligned truth is wrong [m] ..."""
WRONG_RELOC_DEG = 5.0
"""... or turned more than this [deg]."""


@dataclass(frozen=True)
class BenchSequence:
    """One sequence of the benchmark and the set it belongs to."""

    recipe: Recipe
    split: Split
    max_frames: int | None = None
    """Render only the path's first frames (a quick look, tests); None: all."""


def benchmark_sequences(count: int = SEQUENCE_COUNT) -> list[BenchSequence]:
    """The fixed list (module docstring); `count` takes its first sequences."""
    if not 1 <= count <= 1000:
        raise ConfigError(f"count must be in [1, 1000], got {count}")
    k = len(TRAJECTORY_KINDS)
    return [
        BenchSequence(
            draw_recipe(
                i,
                trajectory=TRAJECTORY_KINDS[i % k],
                texture=TEXTURE_KINDS[i % len(TEXTURE_KINDS)],
                depth_model=DEPTH_MODELS[i % len(DEPTH_MODELS)],
            ),
            "tuning" if (i // k) % 2 == 0 else "validation",
        )
        for i in range(count)
    ]


@dataclass(frozen=True)
class MethodFigures:
    """One method's figures on one sequence (module docstring); None where not computed."""

    tracked_fraction: float | None = None
    ate_m: float | None = None
    false_jump_m: float | None = None
    relocalisations: int = 0
    wrong_relocalisations: int = 0
    object_size_error_m: float | None = None
    furniture_size_error_m: float | None = None
    """The same over the furniture alone (every true object but the room, which a partial
    view measures only by the walls it saw)."""
    fps: float | None = None
    error: str | None = None
    """One-line reason when the run or its evaluation failed."""

    @property
    def passed(self) -> bool:
        """Tracked >= 98 %, ATE <= 2 cm, no false jump over 10 cm."""
        return (
            self.error is None
            and self.tracked_fraction is not None
            and self.tracked_fraction >= PASS_TRACKED
            and self.ate_m is not None
            and self.ate_m <= PASS_ATE_M
            and self.false_jump_m is not None
            and self.false_jump_m <= PASS_JUMP_M
        )


@dataclass(frozen=True)
class RobustRow:
    """Both methods on one sequence."""

    name: str
    split: Split
    trajectory: str
    texture: str
    depth_model: str
    symmetric: bool
    frames: int
    planeslam: MethodFigures
    open3d: MethodFigures
    seconds: float = 0.0
    """Wall-clock time of the whole job (rendering included) [s]."""
    blind_frames: int = 0
    """Frames whose images leave the camera unplaced along a world axis (module
    docstring; rows written before the count have 0)."""

    @property
    def ahead_of_open3d(self) -> bool:
        """planeslam tracks at least Open3D's fraction with a lower ATE."""
        ours, theirs = self.planeslam, self.open3d
        if ours.ate_m is None or ours.tracked_fraction is None:
            return False
        if theirs.ate_m is None or theirs.tracked_fraction is None:
            return True
        return ours.tracked_fraction >= theirs.tracked_fraction and ours.ate_m < theirs.ate_m

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RobustRow:
        values = dict(data)
        for key in ("planeslam", "open3d"):
            values[key] = MethodFigures(**values[key])
        return cls(**{f.name: values[f.name] for f in fields(cls) if f.name in values})


# --------------------------------------------------------------------------- metrics


def false_jump_m(evaluation: TrajectoryEvaluation) -> float:
    """Largest translation error [m] of the motion between consecutive evaluated poses
    (`TrajectoryEvaluation.step_errors_m`, evo's RPE over one frame): a jump the truth does
    not have, independent of any alignment; 0 for fewer than two poses."""
    return float(np.max(evaluation.step_errors_m, initial=0.0))


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation [m], rotation [deg]) between two (4, 4) poses."""
    delta = invert_pose(T_a) @ T_b
    angle = np.rad2deg(Rotation.from_matrix(delta[:3, :3]).magnitude())
    return float(np.linalg.norm(delta[:3, 3])), float(angle)


def wrong_relocalisations(
    T_gt_est: np.ndarray, T_world_reloc: np.ndarray, T_world_truth: np.ndarray
) -> int:
    """How many relocalised poses (R, 4, 4), mapped into the truth's world by the (4, 4)
    alignment T_gt_est, lie over WRONG_RELOC_M or WRONG_RELOC_DEG from their (R, 4, 4)
    true poses."""
    wrong = 0
    for T_est, T_true in zip(T_world_reloc, T_world_truth, strict=True):
        metres, degrees = pose_error(T_true, T_gt_est @ T_est)
        wrong += metres > WRONG_RELOC_M or degrees > WRONG_RELOC_DEG
    return wrong


def method_figures(
    truth: Trajectory,
    estimate: Trajectory,
    frames: int,
    fps: float,
    relocalised: Trajectory | None = None,
    objects: list[dict[str, Any]] | None = None,
    truth_objects: Mapping[str, Any] | None = None,
) -> MethodFigures:
    """The figures of one run: `estimate` holds its tracked frames' poses (`frames`
    processed), `relocalised` the online poses of its relocalised frames, `objects` its
    map's objects (map.json schema) against `truth_objects` (truth.json)."""
    tracked = len(estimate) / frames if frames else 0.0
    relocs = 0 if relocalised is None else len(relocalised)
    base = MethodFigures(tracked_fraction=tracked, fps=fps, relocalisations=relocs)
    if objects is not None and truth_objects is not None:
        sizes = object_size_errors(objects, truth_objects)
        base = replace(
            base,
            object_size_error_m=mean_object_size_error(sizes),
            furniture_size_error_m=mean_object_size_error(
                [e for e in sizes if e["class"] != ROOM_CLASS]
            ),
        )
    try:
        ev = _evaluation(truth, estimate)
    except EvaluationError as exc:
        return replace(base, error=f"EvaluationError: {exc}")
    wrong = 0
    if relocalised is not None and len(relocalised):
        true_poses = np.array([_truth_at(truth, t) for t in relocalised.timestamps])
        wrong = wrong_relocalisations(ev.T_gt_est, relocalised.T_world_cam, true_poses)
    return replace(
        base,
        ate_m=ev.ate_rmse_m,
        false_jump_m=false_jump_m(ev),
        wrong_relocalisations=wrong,
    )


def _evaluation(truth: Trajectory, estimate: Trajectory) -> TrajectoryEvaluation:
    """`evaluate_trajectory` aligned, or unaligned where the positions admit no alignment
    (a camera turning in place: both methods start at the true pose)."""
    return evaluate_trajectory(truth, estimate, when_degenerate="none")


def _truth_at(truth: Trajectory, timestamp: float) -> np.ndarray:
    k = int(np.argmin(np.abs(truth.timestamps - timestamp)))
    return truth.T_world_cam[k]


# --------------------------------------------------------------------------- one job


def ensure_rendered(recipe: Recipe, data_dir: Path, max_frames: int | None = None) -> Path:
    """The recipe's dataset folder under `data_dir`, rendered unless it already holds
    this recipe from this generator version (truth.json's 'rendering' names both);
    `max_frames` renders only the first frames, into a folder of its own."""
    suffix = "" if max_frames is None else f"-first{max_frames}"
    root = data_dir / (recipe.name + suffix)
    truth_path = root / "truth.json"
    if truth_path.is_file():
        try:
            stored = json.loads(truth_path.read_text(encoding="utf-8"))["rendering"]
            made = (stored["recipe"], stored["generator_version"])
        except (OSError, ValueError, KeyError, TypeError):
            made = None
        if made == (recipe.record(), GENERATOR_VERSION):
            return root
    write_procedural(recipe, root, max_frames=max_frames)
    return root


def blind_frame_count(recipe: Recipe, root: Path, max_frames: int | None = None) -> int:
    """How many frames of `recipe`, rendered at `root` with its camera.yaml, are blind
    (`planeslam.sim.observability.count_blind_frames`, kept in root/sight.json)."""
    return count_blind_frames(recipe, root, resolve_config(root, None).camera, max_frames)


def _run_planeslam(
    root: Path, overrides: Sequence[ConfigLayer], run_dir: Path | None = None
) -> tuple[MethodFigures, int]:
    """planeslam on the sequence at `root`: its figures and frame count; with `run_dir`,
    its trajectory.txt and frame_errors.csv (each pose's error and its step's, beside the
    tracking path and reason: `write_frame_errors`) are written there."""
    from planeslam.slam import FrameResult, run_frames, slam_for_dataset

    config = resolve_config(root, None, overrides=overrides)
    dataset = open_dataset(root, config.camera, config.dataset)
    truth = dataset.groundtruth
    if truth is None:
        raise EvaluationError(f"{root}: no ground truth")
    relocs: list[tuple[float, np.ndarray]] = []
    records: list[dict[str, Any]] = []

    def note(result: FrameResult) -> None:
        records.append(result.to_record())  # as frames.jsonl holds it
        if result.path is TrackingPath.RELOCALISED:
            relocs.append((result.timestamp, result.T_world_cam.copy()))

    indices = list(range(len(dataset)))
    with slam_for_dataset(config, dataset, 0) as slam:
        summary = run_frames(slam, dataset, indices, on_result=note)
    truth_objects = json.loads((root / "truth.json").read_text(encoding="utf-8"))
    relocalised = Trajectory(
        np.array([t for t, _ in relocs], dtype=np.float64),
        np.array([T for _, T in relocs], dtype=np.float64).reshape(-1, 4, 4),
    )
    trajectory = slam.trajectory()
    figures = method_figures(
        truth,
        trajectory,
        summary.frames,
        summary.frames / summary.seconds if summary.seconds > 0 else 0.0,
        relocalised=relocalised,
        objects=slam.map.to_dict()["objects"],
        truth_objects=truth_objects,
    )
    if run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_tum(run_dir / "trajectory.txt", trajectory)
        if figures.error is None:
            write_frame_errors(_evaluation(truth, trajectory), run_dir / FRAME_ERRORS_CSV, records)
    return figures, summary.frames


def _run_open3d(root: Path) -> MethodFigures:
    from .baselines import run_open3d_odometry

    config = resolve_config(root, None)
    dataset = open_dataset(root, config.camera, config.dataset)
    if dataset.groundtruth is None:
        raise EvaluationError(f"{root}: no ground truth")
    result = run_open3d_odometry(dataset)
    # Frames whose registration failed keep an extrapolated pose: they count as not tracked.
    tracked = result.frames - result.lost_frames
    figures = method_figures(
        dataset.groundtruth,
        result.trajectory,
        result.frames,
        result.frames / result.seconds if result.seconds > 0 else 0.0,
    )
    return replace(figures, tracked_fraction=tracked / result.frames if result.frames else 0.0)


def _failure(exc: Exception) -> MethodFigures:
    message = str(exc).splitlines()[0] if str(exc) else ""
    return MethodFigures(error=f"{type(exc).__name__}: {message}")


def run_sequence(
    sequence: BenchSequence,
    data_dir: str,
    overrides: Sequence[ConfigLayer] = (),
    with_open3d: bool = True,
    runs_dir: str | None = None,
) -> RobustRow:
    """Render (once) and run one sequence with both methods; a method that fails gets
    its one-line error, never stopping the other. With `runs_dir`, planeslam's
    trajectory.txt and frame_errors.csv go to runs_dir/NAME/."""
    start = time.perf_counter()
    recipe = sequence.recipe
    root = ensure_rendered(recipe, Path(data_dir), sequence.max_frames)
    blind = blind_frame_count(recipe, root, sequence.max_frames)
    frames = 0
    try:
        run_dir = None if runs_dir is None else Path(runs_dir) / recipe.name
        ours, frames = _run_planeslam(root, overrides, run_dir)
    except Exception as exc:  # noqa: BLE001 - a failed run is a row of the table
        log.warning("%s: planeslam failed: %s", recipe.name, exc)
        ours = _failure(exc)
    theirs = MethodFigures()
    if with_open3d:
        try:
            theirs = _run_open3d(root)
        except Exception as exc:  # noqa: BLE001 - as above
            log.warning("%s: open3d odometry failed: %s", recipe.name, exc)
            theirs = _failure(exc)
    return RobustRow(
        name=recipe.name,
        split=sequence.split,
        trajectory=recipe.trajectory,
        texture=recipe.texture,
        depth_model=recipe.depth_model,
        symmetric=recipe.symmetric,
        frames=frames,
        planeslam=ours,
        open3d=theirs,
        seconds=time.perf_counter() - start,
        blind_frames=blind,
    )


# --------------------------------------------------------------------------- the benchmark


@dataclass(frozen=True)
class RobustResult:
    rows: list[RobustRow] = field(default_factory=list)
    seconds: float = 0.0
    """Wall-clock time of the whole benchmark [s]."""
    jobs: int = 1
    executor: str = "local"


def run_robust(
    out_dir: str | Path,
    sequences: Sequence[BenchSequence] | None = None,
    jobs: int = 1,
    executor: Literal["local", "dask"] = "local",
    scheduler: str | None = None,
    overrides: Sequence[ConfigLayer] = (),
    with_open3d: bool = True,
    on_row: Callable[[RobustRow], None] | None = None,
) -> RobustResult:
    """Run the benchmark's sequences (default: all) with `jobs` at once, locally or on
    Dask; each finished row is appended to out_dir/rows.jsonl (a stopped run keeps its
    rows) and passed to `on_row`; planeslam's trajectory.txt and frame_errors.csv of each
    sequence go to out_dir/runs/NAME/. Rows come back in list order."""
    if jobs < 1:
        raise ConfigError(f"jobs must be >= 1, got {jobs}")
    seqs = list(sequences if sequences is not None else benchmark_sequences())
    out = Path(out_dir)
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    rows_path.write_text("", encoding="utf-8")
    start = time.perf_counter()
    runs = str(out / "runs")
    job_list = [
        Job(run_sequence, (s, str(data), tuple(overrides), with_open3d, runs)) for s in seqs
    ]
    if executor == "dask":
        outcomes = run_on_dask(job_list, scheduler, jobs)
    elif jobs == 1:
        outcomes = run_here(job_list)
    else:
        outcomes = run_in_processes(job_list, jobs)
    rows: list[RobustRow | None] = [None] * len(seqs)
    for k, outcome in outcomes:
        if isinstance(outcome, RobustRow):
            row = outcome
        else:  # the worker died
            r = seqs[k].recipe
            failed = _failure(outcome)
            row = RobustRow(
                r.name,
                seqs[k].split,
                r.trajectory,
                r.texture,
                r.depth_model,
                r.symmetric,
                0,
                failed,
                failed,
            )
        rows[k] = row
        with open(rows_path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(row.to_dict()) + "\n")
        if on_row is not None:
            on_row(row)
    return RobustResult(
        rows=[r for r in rows if r is not None],
        seconds=time.perf_counter() - start,
        jobs=jobs,
        executor=executor,
    )


# --------------------------------------------------------------------------- summaries


@dataclass(frozen=True)
class GroupSummary:
    """A group of rows (a set, or a set's sequences of one kind)."""

    label: str
    sequences: int
    passed: int
    """Sequences planeslam passes (module docstring)."""
    ahead: int
    """Sequences where planeslam is ahead of Open3D."""
    open3d_passed: int
    tracked_median: float | None
    ate_median_m: float | None
    open3d_ate_median_m: float | None
    false_jumps: int
    """Sequences with a false jump over PASS_JUMP_M."""
    relocalisations: int
    wrong_relocalisations: int
    object_size_error_median_m: float | None
    furniture_size_error_median_m: float | None
    fps_median: float | None
    blind: int = 0
    """Sequences with a blind frame (module docstring)."""
    all_blind: int = 0
    """Sequences blind on every frame."""


def _median(values: Sequence[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.median(kept)) if kept else None


def summarise(label: str, rows: Sequence[RobustRow]) -> GroupSummary:
    ours = [r.planeslam for r in rows]
    return GroupSummary(
        label=label,
        sequences=len(rows),
        passed=sum(m.passed for m in ours),
        ahead=sum(r.ahead_of_open3d for r in rows),
        open3d_passed=sum(r.open3d.passed for r in rows),
        tracked_median=_median([m.tracked_fraction for m in ours]),
        ate_median_m=_median([m.ate_m for m in ours]),
        open3d_ate_median_m=_median([r.open3d.ate_m for r in rows]),
        false_jumps=sum(m.false_jump_m is not None and m.false_jump_m > PASS_JUMP_M for m in ours),
        relocalisations=sum(m.relocalisations for m in ours),
        wrong_relocalisations=sum(m.wrong_relocalisations for m in ours),
        object_size_error_median_m=_median([m.object_size_error_m for m in ours]),
        furniture_size_error_median_m=_median([m.furniture_size_error_m for m in ours]),
        fps_median=_median([m.fps for m in ours]),
        blind=sum(r.blind_frames > 0 for r in rows),
        all_blind=sum(r.frames > 0 and r.blind_frames >= r.frames for r in rows),
    )


def summaries(rows: Sequence[RobustRow]) -> dict[Split, list[GroupSummary]]:
    """Per set: the whole set first, then one group per trajectory kind, texture, depth
    model and symmetric scenes."""
    out: dict[Split, list[GroupSummary]] = {}
    for split in ("tuning", "validation"):
        in_set = [r for r in rows if r.split == split]
        if not in_set:
            continue
        groups = [summarise("all", in_set)]
        for attr, kinds in (
            ("trajectory", TRAJECTORY_KINDS),
            ("texture", TEXTURE_KINDS),
            ("depth_model", DEPTH_MODELS),
        ):
            for kind in kinds:
                members = [r for r in in_set if getattr(r, attr) == kind]
                if members:
                    groups.append(summarise(f"{attr} {kind}", members))
        symmetric = [r for r in in_set if r.symmetric]
        if symmetric:
            groups.append(summarise("symmetric scene", symmetric))
        out[split] = groups
    return out


def _fmt(value: float | None, spec: str, scale: float = 1.0) -> str:
    return "-" if value is None else format(value * scale, spec)


def summary_markdown(rows: Sequence[RobustRow]) -> str:
    """The per-set, per-kind summary tables."""
    head = (
        "| group | seqs | pass | ahead of Open3D | Open3D pass | tracked (median) "
        "| ATE median [cm] | Open3D ATE median [cm] | false jumps | relocs (wrong) "
        "| object size err [cm] | furniture size err [cm] | fps | with blind frames (all) |"
    )
    rule = "|" + "---|" * 14
    parts = []
    for split, groups in summaries(rows).items():
        body = [
            f"| {g.label} | {g.sequences} | {g.passed} | {g.ahead} | {g.open3d_passed} "
            f"| {_fmt(g.tracked_median, '.1%')} | {_fmt(g.ate_median_m, '.2f', 100)} "
            f"| {_fmt(g.open3d_ate_median_m, '.2f', 100)} | {g.false_jumps} "
            f"| {g.relocalisations} ({g.wrong_relocalisations}) "
            f"| {_fmt(g.object_size_error_median_m, '.1f', 100)} "
            f"| {_fmt(g.furniture_size_error_median_m, '.1f', 100)} | {_fmt(g.fps_median, '.1f')} "
            f"| {g.blind} ({g.all_blind}) |"
            for g in groups
        ]
        parts.append(f"**{split} set**\n\n" + "\n".join([head, rule, *body]))
    return "\n\n".join(parts) + "\n"


def read_rows(path: str | Path) -> list[RobustRow]:
    """The rows of an earlier run: its output folder or its rows.jsonl. ConfigError (one
    line, naming the file) when it is missing, unreadable or a line is not a row."""
    file = Path(path)
    if file.is_dir():
        file = file / "rows.jsonl"
    text = read_text(file, ConfigError, MAX_JSON_BYTES, "bench robust rows.jsonl")
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        if line.strip():
            data = load_json(line, f"{file}:{number}", ConfigError)
            try:
                rows.append(RobustRow.from_dict(data))
            except (TypeError, KeyError, AttributeError) as exc:
                raise ConfigError(f"{file}:{number}: not a bench robust row ({exc})") from None
    return rows


def changes_markdown(before: Sequence[RobustRow], after: Sequence[RobustRow]) -> str:
    """planeslam's figures of `after` against `before` on the sequences both ran: per set
    the sequences that pass, then each sequence whose tracked fraction (by 0.1 %), ATE (by
    0.01 cm), largest false jump or object size error (by 0.1 cm) moved."""
    earlier = {r.name: r for r in before}
    shared = [r for r in after if r.name in earlier]
    lines = []
    for split in ("tuning", "validation"):
        pairs = [(earlier[r.name].planeslam, r.planeslam) for r in shared if r.split == split]
        if pairs:
            passed = sum(b.passed for b, _ in pairs), sum(a.passed for _, a in pairs)
            lines.append(f"- {split} set: {passed[0]} -> {passed[1]} of {len(pairs)} pass")
    head = "| sequence | set | tracked | ATE [cm] | false jump [cm] | object size err [cm] | pass |"
    body = []
    for r in shared:
        b, a = earlier[r.name].planeslam, r.planeslam
        shown = [
            (_fmt(x, spec, scale), _fmt(y, spec, scale))
            for x, y, spec, scale in (
                (b.tracked_fraction, a.tracked_fraction, ".1%", 1.0),
                (b.ate_m, a.ate_m, ".2f", 100.0),
                (b.false_jump_m, a.false_jump_m, ".1f", 100.0),
                (b.object_size_error_m, a.object_size_error_m, ".1f", 100.0),
            )
        ]
        if all(x == y for x, y in shown):
            continue
        cells = [f"{x} -> {y}" for x, y in shown]
        verdict = f"{'yes' if b.passed else 'no'} -> {'yes' if a.passed else 'no'}"
        body.append(f"| {r.name} | {r.split} | " + " | ".join(cells) + f" | {verdict} |")
    table = [head, "|" + "---|" * 7, *body] if body else ["No sequence's figures moved."]
    return "\n".join(lines) + "\n\n" + "\n".join(table) + "\n"


def rows_markdown(rows: Sequence[RobustRow]) -> str:
    """One line per sequence: both methods' figures."""
    head = (
        "| sequence | set | frames | tracked | ATE [cm] | false jump [cm] | relocs (wrong) "
        "| object size err [cm] | furniture size err [cm] | fps | Open3D tracked "
        "| Open3D ATE [cm] | Open3D jump [cm] | blind frames | pass | error |"
    )
    rule = "|" + "---|" * 16
    body = []
    for r in rows:
        m, o = r.planeslam, r.open3d
        error = (m.error or o.error or "").replace("|", "/")[:80]
        body.append(
            f"| {r.name} | {r.split} | {r.frames} | {_fmt(m.tracked_fraction, '.1%')} "
            f"| {_fmt(m.ate_m, '.2f', 100)} | {_fmt(m.false_jump_m, '.1f', 100)} "
            f"| {m.relocalisations} ({m.wrong_relocalisations}) "
            f"| {_fmt(m.object_size_error_m, '.1f', 100)} "
            f"| {_fmt(m.furniture_size_error_m, '.1f', 100)} | {_fmt(m.fps, '.1f')} "
            f"| {_fmt(o.tracked_fraction, '.1%')} | {_fmt(o.ate_m, '.2f', 100)} "
            f"| {_fmt(o.false_jump_m, '.1f', 100)} | {r.blind_frames} "
            f"| {'yes' if m.passed else 'no'} | {error} |"
        )
    return "\n".join([head, rule, *body]) + "\n"
