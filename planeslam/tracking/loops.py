"""Loop constraints: a keyframe that revisits older ground, placed against an older keyframe.

Tracking follows the map near the last keyframes. After a long way round, the online map
of a revisited place is off the old one by the drift (5-20 cm in places on the five-pass
7-Scenes replay), and frame-to-map tracking joins whichever copy of a surface is nearest.
At each keyframe, the `pool` older keyframes (all but the `skip_recent` last) nearest its
pose vote with their strongest descriptors (`KeypointMap.vote`; ORB-SLAM's place
recognition votes over the whole map with a bag of words, which by brute force cost
0.15 s a keyframe here); the best-voted are matched in full and a point RANSAC
(`ransac_pose`) places the keyframe against each. The one with the most agreeing matches,
its pose refined by other evidence when the caller gives a `Refine` (the tracker's: both
keyframes' planes, corners and edges), gives a `LoopConstraint` (the keyframe's pose in
the older keyframe's camera frame) when it moves the tracked pose by more than the noise
(`min_correction_*`) and less than a false match would (`max_correction_*`). The backend
adds it as a relative-pose factor, so the optimised poses take the revisited map back
onto the old one.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.geometry import invert_pose
from planeslam.core.types import LoopConstraint
from planeslam.tracking.config import LoopConfig, PointConfig
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.keypoints import (
    KeypointMap,
    Keypoints,
    PointMatches,
    PointPose,
    inlier_threshold,
    ransac_pose,
)

logger = logging.getLogger(__name__)

Refine = Callable[[int, np.ndarray, PointMatches], np.ndarray | None]
"""(older keyframe, (4, 4) T_old_cam of the points, the matches in its camera frame) ->
refined T_old_cam, or None."""


def nearby_older_keyframes(
    keypoint_map: KeypointMap, T_world_cam: np.ndarray, cfg: LoopConfig
) -> np.ndarray:
    """Frame indices (at most `pool`) of the keyframes of `keypoint_map` but the
    `skip_recent` most recent whose camera is within `search_radius_m` of T_world_cam's
    (4, 4) and whose optical axis is within `search_angle_deg` of its, nearest first
    (distance plus `search_radius_m` per `search_angle_deg` of turn): the older keyframes a
    drifted pose can still be revisiting."""
    indices, poses = keypoint_map.poses()
    indices, poses = indices[: -cfg.skip_recent], poses[: -cfg.skip_recent]
    meters = np.linalg.norm(poses[:, :3, 3] - T_world_cam[:3, 3], axis=1)
    cos_angle = np.clip(poses[:, :3, 2] @ T_world_cam[:3, 2], -1.0, 1.0)
    turn = np.degrees(np.arccos(cos_angle)) / cfg.search_angle_deg  # 1 at the limit
    near = np.flatnonzero((meters <= cfg.search_radius_m) & (turn <= 1.0))
    order = np.argsort(meters[near] / cfg.search_radius_m + turn[near], kind="stable")
    return indices[near[order[: cfg.pool]]]


def find_loop(
    keypoint_map: KeypointMap,
    keypoints: Keypoints,
    T_world_cam: np.ndarray,
    cfg: LoopConfig,
    points: PointConfig,
    sensor: DepthNoiseConfig,
    rng: np.random.Generator,
    refine: Refine | None = None,
) -> LoopConstraint | None:
    """The loop constraint of a new keyframe (its `keypoints`, tracked at T_world_cam
    (4, 4)) against the older keyframes of `keypoint_map` (module docstring), or None.
    `refine(old, T_old_cam, matches)`: the points' pose in the older keyframe's camera
    frame refined by other evidence (its matches given in that frame), or None to drop it."""
    if len(keypoints) < cfg.min_inliers:
        return None
    nearby = nearby_older_keyframes(keypoint_map, T_world_cam, cfg)
    if not len(nearby):
        return None
    best: tuple[int, PointPose, PointMatches] | None = None
    for old in keypoint_map.vote(
        keypoints, cfg.candidates, among=nearby, strongest=points.vote_descriptors
    ):
        matches = keypoint_map.matches(keypoints, [old])
        if len(matches) < cfg.min_inliers:
            continue
        p_cam = keypoints.points_cam[matches.observed]
        found = ransac_pose(
            p_cam,
            matches.points_world,
            inlier_threshold(p_cam, points, sensor),
            points.ransac_iterations,
            rng,
            cfg.min_inliers,
        )
        if found is None or found.count < cfg.min_inlier_fraction * len(matches):
            continue
        if best is None or found.count > best[1].count:
            best = (old, found, matches)
    if best is None:
        return None
    old, found, matches = best
    T_world_old = keypoint_map.pose(old)
    T_old_world = invert_pose(T_world_old)
    T_old_cam = T_old_world @ found.T_world_cam
    if refine is not None:
        refined = refine(old, T_old_cam, matches.moved(T_old_world))
        if refined is None:
            return None
        T_old_cam = refined
    meters, degrees = pose_difference(T_world_cam, T_world_old @ T_old_cam)
    if meters < cfg.min_correction_m and degrees < cfg.min_correction_deg:
        return None
    if meters > cfg.max_correction_m or degrees > cfg.max_correction_deg:
        logger.debug(
            "loop against keyframe %d dropped: %.2f m / %.1f deg off the tracked pose",
            old,
            meters,
            degrees,
        )
        return None
    logger.debug(
        "loop against keyframe %d: %.3f m / %.2f deg, %d matches agree",
        old,
        meters,
        degrees,
        found.count,
    )
    return LoopConstraint(old_index=old, T_old_cam=T_old_cam, inliers=found.count)
