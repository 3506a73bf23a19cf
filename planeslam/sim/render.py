"""Synthetic RGB-D frames with exact truth: `render_frame` ray-casts a `Scene` (see
`planeslam.sim.scenes`) from a pose and returns depth, colour and the id of the true plane
seen by each pixel, with one of three depth error models (`planeslam.sim.noise`), chosen
by name (`noise_model=`): 'kinect' (`KinectNoise`, the default), 'disparity'
(`DisparityNoise`) and 'tof' (`TofNoise`, a time-of-flight sensor: `planeslam.sim.tof`).
Whole sequences written to disk with their truth: `planeslam.sim.sequence`.

Colour: a procedural texture per plane in the plane's own (u, v) coordinates (the
scene's `Texture`), so it moves rigidly with the scene; Lambertian shading under the
scene's light plus ambient light; the noise model's sensor noise.

All randomness comes from the `numpy.random.Generator` passed in, in a fixed order, so
the same seed gives identical bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.core.geometry import invert_pose
from planeslam.sim.noise import NoiseModel, SurfaceTruth, noise_model_of
from planeslam.sim.scenes import (
    PLAIN_REFLECTANCE,
    Scene,
    ScenePlane,
)

__all__ = ["RenderedFrame", "plane_in_camera", "render_frame"]

_NEAR_CLIP_M = 0.05


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
        truth = SurfaceTruth(hit, depth_true, incidence, reflectance)
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
