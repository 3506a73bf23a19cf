"""Synthetic RGB-D sequences written to disk with their exact truth (the project's
built-in data): `synthesize` writes a named scene as a TUM-layout folder with
`camera.yaml` and a `truth.json` holding the exact planes, objects, edges, corners and
trajectory (and how it was rendered); `load_truth` reads it back. `SynthOptions` bundles
a noise model, a field of view and `SceneOptions` (camera height, look-at height, first
azimuth, texture) for the CLI and the benchmark suite."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from planeslam.core.bounded_parse import read_json_file
from planeslam.core.camera import CameraConfig
from planeslam.core.config import save_yaml, to_mapping
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.geometry import quat_from_pose
from planeslam.io.trajectory import Trajectory, write_tum
from planeslam.sim.noise import NoiseModel, noise_model_name, noise_model_of
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import (
    SCENES,
    WORLD_UP,
    Scene,
    SceneOptions,
    Texture,
    get_scene,
)

__all__ = [
    "TRUTH_SCHEMA",
    "SynthOptions",
    "SynthResult",
    "camera_with_hfov",
    "load_truth",
    "render_sequence",
    "synthesize",
    "truth_dict",
    "write_sequence",
]

logger = logging.getLogger(__name__)

TRUTH_SCHEMA = "planeslam.truth/1"


@dataclass(frozen=True)
class SynthResult:
    """What `synthesize` wrote."""

    out_dir: Path
    """The sequence folder (TUM layout)."""
    num_frames: int
    """Number of RGB-D frames written."""
    scene_name: str
    """Name of the scene (a key of SCENES)."""
    truth_path: Path
    """truth.json."""
    groundtruth_path: Path
    """groundtruth.txt (TUM trajectory)."""
    camera_path: Path
    """camera.yaml (the CameraConfig keys)."""
    rgb_paths: tuple[Path, ...] = field(repr=False)
    """rgb/<timestamp>.png, one per frame."""
    depth_paths: tuple[Path, ...] = field(repr=False)
    """depth/<timestamp>.png (16-bit, value / depth_scale = metres), one per frame."""


def _vec(a: np.ndarray) -> list[float]:
    return [float(x) + 0.0 for x in np.asarray(a, dtype=np.float64).ravel()]  # no -0.0


def _dump_truth(truth: dict[str, Any], path: Path) -> None:
    """JSON with one line per plane, object, edge, corner and pose (readable, diffable)."""
    lines = ["{"]
    items = list(truth.items())
    for k, (key, value) in enumerate(items):
        comma = "," if k < len(items) - 1 else ""
        if isinstance(value, list) and value and isinstance(value[0], (dict, list)):
            rows = ",\n".join(f"  {json.dumps(v)}" for v in value)
            lines.append(f" {json.dumps(key)}: [\n{rows}\n ]{comma}")
        else:
            lines.append(f" {json.dumps(key)}: {json.dumps(value)}{comma}")
    lines.append("}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def truth_dict(
    scene: Scene,
    trajectory: Trajectory,
    camera: CameraConfig,
    seed: int,
    rendering: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The truth.json content (schema TRUTH_SCHEMA); world frame, metres, seconds.
    `rendering` (how the frames were rendered: noise model and its constants, scene
    options) is stored under 'rendering' when given."""
    t, q = quat_from_pose(trajectory.T_world_cam)
    rows = np.concatenate([trajectory.timestamps[:, None], t, q], axis=1)
    extra = {} if rendering is None else {"rendering": rendering}
    return {
        "schema": TRUTH_SCHEMA,
        "scene": scene.name,
        "seed": int(seed),
        "world_up": _vec(WORLD_UP),
        "camera": to_mapping(camera),
        **extra,
        "planes": [
            {
                "id": p.id,
                "name": p.name,
                "object": p.object_id,
                "normal": _vec(p.normal),
                "d": float(p.d),
                "two_sided": p.two_sided,
                "polygon": (np.asarray(p.polygon).round(12) + 0.0).tolist(),
            }
            for p in scene.planes
        ],
        "objects": [
            {
                "id": o.id,
                "name": o.name,
                "class": o.object_class,
                "planes": list(o.plane_ids),
                "size_m": [float(s) for s in o.size_m],
            }
            for o in scene.objects
        ],
        "edges": [
            {
                "planes": list(e.plane_ids),
                "length_m": e.length_m,
                "segment": (e.segment.round(12) + 0.0).tolist(),
            }
            for e in scene.edges
        ],
        "corners": [{"planes": list(c.plane_ids), "point": _vec(c.point)} for c in scene.corners],
        "trajectory": rows.tolist(),
    }


