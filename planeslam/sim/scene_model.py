"""The synthetic scene model with exact truth: boxes, rooms, panels, their planes, edges
and corners.

A scene is a set of oriented boxes (`kind='solid'`, seen from outside, or
`kind='room'`, enclosing and seen from inside) and structures made of open
rectangular panels (two-sided). Every box face and every panel becomes one
world-frame `ScenePlane` with a stable integer id; `make_scene` also derives
the true real intersections (edges: pairs of faces whose rectangles touch
along a segment) and trihedral corners (three planes pairwise joined by
edges meeting in one point).

World frame: z up (gravity along -z), metres. Plane normals follow the
library convention n . x + d = 0 with the normal on the visible side: out
of a solid box, into a room; a two-sided panel's normal is its `rotation`
third column.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from planeslam.core.errors import ConfigError
from planeslam.core.geometry import point_segment_distance

WORLD_UP = np.array([0.0, 0.0, 1.0])
"""World up direction (opposite to gravity) of every synthetic scene."""

_FACE_AXES: tuple[tuple[str, int, float], ...] = (
    ("+x", 0, 1.0),
    ("-x", 0, -1.0),
    ("+y", 1, 1.0),
    ("-y", 1, -1.0),
    ("+z", 2, 1.0),
    ("-z", 2, -1.0),
)
_ROOM_FACE_NAMES = {"+z": "ceiling", "-z": "floor"}
_BOX_FACE_NAMES = {"+z": "top", "-z": "bottom"}
_TOUCH_TOL_M = 1e-6

DEFAULT_LIGHT_WORLD = np.array([0.3, -0.45, 0.84]) / np.linalg.norm([0.3, -0.45, 0.84])
"""Direction toward the scenes' light (world frame, from above) unless a scene sets one."""
DEFAULT_AMBIENT = 0.35
"""Ambient share of the scenes' light unless a scene sets one."""

TEXTURE_PATTERNS = ("noise", "repetitive", "none", "posters")
"""`Texture.pattern`: a hash of cells plus a coarse checkerboard (natural-looking, every
patch unique), a plain checkerboard (every patch looks like many others), uniform
colour, or uniform surfaces with one textured poster on each plane of 1 m^2 or more."""
PLAIN_REFLECTANCE = 0.725
"""Texture factor of a plain surface: the mean of the default pattern's."""


