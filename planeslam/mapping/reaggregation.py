"""Objects of the merged map (paper 4.2-4.3 re-run on the map graph): the map's plane
graph, corners it implies, corners sharing an edge aggregated into objects, classified
by the pattern table and sized from the edges, with the map's up vector."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import networkx as nx
import numpy as np

from planeslam.frontend.objects import ObjectPattern, classify_and_size
from planeslam.frontend.plane_graph import aggregate_corners, find_corners, plane_orientation
from planeslam.mapping.contents import MapContents
from planeslam.mapping.gravity import refine_up
from planeslam.mapping.records import MapCorner, MapObject

logger = logging.getLogger(__name__)


def map_graph(contents: MapContents) -> nx.Graph:
    """Plane graph of the map (world frame): planes and edges seen at least
    `min_observations` times, with the attributes of
    `planeslam.frontend.plane_graph.build_plane_graph` (orientation w.r.t. the world up;
    'slanted' for every plane while up is unknown)."""
    min_obs = contents.config.min_observations
    tol = contents.object_config.orientation_tol_deg
    g = nx.Graph()
    for p in contents.planes.values():
        if p.observations < min_obs:
            continue
        if contents.up is None:
            orientation, facing = "slanted", ""
        else:
            orientation, facing = plane_orientation(p.normal, contents.up, tol)
        g.add_node(
            p.id,
            normal=p.normal,
            d=p.d,
            area_m2=p.area_m2,
            orientation=orientation,
            facing=facing,
        )
    for (i, j), e in contents.edges.items():
        if e.observations >= min_obs and i in g and j in g:
            g.add_edge(
                i,
                j,
                length_m=e.length_m,
                segment=e.segment,
                angle_rad=e.angle_rad,
                convex=e.convex,
                observations=e.observations,
            )
    return g


def reaggregate(contents: MapContents, patterns: Sequence[ObjectPattern]) -> list[MapObject]:
    """Recompute `contents.objects` (ids 0..K-1) and return them: an up taken from a frame
    first follows the map (`gravity.refine_up`), corners the graph implies are added when
    `derive_corners`, then corners sharing an edge form an object."""
    ocfg = contents.object_config
    if contents.up is not None and contents.up_source.follows_map:
        contents.up = refine_up(contents.up, contents.planes.values(), ocfg.orientation_tol_deg)
    graph = map_graph(contents)
    if contents.config.derive_corners:
        _add_derived_corners(contents, graph)
    live = [c for c in contents.corners.values() if _in_graph(c, graph)]
    up = contents.up if contents.up is not None else np.array([0.0, 0.0, 1.0])
    objects: list[MapObject] = []
    for group in aggregate_corners([c.planes for c in live]):
        object_planes = {p for k in group for p in live[k].planes}
        cls, size = classify_and_size(
            graph, object_planes, up, ocfg.axis_tol_deg, patterns, convex_part_only=True
        )
        objects.append(
            MapObject(
                id=len(objects),
                cls=cls,
                planes=tuple(sorted(object_planes)),
                corners=tuple(sorted(live[k].id for k in group)),
                size_m=tuple(sorted((float(s) for s in size), reverse=True)),
            )
        )
    contents.objects = objects
    return list(objects)


def _add_derived_corners(contents: MapContents, graph: nx.Graph) -> None:
    """Add the trihedral corners of the merged graph that no frame saw (three edges
    observed in different frames), as the paper's re-initialisation; observations 0."""
    ocfg = contents.object_config
    known = {c.planes for c in contents.corners.values()}
    for c in find_corners(graph, ocfg.corner_min_det, ocfg.corner_tol_m):
        if c.planes not in known:
            cid = contents.new_corner_id()
            contents.corners[cid] = MapCorner(
                id=cid,
                planes=c.planes,
                point=c.point,
                convex_edges=c.convex_edges,
                observations=0,
            )
            logger.debug("corner %s derived from the merged map graph", c.planes)


def _in_graph(corner: MapCorner, graph: nx.Graph) -> bool:
    """Whether the corner's three planes and their three edges are all in the graph."""
    a, b, c = corner.planes
    return (
        all(p in graph for p in corner.planes)
        and graph.has_edge(a, b)
        and graph.has_edge(a, c)
        and graph.has_edge(b, c)
    )
