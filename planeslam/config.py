"""The run's configuration: `PlaneSlamConfig` composes the stages' configs (each a leaf
module beside its stage), mirrored by the YAML presets in `configs/`.

Loading rejects unknown keys and names the valid ones (`planeslam.core.config`).
A config is resolved from layers, each overlaid key by key on those below it:

    defaults (the dataclasses) -> preset -> file -> the dataset's camera.yaml
        -> camera override -> key overrides ('section.key=value')

The preset is the one named (`config='tum_fr1'`), or below a file the one the file
names (`base: tum_fr1`, or `base: other.yaml` relative to it, itself layered the same
way), or else the one guessed from the dataset folder's name. `explain_config` also
says which layer set each key.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from planeslam.backend.config import BackendConfig
from planeslam.core.camera import CameraConfig, DepthNoiseConfig, camera_override_values
from planeslam.core.config import (
    ConfigLayer,
    format_with_sources,
    from_mapping,
    parse_override,
    read_yaml,
    resolve_layers,
    save_yaml,
    to_mapping,
)
from planeslam.core.errors import ConfigError
from planeslam.core.safe_files import resolve_path
from planeslam.frontend.config import IntersectionConfig, ObjectConfig, SegmentationConfig
from planeslam.io.config import DatasetConfig
from planeslam.mapping.config import MapConfig
from planeslam.tracking.config import TrackingConfig

if TYPE_CHECKING:
    from planeslam.io.sequence import RgbdDataset

__all__ = [
    "BASIC_KEYS",
    "PRESETS",
    "ConfigLayer",
    "PlaneSlamConfig",
    "ResolvedConfig",
    "RunConfig",
    "camera_layer",
    "config_layers",
    "configuration_markdown",
    "explain_config",
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

BASIC_KEYS: tuple[str, ...] = (
    # the camera: intrinsics and depth encoding
    "camera.fx",
    "camera.fy",
    "camera.cx",
    "camera.cy",
    "camera.width",
    "camera.height",
    "camera.depth_scale",
    "camera.invalid_depth",
    "camera.distortion",
    # the sensor's depth noise (planeslam calibrate fits it)
    "sensor.sigma_a_m",
    "sensor.sigma_b_per_m",
    # reading frames: folders and ROS bags
    "dataset.max_time_difference_s",
    "dataset.undistort",
    "dataset.bag.rgb_topic",
    "dataset.bag.depth_topic",
    "dataset.bag.camera_info_topic",
    "dataset.bag.intrinsics",
    "dataset.bag.groundtruth",
    # frame selection and the run
    "run.backend",
    "run.seed",
    "run.every",
    "run.max_frames",
    "run.start_pose",
    # the backend's main budget
    "backend.window_keyframes",
    "backend.final_iterations",
    "backend.separate_process",
    "backend.keyframe_max_frames",
    # what the front end looks at, and how densely
    "segmentation.method",
    "segmentation.max_depth_m",
    "segmentation.organized.pixel_stride",
)
"""The keys a user may need: `planeslam config show` prints these, `--advanced` every key,
and docs/configuration.md lists them first. Every other key stays valid in YAML files and
`--set`; this list only decides what is shown first."""


@dataclass(frozen=True)
class RunConfig:
    """How a run is made, beyond the stages: saved with every run so that its
    `config.yaml` reproduces it (`planeslam run DATASET --config OUT/config.yaml`)."""

    backend: Literal["isam2", "merge"] = "isam2"
    """'isam2': the GTSAM factor graph; 'merge': the paper's frame-by-frame merging."""
    seed: int = 0
    """Seed of the front end's random generator (the MSAC segmenter's samples)."""
    every: int = 1
    """A dataset run takes every n-th frame (>= 1)."""
    max_frames: int | None = None
    """A dataset run takes at most this many frames (>= 1; null: all)."""
    start_pose: Literal["groundtruth", "identity"] = "groundtruth"
    """Pose of the first frame, which fixes the world frame of the trajectory and map.
    'groundtruth': the ground-truth pose of the first frame when it is known (a dataset
    with ground truth, or `T_world_first` given to `SLAM`), so estimates and truth share
    a frame; the identity when it is not. 'identity': always the identity (the world is
    the first camera's frame), ground truth or not."""

    def __post_init__(self) -> None:
        if self.backend not in ("isam2", "merge"):
            raise ConfigError(f"run.backend must be 'isam2' or 'merge', got {self.backend!r}")
        if self.start_pose not in ("groundtruth", "identity"):
            raise ConfigError(
                f"run.start_pose must be 'groundtruth' or 'identity', got {self.start_pose!r}"
            )
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
    """Backend choice, seed, frame selection and start pose of a run."""


