"""`planeslam run`: SLAM over a dataset (TUM folder or ROS bag) with every output written as it
is produced.

Output folder:
- config.yaml      the resolved configuration (written first);
- trajectory.txt   TUM poses, one row per frame as it is tracked (an interrupted run keeps
                   them), rewritten at the end with the optimised poses;
- frames.jsonl     one record per frame: tracking path, reason, keyframe, stage ms;
- run.json         dataset path, backend, command line, version, start time (written first);
- map.json         the plane-object map (schema planeslam.map/1, world frame; with the
                   keyframes and the frames that saw each plane: `SLAM.map_record`);
- map_planes.ply   its plane polygons as a mesh coloured by object; map_points.ply its
                   sparse cloud;
- metrics.json     speed, memory (map against point cloud, with the breakdown), lost frames;
- eval.json, frame_errors.csv, trajectory.png, ate_over_time.png  when groundtruth.txt exists;
- report.html      one self-contained page (figures embedded), map.png its top-down map.
The run holds the folder's lock while it writes (a second run there is refused) and first
moves a previous run's files into previous-<time>/ (`run_folder.claim_run_folder`); nothing
is written before the dataset, the config and the --map have been read and checked.
The final files are also written when the run is interrupted (Ctrl-C; SIGTERM too under
the CLI) or fails, from the frames processed so far. Whole files are replaced atomically
with the usual permissions, trajectory.txt and frames.jsonl grow a whole line per frame
(a killed run keeps every finished frame). What cannot be evaluated (a malformed ground
truth or truth.json, a trajectory too short to align) is a warning in `RunResult.warnings`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from planeslam.app.dataset_options import TopicOverrides
from planeslam.app.progress import progress_bar
from planeslam.app.ros_export import check_bag_destination, write_results_bag
from planeslam.app.run_folder import claim_run_folder
from planeslam.app.signals import deferred_interrupts
from planeslam.config import PlaneSlamConfig, explain_config, open_configured
from planeslam.core.config import ConfigLayer, override_layer
from planeslam.core.errors import ConfigError, PlaneSlamError
from planeslam.core.safe_files import LineWriter, atomic_output, write_text_atomic
from planeslam.eval.metrics import RunMetrics, slam_run_metrics, write_metrics
from planeslam.eval.report import EvaluationRun, evaluate_to_folder, write_report
from planeslam.eval.run_info import RunInfo, write_run_info
from planeslam.io.odometry import OdometryFile
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import TumWriter, write_tum
from planeslam.mapping.json_io import save_json
from planeslam.mapping.world_map import Map
from planeslam.slam import (
    SLAM,
    FrameResult,
    RunSummary,
    RunTally,
    frame_indices,
    run_frames,
    slam_for_dataset,
)

logger = logging.getLogger(__name__)


class RunObserver(Protocol):
    """Sees a run as it goes (the rerun viewer): the dataset before the first frame,
    every frame's result with the SLAM that made it, and the finished SLAM."""

    def start(self, dataset: RgbdDataset, config: PlaneSlamConfig) -> None: ...

    def frame(self, slam: SLAM, result: FrameResult) -> None: ...

    def finish(self, slam: SLAM) -> None: ...


