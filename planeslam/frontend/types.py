"""What plane segmentation hands to the rest of the front end: `Plane`, `Segmentation`,
and the `Segmenter` protocol every segmentation method implements.

Planes are in the camera frame, n . x + d = 0 with the normal toward the camera (d > 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from planeslam.core.camera import CameraConfig, PixelRays


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
    """(3,) mean of the inliers [m] (for a plane fitted for the depth's quantisation, moved
    onto the plane: see `segment_common`)."""
    covariance: np.ndarray = field(repr=False)
    """(3, 3) covariance of the fit in OrientedPlane3 local coordinates
    (2 tangent-space normal components [rad], then d [m])."""
    scatter: np.ndarray = field(repr=False)
    """(3, 3) sum of outer products of centred inliers [m^2]: with `centroid` and
    `num_points` these are the sufficient statistics to refit or merge planes (they refit
    to this plane, also where it was fitted for the depth's quantisation)."""
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


class Segmenter(Protocol):
    """A plane segmentation method, configured at construction (`segmentation.make_segmenter`)."""

    def segment(
        self,
        cloud: np.ndarray,
        camera_or_rays: CameraConfig | PixelRays,
        rng: np.random.Generator | None = None,
        depth_m: np.ndarray | None = None,
    ) -> Segmentation:
        """The planes of one organised cloud (paper step 2).

        cloud: (H, W, 3) float32 camera-frame points [m] from `cloud.organized_cloud`
        (invalid pixels all zero). camera_or_rays: the camera (geometry cached per
        camera) or its precomputed `PixelRays`. rng: for randomised methods. depth_m:
        the (H, W) depth image the cloud came from, only to say why a frame has no
        valid depth. Planes are numbered 0..N-1 by decreasing number of inliers; a
        frame without valid depth or planes gives an empty result with `reason` set.
        """
        ...
