"""Plane graph, trihedral angles, plane-based objects, classes and sizes (paper 4.2-4.3).

`build_structure` runs the per-frame chain after segmentation:
real intersections -> plane graph -> trihedral corners (edge ends within
`corner_tol_m` of a corner snapped onto it) -> objects (corners
sharing a graph edge, aggregated angle by angle) -> class by subgraph
pattern -> physical size. Everything is in the camera frame, metres.

Classification: each object's plane graph is matched against the pattern
table (`DEFAULT_PATTERNS`, or the caller's) in order with
`networkx.algorithms.isomorphism.GraphMatcher` (subgraph monomorphism with
node and edge attribute constraints); the first pattern that matches gives
the class, 'unknown' when none does. A plane may belong to several objects
(the floor under a box and the floor of the room); planes in no corner are
in no object.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import networkx as nx
import numpy as np
from networkx.algorithms import isomorphism

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.geometry import unit
from planeslam.core.types import GravitySource
from planeslam.frontend.config import IntersectionConfig, ObjectConfig
from planeslam.frontend.intersections import Edge, find_intersections
from planeslam.frontend.plane_graph import (
    Corner,
    GravityEstimate,
    aggregate_corners,
    build_plane_graph,
    estimate_gravity,
    find_corners,
    snap_edges_to_corners,
)
from planeslam.frontend.types import Segmentation

logger = logging.getLogger(__name__)

MAP_SCHEMA = "planeslam.map/1"


@dataclass(frozen=True)
class ObjectPattern:
    """One class of the pattern table: a small plane graph that must occur in an object.

    Attribute constraints map an attribute name to the required value, or to a
    tuple of allowed values. Node attributes: orientation ('horizontal',
    'vertical', 'slanted'), facing ('up', 'down', ''), area_m2, d. Edge
    attributes: convex (bool), length_m, angle_rad.
    """

    cls: str
    """Class name given to matching objects."""
    nodes: tuple[Mapping[str, Any], ...]
    """Required attributes of each pattern node (a plane)."""
    edges: tuple[tuple[int, int, Mapping[str, Any]], ...]
    """Pattern edges (node index, node index, required attributes)."""
    all_edges: Mapping[str, Any] = field(default_factory=dict)
    """Attributes every edge of the object's graph must have (e.g. all concave)."""
    size_from: Literal["edges", "convex_edges", "extent"] = "edges"
    """How the size is measured: 'edges' (longest edge per orthogonal direction, over
    all the object's planes), 'convex_edges' (the same over the planes joined to the
    matched pattern by convex edges: a box without the floor it stands on) or
    'extent' (gravity-aligned bounding box of the object's edge end points)."""
    height_needs_bound: bool = False
    """Report the vertical dimension only when two parallel horizontal planes bound it
    (a room's floor and ceiling); otherwise the size is the horizontal part alone. Walls
    seen from a low camera show only their lower part, so their vertical edges would give
    the visible height, not the room's."""
    description: str = ""

    def graph(self) -> nx.Graph:
        """The pattern as a networkx graph with the constraints as attributes."""
        g = nx.Graph()
        for k, attrs in enumerate(self.nodes):
            g.add_node(k, **dict(attrs))
        for a, b, attrs in self.edges:
            g.add_edge(a, b, **dict(attrs))
        return g


_H = {"orientation": "horizontal"}
_V = {"orientation": "vertical"}
_CONVEX = {"convex": True}
_CONCAVE = {"convex": False}