@dataclass(frozen=True)
class RunResult:
    """What `run_sequence` wrote and measured."""

    out_dir: Path
    summary: RunSummary
    metrics: RunMetrics
    evaluation: EvaluationRun | None
    """None without ground truth, or when it could not be evaluated (see `warnings`)."""
    warnings: tuple[str, ...] = ()
    """What could not be evaluated or read, and why."""

    def text(self) -> str:
        """A few lines for the terminal."""
        m, s = self.metrics, self.summary
        paths = ", ".join(f"{k} {v}" for k, v in sorted(s.paths.items()))
        lines = [
            f"{m.frames} frames ({m.keyframes} keyframes, {m.lost_frames} lost) at "
            f"{m.fps:.1f} fps; tracking: {paths}",
            f"map {m.map_bytes / 1e3:.0f} kB vs the fused 1 cm point cloud "
            f"{m.fused_cloud_bytes / 1e6:.1f} MB ({m.memory_ratio or 0:.0f}x smaller; all "
            f"frames' clouds merged: {m.pointcloud_bytes / 1e6:.0f} MB, "
            f"{m.memory_ratio_merged or 0:.0f}x)",
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
            tracked = (
                f" ({m.tracked_fraction:.1%} of the frames tracked)"
                if m.tracked_fraction is not None
                else ""
            )
            lines.append(f"ATE RMSE {ev.ate_rmse_m:.4f} m, {rpe} over {ev.pairs} poses{tracked}")
        glitches = m.pose_glitches
        if glitches.get("count"):
            shown = ", ".join(f"{t:.2f}" for t in glitches["timestamps"][:8])
            more = " ..." if glitches["count"] > 8 else ""
            lines.append(
                f"pose glitches: {glitches['count']} of {glitches['judged']} poses jump over "
                f"{100 * glitches['min_jump_m']:.0f} cm / {glitches['min_jump_deg']:.0f} deg "
                f"off the frames around them and back (t = {shown}{more} s)"
            )
        if s.skipped_frames:
            lines.append(f"{s.skipped_frames} frames skipped: their images could not be read")
        lines.extend(f"warning: {w}" for w in self.warnings)
        lines.append(f"outputs in {self.out_dir} (open report.html)")
        return "\n".join(lines)


def run_sequence(
    dataset_dir: str | Path,
    out_dir: str | Path,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    backend: str | None = None,
    max_frames: int | None = None,
    every: int | None = None,
    progress: bool = False,
    seed: int | None = None,
    observer: RunObserver | None = None,
    command: str = "",
    topics: TopicOverrides | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
    start_pose: str | None = None,
    map_path: str | Path | None = None,
    localize: bool = False,
    out_bag: str | Path | None = None,
    odometry: OdometryFile | None = None,
) -> RunResult:
    """Run SLAM on a TUM-layout folder and write the outputs listed in the module docstring.
    `map_path`: a map.json to track in (the first frame placed by relocalisation, not by
    ground truth); `localize` leaves it unchanged, else it is extended.
    `overrides` ('section.key=value') apply after `config` and `camera`; `backend`,
    `max_frames`, `every`, `seed` and `start_pose` then override the config's `run`
    section. The saved config.yaml holds the values used, each with its source, and
    reproduces the run as `--config`. `observer` sees every frame; `command` (the
    command line) goes into run.json; `topics` chooses a bag's topics. `out_bag`: a new
    folder for the results as a ROS 2 bag (`planeslam.app.ros_export`), written when the
    run finishes. `odometry`: the camera's measured motion between frames (wheel, IMU),
    fed to `SLAM.process` (`planeslam.io.odometry`)."""
    root = Path(dataset_dir)
    out = Path(out_dir)
    if localize and map_path is None:
        raise ConfigError("localize needs a map to localise in (--map MAP.json)")
    if out_bag is not None:
        check_bag_destination(out_bag)
    flags = {
        "backend": backend,
        "seed": seed,
        "every": every,
        "max_frames": max_frames,
        "start_pose": start_pose,
    }
    flag_layers = []
    for key, value in flags.items():
        if value is not None:
            flag = f"--{key.replace('_', '-')}"
            flag_layers.append(override_layer(f"run.{key}", value, f"{flag} {value}", flag))
    resolved = explain_config(root, config, camera, [*overrides, *flag_layers])
    cfg = resolved.config
    if topics is not None:
        cfg = topics.apply(cfg)
    run = cfg.run
    backend = run.backend
    dataset, cfg = open_configured(root, cfg)
    indices = frame_indices(len(dataset), run.max_frames, run.every)
    if not indices:
        raise ConfigError(f"{root}: no frames to process")
    if odometry is not None:
        odometry.check_covers(dataset.timestamps[indices])
    # Inputs and --map are read and checked before the folder is touched.
    world_map = Map.load(map_path) if map_path is not None else None
    with claim_run_folder(out, [p for p in [dataset.groundtruth_path] if p is not None]):
        write_text_atomic(
            out / "config.yaml", resolved.replaced(cfg, "dataset or topic options").to_yaml()
        )
        write_run_info(RunInfo.now(root, backend, command), out)
        # A stop waits while the compiled kernels load and the backend starts: its
        # exception, raised inside numba's compiler, would be swallowed (a finaliser) or
        # leave the compiler broken. It is delivered right after.
        with deferred_interrupts():
            if world_map is not None:
                slam = SLAM(cfg, map=world_map, localize=localize)
            else:
                slam = slam_for_dataset(cfg, dataset, indices[0])
        if observer is not None:
            observer.start(dataset, cfg)
        summary: RunSummary | None = None
        with (
            slam,
            progress_bar(len(indices), f"{backend} {root.name}", "frame", enabled=progress) as bar,
            TumWriter(out / "trajectory.txt", header=f"planeslam {backend} online") as writer,
            LineWriter(out / "frames.jsonl") as frames_log,
        ):

            def on_result(result: FrameResult) -> None:
                if not result.lost:  # lost frames have no pose (left out, as ORB-SLAM does)
                    writer.write(result.timestamp, result.T_world_cam)
                frames_log.write_line(json.dumps(result.to_record()))
                bar.step(result.path.value)
                if observer is not None:
                    observer.frame(slam, result)

            tally = RunTally()
            try:
                summary = run_frames(
                    slam,
                    dataset,
                    indices,
                    on_result,
                    tally,
                    deferred_interrupts,
                    None if odometry is None else odometry.step,
                )
            finally:
                if summary is None:  # interrupted or failed: keep what was computed
                    _write_stopped(slam, out, backend, tally)
        assert summary is not None
        metrics = _write_final(slam, out, backend, summary)
        if out_bag is not None and slam.tracked_frames:
            write_results_bag(out_bag, slam.trajectory(), slam.map)
        if observer is not None:
            observer.finish(slam)
        evaluation = None
        warnings: list[str] = []
        gt_error = getattr(dataset, "groundtruth_error", "")  # a TUM folder's unreadable truth
        if gt_error:
            warnings.append(f"not evaluated: {gt_error}")
        if dataset.groundtruth is not None:
            gt_path = dataset.groundtruth_path
            if gt_path is None:  # from a bag's /tf: kept beside the outputs for `planeslam eval`
                gt_path = out / "groundtruth.txt"
                write_tum(gt_path, dataset.groundtruth, header=f"ground truth from {root} /tf")
            try:
                evaluation = evaluate_to_folder(
                    gt_path,
                    out / "trajectory.txt",
                    out,
                    cfg.dataset.max_time_difference_s,
                    tracked_fraction=metrics.tracked_fraction,
                )
                warnings.extend(evaluation.warnings)
            except PlaneSlamError as exc:  # SLAM's outputs stand without it
                tracked = f"{slam.tracked_frames} of {slam.frames} frames tracked"
                warnings.append(f"no ATE ({tracked}): {exc}")
                logger.warning("%s", warnings[-1])
        if evaluation is None:
            try:
                write_report(out)
            except PlaneSlamError as exc:
                warnings.append(f"report.html not written: {exc}")
                logger.warning("%s", warnings[-1])
        return RunResult(
            out_dir=out,
            summary=summary,
            metrics=metrics,
            evaluation=evaluation,
            warnings=tuple(warnings),
        )


def _write_stopped(slam: SLAM, out: Path, backend: str, tally: RunTally) -> None:
    """The final files of a run that was interrupted or failed, from its frames so far
    (objects aggregated, as `finish` would). A failure here is logged, not raised: the
    error that stopped the run is the one to report."""
    logger.warning("run stopped after %d frames; writing what it has", slam.frames)
    try:
        if slam.frames:
            slam.map.reaggregate()
        _write_final(slam, out, backend, tally.summary())
    except Exception as exc:
        logger.warning("could not write the final outputs to %s: %s", out, exc)


def _write_final(slam: SLAM, out: Path, backend: str, summary: RunSummary) -> RunMetrics:
    """Final trajectory, map.json, the map's PLY files and metrics.json (from a partial run
    too), each replaced atomically; Ctrl-C and SIGTERM wait until they are written."""
    with deferred_interrupts():
        if slam.frames:
            with atomic_output(out / "trajectory.txt") as tmp:
                write_tum(tmp, slam.trajectory(), header=f"planeslam {backend}")
        save_json(slam.map_record(), out / "map.json")  # atomic itself
        with atomic_output(out / "map_planes.ply") as tmp:
            slam.map.write_planes_ply(tmp)
        with atomic_output(out / "map_points.ply") as tmp:
            slam.map.write_points_ply(tmp)
        metrics = slam_run_metrics(slam, summary)
        with atomic_output(out / "metrics.json") as tmp:
            write_metrics(metrics, tmp)
    return metrics
