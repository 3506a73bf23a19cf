"""The interface between the orchestrator and a backend, and the values that cross it.

A backend takes keyframes (`submit`), returns one `KeyframeUpdate` per keyframe in
submission order (`collect`, at most `lag_frames` frames later) and the final state
(`finish`). The orchestrator merges every keyframe into the plane-object map first, so
landmark ids are the map's plane and corner ids: the map supplies data association, and
it stays the one owner of plane state (the backend only sends it estimates).

Two implementations: `merge.MergeBackend` (the paper's Section 4.4: the map merge is the
whole backend, every tracked frame a keyframe, nothing revised) and `worker.Isam2Worker`
(the iSAM2 factor graph of `isam2.Isam2Backend`, in a child process beside tracking).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from planeslam.core.types import FrameMeasurements, LoopConstraint, PlaneEstimate, RelativePose


class BackendKind(str, enum.Enum):
    """The backends `factory.create_backend` builds."""

    ISAM2 = "isam2"
    MERGE = "merge"

    def __str__(self) -> str:
        return self.value


class ConstraintKind(str, enum.Enum):
    """Constraints the iSAM2 backend can take back out of its graph."""

    RELOCALISATION = "relocalisation"
    """A relocalised keyframe's placement in the map: the factors of its group on older
    landmarks (`planeslam.backend.hypotheses`)."""
    LOOP = "loop"
    """A loop constraint (`LoopConstraint`)."""

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class RejectedConstraint:
    """A relocalisation or loop that later keyframes contradicted: out of the graph."""

    kind: ConstraintKind
    index: int
    """Frame index of the keyframe placed (the relocalised one, or the loop's)."""
    old_index: int
    """The keyframe it was placed against: the previous keyframe of a relocalisation, the
    older keyframe of a loop."""
    at_index: int
    """The keyframe whose update rejected it."""
    reason: str
    """What contradicted it, in words."""


@dataclass(frozen=True)
class KeyframeInput:
    """One keyframe handed to a backend."""

    index: int
    """Frame index, strictly increasing over the keyframes."""
    timestamp: float
    """[s]"""
    T_world_cam: np.ndarray
    """(4, 4) pose from tracking (initialises new landmarks too)."""
    measurements: FrameMeasurements
    plane_ids: dict[int, int]
    """Observed plane id -> landmark (map plane) id."""
    corner_ids: dict[int, int]
    """Index in `measurements.corners` -> landmark (map corner) id."""
    T_prev_cam: np.ndarray | None
    """(4, 4) measured pose in the previous keyframe's camera frame; None for the first."""
    joined_planes: tuple[tuple[int, int], ...] = ()
    """(absorbed, surviving) map plane ids the map joined since the last keyframe
    (`Map.merge_same_segments`): one plane, to be tied in the graph too."""
    odometry: RelativePose | None = None
    """The caller's odometry since the previous keyframe (`SLAM.process(odometry=...)`,
    composed over the frames between), beside tracking's `T_prev_cam`; None: not given."""
    loops: tuple[LoopConstraint, ...] = ()
    """Poses of it or of earlier keyframes (`LoopConstraint.index`: a loop detector beside
    tracking may deliver a keyframe's with a later one) against older keyframes they
    revisit, from the caller's own loop detector (planeslam has none)."""
    relocalised: bool = False
    """Whether `T_prev_cam` is no measured motion: the keyframe was placed by a whole-map
    search, or frames since the previous keyframe were lost. The backend then ties it to the
    previous keyframe only weakly and keeps its placement revocable
    (`BackendConfig.relocalisation_trial_keyframes`)."""


@dataclass(frozen=True)
class KeyframeUpdate:
    """What the backend made of one keyframe."""

    index: int
    """Frame index of the keyframe."""
    T_world_cam: np.ndarray
    """(4, 4) its pose after its own update."""
    planes: dict[int, PlaneEstimate]
    """Plane landmark id -> estimate after the update, for the planes this keyframe saw."""
    corners: dict[int, np.ndarray]
    """Corner landmark id -> p_world (3,) [m] after the update, for its corners."""
    update_ms: float
    """Wall-clock ms of the backend's work for this keyframe."""
    covariance: np.ndarray | None = None
    """(6, 6) marginal covariance of its pose after the update, in the pose's tangent space
    (gtsam's Pose3 order, rotation first); None when the backend has none."""
    rejected: tuple[RejectedConstraint, ...] = ()
    """Relocalisations and loops this update took out of the graph."""


@dataclass(frozen=True)
class BackendResult:
    """A backend's final state (after the batch optimisation of `finish`, if any)."""

    keyframe_poses: dict[int, np.ndarray]
    """Keyframe index -> final T_world_cam (4, 4)."""
    planes: dict[int, PlaneEstimate] = field(default_factory=dict)
    """Plane landmark id -> final estimate (empty: the map's planes stand)."""
    corners: dict[int, np.ndarray] = field(default_factory=dict)
    """Corner landmark id -> final p_world (3,) [m]."""
    update_ms: list[float] = field(default_factory=list)
    """Per keyframe, as in `KeyframeUpdate.update_ms`."""
    batch_ms: float = 0.0
    """Wall-clock ms of the final batch optimisation."""
    failures: int = 0
    """Indeterminate updates caught and handled."""
    num_factors: int = 0
    """Factors in the graph (0 without one)."""
    peak_rss_mb: float = 0.0
    """Peak resident memory of the backend's own process [MiB] (0 when it ran inline)."""
    rejected: tuple[RejectedConstraint, ...] = ()
    """Every relocalisation and loop taken out of the graph, in order."""


class Backend(Protocol):
    """What the orchestrator needs of a backend."""

    kind: BackendKind
    lag_frames: int
    """A keyframe's update is collected before tracking the frame this many frames after
    it (or at the next keyframe, if sooner); 0: at once."""
    objects_every_keyframe: bool
    """Whether the map re-aggregates its objects at every merge (otherwise at `finish`)."""
    takes_loops: bool
    """Whether `KeyframeInput.loops` reach its poses (the merge backend never revises one)."""
    map_cull_single_view_after: int
    """`map.cull_single_view_after` when the config leaves it to the backend (null): 5
    keyframes with isam2; 0 with merge, which merges every frame and never revises one."""
    map_merge_segments: bool
    """`map.merge_segments` when the config leaves it to the backend (null)."""

    def is_keyframe(
        self, T_keyframes: np.ndarray, T_now: np.ndarray, frames_since: int, new_planes: int
    ) -> bool:
        """Whether a mapped frame at T_now (4, 4) becomes a keyframe; T_keyframes (K, 4, 4):
        the keyframes so far, the last one last; `frames_since` the last one."""
        ...

    def submit(self, keyframe: KeyframeInput) -> None:
        """Hand a keyframe over without waiting for its update."""
        ...

    def collect(self) -> KeyframeUpdate:
        """The update of the oldest keyframe not collected yet (waits for it)."""
        ...

    def finish(self) -> BackendResult:
        """Final optimisation and state; the backend then takes no more keyframes."""
        ...

    def close(self) -> None:
        """Stop without optimising, dropping pending work (idempotent, prompt)."""
        ...