DEFAULT_PATTERNS: tuple[ObjectPattern, ...] = (
    ObjectPattern(
        "box",
        nodes=(_H, _V, _V),
        edges=((0, 1, _CONVEX), (0, 2, _CONVEX), (1, 2, _CONVEX)),
        size_from="convex_edges",
        description="a convex corner of a horizontal top (or bottom) and two vertical sides",
    ),
    ObjectPattern(
        "room",
        nodes=(_H, _V, _V),
        edges=((0, 1, _CONCAVE), (0, 2, _CONCAVE), (1, 2, _CONCAVE)),
        all_edges=_CONCAVE,
        height_needs_bound=True,
        description="a concave corner of a floor or ceiling and two walls, no convex edge",
    ),
    ObjectPattern(
        "structure",
        nodes=({}, {}, {}),
        edges=((0, 1, _CONVEX), (1, 2, _CONCAVE), (0, 2, {})),
        size_from="extent",
        description="a corner with both convex and concave edges (panels, steps, shelves)",
    ),
)
"""The pattern table, matched in this order (first match wins). Extend it by passing
your own tuple to `build_structure` / `classify_object`, e.g.
`(my_pattern,) + DEFAULT_PATTERNS`."""


@dataclass(frozen=True)
class PlaneObject:
    """A plane-based object of one frame: corners that share edges, with class and size."""

    id: int
    """Index in `FrameStructure.objects`."""
    cls: str
    """Class from the pattern table ('box', 'room', 'structure', ...) or 'unknown'."""
    planes: tuple[int, ...]
    """Ids of its planes, increasing (a plane can be in several objects)."""
    corners: tuple[int, ...]
    """Indices of its corners in `FrameStructure.corners`."""
    size_m: tuple[float, ...]
    """Extents along up to three mutually orthogonal directions, largest first [m]."""


@dataclass(frozen=True)
class FrameStructure:
    """Edges, plane graph, corners and objects of one frame, camera frame."""

    edges: list[Edge]
    graph: nx.Graph = field(repr=False)
    corners: list[Corner]
    objects: list[PlaneObject]
    gravity_up_cam: np.ndarray
    """(3,) unit up direction used for orientations, camera frame."""
    gravity_source: GravitySource
    """Where `gravity_up_cam` came from: the config, a plane, or the camera fallback."""
    gravity_plane_id: int | None = None
    """Id of the plane that gave `gravity_up_cam` (source `PLANE`), else None."""
    reason: str = ""
    """Why the result is empty or partial; '' when at least one object was found."""


def _allowed(value: Any) -> tuple[Any, ...]:
    return value if isinstance(value, tuple) else (value,)


def _attrs_match(actual: Mapping[str, Any], required: Mapping[str, Any]) -> bool:
    return all(k in actual and actual[k] in _allowed(v) for k, v in required.items())


def match_pattern(object_graph: nx.Graph, pattern: ObjectPattern) -> dict[Any, int] | None:
    """First embedding of `pattern` in `object_graph` (object plane id -> pattern node),
    or None when the pattern does not occur or an edge violates `all_edges`."""
    edge_attrs = [d for _, _, d in object_graph.edges(data=True)]
    if any(not _attrs_match(d, pattern.all_edges) for d in edge_attrs):
        return None
    # Cheap necessary conditions before VF2: every constrained pattern node and
    # edge has at least one candidate in the object.
    node_attrs = [d for _, d in object_graph.nodes(data=True)]
    if any(not any(_attrs_match(d, req) for d in node_attrs) for req in pattern.nodes if req):
        return None
    if any(not any(_attrs_match(d, req) for d in edge_attrs) for _, _, req in pattern.edges if req):
        return None
    matcher = isomorphism.GraphMatcher(
        object_graph, pattern.graph(), node_match=_attrs_match, edge_match=_attrs_match
    )
    return next(iter(matcher.subgraph_monomorphisms_iter()), None)


def classify_object(
    object_graph: nx.Graph, patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS
) -> tuple[str, ObjectPattern | None, dict[Any, int] | None]:
    """Class of one object's plane graph: (class, matched pattern, embedding), first
    match in table order; ('unknown', None, None) when no pattern occurs."""
    for pattern in patterns:
        mapping = match_pattern(object_graph, pattern)
        if mapping is not None:
            return pattern.cls, pattern, mapping
    return "unknown", None, None


