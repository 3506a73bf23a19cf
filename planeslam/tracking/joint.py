"""The joint path of tracking: one robust estimate over every primitive.

`JointEstimator.solve` starts from a pose, associates planes and corners under it,
matches edge ends, takes the keypoint matches within their gate, and runs
`estimator.estimate_pose` (each primitive weighted by its covariance, Huber-robust);
it associates again under the result, drops what is beyond the gates and estimates once
more. `best` runs it from several start poses (the partial plane pose, a point RANSAC's,
the prediction) and keeps the best-supported one that something corroborates.

Frames: map primitives in the world frame, observations in the camera frame; every pose
is T_world_cam (4, 4).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.geometry import transform_points
from planeslam.core.types import TrackingPath
from planeslam.tracking import motion
from planeslam.tracking.association import Association
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.estimator import (
    ConstraintThresholds,
    EstimatorSettings,
    LineTerms,
    PlaneTerms,
    PointTerms,
    PoseConstraints,
    PoseEstimate,
    Primitive,
    constraints,
    estimate_pose,
    fully_constrained,
)
from planeslam.tracking.hypotheses import agreeing_matches, pose_difference
from planeslam.tracking.keypoints import (
    Keypoints,
    PointMatches,
    inlier_threshold,
    point_residuals,
    ransac_pose,
)
from planeslam.tracking.periodic import period_shifts, texture_period
from planeslam.tracking.plane_path import PlanePath, keep_within
from planeslam.tracking.views import FrameView, MapView


@dataclass(frozen=True)
class JointSolve:
    """A robust estimate over every primitive and the correspondences it used."""

    T: np.ndarray
    """(4, 4) T_world_cam, the estimate's."""
    association: Association
    """Plane and corner correspondences kept (within the gates at the solution)."""
    constraints: PoseConstraints
    """Its `terms` count the inlier planes, corners, points and lines."""

    @property
    def point_inliers(self) -> int:
        return self.constraints.terms["points"]

    @property
    def score(self) -> float:
        """Support: inlier planes (1 each), corners (2), point matches (1/10)."""
        terms = self.constraints.terms
        return terms["planes"] + 2.0 * terms["corners"] + terms["points"] / 10.0

    @property
    def path(self) -> TrackingPath:
        c = self.constraints
        if c.planes_full:
            return TrackingPath.PLANES
        if c.plane_rotation_dof == 0 and c.plane_translation_dof == 0:
            return TrackingPath.POINTS
        return TrackingPath.PLANES_POINTS


