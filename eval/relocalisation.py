"""Relocalisation benchmark: frames placed in a finished map one at a time, with no prior.

The map is a SLAM's after a run (planes, corners, edges, objects, and the keypoints of all
its keyframes) or a saved map.json (primitives only). Every chosen frame goes through the
front end and `Tracker.relocalise` on its own: no prediction (the identity only breaks
ties), nothing of earlier attempts kept, the map not changed. A frame counts as
relocalised when the pose is within the tolerances of its ground truth in the map's
frame: the truth moved by the SE(3) that takes the map's own trajectory onto it (as ATE
aligns; the map run's trajectory, or a map.json's keyframes), so a map that started at the
identity (ICL-NUIM: no truth for frame 1) scores as one that started at the true pose.
Without such a trajectory, map and truth are taken to share the world frame.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.config import open_configured, resolve_config
from planeslam.core.config import ConfigLayer
from planeslam.core.errors import EvaluationError
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.io.sequence import RgbdDataset
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.json_io import load_json
from planeslam.mapping.world_map import Map
from planeslam.slam import SLAM, frame_indices, run_frames
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.views import FrameView


@dataclass(frozen=True)
class RelocalisationAttempt:
    """One frame placed in the map on its own."""

    index: int
    """Frame index in the dataset."""
    found: bool
    """Whether relocalisation returned a pose."""
    translation_error_m: float | None
    """Against ground truth; None when no pose was returned."""
    rotation_error_deg: float | None
    milliseconds: float
    """Wall-clock time of the attempt (front end excluded)."""
    map_translation_error_m: float | None = None
    """Against the pose the map's own run gave the frame (its final trajectory): where the
    map says the frame is, free of the map's own error against the truth; None without."""
    map_rotation_error_deg: float | None = None
    aligned_translation_error_m: float | None = None
    """Against ground truth after the map is aligned to it as ATE aligns (the SE(3) that
    takes the map run's trajectory onto the truth): the map's drift from its first frame
    left out; None without the map run."""
    aligned_rotation_error_deg: float | None = None
    run_aligned_translation_error_m: float | None = None
    """The map run's own pose of the frame against the truth, aligned the same way: the
    map's own error here, which the aligned figures inherit; None without the map run or
    a pose."""
    run_aligned_rotation_error_deg: float | None = None


@dataclass(frozen=True)
class RelocalisationReport:
    """All attempts and their summary."""

    attempts: list[RelocalisationAttempt] = field(repr=False)
    tolerance_m: float = 0.05
    tolerance_deg: float = 3.0

    def _within(self, meters: float | None, degrees: float | None) -> bool:
        return (
            meters is not None
            and degrees is not None
            and meters <= self.tolerance_m
            and degrees <= self.tolerance_deg
        )

    @property
    def correct(self) -> int:
        """Attempts within both tolerances of the truth in the map's frame (`aligned`), or
        of the truth as it is when the map has no trajectory to align."""
        aligned = self.aligned
        return self.correct_unaligned if aligned is None else aligned

    @property
    def correct_unaligned(self) -> int:
        """Attempts within both tolerances of the truth as it is (the map's world frame
        taken as the truth's)."""
        return sum(self._within(a.translation_error_m, a.rotation_error_deg) for a in self.attempts)

    @property
    def consistent(self) -> int | None:
        """Attempts within both tolerances of the map run's own pose of the frame (None
        without that run)."""
        return self._count_within("map_translation_error_m", "map_rotation_error_deg")

    @property
    def aligned(self) -> int | None:
        """Attempts within both tolerances of the truth with the map aligned to it (None
        without the map run)."""
        return self._count_within("aligned_translation_error_m", "aligned_rotation_error_deg")

    @property
    def run_aligned(self) -> int | None:
        """Frames whose map-run pose is within both tolerances of the truth, aligned (None
        without the map run): how far the map itself lets `aligned` go (the frames need
        not be the same ones)."""
        return self._count_within(
            "run_aligned_translation_error_m", "run_aligned_rotation_error_deg"
        )

    def _count_within(self, meters_field: str, degrees_field: str) -> int | None:
        """Attempts whose `meters_field` and `degrees_field` are within both tolerances;
        None when a placed attempt lacks them (no map run)."""
        if any(a.found and getattr(a, meters_field) is None for a in self.attempts):
            return None
        return sum(
            self._within(getattr(a, meters_field), getattr(a, degrees_field)) for a in self.attempts
        )

    @property
    def wrong(self) -> int:
        """Attempts that returned a pose outside the tolerances."""
        return sum(a.found for a in self.attempts) - self.correct

    def to_dict(self) -> dict[str, Any]:
        """The summary, and under "frames" every attempt (`RelocalisationAttempt`'s fields)."""
        ms = np.array([a.milliseconds for a in self.attempts])
        n = len(self.attempts)
        return {
            "attempts": n,
            "correct": self.correct,
            "wrong": self.wrong,
            "not_found": n - self.correct - self.wrong,
            "correct_fraction": self.correct / n if n else 0.0,
            "scored_in_map_frame": self.aligned is not None,
            "correct_unaligned": self.correct_unaligned,
            "consistent_with_map_run": self.consistent,
            "correct_with_map_aligned": self.aligned,
            "map_run_correct_aligned": self.run_aligned,
            "tolerance_m": self.tolerance_m,
            "tolerance_deg": self.tolerance_deg,
            "ms_median": float(np.median(ms)) if n else 0.0,
            "ms_max": float(ms.max()) if n else 0.0,
            "frames": [asdict(a) for a in self.attempts],
        }

    def to_text(self) -> str:
        d = self.to_dict()
        return (
            f"{d['correct']} of {d['attempts']} frames relocalised within "
            f"{100 * self.tolerance_m:.0f} cm and {self.tolerance_deg:.0f} deg "
            f"({100 * d['correct_fraction']:.1f} %), {d['wrong']} wrong, "
            f"{d['not_found']} not placed"
            + (
                " (truth and map taken to share the world frame)"
                if self.aligned is None
                else " (truth in the map's frame, aligned as ATE aligns; "
                f"{self.correct_unaligned} against the truth as it is)"
            )
            + f"; {d['ms_median']:.0f} ms per attempt (median, max {d['ms_max']:.0f})"
            + (
                ""
                if self.consistent is None
                else f"; {self.consistent} within them of the map run's own poses"
            )
            + (
                ""
                if self.run_aligned is None
                else f" (the map run's own poses of those frames: {self.run_aligned})"
            )
        )


