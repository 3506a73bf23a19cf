"""`planeslam run` and its config: the saved config.yaml repeats the run, --set and the run
flags land in it with their sources, --start-pose fixes the world frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from planeslam.app.cli import main
from planeslam.config import load_config
from planeslam.io.trajectory import read_tum
from planeslam.sim.sequence import synthesize

pytestmark = pytest.mark.integration  # `planeslam run` twice: the saved config repeats the run


@pytest.fixture(scope="module")
def box_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("data") / "box_room_circle"
    # 12 views 30 deg apart, 1 s between them: within a plausible motion (60 deg/s)
    synthesize("box_room_circle", root, frames=12, seed=0)
    return root


def run(*args: str) -> None:
    assert main(["run", *args, "-q"]) == 0


def test_saved_config_repeats_the_run(box_room: Path, tmp_path: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    run(
        str(box_room),
        "--out", str(first),
        "--backend", "merge",
        "--max-frames", "5",
        "--seed", "3",
        "--start-pose", "identity",
        "--set", "segmentation.organized.pixel_stride=1",
        "--set", "map.voxel_m=0.02",
    )  # fmt: skip
    text = (first / "config.yaml").read_text(encoding="utf-8")
    saved = load_config(first / "config.yaml")
    assert saved.segmentation.organized.pixel_stride == 1 and saved.map.voxel_m == 0.02
    assert (saved.run.backend, saved.run.max_frames, saved.run.seed) == ("merge", 5, 3)
    assert saved.run.start_pose == "identity"
    sources = {
        line.split(":")[0].strip(): line.split("#")[-1].strip()
        for line in text.splitlines()
        if not line.startswith("#") and "#" in line
    }
    assert sources["pixel_stride"] == "--set" and sources["start_pose"] == "--start-pose"
    assert sources["backend"] == "--backend" and sources["fx"] == "camera.yaml"
    assert yaml.safe_load(text)["run"]["every"] == 1
    run(str(box_room), "--out", str(second), "--config", str(first / "config.yaml"))
    assert load_config(second / "config.yaml") == saved
    a, b = read_tum(first / "trajectory.txt"), read_tum(second / "trajectory.txt")
    assert len(a.timestamps) >= 3  # lost frames are left out of trajectory.txt
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)


def test_start_pose_fixes_the_world_frame(box_room: Path, tmp_path: Path) -> None:
    truth = read_tum(box_room / "groundtruth.txt")
    for start_pose in ("groundtruth", "identity"):
        out = tmp_path / start_pose
        run(str(box_room), "--out", str(out), "--backend", "merge", "--max-frames", "3",
            "--start-pose", start_pose)  # fmt: skip
        first = read_tum(out / "trajectory.txt").T_world_cam[0]
        expected = truth.T_world_cam[0] if start_pose == "groundtruth" else np.eye(4)
        np.testing.assert_allclose(first, expected, atol=1e-9)
    assert not np.allclose(truth.T_world_cam[0], np.eye(4))
