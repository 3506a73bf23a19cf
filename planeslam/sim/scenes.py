"""The named synthetic scenes and their camera paths (`box_room_circle`,
`room_boxes_loop`, `zigzag_panels`), each returning the scene (`planeslam.sim.scene_model`)
and a camera `Trajectory` (T_world_cam, camera frame x right, y down, z forward).
`SceneOptions` varies a named scene without changing its geometry: the camera's height,
the point it looks at, where the path starts, and the surfaces' appearance (`Texture`).
`look_at`, `periodic_shake` and `apply_shake` build camera paths.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.core.errors import ConfigError, GeometryError
from planeslam.io.trajectory import Trajectory
from planeslam.sim.scene_model import (
    DEFAULT_AMBIENT,
    DEFAULT_LIGHT_WORLD,
    PLAIN_REFLECTANCE,
    TEXTURE_PATTERNS,
    WORLD_UP,
    Box,
    Panel,
    Scene,
    SceneCorner,
    SceneEdge,
    SceneObject,
    ScenePlane,
    Structure,
    Texture,
    make_scene,
    rot_z,
)

__all__ = [
    "DEFAULT_AMBIENT",
    "DEFAULT_LIGHT_WORLD",
    "PLAIN_REFLECTANCE",
    "SCENES",
    "TEXTURE_PATTERNS",
    "WORLD_UP",
    "Box",
    "Panel",
    "Scene",
    "SceneCorner",
    "SceneEdge",
    "SceneObject",
    "SceneOptions",
    "ScenePlane",
    "Structure",
    "Texture",
    "apply_shake",
    "box_room_circle",
    "get_scene",
    "look_at",
    "make_scene",
    "periodic_shake",
    "rot_z",
    "room_boxes_loop",
    "zigzag_panels",
]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """Camera poses looking from `eye` to `target`: (N, 3), (N, 3) -> (N, 4, 4) T_world_cam.

    Camera frame x right, y down, z forward; the image is upright for world `up`.
    Raises GeometryError when a view direction is parallel to `up`.
    """
    eye = np.atleast_2d(np.asarray(eye, dtype=np.float64))
    target = np.atleast_2d(np.asarray(target, dtype=np.float64))
    z = target - eye
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, up)
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise GeometryError("look_at: view direction parallel to the up vector")
    x /= norm
    y = np.cross(z, x)
    T = np.tile(np.eye(4), (len(eye), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, z, eye
    return T


def periodic_shake(
    phase: np.ndarray, rng: np.random.Generator, amplitude: float, harmonics: tuple[int, int]
) -> np.ndarray:
    """Smooth seeded perturbation, periodic in `phase` (N,) with period 1 -> (N, 3).

    A sum of sines at integer harmonics in [harmonics[0], harmonics[1]] with
    random phases, scaled so each component's RMS is about `amplitude`.
    """
    k = np.arange(harmonics[0], harmonics[1] + 1)
    coeff = rng.normal(size=(3, len(k))) / np.sqrt(len(k)) * amplitude * np.sqrt(2)
    phases = rng.uniform(0, 2 * np.pi, size=(3, len(k)))
    arg = 2 * np.pi * phase[:, None, None] * k[None, None, :] + phases[None]
    return np.sum(coeff[None] * np.sin(arg), axis=2)


def apply_shake(T_world_cam: np.ndarray, dt_m: np.ndarray, drot_rad: np.ndarray) -> np.ndarray:
    """Perturb (N, 4, 4) poses by world translations (N, 3) [m] and camera-frame
    rotation vectors (N, 3) [rad]."""
    out = T_world_cam.copy()
    out[:, :3, :3] = T_world_cam[:, :3, :3] @ Rotation.from_rotvec(drot_rad).as_matrix()
    out[:, :3, 3] += dt_m
    return out


@dataclass(frozen=True)
class SceneOptions:
    """Variations of a named scene (`get_scene`): where the camera goes and what the
    surfaces look like; the geometry and its truth stay the same. None keeps the scene's
    own value."""

    camera_height_m: float | None = None
    """Camera height above the floor [m] (the mean height where the path undulates)."""
    target_height_m: float | None = None
    """Height above the floor of the points the camera looks at [m]."""
    start_azimuth_deg: float | None = None
    """`box_room_circle` only: azimuth of the first pose on the circle [deg] (0: on the
    world x axis, looking square at the box's +x face)."""
    texture: Texture | None = None
    """Appearance of the planes (default: the scene's own seed and ranges)."""

    def __post_init__(self) -> None:
        for name in ("camera_height_m", "target_height_m", "start_azimuth_deg"):
            value = getattr(self, name)
            if value is not None and not np.isfinite(float(value)):
                raise ConfigError(f"scene options: {name} must be a finite number, got {value!r}")
        if self.camera_height_m is not None and self.camera_height_m <= 0:
            raise ConfigError(
                f"scene options: camera_height_m must be > 0 m, got {self.camera_height_m}"
            )

    def reject(self, scene: str, *names: str) -> None:
        """ConfigError when any of the option `names` is set: `scene` does not take it."""
        given = [n for n in names if getattr(self, n) is not None]
        if given:
            raise ConfigError(f"scene {scene!r} does not take the option(s) {', '.join(given)}")


def _check_frames(frames: int | None, default: int) -> int:
    n = default if frames is None else frames
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"frames must be a whole number >= 1, got {frames!r}")
    return int(n)


