"""Plane segmentation of one organised point cloud (paper step 2): pick the method.

Two `Segmenter`s (`planeslam.frontend.types`), chosen by `segmentation.method`:
`organized` (default; cell-wise fits on the image grid merged into planes, in the
spirit of PEAC/CAPE: `planeslam.frontend.organized`, whose docstring gives the
algorithm step by step) and `msac` (the paper's M-estimator sample consensus, plane
by plane on a subsample: `planeslam.frontend.msac`). Both take their thresholds in
multiples of the `sensor` depth noise sigma(z) = a + b z^2.

`segment_planes(depth)` = `cloud.organized_cloud` + `segment_cloud(cloud)`; the
front end calls the two separately (its `cloud` and `planes` stages).
"""

from __future__ import annotations

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.frontend.cloud import back_project
from planeslam.frontend.config import SegmentationConfig
from planeslam.frontend.msac import MsacSegmenter
from planeslam.frontend.organized import OrganizedSegmenter
from planeslam.frontend.segment_common import pixel_grid
from planeslam.frontend.types import Segmentation, Segmenter

__all__ = [
    "MsacSegmenter",
    "OrganizedSegmenter",
    "make_segmenter",
    "segment_cloud",
    "segment_planes",
]


def make_segmenter(
    config: SegmentationConfig | None = None, sensor: DepthNoiseConfig | None = None
) -> Segmenter:
    """The segmenter `config.method` names, configured with `config` and the depth noise."""
    cfg = config or SegmentationConfig()
    noise = sensor or DepthNoiseConfig()
    if cfg.method == "msac":
        return MsacSegmenter(cfg, noise)
    return OrganizedSegmenter(cfg, noise)


def segment_planes(
    depth_m: np.ndarray,
    camera_or_rays: CameraConfig | PixelRays,
    config: SegmentationConfig | None = None,
    rng: np.random.Generator | None = None,
    sensor: DepthNoiseConfig | None = None,
) -> Segmentation:
    """Find the planes of one depth image (paper step 2).

    depth_m: (H, W) depth along the optical axis [m]; 0, negative, NaN, inf and
    values beyond `config.max_depth_m` are invalid. camera_or_rays: the camera
    (rays cached per camera) or its precomputed `PixelRays`. rng: used by
    'msac' only (default: seeded with 0). sensor: the depth noise (default
    `DepthNoiseConfig()`). Returns planes in the camera frame,
    ids 0..N-1 by decreasing number of inliers, and the (H, W) int32 label
    image. A frame without valid depth or without planes gives an empty
    result with `reason` set. Raises GeometryError when the depth shape does
    not match the camera. Same as `organized_cloud` then `segment_cloud`.
    """
    cfg = config or SegmentationConfig()
    cloud = back_project(depth_m, pixel_grid(camera_or_rays).rays32, cfg.max_depth_m)
    return segment_cloud(cloud, camera_or_rays, cfg, rng, depth_m=depth_m, sensor=sensor)


def segment_cloud(
    cloud: np.ndarray,
    camera_or_rays: CameraConfig | PixelRays,
    config: SegmentationConfig | None = None,
    rng: np.random.Generator | None = None,
    depth_m: np.ndarray | None = None,
    sensor: DepthNoiseConfig | None = None,
) -> Segmentation:
    """`segment_planes` on a precomputed organised cloud (the front end's `cloud` stage).

    cloud: (H, W, 3) float32 camera-frame points [m] from `cloud.organized_cloud`
    (invalid pixels all zero; z > 0 is the validity mask); points beyond
    `config.max_depth_m` are ignored. depth_m: the (H, W) depth image it came
    from, used only to say why a frame has no valid depth (NaN, <= 0, too far).
    """
    return make_segmenter(config, sensor).segment(cloud, camera_or_rays, rng, depth_m)
