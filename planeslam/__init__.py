"""planeslam: RGB-D SLAM with a plane-object map and a GTSAM factor-graph backend."""

from planeslam.camera import CameraConfig
from planeslam.config import PlaneSlamConfig, load_config, resolve_config
from planeslam.dataset import DatasetConfig, Frame, TumDataset
from planeslam.errors import (
    AssociationError,
    ConfigError,
    DatasetFormatError,
    EvaluationError,
    GeometryError,
    PlaneSlamError,
)
from planeslam.map import Map, MapConfig
from planeslam.trajectory import Trajectory, read_tum, write_tum

__version__ = "0.1.0"


def __getattr__(name: str):
    """`planeslam.SLAM` is imported on first use (it loads Open3D)."""
    if name == "SLAM":
        from planeslam.slam import SLAM

        return SLAM
    raise AttributeError(f"module 'planeslam' has no attribute {name!r}")


__all__ = [
    "AssociationError",
    "CameraConfig",
    "ConfigError",
    "DatasetConfig",
    "DatasetFormatError",
    "EvaluationError",
    "Frame",
    "GeometryError",
    "Map",
    "MapConfig",
    "PlaneSlamConfig",
    "PlaneSlamError",
    "SLAM",
    "Trajectory",
    "TumDataset",
    "load_config",
    "read_tum",
    "resolve_config",
    "write_tum",
]
