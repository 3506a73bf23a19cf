"""Typed values that flow between the stages: enums for outcomes, frozen dataclasses for
measurements and estimates. Frames are named in the fields (`_cam`, `_world`); units are
metres and radians; planes are n . x + d = 0 with |n| = 1.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import numpy as np

from planeslam.core.errors import GeometryError
from planeslam.core.geometry import compose_covariance, rigid_pose


class TrackingPath(str, enum.Enum):
    """How tracking found a frame's pose (the value is what `frames.jsonl` records)."""

    FIRST = "first"
    """The first frame (or the first of an empty map): it defines the pose."""
    PLANES = "planes"
    """Closed-form pose from planes and corners matched to the map near the prediction."""
    PLANES_POINTS = "planes+points"
    """One robust estimate: the planes fixed some directions, keypoints, corners or edge
    ends the rest."""
    POINTS = "points"
    """One robust estimate in which planes fixed no direction (keypoints, corners, edges)."""
    RELOCALISED = "relocalised"
    """Whole-map search (corner, plane-triple, edge and keypoint hypotheses), no
    prediction needed."""
    PLANES_ODOMETRY = "planes+odometry"
    """Planes fixed some directions, RGB-D odometry the rest."""
    PLANES_ICP = "planes+icp"
    """Planes fixed some directions, ICP the rest."""
    PLANES_MOTION = "planes+motion"
    """Nothing registered the frame, but its planes agree with the prediction: they fixed
    some directions, the constant-velocity motion the rest (a plain wall sliding by)."""
    ODOMETRY = "odometry"
    """RGB-D odometry alone."""
    ICP = "icp"
    """ICP alone."""
    LOST = "lost"
    """No trustworthy pose."""

    def __str__(self) -> str:
        return self.value

    @property
    def maps(self) -> bool:
        """Whether the pose is accurate enough to go into the map or the graph: fixed by
        the map's planes, corners, edges and keypoints in one estimate, or by planes
        completed by RGB-D odometry (ICP-filled directions were 1.5-2 cm off on the
        synthetic scenes; odometry from a plane pose within 0.1 mm)."""
        return self in _MAPPING_PATHS


_MAPPING_PATHS = frozenset(
    {
        TrackingPath.FIRST,
        TrackingPath.PLANES,
        TrackingPath.RELOCALISED,
        TrackingPath.PLANES_ODOMETRY,
        TrackingPath.PLANES_POINTS,
        TrackingPath.POINTS,
    }
)


class GravitySource(str, enum.Enum):
    """Where a frame's up direction came from."""

    CONFIG = "config"
    """`objects.gravity_up_cam`."""
    PLANE = "plane"
    """The largest floor-, table- or ceiling-like plane of the frame."""
    CAMERA = "camera"
    """Fallback: the camera's -y axis (no horizontal-looking plane)."""

    def __str__(self) -> str:
        return self.value

    @property
    def is_fallback(self) -> bool:
        return self is GravitySource.CAMERA


@dataclass(frozen=True)
class PlaneMeasurement:
    """One plane seen in one frame, camera frame, n . x + d = 0, d > 0 (facing the camera)."""

    id: int
    """The plane's index in its frame."""
    n_cam: np.ndarray
    """(3,) unit normal."""
    d_cam: float
    """Offset [m]."""
    covariance: np.ndarray
    """(3, 3) fit covariance in gtsam OrientedPlane3 local coordinates (two tangent-space
    normal components [rad], then d [m])."""
    correlated_covariance: np.ndarray | None = None
    """(3, 3) covariance, same coordinates, of the sensor's depth error that is correlated
    across the plane (calibration, quantisation; `core.plane_fit.patch_covariance`), which
    the fit, counting pixels as independent, leaves out; None when unknown."""


@dataclass(frozen=True)
class EdgeMeasurement:
    """A real intersection of two planes of one frame (paper eq. 1-6), camera frame."""

    planes: tuple[int, int]
    """Ids of the two planes, smaller first."""
    angle_rad: float
    """Dihedral angle between the two plane regions [rad]."""
    convex: bool
    """True for an edge pointing at the camera (box edge), False for a concave one."""


