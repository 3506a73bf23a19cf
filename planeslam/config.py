"""Typed configuration: frozen dataclasses mirrored by YAML files in `configs/`.

Each stage owns its config dataclass in its own module; `PlaneSlamConfig`
composes them. Loading rejects unknown keys and names the valid ones, so a
misspelt key never passes silently. Resolution order for a dataset run:
preset or `--config` file -> the dataset's own `camera.yaml` -> `--camera`.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml

from planeslam.backend import BackendConfig
from planeslam.camera import CameraConfig
from planeslam.dataset import DatasetConfig
from planeslam.errors import ConfigError
from planeslam.intersections import IntersectionConfig
from planeslam.map import MapConfig
from planeslam.objects import ObjectConfig
from planeslam.segmentation import SegmentationConfig
from planeslam.tracking import TrackingConfig

T = TypeVar("T")

PRESETS = ("defaults", "tum_fr1", "tum_fr2", "tum_fr3", "sevenscenes", "synthetic")


@dataclass(frozen=True)
class PlaneSlamConfig:
    """Everything a run needs, one section per stage."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    """Intrinsics and depth encoding."""
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    """How frames are read and associated."""
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


def from_mapping(cls: type[T], data: Any, source: str, section: str = "") -> T:
    """Build dataclass `cls` from a nested mapping, rejecting unknown keys.

    `source` names the file (or option) for error messages; `section` is the
    dotted path of this mapping inside it.
    """
    where = f"{source}: {section}" if section else source
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of keys, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(str, unknown))}; "
            f"valid keys: {', '.join(fields)}"
        )
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = f"{section}.{name}" if section else name
        kwargs[name] = _coerce(hints[name], value, source, sub)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _coerce(hint: Any, value: Any, source: str, key: str) -> Any:
    """Convert a YAML value to the field's annotated type, or fail naming the key."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        return from_mapping(hint, value, source, key)  # type: ignore[arg-type]
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, source, key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {key} expects a list, got {value!r}")
        (item,) = typing.get_args(hint)[:1]
        return tuple(_coerce(item, v, source, key) for v in value)
    if origin is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(f"{source}: {key} must be one of {list(allowed)}, got {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key} expects true or false, got {value!r}")
        return value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {key} expects a number, got {value!r}")
        if hint is int and float(value) != int(value):
            raise ConfigError(f"{source}: {key} expects a whole number, got {value!r}")
        return hint(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key} expects a string, got {value!r}")
        return value
    return value


def read_yaml(path: Path) -> Any:
    """Parse a YAML file, or raise a ConfigError naming it."""
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"{path}: not a readable YAML file ({reason})") from None


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


def to_mapping(obj: Any) -> Any:
    """Dataclass -> plain dict/list tree, ready for YAML or JSON."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_mapping(v) for v in obj]
    return obj


def save_yaml(obj: Any, path: Path) -> None:
    """Write a dataclass (a resolved config) as YAML."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(to_mapping(obj), fh, sort_keys=False)
