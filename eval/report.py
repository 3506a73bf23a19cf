"""Evaluation outputs: eval.json, the plots, and a static report.html tying them together."""

from __future__ import annotations

import dataclasses
import html
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from planeslam.core.errors import EvaluationError

from .object_sizes import object_size_errors_from_files, read_json
from .plots import plot_ate_over_time, plot_trajectories
from .trajectory_metrics import TrajectoryEvaluation, evaluate_trajectory

log = logging.getLogger(__name__)

EVAL_JSON = "eval.json"
METRICS_JSON = "metrics.json"
TRAJECTORY_PNG = "trajectory.png"
ATE_PNG = "ate_over_time.png"
REPORT_HTML = "report.html"

_LABELS = {
    "ate_rmse_m": ("ATE RMSE", "m"),
    "ate_mean_m": ("ATE mean", "m"),
    "ate_median_m": ("ATE median", "m"),
    "ate_max_m": ("ATE max", "m"),
    "rpe_trans_m_per_s": ("RPE translation", "m/s"),
    "rpe_rot_deg_per_s": ("RPE rotation", "deg/s"),
    "pairs": ("associated poses", ""),
    "frames": ("frames", ""),
    "fps": ("frames per second", "Hz"),
    "frame_ms_median": ("median frame time", "ms"),
    "peak_rss_mb": ("peak memory (RSS)", "MiB"),
    "map_bytes": ("map size", "bytes"),
    "pointcloud_bytes": ("point cloud size", "bytes"),
    "memory_ratio": ("point cloud / map", "x"),
    "lost_frames": ("lost frames", ""),
}


def write_evaluation(evaluation: TrajectoryEvaluation, out_dir: str | Path) -> dict[str, Path]:
    """Write eval.json, trajectory.png and ate_over_time.png into `out_dir` (created).

    Returns {"eval": ..., "trajectory_plot": ..., "ate_plot": ...} paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    eval_path = out / EVAL_JSON
    eval_path.write_text(json.dumps(evaluation.to_dict(), indent=2) + "\n", encoding="utf-8")
    paths = {
        "eval": eval_path,
        "trajectory_plot": plot_trajectories(evaluation, out / TRAJECTORY_PNG),
        "ate_plot": plot_ate_over_time(evaluation, out / ATE_PNG),
    }
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths


def _format(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.4f}" if abs(value) < 1e4 else f"{value:.0f}"
    return str(value)


def _table(data: dict[str, Any]) -> str:
    rows = []
    for key, value in data.items():
        if isinstance(value, (dict, list)):
            continue
        label, unit = _LABELS.get(key, (key, ""))
        rows.append(
            f"<tr><th>{html.escape(label)}</th><td>{html.escape(_format(value))}</td>"
            f"<td>{html.escape(unit)}</td></tr>"
        )
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def _stage_table(stage_ms: dict[str, float]) -> str:
    rows = [
        f"<tr><th>{html.escape(str(stage))}</th><td>{ms:.2f}</td><td>ms</td></tr>"
        for stage, ms in stage_ms.items()
    ]
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def _object_table(errors: list[dict[str, Any]]) -> str:
    def sizes(v: Any) -> str:
        return "n/a" if v is None else " x ".join(f"{x:.3f}" for x in v)

    head = (
        "<tr><th>class</th><th>true id</th><th>estimated id</th><th>true size [m]</th>"
        "<th>estimated size [m]</th><th>mean abs. error [m]</th></tr>"
    )
    rows = [
        "<tr>"
        + "".join(
            f"<td>{html.escape(c)}</td>"
            for c in (
                str(e.get("class")),
                _format(e.get("true_id")),
                _format(e.get("estimated_id")),
                sizes(e.get("true_size_m")),
                sizes(e.get("estimated_size_m")),
                _format(e.get("mean_abs_error_m")),
            )
        )
        + "</tr>"
        for e in errors
    ]
    return "<table>\n" + head + "\n" + "\n".join(rows) + "\n</table>"


def _read_json(path: Path) -> dict[str, Any]:
    data = read_json(path)
    if not isinstance(data, dict):
        raise EvaluationError(f"{path}: expected a JSON object")
    return data


def write_report(out_dir: str | Path, title: str = "planeslam evaluation") -> Path:
    """Write `out_dir`/report.html: the eval.json table, the metrics.json table (when present),
    object size errors (when present) and every PNG in `out_dir`, linked relatively.

    The page is static, with no scripts or external resources; move the folder and it
    still works. Raises EvaluationError when neither eval.json nor metrics.json exists.
    """
    out = Path(out_dir)
    eval_path, metrics_path = out / EVAL_JSON, out / METRICS_JSON
    if not eval_path.is_file() and not metrics_path.is_file():
        raise EvaluationError(f"{out}: no {EVAL_JSON} or {METRICS_JSON} to report on")
    sections: list[str] = []
    if eval_path.is_file():
        data = _read_json(eval_path)
        sections.append("<h2>Trajectory</h2>\n" + _table(data))
        if data.get("object_size_errors"):
            sections.append("<h2>Object sizes</h2>\n" + _object_table(data["object_size_errors"]))
    if metrics_path.is_file():
        metrics = _read_json(metrics_path)
        sections.append("<h2>Run</h2>\n" + _table(metrics))
        if metrics.get("stage_ms"):
            sections.append("<h3>Median time per stage</h3>\n" + _stage_table(metrics["stage_ms"]))
    known = [TRAJECTORY_PNG, ATE_PNG]
    pngs = [p for p in known if (out / p).is_file()]
    pngs += sorted(p.name for p in out.glob("*.png") if p.name not in known)
    if pngs:
        sections.append(
            "<h2>Plots</h2>\n"
            + "\n".join(
                f'<figure><img src="{html.escape(name)}" alt="{html.escape(name)}">'
                f"<figcaption>{html.escape(name)}</figcaption></figure>"
                for name in pngs
            )
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
img {{ max-width: 100%; border: 1px solid #eee; }}
figure {{ margin: 1em 0; }}
</style>
</head>
<body>
<h1>{html.escape(title)}</h1>
{chr(10).join(sections)}
</body>
</html>
"""
    path = out / REPORT_HTML
    path.write_text(page, encoding="utf-8")
    log.info("wrote %s", path)
    return path


