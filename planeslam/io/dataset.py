"""RGB-D sequences in the TUM RGB-D layout, read lazily frame by frame.

A dataset folder holds `rgb.txt` and `depth.txt` (`timestamp path` rows),
optionally `associations.txt` (`t_rgb rgb_path t_depth depth_path`, as made
by TUM's `associate.py`), `groundtruth.txt` (TUM trajectory) and
`camera.yaml`. Depth images are 16-bit PNG; value / depth_scale = metres.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import AssociationError, DatasetFormatError
from planeslam.io.config import DatasetConfig
from planeslam.io.trajectory import Trajectory, read_tum
from planeslam.io.tum_text import row_error, tum_rows

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame."""

    index: int
    """Position in the dataset's frame list."""
    timestamp: float
    """Seconds (the RGB image's time stamp, as TUM trajectories use)."""
    rgb: np.ndarray
    """(H, W, 3) uint8, RGB order."""
    depth_m: np.ndarray
    """(H, W) float32 metres along the optical axis; 0 where invalid."""


def read_list_file(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM `timestamp path` list -> (N,) timestamps and N relative paths."""
    expected = "timestamp path"
    stamps: list[float] = []
    names: list[str] = []
    for lineno, fields in tum_rows(path, "list", expected):
        try:
            stamps.append(float(fields[0]))
            names.append(fields[1])
        except (ValueError, IndexError):
            raise row_error(path, lineno, f"'{expected}'", fields) from None
    return np.asarray(stamps), names


def associate_timestamps(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_difference: float
) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) with |a_i - b_j| <= max_difference, closest first
    (as TUM's associate.py), returned sorted by i."""
    order_b = np.argsort(stamps_b)
    sorted_b = stamps_b[order_b]
    pos = np.searchsorted(sorted_b, stamps_a)
    candidates = []
    for offset in (-1, 0):
        j = np.clip(pos + offset, 0, len(sorted_b) - 1)
        diff = np.abs(stamps_a - sorted_b[j])
        ok = diff <= max_difference
        candidates.append(np.stack([np.nonzero(ok)[0], order_b[j[ok]], diff[ok]], axis=1))
    pairs = np.concatenate(candidates)
    pairs = pairs[np.argsort(pairs[:, 2], kind="stable")]
    used_a: set[int] = set()
    used_b: set[int] = set()
    result = []
    for row in pairs.tolist():
        a, b = int(row[0]), int(row[1])
        if a not in used_a and b not in used_b:
            used_a.add(a)
            used_b.add(b)
            result.append((a, b))
    return sorted(result)


class TumDataset:
    """A TUM-layout RGB-D sequence. Frames are read from disk on access, never all at once."""

    def __init__(
        self,
        root: str | Path,
        camera: CameraConfig,
        config: DatasetConfig | None = None,
    ) -> None:
        self.root = Path(root)
        self.camera = camera
        self.config = config or DatasetConfig()
        if not self.root.is_dir():
            raise DatasetFormatError(f"{self.root}: dataset folder not found")
        self.timestamps, self._rgb_paths, self._depth_paths = self._read_frame_list()
        missing = [p for p in (*self._rgb_paths, *self._depth_paths) if not p.is_file()]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise DatasetFormatError(f"{missing[0]}: image listed but not found{more}")
        gt_path = self.root / "groundtruth.txt"
        self.groundtruth: Trajectory | None = read_tum(gt_path) if gt_path.is_file() else None
        self._undistort_maps = self._make_undistort_maps()

    def _read_frame_list(self) -> tuple[np.ndarray, list[Path], list[Path]]:
        assoc = self.root / "associations.txt"
        if self.config.use_associations_file and assoc.is_file():
            return self._read_associations(assoc)
        rgb_t, rgb_names = read_list_file(self.root / "rgb.txt")
        depth_t, depth_names = read_list_file(self.root / "depth.txt")
        pairs = associate_timestamps(rgb_t, depth_t, self.config.max_time_difference_s)
        if not pairs:
            gap = float(np.min(np.abs(rgb_t[:, None] - depth_t[None, :])))
            raise AssociationError(
                f"{self.root}: no rgb/depth pairs within {self.config.max_time_difference_s} s "
                f"(closest pair is {gap:.3f} s apart; raise dataset.max_time_difference_s?)"
            )
        stamps = np.array([rgb_t[i] for i, _ in pairs])
        return (
            stamps,
            [self.root / rgb_names[i] for i, _ in pairs],
            [self.root / depth_names[j] for _, j in pairs],
        )

    def _read_associations(self, path: Path) -> tuple[np.ndarray, list[Path], list[Path]]:
        expected = "t_rgb rgb_path t_depth depth_path"
        stamps: list[float] = []
        rgb: list[Path] = []
        depth: list[Path] = []
        for lineno, fields in tum_rows(path, "associations", expected):
            try:
                t1, t2 = float(fields[0]), float(fields[2])
                name1, name2 = fields[1], fields[3]
            except (ValueError, IndexError):
                raise row_error(path, lineno, f"'{expected}'", fields) from None
            # associate.py writes its first argument first: accept either order.
            if "depth" in name1 and "depth" not in name2:
                t1, name1, name2 = t2, name2, name1
            stamps.append(t1)
            rgb.append(self.root / name1)
            depth.append(self.root / name2)
        return np.asarray(stamps), rgb, depth

    def _make_undistort_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        cam = self.camera
        if not (self.config.undistort and cam.is_distorted):
            return None
        return cv2.initUndistortRectifyMap(
            cam.K, np.asarray(cam.distortion), None, cam.K, (cam.width, cam.height), cv2.CV_32FC1
        )

    def groundtruth_pose(self, timestamp: float) -> np.ndarray:
        """(4, 4) ground-truth T_world_cam nearest to `timestamp` [s] within the association
        window (`max_time_difference_s`), else the identity (also without ground truth).
        Starting an estimate there puts it in the ground truth's world frame."""
        gt = self.groundtruth
        if gt is None or len(gt) == 0:
            return np.eye(4)
        k = int(np.argmin(np.abs(gt.timestamps - timestamp)))
        if abs(gt.timestamps[k] - timestamp) > self.config.max_time_difference_s:
            log.info("no ground-truth pose near %.3f s: starting at the identity", timestamp)
            return np.eye(4)
        return np.array(gt.T_world_cam[k], dtype=np.float64)

    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Frame:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range: {self.root} has {len(self)} frames")
        index = index % len(self)
        depth_m = self.read_depth(self._depth_paths[index])
        rgb = self.read_rgb(self._rgb_paths[index])
        if rgb.shape[:2] != depth_m.shape:
            raise DatasetFormatError(
                f"{self._rgb_paths[index]}: colour image is {rgb.shape[1]}x{rgb.shape[0]} but "
                f"its depth image is {depth_m.shape[1]}x{depth_m.shape[0]}"
            )
        if self._undistort_maps is not None:
            mx, my = self._undistort_maps
            depth_m = cv2.remap(depth_m, mx, my, cv2.INTER_NEAREST)
            rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR)
        return Frame(index=index, timestamp=float(self.timestamps[index]), rgb=rgb, depth_m=depth_m)

    def read_depth(self, path: Path) -> np.ndarray:
        """16-bit depth PNG -> (H, W) float32 metres, 0 where invalid."""
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetFormatError(f"{path}: not a readable image")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetFormatError(
                f"{path}: depth must be a single-channel 16-bit PNG, got {raw.dtype} "
                f"with {1 if raw.ndim == 2 else raw.shape[2]} channel(s)"
            )
        cam = self.camera
        if raw.shape != (cam.height, cam.width):
            raise DatasetFormatError(
                f"{path}: depth is {raw.shape[1]}x{raw.shape[0]}, the camera config says "
                f"{cam.width}x{cam.height}"
            )
        depth_m = raw.astype(np.float32) / np.float32(cam.depth_scale)
        for value in cam.invalid_depth:
            if value != 0:  # raw 0 is already 0 m, which means invalid
                depth_m[raw == value] = 0.0
        return depth_m

    @staticmethod
    def read_rgb(path: Path) -> np.ndarray:
        """Colour image -> (H, W, 3) uint8 RGB."""
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DatasetFormatError(f"{path}: not a readable image")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
