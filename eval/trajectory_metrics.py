"""Absolute trajectory error and relative pose error, computed with `evo`.

ATE follows TUM's `evaluate_ate.py` as `evo_ape tum GT EST -a --t_max_diff 0.02` does it:
poses associated by nearest timestamp within `max_time_difference_s`, the estimate aligned
to the ground truth by Umeyama's SE(3) fit (no scale), then statistics of the translation
error norms. RPE is evo's relative pose error over a fixed span of frames that covers
`rpe_delta_s` seconds at the trajectory's median frame interval, using all pairs
(`evo_rpe ... --delta N --delta_unit f --all_pairs`): evo has no time-based delta unit.
Every number here comes out of evo; this module only converts types and checks inputs.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from evo.core import lie_algebra, metrics, sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D

from planeslam.core.errors import DatasetFormatError, EvaluationError
from planeslam.io.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

MIN_PAIRS = 3
"""Fewest associated poses an SE(3) alignment and an ATE are computed from."""

EVAL_KEYS = (
    "ate_rmse_m",
    "ate_mean_m",
    "ate_median_m",
    "ate_max_m",
    "rpe_trans_m_per_s",
    "rpe_rot_deg_per_s",
    "pairs",
)
"""Keys of eval.json (plus `object_size_errors` when truth for objects is available)."""


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """ATE and RPE of an estimate against ground truth, plus what the plots need."""

    ate_rmse_m: float
    """Root mean square of the translation errors after SE(3) alignment [m]."""
    ate_mean_m: float
    """Mean translation error [m]."""
    ate_median_m: float
    """Median translation error [m]."""
    ate_max_m: float
    """Largest translation error [m]."""
    rpe_trans_m_per_s: float | None
    """RMSE of the relative translation error over `rpe_delta_frames` (about 1 s) [m];
    None when the associated poses span less than the RPE delta."""
    rpe_rot_deg_per_s: float | None
    """RMSE of the relative rotation angle error over the same pairs [deg]; None as above."""
    pairs: int
    """Number of associated (ground truth, estimate) pose pairs."""
    timestamps: np.ndarray = field(repr=False)
    """(P,) estimate timestamps of the associated pairs [s]."""
    T_world_gt: np.ndarray = field(repr=False)
    """(P, 4, 4) associated ground-truth poses (camera-to-world)."""
    T_world_est_aligned: np.ndarray = field(repr=False)
    """(P, 4, 4) associated estimated poses after alignment, in the ground-truth world frame."""
    ate_errors_m: np.ndarray = field(repr=False)
    """(P,) translation error of each pair after alignment [m]."""
    ate_rotation_errors_deg: np.ndarray = field(repr=False)
    """(P,) rotation angle error of each pair after alignment [deg]."""
    step_errors_m: np.ndarray = field(repr=False)
    """(P - 1,) translation error [m] of each motion between consecutive pairs (evo RPE
    over one frame): a wrong step shows where it happened, not in every later pose."""
    step_errors_deg: np.ndarray = field(repr=False)
    """(P - 1,) rotation angle error of each motion between consecutive pairs [deg]."""
    T_gt_est: np.ndarray = field(repr=False)
    """(4, 4) SE(3) alignment applied to the estimate (estimate world -> ground-truth world)."""
    alignment: str = "se3"
    """How the estimate was aligned: "se3" (Umeyama, no scale), "origin" (its first pose
    onto the ground truth's, evo's `align_origin`: the positions admitted no SE(3)
    alignment, a camera turning in place) or "none" (`align` False, or degenerate positions
    with `when_degenerate` "none")."""
    rpe_delta_frames: int = 0
    """Frame span of the RPE pairs (evo `--delta N --delta_unit f --all_pairs`); 0 if no RPE."""
    rpe_delta_s: float = 0.0
    """Time the RPE frame span covers at the median frame interval [s]; 0 if no RPE."""
    max_time_difference_s: float = 0.02
    """Association window used [s]."""
    object_size_errors: list[dict[str, Any]] | None = None
    """Per true object: class, sizes, absolute errors [m] (see `object_size_errors`); None
    when there is no object truth."""
    tracked_fraction: float | None = None
    """Frames the run tracked / frames it processed (the ATE is over the tracked ones);
    None when the estimate's producer did not say."""

    def to_dict(self) -> dict[str, Any]:
        """The eval.json content: exactly `EVAL_KEYS`, plus `alignment` when it is not
        "se3", and `object_size_errors` and `tracked_fraction` when set."""
        out: dict[str, Any] = {key: getattr(self, key) for key in EVAL_KEYS}
        if self.alignment != "se3":
            out["alignment"] = self.alignment
        if self.object_size_errors is not None:
            out["object_size_errors"] = self.object_size_errors
        if self.tracked_fraction is not None:
            out["tracked_fraction"] = self.tracked_fraction
        return out


