"""The backend's geometry update: optimised plane and corner landmarks written into the
map, with outlines, statistics, edges and corners re-seated on the new planes."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from planeslam.core.errors import GeometryError, MapError
from planeslam.core.geometry import intersect_three_planes, rotation_between
from planeslam.mapping.contents import MapContents
from planeslam.mapping.records import MapPlane
from planeslam.mapping.seating import project_to_plane, reseat_edges

logger = logging.getLogger(__name__)


def update_geometry(
    contents: MapContents,
    planes: Mapping[int, tuple[np.ndarray, float]],
    corners: Mapping[int, np.ndarray],
) -> None:
    """Replace planes' (n (3,), d [m]) and corners' points (3,), world frame.

    Each updated plane's centroid and outline are projected onto the new plane, its
    scatter rotated by the smallest rotation from the old to the new normal (so a later
    merge refits consistently); a normal given opposite to the map's is flipped with its
    d. Edges touching updated planes are re-seated on the new intersection lines with
    their lengths kept, and their dihedral angles recomputed. Corners of updated planes
    not in `corners` are re-intersected from their three planes (kept when
    ill-conditioned). MapError for unknown ids or bad values, before anything changes.
    """
    new_planes = {
        int(pid): _moved_plane(contents.plane(pid), n, d) for pid, (n, d) in planes.items()
    }
    new_points: dict[int, np.ndarray] = {}
    for cid, x in corners.items():
        if int(cid) not in contents.corners:
            raise MapError(f"no map corner with id {cid}")
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise MapError(f"corner {cid}: expected a finite (3,) point, got {x!r}")
        new_points[int(cid)] = x
    contents.planes.update(new_planes)
    changed = set(new_planes)
    reseat_edges(contents, changed, update_angles=True)
    for cid, c in contents.corners.items():
        if cid in new_points:
            contents.corners[cid] = replace(c, point=new_points[cid])
        elif changed.intersection(c.planes):
            ps = [contents.planes[p] for p in c.planes]
            try:
                x = intersect_three_planes(
                    np.stack([p.normal for p in ps]),
                    np.array([p.d for p in ps]),
                    min_sin=contents.object_config.corner_min_det,
                )
            except GeometryError:
                logger.debug("corner %d: planes ill-conditioned, point kept", cid)
                continue
            contents.corners[cid] = replace(c, point=x)


def _moved_plane(old: MapPlane, n_in: np.ndarray, d_in: float) -> MapPlane:
    """`old` moved onto the plane (n_in, d_in), oriented like `old`."""
    n = np.asarray(n_in, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(n)) if n.shape == (3,) else 0.0
    if not (norm > 1e-9 and np.all(np.isfinite(n)) and np.isfinite(float(d_in))):
        raise MapError(f"plane {old.id}: expected a finite non-zero (3,) normal and d")
    n, d = n / norm, float(d_in) / norm
    if float(n @ old.normal) < 0:
        n, d = -n, -d
    R = rotation_between(old.normal, n)
    return replace(
        old,
        normal=n,
        d=d,
        centroid=project_to_plane(old.centroid[None], n, d)[0],
        scatter=R @ old.scatter @ R.T,
        outline=project_to_plane(old.outline, n, d),
    )
