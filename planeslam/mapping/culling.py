"""Planes only their first frame saw, dropped from the map once later frames did not see
them again (ORB-SLAM's culling of recent map points, for planes).

A plane seen by one keyframe gives the graph nothing that fixes a pose, and most such
planes are clutter or duplicates that association missed. After `cull_single_view_after`
more merged frames without a second sighting, the plane leaves the map with its edges and
the corners on it; objects follow at the next re-aggregation.
"""

from __future__ import annotations

from planeslam.mapping.contents import MapContents


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
        del contents.planes[pid]
    contents.edges = {k: e for k, e in contents.edges.items() if not dropped.intersection(k)}
    contents.corners = {
        cid: c for cid, c in contents.corners.items() if not dropped.intersection(c.planes)
    }
    return gone
