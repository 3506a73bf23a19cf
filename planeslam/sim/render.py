"""Synthetic RGB-D frames and sequences with exact truth (the project's built-in data).

`render_frame` ray-casts a `Scene` (see `planeslam.sim.scenes`) from a pose
and returns depth, colour and the id of the true plane seen by each pixel,
with one of three depth error models, chosen by name (`noise_model=`):
'kinect' (`KinectNoise`, the default), 'disparity' (`DisparityNoise`) and 'tof'
(`TofNoise`, a time-of-flight sensor: `planeslam.sim.tof`).
`synthesize` writes a whole named scene as a TUM-layout folder with
`camera.yaml` and a `truth.json` holding the exact planes, objects, edges,
corners and trajectory (and how it was rendered); `load_truth` reads it back.
`SynthOptions` bundles a noise model, a field of view and `SceneOptions`
(camera height, look-at height, first azimuth, texture) for the CLI and the
benchmark suite.

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

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, TypeAlias

import cv2
import numpy as np

from planeslam.core.bounded_parse import read_json_file
from planeslam.core.camera import CameraConfig
from planeslam.core.config import save_yaml, to_mapping
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.core.geometry import invert_pose, quat_from_pose
from planeslam.io.trajectory import Trajectory, write_tum
from planeslam.sim.scenes import (
    PLAIN_REFLECTANCE,
    SCENES,
    WORLD_UP,
    Box,
    Panel,
    Scene,
    SceneCorner,
    SceneEdge,
    SceneObject,
    SceneOptions,
    ScenePlane,
    Structure,
    Texture,
    get_scene,
    look_at,
    make_scene,
)
from planeslam.sim.tof import TofNoise

__all__ = [
    "NOISE_MODELS",
    "SCENES",
    "TRUTH_SCHEMA",
    "WORLD_UP",
    "Box",
    "DisparityNoise",
    "KinectNoise",
    "NoiseModel",
    "Panel",
    "RenderedFrame",
    "Scene",
    "SceneCorner",
    "SceneEdge",
    "SceneObject",
    "SceneOptions",
    "ScenePlane",
    "Structure",
    "SynthOptions",
    "SynthResult",
    "Texture",
    "TofNoise",
    "camera_with_hfov",
    "get_scene",
    "load_truth",
    "look_at",
    "make_scene",
    "noise_model_name",
    "noise_model_of",
    "plane_in_camera",
    "render_frame",
    "render_sequence",
    "synthesize",
    "truth_dict",
    "write_sequence",
]

logger = logging.getLogger(__name__)

TRUTH_SCHEMA = "planeslam.truth/1"
_NEAR_CLIP_M = 0.05


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
        self, truth: _SurfaceTruth, camera: CameraConfig, rng: np.random.Generator
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
        self, truth: _SurfaceTruth, camera: CameraConfig, rng: np.random.Generator
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
class _SurfaceTruth:
    """What a pixel sees, exactly: the input of a noise model."""

    hit: np.ndarray
    """(H, W) bool: the ray hits a plane."""
    depth_m: np.ndarray
    """(H, W) float64 exact depth [m]; 0 where no plane is hit."""
    incidence_rad: np.ndarray
    """(H, W) float64 angle between the viewing ray and the plane normal [rad]."""
    reflectance: np.ndarray
    """(H, W) float32 reflectance in [0, 1]: mean RGB albedo times texture, no shading."""


@dataclass(frozen=True)
class RenderedFrame:
    """One synthetic RGB-D frame and its exact truth."""

    depth_m: np.ndarray = field(repr=False)
    """(H, W) float32 measured depth along the optical axis [m]; 0 = invalid."""
    rgb: np.ndarray = field(repr=False)
    """(H, W, 3) uint8, RGB order."""
    plane_id: np.ndarray = field(repr=False)
    """(H, W) int32 id of the scene plane the pixel's ray hits first, -1 = none.
    Set even where depth is invalid (range, dropouts): mask with depth_m > 0."""
    depth_true_m: np.ndarray = field(repr=False)
    """(H, W) float64 exact depth of that surface [m]; 0 where no plane is hit."""
    incidence_rad: np.ndarray = field(repr=False)
    """(H, W) float64 angle between the viewing ray and the plane normal [rad]."""
    T_world_cam: np.ndarray = field(repr=False)
    """(4, 4) camera-to-world pose the frame was rendered from."""
    reflectance: np.ndarray = field(repr=False)
    """(H, W) float32 surface reflectance in [0, 1] (mean albedo times texture, unshaded);
    the 'disparity' model's infrared proxy."""


