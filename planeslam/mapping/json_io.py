"""Map files: the shared schema 'planeslam.map/1' (world frame) with the statistics and
state needed to continue merging after a reload. A save/load round trip is exact, and
the same map always gives the same bytes."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.core.bounded_parse import read_json_file
from planeslam.core.config import from_mapping
from planeslam.core.errors import MapError
from planeslam.core.safe_files import atomic_output
from planeslam.frontend.config import ObjectConfig
from planeslam.frontend.objects import MAP_SCHEMA
from planeslam.mapping.config import MapConfig
from planeslam.mapping.contents import MapContents
from planeslam.mapping.gravity import UpSource
from planeslam.mapping.records import MapCorner, MapEdge, MapObject, MapPlane
from planeslam.mapping.sparse_cloud import SparseCloud

SEPARATORS = (",", ":")
"""The compact JSON encoding map files use."""


def contents_to_dict(contents: MapContents) -> dict[str, Any]:
    """The map as plain JSON types, schema 'planeslam.map/1', world frame."""
    c = contents
    return {
        "schema": MAP_SCHEMA,
        "frame": "world",
        "gravity_up": None if c.up is None else _floats(c.up),
        "gravity_source": str(c.up_source),
        "frames_merged": c.frames_merged,
        "next_plane_id": c.next_plane_id,
        "next_corner_id": c.next_corner_id,
        "config": {"map": asdict(c.config), "objects": asdict(c.object_config)},
        "planes": [
            {
                "id": p.id,
                "normal": _floats(p.normal),
                "d": float(p.d),
                "area_m2": float(p.area_m2),
                "outline": _floats(p.outline),
                "centroid": _floats(p.centroid),
                "scatter": _floats(p.scatter),
                "num_points": int(p.num_points),
                "observations": int(p.observations),
                "seen_in": sorted(int(f) for f in p.seen_in),
            }
            for p in c.planes.values()
        ],
        "edges": [
            {
                "planes": [int(e.planes[0]), int(e.planes[1])],
                "length_m": float(e.length_m),
                "segment": _floats(e.segment),
                "convex": bool(e.convex),
                "angle_rad": float(e.angle_rad),
                "observations": int(e.observations),
            }
            for e in c.edges.values()
        ],
        "corners": [
            {
                "id": k.id,
                "planes": [int(p) for p in k.planes],
                "point": _floats(k.point),
                "convex_edges": int(k.convex_edges),
                "observations": int(k.observations),
            }
            for k in c.corners.values()
        ],
        "objects": [
            {
                "id": o.id,
                "class": o.cls,
                "planes": list(o.planes),
                "corners": list(o.corners),
                "size_m": list(o.size_m),
            }
            for o in c.objects
        ],
        "sparse_cloud": {
            "voxel_m": float(c.config.voxel_m),
            "keys": c.cloud.keys.tolist(),
            "points": _floats(c.cloud.points),
            "counts": c.cloud.counts.tolist(),
            "colors": c.cloud.colors.tolist(),
        },
    }


def contents_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> MapContents:
    """The inverse of `contents_to_dict` (exact). MapError naming `source` for a missing or
    unknown schema or malformed content; ConfigError for a bad stored config. An older
    file's `gravity_source` text reads as `UpSource.parse` says."""
    schema = data.get("schema") if isinstance(data, Mapping) else None
    if schema != MAP_SCHEMA:
        raise MapError(f"{source}: map schema {schema!r}, expected {MAP_SCHEMA!r}")
    if data.get("frame") != "world":
        raise MapError(f"{source}: map frame {data.get('frame')!r}, expected 'world'")
    try:
        cfg = data.get("config", {})
        c = MapContents(
            from_mapping(MapConfig, cfg.get("map", {}), source, "config.map"),
            from_mapping(ObjectConfig, cfg.get("objects", {}), source, "config.objects"),
        )
        up = data.get("gravity_up")
        c.up = None if up is None else np.asarray(up, dtype=np.float64)
        c.up_source = UpSource.parse(str(data.get("gravity_source", "")))
        c.frames_merged = int(data.get("frames_merged", 0))
        for p in data["planes"]:
            c.planes[int(p["id"])] = _plane(p)
        for e in data["edges"]:
            edge = _edge(e)
            c.edges[edge.planes] = edge
        for k in data["corners"]:
            c.corners[int(k["id"])] = _corner(k)
        c.objects = [_object(o) for o in data["objects"]]
        c.cloud = _cloud(data.get("sparse_cloud") or {}, c.config)
        c.next_plane_id = int(data.get("next_plane_id", max(c.planes, default=-1) + 1))
        c.next_corner_id = int(data.get("next_corner_id", max(c.corners, default=-1) + 1))
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError, IndexError) as exc:
        raise MapError(f"{source}: malformed map content ({type(exc).__name__}: {exc})") from None
    except MapError as exc:
        raise MapError(f"{source}: {exc}") from None
    return c


