"""The fast path of tracking: a closed-form pose from the planes and corners associated
under the predicted pose (paper Section 4.4).

`PlanePath.register` associates the frame's planes and corners with the map's under the
prediction (`association.associate_with_corners`), solves the closed-form pose
(`registration.pose_from_planes_and_points`), drops correspondences beyond the residual
gates, associates again under the solution and solves once more (`register`);
`completed` fills the directions the planes leave free from another pose.

Frames: map planes and corners in the world frame, observations in the camera frame;
every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planeslam.core.types import TrackingPath
from planeslam.tracking.association import (
    Association,
    associate_with_corners,
    plane_association_cost,
)
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.estimator import (
    ConstraintThresholds,
    PointTerms,
    PoseConstraints,
    Primitive,
    corner_terms,
)
from planeslam.tracking.registration import (
    RegistrationResult,
    RegistrationStatus,
    pose_from_planes_and_points,
)
from planeslam.tracking.views import FrameView, MapView

PARTIAL = (RegistrationStatus.DEGENERATE_ROTATION, RegistrationStatus.DEGENERATE_TRANSLATION)
"""Plane poses that fixed some directions only."""
DENSE_PATHS = {Primitive.ODOMETRY: TrackingPath.ODOMETRY, Primitive.ICP: TrackingPath.ICP}
"""The path of a dense pose without planes."""
COMPLETED_PATHS = {
    Primitive.ODOMETRY: TrackingPath.PLANES_ODOMETRY,
    Primitive.ICP: TrackingPath.PLANES_ICP,
    Primitive.MOTION: TrackingPath.PLANES_MOTION,
}
"""The path of a partial plane pose completed by each method."""


@dataclass(frozen=True)
class PoseSolve:
    """A closed-form pose and the correspondences it was solved from."""

    registration: RegistrationResult
    association: Association

    @property
    def T(self) -> np.ndarray:
        """(4, 4) T_world_cam."""
        return self.registration.T


class PlanePath:
    """Plane and corner association and the closed-form pose (`register`, `completed`)."""

    def __init__(
        self,
        config: TrackingConfig,
        thresholds: ConstraintThresholds,
    ) -> None:
        """`thresholds`: when a direction counts as fixed."""
        self.config = config
        self.thresholds = thresholds

    def associate(self, frame: FrameView, view: MapView, T: np.ndarray) -> Association:
        """Plane and corner correspondences of `frame` with `view` under T (4, 4)."""
        cfg = self.config
        return associate_with_corners(
            view.normals,
            view.d,
            view.corner_planes,
            view.corner_points,
            frame.normals,
            frame.d,
            frame.corner_planes,
            frame.corner_points,
            T,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            cfg.max_corner_distance_m,
            weights=frame.weights,
            gate=self._size_gate(frame, view.plane_weights),
            weigh_unpaired=self._weighed_map_planes(view),
        )

    def _weighed_map_planes(self, view: MapView) -> bool | np.ndarray:
        """Which map planes' contests weights decide (`associate_planes`' `weigh_unpaired`):
        (M,) bool the structures, map planes of at least `weigh_unpaired_min_area_m2`;
        False when map areas are unknown."""
        cfg = self.config
        if cfg.weigh_unpaired_min_area_m2 is None or view.plane_weights is None:
            return False
        return np.asarray(view.plane_weights >= cfg.weigh_unpaired_min_area_m2)

    def _size_gate(self, frame: FrameView, areas: np.ndarray | None) -> np.ndarray | None:
        """(N, M) bool: an observed plane may only match a map plane (of these areas (M,)
        [m^2]) at least about its size (map outlines grow as planes merge, so a big
        observation never belongs to a small map plane: a floor is not a box top). None
        when sizes are unknown."""
        if frame.areas is None or areas is None:
            return None
        cfg = self.config
        limit = cfg.size_gate_ratio * areas + cfg.size_gate_margin_m2
        return frame.areas[:, None] <= limit[None, :]

    def matchable(
        self,
        frame: FrameView,
        normals: np.ndarray,
        d: np.ndarray,
        areas: np.ndarray | None,
        T_world_cam: np.ndarray,
    ) -> np.ndarray:
        """(N,) bool: which observed planes have a world plane (normals (M, 3), d (M,) [m],
        areas (M,) [m^2] or None) within the association gates at T_world_cam (4, 4)."""
        cfg = self.config
        _, allowed = plane_association_cost(
            normals,
            d,
            frame.normals,
            frame.d,
            T_world_cam,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            gate=self._size_gate(frame, areas),
        )
        return np.asarray(allowed.any(axis=1), dtype=bool)

    def _solve(
        self, frame: FrameView, view: MapView, assoc: Association, T_prior: np.ndarray
    ) -> RegistrationResult:
        cfg = self.config
        obs, mp = assoc.plane_rows()
        co, cm = assoc.corner_rows()
        return pose_from_planes_and_points(
            frame.normals[obs],
            frame.d[obs],
            view.normals[mp],
            view.d[mp],
            frame.corner_points[co],
            view.corner_points[cm],
            sigma_angle_rad=np.radians(cfg.sigma_angle_deg),
            sigma_offset_m=cfg.sigma_offset_m,
            sigma_point_m=cfg.sigma_point_m,
            plane_weights=frame.weights[obs],
            T_prior=T_prior,
        )

    def register(self, frame: FrameView, view: MapView, T_pred: np.ndarray) -> PoseSolve | None:
        """Closed-form pose from the planes and corners associated under T_pred.

        Solved, re-associated under the solution and solved again; after each solve the
        correspondences whose residuals exceed the gates (wrong matches, a plane whose
        border was mis-segmented) are dropped and the pose re-solved without them, so one
        outlier does not cost the frame its plane pose. None without correspondences.
        Every solve starts from T_pred, so a set of correspondences met again (the second
        association often repeats the first) takes its earlier solve."""
        solved: dict[tuple[tuple[tuple[int, int], ...], ...], RegistrationResult] = {}

        def solve(assoc: Association) -> RegistrationResult:
            key = (tuple(assoc.planes), tuple(assoc.corners))
            if key not in solved:
                solved[key] = self._solve(frame, view, assoc, T_pred)
            return solved[key]

        T = T_pred
        result: PoseSolve | None = None
        for _ in range(2):
            assoc = self.associate(frame, view, T)
            if not assoc.planes:
                return result
            reg = solve(assoc)
            for _ in range(self.config.max_outlier_rounds):
                kept = self._inliers(frame, assoc, reg)
                if kept is None:
                    break
                if not kept.planes:
                    return result
                assoc, reg = kept, solve(kept)
            result, T = PoseSolve(reg, assoc), reg.T
        return result

    def completed(
        self, frame: FrameView, view: MapView, solve: PoseSolve, T_other: np.ndarray
    ) -> tuple[np.ndarray, tuple[int, int]]:
        """The plane pose of `solve`, solved again with the directions its planes leave free
        taken from T_other (4, 4) (another method's pose), and the (rotation, translation)
        degrees of freedom the planes fixed."""
        reg = self._solve(frame, view, solve.association, T_other)
        dof = (3 - len(reg.unobservable_rotation_axes), 3 - len(reg.unobservable_translation_dirs))
        return reg.T, dof

    def free_from(
        self, frame: FrameView, view: MapView, solve: PoseSolve, T_other: np.ndarray | None
    ) -> np.ndarray:
        """(4, 4) the pose of `solve`, the directions its planes leave free from T_other
        (`completed`; without T_other, or when the planes fixed all six, its own)."""
        if solve.registration.status not in PARTIAL or T_other is None:
            return solve.T
        return self.completed(frame, view, solve, T_other)[0]

    def _inliers(
        self, frame: FrameView, assoc: Association, reg: RegistrationResult
    ) -> Association | None:
        """`assoc` without the correspondences beyond the residual gates, or None when all
        are within them. Corners go with any of their planes."""
        corner_ok = reg.point_residual_m <= self.config.max_corner_distance_m
        return keep_within(frame, assoc, planes_within_gates(reg, self.config), corner_ok)

    def corner_terms(self, frame: FrameView, view: MapView, assoc: Association) -> PointTerms:
        """Point terms of the associated corners (`sigma_point_m`, split between frame and
        map)."""
        co, cm = assoc.corner_rows()
        return corner_terms(
            frame.corner_points[co], view.corner_points[cm], self.config.sigma_point_m
        )


def planes_within_gates(reg: RegistrationResult, cfg: TrackingConfig) -> np.ndarray:
    """(N,) bool: plane correspondences of `reg` within the residual gates."""
    return (reg.plane_angle_residual_rad <= np.radians(cfg.max_residual_angle_deg)) & (
        np.abs(reg.plane_offset_residual_m) <= cfg.max_residual_offset_m
    )


def trusted(reg: RegistrationResult, cfg: TrackingConfig) -> bool:
    """Whether every plane correspondence of `reg` is within the residual gates."""
    return bool(np.all(planes_within_gates(reg, cfg)))


def plane_constraints(reg: RegistrationResult, terms: dict[str, int]) -> PoseConstraints:
    """The constraints of a closed-form plane pose (from its observability)."""
    return PoseConstraints(
        plane_rotation_dof=3 - len(reg.unobservable_rotation_axes),
        plane_translation_dof=3 - len(reg.unobservable_translation_dirs),
        terms=terms,
    )


def keep_within(
    frame: FrameView, assoc: Association, ok: np.ndarray, corner_ok: np.ndarray
) -> Association | None:
    """`assoc` with the planes `ok` (and the corners `corner_ok` whose planes all stay), or
    None when all are ok."""
    if ok.all() and corner_ok.all():
        return None
    planes = [p for p, keep in zip(assoc.planes, ok, strict=True) if keep]
    kept_obs = {i for i, _ in planes}
    corners = [
        c
        for c, keep in zip(assoc.corners, corner_ok, strict=True)
        if keep and all(int(i) in kept_obs for i in frame.corner_planes[c[0]])
    ]
    return Association(planes=planes, corners=corners)
