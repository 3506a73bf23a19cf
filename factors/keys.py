"""Integer keys of poses, plane landmarks and corner landmarks (gtsam.symbol).

The caller picks the symbol characters so that our variables never collide
with those of a larger factor graph (IMU biases, velocities, other landmarks).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam

from planeslam.errors import ConfigError

_MAX_INDEX = 2**56  # gtsam.Symbol keeps the character in the top 8 bits of a 64-bit key


@dataclass(frozen=True)
class LandmarkKeys:
    """Symbol characters of the backend's variables."""

    pose_char: str = "x"
    """Character of camera poses T_world_cam (gtsam.Pose3)."""
    plane_char: str = "p"
    """Character of plane landmarks in the world frame (gtsam.OrientedPlane3)."""
    corner_char: str = "c"
    """Character of trihedral-corner landmarks in the world frame (gtsam.Point3)."""

    def __post_init__(self) -> None:
        chars = (self.pose_char, self.plane_char, self.corner_char)
        for name, char in zip(("pose_char", "plane_char", "corner_char"), chars, strict=True):
            if not isinstance(char, str) or len(char) != 1 or not (32 < ord(char) < 127):
                raise ConfigError(
                    f"LandmarkKeys.{name}={char!r}: expected one printable ASCII character"
                )
        if len(set(chars)) != 3:
            raise ConfigError(
                f"LandmarkKeys characters {chars!r} must be distinct (pose, plane, corner)"
            )

    def pose(self, i: int) -> int:
        """Key of camera pose `i` (frame index)."""
        return gtsam.symbol(self.pose_char, _checked_index(i))

    def plane(self, j: int) -> int:
        """Key of plane landmark `j`."""
        return gtsam.symbol(self.plane_char, _checked_index(j))

    def corner(self, k: int) -> int:
        """Key of corner landmark `k`."""
        return gtsam.symbol(self.corner_char, _checked_index(k))


def _checked_index(index: int) -> int:
    if isinstance(index, bool) or not 0 <= int(index) < _MAX_INDEX or int(index) != index:
        raise ConfigError(f"landmark key index {index!r}: expected an integer in [0, 2**56)")
    return int(index)