class JointEstimator:
    """The robust estimate over planes, corners, edge ends and keypoints with depth."""

    def __init__(
        self,
        config: TrackingConfig,
        sensor: DepthNoiseConfig,
        planes: PlanePath,
        settings: EstimatorSettings,
        thresholds: ConstraintThresholds,
        rng: np.random.Generator,
    ) -> None:
        """`planes`: association and corner terms; `settings`: the estimate's sigmas and
        Huber constant; `thresholds`: when a direction counts as fixed; `rng`: the point
        RANSAC's draws."""
        self.config = config
        self.sensor = sensor
        self.planes = planes
        self.settings = settings
        self.thresholds = thresholds
        self.rng = rng

    def _estimate(
        self,
        frame: FrameView,
        view: MapView,
        assoc: Association,
        T: np.ndarray,
        keypoints: Keypoints | None,
        matches: PointMatches,
    ) -> PoseEstimate | None:
        """`estimate_pose` from T (4, 4) over the terms under T: associated planes and
        corners, the point matches within twice their inlier threshold, and the real ends
        of edges whose two planes are associated with the two planes of a map edge (the
        nearer map end, within `line_gate_m` along the edge); None without plane or point
        terms."""
        cfg = self.config
        obs, mp = assoc.plane_rows()
        cov = (
            frame.covariances[obs] if frame.covariances is not None else np.zeros((len(obs), 3, 3))
        )
        planes = PlaneTerms(frame.normals[obs], frame.d[obs], view.normals[mp], view.d[mp], cov)
        terms = [self.planes.corner_terms(frame, view, assoc)]
        if keypoints is not None and len(matches):
            p_cam = keypoints.points_cam[matches.observed]
            gate = 2.0 * inlier_threshold(p_cam, cfg.points, self.sensor)
            use = point_residuals(T, p_cam, matches.points_world) < gate
            # A keyframe's pose error is common to all its points: spread its variance over
            # them, so one keyframe's points together weigh at most like its pose.
            _, group, count = np.unique(
                matches.keyframes[use], return_inverse=True, return_counts=True
            )
            shared = (count[group] * cfg.points.keyframe_sigma_m**2)[:, None, None] * np.eye(3)
            terms.append(
                PointTerms(
                    p_cam[use],
                    matches.points_world[use],
                    keypoints.covariances[matches.observed[use]],
                    matches.covariances_world[use] + shared,
                )
            )
        if not len(planes) and not sum(len(p) for p in terms):
            return None
        lines = self._line_terms(frame, view, assoc, T)
        return estimate_pose(T, planes, terms, lines, self.settings)

    def _line_terms(
        self, frame: FrameView, view: MapView, assoc: Association, T: np.ndarray
    ) -> LineTerms:
        to_map = dict(assoc.planes)
        edge_row = {
            frozenset((int(a), int(b))): k for k, (a, b) in enumerate(view.edge_planes.tolist())
        }
        p, u, e = [], [], []
        for k, (a, b) in enumerate(frame.edge_planes.tolist()):
            if a not in to_map or b not in to_map or not frame.edge_real_ends[k].any():
                continue
            j = edge_row.get(frozenset((to_map[a], to_map[b])))
            if j is None:
                continue
            seg = view.edge_segments[j]
            direction = seg[1] - seg[0]
            length = float(np.linalg.norm(direction))
            if length < 1e-6:
                continue
            direction /= length
            for end in np.flatnonzero(frame.edge_real_ends[k]):
                p_cam = frame.edge_segments[k, end]
                s = float(direction @ (T[:3, :3] @ p_cam + T[:3, 3] - seg[0]))
                target = seg[0] if abs(s) <= abs(s - length) else seg[1]
                if min(abs(s), abs(s - length)) <= self.config.line_gate_m:
                    p.append(p_cam)
                    u.append(direction)
                    e.append(target)
        return LineTerms(
            np.array(p).reshape(-1, 3), np.array(u).reshape(-1, 3), np.array(e).reshape(-1, 3)
        )

    def solve(
        self,
        frame: FrameView,
        view: MapView,
        T_start: np.ndarray,
        keypoints: Keypoints | None,
        matches: PointMatches,
    ) -> JointSolve | None:
        """Robust estimate over every primitive from T_start (4, 4): associate under the
        current pose, estimate, associate again, drop planes and corners beyond the gates
        and estimate once more. None when the result is not trusted: some direction is
        left unconstrained, or it rests on points alone with fewer than
        `points.min_inliers` of them."""
        cfg = self.config
        T = T_start
        assoc = Association([], [])
        estimate: PoseEstimate | None = None
        for _ in range(2):
            assoc = self.planes.associate(frame, view, T) if len(view.plane_ids) else assoc
            estimate = self._estimate(frame, view, assoc, T, keypoints, matches)
            if estimate is None:
                return None
            T = estimate.T_world_cam
        assert estimate is not None
        kept = self._inliers(frame, view, assoc, T)
        if kept is not None:
            assoc = kept
            estimate = self._estimate(frame, view, assoc, T, keypoints, matches)
            if estimate is None:
                return None
        if not fully_constrained(estimate, self.thresholds):
            return None
        point_inliers = (
            int(np.count_nonzero(estimate.point_inliers[1]))
            if len(estimate.point_inliers) > 1
            else 0
        )
        terms = {
            "planes": int(np.count_nonzero(estimate.plane_inliers)),
            "corners": len(assoc.corners),
            "points": point_inliers,
            "lines": int(np.count_nonzero(estimate.line_inliers)),
        }
        found = constraints(estimate, self.thresholds, terms)
        if not found.planes_full and Primitive.POINTS in found.filled_by:
            if point_inliers < cfg.points.min_inliers:
                return None
        return JointSolve(estimate.T_world_cam, assoc, found)

    def agreeing(self, T: np.ndarray, keypoints: Keypoints | None, matches: PointMatches) -> int:
        """Point matches within their inlier threshold under T (4, 4)."""
        return int(np.count_nonzero(self.agreeing_masks(T[None], keypoints, matches)))

    def agreeing_masks(
        self, poses: np.ndarray, keypoints: Keypoints | None, matches: PointMatches
    ) -> np.ndarray:
        """(H, M) bool: the point matches within their inlier threshold under each of the
        (H, 4, 4) poses."""
        if keypoints is None or not len(matches):
            return np.zeros((len(poses), len(matches)), dtype=bool)
        p_cam = keypoints.points_cam[matches.observed]
        threshold = inlier_threshold(p_cam, self.config.points, self.sensor)
        return agreeing_matches(poses, p_cam, matches.points_world, threshold)

    def _inliers(
        self, frame: FrameView, view: MapView, assoc: Association, T: np.ndarray
    ) -> Association | None:
        """`assoc` without the planes and corners beyond the residual gates under T."""
        if not assoc.planes:
            return None
        cfg = self.config
        obs, mp = np.array(assoc.planes, dtype=np.int64).T
        n_world = frame.normals[obs] @ T[:3, :3].T
        d_world = frame.d[obs] - n_world @ T[:3, 3]
        cos = np.clip(np.sum(n_world * view.normals[mp], axis=1), -1.0, 1.0)
        ok = (np.arccos(cos) <= np.radians(cfg.max_residual_angle_deg)) & (
            np.abs(d_world - view.d[mp]) <= cfg.max_residual_offset_m
        )
        co, cm = assoc.corner_rows()
        moved = transform_points(T, frame.corner_points[co])
        corner_ok = (
            np.linalg.norm(moved - view.corner_points[cm], axis=1) <= cfg.max_corner_distance_m
        )
        return keep_within(frame, assoc, ok, corner_ok)

    def best(
        self,
        frame: FrameView,
        view: MapView,
        starts: list[np.ndarray],
        keypoints: Keypoints | None,
        matches: PointMatches,
        T_pred: np.ndarray,
        tracking: bool,
        T_last: np.ndarray | None = None,
        frame_gap_s: float = np.inf,
        match_at: Callable[[np.ndarray], PointMatches] | None = None,
    ) -> JointSolve | None:
        """The best-supported `solve` over the start poses that is corroborated. While
        `tracking` (the previous frame was tracked): within the fast path's correction of
        the prediction T_pred (4, 4), or at a pose a plausible motion from the last one
        T_last (4, 4), `frame_gap_s` seconds ago, reaches (`motion.plausible`) with at
        least `points.min_inliers` point matches or `relocalise_min_planes` inlier planes
        (a jump is not taken on one frame's evidence: aliased keypoints agree on wrong
        poses too); with those point matches, the fast path's correction on top of the
        motion (`correction`: the last pose may have drifted, and the points correct it).
        After a loss: at least `points.min_inliers` point matches (planes alone far from a
        prediction prove little: three of them always fit). While tracking, with
        `match_at(T)` (matches by projection under a (4, 4) pose), copies of the best a
        texture period away join its rivals (`with_period_rivals`)."""
        cfg = self.config
        corroborated_solves: list[JointSolve] = []
        solved: list[np.ndarray] = []
        for T0 in starts:
            differences = (pose_difference(T, T0) for T in solved)
            if any(meters < 0.01 and degrees < 0.5 for meters, degrees in differences):
                continue  # where an earlier start already went
            candidate = self.solve(frame, view, T0, keypoints, matches)
            if candidate is None:
                continue
            solved.append(candidate.T)
            if tracking:  # no jump on one frame's evidence
                points = candidate.point_inliers >= cfg.points.min_inliers
                corroborated = motion.near(cfg, candidate.T, T_pred) or (
                    (points or candidate.constraints.terms["planes"] >= cfg.relocalise_min_planes)
                    # with the points' support, the last pose's drift may be corrected too
                    and motion.plausible(cfg, candidate.T, T_last, frame_gap_s, correction=points)
                )
            else:
                corroborated = candidate.point_inliers >= cfg.points.min_inliers
            if corroborated:
                corroborated_solves.append(candidate)
        if not corroborated_solves:
            return None
        best = max(corroborated_solves, key=lambda c: c.score)
        best = self._nearest_of_rivals(best, corroborated_solves, keypoints, matches, T_pred)
        if tracking and match_at is not None:
            best = self.with_period_rivals(frame, view, best, keypoints, matches, T_pred, match_at)
        return best

    def _nearest_of_rivals(
        self,
        best: JointSolve,
        candidates: list[JointSolve],
        keypoints: Keypoints | None,
        matches: PointMatches,
        T_pred: np.ndarray,
    ) -> JointSolve:
        """`best`, unless a candidate nearer the prediction T_pred (4, 4) rivals it
        (`is_rival`: nearly its score, elsewhere, on other point matches): then
        the evidence does not tell them apart (a repetitive texture agrees with poses a
        period apart) and the nearest to the prediction is taken."""
        masks = self.agreeing_masks(np.array([c.T for c in candidates]), keypoints, matches)
        best_mask = masks[next(k for k, c in enumerate(candidates) if c is best)]
        offset = np.linalg.norm(best.T[:3, 3] - T_pred[:3, 3])
        chosen, chosen_offset = best, offset
        for candidate, mask in zip(candidates, masks, strict=True):
            nearer = np.linalg.norm(candidate.T[:3, 3] - T_pred[:3, 3])
            if nearer < chosen_offset and is_rival(best, candidate, best_mask, mask, self.config):
                chosen, chosen_offset = candidate, nearer
        return chosen

    def with_period_rivals(
        self,
        frame: FrameView,
        view: MapView,
        best: JointSolve,
        keypoints: Keypoints | None,
        matches: PointMatches,
        T_pred: np.ndarray,
        match_at: Callable[[np.ndarray], PointMatches],
    ) -> JointSolve:
        """`best`, or a copy of it whole texture periods away (`periodic`) nearer the
        prediction T_pred (4, 4) that rivals it, when points filled a direction the planes
        left free and `best` is not near the prediction: each shifted pose is matched again
        by projection (`match_at(T)`, (4, 4) T_world_cam) and solved."""
        cfg = self.config
        if (
            keypoints is None
            or best.path is not TrackingPath.PLANES_POINTS
            or motion.near(cfg, best.T, T_pred)
        ):
            return best
        period = texture_period(keypoints, best.T[:3, :3], cfg.points.min_inliers)
        if period is None:
            return best
        candidates = [best]
        for T in period_shifts(best.T, period):
            shifted = self.solve(frame, view, T, keypoints, match_at(T))
            if shifted is not None and shifted.point_inliers >= cfg.points.min_inliers:
                candidates.append(shifted)
        return self._nearest_of_rivals(best, candidates, keypoints, matches, T_pred)

    def point_pose(self, keypoints: Keypoints, matches: PointMatches) -> np.ndarray | None:
        """T_world_cam (4, 4) of a point RANSAC over `matches`, or None."""
        cfg = self.config.points
        if len(matches) < cfg.min_inliers:
            return None
        p_cam = keypoints.points_cam[matches.observed]
        found = ransac_pose(
            p_cam,
            matches.points_world,
            inlier_threshold(p_cam, cfg, self.sensor),
            cfg.ransac_iterations,
            self.rng,
            cfg.min_inliers,
        )
        return None if found is None else found.T_world_cam


