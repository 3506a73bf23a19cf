"""The run's configuration: `PlaneSlamConfig` composes the stages' configs (each a leaf
module beside its stage), mirrored by the YAML presets in `configs/`.

Loading rejects unknown keys and names the valid ones (`planeslam.core.config`).
Resolution order for a dataset run:
preset or `--config` file -> the dataset's own `camera.yaml` -> `--camera`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Literal

from planeslam.backend.config import BackendConfig
from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.config import from_mapping, read_yaml, save_yaml, to_mapping
from planeslam.core.errors import ConfigError
from planeslam.frontend.config import IntersectionConfig, ObjectConfig, SegmentationConfig
from planeslam.io.config import DatasetConfig
from planeslam.mapping.config import MapConfig
from planeslam.tracking.config import TrackingConfig

__all__ = [
    "PRESETS",
    "PlaneSlamConfig",
    "RunConfig",
    "from_mapping",
    "guess_preset",
    "load_camera_yaml",
    "load_config",
    "preset_path",
    "read_yaml",
    "resolve_config",
    "save_yaml",
    "to_mapping",
]

PRESETS = ("defaults", "tum_fr1", "tum_fr2", "tum_fr3", "sevenscenes", "synthetic")


@dataclass(frozen=True)
class RunConfig:
    """How a run is made, beyond the stages: saved with every run so that its
    `config.yaml` reproduces it (`planeslam run DATASET --config OUT/config.yaml`)."""

    backend: Literal["isam2", "merge"] = "isam2"
    """'isam2': the GTSAM factor graph; 'merge': the paper's frame-by-frame merging."""
    seed: int = 0
    """Seed of the front end's random generator (the MSAC segmenter's samples)."""
    every: int = 1
    """A dataset run takes every n-th frame."""
    max_frames: int | None = None
    """A dataset run takes at most this many frames (None: all)."""

    def __post_init__(self) -> None:
        if self.backend not in ("isam2", "merge"):
            raise ConfigError(f"run.backend must be 'isam2' or 'merge', got {self.backend!r}")
        if self.every < 1:
            raise ConfigError(f"run.every must be >= 1 (take every n-th frame), got {self.every}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"run.max_frames must be >= 1 or null, got {self.max_frames}")


@dataclass(frozen=True)
class PlaneSlamConfig:
    """Everything a run needs, one section per stage."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    """Intrinsics and depth encoding."""
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """How frames are read and associated."""
    sensor: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise sigma(z) = a + b z^2 of the sensor (segmentation and intersections)."""
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    """Plane segmentation (paper step 2)."""
    intersections: IntersectionConfig = field(default_factory=IntersectionConfig)
    """Real plane intersections (paper eq. 1-6)."""
    objects: ObjectConfig = field(default_factory=ObjectConfig)
    """Plane graph, trihedral angles, objects and classes (paper 4.2-4.3)."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """Frame-to-map association, closed-form pose, ICP and odometry fallbacks (paper 4.4)."""
    map: MapConfig = field(default_factory=MapConfig)
    """The world plane-object map: merging, objects, sparse cloud."""
    backend: BackendConfig = field(default_factory=BackendConfig)
    """The iSAM2 backend: noise, keyframes, landmark factors."""
    run: RunConfig = field(default_factory=RunConfig)
    """Backend choice, seed and frame selection of a run."""


def preset_path(name: str) -> Path:
    """Path of a bundled preset such as 'tum_fr1' (the `configs/` folder)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}")
    return Path(str(resources.files("planeslam.configs").joinpath(f"{name}.yaml")))


def load_config(name_or_path: str | Path | None = None) -> PlaneSlamConfig:
    """Load a preset name ('tum_fr1') or a YAML file path; None gives the defaults."""
    if name_or_path is None:
        return PlaneSlamConfig()
    text = str(name_or_path)
    path = preset_path(text) if text in PRESETS else Path(text)
    if not path.is_file():
        raise ConfigError(
            f"config {text!r}: neither a preset ({', '.join(PRESETS)}) nor a YAML file"
        )
    return from_mapping(PlaneSlamConfig, read_yaml(path), str(path))


def load_camera_yaml(path: Path) -> CameraConfig:
    """Read a dataset's own `camera.yaml` (the keys of `CameraConfig`)."""
    return from_mapping(CameraConfig, read_yaml(path), str(path))


def guess_preset(dataset_dir: Path) -> str | None:
    """Preset implied by a dataset folder's name (TUM 'freiburg1'/'fr1', '7scenes'), if any."""
    name = dataset_dir.resolve().name.lower()
    for key, preset in (
        ("freiburg1", "tum_fr1"),
        ("freiburg2", "tum_fr2"),
        ("freiburg3", "tum_fr3"),
        ("fr1", "tum_fr1"),
        ("fr2", "tum_fr2"),
        ("fr3", "tum_fr3"),
        ("7scenes", "sevenscenes"),
        ("7-scenes", "sevenscenes"),
    ):
        if key in name:
            return preset
    return None


def resolve_config(
    dataset_dir: Path | None = None,
    config: str | Path | None = None,
    camera: str | None = None,
) -> PlaneSlamConfig:
    """The config for a run: `config` (or a preset guessed from the folder name),
    then the folder's `camera.yaml` when present, then the `--camera` override."""
    if config is None and dataset_dir is not None:
        config = guess_preset(dataset_dir)
    cfg = load_config(config)
    if dataset_dir is not None and (dataset_dir / "camera.yaml").is_file():
        cfg = dataclasses.replace(cfg, camera=load_camera_yaml(dataset_dir / "camera.yaml"))
    if camera:
        cfg = dataclasses.replace(cfg, camera=cfg.camera.with_overrides(camera))
    return cfg
