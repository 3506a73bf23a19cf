"""Config layers: a file overlays its base or the guessed preset, key overrides, camera.yaml
overlaid key by key, the provenance of every key, `planeslam config show`, the start pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from planeslam.app.cli import main
from planeslam.config import (
    PlaneSlamConfig,
    explain_config,
    load_config,
    resolve_config,
)
from planeslam.core.config import leaf_keys, parse_override, save_yaml
from planeslam.core.errors import ConfigError
from planeslam.io.trajectory import Trajectory
from planeslam.slam import SLAM, slam_for_dataset

pytestmark = pytest.mark.unit


@pytest.fixture
def fr1_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "rgbd_dataset_freiburg1_desk"
    folder.mkdir()
    return folder


def test_a_one_key_file_keeps_the_guessed_presets_intrinsics(fr1_folder: Path, tmp_path: Path):
    """The README's advice for TUM clips: a file with only `backend: {lag_frames: 0}`."""
    user = tmp_path / "my.yaml"
    user.write_text("backend:\n  lag_frames: 0\n")
    fr1 = load_config("tum_fr1")
    resolved = explain_config(fr1_folder, user)
    cfg = resolved.config
    assert cfg.camera == fr1.camera and cfg.camera.fx == 517.3
    assert cfg.camera.distortion == fr1.camera.distortion != ()
    assert cfg.backend.lag_frames == 0 != fr1.backend.lag_frames
    assert cfg == resolve_config(fr1_folder, user)
    assert resolved.sources["camera.fx"] == "preset tum_fr1"
    assert resolved.sources["backend.lag_frames"] == f"file {user}"
    assert resolved.sources["tracking.rgbd_odometry"] == "default"
    assert "guessed from the folder name 'rgbd_dataset_freiburg1_desk'" in resolved.layers[0]


def test_base_names_the_preset_and_chains_files(fr1_folder: Path, tmp_path: Path):
    base = tmp_path / "base.yaml"
    base.write_text("base: tum_fr3\nsensor:\n  sigma_a_m: 0.002\n")
    user = tmp_path / "sub" / "user.yaml"
    user.parent.mkdir()
    user.write_text("base: ../base.yaml\nsensor:\n  sigma_b_per_m: 0.003\n")
    resolved = explain_config(fr1_folder, user)  # the file's base wins over the folder's guess
    cfg = resolved.config
    assert cfg.camera == load_config("tum_fr3").camera
    assert (cfg.sensor.sigma_a_m, cfg.sensor.sigma_b_per_m) == (0.002, 0.003)
    assert resolved.sources["camera.fx"] == "preset tum_fr3"
    assert resolved.sources["sensor.sigma_a_m"] == f"file {base}"
    assert resolved.sources["sensor.sigma_b_per_m"] == f"file {user}"
    # base: defaults means no preset at all, even for a guessable folder
    plain = tmp_path / "plain.yaml"
    plain.write_text("base: defaults\n")
    assert resolve_config(fr1_folder, plain) == PlaneSlamConfig()
    assert load_config(user) == resolve_config(None, user)  # no folder: the base still applies


@pytest.mark.parametrize(
    "text, message",
    [
        ("base: tum_fr9\n", r"base 'tum_fr9' is neither a preset \(defaults, tum_fr1"),
        ("base: 3\n", "base expects a preset name"),
        ("base: loop.yaml\n", "leads back to"),
        ("- 1\n", "expected a mapping of keys, got list"),
    ],
)
def test_bad_base_names_the_file(tmp_path: Path, text: str, message: str):
    path = tmp_path / "loop.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_overrides_take_yaml_values_with_the_type_checks(fr1_folder: Path):
    cfg = resolve_config(
        fr1_folder,
        overrides=[
            "backend.lag_frames=0",
            "segmentation.organized.pixel_stride=1",
            "camera.invalid_depth=[0, 65535]",
            "sensor.sigma_a_m=1.5e-3",
            "run.max_frames=null",
            "run.backend=merge",
            "objects.gravity_up_cam=[0, -1, 0]",
        ],
    )
    assert cfg.backend.lag_frames == 0 and cfg.segmentation.organized.pixel_stride == 1
    assert cfg.camera.invalid_depth == (0, 65535) and cfg.sensor.sigma_a_m == 0.0015
    assert cfg.run.backend == "merge" and cfg.run.max_frames is None
    assert cfg.camera.fx == 517.3  # the rest of the guessed preset stays
    # later overrides win
    assert resolve_config(overrides=["run.seed=1", "run.seed=2"]).run.seed == 2


@pytest.mark.parametrize(
    "text, message",
    [
        ("camera.fx=fast", "--set camera.fx=fast: camera.fx expects a number, got 'fast'"),
        ("camera.focal=3", "camera: unknown key.*focal; valid keys: fx, fy"),
        ("run.backend=gtsam", "run.backend must be one of"),
        ("segmentation.organized.pixel_stride=5", "pixel_stride must be 1, 2"),
        ("lag_frames=0", "expected section.key=value"),
        ("backend.lag_frames", "expected section.key=value"),
        ("camera.fx=[1, 2", "not a YAML value"),
    ],
)
def test_bad_overrides_name_the_option(text: str, message: str):
    with pytest.raises(ConfigError, match=message) as info:
        resolve_config(overrides=[parse_override(text, "--set")])
    assert "\n" not in str(info.value)