def to_evo(trajectory: Trajectory) -> PoseTrajectory3D:
    """Our `Trajectory` -> evo's `PoseTrajectory3D` (same poses, same timestamps)."""
    return PoseTrajectory3D(
        poses_se3=list(np.asarray(trajectory.T_world_cam, dtype=np.float64)),
        timestamps=np.asarray(trajectory.timestamps, dtype=np.float64),
    )


def _load(source: Trajectory | str | Path, role: str) -> tuple[Trajectory, str]:
    """A trajectory and the name used for it in messages; file problems -> EvaluationError."""
    if isinstance(source, Trajectory):
        trajectory, name = source, role
    else:
        try:
            trajectory = read_tum(source)
        except DatasetFormatError as exc:
            raise EvaluationError(f"{role}: {exc}") from None
        name = str(source)
    if len(trajectory) == 0:
        raise EvaluationError(f"{name}: {role} has no poses")
    if not np.all(np.isfinite(trajectory.T_world_cam)):
        raise EvaluationError(f"{name}: {role} has non-finite poses")
    return trajectory, name


def _closest_gap_s(stamps_a: np.ndarray, stamps_b: np.ndarray) -> float:
    """Smallest |a_i - b_j| over all pairs [s] (stamps_b sorted)."""
    pos = np.searchsorted(stamps_b, stamps_a)
    lower = np.abs(stamps_a - stamps_b[np.clip(pos - 1, 0, len(stamps_b) - 1)])
    upper = np.abs(stamps_a - stamps_b[np.clip(pos, 0, len(stamps_b) - 1)])
    return float(np.minimum(lower, upper).min())


def _no_pairs_message(
    gt: Trajectory, est: Trajectory, gt_name: str, est_name: str, window: float
) -> str:
    gap = _closest_gap_s(np.sort(est.timestamps), np.sort(gt.timestamps))
    return (
        f"no poses of {est_name} within {window} s of {gt_name}: ground truth spans "
        f"{gt.timestamps.min():.3f}..{gt.timestamps.max():.3f} s, estimate spans "
        f"{est.timestamps.min():.3f}..{est.timestamps.max():.3f} s, the closest timestamps are "
        f"{gap:.3f} s apart (same time base? raise max_time_difference_s?)"
    )


