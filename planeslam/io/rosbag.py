"""RGB-D sequences in ROS bags (ROS 1 `.bag` files, ROS 2 bag folders with sqlite3 or mcap
storage), read lazily frame by frame through `rosbags`.

Opening a bag indexes its colour and depth topics once (time stamps only; images are
decoded on access), pairs colour and depth images by their header stamps like TUM's
`associate.py`, reads the intrinsics from the first camera_info message, and finds the
ground truth: a TUM trajectory file beside the bag or the /tf chain from the world frame to
the camera frame (`BagConfig`). Frame time stamps are the colour images' header stamps.

Depth encodings: `16UC1` / `mono16` (value / camera.depth_scale = metres, values in
camera.invalid_depth are invalid) and `32FC1` (metres; NaN, inf and values <= 0 are
invalid). Colour: `rgb8`, `bgr8`, `rgba8`, `bgra8`, `mono8`, or a CompressedImage.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import weakref
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from planeslam.core.camera import CameraConfig, check_image_size
from planeslam.core.errors import (
    AssociationError,
    ConfigError,
    DatasetFormatError,
    FrameReadError,
    PlaneSlamError,
)
from planeslam.core.frame_checks import MAX_RANGE_M, check_depth_units, clean_depth
from planeslam.core.geometry import pose_from_quat
from planeslam.io.config import DatasetConfig
from planeslam.io.dataset import (
    HEADER_BYTES,
    Frame,
    FrameSequence,
    Undistortion,
    associate_timestamps,
    check_depth_size,
    check_rgb_matches_depth,
    depth_m_from_raw,
    image_header_size,
)
from planeslam.io.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

TF_TOPICS = ("/tf", "/tf_static")
"""Topics of tf2 transforms (tf/tfMessage in ROS 1, tf2_msgs/msg/TFMessage)."""

_PIXEL_FORMATS: dict[str, tuple[str, int]] = {
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
    "mono8": ("u1", 1),
    "16uc1": ("u2", 1),
    "mono16": ("u2", 1),
    "32fc1": ("f4", 1),
}
"""sensor_msgs/Image encoding (lower case) -> numpy element type, channels."""

_COLOUR_TO_RGB = {
    "rgb8": None,
    "bgr8": cv2.COLOR_BGR2RGB,
    "rgba8": cv2.COLOR_RGBA2RGB,
    "bgra8": cv2.COLOR_BGRA2RGB,
    "mono8": cv2.COLOR_GRAY2RGB,
}
_COLOUR_FORMATS = {k: _PIXEL_FORMATS[k] for k in _COLOUR_TO_RGB}
_DEPTH_FORMATS = {k: _PIXEL_FORMATS[k] for k in ("16uc1", "mono16", "32fc1")}
_COMPRESSED = "sensor_msgs/msg/CompressedImage"


@dataclass(frozen=True)
class _MessageRef:
    """Where one image message sits in the bag: enough to read it again."""

    connection: Any
    """The rosbags Connection it came on."""
    bag_time_ns: int
    """Its record time in the bag [ns] (not the header stamp)."""
    ordinal: int
    """How many earlier messages of the connection share that record time."""


def stamp_seconds(stamp: Any) -> float:
    """A ROS time (sec, nanosec) -> seconds, rounded once (as a float parsed from text)."""
    return (int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)) / 1_000_000_000


def _image_array(msg: Any, where: str, formats: dict[str, tuple[str, int]]) -> np.ndarray:
    """A sensor_msgs/Image -> (H, W) or (H, W, C) array of its encoding's type, native byte
    order; DatasetFormatError for an encoding not in `formats` or a short buffer."""
    encoding = str(msg.encoding).lower()
    if encoding not in formats:
        raise DatasetFormatError(
            f"{where}: image encoding {msg.encoding!r} not supported here; expected one of "
            f"{', '.join(formats)}"
        )
    kind, channels = formats[encoding]
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    check_image_size(width, height, where, DatasetFormatError)
    row_bytes = width * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < row_bytes or data.size < step * height:
        raise DatasetFormatError(
            f"{where}: {msg.encoding} image {width}x{height} with step {step} needs "
            f"{max(step, row_bytes) * height} bytes, the message has {data.size}"
        )
    rows = np.ascontiguousarray(data[: step * height].reshape(height, step)[:, :row_bytes])
    image = rows.view(dtype).reshape((height, width, channels) if channels > 1 else (height, width))
    return image.astype(dtype.newbyteorder("="), copy=False)


def _decode_compressed(msg: Any, where: str) -> np.ndarray:
    """A sensor_msgs/CompressedImage (jpeg, png) -> its decoded array (BGR when colour)."""
    if "compresseddepth" in str(msg.format).lower():
        raise DatasetFormatError(
            f"{where}: compressedDepth images are not supported; record depth as a raw "
            f"sensor_msgs/Image (16UC1 or 32FC1)"
        )
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    header_size = image_header_size(data[:HEADER_BYTES].tobytes())
    if header_size is not None:
        check_image_size(*header_size, where, DatasetFormatError)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameReadError(f"{where}: CompressedImage ({msg.format!r}) does not decode")
    return image


def rgb_from_message(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """A colour image message -> (H, W, 3) uint8 RGB."""
    if msgtype == _COMPRESSED:
        image = _decode_compressed(msg, where)
        if image.dtype != np.uint8:
            raise DatasetFormatError(f"{where}: compressed colour image is not 8-bit")
        channels = 1 if image.ndim == 2 else image.shape[2]
        to_rgb = {1: cv2.COLOR_GRAY2RGB, 3: cv2.COLOR_BGR2RGB, 4: cv2.COLOR_BGRA2RGB}
        if channels not in to_rgb:
            raise DatasetFormatError(f"{where}: compressed colour image has {channels} channels")
        return cv2.cvtColor(image, to_rgb[channels])
    image = _image_array(msg, where, _COLOUR_FORMATS)
    code = _COLOUR_TO_RGB[str(msg.encoding).lower()]
    return image if code is None else cv2.cvtColor(image, code)


def depth_from_message(msg: Any, msgtype: str, camera: CameraConfig, where: str) -> np.ndarray:
    """A depth image message -> (H, W) float32 metres, 0 where invalid (see the module
    docstring for the encodings)."""
    if msgtype == _COMPRESSED:
        raw = _decode_compressed(msg, where)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetFormatError(
                f"{where}: compressed depth must be a 16-bit single-channel PNG"
            )
    else:
        raw = _image_array(msg, where, _DEPTH_FORMATS)
    check_depth_size(where, raw, camera)
    if raw.dtype == np.uint16:
        depth_m = depth_m_from_raw(raw, camera)
        check_depth_units(depth_m, where, MAX_RANGE_M, camera.depth_scale)
        return depth_m
    depth_m = clean_depth(raw.astype(np.float32), raw.shape, where)  # 32FC1: metres already
    check_depth_units(depth_m, where, MAX_RANGE_M)
    return depth_m


def camera_from_info(msg: Any, camera: CameraConfig, where: str) -> CameraConfig:
    """`camera` with fx fy cx cy, size and distortion from a sensor_msgs/CameraInfo (ROS 1
    names K, D or ROS 2 names k, d); depth scale and invalid values stay."""
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(-1)
    D = np.asarray(msg.d if hasattr(msg, "d") else msg.D, dtype=np.float64).reshape(-1)
    if K.size != 9 or not (K[0] > 0 and K[4] > 0):
        raise DatasetFormatError(
            f"{where}: camera_info holds no intrinsics (K = {K.tolist()}); set "
            f"dataset.bag.intrinsics to 'config' to take them from the camera config"
        )
    model = str(msg.distortion_model)
    if np.any(D != 0) and model not in ("plumb_bob", "rational_polynomial"):
        raise DatasetFormatError(
            f"{where}: camera_info distortion model {model!r} is not supported (expected "
            f"plumb_bob or rational_polynomial)"
        )
    try:
        return dataclasses.replace(
            camera,
            fx=float(K[0]),
            fy=float(K[4]),
            cx=float(K[2]),
            cy=float(K[5]),
            width=int(msg.width),
            height=int(msg.height),
            distortion=tuple(float(v) for v in D) if np.any(D != 0) else (),
        )
    except ConfigError as exc:
        raise DatasetFormatError(f"{where}: camera_info: {exc}") from None


@dataclass
class _TfEdge:
    """Samples of one tf transform T_parent_child."""

    parent: str
    stamps: list[float]
    t_xyz: list[tuple[float, float, float]]
    quat_xyzw: list[tuple[float, float, float, float]]
    static: bool = False

    def poses_at(self, times: np.ndarray) -> np.ndarray:
        """(N, 4, 4) T_parent_child at `times` [s]: constant when static or sampled once,
        else interpolated (translation linearly, rotation by slerp), held at the ends."""
        stamps, order = np.unique(np.asarray(self.stamps), return_index=True)
        t_xyz = np.asarray(self.t_xyz)[order]
        quat = np.asarray(self.quat_xyzw)[order]
        if self.static or len(stamps) == 1:
            return np.repeat(pose_from_quat(t_xyz[-1], quat[-1])[None], len(times), axis=0)
        clamped = np.clip(times, stamps[0], stamps[-1])
        t = np.stack([np.interp(clamped, stamps, t_xyz[:, k]) for k in range(3)], axis=1)
        q = Slerp(stamps, Rotation.from_quat(quat))(clamped).as_quat()
        return pose_from_quat(t, q)


def _frame_name(name: str) -> str:
    """tf frame ids with and without tf1's leading slash are the same frame."""
    return str(name).lstrip("/")


