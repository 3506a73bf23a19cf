"""Symbol characters and noise options of the landmark factors, a leaf module: no gtsam
at import time (keys are computed as `gtsam.symbol` computes them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from planeslam.core.errors import ConfigError


@dataclass(frozen=True)
class LandmarkConfig:
    """Noise and options of the landmark factors."""

    plane_sigma_floor_rad: float = 1e-4
    """Added in quadrature to both normal components of every plane fit's sigma [rad]
    (> 0). Keep it small: the fit covariance itself (with its normal/offset correlation)
    is the better noise model, and a large isotropic floor drowns that correlation."""
    plane_sigma_floor_m: float = 1e-4
    """Added in quadrature to the offset sigma of every plane fit [m] (> 0)."""
    plane_correlated_depth: float = 1.0
    """Sigmas of the sensor's depth error correlated across a plane added to its fit
    covariance (k^2 times `PlaneMeasurement.correlated_covariance`, from the front end's
    `sensor` model; `core.plane_fit.patch_covariance`); 0: the fit covariance alone. At 1
    the optimised graph's error is near its degrees of freedom on real Kinect depth
    (docs/outside_stack.md)."""
    robust_kernel: Literal["huber", "cauchy"] | None = "huber"
    """null: the built-in OrientedPlane3Factor; 'huber' (default) or 'cauchy': the robust
    CustomFactor (slower to linearise: a Python factor). With the fit covariance as noise,
    a mis-segmented border makes a plane an outlier, which the robust kernel down-weights
    rather than letting it pull the poses."""
    robust_k: float | None = None
    """Robust threshold in whitened units (None: 1.345 Huber, 2.3849 Cauchy)."""
    corner_sigma_m: float = 0.01
    """Isotropic sigma of a corner point observation, camera frame [m]."""
    structure_tolerance_deg: float = 5.0
    """An observed edge whose planes' normals are within this of 90 deg (or 0 / 180 deg)
    gets an orthogonality (parallelism) factor [deg], in (0, 45)."""
    structure_sigma_rad: float = 0.01
    """Sigma of the structural factors [rad]."""
    point_on_plane_sigma_m: float = 0.01
    """Sigma of the distance of a corner landmark to each of its three planes [m]."""
    same_plane_sigma_rad: float = 0.005
    """Sigma of each normal component of the tie joining two landmarks of one plane
    (`PlaneLandmarks.join_planes`) [rad]; robust under `robust_kernel`."""
    same_plane_sigma_m: float = 0.005
    """Sigma of the offset difference of that tie [m]."""
    use_structure: bool = True
    """Add orthogonality / parallelism factors between plane landmarks meeting at edges."""
    use_corners: bool = True
    """Add corner landmarks (corner observation + three point-on-plane factors)."""
    associate_max_angle_deg: float = 5.0
    """`associate` gate: angle between an observed normal (moved to the world by the
    predicted pose) and a landmark normal [deg]."""
    associate_max_offset_m: float = 0.04
    """`associate` gate: offset difference [m]. Keep it below the gap between parallel
    surfaces the scene has (two box tops 5 cm apart). A predicted pose worse than a few
    mm / tenths of a degree needs wider gates: give `associate` its covariance."""
    associate_max_corner_distance_m: float = 0.05
    """`associate` gate: distance of an observed corner to a corner landmark [m]."""
    associate_pose_sigmas: float = 3.0
    """When `associate` is given the predicted pose's covariance, each gate above widens
    by this many of the pose's sigmas propagated to that plane or corner (in quadrature:
    gate = sqrt(gate^2 + (k sigma)^2)); the gates above then cover the measurement and
    landmark errors only."""

    def __post_init__(self) -> None:
        positive = (
            "plane_sigma_floor_rad",
            "plane_sigma_floor_m",
            "corner_sigma_m",
            "structure_sigma_rad",
            "point_on_plane_sigma_m",
            "same_plane_sigma_rad",
            "same_plane_sigma_m",
            "associate_max_angle_deg",
            "associate_max_offset_m",
            "associate_max_corner_distance_m",
            "associate_pose_sigmas",
        )
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not (
                isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            ):
                raise ConfigError(f"landmarks.{name}={value!r}: expected a finite number > 0")
        k = self.plane_correlated_depth
        if isinstance(k, bool) or not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
            raise ConfigError(
                f"landmarks.plane_correlated_depth={k!r}: expected a finite number >= 0"
            )
        if self.robust_kernel not in (None, "huber", "cauchy"):
            raise ConfigError(
                f"landmarks.robust_kernel={self.robust_kernel!r}: "
                "expected null, 'huber' or 'cauchy'"
            )
        if self.robust_k is not None and not (math.isfinite(self.robust_k) and self.robust_k > 0):
            raise ConfigError(f"landmarks.robust_k={self.robust_k!r}: expected a number > 0")
        if not 0.0 < self.structure_tolerance_deg < 45.0:
            raise ConfigError(
                f"landmarks.structure_tolerance_deg={self.structure_tolerance_deg!r}: "
                "expected (0, 45)"
            )


_INDEX_BITS = 56
_MAX_INDEX = 2**_INDEX_BITS  # gtsam.Symbol keeps the character in the top 8 bits of a 64-bit key


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
        return _symbol(self.pose_char, i)

    def plane(self, j: int) -> int:
        """Key of plane landmark `j`."""
        return _symbol(self.plane_char, j)

    def corner(self, k: int) -> int:
        """Key of corner landmark `k`."""
        return _symbol(self.corner_char, k)


def _checked_index(index: int) -> int:
    if isinstance(index, bool) or not 0 <= int(index) < _MAX_INDEX or int(index) != index:
        raise ConfigError(f"landmark key index {index!r}: expected an integer in [0, 2**56)")
    return int(index)


def _symbol(char: str, index: int) -> int:
    """gtsam.symbol(char, index), computed as gtsam's Symbol::key() does, without gtsam."""
    return (ord(char) << _INDEX_BITS) | _checked_index(index)
