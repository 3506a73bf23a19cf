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
    "DatasetConfig": "planeslam.io.config",
    "DatasetFormatError": "planeslam.core.errors",
    "EvaluationError": "planeslam.core.errors",
    "Frame": "planeslam.io.dataset",
    "GeometryError": "planeslam.core.errors",
    "Map": "planeslam.mapping.world_map",
    "MapConfig": "planeslam.mapping.config",
    "MapError": "planeslam.core.errors",
    "PlaneSlamConfig": "planeslam.config",
    "PlaneSlamError": "planeslam.core.errors",
    "SLAM": "planeslam.slam",
    "Trajectory": "planeslam.io.trajectory",
    "TumDataset": "planeslam.io.dataset",
    "load_config": "planeslam.config",
    "read_tum": "planeslam.io.trajectory",
    "resolve_config": "planeslam.config",
    "write_tum": "planeslam.io.trajectory",
}
"""Public name -> the module that defines it."""

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
    "MapError",
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

if TYPE_CHECKING:
    from planeslam.config import PlaneSlamConfig, load_config, resolve_config
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
    from planeslam.io.config import DatasetConfig
    from planeslam.io.dataset import Frame, TumDataset
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
