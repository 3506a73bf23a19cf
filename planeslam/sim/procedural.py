"""Procedural sequences: a room, furniture, appearance, a depth model and a camera path,
all drawn from one seed, for the robustness benchmark (`planeslam bench robust`).

`draw_recipe(seed)` decides what a sequence is made of (a `Recipe`: trajectory kind,
texture, depth model, room shape, furniture); `build_sequence(recipe)` turns it into a
`Scene` and a `Trajectory`, drawing sizes and placements from the same seed;
`write_procedural(recipe, folder)` renders it as a normal dataset folder (TUM layout,
camera.yaml, groundtruth.txt, truth.json with object sizes and the recipe). The same
seed always gives the same bytes.

Kinds (each recipe names one of each):
- trajectory (`TRAJECTORY_KINDS`): 'handheld' (30 Hz, 5 s, a smooth sweep with
  hand shake), 'robot_steps' (a robot stepping 10-20 cm and turning 5-15 deg every
  0.5-1 s), 'orbit' (robot steps on a circle around an object, 1 s apart: the paper's
  experiment), 'keyframes' (a hand-held path sampled at 1-5 Hz), 'rotation' (turning
  in place at 30 Hz), 'wall' (sliding along one wall 0.6-1 m away: few planes in
  view), 'loop' (30 Hz, 8 s, a closed loop that returns to its start);
- texture (`TEXTURE_KINDS`): 'none', 'repetitive' (a checkerboard), 'noise'
  (natural-looking, every patch unique), 'posters' (plain walls with posters),
  'low_contrast' (the noise pattern at a fifth of its amplitude);
- depth model (`DEPTH_MODELS`): 'kinect', 'disparity' (structured light), 'tof';
- room: square or not, closed or open (one wall missing, the floor running on 4 m
  beyond it), lighting drawn
  (light direction, ambient share, brightness);
- furniture (`FURNITURE_KINDS`): cubes (symmetric), boxes, cabinets (against a
  wall), tables (a slab at 0.72 m) and shelves (panels), none to four of them, kept
  0.45 m clear of the camera's path.

World frame z up, floor at z = 0, metres and seconds; poses T_world_cam (camera x
right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.io.trajectory import Trajectory
from planeslam.sim.scenes import (
    Box,
    Panel,
    Scene,
    Structure,
    Texture,
    apply_shake,
    look_at,
    make_scene,
    periodic_shake,
    rot_z,
)
from planeslam.sim.sequence import SynthResult, write_sequence

TRAJECTORY_KINDS = (
    "handheld",
    "robot_steps",
    "orbit",
    "keyframes",
    "rotation",
    "wall",
    "loop",
)
TEXTURE_KINDS = ("none", "repetitive", "noise", "posters", "low_contrast")
DEPTH_MODELS = ("kinect", "disparity", "tof")
FURNITURE_KINDS = ("cube", "box", "cabinet", "table", "shelf")

_PATH_CLEARANCE_M = 0.45
"""Furniture footprints stay this far from every camera position [m]."""
_WALL_MARGIN_M = 0.6
"""Camera positions stay this far from the walls [m] (except the 'wall' path)."""
GENERATOR_VERSION = 2
"""Changes whenever a recipe's sequence changes; stored in truth.json, so a benchmark
renders a folder again when it was made by another version."""


@dataclass(frozen=True)
class Recipe:
    """What one procedural sequence is made of; `build_sequence` draws the rest."""

    seed: int
    """Seed of every draw (sizes, placements, path, texture, sensor noise)."""
    trajectory: str
    """One of TRAJECTORY_KINDS."""
    texture: str
    """One of TEXTURE_KINDS."""
    depth_model: str
    """One of DEPTH_MODELS."""
    square_room: bool
    """A square floor (symmetric under quarter turns) or an oblong one."""
    open_room: bool
    """One wall missing, the floor running on beyond it (depth there out of range)."""
    furniture: tuple[str, ...]
    """Kinds of furniture, each one of FURNITURE_KINDS ('orbit' circles the first)."""

    def __post_init__(self) -> None:
        for name, value, kinds in (
            ("trajectory", self.trajectory, TRAJECTORY_KINDS),
            ("texture", self.texture, TEXTURE_KINDS),
            ("depth_model", self.depth_model, DEPTH_MODELS),
        ):
            if value not in kinds:
                raise ConfigError(f"recipe {name} must be one of {', '.join(kinds)}, got {value!r}")
        bad = [f for f in self.furniture if f not in FURNITURE_KINDS]
        if bad:
            raise ConfigError(
                f"recipe furniture {bad} unknown; kinds: {', '.join(FURNITURE_KINDS)}"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"recipe seed must be a whole number >= 0, got {self.seed!r}")

    def record(self) -> dict[str, object]:
        """The recipe as truth.json stores it (JSON types: furniture a list), to compare
        with a stored one."""
        record = asdict(self)
        record["furniture"] = list(self.furniture)
        return record

    @property
    def name(self) -> str:
        """Folder and row name: 's007-orbit-posters-tof'."""
        return f"s{self.seed:03d}-{self.trajectory}-{self.texture}-{self.depth_model}"

    @property
    def symmetric(self) -> bool:
        """A square closed room whose furniture is only cubes: it looks the same after
        quarter turns except for texture."""
        return self.square_room and not self.open_room and set(self.furniture) <= {"cube"}


def draw_recipe(
    seed: int,
    trajectory: str | None = None,
    texture: str | None = None,
    depth_model: str | None = None,
) -> Recipe:
    """The recipe of seed `seed`; a kind given here is used instead of drawn."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be a whole number >= 0, got {seed!r}")
    gen = np.random.default_rng([int(seed), 0])
    drawn_trajectory = str(gen.choice(TRAJECTORY_KINDS))
    drawn_texture = str(gen.choice(TEXTURE_KINDS))
    drawn_depth = str(gen.choice(DEPTH_MODELS))
    square = bool(gen.random() < 0.5)
    open_room = bool(gen.random() < 0.3)
    count = int(gen.integers(0, 5))
    furniture = tuple(str(f) for f in gen.choice(FURNITURE_KINDS, size=count))
    kind = trajectory or drawn_trajectory
    if kind == "orbit" and (not furniture or furniture[0] not in ("cube", "box")):
        # an orbit circles a box: the paper's (any proportions) or a cube
        furniture = (str(gen.choice(("cube", "box"))), *furniture[:2])
    return Recipe(
        seed=int(seed),
        trajectory=kind,
        texture=texture or drawn_texture,
        depth_model=depth_model or drawn_depth,
        square_room=square,
        open_room=open_room,
        furniture=furniture,
    )


