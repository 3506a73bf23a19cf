"""Config of the iSAM2 backend and the keyframe rule, a leaf module: no gtsam, no algorithms."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

from planeslam.core.errors import ConfigError
from planeslam.factors.config import LandmarkConfig, LandmarkKeys


@dataclass(frozen=True)
class BackendConfig:
    """iSAM2 backend: noise of odometry and prior, iSAM2 settings, keyframe selection."""

    odometry_sigma_rot_rad: float = 0.01
    """Sigma of each rotation component of a keyframe-to-keyframe odometry factor [rad]."""
    odometry_sigma_trans_m: float = 0.02
    """Sigma of each translation component of an odometry factor [m]."""
    loop_sigma_rot_rad: float = 0.01
    """Sigma of each rotation component of a loop factor (a keyframe placed against an
    older keyframe by the caller's loop detector, `KeyframeInput.loops`) [rad] ..."""
    loop_sigma_trans_m: float = 0.02
    """... and of each translation component [m]; Huber-robust at `loop_huber_k` sigmas."""
    loop_huber_k: float = 2.0
    """Huber threshold of a loop factor [sigmas]."""
    relocalisation_trial_keyframes: int = 10
    """A relocalised keyframe (`KeyframeInput.relocalised`: placed by a whole-map search, or
    after lost frames) is tied to the previous keyframe only weakly, and for this many
    keyframes its group's factors on landmarks older than it (what places it in the map)
    stay revocable: a loop that puts the group elsewhere waits, and when more such loops
    agree with each other than with the relocalisation, the relocalisation's factors are
    removed and its group moved to where the loops put it (`planeslam.backend.hypotheses`).
    0: a relocalised keyframe enters like a tracked one (a confident odometry factor from
    the guess) and for good."""
    prior_sigma_rot_rad: float = 1e-4
    """Sigma of the prior on the first keyframe's rotation [rad]."""
    prior_sigma_trans_m: float = 1e-4
    """Sigma of the prior on the first keyframe's translation [m]."""
    relinearize_threshold: float = 0.01
    """iSAM2 relinearises a variable whose delta exceeds this (local coordinates). Online
    speed against accuracy: lower costs update time; the final batch optimisation
    (`final_iterations`) recovers the accuracy."""
    relinearize_skip: int = 1
    """iSAM2 checks for relinearisation every this many updates (gtsam's default 10
    converges too loosely for plane landmarks)."""
    extra_updates: int = 0
    """Additional ISAM2.update() iterations after each keyframe's update."""
    final_iterations: int = 2
    """Gauss-Newton iterations over the whole graph when a run finishes (>= 0; 0: none).
    From iSAM2's estimate two suffice; each costs about one batch elimination."""
    max_planes_per_keyframe: int = 0
    """0: every associated plane of a keyframe becomes a factor. N > 0: at most N, the
    re-observed landmarks first, each group chosen to fix the pose best
    (`isam2.informative_planes`); the map keeps every plane, those without a landmark
    stay where merged. An iSAM2 update costs steeply more with the planes per pose (each
    plane seen from many poses fills the Bayes tree); a budget keeps long runs' updates
    flat but moves single runs' accuracy both ways (docs/experiments.md, "Long runs")."""
    tie_joined_planes: bool = True
    """Tie two plane landmarks the map merged into one (`KeyframeInput.joined_planes`) with a
    `same_plane_factor` (sigmas `landmarks.same_plane_sigma_*`), so that the graph, like the
    map, holds one plane. Without the ties a long run that revisits keeps duplicates apart
    (docs/experiments.md, "Long runs")."""
    window_keyframes: int = 100
    """Sliding window of iSAM2 [keyframes] (>= 0). 0: iSAM2 holds the whole graph. N > 0:
    it holds the last N to 1.5 N keyframes, the landmarks they observe and the factors
    among them, with every other variable held at its estimate (`planeslam.backend.window`),
    so the update costs the same however large the map grows; the final batch optimisation
    still runs over the whole graph. Smaller is faster and drifts more."""
    keys: LandmarkKeys = field(default_factory=LandmarkKeys)
    """Symbol characters of poses, plane and corner landmarks."""
    landmarks: LandmarkConfig = field(
        default_factory=lambda: LandmarkConfig(plane_correlated_depth=0.0)
    )
    """Noise and options of the landmark factors. Unlike an outside stack's, the plane
    factors here keep the fit covariance alone (`plane_correlated_depth` 0): the odometry
    factors beside them come from registering the same planes, so the correlated depth
    error is counted there already."""
    keyframe_min_translation_m: float = 0.05
    """A frame this far [m] from the last keyframe becomes a keyframe."""
    keyframe_min_rotation_deg: float = 5.0
    """A frame rotated this much [deg] from the last keyframe becomes a keyframe."""
    keyframe_max_frames: int = 10
    """A frame this many frames [>= 1] after the last keyframe becomes a keyframe."""
    keyframe_new_planes: int = 4
    """A frame with this many planes the map does not have yet becomes a keyframe."""
    keyframe_skip_revisits: bool = True
    """A frame within the translation and rotation thresholds of an earlier keyframe does
    not become one by motion or frame count (a revisit that sees nothing new)."""
    lag_frames: int = 2
    """A keyframe's result is applied to the map and poses before tracking the frame this
    many frames after it (or the next keyframe, if sooner): the smoother works on it
    while the front end processes those frames. 0: at once (no overlap). More lag is
    faster; accuracy moves either way (docs/experiments.md, "The backend's lag")."""
    separate_process: bool = True
    """Run iSAM2 in a separate (child) process, on another core, beside tracking; false
    runs it inline in the caller's process (the same results on one core). Formerly
    `run_in_process`, still read with a warning."""

    RENAMED_KEYS: ClassVar[Mapping[str, str]] = {"run_in_process": "separate_process"}
    """Old key -> new key, read by `planeslam.core.config.from_mapping`."""

    def __post_init__(self) -> None:
        for name in (
            "odometry_sigma_rot_rad",
            "odometry_sigma_trans_m",
            "loop_sigma_rot_rad",
            "loop_sigma_trans_m",
            "loop_huber_k",
            "prior_sigma_rot_rad",
            "prior_sigma_trans_m",
            "relinearize_threshold",
        ):
            _positive(getattr(self, name), f"backend.{name}")
        for name in ("keyframe_min_translation_m", "keyframe_min_rotation_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"backend.{name}={value!r}: expected a finite number >= 0")
        for name, low in (
            ("relinearize_skip", 1),
            ("extra_updates", 0),
            ("lag_frames", 0),
            ("final_iterations", 0),
            ("keyframe_max_frames", 1),
            ("keyframe_new_planes", 1),
            ("max_planes_per_keyframe", 0),
            ("window_keyframes", 0),
            ("relocalisation_trial_keyframes", 0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"backend.{name}={value!r}: expected a whole number >= {low}")


def _positive(value: float, name: str) -> None:
    if isinstance(value, bool) or not (
        isinstance(value, (int, float)) and math.isfinite(value) and value > 0
    ):
        raise ConfigError(f"{name}={value!r}: expected a finite number > 0")