# --------------------------------------------------------------------------- scenes


def box_room_circle(
    frames: int | None = None,
    rng: np.random.Generator | None = None,
    options: SceneOptions | None = None,
) -> tuple[Scene, Trajectory]:
    """The paper's second experiment (Section 5): a box in a small square room.

    Room: 1.88 x 1.88 m floor, walls 1.1 m high (the paper gives only the floor
    size), centred on the world origin, floor at z = 0, ceiling present.
    Box: 0.38 x 0.29 x 0.19 m, on the floor at the centre, long side along the
    world x axis, no bottom face. Camera: on a Nao-sized robot, 0.50 m above
    the floor, walking a circle of radius 0.7 m around the box in `frames`
    equal steps (default 24, at azimuths 7.5 deg + k * 360 / frames, so no view
    is square to a box face), looking at the point 0.05 m above the box's
    centre on the floor (about 33 deg down). Every frame sees the box top, at
    least one side, the floor, two walls and room corners; a second side only
    where the camera is outside both face slabs of the box, which on this
    circle excludes about 12 deg either side of the box's x axis and 16 deg
    either side of its y axis, so 14 of the 24 default views show three box
    faces with measured depth. One frame per step, 1 s apart from t = 0.
    `rng` is unused (the path is exact). `options` change the camera height
    (0.50 m), the look-at height (0.05 m), the first azimuth (7.5 deg) and the
    texture (seed 1).
    """
    n = _check_frames(frames, 24)
    opt = options or SceneOptions()
    room = Box("room", np.array((0.0, 0.0, 0.55)), np.array((1.88, 1.88, 1.10)), kind="room")
    box = Box("box", np.array((0.0, 0.0, 0.095)), np.array((0.38, 0.29, 0.19)), omit_faces=("-z",))
    scene = make_scene("box_room_circle", (room, box), texture=opt.texture or 1)
    start = 7.5 if opt.start_azimuth_deg is None else opt.start_azimuth_deg
    eye_height = 0.50 if opt.camera_height_m is None else opt.camera_height_m
    look_height = 0.05 if opt.target_height_m is None else opt.target_height_m
    azimuth = np.deg2rad(start) + 2 * np.pi * np.arange(n) / n
    eye = np.stack([0.7 * np.cos(azimuth), 0.7 * np.sin(azimuth), np.full(n, eye_height)], axis=1)
    target = np.tile([0.0, 0.0, look_height], (n, 1))
    return scene, Trajectory(np.arange(n, dtype=np.float64), look_at(eye, target))


def room_boxes_loop(
    frames: int | None = None,
    rng: np.random.Generator | None = None,
    options: SceneOptions | None = None,
) -> tuple[Scene, Trajectory]:
    """A 4 x 3.5 x 2.5 m room with four boxes and a hand-held loop at 30 Hz.

    Room centred on the world origin, floor at z = 0. Boxes on the floor (no
    bottom faces), of different sizes and yaws, at least 0.3 m from the walls.
    Camera: an ellipse of semi-axes 1.1 x 0.8 m at about 1.45 m height (with a
    slow 0.1 m vertical wave), looking across the room at a point on an inner
    ellipse 0.6 m above the floor that leads the camera by 150 deg, so views
    take in the boxes, the floor and two walls. Seeded hand-shake (`rng`):
    smooth periodic noise of about 8 mm and 0.5 deg RMS at harmonics 6-25 of
    the loop, so the path is smooth and returns exactly to its start:
    frame i has loop phase i / (frames - 1); the last pose equals the first
    (a loop closure). Default 300 frames, 30 Hz from t = 0. `options` change the
    mean camera height (1.45 m), the look-at height (0.6 m) and the texture (seed 2).
    """
    n = _check_frames(frames, 300)
    rng = rng if rng is not None else np.random.default_rng(0)
    opt = options or SceneOptions()
    opt.reject("room_boxes_loop", "start_azimuth_deg")
    eye_height = 1.45 if opt.camera_height_m is None else opt.camera_height_m
    look_height = 0.6 if opt.target_height_m is None else opt.target_height_m
    room = Box("room", np.array((0.0, 0.0, 1.25)), np.array((4.0, 3.5, 2.5)), kind="room")
    boxes = (
        room,
        Box(
            "crate",
            np.array((0.9, 0.7, 0.225)),
            np.array((0.6, 0.45, 0.45)),
            rot_z(0.35),
            omit_faces=("-z",),
        ),
        Box(
            "cube",
            np.array((-1.0, 0.55, 0.25)),
            np.array((0.5, 0.5, 0.5)),
            rot_z(-0.5),
            omit_faces=("-z",),
        ),
        Box(
            "cabinet",
            np.array((0.2, -1.2, 0.4)),
            np.array((0.9, 0.45, 0.8)),
            rot_z(0.1),
            omit_faces=("-z",),
        ),
        Box(
            "shoebox",
            np.array((-0.6, -0.5, 0.06)),
            np.array((0.33, 0.2, 0.12)),
            rot_z(0.9),
            omit_faces=("-z",),
        ),
    )
    scene = make_scene("room_boxes_loop", boxes, texture=opt.texture or 2)
    phase = np.arange(n) / max(n - 1, 1)
    a = 2 * np.pi * phase
    eye = np.stack([1.1 * np.cos(a), 0.8 * np.sin(a), eye_height + 0.1 * np.sin(2 * a)], axis=1)
    b = a + np.deg2rad(150.0)
    target = np.stack([0.7 * np.cos(b), 0.5 * np.sin(b), np.full(n, look_height)], axis=1)
    T = look_at(eye, target)
    T = apply_shake(
        T, periodic_shake(phase, rng, 0.008, (6, 25)), periodic_shake(phase, rng, 0.009, (6, 25))
    )
    return scene, Trajectory(np.arange(n) / 30.0, T)