def load_truth(path: str | Path) -> dict[str, Any]:
    """Read a truth.json (file or sequence folder); DatasetFormatError unless its
    schema is TRUTH_SCHEMA."""
    path = Path(path)
    if path.is_dir():
        path = path / "truth.json"
    data = read_json_file(path, DatasetFormatError, what="truth file")
    schema = data.get("schema") if isinstance(data, dict) else None
    if schema != TRUTH_SCHEMA:
        raise DatasetFormatError(f"{path}: expected schema {TRUTH_SCHEMA!r}, got {schema!r}")
    missing = [k for k in ("planes", "objects", "edges", "corners", "trajectory") if k not in data]
    if missing:
        raise DatasetFormatError(f"{path}: truth is missing key(s) {', '.join(missing)}")
    return data


def camera_with_hfov(hfov_deg: float, camera: CameraConfig | None = None) -> CameraConfig:
    """`camera` (default `CameraConfig()`) with square pixels and the principal point at the
    image centre, its focal length set for a horizontal field of view of hfov_deg [deg]:
    fx = fy = (width / 2) / tan(hfov / 2). ConfigError outside (0, 180) deg."""
    base = camera or CameraConfig()
    if not 0.0 < float(hfov_deg) < 180.0:
        raise ConfigError(f"horizontal field of view must be in (0, 180) deg, got {hfov_deg}")
    f = (base.width / 2.0) / float(np.tan(np.deg2rad(hfov_deg) / 2.0))
    return replace(base, fx=f, fy=f, cx=(base.width - 1) / 2.0, cy=(base.height - 1) / 2.0)


@dataclass(frozen=True)
class SynthOptions:
    """How to render a named scene beyond its defaults (`planeslam synth` flags, the
    benchmark suite's `synth:` of a scene); the defaults render the scene as it is."""

    noise_model: Literal["kinect", "disparity", "tof"] = "kinect"
    """Depth error model (module docstring), with its default constants."""
    hfov_deg: float | None = None
    """Horizontal field of view [deg] of the 640 x 480 camera (`camera_with_hfov`);
    None: `CameraConfig()` (fx 525 px, 62.7 deg)."""
    scene: SceneOptions = field(default_factory=SceneOptions)
    """Camera height, look-at height, first azimuth and texture of the scene."""
    label: str = ""
    """Short name of this rendering (suite rows, folders); default: built from the options."""

    def __post_init__(self) -> None:
        noise_model_of(self.noise_model)  # a clear error for an unknown name
        if self.hfov_deg is not None:
            camera_with_hfov(self.hfov_deg)
        if self.label and not self.label.replace("_", "").replace("-", "").isalnum():
            raise ConfigError(f"synth label {self.label!r}: use letters, digits, '-' and '_' only")

    def camera(self, base: CameraConfig | None = None) -> CameraConfig:
        """The camera to render with: `base` (default `CameraConfig()`), its field of view
        set when `hfov_deg` is."""
        base = base or CameraConfig()
        return base if self.hfov_deg is None else camera_with_hfov(self.hfov_deg, base)

    @property
    def tag(self) -> str:
        """'' for the defaults, else `label` or a name built from what differs
        ('disparity-fov57-h0.65-az0-tex7')."""
        if self.label:
            return self.label
        o = self.scene
        parts: list[str] = []
        if self.noise_model != "kinect":
            parts.append(self.noise_model)
        for prefix, value in (
            ("fov", self.hfov_deg),
            ("h", o.camera_height_m),
            ("look", o.target_height_m),
            ("az", o.start_azimuth_deg),
        ):
            if value is not None:
                parts.append(f"{prefix}{value:g}")
        if o.texture is not None:
            t, d = o.texture, Texture()
            parts.append(f"tex{t.seed}")
            if t.brightness != d.brightness:
                parts.append("b{:g}-{:g}".format(*t.brightness))
            if t.cell_m != d.cell_m:
                parts.append("c{:g}-{:g}".format(*t.cell_m))
        return "-".join(parts)


def render_sequence(
    scene_name: str,
    out_dir: str | Path,
    options: SynthOptions,
    frames: int | None = None,
    seed: int = 0,
) -> SynthResult:
    """`synthesize` with the camera, noise model and scene options of `options`."""
    return synthesize(
        scene_name,
        out_dir,
        frames=frames,
        seed=seed,
        camera=options.camera(),
        noise_model=options.noise_model,
        scene_options=options.scene,
    )


