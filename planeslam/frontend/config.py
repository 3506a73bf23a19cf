"""Configs of the front-end stages (paper Sections 3-4.3), a leaf module: no algorithms."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.errors import ConfigError


@dataclass(frozen=True)
class OrganizedConfig:
    """Parameters of the organised (cell-grid) segmenter (`planeslam.frontend.organized`)."""

    cell_size_px: int = 16
    """Side of the square image cells fit as small planes [pixels]."""
    min_cell_valid_fraction: float = 0.5
    """A cell needs at least this fraction of valid pixels to be fit."""
    cell_max_rms_sigmas: float = 2.5
    """A cell is planar when its fit RMS residual is below this many sigma(z)."""
    merge_max_rms_sigmas: float = 3.0
    """A cell joins a plane when the RMS distance of its points to that plane is below
    this many sigma(z) (also the test for merging coplanar regions)."""
    merge_max_angle_deg: float = 20.0
    """Largest angle between the normals of a cell and its plane [deg]; widened to 3
    standard deviations of the cell normal's noise for far cells (at most 45 deg)."""
    merge_coplanar: bool = True
    """Merge regions of the same plane even when they do not touch in the image."""
    coplanar_max_angle_deg: float = 5.0
    """Largest angle between two regions merged as one plane [deg]."""
    pixel_stride: int = 2
    """Fit and label every n-th pixel of every n-th row (>= 1; 1 = all; 2, the default, = a
    quarter of the pixels: faster, with planes, edges, corners and box sizes within the
    same tolerances on the test scenes). Cells keep
    `cell_size_px` in full-image pixels; `min_plane_points` stays in full-image pixels;
    `Plane.points` / `num_points` are the fitted (strided) inliers;
    `Segmentation.labels` stays full size (each label covers its n x n block)."""

    def __post_init__(self) -> None:
        for name in (
            "cell_size_px",
            "cell_max_rms_sigmas",
            "merge_max_rms_sigmas",
            "merge_max_angle_deg",
            "coplanar_max_angle_deg",
        ):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(
                    f"segmentation.organized.{name} must be > 0, got {getattr(self, name)!r}"
                )
        if self.pixel_stride not in (1, 2, 3, 4):
            raise ConfigError(
                "segmentation.organized.pixel_stride must be 1, 2, 3 or 4, "
                f"got {self.pixel_stride!r}"
            )
        if self.cell_size_px % self.pixel_stride or self.cell_size_px // self.pixel_stride < 3:
            raise ConfigError(
                f"segmentation.organized.cell_size_px={self.cell_size_px} must be a multiple "
                f"of pixel_stride={self.pixel_stride} and at least 3 strided pixels"
            )
        if not 0 < self.min_cell_valid_fraction <= 1:
            raise ConfigError(
                "segmentation.organized.min_cell_valid_fraction must be in (0, 1], "
                f"got {self.min_cell_valid_fraction}"
            )


@dataclass(frozen=True)
class MsacConfig:
    """Parameters of the paper's MSAC segmenter (`planeslam.frontend.msac`)."""

    max_planes: int = 40
    """Most planes extracted per frame."""
    sample_points: int = 20000
    """Random subsample of valid pixels the planes are searched in."""
    hypotheses: int = 256
    """Plane hypotheses (point triplets) scored per extracted plane."""
    score_points: int = 3000
    """Points of the subsample the hypotheses are scored on (truncated quadratic)."""
    local_radius_px: int = 40
    """The 2nd and 3rd point of a triplet lie within this image radius of the 1st
    [pixels] (local sampling: far more all-inlier triplets than uniform sampling)."""

    def __post_init__(self) -> None:
        for name in (
            "max_planes",
            "sample_points",
            "hypotheses",
            "score_points",
            "local_radius_px",
        ):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(
                    f"segmentation.msac.{name} must be > 0, got {getattr(self, name)!r}"
                )


