"""The compact map's size: bytes per part (planes, edges, corners, objects, sparse
cloud), as held in memory or as written to the map file."""

from __future__ import annotations

import json
from typing import Literal

from planeslam.core.errors import MapError
from planeslam.mapping.contents import MapContents
from planeslam.mapping.json_io import SEPARATORS, contents_to_dict

PARTS = ("planes", "edges", "corners", "objects", "sparse_cloud")
"""The parts, in the order of the result (then 'total')."""


def memory_bytes(
    contents: MapContents, encoding: Literal["arrays", "json"] = "arrays"
) -> dict[str, int]:
    """Bytes of the compact map per part of `PARTS`, and their 'total'.

    'arrays': numpy nbytes of every stored value as held in memory (float64 / int64,
    uint8 colours, bool convexity, utf-8 class names): planes = id, normal, d, centroid,
    scatter, num_points, area, observations, outline; edges = ids, segment, length,
    angle, convex, observations; corners = id, ids, point, convex_edges, observations;
    objects = id, class, plane ids, corner ids, sizes; sparse_cloud = keys, points,
    counts, colours.
    'json': length of each part's compact JSON in the map file's encoding.
    """
    if encoding == "json":
        data = contents_to_dict(contents)
        parts = {k: len(json.dumps(data[k], separators=SEPARATORS).encode()) for k in PARTS}
    elif encoding == "arrays":
        parts = _array_bytes(contents)
    else:
        raise MapError(f"memory_bytes encoding {encoding!r}, expected 'arrays' or 'json'")
    parts["total"] = sum(parts.values())
    return parts


def _array_bytes(contents: MapContents) -> dict[str, int]:
    f8 = i8 = 8  # bytes of a float64, an int64
    return {
        "planes": sum(
            i8 + 3 * f8 + f8 + 3 * f8 + 9 * f8 + i8 + f8 + i8 + p.outline.size * f8
            for p in contents.planes.values()
        ),
        "edges": len(contents.edges) * (2 * i8 + 6 * f8 + f8 + f8 + 1 + i8),
        "corners": len(contents.corners) * (i8 + 3 * i8 + 3 * f8 + i8 + i8),
        "objects": sum(
            i8 + len(o.cls.encode()) + i8 * (len(o.planes) + len(o.corners)) + f8 * len(o.size_m)
            for o in contents.objects
        ),
        "sparse_cloud": contents.cloud.nbytes,
    }