def synthesize(
    scene_name: str,
    out_dir: str | Path,
    frames: int | None = None,
    seed: int = 0,
    camera: CameraConfig | None = None,
    noise: bool = True,
    noise_model: str | NoiseModel | None = None,
    scene_options: SceneOptions | None = None,
) -> SynthResult:
    """Render the named scene into `out_dir` as a TUM-layout sequence with truth.

    Writes rgb/*.png, depth/*.png (16-bit, camera.depth_scale per metre, 0
    invalid), rgb.txt, depth.txt, associations.txt, groundtruth.txt,
    camera.yaml and truth.json (with the noise model, its constants and the
    scene options under 'rendering'). `frames` resamples the scene's path to
    that many poses (None: the scene's default); `seed` drives the trajectory's
    hand-shake and the sensor noise; `noise_model` as in `render_frame`;
    `scene_options` vary the camera path and texture. ConfigError for an unknown
    scene or noise model, an option the scene does not take, or frames < 1.
    """
    if scene_name not in SCENES:
        raise ConfigError(f"unknown scene {scene_name!r}; scenes: {', '.join(SCENES)}")
    model = noise_model_of(noise_model)
    traj_seq, noise_seq = np.random.SeedSequence(seed).spawn(2)
    scene, trajectory = get_scene(
        scene_name, frames, np.random.default_rng(traj_seq), scene_options
    )
    return write_sequence(
        scene,
        trajectory,
        out_dir,
        seed,
        camera=camera,
        noise=noise,
        noise_model=model,
        rng=np.random.default_rng(noise_seq),
        rendering={"scene_options": to_mapping(scene_options or SceneOptions())},
    )


def write_sequence(
    scene: Scene,
    trajectory: Trajectory,
    out_dir: str | Path,
    seed: int,
    camera: CameraConfig | None = None,
    noise: bool = True,
    noise_model: str | NoiseModel | None = None,
    rng: np.random.Generator | None = None,
    rendering: dict[str, Any] | None = None,
) -> SynthResult:
    """Render `scene` along `trajectory` into `out_dir` as a TUM-layout sequence with
    truth (the files `synthesize` lists). `rng` draws the sensor noise (default: seeded
    with `seed`); `rendering` adds entries to truth.json's 'rendering' (how the sequence
    was made). ConfigError for a distorted camera or a depth range the PNGs cannot hold."""
    model = noise_model_of(noise_model)
    camera = camera or CameraConfig()
    if camera.is_distorted:
        raise ConfigError(
            "synthesize renders an ideal pinhole camera: pass a CameraConfig with distortion=()"
        )
    if model.max_range_m * camera.depth_scale > 65535:
        raise ConfigError(
            f"camera.depth_scale {camera.depth_scale} cannot store {model.max_range_m} m "
            f"in a 16-bit depth PNG (need depth_scale <= {int(65535 / model.max_range_m)})"
        )
    rng = rng if rng is not None else np.random.default_rng(seed)
    scene_name = scene.name
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rgb_paths: list[Path] = []
    depth_paths: list[Path] = []
    names: list[str] = []
    for stamp, T in zip(trajectory.timestamps, trajectory.T_world_cam, strict=True):
        frame = render_frame(scene, T, camera, rng, noise=noise, noise_model=model)
        name = f"{stamp:.6f}.png"
        raw = np.clip(np.rint(frame.depth_m.astype(np.float64) * camera.depth_scale), 0, 65535)
        rgb_path, depth_path = out / "rgb" / name, out / "depth" / name
        if not cv2.imwrite(str(depth_path), raw.astype(np.uint16)):
            raise DatasetFormatError(f"{depth_path}: could not write the depth image")
        if not cv2.imwrite(str(rgb_path), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)):
            raise DatasetFormatError(f"{rgb_path}: could not write the colour image")
        rgb_paths.append(rgb_path)
        depth_paths.append(depth_path)
        names.append(name)
    stamps = [f"{s:.6f}" for s in trajectory.timestamps]
    header = (
        f"# planeslam synthetic scene {scene_name}, seed {seed}, "
        f"noise model {noise_model_name(model) if noise else 'none'}\n"
    )
    (out / "rgb.txt").write_text(
        header
        + "# timestamp filename\n"
        + "".join(f"{s} rgb/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    (out / "depth.txt").write_text(
        header
        + "# timestamp filename\n"
        + "".join(f"{s} depth/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    (out / "associations.txt").write_text(
        "".join(f"{s} rgb/{n} {s} depth/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    write_tum(out / "groundtruth.txt", trajectory, header=f"planeslam synthetic {scene_name}")
    save_yaml(camera, out / "camera.yaml")
    truth_path = out / "truth.json"
    rendering = {
        "noise": noise,
        "noise_model": noise_model_name(model),
        "noise_constants": to_mapping(model),
        **(rendering or {}),
    }
    _dump_truth(truth_dict(scene, trajectory, camera, seed, rendering), truth_path)
    logger.info("wrote %d frames of %s to %s", len(names), scene_name, out)
    return SynthResult(
        out_dir=out,
        num_frames=len(names),
        scene_name=scene_name,
        truth_path=truth_path,
        groundtruth_path=out / "groundtruth.txt",
        camera_path=out / "camera.yaml",
        rgb_paths=tuple(rgb_paths),
        depth_paths=tuple(depth_paths),
    )