def rot_z(yaw_rad: float) -> np.ndarray:
    """(3, 3) rotation about the world z axis by `yaw_rad` [rad]."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class Box:
    """An oriented box: solid (seen from outside) or a room (seen from inside)."""

    name: str
    """Object name, used as the prefix of its face names ('box', 'room')."""
    centre: np.ndarray
    """(3,) box centre in the world frame [m]."""
    size_m: np.ndarray
    """(3,) full extents along the box's own x, y, z axes [m]."""
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    """(3, 3) R_world_box: columns are the box axes in the world frame."""
    kind: Literal["solid", "room"] = "solid"
    """'solid': faces point outward; 'room': faces point inward (camera inside)."""
    omit_faces: tuple[str, ...] = ()
    """Faces that do not exist as surfaces ('+x', '-x', '+y', '-y', '+z', '-z'),
    e.g. ('-z',) for a box resting on the floor, whose bottom is never seen."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", np.asarray(self.centre, dtype=np.float64).reshape(3))
        object.__setattr__(self, "size_m", np.asarray(self.size_m, dtype=np.float64).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=np.float64))
        if np.any(self.size_m <= 0):
            raise ConfigError(f"box {self.name!r}: sizes must be > 0 m, got {self.size_m}")
        if self.kind not in ("solid", "room"):
            raise ConfigError(
                f"box {self.name!r}: kind must be 'solid' or 'room', got {self.kind!r}"
            )
        R = self.rotation
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
            raise ConfigError(f"box {self.name!r}: rotation is not a 3x3 orthonormal matrix")
        bad = sorted(set(self.omit_faces) - {f for f, _, _ in _FACE_AXES})
        if bad:
            raise ConfigError(f"box {self.name!r}: unknown face(s) {bad}; faces: +x -x +y -y +z -z")


@dataclass(frozen=True, eq=False)
class Panel:
    """An open rectangular panel, visible from both sides."""

    name: str
    """Panel name (unique within the scene)."""
    centre: np.ndarray
    """(3,) panel centre in the world frame [m]."""
    size_m: np.ndarray
    """(2,) full extents along the panel's first and second axes [m]."""
    rotation: np.ndarray
    """(3, 3) R_world_panel: columns are the width axis, the height axis and the normal."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", np.asarray(self.centre, dtype=np.float64).reshape(3))
        object.__setattr__(self, "size_m", np.asarray(self.size_m, dtype=np.float64).reshape(2))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=np.float64))
        if np.any(self.size_m <= 0):
            raise ConfigError(f"panel {self.name!r}: sizes must be > 0 m, got {self.size_m}")
        R = self.rotation
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
            raise ConfigError(f"panel {self.name!r}: rotation is not a 3x3 orthonormal matrix")


@dataclass(frozen=True, eq=False)
class Structure:
    """A rigid arrangement of panels forming one object of class 'structure'."""

    name: str
    panels: tuple[Panel, ...]


@dataclass(frozen=True, eq=False)
class ScenePlane:
    """One planar rectangle of the scene, world frame, with its appearance."""

    id: int
    """Stable integer id (index into `Scene.planes`)."""
    name: str
    """'<object>.<face>', e.g. 'room.floor', 'box.top', 'zigzag.panel_2'."""
    object_id: int
    """Id of the object it belongs to (index into `Scene.objects`)."""
    normal: np.ndarray
    """(3,) unit normal, world frame, pointing to the visible side."""
    d: float
    """Offset [m]: normal . x + d = 0 for points x on the plane (world frame)."""
    centre: np.ndarray
    """(3,) rectangle centre, world frame [m]."""
    axes: np.ndarray
    """(2, 3) orthonormal in-plane axes u, v of the rectangle (world frame)."""
    half_size_m: np.ndarray
    """(2,) half extents along u and v [m]."""
    two_sided: bool
    """True for panels (visible from both sides), False for box and room faces."""
    albedo_rgb: np.ndarray
    """(3,) base reflectance in [0, 1]."""
    texture_cell_m: float
    """Cell size of the procedural texture [m]."""
    texture_salt: int
    """Per-plane salt of the texture hash."""
    texture_weights: tuple[float, float, float] = (0.45, 0.35, 0.2)
    """(base, hash-noise weight, checkerboard weight) of the texture: reflectance factor
    base + w_noise * noise + w_checker * checker, noise in [0, 1], checker 0 or 1."""
    poster: tuple[float, float, float, float] | None = None
    """(u0, u1, v0, v1) [m] in plane coordinates: the texture only inside this window
    (a poster on a plain wall), uniform outside; None: textured everywhere."""

    @property
    def polygon(self) -> np.ndarray:
        """(4, 3) rectangle corners, world frame [m], counter-clockwise in (u, v)."""
        signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        return self.centre + (signs * self.half_size_m) @ self.axes

    @property
    def area_m2(self) -> float:
        return float(4.0 * self.half_size_m[0] * self.half_size_m[1])


@dataclass(frozen=True, eq=False)
class SceneObject:
    """A physical object made of planes."""

    id: int
    name: str
    object_class: Literal["box", "room", "structure"]
    plane_ids: tuple[int, ...]
    size_m: tuple[float, ...]
    """True size [m]: a box's three extents largest first; a room's length, width,
    height; a structure's world bounding-box extents largest first."""


@dataclass(frozen=True, eq=False)
class SceneEdge:
    """A true real intersection of two planes."""

    plane_ids: tuple[int, int]
    """Smaller id first."""
    segment: np.ndarray
    """(2, 3) end points, world frame [m]."""

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.segment[1] - self.segment[0]))


@dataclass(frozen=True, eq=False)
class SceneCorner:
    """A true trihedral corner: three planes pairwise joined by edges."""

    plane_ids: tuple[int, int, int]
    """Increasing ids."""
    point: np.ndarray
    """(3,) corner point, world frame [m]."""


