"""The plane graph of one frame and its trihedral angles (paper Section 4.2).

Node = plane id, edge = real intersection (`planeslam.frontend.intersections.Edge`).
Trihedral angles (corners) are the graph's 3-cycles whose three planes meet
in a point that lies on all three edges' segments. Corners that share a
graph edge (two planes) belong to one object (`aggregate_corners`).

Pure functions with explicit parameters; `planeslam.frontend.objects` drives them
from `ObjectConfig`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import networkx as nx
import numpy as np

from planeslam.core.errors import GeometryError
from planeslam.core.geometry import intersect_three_planes, point_segment_distance
from planeslam.core.types import GravitySource
from planeslam.frontend.intersections import Edge
from planeslam.frontend.types import Plane

logger = logging.getLogger(__name__)

CAMERA_UP = np.array([0.0, -1.0, 0.0])
"""Up in the camera frame of an upright camera (y points down)."""


@dataclass(frozen=True)
class Corner:
    """A real trihedral angle: three planes pairwise joined by real intersections."""

    planes: tuple[int, int, int]
    """Plane ids, increasing."""
    point: np.ndarray = field(repr=False)
    """(3,) point common to the three planes, camera frame [m]."""
    convex_edges: int
    """How many of its three edges are convex (3: box corner, 0: room corner)."""


@dataclass(frozen=True)
class GravityEstimate:
    """A frame's up direction (opposite to gravity) and where it came from."""

    up_cam: np.ndarray
    """(3,) unit up direction, camera frame."""
    source: GravitySource
    """Config, a plane of the frame, or the camera's -y axis as the fallback."""
    plane_id: int | None = None
    """Id of the plane it came from (source `PLANE`), else None."""


def estimate_gravity(planes: Sequence[Plane], max_tilt_deg: float = 45.0) -> GravityEstimate:
    """Up direction in the camera frame, estimated from a frame's planes.

    For a camera held roughly upright: the largest plane (by area) whose
    normal is within `max_tilt_deg` of the camera's up (-y, a floor or table
    seen from above: up = its normal) or of its down (+y, a ceiling: up =
    minus its normal). Without such a plane, the camera's -y axis.
    """
    cos_max = float(np.cos(np.deg2rad(max_tilt_deg)))
    best: tuple[float, np.ndarray, int] | None = None
    for plane in planes:
        c = float(np.asarray(plane.normal) @ CAMERA_UP)
        if abs(c) >= cos_max and (best is None or plane.area_m2 > best[0]):
            up = np.sign(c) * np.asarray(plane.normal, dtype=np.float64)
            best = (float(plane.area_m2), up / np.linalg.norm(up), int(plane.id))
    if best is None:
        return GravityEstimate(CAMERA_UP.copy(), GravitySource.CAMERA)
    return GravityEstimate(best[1], GravitySource.PLANE, best[2])


def plane_orientation(normal: np.ndarray, up: np.ndarray, tol_deg: float) -> tuple[str, str]:
    """(orientation, facing) of a plane with unit `normal` relative to unit `up`.

    orientation: 'horizontal' when the normal is within `tol_deg` of +-up,
    'vertical' when within `tol_deg` of perpendicular to it, else 'slanted'.
    facing: 'up' / 'down' for horizontal planes (the side the normal, i.e. the
    camera, is on: a floor or box top faces up, a ceiling down), '' otherwise.
    """
    c = float(np.clip(np.asarray(normal) @ np.asarray(up), -1.0, 1.0))
    tilt = float(np.degrees(np.arccos(abs(c))))
    if tilt <= tol_deg:
        return "horizontal", ("up" if c > 0 else "down")
    if tilt >= 90.0 - tol_deg:
        return "vertical", ""
    return "slanted", ""


def build_plane_graph(
    planes: Sequence[Plane], edges: Iterable[Edge], up_cam: np.ndarray, orientation_tol_deg: float
) -> nx.Graph:
    """Plane graph of one frame (camera frame).

    Nodes: every plane id, with attributes normal (3,), d [m], area_m2,
    orientation ('horizontal' / 'vertical' / 'slanted' w.r.t. `up_cam`) and
    facing ('up' / 'down' / ''). Edges: real intersections, with attributes
    length_m, length_eq6_m, segment (2, 3), angle_rad, convex, num_points.
    """
    graph = nx.Graph()
    for plane in planes:
        orientation, facing = plane_orientation(plane.normal, up_cam, orientation_tol_deg)
        graph.add_node(
            int(plane.id),
            normal=np.asarray(plane.normal, dtype=np.float64),
            d=float(plane.d),
            area_m2=float(plane.area_m2),
            orientation=orientation,
            facing=facing,
        )
    for edge in edges:
        i, j = edge.planes
        if i not in graph or j not in graph:
            raise GeometryError(f"edge {edge.planes} names a plane that is not in the frame")
        graph.add_edge(
            i,
            j,
            length_m=edge.length_m,
            length_eq6_m=edge.length_eq6_m,
            segment=edge.segment,
            angle_rad=edge.angle_rad,
            convex=edge.convex,
            num_points=edge.num_points,
        )
    return graph