def preset_path(name: str) -> Path:
    """Path of a bundled preset such as 'tum_fr1' (the `configs/` folder)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}")
    return Path(str(resources.files("planeslam.configs").joinpath(f"{name}.yaml")))


def load_config(name_or_path: str | Path | None = None) -> PlaneSlamConfig:
    """Load a preset name ('tum_fr1') or a YAML file path (over the preset it names as
    `base`, else over the defaults); None gives the defaults."""
    if name_or_path is None:
        return PlaneSlamConfig()
    return explain_config(config=name_or_path).config


def load_camera_yaml(path: Path) -> CameraConfig:
    """Read a dataset's own `camera.yaml` (the keys of `CameraConfig`)."""
    return from_mapping(CameraConfig, read_yaml(path), str(path))


def guess_preset(dataset_dir: Path) -> str | None:
    """Preset implied by a dataset folder's name (TUM 'freiburg1'/'fr1', '7scenes'), if any."""
    name = resolve_path(dataset_dir).name.lower()
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


@dataclass(frozen=True)
class ResolvedConfig:
    """A resolved config and where each of its values came from."""

    config: PlaneSlamConfig
    sources: Mapping[str, str]
    """Dotted key ('camera.fx') -> the label of the layer that set it last ('preset
    tum_fr1', 'file my.yaml', 'camera.yaml', ...), or 'default'."""
    layers: tuple[str, ...]
    """The layers applied over the defaults, in order (later ones win), in full."""

    def to_yaml(self, keys: Collection[str] | None = None) -> str:
        """The config as YAML with the source of every key as a comment after it; it loads
        back (`load_config`) as the same config. `keys` (dotted): only those (e.g.
        `BASIC_KEYS`), the others left at what the layers make them."""
        applied = "".join(f"#   {layer}\n" for layer in self.layers) or "#   (none)\n"
        shown = "" if keys is None else f"# {len(keys)} of {len(self.sources)} keys shown\n"
        return (
            "# planeslam config: the defaults overlaid by these layers (later ones win):\n"
            + applied
            + shown
            + format_with_sources(self.config, self.sources, keys=keys)
        )

    def replaced(self, config: PlaneSlamConfig, label: str) -> ResolvedConfig:
        """This provenance for `config`, a changed copy of this config (e.g. by what a
        dataset says of its camera): the keys whose values differ are marked `label`."""
        old, new = _flat(to_mapping(self.config)), _flat(to_mapping(config))
        changed = {key for key in self.sources if old[key] != new[key]}
        if not changed:
            return self
        sources = {key: label if key in changed else src for key, src in self.sources.items()}
        return ResolvedConfig(config, sources, self.layers + (label,))


def _flat(mapping: Mapping[str, object], prefix: str = "") -> dict[str, object]:
    """Nested mapping -> {dotted key: value}."""
    out: dict[str, object] = {}
    for key, value in mapping.items():
        if isinstance(value, Mapping):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _preset_layer(name: str, why: str = "") -> list[ConfigLayer]:
    """The layer of a bundled preset; none for 'defaults' (the dataclasses' own values)."""
    if name == "defaults":
        return []
    path = preset_path(name)
    return [ConfigLayer(read_yaml(path) or {}, f"preset {name}{why}", f"preset {name}")]


def _file_layers(
    path: Path, fallback: list[ConfigLayer], chain: tuple[Path, ...] = ()
) -> list[ConfigLayer]:
    """A config file's layer over its `base` (a preset name, or a YAML file relative to it,
    layered the same way) or, without one, over `fallback`."""
    data = read_yaml(path)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys, got {type(data).__name__}")
    data = dict(data)
    if "base" not in data:
        below = fallback
    else:
        base = data.pop("base")
        if not isinstance(base, str) or not base:
            raise ConfigError(
                f"{path}: base expects a preset name ({', '.join(PRESETS)}) or a YAML file "
                f"path, got {base!r}"
            )
        if base in PRESETS:
            below = _preset_layer(base)
        else:
            base_path = Path(os.path.normpath(path.parent / base))  # absolute bases stay
            if not base_path.is_file():
                raise ConfigError(
                    f"{path}: base {base!r} is neither a preset ({', '.join(PRESETS)}) nor a "
                    f"YAML file ({base_path} not found)"
                )
            seen = chain + (resolve_path(path),)
            if resolve_path(base_path) in seen:
                raise ConfigError(f"{path}: base {base!r} leads back to {base_path} (a cycle)")
            below = _file_layers(base_path, fallback, seen)
    return below + [ConfigLayer(data, str(path), f"file {path}")]