def measure_size(
    graph: nx.Graph,
    planes: set[int],
    object_planes: set[int],
    axis_tol_deg: float,
    up: np.ndarray | None = None,
    height_needs_bound: bool = False,
) -> tuple[float, ...]:
    """Physical size [m] of the planes `planes` of an object, largest first.

    Uses the edges between the object's planes that touch `planes`, those
    between two planes of `planes` first. Edge directions are grouped
    greedily (longest edge first) into up to three
    mutually orthogonal directions; a dimension is the longest edge along it
    (a dimension seen only partly is as long as seen) or, when two parallel
    planes of `planes` bound it (opposite walls, floor and ceiling), their
    distance if that is larger. With `height_needs_bound` and a unit `up` (3,), the
    dimension along up is left out unless two parallel planes bound it.
    """
    cos_tol = float(np.cos(np.deg2rad(axis_tol_deg)))
    sin_tol = float(np.sin(np.deg2rad(axis_tol_deg)))
    inner: list[tuple[float, np.ndarray, bool]] = []
    outer: list[tuple[float, np.ndarray, bool]] = []
    for i, j, data in graph.edges(data=True):
        if i in object_planes and j in object_planes and (i in planes or j in planes):
            seg = data["segment"]
            both = i in planes and j in planes
            entry = (float(data["length_m"]), unit(seg[1] - seg[0]), False)
            (inner if both else outer).append(entry)
    # Directions come from the edges between the measured planes first (a box's own
    # edges); edges to the object's other planes (the floor under a box) then only
    # lengthen a dimension or add a missing one.
    measures = inner
    members = sorted(planes)
    for a_idx, a in enumerate(members):
        na, da = graph.nodes[a]["normal"], graph.nodes[a]["d"]
        for b in members[a_idx + 1 :]:
            nb, db = graph.nodes[b]["normal"], graph.nodes[b]["d"]
            c = float(na @ nb)
            if abs(c) >= cos_tol:
                gap = abs(da + db) if c < 0 else abs(da - db)
                measures.append((gap, unit(np.asarray(na, dtype=np.float64)), True))
    axes: list[np.ndarray] = []
    dims: list[float] = []
    bounded: list[bool] = []
    for group in (measures, outer):
        for length, direction, is_gap in sorted(group, key=lambda m: -m[0]):
            dots = [abs(float(direction @ ax)) for ax in axes]
            best = int(np.argmax(dots)) if dots else -1
            if dots and dots[best] >= cos_tol:
                dims[best] = max(dims[best], length)
                bounded[best] = bounded[best] or is_gap
            elif len(axes) < 3 and all(d <= sin_tol for d in dots):
                axes.append(direction)
                dims.append(length)
                bounded.append(is_gap)
    if height_needs_bound and up is not None:
        keep = [
            k
            for k, ax in enumerate(axes)
            if bounded[k] or abs(float(ax @ np.asarray(up, dtype=np.float64))) < cos_tol
        ]
        dims = [dims[k] for k in keep]
    return tuple(sorted(dims, reverse=True))


def measure_extent(graph: nx.Graph, object_planes: set[int], up: np.ndarray) -> tuple[float, ...]:
    """Gravity-aligned bounding box [m] of the end points of the edges between
    `object_planes`, largest first: height along unit `up`, and the two horizontal
    extents along the principal directions of the end points' horizontal spread."""
    ends = [
        d["segment"]
        for i, j, d in graph.edges(data=True)
        if i in object_planes and j in object_planes
    ]
    if not ends:
        return ()
    pts = np.concatenate(ends)
    height = float(np.ptp(pts @ up))
    flat = pts - np.outer(pts @ up, up)
    flat = flat - flat.mean(axis=0)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    horizontal = np.ptp(flat @ vt[:2].T, axis=0)
    return tuple(sorted([float(horizontal[0]), float(horizontal[1]), height], reverse=True))


