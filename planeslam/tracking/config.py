"""Config of frame-to-map tracking, a leaf module: no algorithms."""

from __future__ import annotations

from dataclasses import dataclass

from planeslam.core.errors import ConfigError


@dataclass(frozen=True)
class TrackingConfig:
    """Gates and fallbacks of frame-to-map tracking."""

    max_angle_deg: float = 10.0
    """Association gate on the angle between an observed and a map normal [deg]."""
    max_offset_m: float = 0.10
    """Association gate on the offset difference of two planes [m]."""
    max_corner_distance_m: float = 0.25
    """Association gate on the distance between an observed and a map corner [m]."""
    sigma_angle_deg: float = 1.0
    """Normal noise of an observed plane in the closed-form solve [deg]."""
    sigma_offset_m: float = 0.01
    """Offset noise of an observed plane in the closed-form solve [m]."""
    sigma_point_m: float = 0.02
    """Corner point noise in the closed-form solve [m]."""
    max_residual_angle_deg: float = 3.0
    """A plane pose is trusted when every matched normal agrees within this after solving."""
    max_residual_offset_m: float = 0.05
    """... and every matched offset within this [m]. Correspondences beyond either gate are
    dropped and the pose solved again (see `max_outlier_rounds`)."""
    size_gate_ratio: float = 2.0
    """An observed plane may match a map plane of area A when its own visible area is at
    most size_gate_ratio * A + size_gate_margin_m2 (a floor never matches a box top)."""
    size_gate_margin_m2: float = 0.1
    """See `size_gate_ratio` [m^2]."""
    max_outlier_rounds: int = 3
    """Rounds of dropping correspondences beyond the residual gates and solving again."""
    relocalise: bool = True
    """Try corner and plane-triple hypotheses when the prediction gives no trusted pose."""
    max_triple_planes: int = 10
    """Largest observed planes that form plane-triple hypotheses when relocalising."""
    max_triple_map_planes: int = 24
    """Largest map planes that form plane-triple hypotheses when relocalising."""
    relocalise_max_rotation_deg: float = 90.0
    """Hypotheses rotated more than this from the prediction are ignored [deg] (rooms are
    often symmetric), unless tracking has been lost for `relocalise_anywhere_after` frames."""
    relocalise_max_translation_m: float = 1.5
    """Hypotheses farther than this from the prediction are ignored [m] (same exception)."""
    relocalise_candidates: int = 8
    """Hypotheses refined and compared in full when relocalising."""
    relocalise_anywhere_after: int = 10
    """After this many lost frames in a row, hypotheses anywhere are considered."""
    icp: bool = True
    """Use frame-to-frame ICP where planes leave directions free, and as a fallback."""
    icp_stride: int = 4
    """Take every icp_stride-th pixel in each direction for ICP clouds."""
    icp_voxel_m: float = 0.03
    """Voxel size of the ICP clouds [m]."""
    icp_max_distance_m: float = 0.10
    """ICP correspondence gate [m]."""
    icp_min_fitness: float = 0.5
    """ICP result trusted when at least this fraction of points has a correspondence."""
    icp_max_rmse_m: float = 0.03
    """... and their RMSE is below this [m]."""
    rgbd_odometry: bool = True
    """Fall back to Open3D RGB-D odometry when planes and ICP fail (needs colour)."""
    max_depth_m: float = 4.0
    """Points farther than this are left out of ICP and RGB-D odometry [m]."""

    def __post_init__(self) -> None:
        positive = (
            "max_angle_deg",
            "max_offset_m",
            "max_corner_distance_m",
            "sigma_angle_deg",
            "sigma_offset_m",
            "sigma_point_m",
            "max_residual_angle_deg",
            "max_residual_offset_m",
            "relocalise_max_rotation_deg",
            "size_gate_ratio",
            "relocalise_max_translation_m",
            "icp_voxel_m",
            "icp_max_distance_m",
            "icp_max_rmse_m",
            "max_depth_m",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"tracking.{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_triple_planes", "max_triple_map_planes"):
            if getattr(self, name) < 3:
                raise ConfigError(f"tracking.{name} must be >= 3, got {getattr(self, name)}")
        if self.icp_stride < 1:
            raise ConfigError(f"tracking.icp_stride must be >= 1, got {self.icp_stride}")
        if not 0 <= self.icp_min_fitness <= 1:
            raise ConfigError(
                f"tracking.icp_min_fitness must be in [0, 1], got {self.icp_min_fitness}"
            )
