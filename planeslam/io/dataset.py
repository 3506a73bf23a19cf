"""RGB-D sequences in the TUM RGB-D layout, read lazily frame by frame.

A dataset folder holds `rgb.txt` and `depth.txt` (`timestamp path` rows),
optionally `associations.txt` (`t_rgb rgb_path t_depth depth_path`, as made
by TUM's `associate.py`), `groundtruth.txt` (TUM trajectory) and
`camera.yaml`. Depth images are 16-bit PNG; value / depth_scale = metres.

Timestamps must be numbers that increase row by row. A listed image that is missing or
cannot be decoded (truncated, corrupt) makes that frame raise `FrameReadError` when it is
read (`run_frames` skips it with a warning); a malformed `groundtruth.txt` is reported
(`groundtruth_error`) and the sequence is read without ground truth.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from planeslam.core.camera import MAX_IMAGE_SIDE, CameraConfig, check_image_size
from planeslam.core.errors import AssociationError, DatasetFormatError, FrameReadError
from planeslam.core.frame_checks import MAX_RANGE_M, check_depth_units
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
    linenos: list[int] = []
    for lineno, fields in tum_rows(path, "list", expected):
        try:
            stamps.append(_timestamp(fields[0]))
            names.append(fields[1])
        except (ValueError, IndexError):
            raise row_error(path, lineno, f"'{expected}'", fields) from None
        linenos.append(lineno)
    return check_increasing(path, np.asarray(stamps), linenos), names


def _timestamp(text: str) -> float:
    """A finite number of seconds (ValueError otherwise: 'nan' and 'inf' parse as floats)."""
    value = float(text)
    if not np.isfinite(value):
        raise ValueError(text)
    return value


def check_increasing(path: Path, stamps: np.ndarray, linenos: list[int]) -> np.ndarray:
    """`stamps` (N,) [s] of the rows at `linenos` of `path`, unless a row's time is not
    after the previous row's: DatasetFormatError naming the line (rows are in time order,
    one per image)."""
    steps = np.diff(stamps)
    if steps.size and not np.all(steps > 0):
        k = int(np.argmax(~(steps > 0))) + 1
        what = "repeats" if stamps[k] == stamps[k - 1] else "goes back from"
        raise DatasetFormatError(
            f"{path}:{linenos[k]}: timestamp {stamps[k]:.6f} {what} the previous row's "
            f"{stamps[k - 1]:.6f} (line {linenos[k - 1]}); rows must be in increasing time order"
        )
    return stamps


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


def depth_m_from_raw(raw: np.ndarray, camera: CameraConfig) -> np.ndarray:
    """(H, W) uint16 depth values -> (H, W) float32 metres (value / camera.depth_scale), 0
    where the value is one of camera.invalid_depth."""
    depth_m = raw.astype(np.float32) / np.float32(camera.depth_scale)
    for value in camera.invalid_depth:
        if value != 0:  # raw 0 is already 0 m, which means invalid
            depth_m[raw == value] = 0.0
    return depth_m


def check_depth_size(where: str, depth: np.ndarray, camera: CameraConfig) -> None:
    """DatasetFormatError naming `where` unless the (H, W) depth image has the camera's size."""
    if depth.shape[:2] != (camera.height, camera.width):
        raise DatasetFormatError(
            f"{where}: depth is {depth.shape[1]}x{depth.shape[0]}, the camera config says "
            f"{camera.width}x{camera.height}"
        )


def check_rgb_matches_depth(where: str, rgb: np.ndarray, depth_m: np.ndarray) -> None:
    """DatasetFormatError naming `where` unless colour and depth images have one size."""
    if rgb.shape[:2] != depth_m.shape:
        raise DatasetFormatError(
            f"{where}: colour image is {rgb.shape[1]}x{rgb.shape[0]} but "
            f"its depth image is {depth_m.shape[1]}x{depth_m.shape[0]}"
        )


