"""PNG plots of an evaluation: trajectories (top and side view) and ATE over time.

Figures are drawn on matplotlib `Figure` objects with the Agg canvas, never through
pyplot, so plotting needs no display and leaves no global state behind.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .trajectory_metrics import TrajectoryEvaluation

log = logging.getLogger(__name__)

AXIS_NAMES = ("x", "y", "z")
GT_STYLE = {"color": "0.25", "linestyle": "--", "linewidth": 1.5, "label": "ground truth"}
EST_STYLE = {"color": "tab:blue", "linewidth": 1.5, "label": "estimate (aligned)"}
DPI = 110


def view_axes(positions: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """Axis indices of the top view and the side view for (N, 3) positions [m].

    Top view: the two world axes with the largest extent (so a camera-style world with y
    down shows x-z, a z-up world shows x-y), in index order. Side view: the axis of
    largest extent against the remaining (smallest-extent) one.
    """
    extent = np.ptp(np.asarray(positions, dtype=np.float64), axis=0)
    order = np.argsort(-extent, kind="stable")
    top = tuple(sorted((int(order[0]), int(order[1]))))
    side = (int(order[0]), int(order[2]))
    return top, side  # type: ignore[return-value]


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=DPI)
    log.debug("wrote %s", path)
    return path


def _draw_view(ax, gt: np.ndarray, est: np.ndarray, axes: tuple[int, int], title: str) -> None:
    i, j = axes
    marker = "." if len(gt) <= 60 else None  # show the poses of short clips
    ax.plot(gt[:, i], gt[:, j], marker=marker, **GT_STYLE)
    ax.plot(est[:, i], est[:, j], marker=marker, **EST_STYLE)
    ax.plot(gt[0, i], gt[0, j], "o", color="tab:green", label="start")
    ax.set_xlabel(f"{AXIS_NAMES[i]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[j]} [m]")
    ax.set_title(title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def plot_trajectories(evaluation: TrajectoryEvaluation, path: str | Path) -> Path:
    """Top and side view of the associated ground-truth and aligned estimated camera
    centres (ground-truth world frame, metres) as one PNG; returns its path."""
    path = Path(path)
    gt = evaluation.T_world_gt[:, :3, 3]
    est = evaluation.T_world_est_aligned[:, :3, 3]
    top, side = view_axes(gt)
    fig = Figure(figsize=(11, 5), layout="constrained")
    ax_top, ax_side = fig.subplots(1, 2)
    top_name = f"{AXIS_NAMES[top[0]]}-{AXIS_NAMES[top[1]]}"
    side_name = f"{AXIS_NAMES[side[0]]}-{AXIS_NAMES[side[1]]}"
    _draw_view(ax_top, gt, est, top, f"top view ({top_name}: the two axes of largest extent)")
    _draw_view(ax_side, gt, est, side, f"side view ({side_name})")
    fig.suptitle(
        f"trajectory: ATE RMSE {evaluation.ate_rmse_m:.4f} m over {evaluation.pairs} poses"
    )
    return _save(fig, path)


def plot_ate_over_time(evaluation: TrajectoryEvaluation, path: str | Path) -> Path:
    """Translation error after alignment [m] against seconds from the first pose, as a PNG."""
    path = Path(path)
    seconds = evaluation.timestamps - evaluation.timestamps[0]
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax = fig.subplots()
    ax.plot(seconds, evaluation.ate_errors_m, color="tab:red", linewidth=1.2, label="error")
    ax.axhline(
        evaluation.ate_rmse_m,
        color="0.3",
        linestyle="--",
        label=f"RMSE {evaluation.ate_rmse_m:.4f} m",
    )
    ax.axhline(
        evaluation.ate_median_m,
        color="0.6",
        linestyle=":",
        label=f"median {evaluation.ate_median_m:.4f} m",
    )
    ax.set_xlabel("time from first pose [s]")
    ax.set_ylabel("absolute translation error [m]")
    ax.set_title("absolute trajectory error over time (after SE(3) alignment)")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    return _save(fig, path)
