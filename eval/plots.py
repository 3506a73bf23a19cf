"""PNG plots of a run: trajectories (top and side view), ATE over time, a top-down map
picture and a per-frame timeline.

Figures are drawn on matplotlib `Figure` objects with the Agg canvas, never through
pyplot, so plotting needs no display and leaves no global state behind.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from planeslam.core.safe_files import atomic_output
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.records import MapPlane
from planeslam.mapping.world_map import Map

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
    with atomic_output(path) as tmp:  # never through a link planted at `path`
        fig.savefig(tmp, dpi=DPI, format="png")
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


def plot_ate_over_time(
    evaluation: TrajectoryEvaluation,
    path: str | Path,
    glitch_timestamps: np.ndarray | None = None,
) -> Path:
    """Translation error after alignment [m] against seconds from the first pose, as a PNG;
    the poses at `glitch_timestamps` (G,) [s] (`glitches.find_pose_glitches`) marked."""
    path = Path(path)
    seconds = evaluation.timestamps - evaluation.timestamps[0]
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax = fig.subplots()
    ax.plot(seconds, evaluation.ate_errors_m, color="tab:red", linewidth=1.2, label="error")
    if glitch_timestamps is not None and len(glitch_timestamps) and len(seconds):
        rows = np.abs(evaluation.timestamps[None, :] - np.asarray(glitch_timestamps)[:, None])
        nearest = np.argmin(rows, axis=1)
        ax.scatter(
            seconds[nearest],
            evaluation.ate_errors_m[nearest],
            marker="x",
            color="k",
            zorder=3,
            label=f"pose glitches ({len(glitch_timestamps)}; found without the truth)",
        )
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


def top_view_basis(up: np.ndarray | None, positions: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(2, 3) orthonormal rows spanning the ground plane of a top-down view, and the names
    of its two axes. With `up` (3,) near a world axis, the other two world axes (in index
    order); with `up` slanted, two unit vectors perpendicular to it; without `up`, the two
    axes of largest extent of (N, 3) `positions` (`view_axes`)."""
    eye = np.eye(3)
    if up is None:
        (i, j), _ = view_axes(positions if len(positions) > 1 else np.eye(3))
        return eye[[i, j]], [f"{AXIS_NAMES[i]} [m]", f"{AXIS_NAMES[j]} [m]"]
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    k = int(np.argmax(np.abs(up)))
    if abs(up[k]) > 0.9:
        i, j = (a for a in range(3) if a != k)
        return eye[[i, j]], [f"{AXIS_NAMES[i]} [m]", f"{AXIS_NAMES[j]} [m]"]
    e1 = np.cross(up, eye[int(np.argmin(np.abs(up)))])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)]), ["horizontal 1 [m]", "horizontal 2 [m]"]


MAX_OBJECT_LABELS = 8
"""Object labels on the map picture: the largest objects (by plane area) only."""
MAX_SPARSE_POINTS = 20000
"""Sparse-cloud points drawn on the map picture (an even subsample beyond this)."""


