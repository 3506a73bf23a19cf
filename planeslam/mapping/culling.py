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
    for pid in gone:
        plane = contents.planes.pop(pid)
        if not _remembered(contents, plane):
            contents.culled[pid] = plane
    contents.edges = {k: e for k, e in contents.edges.items() if not dropped.intersection(k)}
    contents.corners = {
        cid: c for cid, c in contents.corners.items() if not dropped.intersection(c.planes)
    }
    return gone


def _remembered(contents: MapContents, plane: MapPlane) -> bool:
    """Whether a culled plane already remembered has `plane`'s infinite plane (within the
    consolidation gate's angle and offset) and contains its centroid's footprint: a revisit
    culls the same clutter again."""
    cfg = contents.config
    cos_max = np.cos(np.radians(cfg.consolidate_max_angle_deg))
    for old in contents.culled.values():
        if (
            float(old.normal @ plane.normal) >= cos_max
            and abs(float(old.normal @ plane.centroid) + old.d) <= cfg.consolidate_max_offset_m
            and np.linalg.norm(old.centroid - plane.centroid) <= np.sqrt(old.area_m2)
        ):
            return True
    return False
