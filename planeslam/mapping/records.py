"""The map's element records: planes, edges, corners and objects, world frame.

Records are frozen: the map replaces a record when it changes, so a record handed
out (`Map.planes[...]`) never changes under its holder.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class MapPlane:
    """A plane of the map, world frame, n . x + d = 0 (n oriented as first observed)."""

    id: int
    normal: np.ndarray
    """(3,) unit normal, world frame."""
    d: float
    """Offset [m]."""
    centroid: np.ndarray
    """(3,) mean of all inliers merged so far, world frame [m]."""
    scatter: np.ndarray = field(repr=False)
    """(3, 3) centred sum of outer products of all inliers, world frame [m^2]."""
    num_points: int
    """Inliers merged so far (over all observations)."""
    area_m2: float
    """Area of the outline [m^2] (the frame's visible area until merged once)."""
    outline: np.ndarray = field(repr=False)
    """(M, 3) polygon on the plane, world frame [m]; the convex hull once merged."""
    observations: int
    """Frames that observed it."""
    seen_in: frozenset[int] = frozenset()
    """Merge numbers (`MapContents.frames_merged` before each merge) of the frames that
    observed it: two planes seen apart in one frame are two segments."""


@dataclass(frozen=True, eq=False)
class MapEdge:
    """A real intersection of two map planes, world frame."""

    planes: tuple[int, int]
    """Map plane ids, smaller first."""
    segment: np.ndarray = field(repr=False)
    """(2, 3) end points on the planes' intersection line, world frame [m]."""
    length_m: float
    """Longest length observed [m] (the paper's merge rule)."""
    angle_rad: float
    """Dihedral angle between the regions [rad] (pi - angle between the normals)."""
    convex: bool
    """Convexity of the longest observation."""
    observations: int


@dataclass(frozen=True, eq=False)
class MapCorner:
    """A trihedral corner of three map planes, world frame."""

    id: int
    planes: tuple[int, int, int]
    """Map plane ids, increasing."""
    point: np.ndarray
    """(3,) corner point, world frame [m] (count-weighted mean of the observed points)."""
    convex_edges: int
    """How many of its three edges are convex (3: box corner, 0: room corner)."""
    observations: int
    """Frames that observed it; 0 for a corner derived from the merged map graph."""


@dataclass(frozen=True)
class MapObject:
    """A plane-based object of the map: corners sharing edges, with class and size."""

    id: int
    cls: str
    """Class from the pattern table ('box', 'room', ...) or 'unknown'."""
    planes: tuple[int, ...]
    """Map plane ids, increasing."""
    corners: tuple[int, ...]
    """Map corner ids, increasing."""
    size_m: tuple[float, ...]
    """Extents along up to three orthogonal directions, largest first [m]."""