def groundtruth_from_tf(
    edges: dict[str, _TfEdge], world_frame: str, camera_frame: str, where: str
) -> Trajectory | None:
    """T_world_cam along the tf chain world -> ... -> camera, sampled at the stamps of the
    chain's most often published moving transform (the motion capture); None when the
    frames are not connected or nothing on the chain moves."""
    chain: list[_TfEdge] = []
    frame = camera_frame
    while frame != world_frame and frame in edges:
        chain.append(edges[frame])
        frame = edges[frame].parent
        if len(chain) > len(edges):
            raise DatasetFormatError(f"{where}: the /tf tree has a cycle through {frame!r}")
    if not chain or (world_frame and frame != world_frame):
        return None
    moving = [e for e in chain if not e.static and len(set(e.stamps)) > 1]
    if not moving:
        log.info("%s: nothing moves on the /tf chain to %s: no ground truth", where, camera_frame)
        return None
    times = np.unique(np.asarray(max(moving, key=lambda e: len(e.stamps)).stamps))
    T_world_cam = np.tile(np.eye(4), (len(times), 1, 1))
    for edge in reversed(chain):  # from the world down to the camera
        T_world_cam = T_world_cam @ edge.poses_at(times)
    return Trajectory(timestamps=times, T_world_cam=T_world_cam)


