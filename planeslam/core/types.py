"""Typed values that flow between the stages: enums for outcomes, frozen dataclasses for
measurements and estimates. Frames are named in the fields (`_cam`, `_world`); units are
metres and radians; planes are n . x + d = 0 with |n| = 1.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


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
    """A keyframe placed against an older keyframe it revisits, by keypoint matches and
    both keyframes' planes (`planeslam.tracking.loops`): a relative pose for the backend's
    graph."""

    index: int
    """Frame index of the keyframe placed."""
    old_index: int
    """Frame index of the older keyframe."""
    T_old_cam: np.ndarray
    """(4, 4) the keyframe's pose in the older keyframe's camera frame."""
    inliers: int
    """Keypoint matches that agree with the points' pose."""


@dataclass(frozen=True)
class PlaneEstimate:
    """A plane landmark's estimate, world frame."""

    n_world: np.ndarray
    """(3,) unit normal."""
    d_world: float
    """Offset [m]."""
