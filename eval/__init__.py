"""Trajectory evaluation, reports and the benchmark harness (installed as `planeslam.eval`).

The Open3D baseline lives in `planeslam.eval.baselines` (imported on demand: it loads Open3D).
"""

from .metrics import (
    RunMetrics,
    peak_rss_mb,
    run_metrics,
    stage_medians,
    write_metrics,
)
from .object_sizes import object_size_errors, object_size_errors_from_files
from .report import (
    EvaluationRun,
    evaluate_to_folder,
    write_evaluation,
    write_report,
)
from .trajectory_metrics import (
    EVAL_KEYS,
    TrajectoryEvaluation,
    evaluate_trajectory,
    format_table,
)

__all__ = [
    "EVAL_KEYS",
    "EvaluationRun",
    "RunMetrics",
    "TrajectoryEvaluation",
    "evaluate_to_folder",
    "evaluate_trajectory",
    "format_table",
    "object_size_errors",
    "object_size_errors_from_files",
    "peak_rss_mb",
    "run_metrics",
    "stage_medians",
    "write_evaluation",
    "write_metrics",
    "write_report",
]
