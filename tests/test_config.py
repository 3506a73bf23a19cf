"""Config loading: presets, unknown keys, types, precedence of camera.yaml and --camera."""

from __future__ import annotations

from pathlib import Path

import pytest

from planeslam.config import PRESETS, PlaneSlamConfig, load_config, resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.config import save_yaml
from planeslam.core.errors import ConfigError

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_loads(preset: str) -> None:
    cfg = load_config(preset)
    assert isinstance(cfg, PlaneSlamConfig)
    assert cfg.camera.width == 640 and cfg.camera.height == 480


def test_sevenscenes_preset_has_its_depth_encoding() -> None:
    cam = load_config("sevenscenes").camera
    assert cam.depth_scale == 1000.0
    assert set(cam.invalid_depth) == {0, 65535}
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (585.0, 585.0, 320.0, 240.0)


def test_unknown_key_lists_valid_keys(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("camera:\n  fx: 500\n  focal: 3\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message and "focal" in message and "valid keys: fx, fy" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "text, valid",
    [
        ("segmentation:\n  depth_sigma_a_m: 0.001\n", "valid keys: method, min_plane_points"),
        ("intersections:\n  depth_sigma_b_per_m: 0.001\n", "valid keys: d_thresh_m"),
        ("segmentation:\n  pixel_stride: 1\n", "organized, msac"),
        ("segmentation:\n  organized:\n    hypotheses: 9\n", "valid keys: cell_size_px"),
    ],
)
def test_moved_keys_are_rejected_naming_the_valid_ones(
    tmp_path: Path, text: str, valid: str
) -> None:
    """The depth noise lives in `sensor`; method-only keys in `segmentation.<method>`."""
    path = tmp_path / "old.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=f"unknown key.*{valid}"):
        load_config(path)


def test_nested_sections_load(tmp_path: Path) -> None:
    path = tmp_path / "custom.yaml"
    path.write_text(
        "sensor:\n  sigma_a_m: 0.002\n"
        "segmentation:\n  method: msac\n  organized:\n    pixel_stride: 1\n"
        "  msac:\n    hypotheses: 64\n"
    )
    cfg = load_config(path)
    assert cfg.sensor.sigma_a_m == 0.002 and cfg.sensor.sigma_b_per_m == 0.0019
    assert cfg.segmentation.method == "msac"
    assert cfg.segmentation.organized.pixel_stride == 1 and cfg.segmentation.msac.hypotheses == 64
    save_yaml(cfg, tmp_path / "saved.yaml")
    assert load_config(tmp_path / "saved.yaml") == cfg


def test_unknown_section_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("camrea: {}\n")
    with pytest.raises(ConfigError, match="unknown key.*camrea.*valid keys: camera"):
        load_config(path)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("camera:\n  fx: fast\n", "camera.fx expects a number"),
        ("camera:\n  width: 640.5\n", "camera.width expects a whole number"),
        ("camera:\n  fx: -1\n", "fx must be > 0"),
        ("dataset:\n  undistort: 1\n", "dataset.undistort expects true or false"),
        ("segmentation:\n  method: ransac\n", "segmentation.method must be one of"),
        ("segmentation:\n  organized:\n    pixel_stride: 5\n", "pixel_stride must be 1, 2"),
        ("segmentation:\n  msac:\n    hypotheses: 0\n", "msac.hypotheses must be > 0"),
        ("sensor:\n  sigma_a_m: -0.001\n", "sensor.sigma_a_m must be > 0"),
        (
            "tracking:\n  weigh_unpaired_min_area_m2: -1\n",
            "tracking.weigh_unpaired_min_area_m2 must be a number >= 0",
        ),
        ("camera: [1, 2]\n", "expected a mapping"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=expected):
        load_config(path)


def test_unreadable_yaml_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("camera: {fx: [1, 2\n")
    with pytest.raises(ConfigError, match="broken.yaml: not a readable YAML file"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"missing.yaml': neither a preset \(defaults, tum_fr1"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="'tum_fr9': neither a preset"):
        load_config("tum_fr9")


def test_saved_config_loads_back_equal(tmp_path: Path) -> None:
    cfg = load_config("tum_fr1")
    save_yaml(cfg, tmp_path / "config.yaml")
    assert load_config(tmp_path / "config.yaml") == cfg


def test_dataset_camera_yaml_overrides_config_and_cli_overrides_both(tmp_path: Path) -> None:
    save_yaml(CameraConfig(fx=600.0, fy=601.0, cx=300.0, cy=200.0), tmp_path / "camera.yaml")
    cfg = resolve_config(tmp_path, config="tum_fr1")
    assert (cfg.camera.fx, cfg.camera.cy) == (600.0, 200.0)
    cfg = resolve_config(tmp_path, config="tum_fr1", camera="500,501,310,230,1000")
    assert (cfg.camera.fx, cfg.camera.fy, cfg.camera.cx, cfg.camera.cy) == (500, 501, 310, 230)
    assert cfg.camera.depth_scale == 1000.0


def test_preset_guessed_from_folder_name(tmp_path: Path) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg3_structure_texture_far"
    folder.mkdir()
    assert resolve_config(folder).camera.fx == load_config("tum_fr3").camera.fx


@pytest.mark.parametrize("text", ["1,2,3", "a,b,c,d", "1,2,3,4,5,6"])
def test_bad_camera_override(text: str) -> None:
    with pytest.raises(ConfigError, match="fx,fy,cx,cy"):
        CameraConfig().with_overrides(text)


def test_unknown_preset() -> None:
    from planeslam.config import preset_path

    with pytest.raises(ConfigError, match="presets: defaults, tum_fr1"):
        preset_path("kinect9")


def test_defaults_yaml_lists_every_key_with_the_code_default() -> None:
    """configs/defaults.yaml documents every key; regenerate it when a default changes."""
    import yaml

    from planeslam.config import PlaneSlamConfig, load_config, preset_path
    from planeslam.core.config import to_mapping

    assert load_config("defaults") == PlaneSlamConfig()
    written = yaml.safe_load(preset_path("defaults").read_text(encoding="utf-8"))
    assert written == yaml.safe_load(yaml.safe_dump(to_mapping(PlaneSlamConfig())))


def test_the_old_name_of_backend_separate_process_is_still_read(tmp_path, caplog):
    from planeslam.config import load_config

    old = tmp_path / "old.yaml"
    old.write_text("base: tum_fr1\nbackend:\n  run_in_process: false\n")
    with caplog.at_level("WARNING"):
        assert load_config(old).backend.separate_process is False
    assert "run_in_process is now called separate_process" in caplog.text
    both = tmp_path / "both.yaml"
    both.write_text("backend:\n  run_in_process: false\n  separate_process: true\n")
    with pytest.raises(ConfigError, match="both run_in_process and separate_process"):
        load_config(both)
