"""The result of tracking one frame (`TrackResult`) and how it is built from a pose."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.types import TrackingPath
from planeslam.tracking.association import Association
from planeslam.tracking.estimator import PoseConstraints
from planeslam.tracking.final_poses import FrameTerms, frame_terms
from planeslam.tracking.keypoints import Keypoints
from planeslam.tracking.plane_path import PlanePath
from planeslam.tracking.views import FrameView, MapView


@dataclass(frozen=True)
class TrackResult:
    """Pose of one frame and how it was found."""

    T_world_cam: np.ndarray
    """(4, 4) estimated pose (the prediction when lost)."""
    path: TrackingPath
    reason: str = ""
    """Why a fallback was needed or why the frame is lost; '' on the first path."""
    plane_pairs: list[tuple[int, int]] = field(default_factory=list)
    """(observed plane id, map plane id) correspondences under the final pose."""
    corner_pairs: list[tuple[int, int]] = field(default_factory=list)
    """(observed corner index, map corner id) correspondences under the final pose."""
    new_planes: int = 0
    """Observed planes with no map plane within the association gates under the final pose
    (structure the map does not have yet; an outlier of the pose solve does not count)."""
    constraints: PoseConstraints | None = None
    """Which degrees of freedom the planes fixed and what fixed the rest; None for the
    first frame and lost frames."""
    keypoints: Keypoints | None = field(default=None, repr=False)
    """The frame's keypoints when tracking computed them (a keyframe keeps them)."""
    terms: FrameTerms | None = field(default=None, repr=False)
    """The associated planes and corners with their map ids and covariances, for the
    final re-estimate against the final map (`final_poses`); None when lost or when
    `tracking.final_poses` is off."""

    @property
    def lost(self) -> bool:
        return self.path is TrackingPath.LOST


def track_result(
    planes: PlanePath,
    sensor: DepthNoiseConfig,
    final_poses: bool,
    frame: FrameView,
    view: MapView,
    T_final: np.ndarray,
    assoc: Association,
    path: TrackingPath,
    reason: str,
    found: PoseConstraints | None,
    keypoints: Keypoints | None,
) -> TrackResult:
    """The TrackResult of the pose T_final (4, 4) with its correspondences `assoc` and the
    count of planes the map does not have yet (nor culled as seen once: clutter seen
    again); `final_poses`: keep the terms of the final re-estimate."""
    new = np.ones(len(frame.plane_ids), dtype=bool)
    for normals, d, areas in (
        (view.normals, view.d, view.plane_weights),
        (view.culled_normals, view.culled_d, view.culled_areas),
    ):
        if new.any() and len(d):
            new &= ~planes.matchable(frame, normals, d, areas, T_final)
    return TrackResult(
        T_world_cam=T_final,
        path=path,
        reason=reason,
        plane_pairs=[(int(frame.plane_ids[i]), int(view.plane_ids[j])) for i, j in assoc.planes],
        corner_pairs=[(int(i), int(view.corner_ids[j])) for i, j in assoc.corners],
        new_planes=int(np.count_nonzero(new)),
        constraints=found,
        keypoints=keypoints,
        terms=(frame_terms(frame, view, assoc, sensor) if final_poses else None),
    )