@dataclass(frozen=True)
class CornerMeasurement:
    """A trihedral corner of one frame: three planes pairwise joined by real edges."""

    planes: tuple[int, int, int]
    """Plane ids, increasing."""
    p_cam: np.ndarray
    """(3,) the point common to the three planes, camera frame [m]."""
    convex_edges: int
    """How many of its three edges are convex (3: box corner, 0: room corner)."""


@dataclass(frozen=True)
class FrameMeasurements:
    """What the landmark factors need of one frame: a few kB, safe to send to a process."""

    timestamp: float
    """[s]"""
    planes: tuple[PlaneMeasurement, ...]
    edges: tuple[EdgeMeasurement, ...]
    corners: tuple[CornerMeasurement, ...]

    def plane(self, plane_id: int) -> PlaneMeasurement:
        """The plane with frame id `plane_id` (KeyError when the frame has none)."""
        for plane in self.planes:
            if plane.id == plane_id:
                return plane
        raise KeyError(plane_id)


@dataclass(frozen=True)
class LoopConstraint:
    """A keyframe placed against an older keyframe it revisits (by the caller's loop
    detector: `KeyframeInput.loops`): a relative pose for the backend's graph."""

    index: int
    """Frame index of the keyframe placed."""
    old_index: int
    """Frame index of the older keyframe."""
    T_old_cam: np.ndarray
    """(4, 4) the keyframe's pose in the older keyframe's camera frame."""
    inliers: int
    """Keypoint matches that agree with the points' pose."""


@dataclass(frozen=True)
class RelativePose:
    """A measured motion (wheel, IMU or visual odometry): frame b's pose in frame a, with
    its uncertainty."""

    T_a_b: np.ndarray
    """(4, 4) rigid transform."""
    covariance: np.ndarray
    """(6, 6) in T_a_b's own tangent space, gtsam's Pose3 order: rotation [rad^2] first,
    then translation [m^2]."""

    @classmethod
    def from_odometry(cls, odometry: Any, name: str = "odometry") -> RelativePose:
        """A `RelativePose`, or a (T_prev_cur (4, 4) or gtsam.Pose3, information (6, 6))
        pair -> RelativePose; GeometryError naming `name` for anything else, a pose that is
        not rigid, or an information matrix that is not symmetric positive definite."""
        if isinstance(odometry, RelativePose):
            return odometry
        if not isinstance(odometry, (tuple, list)) or len(odometry) != 2:
            raise GeometryError(
                f"{name} is a {type(odometry).__name__}, expected (T_prev_cur (4, 4), "
                "information (6, 6)) or a RelativePose"
            )
        T = rigid_pose(odometry[0], f"{name}'s T_prev_cur")
        information = np.asarray(odometry[1], dtype=np.float64)
        if (
            information.shape != (6, 6)
            or not np.all(np.isfinite(information))
            or not np.allclose(information, information.T, rtol=1e-9, atol=1e-12)
            or np.linalg.eigvalsh(0.5 * (information + information.T)).min() <= 0
        ):
            raise GeometryError(
                f"{name}'s information of shape {information.shape}: expected a finite "
                "symmetric positive definite (6, 6), rotation [1/rad^2] first"
            )
        covariance = np.linalg.inv(0.5 * (information + information.T))
        return cls(T, 0.5 * (covariance + covariance.T))

    @classmethod
    def identity(cls) -> RelativePose:
        """No motion, known exactly (the start of a chain)."""
        return cls(np.eye(4), np.zeros((6, 6)))

    @property
    def information(self) -> np.ndarray:
        """(6, 6) inverse of `covariance` (LinAlgError for a chain known exactly)."""
        return np.linalg.inv(self.covariance)

    def then(self, T_b_c: RelativePose) -> RelativePose:
        """This motion followed by `T_b_c` (independent): T_a_c with its covariance."""
        return RelativePose(
            self.T_a_b @ T_b_c.T_a_b,
            compose_covariance(self.covariance, T_b_c.T_a_b, T_b_c.covariance),
        )


@dataclass(frozen=True)
class PlaneEstimate:
    """A plane landmark's estimate, world frame."""

    n_world: np.ndarray
    """(3,) unit normal."""
    d_world: float
    """Offset [m]."""
