"""Planes only their first frame saw, dropped from the map once later frames did not see
them again (ORB-SLAM's culling of recent map points, for planes).

A plane seen by one keyframe gives the graph nothing that fixes a pose, and most such
planes are clutter or duplicates that association missed. After `cull_single_view_after`
more merged frames without a second sighting, the plane leaves the map with its edges and
the corners on it; objects follow at the next re-aggregation. It is remembered in
`MapContents.culled` (unless a remembered plane already covers it), so that a revisit
does not count it as new (and make keyframes of the clutter it culled).
"""

from __future__ import annotations

import numpy as np

from planeslam.mapping.contents import MapContents
from planeslam.mapping.records import MapPlane


def cull_single_view(contents: MapContents, after: int) -> list[int]:
    """Drop the planes whose only sighting is merge number `frames_merged - 1 - after` or
    earlier (0: none); their ids, increasing. Planes without a sighting record (a map
    loaded from an older file) stay."""
    if after <= 0:
        return []
    last = contents.frames_merged - 1 - after
    gone = sorted(
        pid
        for pid, plane in contents.planes.items()
        if len(plane.seen_in) == 1 and next(iter(plane.seen_in)) <= last
    )
    if not gone:
        return []
    dropped = set(gone)
    _remember(contents, [contents.planes.pop(pid) for pid in gone])
    contents.edges = {k: e for k, e in contents.edges.items() if not dropped.intersection(k)}
    contents.corners = {
        cid: c for cid, c in contents.corners.items() if not dropped.intersection(c.planes)
    }
    return gone


def _remember(contents: MapContents, planes: list[MapPlane]) -> None:
    """Keep the culled `planes` in `contents.culled`, each unless a plane remembered before
    it has its infinite plane (within the consolidation gate's angle and offset) and
    contains its centroid's footprint (within sqrt(area) of its centroid): a revisit culls
    the same clutter again. One pass over arrays of the remembered planes."""
    cfg = contents.config
    cos_max = np.cos(np.radians(cfg.consolidate_max_angle_deg))
    normals, offsets, centroids, areas = contents.culled_arrays()
    reach = np.sqrt(areas)
    for plane in planes:
        covered = (
            (normals @ plane.normal >= cos_max)
            & (np.abs(normals @ plane.centroid + offsets) <= cfg.consolidate_max_offset_m)
            & (np.linalg.norm(centroids - plane.centroid, axis=1) <= reach)
        )
        if covered.any():
            continue
        contents.culled[plane.id] = plane
        normals = np.vstack([normals, plane.normal])
        offsets = np.append(offsets, plane.d)
        centroids = np.vstack([centroids, plane.centroid])
        reach = np.append(reach, np.sqrt(plane.area_m2))