def save_json(data: Mapping[str, Any], path: str | Path) -> Path:
    """Write a map dict as compact JSON, atomically (temp file then os.replace, the usual
    file mode); returns the path."""
    path = Path(path)
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, separators=SEPARATORS)
    return path


def load_json(path: str | Path) -> dict[str, Any]:
    """The dict in a map file. MapError for a missing / unreadable file, content that is
    not a JSON object, or a number that is not finite (`bounded_parse` limits)."""
    path = Path(path)
    data = read_json_file(path, MapError, what="map file")
    if not isinstance(data, dict):
        raise MapError(f"{path}: map schema None, expected {MAP_SCHEMA!r}")
    return data


def _floats(a: Any) -> list[Any]:
    return np.asarray(a, dtype=np.float64).tolist()


def _plane(p: Mapping[str, Any]) -> MapPlane:
    return MapPlane(
        id=int(p["id"]),
        normal=np.asarray(p["normal"], dtype=np.float64),
        d=float(p["d"]),
        centroid=np.asarray(p["centroid"], dtype=np.float64),
        scatter=np.asarray(p["scatter"], dtype=np.float64).reshape(3, 3),
        num_points=int(p["num_points"]),
        area_m2=float(p["area_m2"]),
        outline=np.asarray(p["outline"], dtype=np.float64).reshape(-1, 3),
        observations=int(p["observations"]),
        seen_in=frozenset(int(f) for f in p.get("seen_in", ())),
    )


def _edge(e: Mapping[str, Any]) -> MapEdge:
    return MapEdge(
        planes=(int(e["planes"][0]), int(e["planes"][1])),
        segment=np.asarray(e["segment"], dtype=np.float64).reshape(2, 3),
        length_m=float(e["length_m"]),
        angle_rad=float(e["angle_rad"]),
        convex=bool(e["convex"]),
        observations=int(e["observations"]),
    )


def _corner(k: Mapping[str, Any]) -> MapCorner:
    return MapCorner(
        id=int(k["id"]),
        planes=tuple(int(p) for p in k["planes"]),  # type: ignore[arg-type]
        point=np.asarray(k["point"], dtype=np.float64),
        convex_edges=int(k["convex_edges"]),
        observations=int(k["observations"]),
    )


def _object(o: Mapping[str, Any]) -> MapObject:
    return MapObject(
        id=int(o["id"]),
        cls=str(o["class"]),
        planes=tuple(int(p) for p in o["planes"]),
        corners=tuple(int(k) for k in o.get("corners", ())),
        size_m=tuple(float(s) for s in o["size_m"]),
    )


def _cloud(cloud: Mapping[str, Any], config: MapConfig) -> SparseCloud:
    return SparseCloud.from_arrays(
        config.voxel_m,
        config.sparse_max_points,
        keys=np.asarray(cloud.get("keys", []), dtype=np.int64).reshape(-1, 3),
        points=np.asarray(cloud.get("points", []), dtype=np.float64).reshape(-1, 3),
        counts=np.asarray(cloud.get("counts", []), dtype=np.int64).reshape(-1),
        colors=np.asarray(cloud.get("colors", []), dtype=np.uint8).reshape(-1, 3),
    )