def associate(
    groundtruth: Trajectory | str | Path,
    estimate: Trajectory | str | Path,
    max_time_difference_s: float = 0.02,
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Associate poses by nearest timestamp (evo `associate_trajectories`, as `evo_ape`).

    Returns evo trajectories (ground truth, estimate) of equal length P >= 3.
    Raises EvaluationError for unreadable/empty inputs, no pairs (with both time ranges
    and the closest gap) or fewer than 3 pairs.
    """
    if not max_time_difference_s >= 0:
        raise EvaluationError(f"max_time_difference_s must be >= 0, got {max_time_difference_s}")
    gt, gt_name = _load(groundtruth, "ground truth")
    est, est_name = _load(estimate, "estimate")
    try:
        gt_sync, est_sync = sync.associate_trajectories(
            to_evo(gt), to_evo(est), max_diff=max_time_difference_s
        )
    except sync.SyncException:
        raise EvaluationError(
            _no_pairs_message(gt, est, gt_name, est_name, max_time_difference_s)
        ) from None
    if gt_sync.num_poses < MIN_PAIRS:
        raise EvaluationError(
            f"only {gt_sync.num_poses} pose(s) of {est_name} within {max_time_difference_s} s "
            f"of {gt_name} (need at least {MIN_PAIRS} for an SE(3) alignment)"
        )
    log.debug("associated %d of %d estimated poses", gt_sync.num_poses, len(est))
    return gt_sync, est_sync


def rpe_delta_frames(timestamps: np.ndarray, rpe_delta_s: float) -> int:
    """Frame span that covers `rpe_delta_s` at the median frame interval of (P,) timestamps [s];
    0 when the timestamps span less than that."""
    stamps = np.asarray(timestamps, dtype=np.float64)
    if stamps.size < 2:
        return 0
    dt = float(np.median(np.diff(stamps)))
    if not dt > 0:
        raise EvaluationError("estimate timestamps do not increase (median frame interval is 0 s)")
    frames = max(1, int(round(rpe_delta_s / dt)))
    return frames if frames < stamps.size else 0


def evaluate_trajectory(
    groundtruth: Trajectory | str | Path,
    estimate: Trajectory | str | Path,
    max_time_difference_s: float = 0.02,
    rpe_delta_s: float = 1.0,
    align: bool = True,
    when_degenerate: Literal["raise", "origin", "none"] = "raise",
) -> TrajectoryEvaluation:
    """ATE (evo APE, translation part, SE(3) Umeyama alignment without scale; with
    `align` False none, for runs that start at the true pose; where the positions admit
    no SE(3) alignment, which `evo_ape -a` refuses, `when_degenerate` says what happens:
    an EvaluationError, the first poses aligned (`--align_origin`) or none) and RPE per
    `rpe_delta_s` (evo RPE, translation [m] and rotation angle [deg], all pairs `rpe_delta_frames`
    apart) of `estimate` against `groundtruth` (T_world_cam trajectories or TUM files).

    Equals `evo_ape tum GT EST -a --t_max_diff W` and
    `evo_rpe tum GT EST -a --t_max_diff W --delta N --delta_unit f --all_pairs` (RMSE),
    N = `rpe_delta_frames` of the associated estimate timestamps.
    Raises EvaluationError (one line) when the evaluation cannot be done.
    """
    if not rpe_delta_s > 0:
        raise EvaluationError(f"rpe_delta_s must be > 0 s, got {rpe_delta_s}")
    gt_sync, est_sync = associate(groundtruth, estimate, max_time_difference_s)

    est_aligned = copy.deepcopy(est_sync)
    T_gt_est, alignment = np.eye(4), "se3" if align else "none"
    try:
        if align:
            rotation, translation, _ = est_aligned.align(gt_sync, correct_scale=False)
            T_gt_est = lie_algebra.se3(rotation, translation)
    except GeometryException as exc:
        if when_degenerate == "raise":
            raise EvaluationError(
                f"cannot align the estimate to the ground truth ({exc}); the "
                f"{gt_sync.num_poses} associated positions are degenerate (all equal or on "
                "one line?)"
            ) from None
        est_aligned, alignment = copy.deepcopy(est_sync), when_degenerate
        if when_degenerate == "origin":
            T_gt_est = est_aligned.align_origin(gt_sync)

    pair = (gt_sync, est_aligned)
    translation_part, angle_deg = (
        metrics.PoseRelation.translation_part,
        metrics.PoseRelation.rotation_angle_deg,
    )
    ape, ape_rotation = metrics.APE(translation_part), metrics.APE(angle_deg)
    ape.process_data(pair)
    ape_rotation.process_data(pair)
    stats = ape.get_all_statistics()

    delta_frames = rpe_delta_frames(est_aligned.timestamps, rpe_delta_s)
    rpe_trans: float | None = None
    rpe_rot: float | None = None
    delta_s = 0.0
    if delta_frames:
        rmse = metrics.StatisticsType.rmse
        rpe_trans = float(_rpe(pair, translation_part, delta_frames).get_statistic(rmse))
        rpe_rot = float(_rpe(pair, angle_deg, delta_frames).get_statistic(rmse))
        delta_s = delta_frames * float(np.median(np.diff(est_aligned.timestamps)))
    else:
        span = float(est_aligned.timestamps[-1] - est_aligned.timestamps[0])
        log.warning(
            "RPE not computed: the %d associated poses span %.3f s, less than the RPE delta %.3f s",
            est_aligned.num_poses,
            span,
            rpe_delta_s,
        )

    return TrajectoryEvaluation(
        ate_rmse_m=float(stats["rmse"]),
        ate_mean_m=float(stats["mean"]),
        ate_median_m=float(stats["median"]),
        ate_max_m=float(stats["max"]),
        rpe_trans_m_per_s=rpe_trans,
        rpe_rot_deg_per_s=rpe_rot,
        pairs=int(gt_sync.num_poses),
        timestamps=np.asarray(est_aligned.timestamps, dtype=np.float64),
        T_world_gt=np.asarray(gt_sync.poses_se3),
        T_world_est_aligned=np.asarray(est_aligned.poses_se3),
        ate_errors_m=np.asarray(ape.error, dtype=np.float64),
        ate_rotation_errors_deg=np.asarray(ape_rotation.error, dtype=np.float64),
        step_errors_m=np.asarray(_rpe(pair, translation_part, 1).error, dtype=np.float64),
        step_errors_deg=np.asarray(_rpe(pair, angle_deg, 1).error, dtype=np.float64),
        T_gt_est=T_gt_est,
        alignment=alignment,
        rpe_delta_frames=delta_frames,
        rpe_delta_s=delta_s,
        max_time_difference_s=float(max_time_difference_s),
    )


def _rpe(
    pair: tuple[PoseTrajectory3D, PoseTrajectory3D],
    relation: metrics.PoseRelation,
    delta_frames: int,
) -> metrics.RPE:
    """evo RPE of (ground truth, estimate) over all pose pairs `delta_frames` apart."""
    rpe = metrics.RPE(relation, delta=delta_frames, delta_unit=metrics.Unit.frames, all_pairs=True)
    rpe.process_data(pair)
    return rpe


def format_table(evaluation: TrajectoryEvaluation) -> str:
    """A short plain-text table of the eval.json figures, for the terminal."""

    def fmt(value: float | None, unit: str, scale: float = 1.0) -> str:
        return (
            "n/a (sequence shorter than the RPE delta)"
            if value is None
            else f"{value * scale:.4f} {unit}"
        )

    rows = [
        ("pairs", str(evaluation.pairs)),
        ("ATE RMSE", fmt(evaluation.ate_rmse_m, "m")),
        ("ATE mean", fmt(evaluation.ate_mean_m, "m")),
        ("ATE median", fmt(evaluation.ate_median_m, "m")),
        ("ATE max", fmt(evaluation.ate_max_m, "m")),
        ("RPE translation", fmt(evaluation.rpe_trans_m_per_s, "m/s")),
        ("RPE rotation", fmt(evaluation.rpe_rot_deg_per_s, "deg/s")),
    ]
    for obj in evaluation.object_size_errors or []:
        rows.append(
            (f"size error {obj['class']} {obj['true_id']}", f"{obj['mean_abs_error_m']:.4f} m")
        )
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)