# --------------------------------------------------------------------------- paths


def _room_size(recipe: Recipe, gen: np.random.Generator) -> np.ndarray:
    """(3,) room length, width, height [m]."""
    if recipe.trajectory == "orbit":
        side = gen.uniform(1.9, 3.2)  # the paper's room is 1.88 m square
    else:
        side = gen.uniform(2.6, 4.5)
    other = side if recipe.square_room else side * gen.uniform(1.2, 1.5)
    return np.array([side, min(other, 5.5), gen.uniform(2.2, 2.8)])


def _shake(T: np.ndarray, gen: np.random.Generator, metres: float, radians: float) -> np.ndarray:
    phase = np.linspace(0.0, 1.0, len(T))
    return apply_shake(
        T, periodic_shake(phase, gen, metres, (3, 15)), periodic_shake(phase, gen, radians, (3, 15))
    )


def _sweep(
    half: np.ndarray, gen: np.random.Generator, n: int, length_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth hand-held sweep inside the room: eye and look-at points (n, 3). The eye
    moves along a segment with ease-in and ease-out; the view turns smoothly by 20-60 deg
    about the vertical while looking 15-35 deg down."""
    span = np.maximum(half[:2] - _WALL_MARGIN_M, 0.2)
    start = gen.uniform(-span, span)
    heading = gen.uniform(0.0, 2 * np.pi)
    direction = np.array([np.cos(heading), np.sin(heading)])
    end = np.clip(start + length_m * direction, -span, span)
    s = np.linspace(0.0, 1.0, n)
    ease = 3 * s**2 - 2 * s**3
    xy = start + (end - start) * ease[:, None]
    height = gen.uniform(1.0, 1.6)
    eye = np.column_stack([xy, height + 0.05 * np.sin(2 * np.pi * s)])
    yaw0 = np.arctan2(-start[1], -start[0]) + gen.uniform(-0.8, 0.8)  # roughly inward
    yaw = yaw0 + gen.choice((-1.0, 1.0)) * np.deg2rad(gen.uniform(20.0, 60.0)) * ease
    pitch = np.deg2rad(gen.uniform(15.0, 35.0))
    look = np.column_stack([np.cos(yaw), np.sin(yaw), np.full(n, -np.tan(pitch))])
    return eye, eye + look


def _steps(half: np.ndarray, gen: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Robot steps of 10-20 cm, turning 5-15 deg each, away from the walls: (n, 2)
    positions and (n,) headings [rad]."""
    span = np.maximum(half[:2] - _WALL_MARGIN_M, 0.2)
    xy = np.zeros((n, 2))
    heading = np.zeros(n)
    xy[0] = gen.uniform(-span, span) * 0.5
    heading[0] = gen.uniform(0.0, 2 * np.pi)
    turn_sign = gen.choice((-1.0, 1.0))
    for k in range(1, n):
        turn = turn_sign * np.deg2rad(gen.uniform(5.0, 15.0))
        ahead = xy[k - 1] + 0.2 * np.array([np.cos(heading[k - 1]), np.sin(heading[k - 1])])
        if np.any(np.abs(ahead) > span):  # a wall ahead: turn toward the room's centre
            to_centre = np.arctan2(-xy[k - 1, 1], -xy[k - 1, 0])
            gap = (to_centre - heading[k - 1] + np.pi) % (2 * np.pi) - np.pi
            turn = np.sign(gap) * np.deg2rad(15.0)
        heading[k] = heading[k - 1] + turn
        step = gen.uniform(0.10, 0.20)
        xy[k] = xy[k - 1] + step * np.array([np.cos(heading[k]), np.sin(heading[k])])
        xy[k] = np.clip(xy[k], -span, span)
    return xy, heading


def _step_times(gen: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(gen.uniform(lo, hi, size=n - 1))])