def groundtruth_file_candidates(bag: Path) -> list[Path]:
    """TUM trajectory files that hold a bag's ground truth, in order of preference:
    `<name>-groundtruth.txt` beside it (TUM's naming), then `groundtruth.txt` in the bag
    folder (ROS 2) or beside the bag file (ROS 1)."""
    name = bag.stem if bag.is_file() else bag.name
    inside = bag / "groundtruth.txt" if bag.is_dir() else bag.parent / "groundtruth.txt"
    return [bag.parent / f"{name}-groundtruth.txt", inside]


class RosBagDataset(FrameSequence):
    """An RGB-D sequence in a ROS 1 or ROS 2 bag; frames are read from the bag on access.
    Close it (or use it as a context manager) to release the file; dropping it does too."""

    def __init__(
        self, path: str | Path, camera: CameraConfig, config: DatasetConfig | None = None
    ) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.root = Path(path)
        self.config = config or DatasetConfig()
        bag = self.config.bag
        if not self.root.exists():
            raise DatasetFormatError(f"{self.root}: bag not found")
        try:
            # ROS 2 bags before Iron store no message definitions: read those with Humble's.
            reader = AnyReader([self.root], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except (AnyReaderError, FileNotFoundError, OSError) as exc:
            raise DatasetFormatError(f"{self.root}: not a readable ROS bag ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - random bytes fail anywhere in rosbags
            reason = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            raise DatasetFormatError(f"{self.root}: not a readable ROS bag ({reason})") from None
        self._reader = reader
        self._lock = threading.Lock()
        self._close = weakref.finalize(self, _close_reader, reader)

        rgb_conns = self._connections(bag.rgb_topic, "colour images", "rgb_topic")
        depth_conns = self._connections(bag.depth_topic, "depth images", "depth_topic")
        info_conns: list[Any] = []
        if bag.intrinsics == "camera_info":
            info_conns = self._connections(
                bag.camera_info_topic, "camera_info", "camera_info_topic"
            )
        self.groundtruth_path: Path | None = None
        if bag.groundtruth in ("auto", "file"):
            self.groundtruth_path = next(
                (p for p in groundtruth_file_candidates(self.root) if p.is_file()), None
            )
            if bag.groundtruth == "file" and self.groundtruth_path is None:
                names = ", ".join(str(p) for p in groundtruth_file_candidates(self.root))
                raise DatasetFormatError(f"{self.root}: no ground-truth file ({names})")
        read_tf = bag.groundtruth == "tf" or (
            bag.groundtruth == "auto" and self.groundtruth_path is None
        )
        tf_conns = [c for c in reader.connections if c.topic in TF_TOPICS] if read_tf else []
        if bag.groundtruth == "tf" and not tf_conns:
            raise DatasetFormatError(f"{self.root}: no /tf topic for the ground truth")

        try:
            rgb, depth, info_msg, edges, frame_id = self._index(
                rgb_conns, depth_conns, info_conns, tf_conns
            )
        except PlaneSlamError:
            raise
        except Exception as exc:  # noqa: BLE001 - rosbags' reader errors have no common base
            raise DatasetFormatError(f"{self.root}: damaged bag ({exc})") from None
        if bag.intrinsics == "camera_info":
            if info_msg is None:
                raise DatasetFormatError(f"{self.root}: topic {bag.camera_info_topic} is empty")
            camera = camera_from_info(info_msg, camera, f"{self.root} {bag.camera_info_topic}")
        self.camera = camera
        self.timestamps, self._rgb_refs, self._depth_refs = self._pair(rgb, depth)
        self.groundtruth: Trajectory | None = None
        if self.groundtruth_path is not None:
            self.groundtruth = read_tum(self.groundtruth_path)
        elif read_tf:
            world = _frame_name(bag.tf_world_frame)
            cam_frame = _frame_name(bag.tf_camera_frame or frame_id)
            self.groundtruth = groundtruth_from_tf(edges, world, cam_frame, str(self.root))
            if self.groundtruth is None and bag.groundtruth == "tf":
                raise DatasetFormatError(
                    f"{self.root}: no moving /tf chain from {world or 'the tf root'} to "
                    f"{cam_frame!r}; frames with a parent: {', '.join(sorted(edges)) or 'none'}"
                )
        self._undistort = Undistortion(self.camera, self.config.undistort)
        log.info(
            "%s: %d frames, ground truth %s",
            self.root,
            len(self),
            self.groundtruth_path or ("from /tf" if self.groundtruth is not None else "none"),
        )

    def _connections(self, topic: str, what: str, key: str) -> list[Any]:
        conns = [c for c in self._reader.connections if c.topic == topic]
        if not conns:
            topics = ", ".join(sorted({c.topic for c in self._reader.connections})) or "none"
            raise DatasetFormatError(
                f"{self.root}: no topic {topic!r} ({what}); choose one with dataset.bag.{key}; "
                f"topics in the bag: {topics}"
            )
        return conns

    def _index(
        self,
        rgb_conns: list[Any],
        depth_conns: list[Any],
        info_conns: list[Any],
        tf_conns: list[Any],
    ) -> tuple[
        list[tuple[float, _MessageRef]],
        list[tuple[float, _MessageRef]],
        Any,
        dict[str, _TfEdge],
        str,
    ]:
        """One pass over the bag: (header stamp, reference) of every colour and depth image,
        the first camera_info, the tf edges, and the colour images' frame_id."""
        reader = self._reader
        rgb_ids = {c.id for c in rgb_conns}
        info_ids = {c.id for c in info_conns}
        tf_ids = {c.id for c in tf_conns}
        tf_static = {c.id for c in tf_conns if c.topic == "/tf_static"}
        rgb: list[tuple[float, _MessageRef]] = []
        depth: list[tuple[float, _MessageRef]] = []
        seen: dict[tuple[int, int], int] = {}
        info_msg: Any = None
        frame_id = ""
        edges: dict[str, _TfEdge] = {}
        conns = [*rgb_conns, *depth_conns, *info_conns, *tf_conns]
        for conn, bag_time, raw in reader.messages(connections=conns):
            if conn.id in info_ids:
                if info_msg is None:
                    info_msg = reader.deserialize(raw, conn.msgtype)
                continue
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn.id in tf_ids:
                _add_transforms(edges, msg, conn.id in tf_static)
                continue
            key = (conn.id, bag_time)
            ref = _MessageRef(conn, bag_time, seen.get(key, 0))
            seen[key] = ref.ordinal + 1
            if conn.id in rgb_ids:
                rgb.append((stamp_seconds(msg.header.stamp), ref))
                frame_id = frame_id or str(msg.header.frame_id)
            else:
                depth.append((stamp_seconds(msg.header.stamp), ref))
        return rgb, depth, info_msg, edges, frame_id

    def _pair(
        self, rgb: list[tuple[float, _MessageRef]], depth: list[tuple[float, _MessageRef]]
    ) -> tuple[np.ndarray, list[_MessageRef], list[_MessageRef]]:
        bag, max_dt = self.config.bag, self.config.max_time_difference_s
        for items, topic in ((rgb, bag.rgb_topic), (depth, bag.depth_topic)):
            if not items:
                raise DatasetFormatError(f"{self.root}: topic {topic} has no messages")
        rgb.sort(key=lambda item: item[0])
        depth.sort(key=lambda item: item[0])
        rgb_t = np.array([t for t, _ in rgb])
        depth_t = np.array([t for t, _ in depth])
        pairs = associate_timestamps(rgb_t, depth_t, max_dt)
        if not pairs:
            gap = float(np.min(np.abs(rgb_t[:, None] - depth_t[None, :])))
            raise AssociationError(
                f"{self.root}: no colour/depth pairs within {max_dt} s (closest pair is "
                f"{gap:.3f} s apart; raise dataset.max_time_difference_s?)"
            )
        return (
            rgb_t[[i for i, _ in pairs]],
            [rgb[i][1] for i, _ in pairs],
            [depth[j][1] for _, j in pairs],
        )

    def _read(self, ref: _MessageRef) -> tuple[Any, str]:
        """The deserialised message `ref` points at, and its type; FrameReadError when it
        cannot be read again (a damaged bag)."""
        if not self._close.alive:
            raise DatasetFormatError(f"{self.root}: the bag was closed")
        where = f"{self.root}: message at {ref.bag_time_ns} ns on {ref.connection.topic}"
        try:
            with self._lock:
                found = self._reader.messages(
                    connections=[ref.connection], start=ref.bag_time_ns, stop=ref.bag_time_ns + 1
                )
                for k, (conn, _, raw) in enumerate(found):
                    if k == ref.ordinal:
                        return self._reader.deserialize(raw, conn.msgtype), conn.msgtype
        except Exception as exc:  # noqa: BLE001 - rosbags' reader errors have no common base
            raise FrameReadError(f"{where}: cannot be read ({exc})") from None
        raise FrameReadError(f"{where}: not found on reading it again")

    def _frame(self, index: int) -> Frame:
        where = f"{self.root} frame {index}"
        rgb_msg, rgb_type = self._read(self._rgb_refs[index])
        depth_msg, depth_type = self._read(self._depth_refs[index])
        rgb = rgb_from_message(rgb_msg, rgb_type, f"{where} ({self.config.bag.rgb_topic})")
        depth_m = depth_from_message(
            depth_msg, depth_type, self.camera, f"{where} ({self.config.bag.depth_topic})"
        )
        check_rgb_matches_depth(where, rgb, depth_m)
        rgb, depth_m = self._undistort(rgb, depth_m)
        return Frame(index=index, timestamp=float(self.timestamps[index]), rgb=rgb, depth_m=depth_m)

    def close(self) -> None:
        """Release the bag file; reading a frame afterwards fails."""
        self._close()

    def __enter__(self) -> RosBagDataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _close_reader(reader: Any) -> None:
    with suppress(Exception):
        reader.close()


def _add_transforms(edges: dict[str, _TfEdge], msg: Any, static: bool) -> None:
    """Add the transforms of one tf message (tf/tfMessage or tf2_msgs/TFMessage)."""
    for tf in msg.transforms:
        child, parent = _frame_name(tf.child_frame_id), _frame_name(tf.header.frame_id)
        edge = edges.get(child)
        if edge is None:
            edge = edges[child] = _TfEdge(parent, [], [], [], static)
        elif edge.parent != parent:
            log.debug(
                "tf frame %s has parents %s and %s: keeping the first", child, edge.parent, parent
            )
            continue
        t, q = tf.transform.translation, tf.transform.rotation
        edge.stamps.append(stamp_seconds(tf.header.stamp))
        edge.t_xyz.append((float(t.x), float(t.y), float(t.z)))
        edge.quat_xyzw.append((float(q.x), float(q.y), float(q.z), float(q.w)))
