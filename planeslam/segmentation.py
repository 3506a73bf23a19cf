"""Plane segmentation of one organised point cloud (paper step 2).

Two methods behind `segment_planes`: `organized` (default; cell-wise fits on
the image grid merged into planes, in the spirit of PEAC/CAPE) and `msac`
(the paper's M-estimator sample consensus, plane by plane on a subsample).
Every plane is expressed in the camera frame with its normal toward the
camera (d > 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class SegmentationConfig:
    """Parameters of plane segmentation."""

    method: Literal["organized", "msac"] = "organized"
    """'organized' (fast, image-grid based, default) or 'msac' (the paper's)."""
    min_plane_points: int = 1500
    """Smallest plane kept [inlier pixels]."""
    max_depth_m: float = 6.0
    """Points farther than this are ignored [m]."""


@dataclass(frozen=True)
class Plane:
    """One plane found in one frame, camera frame, n . x + d = 0, d > 0."""

    id: int
    """Index in `Segmentation.planes` and the value of its pixels in `Segmentation.labels`."""
    normal: np.ndarray
    """(3,) unit normal pointing toward the camera."""
    d: float
    """Offset [m] (distance from the camera centre to the plane)."""
    points: np.ndarray = field(repr=False)
    """(K, 3) float64 inlier points [m]."""
    centroid: np.ndarray
    """(3,) mean of the inliers [m]."""
    covariance: np.ndarray = field(repr=False)
    """(3, 3) covariance of the fit in OrientedPlane3 local coordinates
    (2 tangent-space normal components [rad], then d [m])."""
    scatter: np.ndarray = field(repr=False)
    """(3, 3) sum of outer products of centred inliers [m^2]: with `centroid` and
    `num_points` these are the sufficient statistics to refit or merge planes."""
    num_points: int
    """Number of inliers."""
    area_m2: float
    """Area of the plane's visible region [m^2]."""
    outline: np.ndarray = field(repr=False)
    """(M, 3) closed polygon on the plane bounding its region [m] (M >= 3)."""


@dataclass(frozen=True)
class Segmentation:
    """The planes of one frame and which pixels belong to them."""

    planes: list[Plane]
    labels: np.ndarray = field(repr=False)
    """(H, W) int32: plane id per pixel, -1 for pixels on no plane."""
    reason: str = ""
    """Why the result is empty or partial (no valid depth, ...); '' when all went well."""