class FrameSequence:
    """What the readers (TUM folders, ROS bags) share: length, iteration, index checks and
    the ground-truth pose lookup. A reader sets `root`, `config`, `timestamps` and
    `groundtruth`, and reads frame `index` (0 <= index < len) in `_frame`."""

    root: Path
    config: DatasetConfig
    timestamps: np.ndarray
    groundtruth: Trajectory | None

    def _frame(self, index: int) -> Frame:
        raise NotImplementedError

    def groundtruth_pose(self, timestamp: float) -> np.ndarray:
        """(4, 4) ground-truth T_world_cam nearest to `timestamp` [s] within the association
        window (`max_time_difference_s`), else the identity (also without ground truth).
        Starting an estimate there puts it in the ground truth's world frame."""
        gt = self.groundtruth
        if gt is None or len(gt) == 0:
            return np.eye(4)
        T = gt.pose_near(timestamp, self.config.max_time_difference_s)
        if T is None:
            log.info("no ground-truth pose near %.3f s: starting at the identity", timestamp)
            return np.eye(4)
        return T

    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, index: int) -> Frame:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range: {self.root} has {len(self)} frames")
        return self._frame(index % len(self))


class Undistortion:
    """Removes the camera's lens distortion from a frame's images (nearest neighbour for
    depth, so no depth value is invented at edges); the identity unless `enabled` and the
    camera has distortion coefficients."""

    def __init__(self, camera: CameraConfig, enabled: bool) -> None:
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        if enabled and camera.is_distorted:
            self._maps = cv2.initUndistortRectifyMap(
                camera.K,
                np.asarray(camera.distortion),
                None,
                camera.K,
                (camera.width, camera.height),
                cv2.CV_32FC1,
            )

    def __call__(self, rgb: np.ndarray, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 RGB, (H, W) float32 metres -> the same, undistorted."""
        if self._maps is None:
            return rgb, depth_m
        mx, my = self._maps
        return cv2.remap(rgb, mx, my, cv2.INTER_LINEAR), cv2.remap(
            depth_m, mx, my, cv2.INTER_NEAREST
        )


class TumDataset(FrameSequence):
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
        self._check_images_exist()
        gt_path = self.root / "groundtruth.txt"
        self.groundtruth_path: Path | None = None
        """The TUM file the ground truth was read from (None without ground truth)."""
        self.groundtruth: Trajectory | None = None
        self.groundtruth_error = ""
        """Why groundtruth.txt, present, could not be used ('' when it could or is absent)."""
        if gt_path.is_file():
            try:
                self.groundtruth, self.groundtruth_path = read_tum(gt_path), gt_path
            except DatasetFormatError as exc:
                self.groundtruth_error = str(exc)
                log.warning("%s; reading the sequence without ground truth", exc)
        self._undistort = Undistortion(camera, self.config.undistort)

    def _check_images_exist(self) -> None:
        """A warning when some listed images are missing (those frames raise FrameReadError
        when read); DatasetFormatError when every frame misses one."""
        incomplete = [
            (rgb, depth)
            for rgb, depth in zip(self._rgb_paths, self._depth_paths, strict=True)
            if not (rgb.is_file() and depth.is_file())
        ]
        if not incomplete:
            return
        first = next(p for p in incomplete[0] if not p.is_file())
        if len(incomplete) == len(self):
            raise DatasetFormatError(
                f"{first}: image listed but not found; none of the {len(self)} frames of "
                f"{self.root} has both its images"
            )
        log.warning(
            "%s: image listed but not found; %d of %d frames will be skipped",
            first,
            len(incomplete),
            len(self),
        )

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
        linenos: list[int] = []
        for lineno, fields in tum_rows(path, "associations", expected):
            try:
                t1, t2 = _timestamp(fields[0]), _timestamp(fields[2])
                name1, name2 = fields[1], fields[3]
            except (ValueError, IndexError):
                raise row_error(path, lineno, f"'{expected}'", fields) from None
            # associate.py writes its first argument first: accept either order.
            if "depth" in name1 and "depth" not in name2:
                t1, name1, name2 = t2, name2, name1
            stamps.append(t1)
            rgb.append(self.root / name1)
            depth.append(self.root / name2)
            linenos.append(lineno)
        return check_increasing(path, np.asarray(stamps), linenos), rgb, depth

    def _frame(self, index: int) -> Frame:
        depth_m = self.read_depth(self._depth_paths[index])
        rgb = self.read_rgb(self._rgb_paths[index])
        check_rgb_matches_depth(str(self._rgb_paths[index]), rgb, depth_m)
        rgb, depth_m = self._undistort(rgb, depth_m)
        return Frame(index=index, timestamp=float(self.timestamps[index]), rgb=rgb, depth_m=depth_m)

    def read_depth(self, path: Path) -> np.ndarray:
        """16-bit depth PNG -> (H, W) float32 metres, 0 where invalid. FrameReadError when
        the file is missing or cannot be decoded; DatasetFormatError for another format,
        size, or values that cannot be metres after dividing by the depth scale."""
        raw = decode_image(path, cv2.IMREAD_UNCHANGED)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetFormatError(
                f"{path}: depth must be a single-channel 16-bit PNG (value / depth_scale = "
                f"metres), got {raw.dtype} with {1 if raw.ndim == 2 else raw.shape[2]} channel(s)"
            )
        check_depth_size(str(path), raw, self.camera)
        depth_m = depth_m_from_raw(raw, self.camera)
        check_depth_units(depth_m, str(path), MAX_RANGE_M, self.camera.depth_scale)
        return depth_m

    @staticmethod
    def read_rgb(path: Path) -> np.ndarray:
        """Colour image (any channel count: grey and RGBA are converted) -> (H, W, 3)
        uint8 RGB. FrameReadError when the file is missing or cannot be decoded."""
        bgr = decode_image(path, cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8"


def decode_image(path: Path, flags: int) -> np.ndarray:
    """The image in file `path` (cv2.imdecode with `flags`). FrameReadError naming the file
    when it is missing, unreadable, a PNG or JPEG cut short (OpenCV would fill the missing
    part with grey), or not decodable."""
    try:
        size = os.stat(path).st_size
        if size > MAX_IMAGE_FILE_BYTES:
            raise FrameReadError(
                f"{path}: {size} bytes, more than an image of {MAX_IMAGE_SIDE}x{MAX_IMAGE_SIDE} "
                "pixels needs; not read"
            )
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise FrameReadError(f"{path}: image listed but not found") from None
    except OSError as exc:
        raise FrameReadError(f"{path}: cannot read the image ({exc.strerror})") from None
    head, tail = data[:8].tobytes(), data[-64:].tobytes()
    header_size = image_header_size(data[:HEADER_BYTES].tobytes())
    if header_size is not None:
        check_image_size(*header_size, str(path), FrameReadError)
    if head.startswith(_PNG_SIGNATURE) and b"IEND" not in tail:
        raise FrameReadError(f"{path}: truncated PNG (no IEND chunk at its end, {data.size} bytes)")
    if head.startswith(_JPEG_SIGNATURE) and b"\xff\xd9" not in tail:
        raise FrameReadError(
            f"{path}: truncated JPEG (no end-of-image marker at its end, {data.size} bytes)"
        )
    if head.startswith(_JPEG_SIGNATURE):
        _check_jpeg_scan(path, data)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise FrameReadError(f"{path}: not a decodable image (corrupt, or not an image file)")
    return image


MAX_IMAGE_FILE_BYTES = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 8
"""Largest image file read [bytes]: 4 channels of 16 bits at the largest size."""
HEADER_BYTES = 1 << 16
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""JPEG start-of-frame markers (which hold the image size)."""


def image_header_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) [pixels] from the start of a PNG (its IHDR) or JPEG (its first
    start-of-frame segment) file, read before decoding; None for another format or a
    header not in `head`."""
    if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR" and len(head) >= 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if not head.startswith(_JPEG_SIGNATURE):
        return None
    k = 2
    while k + 9 <= len(head) and head[k] == 0xFF:
        marker, length = head[k + 1], int.from_bytes(head[k + 2 : k + 4], "big")
        if marker in _JPEG_SOF:
            return int.from_bytes(head[k + 7 : k + 9], "big"), int.from_bytes(
                head[k + 5 : k + 7], "big"
            )
        k += 2 + length
    return None


def _check_jpeg_scan(path: Path, data: np.ndarray) -> None:
    """FrameReadError when the JPEG's compressed data hold a byte pair no encoder writes
    (0xFF then 0x01-0xBF): damaged data that libjpeg would decode into grey or noise
    with only a warning on stderr."""
    start = data.tobytes().find(b"\xff\xda")  # start of the first scan
    if start < 0 or start + 4 > data.size:
        raise FrameReadError(f"{path}: corrupt JPEG (no image data)")
    scan = data[start + 2 + (int(data[start + 2]) << 8 | int(data[start + 3])) : -2]
    ff = np.flatnonzero(scan[:-1] == 0xFF)
    bad = ff[(scan[ff + 1] >= 0x01) & (scan[ff + 1] <= 0xBF)]
    if bad.size:
        raise FrameReadError(
            f"{path}: corrupt JPEG (invalid marker 0xFF{int(scan[bad[0] + 1]):02X} in its "
            f"image data, {bad.size} in all)"
        )
