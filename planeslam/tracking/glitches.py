"""Pose glitches: poses that jump away from the frames around them and back.

At video rate a hand-held or robot camera moves smoothly: over a fifth of a second its
path departs from the straight line (and its orientation from the slerp) between the poses
before and after by millimetres (0.5 a t^2 is 1.5 cm at 3 m/s^2 over 0.1 s). A pose
centimetres off that line while the poses around it agree with each other is a tracking or
association error, not motion. Needs no ground truth. Each pose, each two consecutive
poses together, and two poses one frame apart whose pose between fits the same line (two
glitches that would hide each other) are compared with the interpolations between the
neighbours one and two frames before and after them (the smallest departure counts, so a
glitch of one or two frames shows, and the frames next to it do not); poses without such
neighbours within `max_span_s` (the ends, sub-sampled sequences, gaps of lost frames) are
not judged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from planeslam.io.trajectory import Trajectory

_ENDS = ((1, 1), (1, 2), (2, 1), (2, 2))
"""(frames before, frames after) a run of poses of the neighbours it is interpolated from."""

_PATTERNS = ((True,), (True, True), (True, False, True))
"""Runs of consecutive poses judged together: True a pose that must depart, False one that
must fit the same line (two glitches one frame apart, whose lines would pass near each
other)."""


@dataclass(frozen=True)
class PoseGlitches:
    """The glitched poses of a trajectory and how they were judged."""

    timestamps: np.ndarray
    """(G,) timestamps [s] of the poses that jump."""
    judged: int
    """Poses with neighbours on both sides within `max_span_s`."""
    max_span_s: float
    """Longest time between the neighbours a pose is judged against [s]."""
    min_jump_m: float
    """Departure from their straight line that makes a glitch [m] ..."""
    min_jump_deg: float
    """... or from their slerp [deg]."""

    def __len__(self) -> int:
        return int(len(self.timestamps))

    def to_dict(self) -> dict[str, Any]:
        return {
            "count": len(self),
            "judged": self.judged,
            "timestamps": [round(float(t), 6) for t in self.timestamps],
            "max_span_s": self.max_span_s,
            "min_jump_m": self.min_jump_m,
            "min_jump_deg": self.min_jump_deg,
        }


def find_pose_glitches(
    trajectory: Trajectory,
    max_span_s: float = 0.2,
    min_jump_m: float = 0.05,
    min_jump_deg: float = 3.0,
) -> PoseGlitches:
    """The poses of `trajectory` (timestamps increasing) that, alone, with the next one, or
    with the one after it (the pose between fitting), are farther than `min_jump_m` [m]
    from the straight line or turned more than `min_jump_deg` [deg] from the slerp between
    every pair of neighbours around them (one or two frames before and after, at most
    `max_span_s` [s] apart): module docstring."""
    from scipy.spatial.transform import Rotation  # 0.2 s to import: only when a run ends

    stamps = np.asarray(trajectory.timestamps, dtype=np.float64)
    poses = np.asarray(trajectory.T_world_cam, dtype=np.float64)
    n = len(stamps)
    glitch = np.zeros(n, dtype=bool)
    judged = np.zeros(n, dtype=bool)
    if n:
        rotations = Rotation.from_matrix(poses[:, :3, :3])
        for pattern in _PATTERNS:
            run = len(pattern)
            # off[i]: the run starting at pose i, its least departure (in thresholds) over the
            # neighbour pairs around it; > 1 when every pose of the run that must depart
            # departs from all of them (and the others fit each such line)
            off = np.full(n, np.inf)
            for before, after in _ENDS:
                i = np.arange(before, n - run + 1 - after)
                a, b = i - before, i + run - 1 + after
                span = stamps[b] - stamps[a]
                ok = (span > 0) & (span <= max_span_s)
                i, a, b, span = i[ok], a[ok], b[ok], span[ok]
                if not len(i):
                    continue
                least = np.full(len(i), np.inf)
                turn = (rotations[a].inv() * rotations[b]).as_rotvec()
                p_a, p_b = poses[a, :3, 3], poses[b, :3, 3]
                for k, departs in enumerate(pattern):
                    share = ((stamps[i + k] - stamps[a]) / span)[:, None]  # of the way a -> b
                    slerp = rotations[a] * Rotation.from_rotvec(share * turn)
                    line = (1.0 - share) * p_a + share * p_b
                    offset = np.linalg.norm(poses[i + k, :3, 3] - line, axis=1)
                    angle = np.degrees((slerp.inv() * rotations[i + k]).magnitude())
                    away = np.maximum(offset / min_jump_m, angle / min_jump_deg)
                    least = np.minimum(least, away if departs else np.where(away > 1, 0.0, np.inf))
                off[i] = np.minimum(off[i], least)
                if run == 1:
                    judged[i] = True
            flagged = np.isfinite(off) & (off > 1)
            for k, departs in enumerate(pattern):
                if departs:
                    glitch[k:] |= flagged[: n - k]
    return PoseGlitches(
        timestamps=stamps[glitch],
        judged=int(np.count_nonzero(judged)),
        max_span_s=float(max_span_s),
        min_jump_m=float(min_jump_m),
        min_jump_deg=float(min_jump_deg),
    )


__all__ = ["PoseGlitches", "find_pose_glitches"]