def convex_part(graph: nx.Graph, seeds: Sequence[int], object_planes: set[int]) -> set[int]:
    """Planes of the object joined to `seeds` through convex edges only."""
    convex = nx.Graph()
    convex.add_nodes_from(seeds)
    convex.add_edges_from(
        (i, j)
        for i, j, d in graph.edges(data=True)
        if d["convex"] and i in object_planes and j in object_planes
    )
    part: set[int] = set()
    for s in seeds:
        part |= nx.node_connected_component(convex, s)
    return part


def _all_parallel(segmentation: Segmentation, min_angle_deg: float) -> bool:
    normals = np.stack([p.normal for p in segmentation.planes])
    cos = np.abs(normals @ normals.T)
    return bool(np.all(cos >= np.cos(np.deg2rad(min_angle_deg))))


def classify_and_size(
    graph: nx.Graph,
    object_planes: set[int],
    up: np.ndarray,
    axis_tol_deg: float,
    patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    convex_part_only: bool = False,
) -> tuple[str, tuple[float, ...]]:
    """(class, size [m]) of the object made of `object_planes` in a plane graph (paper
    4.3): the pattern table names the class and how it is sized (edge lengths along the
    object's axes, or its extent). `convex_part_only` measures a pattern sized by its
    convex edges within that part alone: in a merged map the concave contact edges with
    the support (a box on the floor) come out longer than the object, and the
    longest-edge rule keeps the worst."""
    sub = graph.subgraph(object_planes).copy()  # a plain graph iterates faster than a view
    cls, pattern, mapping = classify_object(sub, patterns)
    size_from = pattern.size_from if pattern is not None else "extent"
    if size_from == "extent":
        return cls, measure_extent(graph, object_planes, up)
    measured, within = object_planes, object_planes
    if size_from == "convex_edges" and mapping is not None:
        measured = convex_part(graph, list(mapping), object_planes)
        if convex_part_only:
            within = measured
    size = measure_size(
        graph,
        measured,
        within,
        axis_tol_deg,
        up,
        pattern is not None and pattern.height_needs_bound,
    )
    return cls, size


def find_objects(
    graph: nx.Graph,
    corners: Sequence[Corner],
    up: np.ndarray,
    object_config: ObjectConfig | None = None,
    patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
) -> list[PlaneObject]:
    """Objects of one frame (paper 4.2-4.3): corners sharing a graph edge aggregated
    angle by angle, each classified by the pattern table and sized [m] (camera frame)."""
    ocfg = object_config or ObjectConfig()
    groups = aggregate_corners([c.planes for c in corners])
    objects: list[PlaneObject] = []
    for group in groups:
        object_planes = {p for k in group for p in corners[k].planes}
        cls, size = classify_and_size(graph, object_planes, up, ocfg.axis_tol_deg, patterns)
        objects.append(
            PlaneObject(
                id=len(objects),
                cls=cls,
                planes=tuple(sorted(object_planes)),
                corners=tuple(group),
                size_m=size,
            )
        )
    return objects


def gravity_up(
    segmentation: Segmentation, object_config: ObjectConfig | None = None
) -> GravityEstimate:
    """The frame's up direction (camera frame): from the config when given, else
    estimated from the frame's planes (`plane_graph.estimate_gravity`)."""
    ocfg = object_config or ObjectConfig()
    if ocfg.gravity_up_cam:
        up = unit(np.asarray(ocfg.gravity_up_cam, dtype=np.float64))
        return GravityEstimate(up, GravitySource.CONFIG)
    return estimate_gravity(segmentation.planes, ocfg.gravity_max_tilt_deg)


