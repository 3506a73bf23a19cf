"""What SLAM, the baselines and the commands read: an RGB-D sequence behind one small
interface (`RgbdDataset`), opened from a TUM-layout folder or a ROS bag by `open_dataset`."""

from __future__ import annotations

import enum
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import DatasetFormatError
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import Frame, TumDataset
from planeslam.io.trajectory import Trajectory


class RgbdDataset(Protocol):
    """An RGB-D sequence read frame by frame (TUM folder, ROS 1 bag, ROS 2 bag)."""

    root: Path
    """The folder or bag file it was opened from."""
    camera: CameraConfig
    """Intrinsics and depth encoding of its frames (a bag's camera_info applied)."""
    config: DatasetConfig
    """How it is read."""
    timestamps: np.ndarray
    """(N,) frame time stamps [s], the colour images' times."""
    groundtruth: Trajectory | None
    """T_world_cam ground truth, None when the sequence has none."""
    groundtruth_path: Path | None
    """The TUM file holding the ground truth; None when there is none or it came from
    elsewhere (a bag's /tf)."""

    def groundtruth_pose(self, timestamp: float) -> np.ndarray:
        """(4, 4) ground-truth T_world_cam nearest to `timestamp` [s] within the association
        window, else the identity."""
        ...

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...


class DatasetKind(enum.Enum):
    """The storage a sequence comes in."""

    FOLDER = "folder"
    """TUM RGB-D layout: rgb.txt, depth.txt, rgb/, depth/, groundtruth.txt."""
    ROS1_BAG = "ros1_bag"
    """A ROS 1 `.bag` file (TUM's bags, RealSense recordings)."""
    ROS2_BAG = "ros2_bag"
    """A ROS 2 bag folder (metadata.yaml with sqlite3 or mcap storage)."""


def dataset_kind(path: str | Path) -> DatasetKind:
    """What `path` holds, from its name and contents (DatasetFormatError when nothing)."""
    path = Path(path)
    if path.is_file() and path.suffix == ".bag":
        return DatasetKind.ROS1_BAG
    if path.is_dir():
        return DatasetKind.ROS2_BAG if (path / "metadata.yaml").is_file() else DatasetKind.FOLDER
    if path.is_file() and path.suffix in (".db3", ".mcap"):
        raise DatasetFormatError(
            f"{path}: a ROS 2 bag is read as its folder (the one holding metadata.yaml), "
            f"not one of its storage files"
        )
    if not path.exists():
        raise DatasetFormatError(
            f"{path}: dataset not found (expected a TUM-layout folder, "
            f"a ROS 1 .bag file or a ROS 2 bag folder)"
        )
    raise DatasetFormatError(
        f"{path}: not a dataset (expected a TUM-layout folder, a ROS 1 .bag file or a ROS 2 "
        f"bag folder with metadata.yaml)"
    )


def open_dataset(
    path: str | Path, camera: CameraConfig, config: DatasetConfig | None = None
) -> RgbdDataset:
    """The sequence at `path`: a TUM-layout folder, a ROS 1 `.bag` file or a ROS 2 bag
    folder (sqlite3 or mcap), read with `camera` (a bag's camera_info replaces its
    intrinsics unless `config.bag.intrinsics` is 'config') and `config`."""
    kind = dataset_kind(path)
    if kind is DatasetKind.FOLDER:
        return TumDataset(path, camera, config)
    from planeslam.io.rosbag import RosBagDataset

    return RosBagDataset(path, camera, config)