def zigzag_panels(
    frames: int | None = None,
    rng: np.random.Generator | None = None,
    options: SceneOptions | None = None,
) -> tuple[Scene, Trajectory]:
    """A zig-zag of four panels standing on the floor (like TUM fr3/structure_texture_far).

    Room 10 x 8 x 3 m centred on the world origin (floor z = 0), so its walls are
    mostly beyond the sensor's range. Structure 'zigzag': four 1.0 x 0.8 m
    vertical panels whose bottom edges follow a zig-zag on the floor between
    y = 0 and y = 0.64 m (panels at +-40 deg to the x axis), spanning x in
    [-1.53, 1.53] m; neighbours share a vertical edge. Camera: about 2.2 m in
    front of it (y = -2.2 m) at 1.3 m height, looking at the structure about
    20 deg down, moving sideways from x = -0.9 to +0.9 m at 30 Hz with seeded
    hand-shake of about 5 mm and 0.4 deg RMS. Default 150 frames (5 s). `options`
    change the camera height (1.3 m), the look-at height (0.5 m) and the texture (seed 3).
    """
    n = _check_frames(frames, 150)
    rng = rng if rng is not None else np.random.default_rng(0)
    opt = options or SceneOptions()
    opt.reject("zigzag_panels", "start_azimuth_deg")
    eye_height = 1.3 if opt.camera_height_m is None else opt.camera_height_m
    look_height = 0.5 if opt.target_height_m is None else opt.target_height_m
    room = Box("room", np.array((0.0, 0.0, 1.5)), np.array((10.0, 8.0, 3.0)), kind="room")
    angle = np.deg2rad(40.0)
    width, height = 1.0, 0.8
    dx, dy = width * np.cos(angle), width * np.sin(angle)
    xs = (np.arange(5) - 2) * dx
    ys = np.array([0.0, dy, 0.0, dy, 0.0])
    panels = []
    for k in range(4):
        p0 = np.array([xs[k], ys[k], 0.0])
        p1 = np.array([xs[k + 1], ys[k + 1], 0.0])
        u = (p1 - p0) / np.linalg.norm(p1 - p0)
        v = WORLD_UP
        normal = np.cross(u, v)
        if normal[1] > 0:  # face the camera side (-y) by convention
            normal = -normal
        R = np.stack([u, v, normal], axis=1)
        centre = (p0 + p1) / 2 + v * height / 2
        panels.append(Panel(f"panel_{k}", centre, np.array((width, height)), R))
    scene = make_scene(
        "zigzag_panels", (room,), (Structure("zigzag", tuple(panels)),), opt.texture or 3
    )
    phase = np.arange(n) / max(n - 1, 1)
    x = -0.9 + 1.8 * phase
    eye = np.stack([x, np.full(n, -2.2), np.full(n, eye_height)], axis=1)
    target = np.stack([0.6 * x, np.full(n, 0.3), np.full(n, look_height)], axis=1)
    T = look_at(eye, target)
    T = apply_shake(
        T, periodic_shake(phase, rng, 0.005, (3, 12)), periodic_shake(phase, rng, 0.007, (3, 12))
    )
    return scene, Trajectory(np.arange(n) / 30.0, T)


SceneFactory = Callable[
    [int | None, np.random.Generator | None, SceneOptions | None], tuple[Scene, Trajectory]
]

SCENES: dict[str, SceneFactory] = {
    "box_room_circle": box_room_circle,
    "room_boxes_loop": room_boxes_loop,
    "zigzag_panels": zigzag_panels,
}
"""Scene name -> factory(frames, rng, options) returning (scene, trajectory)."""


def get_scene(
    name: str,
    frames: int | None = None,
    rng: np.random.Generator | None = None,
    options: SceneOptions | None = None,
) -> tuple[Scene, Trajectory]:
    """Build a named scene and its trajectory; ConfigError listing the names when unknown,
    or naming an option the scene does not take."""
    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r}; scenes: {', '.join(SCENES)}")
    return SCENES[name](frames, rng, options)
