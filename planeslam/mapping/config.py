"""Config of the world map, a leaf module: no algorithms."""

from __future__ import annotations

from dataclasses import dataclass

from planeslam.core.errors import ConfigError


@dataclass(frozen=True)
class MapConfig:
    """Parameters of the world map: merging, objects and the sparse cloud (config section `map`)."""

    voxel_m: float = 0.05
    """Edge of a voxel of the sparse (non-planar) cloud [m]; one averaged point per voxel."""
    sparse_max_points: int = 50_000
    """Most voxels kept in the sparse cloud; beyond it the least-supported voxels are dropped."""
    merge_max_angle_deg: float = 30.0
    """Sanity gate on the given plane pairs: a pair whose normals (in the world frame) differ
    by more than this is not merged and the observed plane becomes a new map plane [deg]."""
    min_observations: int = 1
    """Planes and edges seen in fewer frames are kept but left out of objects."""
    derive_corners: bool = True
    """Re-aggregation also adds the trihedral corners of the merged map graph that no single
    frame saw (three edges observed in different frames), as the paper's re-initialisation."""
    consolidate: bool = True
    """An observed plane that data association left unmatched joins a map plane that is the
    same plane segment (the gates below) instead of becoming a new one: one landmark per
    physical plane segment, and a revisit adds none."""
    consolidate_max_sigmas: float = 3.0
    """Same plane: the map plane, seen from the frame's pose, within this many standard
    deviations of the observed plane's fit (tangent normal and offset) ..."""
    consolidate_pose_sigma_rad: float = 0.005
    """... whose covariance is widened by this rotation uncertainty of the pose [rad] ..."""
    consolidate_pose_sigma_m: float = 0.005
    """... and this translation uncertainty [m]; ..."""
    consolidate_correlated_depth: float = 1.0
    """... and by a depth error correlated across the patch of this many sigma(z) of the
    sensor (`sensor:`), which offsets a patch and tilts it by that over its half-width; ..."""
    consolidate_max_angle_deg: float = 10.0
    """... normals within this at most [deg] ..."""
    consolidate_max_offset_m: float = 0.05
    """... the observed centroid within this of the map plane at most [m] (larger merges
    more revisited planes and costs accuracy on single passes; docs/experiments.md) ..."""
    consolidate_max_gap_m: float = 0.10
    """... and outlines (convex hulls on the map plane) overlapping or at most this far
    apart [m]."""
    cull_single_view_after: int | None = None
    """N > 0: a plane that only the frame which made it has seen leaves the map (with its
    edges and corners) when N more frames have been merged without seeing it again
    (`culling`; ORB-SLAM culls recent map points so); 0 keeps every plane; None: the
    backend's choice (`Backend.map_cull_single_view_after`: 5 keyframes with isam2, 0 with
    merge, whose every frame is merged). A culled plane is remembered, so that a frame that
    sees it again does not count it as new (no keyframe for clutter). With isam2 and
    `merge_segments` it keeps the map at about half the planes on long runs; with the
    merge backend it costs accuracy, hence the backend's choice."""
    merge_segments: bool | None = None
    """After the backend moved a keyframe's planes, a map plane that came to lie on another
    one's segment (outlines as above) is merged into it (`segment_merge`), and the backend
    ties the two landmarks (`backend.tie_joined_planes`); None: the backend's choice
    (`Backend.map_merge_segments`: on with isam2, off with merge)."""
    merge_segments_max_angle_deg: float = 2.0
    """... when their normals are within this [deg] ..."""
    merge_segments_max_offset_m: float = 0.02
    """... and each one's centroid within this of the other plane [m]."""

    def __post_init__(self) -> None:
        if not (isinstance(self.voxel_m, (int, float)) and self.voxel_m > 0):
            raise ConfigError(f"map.voxel_m must be > 0 [m], got {self.voxel_m!r}")
        if isinstance(self.sparse_max_points, bool) or not (
            isinstance(self.sparse_max_points, int) and self.sparse_max_points >= 0
        ):
            raise ConfigError(
                f"map.sparse_max_points must be a whole number >= 0, got {self.sparse_max_points!r}"
            )
        if not 0 < float(self.merge_max_angle_deg) <= 180:
            raise ConfigError(
                f"map.merge_max_angle_deg must be in (0, 180], got {self.merge_max_angle_deg!r}"
            )
        if isinstance(self.min_observations, bool) or not (
            isinstance(self.min_observations, int) and self.min_observations >= 1
        ):
            raise ConfigError(
                f"map.min_observations must be a whole number >= 1, got {self.min_observations!r}"
            )
        cull = self.cull_single_view_after
        if cull is not None and (
            isinstance(cull, bool) or not (isinstance(cull, int) and cull >= 0)
        ):
            raise ConfigError(
                "map.cull_single_view_after must be a whole number >= 0 (frames) or null (the "
                f"backend's choice), got {cull!r}"
            )
        if self.merge_segments is not None and not isinstance(self.merge_segments, bool):
            raise ConfigError(
                "map.merge_segments must be true, false or null (the backend's choice), got "
                f"{self.merge_segments!r}"
            )
        for name in (
            "consolidate_max_sigmas",
            "consolidate_pose_sigma_rad",
            "consolidate_pose_sigma_m",
            "consolidate_max_angle_deg",
            "consolidate_max_offset_m",
            "merge_segments_max_angle_deg",
            "merge_segments_max_offset_m",
        ):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"map.{name} must be > 0, got {getattr(self, name)!r}")
        if not float(self.consolidate_correlated_depth) >= 0:
            raise ConfigError(
                "map.consolidate_correlated_depth must be >= 0 (sigmas of sensor depth), got "
                f"{self.consolidate_correlated_depth!r}"
            )
        if not float(self.consolidate_max_gap_m) >= 0:
            raise ConfigError(
                f"map.consolidate_max_gap_m must be >= 0 [m], got {self.consolidate_max_gap_m!r}"
            )
        if not isinstance(self.derive_corners, bool):
            raise ConfigError(
                f"map.derive_corners must be true or false, got {self.derive_corners!r}"
            )
