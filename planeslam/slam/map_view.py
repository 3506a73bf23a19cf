"""The plane-object map as tracking's view: its planes, corners, edges and objects as
arrays (world frame), rebuilt by `SLAM.map_view` after the map changed."""

from __future__ import annotations

import numpy as np

from planeslam.mapping.world_map import Map
from planeslam.tracking.views import MapView


def map_view(world_map: Map) -> MapView:
    """The planes, corners, edges and objects (with corners) of `world_map` as tracking's
    arrays, world frame."""
    ids, normals, d = world_map.plane_arrays()
    corner_ids, corner_planes, corner_points = world_map.corner_arrays()
    corners, planes = world_map.corners, world_map.planes
    row = {int(pid): k for k, pid in enumerate(ids)}
    edges = list(world_map.edges.values())
    objects = [o for o in world_map.objects if o.corners and all(c in corners for c in o.corners)]
    culled_normals, culled_d, culled_areas = world_map.culled_plane_arrays()
    return MapView(
        ids,
        normals,
        d,
        corner_ids,
        corner_planes,
        corner_points,
        np.array([corners[int(c)].convex_edges for c in corner_ids], dtype=np.int64),
        np.array([planes[int(i)].area_m2 for i in ids], dtype=np.float64),
        edge_planes=np.array([[row[a], row[b]] for a, b in (e.planes for e in edges)])
        .astype(np.int64)
        .reshape(-1, 2),
        edge_segments=np.array([e.segment for e in edges], dtype=np.float64).reshape(-1, 2, 3),
        edge_lengths=np.array([e.length_m for e in edges], dtype=np.float64),
        edge_angles=np.array([e.angle_rad for e in edges], dtype=np.float64),
        edge_convex=np.array([e.convex for e in edges], dtype=bool),
        object_classes=tuple(o.cls for o in objects),
        object_sizes=tuple(tuple(o.size_m) for o in objects),
        object_centres=np.array(
            [np.mean([corners[c].point for c in o.corners], axis=0) for o in objects]
        ).reshape(-1, 3),
        culled_normals=culled_normals,
        culled_d=culled_d,
        culled_areas=culled_areas,
    )