@dataclass(frozen=True, eq=False)
class Scene:
    """A complete synthetic scene; build it with `make_scene`."""

    name: str
    boxes: tuple[Box, ...]
    structures: tuple[Structure, ...]
    planes: tuple[ScenePlane, ...]
    objects: tuple[SceneObject, ...]
    edges: tuple[SceneEdge, ...]
    corners: tuple[SceneCorner, ...]
    light_world: np.ndarray = field(default_factory=lambda: DEFAULT_LIGHT_WORLD.copy())
    """(3,) unit direction toward the light, world frame (Lambertian shading)."""
    ambient: float = DEFAULT_AMBIENT
    """Share of the light that reaches every surface whatever its normal, in [0, 1]."""

    def plane_by_name(self, name: str) -> ScenePlane:
        """The plane called `name`; ConfigError listing the names when absent."""
        return self._by_name(self.planes, "plane", name)

    def object_by_name(self, name: str) -> SceneObject:
        """The object called `name`; ConfigError listing the names when absent."""
        return self._by_name(self.objects, "object", name)

    def _by_name(self, items: tuple[Any, ...], kind: str, name: str) -> Any:
        for item in items:
            if item.name == name:
                return item
        raise ConfigError(
            f"scene {self.name!r} has no {kind} {name!r}; {kind}s: "
            + ", ".join(i.name for i in items)
        )


@dataclass(frozen=True)
class Texture:
    """Appearance of a scene's planes: each plane draws a hue, a brightness and a texture
    cell size from a generator seeded with (`seed`, plane id), so a plane looks the same
    in every frame and every run."""

    seed: int = 0
    """Seed of the per-plane draws."""
    brightness: tuple[float, float] = (0.6, 0.6)
    """Range of a plane's mean albedo (the mean of its RGB reflectances) in (0, 1]; each
    channel is that mean plus a hue of amplitude 0.35, clipped to [0.03, 0.95]."""
    cell_m: tuple[float, float] = (0.02, 0.05)
    """Range of the texture's cell size [m] (the pattern is a hash of cells plus a
    checkerboard of 4 x 4 cells)."""
    pattern: str = "noise"
    """One of TEXTURE_PATTERNS."""
    contrast: float = 1.0
    """Scale of the pattern's amplitude in (0, 1] (low-contrast surfaces below 0.3)."""

    def __post_init__(self) -> None:
        if self.pattern not in TEXTURE_PATTERNS:
            raise ConfigError(
                f"texture.pattern must be one of {', '.join(TEXTURE_PATTERNS)}, "
                f"got {self.pattern!r}"
            )
        if not 0.0 < float(self.contrast) <= 1.0:
            raise ConfigError(f"texture.contrast must be in (0, 1], got {self.contrast!r}")
        object.__setattr__(self, "brightness", tuple(float(v) for v in self.brightness))
        object.__setattr__(self, "cell_m", tuple(float(v) for v in self.cell_m))
        lo, hi = self.brightness if len(self.brightness) == 2 else (np.nan, np.nan)
        if not 0.0 < lo <= hi <= 1.0:
            raise ConfigError(
                f"texture.brightness must be [low, high] with 0 < low <= high <= 1, "
                f"got {list(self.brightness)}"
            )
        lo, hi = self.cell_m if len(self.cell_m) == 2 else (np.nan, np.nan)
        if not 0.0 < lo <= hi:
            raise ConfigError(
                f"texture.cell_m must be [low, high] with 0 < low <= high [m], "
                f"got {list(self.cell_m)}"
            )


def _appearance(texture: Texture, plane_id: int) -> tuple[np.ndarray, float, int]:
    gen = np.random.default_rng([texture.seed, plane_id])
    hue = Rotation.from_rotvec(np.array([1.0, 1.0, 1.0]) / np.sqrt(3) * gen.uniform(0, 2 * np.pi))
    cell = float(gen.uniform(*texture.cell_m))
    salt = int(gen.integers(1, 2**20))
    # Drawn last, so the hue, cell and salt of a seed do not depend on the brightness range.
    brightness = float(gen.uniform(*texture.brightness))
    albedo = brightness + 0.35 * hue.apply(np.array([0.6, -0.3, -0.3]))
    return np.clip(albedo, 0.03, 0.95), cell, salt


