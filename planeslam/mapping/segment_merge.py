"""Map planes that came to lie on one plane segment, merged into one.

Consolidation at merge time (`merge._same_plane_segment`) joins an observation to the map
plane it is part of, under the pose of that moment. Two map planes made apart (at frames
whose poses the backend later corrected, or as two segments of one frame) can still come
to lie on one segment once the backend has moved them: the same infinite plane within
`merge_segments_max_angle_deg` and `merge_segments_max_offset_m` (each plane's centroid
off the other), outlines overlapping or at most `consolidate_max_gap_m` apart, and never
seen apart in one frame (two segments of one wall, left and right of a cupboard: merged,
the next frame would find two observed planes for one map plane, and one-to-one
association would make the second a new plane every time). The plane seen more often
absorbs the other: moments, outline and observations joined, its edges and
corners re-pointed (duplicates joined). Objects follow at the next re-aggregation; the
orchestrator sends each pair to the backend, which ties the two landmarks in the graph
(`PlaneLandmarks.join_planes`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from planeslam.core.plane_fit import merge_moments
from planeslam.mapping.contents import MapContents
from planeslam.mapping.records import MapEdge, MapPlane
from planeslam.mapping.seating import hull_on_plane, outline_gap, project_to_plane, reseat_edges


def merge_same_segments(contents: MapContents, plane_ids: Iterable[int]) -> dict[int, int]:
    """Merge each map plane of `plane_ids` with a map plane on the same segment (module
    docstring); {absorbed plane id: surviving plane id}."""
    candidates = [int(p) for p in sorted(set(plane_ids)) if int(p) in contents.planes]
    if not candidates:
        return {}
    ids, normals, offsets = contents.plane_arrays()  # once: a merge keeps the survivor's
    centroids = np.array([p.centroid for p in contents.planes.values()]).reshape(-1, 3)
    row = {int(pid): k for k, pid in enumerate(ids)}
    alive = np.ones(len(ids), dtype=bool)
    absorbed: dict[int, int] = {}
    for pid in candidates:
        plane = contents.planes.get(pid)
        if plane is None:
            continue
        partner = _same_segment(
            contents, plane, ids[alive], normals[alive], offsets[alive], centroids[alive]
        )
        if partner is None:
            continue
        keep, gone = sorted((plane, partner), key=lambda p: (-p.observations, p.id))
        _absorb(contents, keep, gone)
        absorbed[gone.id] = keep.id
        alive[row[gone.id]] = False
        centroids[row[keep.id]] = contents.planes[keep.id].centroid
    return {gone: _final(absorbed, keep) for gone, keep in absorbed.items()}


def _final(absorbed: dict[int, int], pid: int) -> int:
    """Where plane `pid` went after a chain of merges."""
    while pid in absorbed:
        pid = absorbed[pid]
    return pid


def _same_segment(
    contents: MapContents,
    plane: MapPlane,
    ids: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    centroids: np.ndarray,
) -> MapPlane | None:
    """The map plane of ids (M,) (normals (M, 3), offsets (M,), centroids (M, 3), world
    frame), other than `plane`, on its segment with the nearest outline, or None."""
    cfg = contents.config
    close = (
        (normals @ plane.normal >= math.cos(math.radians(cfg.merge_segments_max_angle_deg)))
        & (np.abs(normals @ plane.centroid + offsets) <= cfg.merge_segments_max_offset_m)
        & (np.abs(centroids @ plane.normal + plane.d) <= cfg.merge_segments_max_offset_m)
        & (ids != plane.id)
    )
    if not close.any():
        return None
    best, best_gap = None, cfg.consolidate_max_gap_m
    for pid in ids[close]:
        other = contents.planes[int(pid)]
        if other.seen_in & plane.seen_in:
            continue
        gap = outline_gap(plane.outline, other.outline, plane.normal, plane.d)
        if gap <= best_gap:
            best, best_gap = other, gap
    return best


def _absorb(contents: MapContents, keep: MapPlane, gone: MapPlane) -> None:
    """`gone` joined into `keep` (planes, edges, corners); `gone` leaves the map."""
    total, centroid, scatter = merge_moments(
        np.array([keep.num_points, gone.num_points]),
        np.stack([keep.centroid, gone.centroid]),
        np.stack([keep.scatter, gone.scatter]),
    )
    outline, area = hull_on_plane(np.concatenate([keep.outline, gone.outline]), keep.normal, keep.d)
    contents.planes[keep.id] = replace(
        keep,
        centroid=project_to_plane(centroid[None], keep.normal, keep.d)[0],
        scatter=scatter,
        num_points=total,
        area_m2=area,
        outline=outline,
        observations=keep.observations + gone.observations,
        seen_in=keep.seen_in | gone.seen_in,
    )
    del contents.planes[gone.id]
    for key in [k for k in contents.edges if gone.id in k]:
        edge = contents.edges.pop(key)
        other = key[0] if key[1] == gone.id else key[1]
        if other == keep.id:
            continue
        new_key = (min(keep.id, other), max(keep.id, other))
        existing = contents.edges.get(new_key)
        contents.edges[new_key] = _joined_edge(new_key, edge, existing)
    reseat_edges(contents, {keep.id})
    on_gone = [cid for cid, c in contents.corners.items() if gone.id in c.planes]
    by_triple = {c.planes: c.id for c in contents.corners.values()} if on_gone else {}
    for cid in on_gone:
        corner = contents.corners.pop(cid)
        triple = tuple(sorted(keep.id if p == gone.id else p for p in corner.planes))
        if len(set(triple)) < 3:
            continue
        twin = by_triple.get(triple)  # type: ignore[arg-type]
        if twin is None or twin not in contents.corners:
            contents.corners[cid] = replace(corner, planes=triple)  # type: ignore[arg-type]
            by_triple[triple] = cid  # type: ignore[index]
            continue
        old = contents.corners[twin]
        w_old, w_new = max(old.observations, 1), max(corner.observations, 1)  # derived: 0
        point = (old.point * w_old + corner.point * w_new) / (w_old + w_new)
        contents.corners[twin] = replace(
            old, point=point, observations=old.observations + corner.observations
        )


def _joined_edge(key: tuple[int, int], edge: MapEdge, existing: MapEdge | None) -> MapEdge:
    """`edge` re-keyed to `key`, joined with the edge already there (longest kept)."""
    if existing is None:
        return replace(edge, planes=key)
    longer = edge if edge.length_m > existing.length_m else existing
    count = edge.observations + existing.observations
    angle = (edge.angle_rad * edge.observations + existing.angle_rad * existing.observations) / max(
        count, 1
    )
    return replace(longer, planes=key, angle_rad=angle, observations=count)
