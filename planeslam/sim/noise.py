"""Depth and colour error models of the synthetic sensor: what `render_frame`
(`planeslam.sim.render`) turns the exact surface seen by each pixel into, chosen by name
('kinect', 'disparity', 'tof'; `noise_model_of`).

Depth model 'kinect' (`KinectNoise`, defaults for a Kinect v1 / Xtion at 640x480).
Its axial sigma is the one the front end assumes (`sensor` config), so tests on
it are in-distribution:

1. Axial noise, Gaussian with Nguyen, Izadi, Lovell (3DIMPVT 2012) sigma
   sigma(z, theta) = 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2
   [m], z the true depth [m], theta the incidence angle between the viewing
   ray and the surface normal [rad] (the last term matters only near grazing).
2. Disparity quantisation: the Kinect measures disparity D = f * b / z [px]
   in steps of 1/8 px (f = camera.fx, baseline b = 0.075 m), so the noisy depth
   is snapped to z_q = f b / (round(8 f b / z) / 8); the step is z^2 / (8 f b),
   about 1.3 cm at 2 m and 8 cm at 5 m for f = 525.
3. Dropouts (depth 0): incidence beyond 85 deg always, between 75 and 85 deg
   with a probability rising linearly from 0 to 1; at depth discontinuities
   (neighbouring true depths differing by more than 5 % of the nearer one),
   a 1-pixel band around the jump with probability 0.7; and 0.2 % of pixels at
   random. Measured depths outside [0.4, 5.5] m are invalid (0).

Depth model 'disparity' (`DisparityNoise`): a structured-light sensor that
measures disparity, independent of the front end's sigma(z) (after Khoshelham
& Elberink, Sensors 2012; Smisek et al., ICCV-W 2011; the ICL-NUIM noise of
Handa et al., ICRA 2014). Everything happens in disparity D = F b / z [px] of
the sensor's own infrared camera (F = `focal_px`, 580 px, b = `baseline_m`,
0.075 m; not the colour camera's fx):

1. Flying pixels: a pixel within `flying_band_px` (1) of a depth edge (a
   neighbour's true disparity differs by more than `edge_jump_px`, 1 px) takes,
   with probability `flying_prob` (0.5), a mix D = (1 - a) D + a D_other of its
   own and the other side's disparity, a ~ U(0, 1), as a correlation window
   straddling a silhouette does: depths between the two surfaces.
2. Per-pixel noise in disparity, not depth: white Gaussian of `sigma_white_px`
   (0.04 px) plus a spatially correlated Gaussian field of `sigma_correlated_px`
   (0.06 px; white noise blurred with a Gaussian of `correlation_px`, 3 px, and
   rescaled to that sigma), so sigma_z = z^2 sigma_D / (F b) (no constant term;
   about 1.6 mm at 1 m and 6.5 mm at 2 m) and neighbouring pixels err together.
3. Quantisation: D is rounded to steps of `disparity_step_px` (1/8 px) and
   z = F b / D_q, so every measured depth lies on one of the levels
   F b / (k / 8), k an integer; the step is z^2 / (8 F b), about 2.9 mm at 1 m
   and 1.15 cm at 2 m.
4. Dropouts (depth 0): the returned infrared signal s = rho cos(theta) (rho the
   surface's reflectance: the mean of its RGB albedo times its texture, in
   [0, 1]; theta the incidence angle) drops a pixel with probability rising
   linearly from 0 at s = `dropout_signal_high` (0.12) to 1 at
   `dropout_signal_low` (0.04): grazing and dark surfaces lose depth, dark
   texture cells first. Projector shadows (`projector_shadows`): the projector
   sits `baseline_m` along the camera's +x axis; a pixel that the projector
   cannot see (a surface to its right, nearer, covers its projector column:
   column u - fx b / z, fx the rendered camera's) has no depth, which blanks
   a band of about fx b (1/z_near - 1/z_far) px left of each silhouette. And
   `random_dropout_prob` (0.1 %) at random. Depths outside [0.5, 4.5] m are
   invalid (0).

Colour (both models): a procedural texture per plane in the plane's own (u, v)
coordinates (a hash of cells and a checkerboard of 4 cells, the cell size and
albedo from the scene's `Texture`), so it moves rigidly with the scene;
Lambertian shading under a fixed world light from above plus ambient light;
sensor noise of sigma `rgb_sigma` grey levels (2 for 'kinect', 3 for
'disparity'; uniform, which is cheap to draw).

Not modelled: lateral noise, lens distortion, motion blur, rolling shutter,
the Kinect's systematic depth distortion, infrared interference.

All randomness comes from the `numpy.random.Generator` passed in, in a fixed
order, so the same seed gives identical bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeAlias

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.sim.tof import TofNoise

__all__ = [
    "NOISE_MODELS",
    "DisparityNoise",
    "KinectNoise",
    "NoiseModel",
    "SurfaceTruth",
    "TofNoise",
    "noise_model_name",
    "noise_model_of",
]


@dataclass(frozen=True)
class KinectNoise:
    """Constants of the Kinect-v1-like depth and colour error model (module docstring)."""

    baseline_m: float = 0.075
    """Projector-camera baseline b [m]."""
    disparity_step_px: float = 1.0 / 8.0
    """Disparity quantisation step [px]."""
    sigma_const_m: float = 0.0012
    """Constant term of the axial sigma [m]."""
    sigma_quad_m: float = 0.0019
    """Coefficient of (z - 0.4)^2 in the axial sigma [1/m]."""
    sigma_angle_m: float = 0.0001
    """Coefficient of theta^2 / (pi/2 - theta)^2 / sqrt(z) in the axial sigma [m^1.5]."""
    min_range_m: float = 0.4
    """Nearest valid depth [m]."""
    max_range_m: float = 5.5
    """Farthest valid depth [m]."""
    grazing_start_deg: float = 75.0
    """Incidence angle where dropouts start [deg]."""
    grazing_full_deg: float = 85.0
    """Incidence angle beyond which depth is always missing [deg]."""
    edge_jump_ratio: float = 0.05
    """A depth discontinuity: neighbouring depths differ by more than this fraction."""
    edge_dropout_prob: float = 0.7
    """Probability of a dropout in the 1-pixel band around a discontinuity."""
    random_dropout_prob: float = 0.002
    """Probability of an isolated dropout anywhere."""
    rgb_sigma: float = 2.0
    """Colour noise sigma [grey levels]."""

    def depth_sigma(self, z_m: np.ndarray, incidence_rad: np.ndarray | float = 0.0) -> np.ndarray:
        """Axial noise sigma [m] at true depth z_m [m] and incidence angle [rad], any shape."""
        z = np.asarray(z_m, dtype=np.float64)
        theta = np.minimum(np.asarray(incidence_rad, dtype=np.float64), np.deg2rad(89.0))
        angular = self.sigma_angle_m / np.sqrt(np.maximum(z, 1e-3)) * theta**2
        return (
            self.sigma_const_m
            + self.sigma_quad_m * (z - 0.4) ** 2
            + angular / (np.pi / 2 - theta) ** 2
        )

    def quantisation_step(self, z_m: np.ndarray, fx: float) -> np.ndarray:
        """Depth step [m] of one disparity quantum at depth z_m [m]: z^2 step / (f b)."""
        z = np.asarray(z_m, dtype=np.float64)
        return z**2 * self.disparity_step_px / (fx * self.baseline_m)

    def measure_depth(
        self, truth: SurfaceTruth, camera: CameraConfig, rng: np.random.Generator
    ) -> np.ndarray:
        """Measured depth (H, W) float32 [m], 0 = invalid, from the exact surface."""
        hit, depth_true, incidence = truth.hit, truth.depth_m, truth.incidence_rad
        H, W = depth_true.shape
        sigma = self.depth_sigma(np.where(hit, depth_true, 1.0), incidence)
        z = depth_true + sigma * rng.standard_normal((H, W))
        fb = camera.fx * self.baseline_m
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity = np.rint(fb / z / self.disparity_step_px) * self.disparity_step_px
            z = np.where(hit & (disparity > 0), fb / disparity, 0.0)
        valid = hit & (z >= self.min_range_m) & (z <= self.max_range_m)
        # Grazing incidence dropouts.
        lo, hi = np.deg2rad(self.grazing_start_deg), np.deg2rad(self.grazing_full_deg)
        p_graze = np.clip((incidence - lo) / (hi - lo), 0.0, 1.0)
        valid &= rng.random((H, W), dtype=np.float32) >= p_graze
        # Depth-discontinuity dropouts: a 1-pixel band around jumps of the true depth.
        zt = np.where(hit, depth_true, np.inf)
        jump = np.zeros((H, W), dtype=bool)
        with np.errstate(invalid="ignore"):
            jx = np.abs(zt[:, 1:] - zt[:, :-1]) > self.edge_jump_ratio * np.minimum(
                zt[:, 1:], zt[:, :-1]
            )
            jy = np.abs(zt[1:, :] - zt[:-1, :]) > self.edge_jump_ratio * np.minimum(
                zt[1:, :], zt[:-1, :]
            )
        jump[:, 1:] |= jx
        jump[:, :-1] |= jx
        jump[1:, :] |= jy
        jump[:-1, :] |= jy
        valid &= ~(jump & (rng.random((H, W), dtype=np.float32) < self.edge_dropout_prob))
        valid &= rng.random((H, W), dtype=np.float32) >= self.random_dropout_prob
        return np.where(valid, z, 0.0).astype(np.float32)


@dataclass(frozen=True)
class DisparityNoise:
    """Constants of the structured-light disparity model 'disparity' (module docstring)."""

    focal_px: float = 580.0
    """Focal length F of the sensor's infrared camera, where disparity is measured [px]."""
    baseline_m: float = 0.075
    """Projector-camera baseline b [m]; the projector sits at +b along the camera's x axis."""
    disparity_step_px: float = 1.0 / 8.0
    """Disparity quantisation step [px] (sub-pixel refinement of the correlation peak)."""
    sigma_white_px: float = 0.04
    """Sigma of the independent per-pixel disparity noise [px]."""
    sigma_correlated_px: float = 0.06
    """Sigma of the spatially correlated disparity noise [px]."""
    correlation_px: float = 3.0
    """Gaussian blur sigma that correlates that noise across pixels [px]."""
    edge_jump_px: float = 1.0
    """A depth edge: neighbouring true disparities differ by more than this [px]."""
    flying_band_px: int = 1
    """Pixels within this distance of a depth edge may fly (mixed depths) [px]."""
    flying_prob: float = 0.5
    """Probability that a pixel of that band takes a mixed disparity."""
    dropout_signal_low: float = 0.04
    """Signal rho cos(theta) at and below which depth is always missing."""
    dropout_signal_high: float = 0.12
    """Signal at and above which depth is never missing (linear in between)."""
    projector_shadows: bool = True
    """Blank the pixels the projector cannot see (occlusion shadows beside silhouettes)."""
    random_dropout_prob: float = 0.001
    """Probability of an isolated dropout anywhere."""
    min_range_m: float = 0.5
    """Nearest valid depth [m]."""
    max_range_m: float = 4.5
    """Farthest valid depth [m]."""
    rgb_sigma: float = 3.0
    """Colour noise sigma [grey levels]."""

    def __post_init__(self) -> None:
        for name in ("focal_px", "baseline_m", "disparity_step_px", "correlation_px"):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"DisparityNoise.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.dropout_signal_low < self.dropout_signal_high:
            raise ConfigError(
                "DisparityNoise: need 0 <= dropout_signal_low < dropout_signal_high, got "
                f"{self.dropout_signal_low}, {self.dropout_signal_high}"
            )
        if not 0 < self.min_range_m < self.max_range_m:
            raise ConfigError(
                f"DisparityNoise: need 0 < min_range_m < max_range_m, got "
                f"{self.min_range_m}, {self.max_range_m}"
            )

    @property
    def fb_px_m(self) -> float:
        """F b [px m]: disparity D [px] = F b / z [m]."""
        return self.focal_px * self.baseline_m

    def depth_levels(self, z_lo_m: float, z_hi_m: float) -> np.ndarray:
        """The measurable depths [m] in [z_lo_m, z_hi_m], increasing: F b / (k step)."""
        k_lo = int(np.ceil(self.fb_px_m / z_hi_m / self.disparity_step_px))
        k_hi = int(np.floor(self.fb_px_m / z_lo_m / self.disparity_step_px))
        return self.fb_px_m / (np.arange(k_hi, k_lo - 1, -1) * self.disparity_step_px)

    def quantisation_step(self, z_m: np.ndarray) -> np.ndarray:
        """Depth step [m] of one disparity quantum at depth z_m [m]: z^2 step / (F b)."""
        z = np.asarray(z_m, dtype=np.float64)
        return z**2 * self.disparity_step_px / self.fb_px_m

    def depth_sigma(self, z_m: np.ndarray) -> np.ndarray:
        """Sigma [m] of the disparity noise (white and correlated together) at depth z_m
        [m], before quantisation: z^2 sigma_D / (F b)."""
        z = np.asarray(z_m, dtype=np.float64)
        sigma_d = np.hypot(self.sigma_white_px, self.sigma_correlated_px)
        return z**2 * sigma_d / self.fb_px_m

    def dropout_probability(self, reflectance: np.ndarray, incidence_rad: np.ndarray) -> np.ndarray:
        """Probability of a signal dropout for reflectance rho in [0, 1] and incidence
        theta [rad] (same shapes): linear in s = rho cos(theta) between the thresholds."""
        signal = np.asarray(reflectance) * np.cos(np.asarray(incidence_rad))
        span = self.dropout_signal_high - self.dropout_signal_low
        return np.clip((self.dropout_signal_high - signal) / span, 0.0, 1.0)

    def true_disparity(self, depth_true_m: np.ndarray) -> np.ndarray:
        """(H, W) disparity F b / z [px] of exact depths [m]; 0 where depth is 0 (no surface)."""
        hit = depth_true_m > 0
        return np.where(hit, self.fb_px_m / np.where(hit, depth_true_m, 1.0), 0.0)

    def flying_candidates(self, depth_true_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels within `flying_band_px` of a depth edge, and the other side's true
        disparity there: ((H, W) bool, (H, W) float64 [px]). depth_true_m: (H, W) exact
        depth [m], 0 where no surface."""
        hit = depth_true_m > 0
        d_true = self.true_disparity(depth_true_m)
        size = 2 * self.flying_band_px + 1
        kernel = np.ones((size, size), dtype=np.uint8)
        d32 = d_true.astype(np.float32)
        d_max = cv2.dilate(d32, kernel, borderType=cv2.BORDER_REPLICATE).astype(np.float64)
        d_min = cv2.erode(
            np.where(hit, d32, np.float32(np.inf)), kernel, borderType=cv2.BORDER_REPLICATE
        ).astype(np.float64)
        other = np.where(d_max - d_true > d_true - d_min, d_max, d_min)
        near_edge = hit & np.isfinite(other) & (other > 0)
        near_edge &= np.abs(other - d_true) > self.edge_jump_px
        return near_edge, np.where(near_edge, other, d_true)

    def shadowed(self, depth_true_m: np.ndarray, camera: CameraConfig) -> np.ndarray:
        """(H, W) bool: pixels the projector (at +baseline along x) cannot see, from the
        (H, W) exact depth [m] (0: no surface) seen by `camera`. A pixel is in shadow when
        a pixel to its right in the same row maps to the same or a smaller projector
        column u - fx b / z (exact for occluders wider than their shadow)."""
        H, W = depth_true_m.shape
        hit = depth_true_m > 0
        u = np.arange(W, dtype=np.float64)[None, :]
        shift = camera.fx * self.baseline_m / np.where(hit, depth_true_m, 1.0)
        column = np.where(hit, u - shift, np.inf)
        right_min = np.minimum.accumulate(column[:, ::-1], axis=1)[:, ::-1]
        right_min = np.concatenate([right_min[:, 1:], np.full((H, 1), np.inf)], axis=1)
        return hit & (column >= right_min)

    def measure_depth(
        self, truth: SurfaceTruth, camera: CameraConfig, rng: np.random.Generator
    ) -> np.ndarray:
        """Measured depth (H, W) float32 [m], 0 = invalid, from the exact surface."""
        hit = truth.hit
        H, W = truth.depth_m.shape
        white = rng.standard_normal((H, W))
        field_ = rng.standard_normal((H, W))
        mix = rng.random((H, W))
        fly_draw = rng.random((H, W), dtype=np.float32)
        drop_draw = rng.random((H, W), dtype=np.float32)
        random_draw = rng.random((H, W), dtype=np.float32)
        d = self.true_disparity(truth.depth_m)
        near_edge, other = self.flying_candidates(truth.depth_m)
        flying = near_edge & (fly_draw < self.flying_prob)
        d = np.where(flying, d + mix * (other - d), d)
        d += self.sigma_white_px * white
        d += self.sigma_correlated_px * _correlated_field(field_, self.correlation_px)
        d_q = np.rint(d / self.disparity_step_px) * self.disparity_step_px
        z = np.where(hit & (d_q > 0), self.fb_px_m / np.where(d_q > 0, d_q, 1.0), 0.0)
        valid = hit & (d_q > 0) & (z >= self.min_range_m) & (z <= self.max_range_m)
        valid &= drop_draw >= self.dropout_probability(truth.reflectance, truth.incidence_rad)
        if self.projector_shadows:
            valid &= ~self.shadowed(truth.depth_m, camera)
        valid &= random_draw >= self.random_dropout_prob
        return np.where(valid, z, 0.0).astype(np.float32)


NoiseModel: TypeAlias = KinectNoise | DisparityNoise | TofNoise
"""A depth error model: how `render_frame` turns the exact surface into measured depth."""

NOISE_MODELS: dict[str, type[KinectNoise] | type[DisparityNoise] | type[TofNoise]] = {
    "kinect": KinectNoise,
    "disparity": DisparityNoise,
    "tof": TofNoise,
}
"""Noise model name -> its parameter class (default parameters: `noise_model_of(name)`)."""


def noise_model_of(model: str | NoiseModel | None = None) -> NoiseModel:
    """A noise model by name ('kinect', 'disparity', 'tof'), or the instance itself; None
    gives the default 'kinect'. ConfigError listing the names for an unknown one."""
    if model is None:
        return KinectNoise()
    if isinstance(model, (KinectNoise, DisparityNoise, TofNoise)):
        return model
    if model not in NOISE_MODELS:
        raise ConfigError(
            f"unknown depth noise model {model!r}; noise models: {', '.join(NOISE_MODELS)}"
        )
    return NOISE_MODELS[model]()


def noise_model_name(model: NoiseModel) -> str:
    """The registry name of a noise model instance."""
    return next(name for name, cls in NOISE_MODELS.items() if isinstance(model, cls))


def _correlated_field(white: np.ndarray, sigma_px: float) -> np.ndarray:
    """Unit-variance Gaussian field with correlation length sigma_px [px] from (H, W)
    white noise: a Gaussian blur rescaled by the kernel's norm."""
    ksize = 2 * int(np.ceil(3 * sigma_px)) + 1
    k = cv2.getGaussianKernel(ksize, sigma_px, cv2.CV_64F)
    gain = float(np.sum(k**2))  # the 2-D kernel's squared norm is the 1-D one's squared
    blurred = cv2.GaussianBlur(white, (ksize, ksize), sigma_px, borderType=cv2.BORDER_REFLECT)
    return blurred / gain


@dataclass(frozen=True)
class SurfaceTruth:
    """What a pixel sees, exactly: the input of a noise model."""

    hit: np.ndarray
    """(H, W) bool: the ray hits a plane."""
    depth_m: np.ndarray
    """(H, W) float64 exact depth [m]; 0 where no plane is hit."""
    incidence_rad: np.ndarray
    """(H, W) float64 angle between the viewing ray and the plane normal [rad]."""
    reflectance: np.ndarray
    """(H, W) float32 reflectance in [0, 1]: mean RGB albedo times texture, no shading."""
