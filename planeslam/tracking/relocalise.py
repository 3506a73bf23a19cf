"""Whole-map relocalisation: pose candidates for a frame with no usable prediction.

Candidates come from every primitive (`hypotheses`: corners, plane triples, two planes
with an edge) against the whole map, and from keypoints: the keyframes anywhere in the
map that share most descriptors with the frame (`KeypointMap.vote`) are matched in full
and a point RANSAC gives one more candidate (the only one when its inliers outweigh all
that a pose elsewhere could fit: then no rival can exist). Every candidate is verified
against all of the frame's primitives (`hypotheses.score_hypotheses`; the point matches
that agree under it add to the best-scored candidates); the best `relocalise_candidates`
go on to the robust estimate (`relocalise`). Ties go to the candidate nearest the
prediction, so a symmetric room keeps its orientation when nothing else tells them apart.

`relocalise` refines the candidates by the joint estimate and takes the best only with
more support than a minimal set gives and without a rival elsewhere (`is_rival`).
`relocalise_nearby` is the search right after a tracked frame: the primitive hypotheses a
plausible motion reaches, the best taken without a rival within that bound.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.tracking import hypotheses, motion
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.joint import JointEstimator, JointSolve, is_rival
from planeslam.tracking.keypoints import (
    KeypointMap,
    Keypoints,
    PointMatches,
    inlier_threshold,
    ransac_pose,
)
from planeslam.tracking.views import FrameView, MapView

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Candidates:
    """Relocalisation candidates, best first, and the point matches they were scored with."""

    poses: np.ndarray
    """(K, 4, 4) T_world_cam."""
    matches: PointMatches
    """Matches of the frame's keypoints with the best-voted keyframes (world frame)."""