def structure_reason(
    segmentation: Segmentation,
    edges: Sequence[Edge],
    corners: Sequence[Corner],
    min_angle_deg: float,
) -> str:
    """Why a frame's structure is empty or partial ('' when it has corners)."""
    planes = segmentation.planes
    if not planes:
        return "no planes in the frame"
    if len(planes) == 1:
        return "only one plane: no intersections possible"
    if not edges:
        if _all_parallel(segmentation, min_angle_deg):
            return f"all {len(planes)} planes are nearly parallel: no intersections"
        return f"no real intersections among {len(planes)} planes"
    if not corners:
        return f"{len(edges)} real intersections but no trihedral corner: no objects"
    return ""


def build_structure(
    segmentation: Segmentation,
    intersection_config: IntersectionConfig | None = None,
    object_config: ObjectConfig | None = None,
    patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    lap: Callable[[], None] | None = None,
    sensor: DepthNoiseConfig | None = None,
) -> FrameStructure:
    """Edges, plane graph, corners and classified, sized objects of one frame.

    Camera frame, metres. The composition of the front end's stages `edges`
    (`find_intersections`), `graph` (`gravity_up`, `build_plane_graph`),
    `corners` (`find_corners`, which also snaps edge ends to their corners) and
    `objects` (`find_objects`). Degenerate input (no planes, one plane, only
    parallel planes, no corner) gives an empty or partial result whose
    `reason` says why; it never raises for such frames. `lap`, when given, is
    called after each of the four stages (the front end times them with it).
    `sensor`: the depth noise the intersections use (default `DepthNoiseConfig()`).
    """
    icfg = intersection_config or IntersectionConfig()
    ocfg = object_config or ObjectConfig()
    lap = lap or (lambda: None)
    edges = find_intersections(segmentation, icfg, sensor) if len(segmentation.planes) >= 2 else []
    lap()
    gravity = gravity_up(segmentation, ocfg)
    up = gravity.up_cam
    graph = build_plane_graph(segmentation.planes, edges, up, ocfg.orientation_tol_deg)
    lap()
    corners = find_corners(graph, ocfg.corner_min_det, ocfg.corner_tol_m)
    edges = snap_edges_to_corners(graph, corners, edges, ocfg.corner_tol_m)
    lap()
    objects = find_objects(graph, corners, up, ocfg, patterns)
    lap()
    return FrameStructure(
        edges=edges,
        graph=graph,
        corners=corners,
        objects=objects,
        gravity_up_cam=up,
        gravity_source=gravity.source,
        gravity_plane_id=gravity.plane_id,
        reason=structure_reason(segmentation, edges, corners, icfg.min_angle_deg),
    )


def _floats(a: np.ndarray) -> list[Any]:
    return np.asarray(a, dtype=np.float64).tolist()


def to_map_dict(segmentation: Segmentation, structure: FrameStructure) -> dict[str, Any]:
    """The shared map schema ('planeslam.map/1') of one frame, camera frame, plain JSON types.

    {"schema", "planes": [{"id", "normal", "d", "area_m2", "outline"}],
    "edges": [{"planes", "length_m", "segment", "convex"}], "corners":
    [{"planes", "point"}], "objects": [{"id", "class", "planes", "size_m"}]};
    size_m largest first.
    """
    return {
        "schema": MAP_SCHEMA,
        "planes": [
            {
                "id": int(p.id),
                "normal": _floats(p.normal),
                "d": float(p.d),
                "area_m2": float(p.area_m2),
                "outline": _floats(p.outline),
            }
            for p in segmentation.planes
        ],
        "edges": [
            {
                "planes": [int(e.planes[0]), int(e.planes[1])],
                "length_m": float(e.length_m),
                "segment": _floats(e.segment),
                "convex": bool(e.convex),
            }
            for e in structure.edges
        ],
        "corners": [
            {"planes": [int(k) for k in c.planes], "point": _floats(c.point)}
            for c in structure.corners
        ],
        "objects": [
            {
                "id": int(o.id),
                "class": str(o.cls),
                "planes": [int(k) for k in o.planes],
                "size_m": [float(s) for s in sorted(o.size_m, reverse=True)],
            }
            for o in structure.objects
        ],
    }