def is_rival(
    best: JointSolve,
    other: JointSolve,
    best_points: np.ndarray,
    other_points: np.ndarray,
    cfg: TrackingConfig,
) -> bool:
    """Whether `other` makes a relocalisation to `best` ambiguous: it scores at least
    `relocalise_ambiguity` of the best, lies elsewhere (beyond 10 cm or 5 deg) and is not the
    same place fitted worse, which explains the same point matches (the (M,) bool masks of
    the matches agreeing with each: half of the other's, and at least `points.min_inliers`,
    are the best's too). A symmetric room's other corners match other keypoints, or none."""
    if other.score < cfg.relocalise_ambiguity * best.score or _same_pose(other.T, best.T):
        return False
    shared = np.count_nonzero(other_points & best_points)
    return bool(shared < max(cfg.points.min_inliers, 0.5 * np.count_nonzero(other_points)))


def _same_pose(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """Whether two (4, 4) poses are within 10 cm and 5 deg of each other."""
    meters, degrees = pose_difference(T_a, T_b)
    return meters <= 0.10 and degrees <= 5.0


def estimator_settings(
    config: TrackingConfig,
) -> tuple[EstimatorSettings, EstimatorSettings, ConstraintThresholds]:
    """The robust estimate's settings, those of the plane pose's refinement (its floors on
    the plane sigmas), and when a direction counts as fixed, from the tracking config."""
    settings = EstimatorSettings(
        plane_sigma_angle_rad=np.radians(config.sigma_angle_deg),
        plane_sigma_offset_m=config.sigma_offset_m,
        line_sigma_m=config.sigma_line_m,
        huber_k=config.huber_k,
    )
    refine = replace(
        settings,
        plane_sigma_angle_rad=np.radians(config.refine_floor_deg),
        plane_sigma_offset_m=config.refine_floor_m,
    )
    thresholds = ConstraintThresholds(
        max_sigma_rad=np.radians(config.max_sigma_deg), max_sigma_m=config.max_sigma_m
    )
    return settings, refine, thresholds