def primitive_hypotheses(frame: FrameView, view: MapView, cfg: TrackingConfig) -> np.ndarray:
    """(H, 4, 4) every corner, plane-triple and edge hypothesis against the whole map."""
    gate = np.radians(cfg.max_angle_deg)
    return np.concatenate(
        [
            hypotheses.corner_hypotheses(frame, view, gate),
            hypotheses.triple_hypotheses(
                frame,
                view,
                gate,
                cfg.max_triple_planes,
                cfg.max_triple_map_planes,
                cfg.relocalise_max_hypotheses,
            ),
            hypotheses.edge_hypotheses(frame, view, gate, cfg.relocalise_max_hypotheses // 8),
        ]
    )


def relocalisation_candidates(
    frame: FrameView,
    view: MapView,
    keypoints: Keypoints | None,
    keypoint_map: KeypointMap | None,
    cfg: TrackingConfig,
    sensor: DepthNoiseConfig,
    rng: np.random.Generator,
    T_pred: np.ndarray,
) -> Candidates:
    """The `relocalise_candidates` best-supported pose candidates for `frame` anywhere in
    the map (see the module docstring); T_pred (4, 4) only breaks ties."""
    matches = PointMatches.empty()
    poses = np.zeros((0, 4, 4))
    threshold = np.zeros(0)
    p_cam = np.zeros((0, 3))
    if keypoints is not None and keypoint_map is not None and len(keypoints):
        voted = keypoint_map.vote(keypoints, cfg.points.vote_keyframes)
        matches = keypoint_map.matches(keypoints, voted)
        if len(matches) >= cfg.points.min_inliers:
            p_cam = keypoints.points_cam[matches.observed]
            threshold = inlier_threshold(p_cam, cfg.points, sensor)
            found = ransac_pose(
                p_cam,
                matches.points_world,
                threshold,
                cfg.points.ransac_iterations,
                rng,
                cfg.points.min_inliers,
            )
            if found is not None:
                if _points_decide(frame, found.count, len(matches), cfg):
                    return Candidates(found.T_world_cam[None], matches)
                poses = np.concatenate([found.T_world_cam[None], poses])
    if not could_be_enough(frame, len(matches), cfg):
        return Candidates(np.zeros((0, 4, 4)), matches)
    if not view.empty:
        poses = np.concatenate([poses, primitive_hypotheses(frame, view, cfg)])
    if not len(poses):
        return Candidates(np.zeros((0, 4, 4)), matches)
    scores = np.zeros(len(poses)) if view.empty else _scores(frame, view, poses, cfg)
    if len(p_cam):  # the points' say, for the point pose and the best of the rest
        top = np.argsort(-scores, kind="stable")[: 8 * cfg.relocalise_candidates]
        top = np.union1d(top, [0])  # the point RANSAC pose comes first
        agreeing = hypotheses.agreeing_matches(poses[top], p_cam, matches.points_world, threshold)
        scores[top] += np.count_nonzero(agreeing, axis=1) / 10.0
    return Candidates(_best_distinct(poses, scores, T_pred, cfg.relocalise_candidates), matches)


def _scores(frame: FrameView, view: MapView, poses: np.ndarray, cfg: TrackingConfig) -> np.ndarray:
    """(H,) `hypotheses.score_hypotheses` of (H, 4, 4) poses under the tracking gates."""
    gate = np.radians(cfg.max_angle_deg)
    return hypotheses.score_hypotheses(
        frame, view, poses, gate, cfg.max_offset_m, cfg.max_corner_distance_m
    )


def _best_distinct(
    poses: np.ndarray, scores: np.ndarray, T_near: np.ndarray, count: int
) -> np.ndarray:
    """(K, 4, 4): the `count` best-scored of (H, 4, 4) `poses`, ties to the nearest to
    T_near (4, 4), without poses within 2 cm and 2 deg of a better one (`_distinct`)."""
    distance = np.linalg.norm(poses[:, :3, 3] - T_near[:3, 3], axis=1)
    return poses[_distinct(poses, np.lexsort((distance, -np.round(scores, 6))), count)]


def could_be_enough(frame: FrameView, matches: int, cfg: TrackingConfig) -> bool:
    """Whether any candidate could pass `relocalise`'s support test: a pose's inlier
    planes are at most the frame's and its agreeing points at most its `matches`. A wall
    or two parallel planes with few keypoints never relocalises, so no hypothesis is made."""
    return matches >= cfg.relocalise_min_points or len(frame.plane_ids) >= cfg.relocalise_min_planes


def _points_decide(frame: FrameView, inliers: int, matches: int, cfg: TrackingConfig) -> bool:
    """Whether the point pose's `inliers` of `matches` leave no room for a rival (see
    `relocalise`): a pose elsewhere could at most fit all the frame's planes and
    corners and the other matches, and that would score below `relocalise_ambiguity` of
    the inliers' own score, so the primitive hypotheses need not be made."""
    most_elsewhere = len(frame.plane_ids) + 2.0 * len(frame.corner_points)
    most_elsewhere += (matches - inliers) / 10.0
    return inliers >= cfg.relocalise_min_points and (
        most_elsewhere < cfg.relocalise_ambiguity * inliers / 10.0
    )


def _distinct(poses: np.ndarray, order: np.ndarray, count: int) -> np.ndarray:
    """`order` without poses within 2 cm and 2 deg of a better one (the same hypothesis
    from another primitive), at most `count`."""
    kept: list[int] = []
    for k in order:
        differences = (hypotheses.pose_difference(poses[j], poses[k]) for j in kept)
        if not any(meters < 0.02 and degrees < 2.0 for meters, degrees in differences):
            kept.append(int(k))
        if len(kept) == count:
            break
    return np.array(kept, dtype=np.int64)


def relocalise(
    frame: FrameView,
    view: MapView,
    T_pred: np.ndarray,
    keypoints: Keypoints | None,
    keypoint_map: KeypointMap | None,
    joint: JointEstimator,
) -> JointSolve | None:
    """The best candidate of a whole-map search (`relocalisation_candidates`), refined
    by `joint`. Taken only with more support than a minimal set gives (at least
    `relocalise_min_planes` inlier planes that are `relocalise_min_plane_fraction` of the
    frame's, or `relocalise_min_points` inlier point matches) and without a rival
    (`is_rival`): a refined candidate elsewhere with nearly its score and other evidence
    means the map is ambiguous there (a symmetric room), and the frame stays lost. Point
    matches count when they agree with a pose within their inlier threshold."""
    cfg = joint.config
    candidates = relocalisation_candidates(
        frame, view, keypoints, keypoint_map, cfg, joint.sensor, joint.rng, T_pred
    )
    solved = [
        s
        for s in (
            joint.solve(frame, view, T0, keypoints, candidates.matches) for T0 in candidates.poses
        )
        if s is not None
    ]
    if not solved:
        return None
    ranked = _ranked(solved, keypoints, candidates.matches, joint)
    best = ranked[0][0]
    planes = best.constraints.terms["planes"]
    enough = best.point_inliers >= cfg.relocalise_min_points or (
        planes >= cfg.relocalise_min_planes
        and planes >= cfg.relocalise_min_plane_fraction * len(frame.plane_ids)
    )
    if not enough:
        logger.debug(
            "relocalisation: best candidate has too little support (%s)", best.constraints.terms
        )
        return None
    return _unrivalled(ranked, cfg)


def _ranked(
    solved: list[JointSolve],
    keypoints: Keypoints | None,
    matches: PointMatches,
    joint: JointEstimator,
) -> list[tuple[JointSolve, np.ndarray]]:
    """The refined candidates `solved`, each with its point term counting the `matches`
    that agree with it and that (M,) bool mask, best score first."""
    agreeing = joint.agreeing_masks(np.array([s.T for s in solved]), keypoints, matches)
    return sorted(
        (_with_point_inliers(s, mask) for s, mask in zip(solved, agreeing, strict=True)),
        key=lambda pair: -pair[0].score,
    )


def _unrivalled(
    ranked: list[tuple[JointSolve, np.ndarray]], cfg: TrackingConfig
) -> JointSolve | None:
    """The first of `ranked` (`_ranked`), or None when another rivals it (`is_rival`)."""
    best, best_points = ranked[0]
    for rival, rival_points in ranked[1:]:
        if is_rival(best, rival, best_points, rival_points, cfg):
            logger.debug("ambiguous: scores %.1f and %.1f", best.score, rival.score)
            return None
    return best


def _with_point_inliers(solve: JointSolve, agreeing: np.ndarray) -> tuple[JointSolve, np.ndarray]:
    """`solve` with its point term counting the matches `agreeing` ((M,) bool: within their
    inlier threshold at its pose), and that mask. The estimate's own point gate is wide (a
    keyframe's pose error is shared by its points), so refined poses a few cm apart would
    look equally supported."""
    terms = {**solve.constraints.terms, "points": int(np.count_nonzero(agreeing))}
    return replace(solve, constraints=replace(solve.constraints, terms=terms)), agreeing


def relocalise_nearby(
    frame: FrameView,
    view: MapView,
    T_last: np.ndarray,
    gap_s: float,
    keypoints: Keypoints | None,
    matches: PointMatches,
    joint: JointEstimator,
) -> JointSolve | None:
    """Right after a tracked frame at T_last (4, 4), `gap_s` seconds ago: the map-wide
    primitive hypotheses that a plausible motion reaches (`motion.plausible`), refined by
    `joint` (with the frame's point `matches` against the recent keyframes), the best taken
    when no refined candidate within the same bound rivals it (`is_rival`). The bound does
    the work of `relocalise`'s support test: a symmetric room's alternatives lie a quarter
    or half turn away, beyond any motion between two frames, so a wide step (a robot's,
    a slow frame rate) is placed from what the frame shares with the map nearby."""
    cfg = joint.config
    poses = primitive_hypotheses(frame, view, cfg)
    poses = poses[[motion.plausible(cfg, T, T_last, gap_s) for T in poses]]
    if not len(poses):
        return None
    starts = _best_distinct(
        poses, _scores(frame, view, poses, cfg), T_last, cfg.relocalise_candidates
    )
    solved = [
        s
        for s in (joint.solve(frame, view, T0, keypoints, matches) for T0 in starts)
        if s is not None and motion.plausible(cfg, s.T, T_last, gap_s)
    ]
    return _unrivalled(_ranked(solved, keypoints, matches, joint), cfg) if solved else None
