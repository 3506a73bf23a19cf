"""Final poses of the frames between keyframes, re-estimated against the final map.

Only keyframes are in the factor graph. A frame between them keeps the pose tracking gave
it relative to its anchor keyframe (`SLAM`), which carries the map's error at that moment
(on a revisit, the map as it stood then) and the closed-form plane pose's jitter along
directions that only small patches fix. Once the backend has optimised the whole graph,
each such frame's pose is estimated again from the planes and corners it was tracked with
(their map ids, `FrameTerms`), against the final landmarks: the robust estimate of
`estimator.estimate_pose`, each plane weighted by its fit plus the sensor's correlated
depth error over its patch (`FrameView.plane_covariances`) plus `refine_floor_*`, from the
anchored pose. A frame keeps the anchored pose when fewer than three of its planes are
still in the map, when they leave a direction free, when the estimate leaves out a plane
that the anchored pose fits (another solution, not a correction).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.tracking.association import Association, pair_rows
from planeslam.tracking.estimator import (
    ConstraintThresholds,
    EstimatorSettings,
    PlaneTerms,
    PointTerms,
    PoseEstimate,
    corner_terms,
    estimate_pose,
    fully_constrained,
)
from planeslam.tracking.views import FrameView, MapView


@dataclass(frozen=True)
class FrameTerms:
    """What a tracked frame's pose rests on: its associated planes and corners (camera
    frame) and the map ids they matched. About 100 bytes per plane."""

    n_cam: np.ndarray
    """(N, 3) observed unit normals."""
    d_cam: np.ndarray
    """(N,) observed offsets [m]."""
    covariance: np.ndarray
    """(N, 3, 3) fit plus patch covariance (OrientedPlane3 local coordinates of n_cam)."""
    plane_ids: np.ndarray
    """(N,) map plane ids."""
    corner_points: np.ndarray
    """(M, 3) observed corner points [m]."""
    corner_ids: np.ndarray
    """(M,) map corner ids."""


def frame_terms(
    frame: FrameView, view: MapView, assoc: Association, sensor: DepthNoiseConfig
) -> FrameTerms | None:
    """The `FrameTerms` of `assoc` (frame rows against `view` rows); None for a view built
    without its planes' statistics (tests) or without associated planes."""
    obs, mp = assoc.plane_rows()
    co, cm = assoc.corner_rows()
    covariance = frame.plane_covariances(obs, sensor)
    if covariance is None or not len(obs):
        return None
    return FrameTerms(
        n_cam=frame.normals[obs],
        d_cam=frame.d[obs],
        covariance=covariance,
        plane_ids=view.plane_ids[mp].astype(np.int64),
        corner_points=frame.corner_points[co].reshape(-1, 3),
        corner_ids=view.corner_ids[cm].astype(np.int64),
    )


def final_poses(
    frames: Mapping[int, tuple[FrameTerms, np.ndarray]],
    view: MapView,
    settings: EstimatorSettings,
    thresholds: ConstraintThresholds,
    sigma_point_m: float,
) -> dict[int, np.ndarray]:
    """{frame: re-estimated T_world_cam (4, 4)} for the `frames` ({frame: (its terms, its
    anchored T_world_cam (4, 4))}) that the final map `view` (world frame) fixes (module
    docstring); the others are left out. `sigma_point_m`: corner noise, split between
    frame and map as tracking splits it."""
    plane_row = {int(pid): k for k, pid in enumerate(view.plane_ids)}
    corner_row = {int(cid): k for k, cid in enumerate(view.corner_ids)}
    found: dict[int, np.ndarray] = {}
    for index, (terms, T_init) in frames.items():
        keep = [j for j, pid in enumerate(terms.plane_ids.tolist()) if pid in plane_row]
        if len(keep) < 3:
            continue
        rows = [plane_row[int(terms.plane_ids[j])] for j in keep]
        planes = PlaneTerms(
            terms.n_cam[keep],
            terms.d_cam[keep],
            view.normals[rows],
            view.d[rows],
            terms.covariance[keep],
        )
        matched = [
            (j, corner_row[c]) for j, c in enumerate(terms.corner_ids.tolist()) if c in corner_row
        ]
        seen, known = pair_rows(matched)
        points = corner_terms(terms.corner_points[seen], view.corner_points[known], sigma_point_m)
        estimate = estimate_pose(T_init, planes, [points], None, settings)
        if not fully_constrained(estimate, thresholds):
            continue
        if _rejects_a_fitting_plane(estimate, T_init, planes, points, settings):
            continue
        found[index] = estimate.T_world_cam
    return found


def _rejects_a_fitting_plane(
    estimate: PoseEstimate,
    T_init: np.ndarray,
    planes: PlaneTerms,
    points: PointTerms,
    settings: EstimatorSettings,
) -> bool:
    """Whether `estimate` leaves out (beyond the Huber threshold) a plane that the anchored
    pose T_init (4, 4) fits: it went to another solution rather than correcting T_init. On
    the synthetic room_boxes_loop one such frame moved 2.7 cm, off the truth."""
    if estimate.plane_inliers.all():
        return False
    at_init = estimate_pose(T_init, planes, [points], None, replace(settings, iterations=0))
    return bool((at_init.plane_inliers & ~estimate.plane_inliers).any())


__all__ = ["FrameTerms", "final_poses", "frame_terms"]