@dataclass(frozen=True)
class EvaluationRun:
    """What `evaluate_to_folder` computed and wrote."""

    evaluation: TrajectoryEvaluation
    """The figures (eval.json) and plot data."""
    paths: dict[str, Path]
    """Written files: eval, trajectory_plot, ate_plot, report."""


def evaluate_to_folder(
    groundtruth: str | Path,
    estimate: str | Path,
    out_dir: str | Path | None = None,
    max_time_difference_s: float = 0.02,
    rpe_delta_s: float = 1.0,
    truth_json: str | Path | None = None,
    map_json: str | Path | None = None,
) -> EvaluationRun:
    """`planeslam eval GROUNDTRUTH ESTIMATE [--out DIR]` as one call.

    Evaluates the TUM files, adds object size errors when a truth.json (default: next to
    GROUNDTRUTH) and a map JSON with an 'objects' list (default: map.json next to ESTIMATE)
    both exist, then writes eval.json, the plots and report.html into `out_dir` (default:
    the estimate's folder).
    """
    gt_path, est_path = Path(groundtruth), Path(estimate)
    out = Path(out_dir) if out_dir is not None else est_path.parent
    evaluation = evaluate_trajectory(gt_path, est_path, max_time_difference_s, rpe_delta_s)
    truth = Path(truth_json) if truth_json is not None else gt_path.parent / "truth.json"
    objects = Path(map_json) if map_json is not None else est_path.parent / "map.json"
    if truth.is_file() and objects.is_file():
        errors = object_size_errors_from_files(objects, truth)
        evaluation = dataclasses.replace(evaluation, object_size_errors=errors)
    elif truth_json is not None or map_json is not None:
        missing = truth if not truth.is_file() else objects
        raise EvaluationError(f"{missing}: not found (object sizes need truth.json and a map)")
    paths = write_evaluation(evaluation, out)
    paths["report"] = write_report(out)
    return EvaluationRun(evaluation=evaluation, paths=paths)
