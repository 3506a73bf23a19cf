"""The per-frame front end (the paper's Fig. 2): depth -> planes -> real
intersections -> plane graph -> trihedral angles -> objects with classes and sizes.

`FrontEnd` precomputes what depends only on the camera and times every stage.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planeslam.camera import PixelRays
from planeslam.config import PlaneSlamConfig
from planeslam.objects import FrameStructure, build_structure, to_map_dict
from planeslam.segmentation import Segmentation, segment_planes

STAGES = ("planes", "structure")


@dataclass(frozen=True)
class FrameObservation:
    """Everything the front end found in one frame, camera frame."""

    timestamp: float
    segmentation: Segmentation = field(repr=False)
    structure: FrameStructure = field(repr=False)
    stage_ms: dict[str, float]
    """Wall-clock milliseconds per stage."""

    @property
    def reason(self) -> str:
        """Why the result is empty or partial; '' when all went well."""
        return self.segmentation.reason or self.structure.reason

    def to_dict(self) -> dict[str, Any]:
        """frame.json: the shared map schema in the camera frame, plus timing."""
        data = to_map_dict(self.segmentation, self.structure)
        data["frame"] = "camera"
        data["timestamp"] = self.timestamp
        data["reason"] = self.reason
        data["stage_ms"] = {k: round(v, 3) for k, v in self.stage_ms.items()}
        return data


class FrontEnd:
    """Runs the per-frame stages with one config; reuse it across frames."""

    def __init__(self, config: PlaneSlamConfig, seed: int = 0) -> None:
        self.config = config
        self.rays = PixelRays.for_camera(config.camera)
        self.rng = np.random.default_rng(seed)

    def process(self, depth_m: np.ndarray, timestamp: float = 0.0) -> FrameObservation:
        """(H, W) depth [m], 0 = invalid -> the frame's planes, edges, corners and objects."""
        cfg = self.config
        t0 = time.perf_counter()
        segmentation = segment_planes(depth_m, self.rays, cfg.segmentation, rng=self.rng)
        t1 = time.perf_counter()
        structure = build_structure(segmentation, cfg.intersections, cfg.objects)
        t2 = time.perf_counter()
        return FrameObservation(
            timestamp=timestamp,
            segmentation=segmentation,
            structure=structure,
            stage_ms={"planes": (t1 - t0) * 1e3, "structure": (t2 - t1) * 1e3},
        )
