"""Run metrics (speed, memory, map size) and the metrics.json file."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planeslam.core.bounded_parse import read_json_file
from planeslam.core.errors import EvaluationError
from planeslam.core.resources import peak_rss_mb
from planeslam.tracking.glitches import PoseGlitches

if TYPE_CHECKING:
    from planeslam.slam import SLAM, RunSummary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunMetrics:
    """What one run cost: the metrics.json keys, in this order."""

    frames: int
    """Frames processed."""
    fps: float
    """Frames processed per wall-clock second of processing (start-up excluded)."""
    frame_ms_median: float
    """Median wall-clock time of one frame [ms]."""
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Stage name -> median time per frame [ms]."""
    peak_rss_mb: float = 0.0
    """Peak resident set size of this (the main) process [MiB]."""
    backend_peak_rss_mb: float = 0.0
    """Peak resident set size of the backend's process [MiB] (0 when it runs inline)."""
    map_bytes: int = 0
    """Size of the high-level map as held in memory [bytes]."""
    fused_cloud_bytes: int = 0
    """Size of the point-cloud map the plane map stands in for: the frames' points fused
    with the estimated poses and voxel-downsampled at 1 cm, `point_bytes` per point."""
    memory_ratio: float | None = None
    """fused_cloud_bytes / map_bytes, the headline; None without a map."""
    pointcloud_bytes: int = 0
    """All processed frames' clouds merged, `point_bytes` per valid pixel (the paper's
    comparison; it grows with the number of frames)."""
    memory_ratio_merged: float | None = None
    """pointcloud_bytes / map_bytes, the paper's 'about 60x less memory'."""
    point_bytes: int = 15
    """Bytes per point of both clouds: float32 x, y, z and uint8 r, g, b."""
    map_counts: dict[str, int] = field(default_factory=dict)
    """Planes, edges, corners and objects in the map at the end."""
    lost_frames: int = 0
    """Frames whose pose could not be estimated (tracking lost, registration failed)."""
    tracked_fraction: float | None = None
    """Frames with a pose (in trajectory.txt) / frames processed; None when not known (a
    method that does not say). ATE is computed over the tracked frames only."""
    keyframes: int = 0
    """Frames that went into the map / the backend's graph (0 for methods without a map)."""
    tracking_paths: dict[str, int] = field(default_factory=dict)
    """How each frame's pose was found (tracking path -> frames), for methods that say."""
    map_bytes_breakdown: dict[str, int] = field(default_factory=dict)
    """map_bytes by part (planes, edges, corners, objects, sparse_cloud)."""
    final_poses: dict[str, float] = field(default_factory=dict)
    """Frames between keyframes re-estimated against the final map at the end
    ('reestimated'), left at their pose anchored on a keyframe ('kept'), and the 'ms' it
    took (`tracking.final_poses`; empty when it did not run)."""
    backend: dict[str, float] = field(default_factory=dict)
    """The iSAM2 backend's own figures, when it ran: update_ms_median and update_ms_max
    (per keyframe, in its process; the 'backend' stage is what tracking waited), batch_ms
    (the final optimisation), failures (indeterminate updates handled) and factors."""
    pose_glitches: dict[str, Any] = field(default_factory=dict)
    """Poses of trajectory.txt that jump away from the frames around them and back
    (`planeslam.tracking.glitches.PoseGlitches`: count, judged, timestamps and the
    thresholds); empty for methods without a trajectory."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def stage_medians(frame_timings: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Per-frame {stage: ms} dicts -> {stage: median ms over the frames that ran it},
    stages in first-seen order."""
    samples: dict[str, list[float]] = {}
    for timing in frame_timings:
        for stage, ms in timing.items():
            samples.setdefault(stage, []).append(float(ms))
    return {stage: float(np.median(values)) for stage, values in samples.items()}


def memory_ratio(map_bytes: int, pointcloud_bytes: int) -> float | None:
    """pointcloud_bytes / map_bytes, None when there is no map (map_bytes == 0)."""
    if map_bytes < 0 or pointcloud_bytes < 0:
        raise EvaluationError(
            f"byte counts must be >= 0, got map {map_bytes}, point cloud {pointcloud_bytes}"
        )
    return float(pointcloud_bytes) / float(map_bytes) if map_bytes > 0 else None