def plane_in_camera(plane: ScenePlane, T_world_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """A scene plane in the camera frame, oriented toward the sensor: (n_cam (3,), d_cam [m])
    with d_cam >= 0, as the segmentation reports observed planes."""
    n_cam = T_world_cam[:3, :3].T @ plane.normal
    d_cam = plane.d + float(plane.normal @ T_world_cam[:3, 3])
    return (n_cam, d_cam) if d_cam >= 0 else (-n_cam, -d_cam)


def _clip_polygon_near(poly_cam: np.ndarray, z_near: float) -> np.ndarray:
    """Clip a convex (K, 3) camera-frame polygon to z >= z_near (Sutherland-Hodgman)."""
    out = []
    k = len(poly_cam)
    for i in range(k):
        a, b = poly_cam[i], poly_cam[(i + 1) % k]
        a_in, b_in = a[2] >= z_near, b[2] >= z_near
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (z_near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def _pixel_window(poly_cam: np.ndarray, camera: CameraConfig) -> tuple[int, int, int, int] | None:
    """Pixel bounding box (u0, u1, v0, v1), end-exclusive, of a camera-frame polygon."""
    clipped = _clip_polygon_near(poly_cam, _NEAR_CLIP_M)
    if len(clipped) < 3:
        return None
    u = camera.fx * clipped[:, 0] / clipped[:, 2] + camera.cx
    v = camera.fy * clipped[:, 1] / clipped[:, 2] + camera.cy
    u0 = max(int(np.floor(u.min())) - 1, 0)
    u1 = min(int(np.ceil(u.max())) + 2, camera.width)
    v0 = max(int(np.floor(v.min())) - 1, 0)
    v1 = min(int(np.ceil(v.max())) + 2, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def _cast(
    scene: Scene, T_world_cam: np.ndarray, camera: CameraConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact ray casting -> depth (H,W) [m] (inf: no hit), plane id (H,W) int32,
    plane coordinates u, v (H,W) [m] and (P,) camera-frame plane offsets |d_c| [m].
    A loop over planes, each vectorised over its pixel window."""
    H, W = camera.height, camera.width
    xs = (np.arange(W) - camera.cx) / camera.fx
    ys = (np.arange(H) - camera.cy) / camera.fy
    depth = np.full((H, W), np.inf)
    pid = np.full((H, W), -1, dtype=np.int32)
    coord_u = np.zeros((H, W))
    coord_v = np.zeros((H, W))
    T_cam_world = invert_pose(T_world_cam)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    eye_world = T_world_cam[:3, 3]
    offsets_cam = np.zeros(len(scene.planes))
    for plane in scene.planes:
        d_c = plane.d + float(plane.normal @ eye_world)
        offsets_cam[plane.id] = abs(d_c)
        if abs(d_c) < 1e-9 or (d_c < 0 and not plane.two_sided):
            continue  # back face, or the camera lies in the plane
        window = _pixel_window(plane.polygon @ R.T + t, camera)
        if window is None:
            continue
        u0, u1, v0, v1 = window
        n_c = R @ plane.normal
        if d_c < 0:
            n_c, d_c = -n_c, -d_c
        c_c = R @ plane.centre + t
        ax_c = plane.axes @ R.T
        wx, wy = xs[u0:u1], ys[v0:v1]
        denom = n_c[0] * wx[None, :] + (n_c[1] * wy[:, None] + n_c[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(denom < -1e-12, -d_c / denom, np.inf)
        s0 = z * (ax_c[0, 0] * wx[None, :] + (ax_c[0, 1] * wy[:, None] + ax_c[0, 2]))
        s0 -= float(c_c @ ax_c[0])
        s1 = z * (ax_c[1, 0] * wx[None, :] + (ax_c[1, 1] * wy[:, None] + ax_c[1, 2]))
        s1 -= float(c_c @ ax_c[1])
        zwin = depth[v0:v1, u0:u1]
        hit = np.abs(s0) <= plane.half_size_m[0]
        hit &= np.abs(s1) <= plane.half_size_m[1]
        hit &= z < zwin
        zwin[hit] = z[hit]
        pid[v0:v1, u0:u1][hit] = plane.id
        coord_u[v0:v1, u0:u1][hit] = s0[hit]
        coord_v[v0:v1, u0:u1][hit] = s1[hit]
    return depth, pid, coord_u, coord_v, offsets_cam


def _shade(
    scene: Scene,
    T_world_cam: np.ndarray,
    pid: np.ndarray,
    coord_u: np.ndarray,
    coord_v: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free colour (H, W, 3) float32 in [0, 255]: per-plane texture in plane
    coordinates times Lambertian shading under a fixed world light; and the
    reflectance (H, W) float32 in [0, 1]: mean albedo times texture, unshaded."""
    P = len(scene.planes)
    albedo = np.stack([p.albedo_rgb for p in scene.planes] + [np.zeros(3)]).astype(np.float32)
    inv_cell = np.array([1.0 / p.texture_cell_m for p in scene.planes] + [1.0])
    salt = np.array([p.texture_salt for p in scene.planes] + [0], dtype=np.int32)
    eye = T_world_cam[:3, 3]
    normals = np.stack([p.normal for p in scene.planes])
    offsets = np.array([p.d for p in scene.planes])
    facing = np.where(normals @ eye + offsets < 0, -1.0, 1.0)  # two-sided panels seen from behind
    lambert = np.maximum(facing * (normals @ scene.light_world), 0.0)
    shade = np.append(scene.ambient + (1.0 - scene.ambient) * lambert, 0.0).astype(np.float32)
    idx = np.where(pid < 0, P, pid)
    inv_c = np.take(inv_cell, idx)
    iu = np.floor(coord_u * inv_c).astype(np.int32)
    iv = np.floor(coord_v * inv_c).astype(np.int32)
    with np.errstate(over="ignore"):
        h = ((iu * np.int32(73856093)) ^ (iv * np.int32(19349663)) ^ np.take(salt, idx)).view(
            np.uint32
        )
        h = h * np.uint32(2654435761)
    noise = ((h >> np.uint32(13)) & np.uint32(255)).astype(np.float32) * np.float32(1.0 / 255.0)
    checker = ((np.right_shift(iu, 2) + np.right_shift(iv, 2)) & 1).astype(np.float32)
    weights = np.array([p.texture_weights for p in scene.planes] + [(0.45, 0.35, 0.2)])
    windows = np.array(
        [p.poster or (-np.inf, np.inf, -np.inf, np.inf) for p in scene.planes]
        + [(-np.inf, np.inf, -np.inf, np.inf)]
    )
    w = np.take(weights.astype(np.float32), idx, axis=0)
    win = np.take(windows, idx, axis=0)
    plain = (coord_u < win[..., 0]) | (coord_u > win[..., 1])
    plain |= (coord_v < win[..., 2]) | (coord_v > win[..., 3])
    if plain.any():
        w[plain] = np.array([PLAIN_REFLECTANCE, 0.0, 0.0], dtype=np.float32)
    tex = w[..., 0] + w[..., 1] * noise + w[..., 2] * checker
    reflectance = tex * np.take(albedo.mean(axis=1), idx)
    tex *= np.take(shade * np.float32(255.0), idx)
    return np.take(albedo, idx, axis=0) * tex[..., None], reflectance


def render_frame(
    scene: Scene,
    T_world_cam: np.ndarray,
    camera: CameraConfig,
    rng: np.random.Generator,
    noise: bool = True,
    noise_model: str | NoiseModel | None = None,
) -> RenderedFrame:
    """Render one RGB-D frame of `scene` from the (4, 4) pose T_world_cam.

    Camera frame x right, y down, z forward; pixel (u, v) looks along
    ((u - cx) / fx, (v - cy) / fy, 1) (lens distortion is not simulated).
    `noise_model`: 'kinect' (default), 'disparity', or a `KinectNoise` /
    `DisparityNoise` with its own constants (module docstring). With
    `noise=False` depth is exact (float32) except outside the model's range,
    and colour has no sensor noise; with `noise=True` the model applies,
    drawing from `rng` only.
    """
    model = noise_model_of(noise_model)
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    if T_world_cam.shape != (4, 4) or not np.all(np.isfinite(T_world_cam)):
        raise ConfigError(
            f"render_frame: T_world_cam must be a finite 4x4 pose, got shape {T_world_cam.shape}"
        )
    depth, pid, cu, cv, offsets_cam = _cast(scene, T_world_cam, camera)
    hit = pid >= 0
    depth_true = np.where(hit, depth, 0.0)
    # Incidence from n . (z r) = -d: cos(theta) = |d_c| / (z |r|).
    xs = (np.arange(camera.width) - camera.cx) / camera.fx
    ys = (np.arange(camera.height) - camera.cy) / camera.fy
    ray_norm = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    d_pix = np.take(np.append(offsets_cam, 0.0), np.where(hit, pid, len(scene.planes)))
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_inc = np.where(hit, d_pix / (depth_true * ray_norm), 1.0)
    incidence = np.arccos(np.clip(cos_inc, 0.0, 1.0))
    colour, reflectance = _shade(scene, T_world_cam, pid, cu, cv)

    if not noise:
        depth_m = depth_true.astype(np.float32)
        in_range = (depth_true >= model.min_range_m) & (depth_true <= model.max_range_m)
        depth_m[~in_range] = 0.0
    else:
        truth = _SurfaceTruth(hit, depth_true, incidence, reflectance)
        depth_m = model.measure_depth(truth, camera, rng)
        # Colour noise: uniform with standard deviation rgb_sigma (one cheap draw).
        scale = np.float32(model.rgb_sigma * np.sqrt(12.0))
        colour += scale * (rng.random(colour.shape, dtype=np.float32) - np.float32(0.5))
    rgb = np.rint(colour).clip(0, 255).astype(np.uint8)
    return RenderedFrame(
        depth_m=depth_m,
        rgb=rgb,
        plane_id=pid,
        depth_true_m=depth_true,
        incidence_rad=incidence,
        T_world_cam=T_world_cam.copy(),
        reflectance=reflectance,
    )


# --------------------------------------------------------------------------- sequences


@dataclass(frozen=True)
class SynthResult:
    """What `synthesize` wrote."""

    out_dir: Path
    """The sequence folder (TUM layout)."""
    num_frames: int
    """Number of RGB-D frames written."""
    scene_name: str
    """Name of the scene (a key of SCENES)."""
    truth_path: Path
    """truth.json."""
    groundtruth_path: Path
    """groundtruth.txt (TUM trajectory)."""
    camera_path: Path
    """camera.yaml (the CameraConfig keys)."""
    rgb_paths: tuple[Path, ...] = field(repr=False)
    """rgb/<timestamp>.png, one per frame."""
    depth_paths: tuple[Path, ...] = field(repr=False)
    """depth/<timestamp>.png (16-bit, value / depth_scale = metres), one per frame."""


def _vec(a: np.ndarray) -> list[float]:
    return [float(x) + 0.0 for x in np.asarray(a, dtype=np.float64).ravel()]  # no -0.0


def _dump_truth(truth: dict[str, Any], path: Path) -> None:
    """JSON with one line per plane, object, edge, corner and pose (readable, diffable)."""
    lines = ["{"]
    items = list(truth.items())
    for k, (key, value) in enumerate(items):
        comma = "," if k < len(items) - 1 else ""
        if isinstance(value, list) and value and isinstance(value[0], (dict, list)):
            rows = ",\n".join(f"  {json.dumps(v)}" for v in value)
            lines.append(f" {json.dumps(key)}: [\n{rows}\n ]{comma}")
        else:
            lines.append(f" {json.dumps(key)}: {json.dumps(value)}{comma}")
    lines.append("}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def truth_dict(
    scene: Scene,
    trajectory: Trajectory,
    camera: CameraConfig,
    seed: int,
    rendering: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The truth.json content (schema TRUTH_SCHEMA); world frame, metres, seconds.
    `rendering` (how the frames were rendered: noise model and its constants, scene
    options) is stored under 'rendering' when given."""
    t, q = quat_from_pose(trajectory.T_world_cam)
    rows = np.concatenate([trajectory.timestamps[:, None], t, q], axis=1)
    extra = {} if rendering is None else {"rendering": rendering}
    return {
        "schema": TRUTH_SCHEMA,
        "scene": scene.name,
        "seed": int(seed),
        "world_up": _vec(WORLD_UP),
        "camera": to_mapping(camera),
        **extra,
        "planes": [
            {
                "id": p.id,
                "name": p.name,
                "object": p.object_id,
                "normal": _vec(p.normal),
                "d": float(p.d),
                "two_sided": p.two_sided,
                "polygon": (np.asarray(p.polygon).round(12) + 0.0).tolist(),
            }
            for p in scene.planes
        ],
        "objects": [
            {
                "id": o.id,
                "name": o.name,
                "class": o.object_class,
                "planes": list(o.plane_ids),
                "size_m": [float(s) for s in o.size_m],
            }
            for o in scene.objects
        ],
        "edges": [
            {
                "planes": list(e.plane_ids),
                "length_m": e.length_m,
                "segment": (e.segment.round(12) + 0.0).tolist(),
            }
            for e in scene.edges
        ],
        "corners": [{"planes": list(c.plane_ids), "point": _vec(c.point)} for c in scene.corners],
        "trajectory": rows.tolist(),
    }


def load_truth(path: str | Path) -> dict[str, Any]:
    """Read a truth.json (file or sequence folder); DatasetFormatError unless its
    schema is TRUTH_SCHEMA."""
    path = Path(path)
    if path.is_dir():
        path = path / "truth.json"
    data = read_json_file(path, DatasetFormatError, what="truth file")
    schema = data.get("schema") if isinstance(data, dict) else None
    if schema != TRUTH_SCHEMA:
        raise DatasetFormatError(f"{path}: expected schema {TRUTH_SCHEMA!r}, got {schema!r}")
    missing = [k for k in ("planes", "objects", "edges", "corners", "trajectory") if k not in data]
    if missing:
        raise DatasetFormatError(f"{path}: truth is missing key(s) {', '.join(missing)}")
    return data


def camera_with_hfov(hfov_deg: float, camera: CameraConfig | None = None) -> CameraConfig:
    """`camera` (default `CameraConfig()`) with square pixels and the principal point at the
    image centre, its focal length set for a horizontal field of view of hfov_deg [deg]:
    fx = fy = (width / 2) / tan(hfov / 2). ConfigError outside (0, 180) deg."""
    base = camera or CameraConfig()
    if not 0.0 < float(hfov_deg) < 180.0:
        raise ConfigError(f"horizontal field of view must be in (0, 180) deg, got {hfov_deg}")
    f = (base.width / 2.0) / float(np.tan(np.deg2rad(hfov_deg) / 2.0))
    return replace(base, fx=f, fy=f, cx=(base.width - 1) / 2.0, cy=(base.height - 1) / 2.0)


@dataclass(frozen=True)
class SynthOptions:
    """How to render a named scene beyond its defaults (`planeslam synth` flags, the
    benchmark suite's `synth:` of a scene); the defaults render the scene as it is."""

    noise_model: Literal["kinect", "disparity", "tof"] = "kinect"
    """Depth error model (module docstring), with its default constants."""
    hfov_deg: float | None = None
    """Horizontal field of view [deg] of the 640 x 480 camera (`camera_with_hfov`);
    None: `CameraConfig()` (fx 525 px, 62.7 deg)."""
    scene: SceneOptions = field(default_factory=SceneOptions)
    """Camera height, look-at height, first azimuth and texture of the scene."""
    label: str = ""
    """Short name of this rendering (suite rows, folders); default: built from the options."""

    def __post_init__(self) -> None:
        noise_model_of(self.noise_model)  # a clear error for an unknown name
        if self.hfov_deg is not None:
            camera_with_hfov(self.hfov_deg)
        if self.label and not self.label.replace("_", "").replace("-", "").isalnum():
            raise ConfigError(f"synth label {self.label!r}: use letters, digits, '-' and '_' only")

    def camera(self, base: CameraConfig | None = None) -> CameraConfig:
        """The camera to render with: `base` (default `CameraConfig()`), its field of view
        set when `hfov_deg` is."""
        base = base or CameraConfig()
        return base if self.hfov_deg is None else camera_with_hfov(self.hfov_deg, base)

    @property
    def tag(self) -> str:
        """'' for the defaults, else `label` or a name built from what differs
        ('disparity-fov57-h0.65-az0-tex7')."""
        if self.label:
            return self.label
        o = self.scene
        parts: list[str] = []
        if self.noise_model != "kinect":
            parts.append(self.noise_model)
        for prefix, value in (
            ("fov", self.hfov_deg),
            ("h", o.camera_height_m),
            ("look", o.target_height_m),
            ("az", o.start_azimuth_deg),
        ):
            if value is not None:
                parts.append(f"{prefix}{value:g}")
        if o.texture is not None:
            t, d = o.texture, Texture()
            parts.append(f"tex{t.seed}")
            if t.brightness != d.brightness:
                parts.append("b{:g}-{:g}".format(*t.brightness))
            if t.cell_m != d.cell_m:
                parts.append("c{:g}-{:g}".format(*t.cell_m))
        return "-".join(parts)


def render_sequence(
    scene_name: str,
    out_dir: str | Path,
    options: SynthOptions,
    frames: int | None = None,
    seed: int = 0,
) -> SynthResult:
    """`synthesize` with the camera, noise model and scene options of `options`."""
    return synthesize(
        scene_name,
        out_dir,
        frames=frames,
        seed=seed,
        camera=options.camera(),
        noise_model=options.noise_model,
        scene_options=options.scene,
    )


def synthesize(
    scene_name: str,
    out_dir: str | Path,
    frames: int | None = None,
    seed: int = 0,
    camera: CameraConfig | None = None,
    noise: bool = True,
    noise_model: str | NoiseModel | None = None,
    scene_options: SceneOptions | None = None,
) -> SynthResult:
    """Render the named scene into `out_dir` as a TUM-layout sequence with truth.

    Writes rgb/*.png, depth/*.png (16-bit, camera.depth_scale per metre, 0
    invalid), rgb.txt, depth.txt, associations.txt, groundtruth.txt,
    camera.yaml and truth.json (with the noise model, its constants and the
    scene options under 'rendering'). `frames` resamples the scene's path to
    that many poses (None: the scene's default); `seed` drives the trajectory's
    hand-shake and the sensor noise; `noise_model` as in `render_frame`;
    `scene_options` vary the camera path and texture. ConfigError for an unknown
    scene or noise model, an option the scene does not take, or frames < 1.
    """
    if scene_name not in SCENES:
        raise ConfigError(f"unknown scene {scene_name!r}; scenes: {', '.join(SCENES)}")
    model = noise_model_of(noise_model)
    traj_seq, noise_seq = np.random.SeedSequence(seed).spawn(2)
    scene, trajectory = get_scene(
        scene_name, frames, np.random.default_rng(traj_seq), scene_options
    )
    return write_sequence(
        scene,
        trajectory,
        out_dir,
        seed,
        camera=camera,
        noise=noise,
        noise_model=model,
        rng=np.random.default_rng(noise_seq),
        rendering={"scene_options": to_mapping(scene_options or SceneOptions())},
    )


def write_sequence(
    scene: Scene,
    trajectory: Trajectory,
    out_dir: str | Path,
    seed: int,
    camera: CameraConfig | None = None,
    noise: bool = True,
    noise_model: str | NoiseModel | None = None,
    rng: np.random.Generator | None = None,
    rendering: dict[str, Any] | None = None,
) -> SynthResult:
    """Render `scene` along `trajectory` into `out_dir` as a TUM-layout sequence with
    truth (the files `synthesize` lists). `rng` draws the sensor noise (default: seeded
    with `seed`); `rendering` adds entries to truth.json's 'rendering' (how the sequence
    was made). ConfigError for a distorted camera or a depth range the PNGs cannot hold."""
    model = noise_model_of(noise_model)
    camera = camera or CameraConfig()
    if camera.is_distorted:
        raise ConfigError(
            "synthesize renders an ideal pinhole camera: pass a CameraConfig with distortion=()"
        )
    if model.max_range_m * camera.depth_scale > 65535:
        raise ConfigError(
            f"camera.depth_scale {camera.depth_scale} cannot store {model.max_range_m} m "
            f"in a 16-bit depth PNG (need depth_scale <= {int(65535 / model.max_range_m)})"
        )
    rng = rng if rng is not None else np.random.default_rng(seed)
    scene_name = scene.name
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    rgb_paths: list[Path] = []
    depth_paths: list[Path] = []
    names: list[str] = []
    for stamp, T in zip(trajectory.timestamps, trajectory.T_world_cam, strict=True):
        frame = render_frame(scene, T, camera, rng, noise=noise, noise_model=model)
        name = f"{stamp:.6f}.png"
        raw = np.clip(np.rint(frame.depth_m.astype(np.float64) * camera.depth_scale), 0, 65535)
        rgb_path, depth_path = out / "rgb" / name, out / "depth" / name
        if not cv2.imwrite(str(depth_path), raw.astype(np.uint16)):
            raise DatasetFormatError(f"{depth_path}: could not write the depth image")
        if not cv2.imwrite(str(rgb_path), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)):
            raise DatasetFormatError(f"{rgb_path}: could not write the colour image")
        rgb_paths.append(rgb_path)
        depth_paths.append(depth_path)
        names.append(name)
    stamps = [f"{s:.6f}" for s in trajectory.timestamps]
    header = (
        f"# planeslam synthetic scene {scene_name}, seed {seed}, "
        f"noise model {noise_model_name(model) if noise else 'none'}\n"
    )
    (out / "rgb.txt").write_text(
        header
        + "# timestamp filename\n"
        + "".join(f"{s} rgb/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    (out / "depth.txt").write_text(
        header
        + "# timestamp filename\n"
        + "".join(f"{s} depth/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    (out / "associations.txt").write_text(
        "".join(f"{s} rgb/{n} {s} depth/{n}\n" for s, n in zip(stamps, names, strict=True))
    )
    write_tum(out / "groundtruth.txt", trajectory, header=f"planeslam synthetic {scene_name}")
    save_yaml(camera, out / "camera.yaml")
    truth_path = out / "truth.json"
    rendering = {
        "noise": noise,
        "noise_model": noise_model_name(model),
        "noise_constants": to_mapping(model),
        **(rendering or {}),
    }
    _dump_truth(truth_dict(scene, trajectory, camera, seed, rendering), truth_path)
    logger.info("wrote %d frames of %s to %s", len(names), scene_name, out)
    return SynthResult(
        out_dir=out,
        num_frames=len(names),
        scene_name=scene_name,
        truth_path=truth_path,
        groundtruth_path=out / "groundtruth.txt",
        camera_path=out / "camera.yaml",
        rgb_paths=tuple(rgb_paths),
        depth_paths=tuple(depth_paths),
    )