def relocalise_frames(
    slam: SLAM,
    dataset: RgbdDataset,
    indices: list[int],
    tolerance_m: float = 0.05,
    tolerance_deg: float = 3.0,
    reference: Trajectory | None = None,
) -> RelocalisationReport:
    """Place each frame `indices` of `dataset` in `slam`'s map on its own (module
    docstring), against ground truth and, when given, the map run's own `reference`
    trajectory and the truth with the map aligned to it by the SE(3) that takes
    `reference` onto the truth (as ATE aligns). EvaluationError when the dataset has no
    ground truth."""
    if dataset.groundtruth is None:
        raise EvaluationError(f"{dataset.root}: relocalisation needs groundtruth.txt")
    window_s = dataset.config.max_time_difference_s
    T_truth_map = (
        None
        if reference is None
        else evaluate_trajectory(dataset.groundtruth, reference, window_s).T_gt_est
    )
    view = slam.map_view()
    tracker = slam.tracker
    detector = tracker.keypoint_map.detector if tracker.keypoint_map is not None else None
    attempts = []
    for index in indices:
        frame = dataset[index]
        T_true = dataset.groundtruth.pose_near(frame.timestamp, window_s)
        if T_true is None:  # no ground truth for this frame: nothing to score against
            continue
        observation = slam.front_end.process(frame.depth_m, frame.timestamp)
        start = time.perf_counter()
        keypoints = None
        if detector is not None and frame.rgb is not None and observation.cloud is not None:
            keypoints = detector.detect(frame.rgb, observation.cloud)
        solved = tracker.relocalise(
            FrameView.of(observation, slam.config.camera), view, np.eye(4), keypoints
        )
        ms = 1e3 * (time.perf_counter() - start)
        if solved is None:
            attempts.append(RelocalisationAttempt(index, False, None, None, ms))
            continue
        meters, degrees = pose_difference(T_true, solved.T)
        map_meters = map_degrees = aligned_meters = aligned_degrees = None
        run_meters = run_degrees = None
        if reference is not None and T_truth_map is not None:
            T_map_run = reference.pose_near(frame.timestamp, 1e-6)  # the same frame's
            if T_map_run is not None:
                map_meters, map_degrees = pose_difference(T_map_run, solved.T)
                run_meters, run_degrees = pose_difference(T_true, T_truth_map @ T_map_run)
            aligned_meters, aligned_degrees = pose_difference(T_true, T_truth_map @ solved.T)
        attempts.append(
            RelocalisationAttempt(
                index,
                True,
                meters,
                degrees,
                ms,
                map_meters,
                map_degrees,
                aligned_meters,
                aligned_degrees,
                run_meters,
                run_degrees,
            )
        )
    return RelocalisationReport(attempts, tolerance_m, tolerance_deg)


def keyframe_trajectory(map_path: str | Path) -> Trajectory | None:
    """The keyframes a map.json lists (`SLAM.map_record`: timestamps, final poses) as a
    trajectory, or None when it lists fewer than 3 (an older file, a map of no run)."""
    keyframes = load_json(map_path).get("keyframes") or []
    if len(keyframes) < 3:
        return None
    return Trajectory(
        np.array([float(k["timestamp"]) for k in keyframes]),
        np.array([k["T_world_cam"] for k in keyframes], dtype=np.float64).reshape(-1, 4, 4),
    )


def relocalisation_benchmark(
    dataset_dir: str | Path,
    map_path: str | Path | None = None,
    every: int = 10,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> RelocalisationReport:
    """Every `every`-th frame of a TUM-layout dataset placed on its own in a map: the map of
    `map_path` (primitives only), or else the map of a full SLAM run over the dataset made
    first (with the keypoints of every keyframe)."""
    root = Path(dataset_dir)
    cfg = resolve_config(root, config, camera, list(overrides))
    dataset, cfg = open_configured(root, cfg)
    indices = frame_indices(len(dataset), None, every)
    if map_path is not None:
        slam = SLAM(cfg, "merge", map=Map.load(map_path), localize=True)
        return relocalise_frames(slam, dataset, indices, reference=keyframe_trajectory(map_path))
    first = None
    if cfg.run.start_pose == "groundtruth":
        first = dataset.groundtruth_pose(dataset.timestamps[0])
    with SLAM(cfg, T_world_first=first, every_keyframe_keypoints=True) as slam:
        run_frames(slam, dataset, range(len(dataset)))
        return relocalise_frames(slam, dataset, indices, reference=slam.trajectory())
