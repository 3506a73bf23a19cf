"""Planes from quantised inverse depth (`core.quantised_fit`): the interval likelihood's
derivatives, the far wall that least squares biases, and the gate that leaves dithered
depth to least squares."""

from __future__ import annotations

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.errors import ConfigError, GeometryError
from planeslam.core.plane_fit import plane_covariance, plane_from_moments
from planeslam.core.quantised_fit import (
    _interval_terms,
    fit_quantised_plane,
    inverse_depth_residual_steps,
    quantisation_bias_m,
)
from planeslam.frontend.segmentation import segment_planes
from tests.conftest import shared_sequence

pytestmark = pytest.mark.unit

RAYS = PixelRays.for_camera(CameraConfig())
STEP = DepthNoiseConfig().inverse_depth_step_per_m
NOT_QUANTISED = DepthNoiseConfig(inverse_depth_step_per_m=0.0)


def _quantised_wall(normal, d: float, sigma_steps: float, rng) -> np.ndarray:
    """(H, W) depth [m] of the plane (normal, d) in a 300 x 200 pixel window: 1/z with
    Gaussian noise of `sigma_steps` steps, then rounded to the step (a Kinect's disparity)."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    w = -(RAYS.rays @ n) / d + sigma_steps * STEP * rng.standard_normal(RAYS.rays.shape[:2])
    depth = np.zeros(w.shape, dtype=np.float32)
    window = (slice(140, 340), slice(170, 470))
    depth[window] = 1.0 / (np.rint(w[window] / STEP) * STEP)
    return depth


def test_interval_terms_match_numerical_derivatives(rng) -> None:
    r = rng.uniform(-4e-3, 4e-3, 50)
    half, sigma, eps = 0.5 * STEP, 0.3 * STEP, 1e-9
    _, g_r, g_t, h_rr, h_rt, h_tt = _interval_terms(r, half, sigma)

    def at(dr: float = 0.0, dt: float = 0.0) -> tuple[np.ndarray, ...]:
        return _interval_terms(r + dr, half, sigma * np.exp(dt))

    def central(k: int, dr: float = 0.0, dt: float = 0.0) -> np.ndarray:
        return (at(dr, dt)[k] - at(-dr, -dt)[k]) / (2 * max(dr, dt))

    np.testing.assert_allclose(g_r, central(0, dr=eps), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(g_t, central(0, dt=1e-6), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(h_rr, central(1, dr=eps), rtol=1e-4, atol=10.0)
    np.testing.assert_allclose(h_rt, central(1, dt=1e-6), rtol=1e-5, atol=1e-2)
    np.testing.assert_allclose(h_tt, central(2, dt=1e-6), rtol=1e-5, atol=1e-6)
    # Far outside the interval the likelihood stays finite (the lower-tail evaluation).
    assert np.all(np.isfinite(_interval_terms(np.array([-0.05, 0.05]), half, sigma)[0]))


def test_a_far_wall_on_few_depth_levels_is_fit_without_the_rounding_bias(rng) -> None:
    """A wall at 5.5-5.6 m, 1.2 deg off frontal, spans about two depth levels 9 cm apart;
    noise of 0.2 steps does not dither them. Least squares is off by up to about 4 mm,
    varying with the offset; the maximum-likelihood fit stays within 2 mm."""
    normal = np.array([0.02, -0.006, -1.0])
    normal /= np.linalg.norm(normal)
    errors_ls, errors_ml = [], []
    for d in np.linspace(5.5, 5.6, 8):
        depth = _quantised_wall(normal, d, 0.2, rng)
        (ls,) = segment_planes(depth, RAYS, sensor=NOT_QUANTISED).planes
        (ml,) = segment_planes(depth, RAYS).planes
        errors_ls.append(ls.d - d)
        errors_ml.append(ml.d - d)
        assert np.degrees(np.arccos(ml.normal @ normal)) < 0.2
        # Its moments refit to it (map merges start from it), with the same covariance.
        n_moments, d_moments, rss = plane_from_moments(ml.centroid, ml.scatter)
        assert n_moments @ ml.normal == pytest.approx(1.0, abs=1e-12)
        assert d_moments == pytest.approx(ml.d, abs=1e-9)
        covariance = plane_covariance(ml.normal, ml.centroid, ml.scatter, ml.num_points, rss)
        np.testing.assert_allclose(covariance, ml.covariance, rtol=1e-6)
    rms_ls, rms_ml = np.sqrt(np.mean(np.square(errors_ls))), np.sqrt(np.mean(np.square(errors_ml)))
    assert np.max(np.abs(errors_ls)) > 0.003 and np.max(np.abs(errors_ml)) < 0.002
    assert rms_ml < 0.4 * rms_ls
    # The fit on its own (no segmentation) and its noise estimate.
    depth = _quantised_wall(normal, 5.55, 0.2, rng)
    points = depth[depth > 0][:, None] * RAYS.rays[depth > 0]
    fit = fit_quantised_plane(points, STEP)
    assert fit.d == pytest.approx(5.55, abs=0.002) and fit.sigma_steps == pytest.approx(
        0.2, abs=0.03
    )


def test_dithered_depth_keeps_the_least_squares_plane(rng) -> None:
    """Noise of half a step dithers the rounding: the gate leaves the plane to least squares,
    bit for bit."""
    depth = _quantised_wall([0.02, -0.006, -1.0], 3.0, 0.5, rng)
    (default,) = segment_planes(depth, RAYS).planes
    (plain,) = segment_planes(depth, RAYS, sensor=NOT_QUANTISED).planes
    assert default.d == plain.d and np.array_equal(default.normal, plain.normal)
    points = depth[depth > 0][:, None] * RAYS.rays[depth > 0]
    noise = inverse_depth_residual_steps(points, plain.normal, plain.d, STEP)
    assert noise == pytest.approx(0.5, abs=0.05)


def test_the_rounding_bias_bound_and_bad_values() -> None:
    # No noise: up to z^2 s / pi; half a step of noise: below 1 % of that.
    assert quantisation_bias_m(5.0, STEP, 0.0) == pytest.approx(25 * STEP / np.pi)
    assert quantisation_bias_m(5.0, STEP, 0.5) < 0.01 * quantisation_bias_m(5.0, STEP, 0.0)
    with pytest.raises(ConfigError, match="sensor.inverse_depth_step_per_m"):
        DepthNoiseConfig(inverse_depth_step_per_m=-0.001)
    with pytest.raises(GeometryError, match="at least 4 points"):
        fit_quantised_plane(np.ones((3, 3)), STEP)


def test_the_gate_decides_as_numpy_at_its_threshold(rng) -> None:
    """`_rounding_could_bias` takes the noise from a compiled pass; with the offset sigma
    set so that the bias is 1e-9 (relative) on either side of the threshold, too close for
    that pass, numpy's computation decides."""
    from planeslam.frontend.segment_common import _rounding_could_bias

    depth = _quantised_wall([0.02, -0.006, -1.0], 5.55, 0.2, rng)
    (plain,) = segment_planes(depth, RAYS, sensor=NOT_QUANTISED).planes
    xyz = np.ascontiguousarray(plain.points.T)
    sample = xyz[:, :: max(1, xyz.shape[1] // 4096)].T  # the gate's evenly spread points
    noise = inverse_depth_residual_steps(sample, plain.normal, plain.d, STEP)
    bias = quantisation_bias_m(float(plain.centroid[2]), STEP, noise)
    for factor, expected in ((1.0 - 1e-9, True), (1.0 + 1e-9, False)):
        covariance = np.diag([1.0, 1.0, (0.5 * bias * factor) ** 2])
        gate = _rounding_could_bias(xyz, plain.normal, plain.d, plain.centroid, covariance, STEP)
        assert gate is expected


def test_a_fit_that_fails_keeps_the_least_squares_plane(rng, monkeypatch) -> None:
    import planeslam.frontend.segment_common as segment_common

    depth = _quantised_wall([0.02, -0.006, -1.0], 5.55, 0.2, rng)
    (plain,) = segment_planes(depth, RAYS, sensor=NOT_QUANTISED).planes

    def fails(points: np.ndarray, step: float) -> None:
        raise GeometryError("the quantised plane fit did not converge")

    monkeypatch.setattr(segment_common, "fit_quantised_plane", fails)
    (kept,) = segment_planes(depth, RAYS).planes
    assert kept.d == plain.d and np.array_equal(kept.normal, plain.normal)


@pytest.mark.data
def test_icl_nuim_back_wall_varies_less_under_the_true_poses() -> None:
    """ICL-NUIM's back wall at 5.5 m sits on two or three depth levels: under the true poses
    its least-squares offset jumps by 1.5 cm between frames 24 and 28 (7.7 mm standard
    deviation over every 3rd frame); the quantised fit takes 40 % off the spread."""
    from planeslam.config import resolve_config
    from planeslam.io.dataset import TumDataset

    root = shared_sequence("iclnuim_of_kt0")
    cfg = resolve_config(root)
    dataset = TumDataset(root, cfg.camera)
    rays = PixelRays.for_camera(cfg.camera)
    offsets: dict[str, list[float]] = {"least squares": [], "quantised": []}
    for index in range(1, 101, 3):
        frame = dataset[index]
        T_world_cam = dataset.groundtruth_pose(frame.timestamp)
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        for name, sensor in (("least squares", NOT_QUANTISED), ("quantised", cfg.sensor)):
            planes = segment_planes(frame.depth_m, rays, cfg.segmentation, sensor=sensor).planes
            # (n_world, d_world) of each plane; the back wall: n_world = (0, 0, -1), d 3.19 m
            in_world = [(R @ p.normal, p.d - (R @ p.normal) @ t, p.num_points) for p in planes]
            walls = [(d, k) for n, d, k in in_world if n[2] < -0.98 and abs(d - 3.19) < 0.1]
            offsets[name].append(max(walls, key=lambda wall: wall[1])[0])
    spread = {name: float(np.std(values)) for name, values in offsets.items()}
    assert spread["least squares"] > 0.005
    assert spread["quantised"] < 0.7 * spread["least squares"]  # 4.5 against 7.7 mm
