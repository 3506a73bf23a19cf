"""`planeslam calibrate`: the depth noise model recovered from rendered frames of known
noise (two sensors), the 1/z lattice found or not, and the file it writes read back as a
config on a real TUM clip."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_sequence

from planeslam.app.calibrate import calibrate_sequence
from planeslam.config import load_config, resolve_config
from planeslam.frontend.calibration import fit_depth_noise, inverse_depth_step
from planeslam.sim.noise import KinectNoise
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle

pytestmark = pytest.mark.unit


@pytest.mark.integration
@pytest.mark.parametrize(
    "model",
    [KinectNoise(), KinectNoise(sigma_const_m=0.0024, sigma_quad_m=0.0038)],
    ids=["kinect", "twice-as-noisy"],
)
def test_a_rendered_sensors_noise_is_recovered_within_20_percent(model: KinectNoise):
    """Frames of the box room rendered with a known axial sigma and disparity rounding;
    the segmentation starts from the default model whichever sensor rendered them."""
    scene, trajectory = box_room_circle(frames=24)
    config = load_config("synthetic")
    rng = np.random.default_rng(0)
    depths = [
        render_frame(scene, T, config.camera, rng, noise_model=model).depth_m
        for T in trajectory.T_world_cam[::3]
    ]
    fit = fit_depth_noise(depths, config)
    z = np.array([0.75, 1.0, 1.5, 2.0])  # the depths the room is seen at
    ratio = fit.sensor.sigma_m(z) / model.depth_sigma(z)
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    step = model.disparity_step_px / (config.camera.fx * model.baseline_m)
    assert fit.step_found and fit.sensor.inverse_depth_step_per_m == pytest.approx(step, 1e-6)


def test_the_inverse_depth_lattice_is_found_only_where_there_is_one():
    rng = np.random.default_rng(1)
    step = 0.00285
    lattice = 1.0 / (step * rng.integers(120, 600, (48, 64)))
    assert inverse_depth_step([lattice]) == pytest.approx(step, 1e-9)
    assert inverse_depth_step([rng.uniform(0.5, 4.0, (48, 64))]) is None


@pytest.mark.data
def test_the_written_sensor_file_is_a_config_on_a_real_clip(tmp_path):
    root = shared_sequence("tum_fr1_xyz_10f")
    result = calibrate_sequence(root, tmp_path / "sensor.yaml")
    sensor = result.fit.sensor
    assert 0.0005 < sensor.sigma_m(1.0) < 0.02, result.text()  # millimetres, not metres
    assert resolve_config(root, result.path).sensor == sensor  # with fr1's camera
    assert "depth noise from" in result.text() and result.path.is_file()