def plot_map_top_view(
    world_map: Map,
    path: str | Path,
    estimate: Trajectory | None = None,
    groundtruth: Trajectory | None = None,
) -> Path:
    """Top-down picture of a plane-object map (world frame, metres) as a PNG: the planes of
    objects as polygons coloured by object (`Map.plane_colors`), the other planes as thin
    grey outlines, the sparse cloud in grey dots, the largest
    objects labelled with class and size, and the estimated camera path (same world frame
    as the map) against the ground truth over the same time span. Looks down the map's up
    vector when it is known."""
    path = Path(path)
    est = estimate.positions if estimate is not None and len(estimate) else np.zeros((0, 3))
    gt = groundtruth.positions if groundtruth is not None and len(groundtruth) else est[:0]
    if len(est) and len(gt):  # the ground truth of the frames the run processed
        assert estimate is not None and groundtruth is not None
        t = groundtruth.timestamps
        gt = gt[(t >= estimate.timestamps[0] - 0.05) & (t <= estimate.timestamps[-1] + 0.05)]
    planes = world_map.planes
    outlines = [p.outline for p in planes.values() if len(p.outline) >= 3]
    everything = np.concatenate([est, gt, *outlines]) if outlines else np.concatenate([est, gt])
    up = world_map.gravity_up
    basis, names = top_view_basis(up, everything)
    colors = {pid: c / 255.0 for pid, c in world_map.plane_colors().items()}

    fig = Figure(figsize=(9, 8), layout="constrained")
    ax: Any = fig.subplots()
    sparse = world_map.sparse_points
    if len(sparse):
        step = max(1, len(sparse) // MAX_SPARSE_POINTS)
        xy = sparse[::step] @ basis.T
        ax.scatter(xy[:, 0], xy[:, 1], s=0.5, c="0.6", alpha=0.5, linewidths=0, zorder=1)

    def flatness(p: MapPlane) -> float:  # horizontal planes (floor, tables) drawn first
        return 0.0 if up is None else -abs(float(p.normal @ up))

    in_objects = {k for o in world_map.objects for k in o.planes}
    for p in sorted(planes.values(), key=lambda p: (flatness(p), -p.area_m2)):
        if len(p.outline) < 3:
            continue
        xy = p.outline @ basis.T
        if p.id not in in_objects:  # context only: a thin grey outline
            ax.fill(xy[:, 0], xy[:, 1], fill=False, edgecolor="0.6", linewidth=0.5, zorder=2)
            continue
        horizontal = up is not None and abs(float(p.normal @ up)) > 0.9
        ax.fill(
            xy[:, 0],
            xy[:, 1],
            facecolor=(*colors[p.id], 0.12 if horizontal else 0.35),
            edgecolor=colors[p.id],
            linewidth=1.0 if horizontal else 2.0,
            zorder=3 if horizontal else 4,
        )

    objects = sorted(
        world_map.objects,
        key=lambda o: -sum(planes[k].area_m2 for k in o.planes if k in planes),
    )
    for obj in objects[:MAX_OBJECT_LABELS]:
        pts = [planes[k].outline for k in obj.planes if k in planes and len(planes[k].outline)]
        if not pts:
            continue
        centre = np.concatenate(pts).mean(axis=0) @ basis.T
        size = " x ".join(f"{v:.2f}" for v in obj.size_m)
        colour = colors[obj.planes[0]] if obj.planes[0] in colors else (0.2, 0.2, 0.2)
        ax.annotate(
            f"{obj.cls} {obj.id}\n{size} m" if size else f"{obj.cls} {obj.id}",
            centre,
            fontsize="x-small",
            ha="center",
            va="center",
            zorder=7,
            bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": colour},
        )

    if len(gt):
        xy = gt @ basis.T
        ax.plot(xy[:, 0], xy[:, 1], zorder=5, **GT_STYLE)
    if len(est):
        xy = est @ basis.T
        ax.plot(xy[:, 0], xy[:, 1], zorder=6, color="tab:blue", linewidth=1.5, label="estimate")
        ax.plot(xy[0, 0], xy[0, 1], "o", color="tab:green", zorder=6, label="start")
    ax.set_xlabel(names[0])
    ax.set_ylabel(names[1])
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    if len(est) or len(gt):
        ax.legend(loc="best", fontsize="small")
    classes = sorted({o.cls for o in world_map.objects})
    ax.set_title(
        f"top-down map: {len(planes)} planes, {len(world_map.objects)} objects"
        + (f" ({', '.join(classes)})" if classes else "")
        + ("" if up is not None else "; up unknown: the two widest axes")
    )
    return _save(fig, path)


def plot_frame_timeline(records: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Per frame of a run (`frames.jsonl` records): the stage times stacked [ms] above, and
    below how tracking found the pose, with keyframes and lost frames marked; as a PNG."""
    path = Path(path)
    index = np.array([int(r["index"]) for r in records])
    stages: list[str] = []
    for r in records:
        stages += [s for s in r.get("stage_ms", {}) if s not in stages]
    ms = np.array([[float(r.get("stage_ms", {}).get(s, 0.0)) for r in records] for s in stages])
    fig = Figure(figsize=(11, 6), layout="constrained")
    ax_ms, ax_path = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    if stages:
        ax_ms.stackplot(index, ms.reshape(len(stages), -1), labels=stages, linewidth=0)
        ax_ms.legend(loc="upper left", fontsize="x-small", ncol=min(6, len(stages)))
    ax_ms.set_ylabel("time per frame [ms]")
    ax_ms.set_title("frame time by stage, and how tracking found each pose")
    ax_ms.grid(True, alpha=0.3)

    paths = [str(r["path"]) for r in records]
    names = list(dict.fromkeys(paths))
    rows = {name: k for k, name in enumerate(names)}
    y = np.array([rows[p] for p in paths])
    lost = np.array([p == "lost" for p in paths])
    keyframe = np.array([bool(r.get("keyframe")) for r in records])
    ax_path.scatter(index[~lost], y[~lost], s=6, c="tab:blue", label="tracked")
    ax_path.scatter(index[lost], y[lost], s=14, c="tab:red", marker="x", label="lost")
    kf_row = len(names)
    ax_path.scatter(
        index[keyframe], np.full(keyframe.sum(), kf_row), s=20, c="k", marker="|", label="keyframe"
    )
    ax_path.set_yticks(range(len(names) + 1), [*names, "keyframe"])
    ax_path.set_ylim(-0.5, len(names) + 0.5)
    ax_path.set_xlabel("frame")
    ax_path.grid(True, axis="x", alpha=0.3)
    return _save(fig, path)