def _path(
    recipe: Recipe, half: np.ndarray, centre_xy: np.ndarray, gen: np.random.Generator
) -> Trajectory:
    """The camera path of the recipe's trajectory kind (room of half extents `half`,
    `centre_xy` the object an orbit circles)."""
    kind = recipe.trajectory
    if kind in ("handheld", "keyframes"):
        n = 150 if kind == "handheld" else 40 * 30
        eye, target = _sweep(half, gen, n, gen.uniform(1.0, 1.8) * (1 if n == 150 else 3))
        T = _shake(look_at(eye, target), gen, 0.006, 0.008)
        stamps = np.arange(n) / 30.0
        if kind == "keyframes":
            stride = int(gen.integers(6, 31))  # 5 Hz .. 1 Hz
            keep = np.arange(0, n, stride)[:40]
            return Trajectory(stamps[keep], T[keep])
        return Trajectory(stamps, T)
    if kind == "robot_steps":
        n = 32
        xy, heading = _steps(half, gen, n)
        height = gen.uniform(0.5, 1.0)
        pitch = np.deg2rad(gen.uniform(8.0, 25.0))
        eye = np.column_stack([xy, np.full(n, height)])
        look = np.column_stack([np.cos(heading), np.sin(heading), -np.full(n, np.tan(pitch))])
        return Trajectory(_step_times(gen, n, 0.5, 1.0), look_at(eye, eye + look))
    if kind == "orbit":
        n = int(gen.integers(24, 37))
        radius = gen.uniform(0.7, 1.1)
        start = gen.uniform(0.0, 2 * np.pi)
        azimuth = start + 2 * np.pi * np.arange(n) / n
        height = gen.uniform(0.45, 0.9)
        eye = np.column_stack(
            [
                centre_xy + radius * np.column_stack([np.cos(azimuth), np.sin(azimuth)]),
                np.full(n, height),
            ]
        )
        target = np.tile([*centre_xy, gen.uniform(0.0, 0.2)], (n, 1))
        return Trajectory(_step_times(gen, n, 0.9, 1.1), look_at(eye, target))
    if kind == "rotation":
        n = 90
        span = np.maximum(half[:2] - _WALL_MARGIN_M - 0.3, 0.1)
        eye = np.tile([*gen.uniform(-span, span), gen.uniform(1.0, 1.5)], (n, 1))
        s = np.linspace(0.0, 1.0, n)
        yaw0 = gen.uniform(0.0, 2 * np.pi)
        yaw = yaw0 + np.deg2rad(gen.uniform(60.0, 120.0)) * (3 * s**2 - 2 * s**3)
        pitch = np.deg2rad(gen.uniform(10.0, 30.0)) + np.deg2rad(8.0) * np.sin(2 * np.pi * s)
        look = np.column_stack([np.cos(yaw), np.sin(yaw), -np.tan(pitch)])
        T = look_at(eye, eye + look)
        phase = np.linspace(0.0, 1.0, n)
        T = apply_shake(T, np.zeros((n, 3)), periodic_shake(phase, gen, 0.006, (3, 15)))
        return Trajectory(np.arange(n) / 30.0, T)
    if kind == "wall":
        n = 120
        axis = int(gen.integers(0, 2))
        side = float(gen.choice((-1.0, 1.0)))
        distance = gen.uniform(0.6, 1.0)
        along = 1 - axis
        reach = max(half[along] - 0.8, 0.3)
        s = np.linspace(-1.0, 1.0, n) * min(reach, gen.uniform(0.5, 0.8))
        eye = np.zeros((n, 3))
        eye[:, axis] = side * (half[axis] - distance)
        eye[:, along] = s
        eye[:, 2] = gen.uniform(1.0, 1.5)
        target = eye.copy()
        target[:, axis] = side * half[axis]
        target[:, along] += gen.uniform(-0.3, 0.3)
        target[:, 2] = eye[:, 2] - gen.uniform(0.0, 0.6)
        T = _shake(look_at(eye, target), gen, 0.004, 0.006)
        return Trajectory(np.arange(n) / 30.0, T)
    if kind == "loop":
        n = 240
        phase = np.arange(n) / (n - 1)
        a = 2 * np.pi * phase + gen.uniform(0.0, 2 * np.pi)
        radii = np.maximum(half[:2] - _WALL_MARGIN_M - 0.2, 0.3) * gen.uniform(0.5, 0.9)
        height = gen.uniform(1.1, 1.6)
        eye = np.column_stack([radii[0] * np.cos(a), radii[1] * np.sin(a), np.full(n, height)])
        lead = a + np.deg2rad(gen.uniform(120.0, 180.0))
        target = np.column_stack(
            [0.6 * half[0] * np.cos(lead), 0.6 * half[1] * np.sin(lead), np.full(n, 0.5)]
        )
        T = look_at(eye, target)
        T = apply_shake(
            T,
            periodic_shake(phase, gen, 0.006, (6, 25)),
            periodic_shake(phase, gen, 0.008, (6, 25)),
        )
        return Trajectory(np.arange(n) / 30.0, T)
    raise ConfigError(f"unknown trajectory kind {kind!r}")  # pragma: no cover - checked


