"""planeslam: RGB-D SLAM with a plane-object map and a GTSAM factor-graph backend.

The public names below are imported on first use (PEP 562), so `import planeslam`
and `import planeslam.frontend` load no more than they need (no gtsam, no Open3D).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "AssociationError": "planeslam.core.errors",
    "CameraConfig": "planeslam.core.camera",
    "ConfigError": "planeslam.core.errors",
    "CornerMeasurement": "planeslam.core.types",
    "DatasetConfig": "planeslam.io.config",
    "DatasetFormatError": "planeslam.core.errors",
    "EdgeMeasurement": "planeslam.core.types",
    "EvaluationError": "planeslam.core.errors",
    "Frame": "planeslam.io.dataset",
    "FrameMeasurements": "planeslam.core.types",
    "FrameObservation": "planeslam.frontend.pipeline",
    "FrontEnd": "planeslam.frontend.pipeline",
    "FrontEndConfig": "planeslam.frontend.config",
    "GeometryError": "planeslam.core.errors",
    "LandmarkConfig": "planeslam.factors.config",
    "LandmarkKeys": "planeslam.factors.config",
    "LandmarkObject": "planeslam.factors.landmark_objects",
    "Map": "planeslam.mapping.world_map",
    "MapConfig": "planeslam.mapping.config",
    "MapError": "planeslam.core.errors",
    "PlaneEstimate": "planeslam.core.types",
    "PlaneLandmarks": "planeslam.factors.landmarks",
    "PlaneMeasurement": "planeslam.core.types",
    "PlaneSlamConfig": "planeslam.config",
    "PlaneSlamError": "planeslam.core.errors",
    "RelativePose": "planeslam.core.types",
    "RosBagDataset": "planeslam.io.rosbag",
    "RecoveringISAM2": "planeslam.factors.recovery",
    "ResolvedConfig": "planeslam.config",
    "SLAM": "planeslam.slam",
    "TrackingPath": "planeslam.core.types",
    "Trajectory": "planeslam.io.trajectory",
    "TumDataset": "planeslam.io.dataset",
    "explain_config": "planeslam.config",
    "load_config": "planeslam.config",
    "open_dataset": "planeslam.io.sequence",
    "read_tum": "planeslam.io.trajectory",
    "resolve_config": "planeslam.config",
    "write_tum": "planeslam.io.trajectory",
}
"""Public name -> the module that defines it."""

__all__ = [
    "AssociationError",
    "CameraConfig",
    "ConfigError",
    "CornerMeasurement",
    "DatasetConfig",
    "DatasetFormatError",
    "EdgeMeasurement",
    "EvaluationError",
    "Frame",
    "FrameMeasurements",
    "FrameObservation",
    "FrontEnd",
    "FrontEndConfig",
    "GeometryError",
    "LandmarkConfig",
    "LandmarkKeys",
    "LandmarkObject",
    "Map",
    "MapConfig",
    "MapError",
    "PlaneEstimate",
    "PlaneLandmarks",
    "PlaneMeasurement",
    "PlaneSlamConfig",
    "PlaneSlamError",
    "RelativePose",
    "RosBagDataset",
    "RecoveringISAM2",
    "ResolvedConfig",
    "SLAM",
    "TrackingPath",
    "Trajectory",
    "TumDataset",
    "explain_config",
    "load_config",
    "open_dataset",
    "read_tum",
    "resolve_config",
    "write_tum",
]

if TYPE_CHECKING:
    from planeslam.config import (
        PlaneSlamConfig,
        ResolvedConfig,
        explain_config,
        load_config,
        resolve_config,
    )
    from planeslam.core.camera import CameraConfig
    from planeslam.core.errors import (
        AssociationError,
        ConfigError,
        DatasetFormatError,
        EvaluationError,
        GeometryError,
        MapError,
        PlaneSlamError,
    )
    from planeslam.core.types import (
        CornerMeasurement,
        EdgeMeasurement,
        FrameMeasurements,
        PlaneEstimate,
        PlaneMeasurement,
        RelativePose,
        TrackingPath,
    )
    from planeslam.factors.config import LandmarkConfig, LandmarkKeys
    from planeslam.factors.landmark_objects import LandmarkObject
    from planeslam.factors.landmarks import PlaneLandmarks
    from planeslam.factors.recovery import RecoveringISAM2
    from planeslam.frontend.config import FrontEndConfig
    from planeslam.frontend.pipeline import FrameObservation, FrontEnd
    from planeslam.io.config import DatasetConfig
    from planeslam.io.dataset import Frame, TumDataset
    from planeslam.io.rosbag import RosBagDataset
    from planeslam.io.sequence import open_dataset
    from planeslam.io.trajectory import Trajectory, read_tum, write_tum
    from planeslam.mapping.config import MapConfig
    from planeslam.mapping.world_map import Map
    from planeslam.slam import SLAM


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'planeslam' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
