"""Depth model 'tof': a time-of-flight sensor (Kinect v2 / Azure Kinect-like).

Its errors follow other laws than the two structured-light models of
`planeslam.sim.render`, so a tracker tuned on those meets something new:

1. Noise from the returned signal, not from disparity: the amplitude
   s = rho cos(theta) (z_ref / z)^2 (rho the surface reflectance in [0, 1],
   theta the incidence angle, z the true depth [m], z_ref = 1 m) gives an axial
   sigma = `sigma_ref_m` sqrt(`signal_ref` / s): about 2.5 mm on a bright wall
   at 1 m, 7.5 mm at 3 m, several cm on a dark surface far away. No quantisation
   steps (depth is stored at the image's own 1 mm or finer resolution).
2. A systematic 'wiggling' error, a bias of `wiggle_m` sin(2 pi z / `wiggle_period_m`)
   from the modulation's harmonics: the same for every pixel at one depth, so
   tilted planes bend slightly.
3. Mixed pixels: within `mixed_band_px` of a depth edge (neighbouring depths
   differing by more than `edge_jump_m`), with probability `mixed_prob`, the
   measured depth is a mix of the two surfaces' depths (no dropout there).
4. Dropouts: signal below `dropout_signal_low` always, rising linearly to none
   at `dropout_signal_high`: dark and grazing faces lose depth; `random_dropout_prob`
   anywhere. Depths outside [`min_range_m`, `max_range_m`] are invalid (0).

All randomness comes from the generator passed in, in a fixed order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError

if TYPE_CHECKING:
    from planeslam.sim.noise import SurfaceTruth


@dataclass(frozen=True)
class TofNoise:
    """Constants of the time-of-flight depth model 'tof' (module docstring)."""

    sigma_ref_m: float = 0.0025
    """Axial sigma at the reference signal [m]."""
    signal_ref: float = 0.5
    """Reference signal rho cos(theta) (1 m / z)^2 of `sigma_ref_m`."""
    wiggle_m: float = 0.002
    """Amplitude of the systematic depth bias [m]."""
    wiggle_period_m: float = 1.2
    """Period of that bias in depth [m]."""
    edge_jump_m: float = 0.05
    """A depth edge: neighbouring true depths differ by more than this [m]."""
    mixed_band_px: int = 1
    """Pixels within this distance of an edge may mix the two depths [px]."""
    mixed_prob: float = 0.6
    """Probability that a pixel of that band is mixed."""
    dropout_signal_low: float = 0.015
    """Signal at and below which depth is always missing."""
    dropout_signal_high: float = 0.05
    """Signal at and above which depth is never missing (linear in between)."""
    random_dropout_prob: float = 0.001
    """Probability of an isolated dropout anywhere."""
    min_range_m: float = 0.3
    """Nearest valid depth [m]."""
    max_range_m: float = 4.5
    """Farthest valid depth [m]."""
    rgb_sigma: float = 2.0
    """Colour noise sigma [grey levels]."""

    def __post_init__(self) -> None:
        for name in ("sigma_ref_m", "signal_ref", "wiggle_period_m", "edge_jump_m"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"TofNoise.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.dropout_signal_low < self.dropout_signal_high:
            raise ConfigError(
                "TofNoise: need 0 <= dropout_signal_low < dropout_signal_high, got "
                f"{self.dropout_signal_low}, {self.dropout_signal_high}"
            )
        if not 0 < self.min_range_m < self.max_range_m:
            raise ConfigError(
                f"TofNoise: need 0 < min_range_m < max_range_m, got "
                f"{self.min_range_m}, {self.max_range_m}"
            )

    def signal(
        self, reflectance: np.ndarray, incidence_rad: np.ndarray, z_m: np.ndarray
    ) -> np.ndarray:
        """Returned amplitude rho cos(theta) (1 m / z)^2 (same shapes as the inputs)."""
        z = np.maximum(np.asarray(z_m, dtype=np.float64), 1e-3)
        return np.asarray(reflectance) * np.cos(np.asarray(incidence_rad)) / z**2

    def depth_sigma(self, signal: np.ndarray) -> np.ndarray:
        """Axial sigma [m] at a returned signal (any shape)."""
        return self.sigma_ref_m * np.sqrt(self.signal_ref / np.maximum(signal, 1e-6))

    def bias(self, z_m: np.ndarray) -> np.ndarray:
        """Systematic wiggling error [m] at true depth z_m [m]."""
        return self.wiggle_m * np.sin(2.0 * np.pi * np.asarray(z_m) / self.wiggle_period_m)

    def measure_depth(
        self, truth: SurfaceTruth, camera: CameraConfig, rng: np.random.Generator
    ) -> np.ndarray:
        """Measured depth (H, W) float32 [m], 0 = invalid, from the exact surface."""
        hit, z_true = truth.hit, truth.depth_m
        H, W = z_true.shape
        gauss = rng.standard_normal((H, W))
        mix = rng.random((H, W))
        mix_draw = rng.random((H, W), dtype=np.float32)
        drop_draw = rng.random((H, W), dtype=np.float32)
        random_draw = rng.random((H, W), dtype=np.float32)
        z_safe = np.where(hit, z_true, 1.0)
        signal = np.where(hit, self.signal(truth.reflectance, truth.incidence_rad, z_safe), 0.0)
        z = z_true + self.bias(z_safe) + self.depth_sigma(signal) * gauss
        # Mixed pixels: the other side of a nearby edge, nearest or farthest.
        size = 2 * self.mixed_band_px + 1
        kernel = np.ones((size, size), dtype=np.uint8)
        z32 = np.where(hit, z_true, 0.0).astype(np.float32)
        far = cv2.dilate(z32, kernel, borderType=cv2.BORDER_REPLICATE).astype(np.float64)
        near = cv2.erode(
            np.where(hit, z32, np.float32(np.inf)), kernel, borderType=cv2.BORDER_REPLICATE
        ).astype(np.float64)
        other = np.where(far - z_true > z_true - near, far, near)
        edge = hit & np.isfinite(other) & (np.abs(other - z_true) > self.edge_jump_m)
        mixed = edge & (mix_draw < self.mixed_prob)
        z = np.where(mixed, z + mix * (other - z_true), z)
        valid = hit & (z >= self.min_range_m) & (z <= self.max_range_m)
        span = self.dropout_signal_high - self.dropout_signal_low
        p_drop = np.clip((self.dropout_signal_high - signal) / span, 0.0, 1.0)
        valid &= drop_draw >= p_drop
        valid &= random_draw >= self.random_dropout_prob
        return np.where(valid, z, 0.0).astype(np.float32)