# --------------------------------------------------------------------------- furniture


def _furniture_piece(
    kind: str, name: str, xy: np.ndarray, yaw: float, gen: np.random.Generator
) -> tuple[Box | None, Structure | None, np.ndarray]:
    """One piece at floor position `xy` and yaw: (box or None, structure or None,
    (2,) footprint half extents along its own axes [m])."""
    R = rot_z(yaw)
    if kind == "cube":
        s = gen.uniform(0.3, 0.6)
        size = np.array([s, s, s])
    elif kind == "box":
        size = np.array([gen.uniform(0.25, 0.7), gen.uniform(0.2, 0.6), gen.uniform(0.15, 0.5)])
    elif kind == "cabinet":
        size = np.array([gen.uniform(0.5, 1.0), gen.uniform(0.35, 0.5), gen.uniform(0.7, 1.6)])
    elif kind == "table":
        size = np.array([gen.uniform(0.8, 1.4), gen.uniform(0.6, 0.9), 0.04])
        box = Box(name, np.array([*xy, 0.72]), size, R)
        return box, None, size[:2] / 2
    else:  # shelf: two sides and 3-4 boards, open front and back
        width, depth = gen.uniform(0.6, 1.0), gen.uniform(0.3, 0.4)
        height = gen.uniform(1.0, 1.8)
        boards = int(gen.integers(3, 5))
        u, v = R[:, 0], R[:, 1]
        up = np.array([0.0, 0.0, 1.0])
        centre = np.array([*xy, 0.0])
        panels = [
            Panel(
                f"side{k}",
                centre + sgn * width / 2 * u + up * height / 2,
                np.array([depth, height]),
                np.column_stack([v, up, u]),
            )
            for k, sgn in enumerate((-1.0, 1.0))
        ]
        for b in range(boards):
            z = 0.05 + (height - 0.1) * b / (boards - 1)
            panels.append(
                Panel(
                    f"board{b}",
                    centre + up * z,
                    np.array([width, depth]),
                    np.column_stack([u, v, up]),
                )
            )
        return None, Structure(name, tuple(panels)), np.array([width, depth]) / 2
    box = Box(name, np.array([*xy, size[2] / 2]), size, R, omit_faces=("-z",))
    return box, None, size[:2] / 2


