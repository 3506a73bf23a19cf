"""GTSAM factors for plane and trihedral-corner landmarks (installed as `planeslam.factors`).

Variables: camera poses T_world_cam (Pose3), plane landmarks in the world frame
(OrientedPlane3, n . x + d = 0), corner landmarks in the world frame (Point3).
Keys come from `LandmarkKeys`, whose symbol characters the caller chooses.

Pattern to follow: give every pose an odometry factor (BetweenFactorPose3) or a
prior. A pose observed only through planes needs three planes with linearly
independent normals; with fewer, ISAM2 and Gauss-Newton raise "Indeterminate
linear system" (a RuntimeError); `RecoveringISAM2` recovers from it (`recovery`).

Each factory returns a ready gtsam factor; the Python (CustomFactor) ones cost
about an order of magnitude more to linearise than built-ins and hold the GIL,
so `plane_factor` (built-in) is the default and `robust_plane_factor` the
choice when outliers are expected.

The names are imported on first use, so `planeslam.factors.config` loads no gtsam.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "AddedFactors": ".landmarks",
    "LandmarkConfig": ".config",
    "LandmarkKeys": ".config",
    "LandmarkObject": ".landmark_objects",
    "PlaneLandmarks": ".landmarks",
    "PoseGateSigmas": ".gating",
    "RecoveringISAM2": ".recovery",
    "UpdateOutcome": ".recovery",
    "corner_factor": ".corner_observation",
    "measured_plane": ".plane_observation",
    "orthogonal_planes_factor": ".plane_structure",
    "parallel_planes_factor": ".plane_structure",
    "plane_factor": ".plane_observation",
    "point_on_plane_factor": ".point_on_plane",
    "pose_gate_sigmas": ".gating",
    "robust_plane_factor": ".plane_observation",
    "same_plane_factor": ".plane_structure",
    "structural_factor": ".plane_structure",
}
"""Public name -> the module (relative to this package) that defines it."""

__all__ = [
    "AddedFactors",
    "LandmarkConfig",
    "LandmarkKeys",
    "LandmarkObject",
    "PlaneLandmarks",
    "PoseGateSigmas",
    "RecoveringISAM2",
    "UpdateOutcome",
    "corner_factor",
    "measured_plane",
    "orthogonal_planes_factor",
    "parallel_planes_factor",
    "plane_factor",
    "point_on_plane_factor",
    "pose_gate_sigmas",
    "robust_plane_factor",
    "same_plane_factor",
    "structural_factor",
]

if TYPE_CHECKING:
    from .config import LandmarkConfig, LandmarkKeys
    from .corner_observation import corner_factor
    from .gating import PoseGateSigmas, pose_gate_sigmas
    from .landmark_objects import LandmarkObject
    from .landmarks import AddedFactors, PlaneLandmarks
    from .plane_observation import measured_plane, plane_factor, robust_plane_factor
    from .plane_structure import (
        orthogonal_planes_factor,
        parallel_planes_factor,
        same_plane_factor,
        structural_factor,
    )
    from .point_on_plane import point_on_plane_factor
    from .recovery import RecoveringISAM2, UpdateOutcome


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'planeslam.factors' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