def _pattern(
    texture: Texture, plane_id: int, half_size_m: np.ndarray
) -> tuple[tuple[float, float, float], tuple[float, float, float, float] | None]:
    """(base, noise weight, checker weight) and the poster window of one plane."""
    c = float(texture.contrast)
    noise_weights = (PLAIN_REFLECTANCE - c * 0.275, c * 0.35, c * 0.2)
    if c == 1.0:
        noise_weights = (0.45, 0.35, 0.2)  # the historic constants, bit for bit
    checker_weights = (PLAIN_REFLECTANCE - c * 0.25, 0.0, c * 0.5)
    if texture.pattern == "noise":
        return noise_weights, None
    if texture.pattern == "repetitive":
        return checker_weights, None
    if texture.pattern == "none":
        return (PLAIN_REFLECTANCE, 0.0, 0.0), None
    # posters: a window of 0.4-1.0 m on planes of 1 m^2 or more, the rest plain
    gen = np.random.default_rng([texture.seed, plane_id, 1])
    content = noise_weights if gen.random() < 0.5 else checker_weights
    if 4.0 * half_size_m[0] * half_size_m[1] < 1.0:
        return (PLAIN_REFLECTANCE, 0.0, 0.0), None
    size = gen.uniform(0.4, 1.0, size=2)
    size = np.minimum(size, 2.0 * half_size_m * 0.8)
    lo = gen.uniform(-half_size_m * 0.9, half_size_m * 0.9 - size)
    window = (float(lo[0]), float(lo[0] + size[0]), float(lo[1]), float(lo[1] + size[1]))
    return content, window


def _box_faces(box: Box) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(face name, normal, centre, axes (2,3), half sizes (2,)) of a box's existing faces."""
    faces = []
    half = box.size_m / 2.0
    names = _ROOM_FACE_NAMES if box.kind == "room" else _BOX_FACE_NAMES
    for face, axis, sign in _FACE_AXES:
        if face in box.omit_faces:
            continue
        outward = sign * box.rotation[:, axis]
        centre = box.centre + outward * half[axis]
        others = [a for a in range(3) if a != axis]
        normal = -outward if box.kind == "room" else outward
        label = names.get(face, f"wall_{face}" if box.kind == "room" else f"side_{face}")
        faces.append((label, normal, centre, box.rotation[:, others].T.copy(), half[others]))
    return faces


def make_scene(
    name: str,
    boxes: tuple[Box, ...] = (),
    structures: tuple[Structure, ...] = (),
    texture: Texture | int = 0,
    light_world: np.ndarray | None = None,
    ambient: float | None = None,
) -> Scene:
    """Compile boxes and structures into planes (ids in order: boxes, then structures),
    objects, true edges and true corners. Appearance is a fixed function of the
    `texture` (a `Texture`, or just its seed) and the plane id; `light_world` (3,) and
    `ambient` set the lighting (default: light from above, ambient 0.35)."""
    texture = texture if isinstance(texture, Texture) else Texture(seed=int(texture))
    planes: list[ScenePlane] = []
    objects: list[SceneObject] = []
    raw: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]] = []
    for box in boxes:
        obj_id = len(objects)
        ids = []
        for label, normal, centre, axes, half in _box_faces(box):
            ids.append(len(raw))
            raw.append((obj_id, f"{box.name}.{label}", normal, centre, axes, half, False))
        if box.kind == "room":
            horiz = sorted(box.size_m[:2].tolist(), reverse=True)
            size = (horiz[0], horiz[1], float(box.size_m[2]))
            cls: Literal["box", "room", "structure"] = "room"
        else:
            size = tuple(sorted(box.size_m.tolist(), reverse=True))
            cls = "box"
        objects.append(SceneObject(obj_id, box.name, cls, tuple(ids), size))
    for struct in structures:
        obj_id = len(objects)
        ids = []
        pts = []
        for panel in struct.panels:
            ids.append(len(raw))
            axes = panel.rotation[:, :2].T.copy()
            raw.append(
                (
                    obj_id,
                    f"{struct.name}.{panel.name}",
                    panel.rotation[:, 2].copy(),
                    panel.centre,
                    axes,
                    panel.size_m / 2.0,
                    True,
                )
            )
            signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
            pts.append(panel.centre + (signs * panel.size_m / 2.0) @ axes)
        extent = np.ptp(np.concatenate(pts), axis=0)
        size = tuple(sorted(extent.tolist(), reverse=True))
        objects.append(SceneObject(obj_id, struct.name, "structure", tuple(ids), size))
    for pid, (obj_id, pname, normal, centre, axes, half, two_sided) in enumerate(raw):
        albedo, cell, salt = _appearance(texture, pid)
        weights, poster = _pattern(texture, pid, np.asarray(half))
        normal = normal / np.linalg.norm(normal)
        planes.append(
            ScenePlane(
                id=pid,
                name=pname,
                object_id=obj_id,
                normal=normal,
                d=float(-normal @ centre),
                centre=np.asarray(centre, dtype=np.float64),
                axes=np.asarray(axes, dtype=np.float64),
                half_size_m=np.asarray(half),
                two_sided=two_sided,
                albedo_rgb=albedo,
                texture_cell_m=cell,
                texture_salt=salt,
                texture_weights=weights,
                poster=poster,
            )
        )
    names = [p.name for p in planes]
    if len(set(names)) != len(names):
        raise ConfigError(f"scene {name!r}: plane names are not unique: {names}")
    edges = _true_edges(planes)
    corners = _true_corners(planes, edges)
    light = DEFAULT_LIGHT_WORLD if light_world is None else np.asarray(light_world, float)
    if light.shape != (3,) or not np.isfinite(light).all() or np.linalg.norm(light) < 1e-9:
        raise ConfigError(f"scene {name!r}: light_world must be a non-zero 3-vector")
    ambient = DEFAULT_AMBIENT if ambient is None else float(ambient)
    if not 0.0 <= ambient <= 1.0:
        raise ConfigError(f"scene {name!r}: ambient must be in [0, 1], got {ambient}")
    return Scene(
        name=name,
        boxes=tuple(boxes),
        structures=tuple(structures),
        planes=tuple(planes),
        objects=tuple(objects),
        edges=tuple(edges),
        corners=tuple(corners),
        light_world=light / np.linalg.norm(light),
        ambient=ambient,
    )