def _footprint_clear(
    xy: np.ndarray, yaw: float, half_fp: np.ndarray, points_xy: np.ndarray, margin: float
) -> bool:
    """Whether no point of (N, 2) lies within `margin` of the yawed rectangle."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = (points_xy - xy) @ np.array([[c, -s], [s, c]])
    outside = np.maximum(np.abs(local) - half_fp, 0.0)
    return bool(np.all(np.linalg.norm(outside, axis=1) > margin)) if len(points_xy) else True


def _place_furniture(
    recipe: Recipe,
    half: np.ndarray,
    path_xy: np.ndarray,
    centre_xy: np.ndarray,
    gen: np.random.Generator,
) -> tuple[list[Box], list[Structure]]:
    """Furniture in the room, clear of the path and of each other; a piece that finds no
    place in 40 tries is left out (the truth then has no such object)."""
    boxes: list[Box] = []
    structures: list[Structure] = []
    taken: list[np.ndarray] = []  # corner points of the pieces placed so far
    for k, kind in enumerate(recipe.furniture):
        name = f"{kind}{k}"
        for _ in range(40):
            yaw = gen.uniform(0.0, np.pi)
            if k == 0 and recipe.trajectory == "orbit":
                xy = centre_xy.copy()
            elif kind == "cabinet":  # against a wall
                axis = int(gen.integers(0, 2))
                xy = gen.uniform(-half[:2] + 0.6, half[:2] - 0.6)
                xy[axis] = float(gen.choice((-1.0, 1.0))) * (half[axis] - 0.3)
                yaw = 0.0 if axis == 1 else np.pi / 2
            else:
                xy = gen.uniform(-half[:2] + 0.5, half[:2] - 0.5)
            box, structure, half_fp = _furniture_piece(kind, name, xy, yaw, gen)
            corners = xy + (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half_fp) @ np.array(
                [[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]]
            )
            inside = np.all(np.abs(corners) < half[:2] - 0.05)
            clear = _footprint_clear(xy, yaw, half_fp, path_xy, _PATH_CLEARANCE_M)
            apart = all(_footprint_clear(xy, yaw, half_fp, other, 0.25) for other in taken)
            if inside and clear and apart or (k == 0 and recipe.trajectory == "orbit"):
                if box is not None:
                    boxes.append(box)
                if structure is not None:
                    structures.append(structure)
                taken.append(corners)
                break
    return boxes, structures


def build_sequence(recipe: Recipe) -> tuple[Scene, Trajectory]:
    """The scene and camera path of `recipe` (world frame z up, floor z = 0)."""
    gen = np.random.default_rng([recipe.seed, 1])
    size = _room_size(recipe, gen)
    half = size / 2
    centre_xy = gen.uniform(-0.15, 0.15, size=2) if recipe.trajectory == "orbit" else np.zeros(2)
    trajectory = _path(recipe, half, centre_xy, gen)
    path_xy = trajectory.T_world_cam[:, :2, 3]
    centre = np.array([0.0, 0.0, size[2] / 2])
    outer = size.copy()
    omit: tuple[str, ...] = ()
    if recipe.open_room:
        # One side opens onto more floor: its wall is gone and the floor runs on 4 m.
        facing = trajectory.T_world_cam[0, :3, 2]
        kept = ("+" if facing[0] > 0 else "-") + "x"
        if recipe.trajectory == "wall":  # the wall the path slides along stays
            axis = int(np.argmax(np.abs(facing[:2])))
            kept = ("+" if facing[axis] > 0 else "-") + "xy"[axis]
        wall = str(gen.choice([w for w in ("+x", "-x", "+y", "-y") if w != kept]))
        axis = "xy".index(wall[1])
        sign = 1.0 if wall[0] == "+" else -1.0
        outer[axis] += 4.0
        centre[axis] += sign * 2.0
        omit = (wall,)
    room = Box("room", centre, outer, kind="room", omit_faces=omit)
    boxes, structures = _place_furniture(recipe, half, path_xy, centre_xy, gen)
    brightness = gen.uniform(0.35, 0.8)
    texture = Texture(
        seed=recipe.seed,
        brightness=(brightness - 0.2, brightness + 0.15),
        pattern="noise" if recipe.texture == "low_contrast" else recipe.texture,
        contrast=0.2 if recipe.texture == "low_contrast" else 1.0,
    )
    light = np.array([*gen.uniform(-0.6, 0.6, size=2), 1.0])
    scene = make_scene(
        recipe.name,
        (room, *boxes),
        tuple(structures),
        texture=texture,
        light_world=light,
        ambient=gen.uniform(0.2, 0.6),
    )
    return scene, trajectory


def write_procedural(
    recipe: Recipe,
    out_dir: str | Path,
    camera: CameraConfig | None = None,
    max_frames: int | None = None,
) -> SynthResult:
    """Render `recipe` into `out_dir` as a dataset folder with truth (see
    `planeslam.sim.render.write_sequence`); truth.json's 'rendering' holds the recipe.
    `max_frames` keeps only the path's first frames (a quick look, tests)."""
    scene, trajectory = build_sequence(recipe)
    if max_frames is not None:
        if max_frames < 1:
            raise ConfigError(f"max_frames must be >= 1, got {max_frames}")
        trajectory = Trajectory(
            trajectory.timestamps[:max_frames], trajectory.T_world_cam[:max_frames]
        )
    return write_sequence(
        scene,
        trajectory,
        out_dir,
        recipe.seed,
        camera=camera,
        noise_model=recipe.depth_model,
        rng=np.random.default_rng([recipe.seed, 2]),
        rendering={"recipe": recipe.record(), "generator_version": GENERATOR_VERSION},
    )