def run_metrics(
    frames: int,
    seconds: float,
    frame_timings: Sequence[Mapping[str, float]] = (),
    frame_ms: Sequence[float] | None = None,
    map_bytes: int = 0,
    pointcloud_bytes: int = 0,
    fused_cloud_bytes: int = 0,
    lost_frames: int = 0,
    keyframes: int = 0,
    tracking_paths: Mapping[str, int] | None = None,
    map_bytes_breakdown: Mapping[str, int] | None = None,
    backend: Mapping[str, float] | None = None,
    final_poses: Mapping[str, float] | None = None,
    backend_peak_rss_mb: float = 0.0,
    map_counts: Mapping[str, int] | None = None,
    tracked_fraction: float | None = None,
    pose_glitches: PoseGlitches | None = None,
) -> RunMetrics:
    """Build RunMetrics from a run's counts and timings.

    `seconds` is the wall-clock processing time (start-up excluded); `frame_timings` holds one
    {stage: ms} dict per frame; `frame_ms` the total ms per frame (default: the sum of each
    frame's stages, else seconds / frames). Peak RSS is read from this process.
    """
    if frames < 0 or not seconds >= 0:
        raise EvaluationError(f"need frames >= 0 and seconds >= 0, got {frames} and {seconds}")
    if frame_ms is None:
        frame_ms = [float(sum(t.values())) for t in frame_timings]
    if len(frame_ms):
        median_ms = float(np.median(np.asarray(frame_ms, dtype=np.float64)))
    else:
        median_ms = 1000.0 * seconds / frames if frames else 0.0
    return RunMetrics(
        frames=int(frames),
        fps=float(frames) / seconds if seconds > 0 else 0.0,
        frame_ms_median=median_ms,
        stage_ms=stage_medians(frame_timings),
        peak_rss_mb=peak_rss_mb(),
        backend_peak_rss_mb=float(backend_peak_rss_mb),
        map_bytes=int(map_bytes),
        fused_cloud_bytes=int(fused_cloud_bytes),
        memory_ratio=memory_ratio(map_bytes, fused_cloud_bytes),
        pointcloud_bytes=int(pointcloud_bytes),
        memory_ratio_merged=memory_ratio(map_bytes, pointcloud_bytes),
        map_counts=dict(map_counts or {}),
        lost_frames=int(lost_frames),
        tracked_fraction=None if tracked_fraction is None else float(tracked_fraction),
        keyframes=int(keyframes),
        tracking_paths=dict(tracking_paths or {}),
        map_bytes_breakdown={k: int(v) for k, v in (map_bytes_breakdown or {}).items()},
        final_poses=dict(final_poses or {}),
        backend=dict(backend or {}),
        pose_glitches={} if pose_glitches is None else pose_glitches.to_dict(),
    )


def slam_run_metrics(slam: SLAM, summary: RunSummary | None) -> RunMetrics:
    """RunMetrics of a `planeslam.slam.SLAM` run: speed and paths from its `RunSummary`
    (None for an interrupted run: frame count only), the map's bytes by part against the
    fused and the merged point clouds of the processed frames, the trajectory's glitches."""
    breakdown = slam.map.memory_bytes()
    result = slam.backend_result
    common: dict[str, Any] = dict(
        map_bytes=breakdown["total"],
        pointcloud_bytes=slam.pointcloud_bytes,
        fused_cloud_bytes=slam.fused_cloud_bytes,
        map_bytes_breakdown={k: v for k, v in breakdown.items() if k != "total"},
        map_counts={
            "planes": len(slam.map.planes),
            "edges": len(slam.map.edges),
            "corners": len(slam.map.corners),
            "objects": len(slam.map.objects),
        },
        backend_peak_rss_mb=result.peak_rss_mb if result is not None else 0.0,
        final_poses=slam.final_poses,
        tracked_fraction=slam.tracked_frames / slam.frames if slam.frames else None,
        pose_glitches=slam.pose_glitches(),
    )
    if summary is None:
        return run_metrics(frames=slam.frames, seconds=0.0, **common)
    return run_metrics(
        frames=summary.frames,
        seconds=summary.seconds,
        frame_timings=summary.frame_timings,
        lost_frames=slam.frames - slam.tracked_frames,  # segments joined later count
        keyframes=summary.keyframes,
        tracking_paths=summary.paths,
        backend=_backend_figures(slam),
        **common,
    )


def _backend_figures(slam: SLAM) -> dict[str, float]:
    result = slam.backend_result
    if result is None or not result.num_factors:  # no factor graph (the paper's merge)
        return {}
    update_ms = np.asarray(result.update_ms, dtype=np.float64)
    return {
        "update_ms_median": float(np.median(update_ms)) if update_ms.size else 0.0,
        "update_ms_max": float(update_ms.max()) if update_ms.size else 0.0,
        "batch_ms": float(result.batch_ms),
        "failures": int(result.failures),
        "factors": int(result.num_factors),
    }


METRICS_SCHEMA = "planeslam.metrics/1"
"""The `schema` key of metrics.json (its JSON Schema: `planeslam.schemas`)."""


def write_metrics(metrics: RunMetrics, path: str | Path) -> Path:
    """Write metrics.json (`schema`, then the keys of RunMetrics); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"schema": METRICS_SCHEMA, **metrics.to_dict()}
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    log.debug("wrote %s", path)
    return path


def read_metrics(path: str | Path) -> RunMetrics:
    """Read a metrics.json written by `write_metrics`."""
    path = Path(path)
    data = read_json_file(path, EvaluationError, what="metrics file")
    if not isinstance(data, dict):
        raise EvaluationError(f"{path}: not a metrics.json (expected a JSON object)")
    try:
        schema = data.pop("schema", METRICS_SCHEMA)  # files before the key had none
        if schema != METRICS_SCHEMA:
            raise EvaluationError(f"{path}: metrics schema {schema!r}, expected {METRICS_SCHEMA!r}")
        return RunMetrics(**data)
    except TypeError as exc:
        raise EvaluationError(f"{path}: not a metrics.json ({exc})") from None
