"""Evaluation outputs: eval.json, the plots, and report.html, one self-contained page
(figures embedded) that can be mailed or moved alone."""

from __future__ import annotations

import base64
import csv
import dataclasses
import html
import io
import json
import logging
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from planeslam import __version__
from planeslam.core.bounded_parse import (
    MAX_ABS_NUMBER,
    MAX_JSON_BYTES,
    check_tree,
    load_json,
    read_text,
)
from planeslam.core.errors import EvaluationError
from planeslam.core.safe_files import read_regular_file, write_text_atomic
from planeslam.io.trajectory import read_tum
from planeslam.mapping.world_map import Map
from planeslam.tracking.glitches import find_pose_glitches

from .object_sizes import object_size_errors_from_files, read_json
from .plots import plot_ate_over_time, plot_frame_timeline, plot_map_top_view, plot_trajectories
from .run_info import RUN_JSON, RunInfo, read_run_info
from .trajectory_metrics import TrajectoryEvaluation, evaluate_trajectory

log = logging.getLogger(__name__)

EVAL_JSON = "eval.json"
METRICS_JSON = "metrics.json"
TRAJECTORY_PNG = "trajectory.png"
ATE_PNG = "ate_over_time.png"
FRAME_ERRORS_CSV = "frame_errors.csv"
REPORT_HTML = "report.html"

FRAMES_JSONL = "frames.jsonl"
MAP_JSON = "map.json"
TRAJECTORY_TXT = "trajectory.txt"
MAP_PNG = "map.png"
TIMELINE_PNG = "frames.png"
MAX_PICTURE_BYTES = 64 << 20
"""A picture larger than this is not one of ours: it is not embedded."""

_LABELS = {
    "ate_rmse_m": "ATE RMSE",
    "ate_mean_m": "ATE mean",
    "ate_median_m": "ATE median",
    "ate_max_m": "ATE max",
    "rpe_trans_m_per_s": "RPE translation",
    "rpe_rot_deg_per_s": "RPE rotation",
    "pairs": "associated poses",
    "frames": "frames",
    "fps": "frames per second",
    "frame_ms_median": "median frame time",
    "peak_rss_mb": "peak memory (RSS)",
    "backend_peak_rss_mb": "backend process peak memory (RSS)",
    "map_bytes": "map size",
    "fused_cloud_bytes": "fused 1 cm point cloud",
    "pointcloud_bytes": "all frames' clouds merged",
    "memory_ratio": "point cloud / map",
    "memory_ratio_merged": "merged clouds / map",
    "point_bytes": "bytes per point",
    "lost_frames": "lost frames",
    "keyframes": "keyframes",
    "tracked_fraction": "frames tracked",
    "update_ms_median": "iSAM2 update per keyframe, median",
    "update_ms_max": "iSAM2 update per keyframe, max",
    "batch_ms": "final batch optimisation",
    "failures": "indeterminate updates handled",
    "factors": "factors in the graph",
    "rpe_delta_s": "RPE span",
    "rpe_delta_frames": "RPE span",
    "max_time_difference_s": "pose association window",
}
"""metrics.json / eval.json key -> row label; other keys show as their name."""

_UNITS = (  # unit word of a key (its last one, or 'ms' / 'mb' anywhere) -> unit, digits
    ("m_per_s", "m/s", 4),
    ("deg_per_s", "deg/s", 3),
    ("ms", "ms", 1),
    ("mb", "MiB", 1),
    ("mib", "MiB", 1),
    ("s", "s", 3),
    ("m", "m", 4),
    ("m2", "m²", 2),
    ("deg", "deg", 2),
)