def _clip_line_to_rect(
    point: np.ndarray, direction: np.ndarray, plane: ScenePlane, lo: float, hi: float
) -> tuple[float, float]:
    """Narrow the line parameter interval [lo, hi] to the part inside the plane's rectangle."""
    for axis, half in zip(plane.axes, plane.half_size_m, strict=True):
        a = float((point - plane.centre) @ axis)
        b = float(direction @ axis)
        if abs(b) < 1e-9:
            # The line runs along this side: it touches when it lies within the
            # rectangle up to rounding.
            if abs(a) > half + _TOUCH_TOL_M:
                return 1.0, 0.0
            continue
        s1, s2 = sorted(((-half - a) / b, (half - a) / b))
        lo, hi = max(lo, s1), min(hi, s2)
    return lo, hi


def _true_edges(planes: list[ScenePlane]) -> list[SceneEdge]:
    """Pairs of non-parallel rectangles that share a segment of their common line."""
    edges = []
    for p, q in itertools.combinations(planes, 2):
        direction = np.cross(p.normal, q.normal)
        s = float(np.linalg.norm(direction))
        if s < 1e-6:
            continue
        direction /= s
        A = np.stack([p.normal, q.normal, direction])
        point = np.linalg.solve(A, np.array([-p.d, -q.d, 0.0]))
        lo, hi = _clip_line_to_rect(point, direction, p, -np.inf, np.inf)
        lo, hi = _clip_line_to_rect(point, direction, q, lo, hi)
        if hi - lo > 1e-3:
            segment = point + np.array([lo, hi])[:, None] * direction
            edges.append(SceneEdge((p.id, q.id), segment))
    return edges


def _true_corners(planes: list[ScenePlane], edges: list[SceneEdge]) -> list[SceneCorner]:
    """Triples of planes pairwise joined by edges whose three segments meet in one point."""
    by_pair = {e.plane_ids: e for e in edges}
    corners = []
    ids = sorted({i for e in edges for i in e.plane_ids})
    for i, j, k in itertools.combinations(ids, 3):
        trio = [by_pair.get(pair) for pair in ((i, j), (i, k), (j, k))]
        if any(e is None for e in trio):
            continue
        normals = np.stack([planes[m].normal for m in (i, j, k)])
        if abs(np.linalg.det(normals)) < 1e-6:
            continue
        point = np.linalg.solve(normals, -np.array([planes[m].d for m in (i, j, k)]))
        if all(point_segment_distance(point, e.segment) < 1e-6 for e in trio):  # type: ignore[union-attr]
            corners.append(SceneCorner((i, j, k), point))
    return corners