def test_layers_apply_in_order(fr1_folder: Path, tmp_path: Path):
    """preset < file < camera.yaml (key by key) < camera override < key overrides."""
    user = tmp_path / "user.yaml"
    user.write_text("camera:\n  fx: 400.0\n  fy: 401.0\n  cx: 300.0\n")
    (fr1_folder / "camera.yaml").write_text("fy: 450.0\ncx: 310.0\ncy: 250.0\n")
    resolved = explain_config(fr1_folder, user)
    cam = resolved.config.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (400.0, 450.0, 310.0, 250.0)
    assert cam.distortion == load_config("tum_fr1").camera.distortion  # not in camera.yaml
    assert [resolved.sources[f"camera.{k}"] for k in ("fx", "fy", "distortion")] == [
        f"file {user}",
        "camera.yaml",
        "preset tum_fr1",
    ]
    resolved = explain_config(
        fr1_folder, user, "500,501,320,240", ["camera.fx=600", "camera.depth_scale=1000"]
    )
    cam = resolved.config.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (600, 501, 320, 240, 1000)
    assert resolved.sources["camera.fx"] == resolved.sources["camera.depth_scale"] == "override"
    assert resolved.sources["camera.fy"] == "camera override"


def test_the_shown_config_loads_back_equal_and_names_every_key(fr1_folder: Path, tmp_path: Path):
    resolved = explain_config(fr1_folder, overrides=["backend.lag_frames=0"])
    text = resolved.to_yaml()
    lines = [line for line in text.splitlines() if not line.lstrip().startswith("#")]
    leaves = [line for line in lines if "#" in line]
    assert len(leaves) == len(leaf_keys(PlaneSlamConfig))
    assert any(
        line.split("#")[0].strip() == "lag_frames: 0" and "# override" in line for line in leaves
    )
    saved = tmp_path / "shown.yaml"
    saved.write_text(text)
    assert load_config(saved) == resolved.config
    assert yaml.safe_load(text)["camera"]["fx"] == 517.3


def test_config_show_command(fr1_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    user = tmp_path / "user.yaml"
    user.write_text("backend:\n  lag_frames: 0\n")
    assert (
        main(
            [
                "config",
                "show",
                str(user),
                "--dataset",
                str(fr1_folder),
                "--set",
                "run.seed=7",
                "--camera",
                "500,500,320,240",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    rows = {line.split(":")[0].strip(): line for line in out.splitlines() if "#" in line[2:]}
    assert rows["lag_frames"].endswith(f"# file {user}")
    assert rows["seed"].endswith("# --set") and "7" in rows["seed"]
    assert rows["fx"].endswith("# --camera") and rows["distortion"].endswith("# preset tum_fr1")
    assert main(["config", "show", str(fr1_folder)]) == 0  # a folder: what `run` would use
    assert "# preset tum_fr1" in capsys.readouterr().out
    assert main(["config", "show", "sevenscenes"]) == 0
    assert "depth_scale: 1000.0" in capsys.readouterr().out
    assert main(["config", "show", "--set", "camera.fx=x"]) == 2
    assert "--set camera.fx=x: camera.fx expects a number" in capsys.readouterr().err


def test_saved_run_config_overlays_nothing_it_does_not_set(fr1_folder: Path, tmp_path: Path):
    """A saved (complete) config means the same whatever folder it is used with."""
    cfg = resolve_config(fr1_folder, overrides=["run.start_pose=identity"])
    save_yaml(cfg, tmp_path / "config.yaml")
    assert resolve_config(tmp_path, tmp_path / "config.yaml") == cfg
    assert resolve_config(fr1_folder, tmp_path / "config.yaml") == cfg


class _Dataset:
    """What `slam_for_dataset` reads of a dataset."""

    def __init__(self, T_first: np.ndarray | None) -> None:
        self.timestamps = np.array([5.0, 6.0])
        self.groundtruth = None if T_first is None else Trajectory(np.array([5.0]), T_first[None])

    def groundtruth_pose(self, timestamp: float) -> np.ndarray:
        assert timestamp == 5.0
        return np.eye(4) if self.groundtruth is None else self.groundtruth.T_world_cam[0]


def test_start_pose_setting_in_slam_and_for_datasets():
    T_first = np.eye(4)
    T_first[:3, 3] = [1.0, 2.0, 3.0]
    merge = resolve_config(overrides=["run.backend=merge"])
    identity = resolve_config(overrides=["run.backend=merge", "run.start_pose=identity"])
    with slam_for_dataset(merge, _Dataset(T_first), 0) as slam:  # type: ignore[arg-type]
        np.testing.assert_array_equal(slam.predicted_pose(), T_first)
    with slam_for_dataset(identity, _Dataset(T_first), 0) as slam:  # type: ignore[arg-type]
        np.testing.assert_array_equal(slam.predicted_pose(), np.eye(4))
    with slam_for_dataset(merge, _Dataset(None), 0) as slam:  # type: ignore[arg-type]
        np.testing.assert_array_equal(slam.predicted_pose(), np.eye(4))
    import gtsam

    with SLAM(merge, T_world_first=gtsam.Pose3(T_first)) as slam:  # a Pose3 is a pose too
        np.testing.assert_allclose(slam.predicted_pose(), T_first)
    with SLAM(merge) as slam:
        np.testing.assert_array_equal(slam.predicted_pose(), np.eye(4))
    with pytest.raises(ConfigError, match="run.start_pose is 'identity'"):
        SLAM(identity, T_world_first=T_first)
    with pytest.raises(ConfigError, match="T_world_first has shape"):
        SLAM(merge, T_world_first=np.eye(3))
    with pytest.raises(ConfigError, match="run.start_pose must be one of"):
        resolve_config(overrides=["run.start_pose=first"])