def camera_layer(text: str, label: str = "camera override") -> ConfigLayer:
    """The layer of a camera override 'fx,fy,cx,cy[,depth_scale]'."""
    return ConfigLayer({"camera": camera_override_values(text)}, f"{label} {text!r}", label)


def config_layers(
    dataset_dir: Path | None = None,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> list[ConfigLayer]:
    """The layers of a run's config, in the order they apply (see the module docstring).

    config: a preset name or a YAML file (None: the preset guessed from the folder name,
    or the defaults); camera: 'fx,fy,cx,cy[,depth_scale]' or a layer; overrides:
    'section.key=value' strings (`planeslam.core.config.parse_override`) or layers."""
    guessed: list[ConfigLayer] = []
    preset = guess_preset(dataset_dir) if dataset_dir is not None else None
    if preset is not None:
        assert dataset_dir is not None
        guessed = _preset_layer(preset, f" (guessed from the folder name {dataset_dir.name!r})")
    text = None if config is None else str(config)
    if text is None:
        layers = guessed
    elif text in PRESETS:
        layers = _preset_layer(text)
    elif Path(text).is_file():
        layers = _file_layers(Path(text), guessed)
    else:
        raise ConfigError(
            f"config {text!r}: neither a preset ({', '.join(PRESETS)}) nor a YAML file"
        )
    camera_yaml = None if dataset_dir is None else dataset_dir / "camera.yaml"
    if camera_yaml is not None and camera_yaml.is_file():
        data = read_yaml(camera_yaml)
        layers.append(
            ConfigLayer({"camera": {} if data is None else data}, str(camera_yaml), "camera.yaml")
        )
    if camera:
        layers.append(camera_layer(camera) if isinstance(camera, str) else camera)
    layers += [parse_override(o) if isinstance(o, str) else o for o in overrides]
    return layers


def explain_config(
    dataset_dir: Path | None = None,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> ResolvedConfig:
    """The config for a run (arguments as `config_layers`) with the source of every key."""
    layers = config_layers(dataset_dir, config, camera, overrides)
    cfg, sources = resolve_layers(PlaneSlamConfig, layers)
    return ResolvedConfig(cfg, sources, tuple(layer.source for layer in layers))


def resolve_config(
    dataset_dir: Path | None = None,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> PlaneSlamConfig:
    """The config for a run: the preset (named, named as a file's `base`, or guessed from
    the folder name), then the `config` file, the folder's `camera.yaml` when present, the
    camera override and the key overrides, each overlaid key by key."""
    return explain_config(dataset_dir, config, camera, overrides).config


CONFIGURATION_HEADER = """\
Every key of a run's configuration, with the values it takes, its default and its meaning
(units in the name or in brackets). A config is built from layers, each overlaid key by
key: the defaults below; a preset (`--config tum_fr1`, or a file's `base: tum_fr1`, or the
one guessed from the dataset folder's name); the `--config` file; the dataset's
`camera.yaml`; `--camera fx,fy,cx,cy[,depth_scale]`; `--set SECTION.KEY=VALUE` (the value in
YAML syntax); for `planeslam run`, its flags (`--backend`, `--every`, `--max-frames`,
`--seed`, `--start-pose`). An unknown key is an error that lists the valid ones.

The basic keys are the ones a user may need; `planeslam config show` prints them with
their values and where each came from, `planeslam config show --advanced` every key. The
advanced keys are tuned on the robustness benchmark's tuning set (docs/benchmarks.md);
change them to experiment."""


def configuration_markdown(command: str = "planeslam config docs --markdown FILE") -> str:
    """docs/configuration.md: every key of `PlaneSlamConfig` from its docstring, the
    `BASIC_KEYS` first (`planeslam.core.config_docs`)."""
    from planeslam.core.config_docs import reference_markdown

    return reference_markdown(PlaneSlamConfig, BASIC_KEYS, CONFIGURATION_HEADER, command)


def open_configured(
    path: str | Path, config: PlaneSlamConfig
) -> tuple[RgbdDataset, PlaneSlamConfig]:
    """The sequence at `path` read with `config`, and `config` with the sequence's camera
    (a bag's camera_info replaces the configured intrinsics)."""
    from planeslam.io.sequence import open_dataset  # reading images: not at start-up

    dataset = open_dataset(path, config.camera, config.dataset)
    return dataset, dataclasses.replace(config, camera=dataset.camera)
