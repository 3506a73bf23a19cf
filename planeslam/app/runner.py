"""`planeslam run`: SLAM over a dataset folder with every output written as it is produced.

Output folder:
- config.yaml      the resolved configuration (written first);
- trajectory.txt   TUM poses, one row per frame as it is tracked (an interrupted run keeps
                   them), rewritten at the end with the optimised poses;
- frames.jsonl     one record per frame: tracking path, reason, keyframe, stage ms;
- map.json         the plane-object map (schema planeslam.map/1, world frame), map.ply;
- metrics.json     speed, memory (map against point cloud, with the breakdown), lost frames;
- eval.json, trajectory.png, ate_over_time.png, report.html  when groundtruth.txt exists.
The final files are also written when the run is interrupted (Ctrl-C), from the frames
processed so far.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from planeslam.app.progress import progress_bar
from planeslam.config import RunConfig, resolve_config
from planeslam.core.config import save_yaml
from planeslam.core.errors import ConfigError
from planeslam.eval.metrics import RunMetrics, slam_run_metrics, write_metrics
from planeslam.eval.report import EvaluationRun, evaluate_to_folder, write_report
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import TumWriter, write_tum
from planeslam.slam import (
    SLAM,
    FrameResult,
    RunSummary,
    frame_indices,
    run_frames,
    slam_for_dataset,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunResult:
    """What `run_sequence` wrote and measured."""

    out_dir: Path
    summary: RunSummary
    metrics: RunMetrics
    evaluation: EvaluationRun | None
    """None without ground truth."""

    def text(self) -> str:
        """A few lines for the terminal."""
        m, s = self.metrics, self.summary
        paths = ", ".join(f"{k} {v}" for k, v in sorted(s.paths.items()))
        lines = [
            f"{m.frames} frames ({m.keyframes} keyframes, {m.lost_frames} lost) at "
            f"{m.fps:.1f} fps; tracking: {paths}",
            f"map {m.map_bytes} bytes vs point cloud {m.pointcloud_bytes} bytes "
            f"({m.memory_ratio or 0:.0f}x smaller)",
        ]
        if m.backend:
            b = m.backend
            lines.append(
                f"iSAM2: {b['factors']:.0f} factors, update median "
                f"{b['update_ms_median']:.0f} ms (max {b['update_ms_max']:.0f}) per keyframe, "
                f"final batch {b['batch_ms']:.0f} ms, {b['failures']:.0f} failures handled"
            )
        if self.evaluation is not None:
            ev = self.evaluation.evaluation
            rpe = (
                f"RPE {ev.rpe_trans_m_per_s:.4f} m/s {ev.rpe_rot_deg_per_s:.3f} deg/s"
                if ev.rpe_trans_m_per_s is not None
                else "RPE not computed (sequence shorter than the RPE span)"
            )
            lines.append(f"ATE RMSE {ev.ate_rmse_m:.4f} m, {rpe} over {ev.pairs} poses")
        lines.append(f"outputs in {self.out_dir} (open report.html)")
        return "\n".join(lines)


def run_sequence(
    dataset_dir: str | Path,
    out_dir: str | Path,
    config: str | Path | None = None,
    camera: str | None = None,
    backend: str | None = None,
    max_frames: int | None = None,
    every: int | None = None,
    progress: bool = False,
    seed: int | None = None,
) -> RunResult:
    """Run SLAM on a TUM-layout folder and write the outputs listed in the module docstring.
    `backend`, `max_frames`, `every` and `seed` override the config's `run` section; the
    saved config.yaml holds the values used."""
    root = Path(dataset_dir)
    out = Path(out_dir)
    cfg = resolve_config(root, config, camera)
    run = RunConfig(
        backend=cfg.run.backend if backend is None else backend,  # type: ignore[arg-type]
        seed=cfg.run.seed if seed is None else seed,
        every=cfg.run.every if every is None else every,
        max_frames=cfg.run.max_frames if max_frames is None else max_frames,
    )
    cfg = dataclasses.replace(cfg, run=run)
    backend = run.backend
    dataset = TumDataset(root, cfg.camera, cfg.dataset)
    indices = frame_indices(len(dataset), run.max_frames, run.every)
    if not indices:
        raise ConfigError(f"{root}: no frames to process")
    out.mkdir(parents=True, exist_ok=True)
    save_yaml(cfg, out / "config.yaml")
    slam = slam_for_dataset(cfg, dataset, indices[0])
    summary: RunSummary | None = None
    with (
        slam,
        progress_bar(len(indices), f"{backend} {root.name}", "frame", enabled=progress) as bar,
        TumWriter(out / "trajectory.txt", header=f"planeslam {backend} online") as writer,
        open(out / "frames.jsonl", "w", encoding="utf-8") as frames_fh,
    ):

        def on_result(result: FrameResult) -> None:
            writer.write(result.timestamp, result.T_world_cam)
            frames_fh.write(json.dumps(result.to_record()) + "\n")
            frames_fh.flush()
            bar.step(result.path.value)

        try:
            summary = run_frames(slam, dataset, indices, on_result)
        finally:
            if summary is None:  # interrupted or failed: keep what was computed
                logger.warning("run stopped after %d frames; writing what it has", slam.frames)
                _write_final(slam, out, backend, None)
    assert summary is not None
    metrics = _write_final(slam, out, backend, summary)
    evaluation = None
    if dataset.groundtruth is not None:
        evaluation = evaluate_to_folder(
            root / "groundtruth.txt", out / "trajectory.txt", out, cfg.dataset.max_time_difference_s
        )
    else:
        write_report(out, title=f"planeslam {backend}: {root.name}")
    return RunResult(out_dir=out, summary=summary, metrics=metrics, evaluation=evaluation)


def _write_final(slam: SLAM, out: Path, backend: str, summary: RunSummary | None) -> RunMetrics:
    """Final trajectory, map.json, map.ply and metrics.json (from a partial run too)."""
    if slam.frames:
        tmp = out / "trajectory.txt.tmp"
        write_tum(tmp, slam.trajectory(), header=f"planeslam {backend}")
        os.replace(tmp, out / "trajectory.txt")
    slam.map.save(out / "map.json")
    slam.map.write_ply(out / "map.ply")
    metrics = slam_run_metrics(slam, summary)
    write_metrics(metrics, out / "metrics.json")
    return metrics
