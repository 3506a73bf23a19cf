"""The per-frame front end (the paper's Fig. 2): depth -> organised cloud -> planes ->
real intersections -> plane graph -> trihedral angles -> objects with classes and sizes.

`FrontEnd` precomputes what depends only on the camera and times every stage
(`STAGES`, in order) separately.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.plane_fit import patch_covariance
from planeslam.core.types import (
    CornerMeasurement,
    EdgeMeasurement,
    FrameMeasurements,
    PlaneMeasurement,
)
from planeslam.frontend.cloud import check_depth_shape, organized_cloud
from planeslam.frontend.config import FrontEndSettings, front_end_settings
from planeslam.frontend.kernels import warm_up
from planeslam.frontend.objects import FrameStructure, build_structure, to_map_dict
from planeslam.frontend.segmentation import make_segmenter
from planeslam.frontend.types import Segmentation

log = logging.getLogger(__name__)

STAGES = ("cloud", "planes", "edges", "graph", "corners", "objects")
"""Timed stages of `FrontEnd.process`, in order (keys of `FrameObservation.stage_ms`):
cloud = depth back-projection; planes = plane segmentation; edges = real
intersections; graph = gravity and plane graph; corners = trihedral angles (and
edge ends snapped to them); objects = aggregation, classes and sizes."""


@dataclass(frozen=True)
class FrameObservation:
    """Everything the front end found in one frame, camera frame."""

    timestamp: float
    segmentation: Segmentation = field(repr=False)
    structure: FrameStructure = field(repr=False)
    stage_ms: dict[str, float]
    """Wall-clock milliseconds per stage, keys `STAGES` in order."""
    cloud: np.ndarray | None = field(default=None, repr=False)
    """(H, W, 3) float32 organised cloud, camera frame [m], invalid pixels (0, 0, 0)
    (the array the planes were found in, not a copy)."""
    sensor: DepthNoiseConfig | None = field(default=None, repr=False)
    """The depth noise model the frame was segmented with (None: unknown); it gives each
    plane measurement its correlated depth covariance."""

    @property
    def reason(self) -> str:
        """Why the result is empty or partial; '' when all went well."""
        return self.segmentation.reason or self.structure.reason

    def measurements(self) -> FrameMeasurements:
        """The typed planes, edges and corners the landmark factors need (no pixels,
        points, outlines or objects: a few kB); each plane with its correlated depth
        covariance when the sensor is known."""
        sensor = self.sensor
        return FrameMeasurements(
            timestamp=self.timestamp,
            planes=tuple(
                PlaneMeasurement(
                    p.id,
                    p.normal,
                    float(p.d),
                    p.covariance,
                    None
                    if sensor is None
                    else patch_covariance(sensor, p.normal, p.centroid, p.area_m2),
                )
                for p in self.segmentation.planes
            ),
            edges=tuple(
                EdgeMeasurement(e.planes, float(e.angle_rad), bool(e.convex))
                for e in self.structure.edges
            ),
            corners=tuple(
                CornerMeasurement(c.planes, c.point, int(c.convex_edges))
                for c in self.structure.corners
            ),
        )

    def to_dict(self) -> dict[str, Any]:
        """frame.json: the shared map schema in the camera frame, plus timing."""
        data = to_map_dict(self.segmentation, self.structure)
        data["frame"] = "camera"
        data["timestamp"] = self.timestamp
        data["reason"] = self.reason
        data["stage_ms"] = {k: round(v, 3) for k, v in self.stage_ms.items()}
        return data


class FrontEnd:
    """Runs the per-frame stages with one config; reuse it across frames.

    It changes nothing process-wide; an application may call
    `planeslam.core.native_tuning.keep_freed_memory` once (the CLI does) for about
    15 % more speed.
    """

    def __init__(self, config: FrontEndSettings | CameraConfig, seed: int = 0) -> None:
        """config: a `PlaneSlamConfig` (`load_config`), a `FrontEndConfig`, or a bare
        `CameraConfig` (the other sections at their defaults)."""
        config = front_end_settings(config)
        self.config = config
        self.rays = PixelRays.for_camera(config.camera)
        self.rng = np.random.default_rng(seed)
        self.segmenter = make_segmenter(config.segmentation, config.sensor)
        warm_up()  # the compiled kernels, before the first frame's clock starts

    def process(self, depth_m: np.ndarray, timestamp: float = 0.0) -> FrameObservation:
        """(H, W) depth [m], 0 = invalid -> the frame's planes, edges, corners and objects.

        NaN, inf, negative and too-far depths are invalid pixels; a frame without
        valid depth or planes gives an empty result with `reason` set. Raises
        GeometryError only when the depth image's shape does not match the camera.
        """
        cfg = self.config
        check_depth_shape(depth_m, self.rays.rays.shape[:2])
        t = [time.perf_counter()]
        cloud = organized_cloud(depth_m, self.rays, cfg.segmentation.max_depth_m)
        t.append(time.perf_counter())
        seg = self.segmenter.segment(cloud, self.rays, self.rng, depth_m)
        t.append(time.perf_counter())
        structure = build_structure(
            seg,
            cfg.intersections,
            cfg.objects,
            lap=lambda: t.append(time.perf_counter()),
            sensor=cfg.sensor,
        )
        return FrameObservation(
            timestamp=timestamp,
            segmentation=seg,
            structure=structure,
            stage_ms={
                name: 1e3 * (b - a) for name, a, b in zip(STAGES, t[:-1], t[1:], strict=True)
            },
            cloud=cloud,
            sensor=cfg.sensor,
        )
