"""Writes a TUM-layout folder into a ROS 1 or ROS 2 bag with rosbags' writers, the way TUM
and robots record them: colour (rgb8), depth (16UC1 or 32FC1 metres), camera_info, and
optionally the ground truth as a /tf chain world -> kinect (moving) -> camera (static)."""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.geometry import invert_pose, pose_from_quat, quat_from_pose
from planeslam.io.trajectory import read_tum

CAMERA_FRAME = "/openni_rgb_optical_frame"
"""The colour images' frame_id, with tf1's leading slash as in TUM's bags."""
T_KINECT_CAM = pose_from_quat(np.array([0.02, -0.05, 0.1]), np.array([0.5, -0.5, 0.5, -0.5]))
"""A static mounting of the camera on the tracked body (T_kinect_cam)."""
DEPTH_DELAY_NS = 3_000_000
"""Depth header stamps trail the colour ones by 3 ms (pairing by stamps is exercised)."""


@dataclass(frozen=True)
class BagSpec:
    """What to write."""

    ros: Literal[1, 2] = 1
    storage: Literal["sqlite3", "mcap"] = "sqlite3"
    """ROS 2 storage plugin."""
    depth_encoding: Literal["16UC1", "32FC1"] = "16UC1"
    tf: bool = False
    """Write the ground truth as /tf (moving) + /tf_static (camera mount)."""
    rgb_topic: str = "/camera/rgb/image_color"
    depth_topic: str = "/camera/depth/image"
    info_topic: str = "/camera/rgb/camera_info"


def stamp_ns(text: str) -> int:
    """A TUM time stamp as written ('1305031102.1658') -> integer nanoseconds, exactly."""
    return int(Decimal(text) * 1_000_000_000)


def _time(ts: Any, ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts: Any, ns: int, frame_id: str) -> Any:
    Header = ts.types["std_msgs/msg/Header"]
    fields = Header.__dataclass_fields__
    extra = {"seq": 0} if "seq" in fields else {}
    return Header(stamp=_time(ts, ns), frame_id=frame_id, **extra)


def _case(ts: Any, msgtype: str, **values: Any) -> Any:
    """A message whose fields are given in ROS 2 (lower) case; ROS 1 names K, D, R, P."""
    cls = ts.types[msgtype]
    names = set(cls.__dataclass_fields__)
    return cls(**{(k if k in names else k.upper()): v for k, v in values.items()})


def _image(ts: Any, ns: int, array: np.ndarray, encoding: str) -> Any:
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
    return ts.types["sensor_msgs/msg/Image"](
        header=_header(ts, ns, CAMERA_FRAME),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=data.size // height,
        data=data,
    )


def camera_info(ts: Any, ns: int, camera: CameraConfig) -> Any:
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    K = camera.K.reshape(-1)
    P = np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1)
    return _case(
        ts,
        "sensor_msgs/msg/CameraInfo",
        header=_header(ts, ns, CAMERA_FRAME),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=np.asarray(camera.distortion or (0.0,) * 5, dtype=np.float64),
        k=K,
        r=np.eye(3).reshape(-1),
        p=P,
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def _tf_message(ts: Any, msgtype: str, ns: int, parent: str, child: str, T: np.ndarray) -> Any:
    t, q = quat_from_pose(T)
    transform = ts.types["geometry_msgs/msg/Transform"](
        translation=ts.types["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
        rotation=ts.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    stamped = ts.types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, ns, parent), child_frame_id=child, transform=transform
    )
    return ts.types[msgtype](transforms=[stamped])


def write_bag(folder: Path, dest: Path, camera: CameraConfig, spec: BagSpec) -> Path:
    """Write the frames of TUM folder `folder` (its associations.txt) into bag `dest`
    (a .bag file for ROS 1, a folder for ROS 2); returns `dest`."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    rows = [
        line.split()
        for line in (folder / "associations.txt").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    if spec.ros == 1:
        ts = get_typestore(Stores.ROS1_NOETIC)
        tf_type = "tf/msg/tfMessage"  # what TUM's 2011 bags carry
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", tf_type))
    else:
        ts = get_typestore(Stores.ROS2_HUMBLE)
        tf_type = "tf2_msgs/msg/TFMessage"
    messages: list[tuple[str, str, int, Any]] = []  # topic, type, bag time, message
    for t_rgb, rgb_name, _, depth_name in rows:
        ns = stamp_ns(t_rgb)
        rgb = cv2.cvtColor(cv2.imread(str(folder / rgb_name), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        raw = cv2.imread(str(folder / depth_name), cv2.IMREAD_UNCHANGED)
        if spec.depth_encoding == "16UC1":
            depth = _image(ts, ns + DEPTH_DELAY_NS, raw, "16UC1")
        else:  # metres computed as the folder reader does
            depth = _image(
                ts, ns + DEPTH_DELAY_NS, raw.astype(np.float32) / np.float32(5000), "32FC1"
            )
        receive = ns + 20_000_000  # recorded 20 ms after capture
        messages.append(
            (spec.rgb_topic, "sensor_msgs/msg/Image", receive, _image(ts, ns, rgb, "rgb8"))
        )
        messages.append((spec.depth_topic, "sensor_msgs/msg/Image", receive + 1, depth))
        messages.append(
            (spec.info_topic, "sensor_msgs/msg/CameraInfo", receive, camera_info(ts, ns, camera))
        )
    if spec.tf:
        gt = read_tum(folder / "groundtruth.txt")  # sorted by time, as the rows below
        gt_stamps = sorted(
            (
                line.split()[0]
                for line in (folder / "groundtruth.txt").read_text().splitlines()
                if line.strip() and not line.startswith("#")
            ),
            key=Decimal,
        )
        first = stamp_ns(rows[0][0])
        messages.append(
            (
                "/tf_static",
                tf_type,
                first,
                _tf_message(ts, tf_type, first, "/kinect", CAMERA_FRAME, T_KINECT_CAM),
            )
        )
        T_kinect_cam_inv = invert_pose(T_KINECT_CAM)
        for text, T_world_cam in zip(gt_stamps, gt.T_world_cam, strict=True):
            ns = stamp_ns(text)
            msg = _tf_message(ts, tf_type, ns, "/world", "/kinect", T_world_cam @ T_kinect_cam_inv)
            messages.append(("/tf", tf_type, ns + 1_000_000, msg))
    messages.sort(key=lambda m: m[2])
    types = {topic: msgtype for topic, msgtype, _, _ in messages}
    if spec.ros == 1:
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(dest) as writer:
            conns = {t: writer.add_connection(t, m, typestore=ts) for t, m in types.items()}
            for topic, msgtype, t, msg in messages:
                writer.write(conns[topic], t, ts.serialize_ros1(msg, msgtype))
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if spec.storage == "mcap" else StoragePlugin.SQLITE3
        with Writer2(dest, version=9, storage_plugin=plugin) as writer:
            conns = {t: writer.add_connection(t, m, typestore=ts) for t, m in types.items()}
            for topic, msgtype, t, msg in messages:
                writer.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))
    return dest
