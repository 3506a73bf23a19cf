"""Whole-map relocalisation: pose candidates for a frame with no usable prediction.

Candidates come from every primitive (`hypotheses`: corners, plane triples, two planes
with an edge) against the whole map, and from keypoints: the keyframes anywhere in the
map that share most descriptors with the frame (`KeypointMap.vote`) are matched in full
and a point RANSAC gives one more candidate (the only one when its inliers outweigh all
that a pose elsewhere could fit: then no rival can exist). Every candidate is verified
against all of the frame's primitives (`hypotheses.score_hypotheses`; the point matches
that agree under it add to the best-scored candidates); the best `relocalise_candidates`
go on to the tracker's robust estimate. Ties go to the candidate nearest the prediction, so a
symmetric room keeps its orientation when nothing else tells them apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.tracking import hypotheses
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.keypoints import (
    KeypointMap,
    Keypoints,
    PointMatches,
    inlier_threshold,
    ransac_pose,
)
from planeslam.tracking.views import FrameView, MapView


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
            hypotheses.edge_hypotheses(
                frame, view, gate, cfg.edge_length_ratio, cfg.relocalise_max_hypotheses // 8
            ),
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
    if not view.empty:
        poses = np.concatenate([poses, primitive_hypotheses(frame, view, cfg)])
    if not len(poses):
        return Candidates(np.zeros((0, 4, 4)), matches)
    scores = np.zeros(len(poses))
    if not view.empty:
        scores = hypotheses.score_hypotheses(
            frame,
            view,
            poses,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            cfg.max_corner_distance_m,
        )
    if len(p_cam):  # the points' say, for the point pose and the best of the rest
        top = np.argsort(-scores, kind="stable")[: 8 * cfg.relocalise_candidates]
        top = np.union1d(top, [0])  # the point RANSAC pose comes first
        agreeing = agreeing_matches(poses[top], p_cam, matches.points_world, threshold)
        scores[top] += np.count_nonzero(agreeing, axis=1) / 10.0
    distance = np.linalg.norm(poses[:, :3, 3] - T_pred[:3, 3], axis=1)
    order = np.lexsort((distance, -np.round(scores, 6)))
    order = _distinct(poses, order, cfg.relocalise_candidates)
    return Candidates(poses[order], matches)


def _points_decide(frame: FrameView, inliers: int, matches: int, cfg: TrackingConfig) -> bool:
    """Whether the point pose's `inliers` of `matches` leave no room for a rival (see
    `Tracker.relocalise`): a pose elsewhere could at most fit all the frame's planes and
    corners and the other matches, and that would score below `relocalise_ambiguity` of
    the inliers' own score, so the primitive hypotheses need not be made."""
    most_elsewhere = len(frame.plane_ids) + 2.0 * len(frame.corner_points)
    most_elsewhere += (matches - inliers) / 10.0
    return inliers >= cfg.relocalise_min_points and (
        most_elsewhere < cfg.relocalise_ambiguity * inliers / 10.0
    )


def agreeing_matches(
    poses: np.ndarray, p_cam: np.ndarray, p_world: np.ndarray, threshold: np.ndarray
) -> np.ndarray:
    """(H, M) bool: the matches (camera (M, 3) -> world (M, 3)) within their (M,)
    thresholds [m] under each of the (H, 4, 4) poses."""
    dist = np.linalg.norm(hypotheses.moved_points(poses, p_cam) - p_world[None], axis=2)
    return dist < threshold[None]


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
