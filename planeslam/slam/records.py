"""What SLAM made of one frame (`FrameResult`, a line of frames.jsonl) and of a run
(`RunTally` as it goes, `RunSummary` at the end)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planeslam.core.types import TrackingPath
from planeslam.frontend.pipeline import FrameObservation
from planeslam.tracking.estimator import PoseConstraints


@dataclass(frozen=True)
class FrameResult:
    """What SLAM made of one frame."""

    index: int
    """Position of the frame in the processed sequence (0, 1, ...)."""
    timestamp: float
    """[s]"""
    T_world_cam: np.ndarray
    """(4, 4) pose estimated online (before later optimisation)."""
    path: TrackingPath
    """How the pose was found."""
    reason: str
    """Why tracking needed a fallback or lost the frame; '' otherwise."""
    keyframe: bool
    """Whether the frame went into the map (merge) or the graph (isam2)."""
    observation: FrameObservation = field(repr=False)
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Wall-clock ms per stage: the front end's, then tracking, map, backend."""
    rgb: np.ndarray | None = field(default=None, repr=False)
    """(H, W, 3) uint8 colour image as given to `process` (not copied), or None."""
    constraints: PoseConstraints | None = None
    """Which degrees of freedom the planes fixed and what fixed the rest (None: first or
    lost frame)."""
    anchor: int | None = None
    """The keyframe (its `index`) whose final pose this frame's pose follows in
    `SLAM.trajectory`: the frame itself if a keyframe, else the keyframe nearest in pose
    (None: lost before any keyframe)."""
    pose_covariance: np.ndarray | None = None
    """(6, 6) covariance of `T_world_cam` in its tangent space (gtsam's Pose3 order,
    rotation [rad^2] first, then translation [m^2]): a keyframe's backend marginal once
    its update is in, else the latest keyframe marginal moved to this frame with one
    tracking step's noise (the backend's `odometry_sigma_*`). None without a graph
    (merge backend), before the first update, and for lost frames."""

    @property
    def lost(self) -> bool:
        return self.path is TrackingPath.LOST

    def to_record(self) -> dict[str, Any]:
        """One line of frames.jsonl."""
        return {
            "index": self.index,
            "timestamp": self.timestamp,
            "path": self.path.value,
            "reason": self.reason,
            "keyframe": self.keyframe,
            "planes": len(self.observation.segmentation.planes),
            "corners": len(self.observation.structure.corners),
            "frontend_reason": self.observation.reason,
            "stage_ms": {k: round(v, 3) for k, v in self.stage_ms.items()},
            "constraints": None if self.constraints is None else self.constraints.to_record(),
            "anchor": self.anchor,
        }


@dataclass(frozen=True)
class RunSummary:
    """Counts and timings of `run_frames`."""

    frames: int
    seconds: float
    """Wall-clock seconds of processing (frame reading included, start-up excluded)."""
    lost_frames: int
    keyframes: int
    paths: dict[str, int]
    """Tracking path -> number of frames."""
    frame_timings: list[dict[str, float]] = field(repr=False)
    """Per frame {stage: ms}."""
    finish_ms: float = 0.0
    """`SLAM.finish` (final batch optimisation), included in `seconds`."""
    skipped_frames: int = 0
    """Frames left out because an image could not be read (FrameReadError)."""


@dataclass
class RunTally:
    """What `run_frames` has done so far. A caller that passes its own keeps the counts of
    a run that is interrupted or fails: `summary()` then describes the frames until then."""

    start: float = field(default_factory=time.perf_counter)
    """`time.perf_counter()` when processing started."""
    frame_timings: list[dict[str, float]] = field(default_factory=list)
    """Per processed frame {stage: ms}, 'read' first."""
    paths: dict[str, int] = field(default_factory=dict)
    lost_frames: int = 0
    keyframes: int = 0
    skipped_frames: int = 0
    finish_ms: float = 0.0

    def add(self, result: FrameResult, read_ms: float) -> None:
        self.frame_timings.append({"read": read_ms, **result.stage_ms})
        self.paths[result.path.value] = self.paths.get(result.path.value, 0) + 1
        self.lost_frames += result.lost
        self.keyframes += result.keyframe

    def summary(self) -> RunSummary:
        """The counts, with the seconds since `start`."""
        return RunSummary(
            frames=len(self.frame_timings),
            seconds=time.perf_counter() - self.start,
            lost_frames=self.lost_frames,
            keyframes=self.keyframes,
            paths=dict(self.paths),
            frame_timings=list(self.frame_timings),
            finish_ms=self.finish_ms,
            skipped_frames=self.skipped_frames,
        )
