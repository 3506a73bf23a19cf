"""TUM-layout reader: the real sequences in ../shared/data, and every bad-input case."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from planeslam.config import resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import AssociationError, DatasetFormatError
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import TumDataset, associate_timestamps
from tests.conftest import shared_sequence

pytestmark = pytest.mark.unit

# (folder, frames, median valid depth range [m] per frame, from each SOURCE.md)
REAL = [
    ("7scenes_redkitchen_1000f", 1000, (1.18, 2.47)),
    ("tum_fr1_desk_9f", 9, (1.08, 1.19)),
    ("tum_fr1_xyz_10f", 10, (1.01, 1.18)),
]


def open_real(name: str) -> TumDataset:
    path = shared_sequence(name)
    cfg = resolve_config(path)
    return TumDataset(path, cfg.camera, cfg.dataset)


@pytest.mark.data
@pytest.mark.parametrize("name, frames, median_range", REAL)
def test_real_sequences_read(name: str, frames: int, median_range: tuple[float, float]) -> None:
    ds = open_real(name)
    assert len(ds) == frames
    step = max(1, frames // 20)
    lo, hi = median_range
    for i in range(0, frames, step):
        frame = ds[i]
        assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
        assert frame.depth_m.dtype == np.float32
        valid = frame.depth_m[frame.depth_m > 0]
        assert valid.max() < 10.0, "invalid raw values (65535) must not become depth"
        assert lo - 0.01 <= float(np.median(valid)) <= hi + 0.01
    assert ds.groundtruth is not None
    # Every frame has a ground-truth pose within the association window.
    gap = np.abs(ds.timestamps[:, None] - ds.groundtruth.timestamps[None, :]).min(axis=1)
    assert gap.max() <= 0.02


@pytest.mark.data
def test_timestamp_association_matches_the_official_associations_file() -> None:
    path = shared_sequence("tum_fr1_desk_9f")
    cam = resolve_config(path).camera
    official = TumDataset(path, cam)
    own = TumDataset(path, cam, DatasetConfig(use_associations_file=False))
    np.testing.assert_array_equal(official.timestamps, own.timestamps)


@pytest.mark.data
def test_undistortion_moves_pixels_but_keeps_depth_values() -> None:
    path = shared_sequence("tum_fr1_xyz_10f")
    cam = resolve_config(path).camera
    plain = TumDataset(path, cam)[0]
    undistorted = TumDataset(path, cam, DatasetConfig(undistort=True))[0]
    assert not np.array_equal(plain.depth_m, undistorted.depth_m)
    # Nearest-neighbour remapping: no new depth values are invented at edges.
    assert np.isin(np.unique(undistorted.depth_m), np.unique(plain.depth_m)).all()


def test_associate_timestamps_is_one_to_one_and_windowed() -> None:
    rgb = np.array([0.00, 0.033, 0.066, 0.5])
    depth = np.array([0.01, 0.02, 0.07, 0.9])
    assert associate_timestamps(rgb, depth, 0.02) == [(0, 0), (1, 1), (2, 2)]


# ---- bad input: a tiny fake dataset in tmp_path ------------------------------------------

CAM = CameraConfig(fx=50.0, fy=50.0, cx=15.5, cy=11.5, width=32, height=24)


def make_dataset(root: Path, n: int = 3, depth_dtype=np.uint16, rgb_size=(32, 24)) -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i in range(n):
        t = 100.0 + i / 30
        cv2.imwrite(str(root / f"rgb/{i}.png"), np.full((*rgb_size[::-1], 3), 80, np.uint8))
        depth_value = 5000 if depth_dtype == np.uint16 else 50
        cv2.imwrite(str(root / f"depth/{i}.png"), np.full((24, 32), depth_value, depth_dtype))
        rgb_lines.append(f"{t:.6f} rgb/{i}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{i}.png")
    (root / "rgb.txt").write_text("# color\n" + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")
    return root


def test_fake_dataset_reads(tmp_path: Path) -> None:
    ds = TumDataset(make_dataset(tmp_path / "seq"), CAM)
    assert len(ds) == 3
    frames = list(ds)
    assert all(np.allclose(f.depth_m, 1.0) for f in frames)
    assert ds.groundtruth is None


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetFormatError, match="nope: dataset folder not found"):
        TumDataset(tmp_path / "nope", CAM)


def test_missing_list_file(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq")
    (root / "depth.txt").unlink()
    with pytest.raises(DatasetFormatError, match=r"depth.txt: list file not found"):
        TumDataset(root, CAM)


def test_list_names_missing_image(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq")
    (root / "rgb" / "1.png").unlink()
    dataset = TumDataset(root, CAM)  # a warning; the frame is skipped when a run reads it
    with pytest.raises(DatasetFormatError, match=r"rgb/1.png: image listed but not found"):
        dataset[1]


def test_malformed_list_row(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq")
    (root / "rgb.txt").write_text("100.0\n")
    with pytest.raises(DatasetFormatError, match=r"rgb.txt:1: expected 'timestamp path'"):
        TumDataset(root, CAM)


def test_depth_not_16_bit(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq", depth_dtype=np.uint8)
    message = r"depth/0.png: depth must be a single-channel 16-bit"
    with pytest.raises(DatasetFormatError, match=message):
        TumDataset(root, CAM)[0]


def test_mismatched_image_sizes(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq", rgb_size=(16, 12))
    message = r"colour image is 16x12 but its depth image is 32x24"
    with pytest.raises(DatasetFormatError, match=message):
        TumDataset(root, CAM)[0]


def test_depth_size_differs_from_camera(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq")
    with pytest.raises(DatasetFormatError, match=r"depth is 32x24, the camera config says 640x480"):
        TumDataset(root, CameraConfig())[0]


def test_no_pairs_within_window(tmp_path: Path) -> None:
    root = make_dataset(tmp_path / "seq")
    (root / "depth.txt").write_text("500.0 depth/0.png\n")
    message = r"no rgb/depth pairs within 0.02 s \(closest pair is"
    with pytest.raises(AssociationError, match=message):
        TumDataset(root, CAM)