def write_evaluation(
    evaluation: TrajectoryEvaluation,
    out_dir: str | Path,
    glitch_timestamps: np.ndarray | None = None,
    records: Sequence[Mapping[str, Any]] = (),
) -> dict[str, Path]:
    """Write eval.json, frame_errors.csv (`write_frame_errors`, with the run's `records`
    from frames.jsonl), trajectory.png and ate_over_time.png (with the poses at
    `glitch_timestamps` (G,) [s] marked, `glitches.find_pose_glitches`) into `out_dir`
    (created).

    Returns {"eval": ..., "frame_errors": ..., "trajectory_plot": ..., "ate_plot": ...}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(evaluation.to_dict(), indent=2) + "\n"
    eval_path = write_text_atomic(out / EVAL_JSON, text)
    paths = {
        "eval": eval_path,
        "frame_errors": write_frame_errors(evaluation, out / FRAME_ERRORS_CSV, records),
        "trajectory_plot": plot_trajectories(evaluation, out / TRAJECTORY_PNG),
        "ate_plot": plot_ate_over_time(evaluation, out / ATE_PNG, glitch_timestamps),
    }
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths


def write_frame_errors(
    evaluation: TrajectoryEvaluation,
    path: str | Path,
    records: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """frame_errors.csv: one row per evaluated pose, in time order: the estimate's
    timestamp [s], the aligned pose's translation [m] and rotation [deg] errors, the errors
    of the motion from the previous evaluated pose (empty on the first row), and, where a
    frames.jsonl record of the run has its timestamp (to the microsecond), the frame index,
    tracking path and reason. Written atomically; returns `path`."""
    by_stamp = {
        round(float(r["timestamp"]), 6): r
        for r in records
        if isinstance(r.get("timestamp"), (int, float))
    }
    steps = zip(evaluation.step_errors_m, evaluation.step_errors_deg, strict=True)
    step_cells = [("", ""), *((f"{m:.6f}", f"{deg:.4f}") for m, deg in steps)]
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(
        ["timestamp", "error_m", "error_deg", "step_error_m", "step_error_deg"]
        + ["frame", "path", "reason"]
    )
    for k, t in enumerate(evaluation.timestamps):
        record = by_stamp.get(round(float(t), 6), {})
        writer.writerow(
            [
                f"{t:.6f}",
                f"{evaluation.ate_errors_m[k]:.6f}",
                f"{evaluation.ate_rotation_errors_deg[k]:.4f}",
                *step_cells[k],
                *(record.get(key, "") for key in ("index", "path", "reason")),
            ]
        )
    return write_text_atomic(Path(path), table.getvalue())


def format_figure(key: str, value: Any) -> tuple[str, str]:
    """(text, unit) of one metric at a sensible precision, chosen by its key: metres to 0.1
    mm, milliseconds to 0.1 ms, MiB to 0.1 MiB, fps to 0.1 Hz, bytes as KB / MB / GB, a
    fraction as a percentage, a ratio to 1x, counts as integers."""
    if value is None:
        return "n/a", ""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value), ""
    if key.endswith("_bytes") or key == "bytes":
        return format_bytes(int(value)), ""
    if key.endswith("_fraction"):
        return f"{100.0 * value:.1f}", "%"
    if key == "fps":
        return f"{value:.1f}", "Hz"
    if key.endswith("_ratio"):
        return f"{value:.0f}", "x"
    words = key.split("_")
    for name, unit, digits in _UNITS:
        if key.endswith("_" + name) or (name in ("ms", "mb", "mib") and name in words[1:]):
            return f"{value:.{digits}f}", unit
    if isinstance(value, int) or float(value).is_integer():
        return f"{int(value)}", ""
    return f"{value:.4g}", ""


def format_bytes(n: int) -> str:
    """1690000 -> '1.69 MB' (decimal units, three significant figures)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("KB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def _row(label: str, text: str, unit: str | None = None) -> str:
    """A table row: label, value and (unless None) unit."""
    cells = f"<th>{html.escape(label)}</th><td>{html.escape(text)}</td>"
    return (
        f"<tr>{cells}<td>{html.escape(unit)}</td></tr>" if unit is not None else f"<tr>{cells}</tr>"
    )


def _table(data: Mapping[str, Any], keys: Sequence[str] | None = None, unit_word: str = "") -> str:
    """Rows of the scalar entries of `data` (those in `keys`, in that order, when given),
    formatted by key; `unit_word` ('ms', 'bytes') formats keys that are plain names."""
    rows = []
    for key in data if keys is None else [k for k in keys if k in data]:
        value = data[key]
        if isinstance(value, (dict, list)):
            continue
        label = _LABELS.get(key, key.replace("_", " "))
        rows.append(_row(label, *format_figure(f"{key}_{unit_word}" if unit_word else key, value)))
    return "<table>\n" + "\n".join(rows) + "\n</table>" if rows else ""


def _grid(head: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A table with a header row; cells are escaped."""
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "\n".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table>\n<tr>{th}</tr>\n{body}\n</table>"


def _largest_step_errors(path: Path, shown: int = 10) -> str:
    """The `shown` largest step errors of a frame_errors.csv (`write_frame_errors`) as a
    table, largest first: where the trajectory went wrong, and on which tracking path."""
    text = read_text(path, EvaluationError, MAX_JSON_BYTES, FRAME_ERRORS_CSV)
    rows = [r for r in csv.DictReader(io.StringIO(text)) if r.get("step_error_m")]
    try:
        steps = [
            (float(r["step_error_m"]), float(r["step_error_deg"]), float(r["error_m"]), r)
            for r in rows
        ]
    except (KeyError, TypeError, ValueError):
        raise EvaluationError(f"{path}: expected the columns of {FRAME_ERRORS_CSV}") from None
    steps.sort(key=lambda step: -step[0])
    head = ("frame", "path", "step error [cm]", "step error [deg]", "pose error [cm]")
    cells = [
        (
            r.get("frame") or "",
            r.get("path") or "",
            f"{100 * m:.1f}",
            f"{deg:.2f}",
            f"{100 * pose_m:.1f}",
        )
        for m, deg, pose_m, r in steps[:shown]
    ]
    return "<h3>Largest step errors</h3>\n" + _grid(head, cells)


def _object_table(errors: list[dict[str, Any]]) -> str:
    def sizes(v: Any) -> str:
        return "n/a" if v is None else " x ".join(f"{x:.3f}" for x in v)

    return _grid(
        ("class", "true id", "estimated id", "true size [m]", "estimated size [m]", "error [m]"),
        (
            (
                str(e.get("class")),
                format_figure("id", e.get("true_id"))[0],
                format_figure("id", e.get("estimated_id"))[0],
                sizes(e.get("true_size_m")),
                sizes(e.get("estimated_size_m")),
                format_figure("error_m", e.get("mean_abs_error_m"))[0],
            )
            for e in errors
        ),
    )


def _read_json(path: Path) -> dict[str, Any]:
    data = read_json(path)
    if not isinstance(data, dict):
        raise EvaluationError(f"{path}: expected a JSON object")
    return data


def read_frame_records(path: str | Path) -> list[dict[str, Any]]:
    """The records of a frames.jsonl (one JSON object a line). EvaluationError naming the
    file and line for anything else."""
    path = Path(path)
    records = []
    text = read_text(path, EvaluationError, MAX_JSON_BYTES, "frames.jsonl")
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        record = load_json(line, where, EvaluationError)
        check_tree(record, where, EvaluationError, MAX_ABS_NUMBER)
        if not isinstance(record, dict) or not {"index", "path"} <= record.keys():
            raise EvaluationError(f"{where}: expected an object with 'index' and 'path'")
        for key, (kinds, expected) in _RECORD_KEYS.items():
            value = record.get(key)
            if key in record and (not isinstance(value, kinds) or isinstance(value, bool)):
                raise EvaluationError(f"{where}: {key} must be {expected}, got {value!r:.40}")
        records.append(record)
    return records


_RECORD_KEYS: dict[str, tuple[Any, str]] = {
    "index": (int, "a whole number"),
    "timestamp": ((int, float), "a number"),
    "path": (str, "a string"),
}
"""Types of the frames.jsonl keys that readers use."""


def _image(path: Path, caption: str) -> str:
    """A PNG embedded as a data URI: the page needs no file beside it."""
    data = base64.b64encode(read_regular_file(path, MAX_PICTURE_BYTES)).decode("ascii")
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


def _header(info: RunInfo | None) -> str:
    generated = datetime.now(timezone.utc).isoformat(timespec="seconds")
    if info is None:
        rows = [_row("planeslam version", __version__)]
    else:
        rows = [
            _row("dataset", f"{info.dataset_name} ({info.dataset})"),
            _row("backend", info.backend),
            _row("command", info.command or "(called from Python)"),
            _row("planeslam version", info.version),
            _row("run started (UTC)", info.started_utc or "n/a"),
        ]
    rows.append(_row("report written (UTC)", generated))
    return '<table class="header">\n' + "\n".join(rows) + "\n</table>"


def _headline(evaluation: Mapping[str, Any], metrics: Mapping[str, Any]) -> str:
    """One line of the figures a reader looks for first."""
    parts = []
    for key, data in (
        ("ate_rmse_m", evaluation),
        ("fps", metrics),
        ("frames", metrics),
        ("keyframes", metrics),
        ("lost_frames", metrics),
        ("tracked_fraction", metrics),
        ("memory_ratio", metrics),
    ):
        if data.get(key) is not None:
            text, unit = format_figure(key, data[key])
            unit = "" if not unit else (unit if unit in ("%", "x") else f" {unit}")
            parts.append(f"<b>{html.escape(_LABELS.get(key, key))}</b> {text}{unit}")
    return f'<p class="headline">{" &middot; ".join(parts)}</p>' if parts else ""


def _tracking_section(metrics: Mapping[str, Any], records: list[dict[str, Any]]) -> str:
    paths = dict(metrics.get("tracking_paths") or {})
    if not paths:
        paths = Counter(str(r["path"]) for r in records)
    total = sum(paths.values())
    parts = []
    if paths:
        parts.append(
            _grid(
                ("tracking path", "frames", "share"),
                (
                    (name, str(n), f"{100.0 * n / total:.1f} %")
                    for name, n in sorted(paths.items(), key=lambda kv: -kv[1])
                ),
            )
        )
    parts.append(_table(metrics, ("keyframes", "lost_frames", "tracked_fraction")))
    lost = [r for r in records if r.get("path") == "lost"]
    if lost:
        shown = lost[:20]
        more = f" (the first 20 of {len(lost)})" if len(lost) > len(shown) else ""
        parts.append(f"<h3>Lost frames{more}</h3>")
        parts.append(
            _grid(
                ("frame", "time [s]", "reason"),
                (
                    (
                        str(r["index"]),
                        f"{float(r.get('timestamp', 0)):.3f}",
                        str(r.get("reason", "")),
                    )
                    for r in shown
                ),
            )
        )
    return "<h2>Tracking</h2>\n" + "\n".join(p for p in parts if p)


def _map_section(world_map: Map) -> str:
    counts = {
        "planes": len(world_map.planes),
        "real intersections": len(world_map.edges),
        "trihedral corners": len(world_map.corners),
        "objects": len(world_map.objects),
        "sparse points": len(world_map.sparse_points),
    }
    parts = ["<h2>Map</h2>", _table(counts)]
    if world_map.objects:
        parts.append(
            _grid(
                ("object", "class", "size [m]", "planes", "corners"),
                (
                    (
                        str(o.id),
                        o.cls,
                        " x ".join(f"{v:.3f}" for v in o.size_m) or "n/a",
                        str(len(o.planes)),
                        str(len(o.corners)),
                    )
                    for o in world_map.objects
                ),
            )
        )
    return "\n".join(parts)


_SHOWN_METRICS = (  # in this order when present; other scalars go to "Other figures"
    "frames",
    "fps",
    "frame_ms_median",
    "keyframes",
    "lost_frames",
    "tracked_fraction",
    "map_bytes",
    "fused_cloud_bytes",
    "memory_ratio",
    "pointcloud_bytes",
    "memory_ratio_merged",
    "peak_rss_mb",
    "backend_peak_rss_mb",
)


def write_report(
    out_dir: str | Path,
    title: str | None = None,
    groundtruth: str | Path | None = None,
) -> Path:
    """Write `out_dir`/report.html from the files of a run or evaluation folder, and the
    pictures it shows (map.png, frames.png). Uses, when present: run.json (header: dataset,
    backend, command, version, date), eval.json, metrics.json, frames.jsonl,
    frame_errors.csv (its largest step errors), map.json with trajectory.txt, and the
    ground truth (`groundtruth`, else the run's dataset's groundtruth.txt) for the map
    picture. The run's own pictures (map.png, frames.png,
    trajectory.png, ate_over_time.png; never through a symbolic link) are embedded: the
    page stands alone, with no scripts or external resources.

    Raises EvaluationError when neither eval.json nor metrics.json exists.
    """
    out = Path(out_dir)
    eval_path, metrics_path = out / EVAL_JSON, out / METRICS_JSON
    if not eval_path.is_file() and not metrics_path.is_file():
        raise EvaluationError(f"{out}: no {EVAL_JSON} or {METRICS_JSON} to report on")
    info = read_run_info(out) if (out / RUN_JSON).is_file() else None
    if title is None:
        title = f"planeslam {info.backend}: {info.dataset_name}" if info else "planeslam evaluation"
    evaluation = _read_json(eval_path) if eval_path.is_file() else {}
    metrics = _read_json(metrics_path) if metrics_path.is_file() else {}
    records = read_frame_records(out / FRAMES_JSONL) if (out / FRAMES_JSONL).is_file() else []
    gt_file = Path(groundtruth) if groundtruth is not None else None
    if gt_file is None:  # the dataset's; a bag's ground truth is kept beside the outputs
        beside = out / "groundtruth.txt"
        in_dataset = beside if info is None else Path(info.dataset) / "groundtruth.txt"
        gt_file = in_dataset if in_dataset.is_file() else beside
    gt = read_tum(gt_file) if gt_file.is_file() else None
    world_map = Map.load(out / MAP_JSON) if (out / MAP_JSON).is_file() else None

    sections = [_header(info), _headline(evaluation, metrics)]
    if world_map is not None:
        est_path = out / TRAJECTORY_TXT
        estimate = read_tum(est_path) if est_path.is_file() else None
        plot_map_top_view(world_map, out / MAP_PNG, estimate, gt)
        sections.append(
            "<h2>Top-down map</h2>\n"
            + _image(
                out / MAP_PNG,
                "planes coloured by object, objects with class and size "
                "[m], the estimated camera path against the ground truth (map frame)",
            )
        )
    if evaluation:
        keys = [k for k in evaluation if k != "object_size_errors"]
        sections.append("<h2>Trajectory</h2>\n" + _table(evaluation, keys))
        for name, caption in (
            (TRAJECTORY_PNG, "estimate aligned to the ground truth (SE(3), no scale)"),
            (ATE_PNG, "absolute trajectory error over time"),
        ):
            if (out / name).is_file():
                sections.append(_image(out / name, caption))
        if (out / FRAME_ERRORS_CSV).is_file():
            sections.append(_largest_step_errors(out / FRAME_ERRORS_CSV))
    if metrics or records:
        sections.append(_tracking_section(metrics, records))
    if records:
        plot_frame_timeline(records, out / TIMELINE_PNG)
        sections.append(_image(out / TIMELINE_PNG, "per frame: stage times and tracking path"))
    if metrics.get("backend"):
        sections.append("<h2>Backend</h2>\n" + _table(metrics["backend"]))
    if metrics:
        sections.append("<h2>Speed and memory</h2>\n" + _table(metrics, _SHOWN_METRICS))
        if metrics.get("stage_ms"):
            sections.append(
                "<h3>Median time per stage</h3>\n" + _table(metrics["stage_ms"], unit_word="ms")
            )
        if metrics.get("map_bytes_breakdown"):
            sections.append(
                "<h3>Map size by part</h3>\n"
                + _table(metrics["map_bytes_breakdown"], unit_word="bytes")
            )
        shown = {*_SHOWN_METRICS, "tracking_paths"}
        others = _table({k: v for k, v in metrics.items() if k not in shown})
        if others:
            sections.append("<h3>Other figures</h3>\n" + others)
    if world_map is not None:
        sections.append(_map_section(world_map))
    if evaluation.get("object_size_errors"):
        sections.append(
            "<h2>Object sizes against truth</h2>\n"
            + _object_table(evaluation["object_size_errors"])
        )
    page = f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1200px; }}
table {{ border-collapse: collapse; margin-bottom: 1em; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.75em; text-align: left; }}
td {{ font-variant-numeric: tabular-nums; }}
table.header th {{ background: #f4f4f4; }}
p.headline {{ font-size: 1.15em; }}
img {{ max-width: 100%; border: 1px solid #eee; }}
figure {{ margin: 1em 0; }}
</style>
</head>
<body>
<h1>{html.escape(title)}</h1>
{chr(10).join(s for s in sections if s)}
</body>
</html>
"""
    path = write_text_atomic(out / REPORT_HTML, page)
    log.info("wrote %s", path)
    return path


@dataclass(frozen=True)
class EvaluationRun:
    """What `evaluate_to_folder` computed and wrote."""

    evaluation: TrajectoryEvaluation
    """The figures (eval.json) and plot data."""
    paths: dict[str, Path]
    """Written files: eval, trajectory_plot, ate_plot, report."""
    warnings: tuple[str, ...] = ()
    """What could not be evaluated and why (a foreign or malformed truth.json found beside
    the ground truth)."""


def evaluate_to_folder(
    groundtruth: str | Path,
    estimate: str | Path,
    out_dir: str | Path | None = None,
    max_time_difference_s: float = 0.02,
    rpe_delta_s: float = 1.0,
    truth_json: str | Path | None = None,
    map_json: str | Path | None = None,
    tracked_fraction: float | None = None,
) -> EvaluationRun:
    """`planeslam eval GROUNDTRUTH ESTIMATE [--out DIR]` as one call.

    Evaluates the TUM files, adds object size errors when a truth.json (default: next to
    GROUNDTRUTH) and a map JSON with an 'objects' list (default: map.json next to ESTIMATE)
    both exist, then writes eval.json (with `tracked_fraction` when given: the share of
    the run's frames in ESTIMATE), the plots (ESTIMATE's pose glitches marked) and
    report.html into `out_dir` (default: the estimate's folder). A truth.json found there
    (not given) that cannot be used gives a warning in `EvaluationRun.warnings`, not an
    error; so does a ground truth whose positions admit no SE(3) alignment (a camera
    turning in place), evaluated after aligning the first poses instead.
    """
    gt_path, est_path = Path(groundtruth), Path(estimate)
    out = Path(out_dir) if out_dir is not None else est_path.parent
    evaluation = evaluate_trajectory(
        gt_path, est_path, max_time_difference_s, rpe_delta_s, when_degenerate="origin"
    )
    evaluation = dataclasses.replace(evaluation, tracked_fraction=tracked_fraction)
    truth = Path(truth_json) if truth_json is not None else gt_path.parent / "truth.json"
    objects = Path(map_json) if map_json is not None else est_path.parent / "map.json"
    warnings: list[str] = []
    if evaluation.alignment == "origin":
        warnings.append(
            f"{gt_path}: the ground truth's positions admit no SE(3) alignment (a camera "
            "turning in place?): ATE after aligning the first poses (evo's align_origin)"
        )
        log.warning("%s", warnings[-1])
    if truth.is_file() and objects.is_file():
        try:
            errors = object_size_errors_from_files(objects, truth)
            evaluation = dataclasses.replace(evaluation, object_size_errors=errors)
        except EvaluationError as exc:
            if truth_json is not None or map_json is not None:  # asked for: an error
                raise
            # Found beside the data, perhaps another tool's file: the rest still counts.
            warnings.append(f"object sizes not evaluated: {exc}")
            log.warning("%s", warnings[-1])
    elif truth_json is not None or map_json is not None:
        missing = truth if not truth.is_file() else objects
        raise EvaluationError(f"{missing}: not found (object sizes need truth.json and a map)")
    glitches = find_pose_glitches(read_tum(est_path))
    frames = est_path.parent / FRAMES_JSONL
    records: list[dict[str, Any]] = []
    if frames.is_file():
        try:
            records = read_frame_records(frames)
        except EvaluationError as exc:  # the figures do not need it
            warnings.append(f"frame_errors.csv without paths: {exc}")
            log.warning("%s", warnings[-1])
    paths = write_evaluation(evaluation, out, glitches.timestamps, records)
    paths["report"] = write_report(out, groundtruth=gt_path)
    return EvaluationRun(evaluation=evaluation, paths=paths, warnings=tuple(warnings))
