"""Pinhole camera model with depth-sensor conventions (scale, invalid values, distortion)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import overload

import numpy as np

from planeslam.core.errors import ConfigError

MAX_IMAGE_SIDE = 8192
"""Largest image width or height accepted [pixels], checked before anything is allocated
(from camera.yaml, a bag's camera_info, an image file's header)."""


def check_image_size(width: int, height: int, where: str, error: type[Exception]) -> None:
    """`error` naming `where` unless 0 < width, height <= MAX_IMAGE_SIDE."""
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        raise error(
            f"{where}: image size {width}x{height} outside 1..{MAX_IMAGE_SIDE} pixels a side"
        )


@dataclass(frozen=True)
class CameraConfig:
    """Intrinsics and depth encoding of an RGB-D camera (depth registered to colour)."""

    fx: float = 525.0
    """Focal length along x [pixels]."""
    fy: float = 525.0
    """Focal length along y [pixels]."""
    cx: float = 319.5
    """Principal point x [pixels]."""
    cy: float = 239.5
    """Principal point y [pixels]."""
    width: int = 640
    """Image width [pixels]."""
    height: int = 480
    """Image height [pixels]."""
    depth_scale: float = 5000.0
    """Depth PNG value per metre [1/m] (> 0; TUM 5000, RealSense and 7-Scenes 1000)."""
    invalid_depth: tuple[int, ...] = (0,)
    """Raw depth values meaning 'no measurement' (0 always; 65535 for 7-Scenes)."""
    distortion: tuple[float, ...] = ()
    """OpenCV radial-tangential coefficients k1 k2 p1 p2 k3; empty for none."""

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "depth_scale"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"camera.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("fx", "fy", "cx", "cy", "depth_scale"):
            if not np.isfinite(float(getattr(self, name))):
                raise ConfigError(
                    f"camera.{name} must be a finite number, got {getattr(self, name)!r}"
                )
        check_image_size(self.width, self.height, "camera", ConfigError)
        if len(self.distortion) not in (0, 4, 5, 8):
            raise ConfigError(
                f"camera.distortion needs 0, 4, 5 or 8 coefficients, got {len(self.distortion)}"
            )
        object.__setattr__(self, "invalid_depth", tuple(int(v) for v in self.invalid_depth))
        object.__setattr__(self, "distortion", tuple(float(v) for v in self.distortion))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_distorted(self) -> bool:
        return any(abs(c) > 0 for c in self.distortion)

    def with_overrides(self, text: str) -> CameraConfig:
        """Apply a command-line override 'fx,fy,cx,cy[,depth_scale]'."""
        return replace(self, **camera_override_values(text))  # type: ignore[arg-type]


def nearest_pixels(
    camera: CameraConfig, points: np.ndarray, min_depth_m: float = 0.1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, inside) of camera-frame points (..., 3) [m]: the nearest pixel's column and
    row (int64, 0 where not inside, so they index an image safely) and whether the point is
    at least `min_depth_m` in front of the camera and projects into the image."""
    z = points[..., 2]
    front = z > min_depth_m
    z_safe = np.where(front, z, 1.0)
    u = np.rint(camera.fx * points[..., 0] / z_safe + camera.cx).astype(np.int64)
    v = np.rint(camera.fy * points[..., 1] / z_safe + camera.cy).astype(np.int64)
    inside = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return np.where(inside, u, 0), np.where(inside, v, 0), inside


def camera_override_values(text: str) -> dict[str, float]:
    """'fx,fy,cx,cy[,depth_scale]' -> {'fx': .., 'fy': .., 'cx': .., 'cy': ..[, 'depth_scale']}."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (4, 5):
        raise ConfigError(
            f"camera override: expected 'fx,fy,cx,cy[,depth_scale]' (4 or 5 numbers), got {text!r}"
        )
    return dict(zip(("fx", "fy", "cx", "cy", "depth_scale"), values, strict=False))


@dataclass(frozen=True)
class PixelRays:
    """Per-pixel viewing rays for one camera, precomputed once.

    `rays[v, u]` is the camera-frame point at depth 1 m seen by pixel (u, v),
    so the organised cloud is `depth_m[..., None] * rays` (x right, y down, z forward).
    """

    rays: np.ndarray = field(repr=False)
    """(H, W, 3) float64 rays with z = 1."""

    @classmethod
    def for_camera(cls, camera: CameraConfig) -> PixelRays:
        u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
        rays = np.stack(
            [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1
        )
        return cls(rays=rays.astype(np.float64))


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Depth noise of the sensor (Kinect-like): sigma(z) = a + b z^2 [m] at depth z [m].

    Every depth-dependent distance threshold of the front end (segmentation inliers,
    edge extents) is a multiple of sigma at the depth where it is applied.
    """

    sigma_a_m: float = 0.0012
    """Constant term a of sigma(z) = a + b z^2 [m] (> 0; `planeslam calibrate` fits it)."""
    sigma_b_per_m: float = 0.0019
    """Quadratic coefficient b of sigma(z) = a + b z^2 [1/m] (>= 0)."""
    inverse_depth_step_per_m: float = 0.00285
    """Step of the sensor's quantised 1/z [1/m] (>= 0; Kinect v1: 1/8 px of disparity at
    580 px x 7.5 cm); far planes whose fit the rounding could bias are refit for it
    (`core.quantised_fit`). 0: not quantised."""

    def __post_init__(self) -> None:
        if not float(self.sigma_a_m) > 0:
            raise ConfigError(f"sensor.sigma_a_m must be > 0, got {self.sigma_a_m!r}")
        if not float(self.sigma_b_per_m) >= 0:
            raise ConfigError(f"sensor.sigma_b_per_m must be >= 0, got {self.sigma_b_per_m!r}")
        if not float(self.inverse_depth_step_per_m) >= 0:
            raise ConfigError(
                "sensor.inverse_depth_step_per_m must be >= 0 (0: depth not quantised), "
                f"got {self.inverse_depth_step_per_m!r}"
            )

    @overload
    def sigma_m(self, z_m: float) -> float: ...
    @overload
    def sigma_m(self, z_m: np.ndarray) -> np.ndarray: ...
    def sigma_m(self, z_m: np.ndarray | float) -> np.ndarray | float:
        """sigma(z) = a + b z^2 [m] at depth z_m [m] (a number or an array of any shape)."""
        return self.sigma_a_m + self.sigma_b_per_m * z_m * z_m
