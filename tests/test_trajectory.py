"""TUM trajectory files: round trip, incremental writing, malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planeslam.core.errors import DatasetFormatError
from planeslam.core.geometry import invert_pose, pose_from_quat, quat_from_pose
from planeslam.io.trajectory import Trajectory, TumWriter, read_tum, write_tum

pytestmark = pytest.mark.unit


def random_trajectory(rng: np.random.Generator, n: int = 20) -> Trajectory:
    quats = Rotation.random(n, random_state=rng.integers(1 << 31)).as_quat()
    T = pose_from_quat(rng.normal(size=(n, 3)), quats)
    return Trajectory(timestamps=np.arange(n) / 30.0 + 1305031102.0, T_world_cam=T)


def test_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    traj = random_trajectory(rng)
    write_tum(tmp_path / "t.txt", traj, header="test")
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.T_world_cam, traj.T_world_cam, atol=1e-8)


def test_quaternion_round_trip_and_inverse(rng: np.random.Generator) -> None:
    traj = random_trajectory(rng, 5)
    t, q = quat_from_pose(traj.T_world_cam)
    np.testing.assert_allclose(pose_from_quat(t, q), traj.T_world_cam, atol=1e-12)
    eye = np.einsum("nij,njk->nik", invert_pose(traj.T_world_cam), traj.T_world_cam)
    np.testing.assert_allclose(eye, np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)


def test_writer_keeps_rows_written_before_an_interruption(tmp_path: Path) -> None:
    writer = TumWriter(tmp_path / "partial.txt")
    writer.write(1.0, np.eye(4))
    writer.write(2.0, np.eye(4))
    # Not closed (as after a crash): every row is already on disk.
    assert len(read_tum(tmp_path / "partial.txt")) == 2
    writer.close()


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", "no poses"),
        ("# only a comment\n", "no poses"),
        ("1.0 0 0 0 0 0 0\n", r":1: expected 8 numbers"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 x 0 0 0 1\n", r":2: expected 8 numbers"),
        ("1.0 0 0 0 0 0 0 0\n", r":1: quaternion qx qy qz qw has norm 0, expected a unit"),
    ],
)
def test_malformed_files(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "traj.txt"
    path.write_text(text)
    with pytest.raises(DatasetFormatError, match=expected):
        read_tum(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetFormatError, match="trajectory file not found"):
        read_tum(tmp_path / "nope.txt")