def find_triangles(graph: nx.Graph) -> list[tuple[int, int, int]]:
    """All 3-cycles of the graph as increasing plane-id triples, sorted.

    Same set as `nx.simple_cycles(graph, length_bound=3)` (checked in the
    tests), enumerated directly from the adjacency: an order of magnitude
    cheaper on plane graphs of a few dozen nodes.
    """
    adj = {n: set(graph.adj[n]) for n in graph}
    triangles: list[tuple[int, int, int]] = []
    for a in adj:
        for b in adj[a]:
            if b <= a:
                continue
            for c in adj[a] & adj[b]:
                if c > b:
                    x, y, z = sorted((a, b, c))
                    triangles.append((x, y, z))
    return sorted(triangles)


def find_corners(graph: nx.Graph, min_det: float = 0.2, tol_m: float = 0.05) -> list[Corner]:
    """Real trihedral angles of a plane graph (camera frame).

    For each 3-cycle the corner point solves the three plane equations
    (triples with |det(normals)| < `min_det` are refused as ill-conditioned);
    it is kept only when it lies within `tol_m` of each of its three edges'
    segments, so virtual corners far outside the regions are dropped.
    """
    corners = []
    for tri in find_triangles(graph):
        normals = np.stack([graph.nodes[k]["normal"] for k in tri])
        offsets = np.array([graph.nodes[k]["d"] for k in tri])
        try:
            point = intersect_three_planes(normals, offsets, min_sin=min_det)
        except GeometryError:
            logger.debug("triangle %s: ill-conditioned, not a corner", tri)
            continue
        pairs = ((tri[0], tri[1]), (tri[0], tri[2]), (tri[1], tri[2]))
        gaps = [point_segment_distance(point, graph.edges[p]["segment"]) for p in pairs]
        if max(gaps) > tol_m:
            logger.debug("triangle %s: virtual corner (%.3f m off its edges)", tri, max(gaps))
            continue
        convex = sum(bool(graph.edges[p]["convex"]) for p in pairs)
        corners.append(Corner(planes=tri, point=point, convex_edges=convex))
    return corners


def snap_edges_to_corners(
    graph: nx.Graph, corners: Sequence[Corner], edges: Sequence[Edge], tol_m: float = 0.05
) -> list[Edge]:
    """Move each edge end that lies within `tol_m` [m] of one of its corners onto
    that corner (camera frame), in the graph's edge attributes and in the returned
    copies of `edges` (segment, length_m).

    A corner is three plane equations solved together, a few mm from the truth; an
    edge's ends come from the extent of its points, which overshoots a corner where
    a face's pixels bleed along the neighbour plane and stops short where a face
    narrows to a thin wedge. An end farther than `tol_m` from the corner (a
    T-junction: the edge runs on past it) is left alone.
    """
    segments = {pair: np.array(graph.edges[pair]["segment"], dtype=np.float64) for pair in
                {tuple(sorted(p)) for c in corners for p in
                 ((c.planes[0], c.planes[1]), (c.planes[0], c.planes[2]),
                  (c.planes[1], c.planes[2]))}}  # fmt: skip
    for corner in corners:
        a, b, c = corner.planes
        for pair in ((a, b), (a, c), (b, c)):
            seg = segments[pair]
            gaps = np.linalg.norm(seg - corner.point, axis=1)
            end = int(np.argmin(gaps))
            if gaps[end] <= tol_m and gaps[end] < 0.5 * np.linalg.norm(seg[1] - seg[0]):
                seg[end] = corner.point
    out = []
    for edge in edges:
        i, j = sorted(edge.planes)
        pair = (i, j)
        if pair in segments:
            seg = segments[pair]
            length = float(np.linalg.norm(seg[1] - seg[0]))
            graph.edges[pair]["segment"] = seg
            graph.edges[pair]["length_m"] = length
            edge = replace(edge, segment=seg, length_m=length)
        out.append(edge)
    return out


def aggregate_corners(triples: Sequence[tuple[int, int, int]]) -> list[list[int]]:
    """Group corners that share a graph edge (two planes) into objects (paper 4.2).

    `triples` are the corners' plane-id triples; returns the groups as lists of
    indices into `triples` (connected components of the 'shares an edge'
    relation, aggregated angle by angle), each sorted, ordered by first index.
    """
    link = nx.Graph()
    link.add_nodes_from(range(len(triples)))
    by_pair: dict[tuple[int, int], list[int]] = {}
    for idx, tri in enumerate(triples):
        a, b, c = sorted(tri)
        for pair in ((a, b), (a, c), (b, c)):
            by_pair.setdefault(pair, []).append(idx)
    for members in by_pair.values():
        link.add_edges_from(zip(members[:-1], members[1:], strict=True))
    groups = [sorted(c) for c in nx.connected_components(link)]
    return sorted(groups, key=lambda g: g[0])
