"""Real intersections between planes of one frame (paper Section 4.1, eq. 1-6)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class IntersectionConfig:
    """Parameters of real-intersection (edge) detection."""

    d_thresh_m: float = 0.02
    """Points closer than this to both planes are edge points (paper d_thresh) [m]."""


@dataclass(frozen=True)
class Edge:
    """A real intersection of two planes, camera frame."""

    planes: tuple[int, int]
    """Ids of the two planes, smaller first."""
    segment: np.ndarray = field(repr=False)
    """(2, 3) end points of the edge on the planes' intersection line [m]."""
    length_m: float
    """Robust extent of the edge points along the line [m]."""
    length_eq6_m: float
    """Length by the paper's eq. 6 from the farthest pair of edge points [m]."""
    angle_rad: float
    """Dihedral angle between the two plane regions [rad] (pi/2 for a box edge)."""
    convex: bool
    """True when the edge points toward the camera (box edge), False for a concave (room) one."""
    num_points: int
    """Number of edge points supporting it."""