@dataclass(frozen=True)
class SegmentationConfig:
    """Parameters of plane segmentation: the method, what both methods share, and each
    method's own section. The depth noise sigma(z) is the `sensor` section
    (`planeslam.core.camera.DepthNoiseConfig`)."""

    method: Literal["organized", "msac"] = "organized"
    """'organized' (fast, image-grid based, default) or 'msac' (the paper's)."""
    min_plane_points: int = 1500
    """Smallest plane kept [inlier pixels]."""
    max_depth_m: float = 6.0
    """Points farther than this are ignored [m] (> 0)."""
    max_incidence_deg: float = 78.0
    """Cells and planes seen more obliquely than this (angle between the viewing ray
    and the normal) are rejected [deg]: depth edges leave 'veils' of mixed pixels
    along the rays that look like planes nearly through the camera centre."""
    pixel_max_distance_sigmas: float = 3.0
    """Largest distance of an inlier pixel from its plane, in sigma(z)."""
    outline_epsilon_px: float = 3.0
    """Tolerance of the outline polygon simplification (cv2.approxPolyDP) [pixels]."""
    organized: OrganizedConfig = field(default_factory=OrganizedConfig)
    """The organised (cell-grid) method's own parameters."""
    msac: MsacConfig = field(default_factory=MsacConfig)
    """The MSAC method's own parameters."""

    def __post_init__(self) -> None:
        if self.method not in ("organized", "msac"):
            raise ConfigError(
                f"segmentation.method must be 'organized' or 'msac', got {self.method!r}"
            )
        for name in (
            "min_plane_points",
            "max_depth_m",
            "max_incidence_deg",
            "pixel_max_distance_sigmas",
            "outline_epsilon_px",
        ):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"segmentation.{name} must be > 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class IntersectionConfig:
    """Parameters of real-intersection (edge) detection."""

    d_thresh_m: float = 0.02
    """Points closer than this to both planes are edge points (paper d_thresh) [m]."""
    d_min_m: float = 0.0
    """The paper's d_min, read literally: edge points must also be at least this far
    from the other plane [m]. The paper gives no value; a literal lower bound drops
    the points closest to the line, so the default 0 disables it and noise is handled
    by `min_edge_points` and the trimmed extent instead."""
    min_edge_points: int = 20
    """Fewest edge points each of the two planes must contribute (counted at full
    resolution: a strided plane's points count `stride` times); fewer means the
    planes have no real intersection (noise-level coincidence)."""
    min_length_m: float = 0.03
    """Shortest edge kept [m]."""
    min_angle_deg: float = 20.0
    """Pairs whose normals are closer than this to parallel are never intersected [deg]."""
    adjacency_px: int = 8
    """Planes whose labelled pixels come within this many pixels of each other in
    the image are candidate pairs [px]; covers unlabelled seams left by segmentation."""
    min_contact_px: int = 3
    """Fewest touching pixel pairs (on the `label_stride` grid) for a candidate pair."""
    label_stride: int = 4
    """Subsampling of the label image for the adjacency pass [px]."""
    extent_trim_points: int = 3
    """Edge points dropped at each end of each side's extent (stray inliers)."""
    max_points_per_plane: int = 8000
    """Planes with more inliers are strided down to at most this many for speed; 0 keeps
    all. Edge lengths stay within a few mm of the full-resolution ones (tests)."""
    extent_min_sigmas: float = 3.0
    """Extent of a side: ignore its edge points closer than this many depth-noise sigma(z)
    (the `sensor` section) to the other plane when enough farther ones remain (a quarter
    of them and `min_edge_points`; 0 disables); points where that distance exceeds
    d_thresh / 2 (far, noisy) always count. Those points fit both planes: where a face's
    plane meets its neighbour beyond the face's end (a box side's plane running on along
    the floor), a segmenter gives some of the neighbour's pixels to the face, and they
    would stretch the edge past the face."""

    def __post_init__(self) -> None:
        for name in ("d_thresh_m",):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"intersections.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 <= self.d_min_m < self.d_thresh_m:
            raise ConfigError(
                f"intersections.d_min_m must be in [0, d_thresh_m={self.d_thresh_m}), "
                f"got {self.d_min_m!r}"
            )
        if not 0 < self.min_angle_deg < 90:
            raise ConfigError(
                f"intersections.min_angle_deg must be in (0, 90), got {self.min_angle_deg!r}"
            )
        for name in ("min_edge_points", "adjacency_px", "min_contact_px", "label_stride"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"intersections.{name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("extent_min_sigmas",):
            if not float(getattr(self, name)) >= 0:
                raise ConfigError(f"intersections.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("extent_trim_points", "max_points_per_plane"):
            if int(getattr(self, name)) < 0:
                raise ConfigError(f"intersections.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.min_length_m < 0:
            raise ConfigError(f"intersections.min_length_m must be >= 0, got {self.min_length_m!r}")


@dataclass(frozen=True)
class ObjectConfig:
    """Parameters of the plane graph, corners, objects and classification."""

    gravity_up_cam: tuple[float, ...] = ()
    """Up direction (opposite to gravity) in the camera frame when known; empty: estimate it."""
    gravity_max_tilt_deg: float = 45.0
    """Estimating gravity: a plane whose normal is within this of the camera's -y (or +y)
    axis can be the floor/table (or ceiling) that defines up; the largest such plane
    wins [deg]. 45, not 30: the paper's robot camera looks about 33 deg down."""
    orientation_tol_deg: float = 15.0
    """A plane is horizontal (vertical) when its normal is within this of up
    (of perpendicular to up), else slanted [deg]."""
    corner_min_det: float = 0.2
    """Three planes whose unit normals span a volume |det| below this give no corner."""
    corner_tol_m: float = 0.08
    """A corner point must lie within this of each of its three edges' segments [m];
    edge ends within this of a corner are moved onto it. Not less than about 2x the
    segmenter's pixel tolerance at the corner's depth (3 sigma(2 m) = 2.6 cm): near
    a concave corner the three planes share the pixels within that distance of two
    of them, so each edge stops that much short of the corner."""
    axis_tol_deg: float = 20.0
    """Sizes: edges within this of one direction measure the same dimension, and a new
    dimension must be within this of orthogonal to the others [deg]."""

    def __post_init__(self) -> None:
        if len(self.gravity_up_cam) not in (0, 3):
            raise ConfigError(
                f"objects.gravity_up_cam must be empty or 3 numbers, got {self.gravity_up_cam!r}"
            )
        if len(self.gravity_up_cam) == 3 and not np.linalg.norm(self.gravity_up_cam) > 1e-9:
            raise ConfigError(
                f"objects.gravity_up_cam must be non-zero, got {self.gravity_up_cam!r}"
            )
        for name in ("gravity_max_tilt_deg", "orientation_tol_deg", "axis_tol_deg"):
            if not 0 < float(getattr(self, name)) < 90:
                raise ConfigError(
                    f"objects.{name} must be in (0, 90) deg, got {getattr(self, name)!r}"
                )
        if not 0 < self.corner_min_det <= 1:
            raise ConfigError(
                f"objects.corner_min_det must be in (0, 1], got {self.corner_min_det!r}"
            )
        if not self.corner_tol_m > 0:
            raise ConfigError(f"objects.corner_tol_m must be > 0, got {self.corner_tol_m!r}")


class FrontEndSettings(Protocol):
    """What the front end reads of a config (`planeslam.config.PlaneSlamConfig` has it)."""

    @property
    def camera(self) -> CameraConfig: ...
    @property
    def sensor(self) -> DepthNoiseConfig: ...
    @property
    def segmentation(self) -> SegmentationConfig: ...
    @property
    def intersections(self) -> IntersectionConfig: ...
    @property
    def objects(self) -> ObjectConfig: ...


@dataclass(frozen=True)
class FrontEndConfig:
    """The front end's own sections, for a caller without a whole `PlaneSlamConfig`
    (`FrontEnd(camera)` makes one with the defaults; it has what `FrontEndSettings` asks)."""

    camera: CameraConfig
    """Intrinsics and depth encoding."""
    sensor: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise sigma(z) = a + b z^2 (segmentation, intersections, factor noise)."""
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    """Plane segmentation (paper step 2)."""
    intersections: IntersectionConfig = field(default_factory=IntersectionConfig)
    """Real plane intersections (paper eq. 1-6)."""
    objects: ObjectConfig = field(default_factory=ObjectConfig)
    """Plane graph, trihedral angles, objects and classes (paper 4.2-4.3)."""


def front_end_settings(config: FrontEndSettings | CameraConfig) -> FrontEndSettings:
    """A config with the front end's sections: `config` itself, or for a bare
    `CameraConfig` a `FrontEndConfig` with it and the defaults; ConfigError otherwise."""
    if isinstance(config, CameraConfig):
        return FrontEndConfig(config)
    missing = [
        name
        for name in ("camera", "sensor", "segmentation", "intersections", "objects")
        if not hasattr(config, name)
    ]
    if missing:
        raise ConfigError(
            f"front end config is a {type(config).__name__} without {', '.join(missing)}: "
            "expected a PlaneSlamConfig (load_config), a FrontEndConfig or a CameraConfig"
        )
    return config
