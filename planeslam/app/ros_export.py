"""A run's results as a ROS 2 bag (`planeslam run --out-bag`), written with rosbags, to open
in Foxglove or RViz beside the input bag:

- /tf (tf2_msgs/TFMessage): `WORLD_FRAME` -> `CAMERA_FRAME` at every pose of the
  trajectory, at its timestamp;
- /planeslam/path (nav_msgs/Path): the whole trajectory;
- /planeslam/planes (visualization_msgs/MarkerArray): each map plane's polygon as a
  TRIANGLE_LIST coloured by object, marker id = map.json's plane id;
- /planeslam/objects (visualization_msgs/MarkerArray): each object's class and size as a
  TEXT_VIEW_FACING label at its planes' area-weighted centre, marker id = map.json's
  object id.

The path and the markers are written at the first and at the last timestamp, so a player
shows the final map from the start. World frame as map.json's, metres.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from planeslam.core.errors import ConfigError
from planeslam.core.geometry import quat_from_pose
from planeslam.io.trajectory import Trajectory
from planeslam.mapping.world_map import Map

WORLD_FRAME = "world"
CAMERA_FRAME = "planeslam_camera"
TOPICS = {
    "/tf": "tf2_msgs/msg/TFMessage",
    "/planeslam/path": "nav_msgs/msg/Path",
    "/planeslam/planes": "visualization_msgs/msg/MarkerArray",
    "/planeslam/objects": "visualization_msgs/msg/MarkerArray",
}
"""Topic -> message type of the bag."""


def check_bag_destination(dest: str | Path) -> Path:
    """`dest` as a Path; ConfigError when something is already there (a bag is a folder
    rosbags will not write over)."""
    dest = Path(dest)
    if dest.exists():
        raise ConfigError(f"--out-bag {dest}: already exists; expected a new folder for the bag")
    return dest


def write_results_bag(
    dest: str | Path,
    trajectory: Trajectory,
    world_map: Map,
    storage: Literal["mcap", "sqlite3"] = "mcap",
) -> Path:
    """Write the trajectory (timestamps [s], T_world_cam) and the map's planes and objects
    into a new ROS 2 bag folder `dest` (module docstring); returns `dest`."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    dest = check_bag_destination(dest)
    if len(trajectory) == 0:
        raise ConfigError("no poses to write into a bag: the run tracked no frame")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    stamps = [int(round(t * 1e9)) for t in trajectory.timestamps]
    messages: list[tuple[str, int, Any]] = [
        ("/tf", ns, _tf(ts, ns, T)) for ns, T in zip(stamps, trajectory.T_world_cam, strict=True)
    ]
    path = _path(ts, stamps, trajectory.T_world_cam)
    planes, objects = _plane_markers(ts, world_map), _object_markers(ts, world_map)
    for ns in sorted({stamps[0], stamps[-1]}):
        messages += [
            ("/planeslam/path", ns, path),
            ("/planeslam/planes", ns, planes),
            ("/planeslam/objects", ns, objects),
        ]
    messages.sort(key=lambda m: m[1])
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(dest, version=9, storage_plugin=plugin) as writer:
        connections = {
            topic: writer.add_connection(topic, msgtype, typestore=ts)
            for topic, msgtype in TOPICS.items()
        }
        for topic, ns, msg in messages:
            writer.write(connections[topic], ns, ts.serialize_cdr(msg, TOPICS[topic]))
    return dest


def _header(ts: Any, ns: int, frame_id: str = WORLD_FRAME) -> Any:
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def _point(ts: Any, p: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _pose(ts: Any, T: np.ndarray) -> Any:
    t, q = quat_from_pose(np.asarray(T, dtype=np.float64))
    quaternion = ts.types["geometry_msgs/msg/Quaternion"](
        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
    )
    return ts.types["geometry_msgs/msg/Pose"](position=_point(ts, t), orientation=quaternion)


def _tf(ts: Any, ns: int, T_world_cam: np.ndarray) -> Any:
    pose = _pose(ts, T_world_cam)
    p = pose.position
    transform = ts.types["geometry_msgs/msg/Transform"](
        translation=ts.types["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=p.z),
        rotation=pose.orientation,
    )
    stamped = ts.types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, ns), child_frame_id=CAMERA_FRAME, transform=transform
    )
    return ts.types["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def _path(ts: Any, stamps: list[int], T_world_cam: np.ndarray) -> Any:
    PoseStamped = ts.types["geometry_msgs/msg/PoseStamped"]
    poses = [
        PoseStamped(header=_header(ts, ns), pose=_pose(ts, T))
        for ns, T in zip(stamps, T_world_cam, strict=True)
    ]
    return ts.types["nav_msgs/msg/Path"](header=_header(ts, stamps[-1]), poses=poses)


def _marker(ts: Any, ns: str, marker_id: int, kind: str, **fields: Any) -> Any:
    """A visualization_msgs/Marker in the world frame (stamp 0: the latest transform) with
    the defaults filled in."""
    Marker = ts.types["visualization_msgs/msg/Marker"]
    values: dict[str, Any] = {
        "header": _header(ts, 0),
        "ns": ns,
        "id": int(marker_id),
        "type": getattr(Marker, kind),
        "action": Marker.ADD,
        "pose": _pose(ts, np.eye(4)),
        "scale": ts.types["geometry_msgs/msg/Vector3"](x=1.0, y=1.0, z=1.0),
        "color": _color(ts, np.array([200, 200, 200])),
        "lifetime": ts.types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        "frame_locked": False,
        "points": [],
        "colors": [],
        "texture_resource": "",
        "texture": ts.types["sensor_msgs/msg/CompressedImage"](
            header=_header(ts, 0), format="", data=np.zeros(0, dtype=np.uint8)
        ),
        "uv_coordinates": [],
        "text": "",
        "mesh_resource": "",
        "mesh_file": ts.types["visualization_msgs/msg/MeshFile"](
            filename="", data=np.zeros(0, dtype=np.uint8)
        ),
        "mesh_use_embedded_materials": False,
    }
    values.update(fields)
    return Marker(**values)


def _color(ts: Any, rgb: np.ndarray, alpha: float = 1.0) -> Any:
    r, g, b = (float(c) / 255.0 for c in rgb)
    return ts.types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=alpha)


def _plane_markers(ts: Any, world_map: Map) -> Any:
    """One TRIANGLE_LIST per plane (its outline as a fan), coloured by object."""
    colors = world_map.plane_colors()
    markers = []
    for plane_id, plane in world_map.planes.items():
        ring = np.asarray(plane.outline, dtype=np.float64)
        if len(ring) < 3:
            continue
        centre = ring.mean(axis=0)
        following = np.roll(ring, -1, axis=0)
        corners = np.stack([np.broadcast_to(centre, ring.shape), ring, following], axis=1)
        markers.append(
            _marker(
                ts,
                "planes",
                plane_id,
                "TRIANGLE_LIST",
                points=[_point(ts, p) for p in corners.reshape(-1, 3)],
                color=_color(ts, colors[plane_id], 0.8),
            )
        )
    return ts.types["visualization_msgs/msg/MarkerArray"](markers=markers)


def _object_markers(ts: Any, world_map: Map) -> Any:
    """One text label per object: class and size [m] at its planes' area-weighted centre."""
    planes = world_map.planes
    markers = []
    for obj in world_map.objects:
        own = [planes[p] for p in obj.planes if p in planes]
        if not own:
            continue
        areas = np.array([p.area_m2 for p in own]) + 1e-9
        centre = np.average([p.centroid for p in own], axis=0, weights=areas)
        size = " x ".join(f"{s:.2f}" for s in obj.size_m)
        pose = np.eye(4)
        pose[:3, 3] = centre
        markers.append(
            _marker(
                ts,
                "objects",
                obj.id,
                "TEXT_VIEW_FACING",
                pose=_pose(ts, pose),
                scale=ts.types["geometry_msgs/msg/Vector3"](x=0.1, y=0.1, z=0.1),
                color=_color(ts, np.array([255, 255, 255])),
                text=f"{obj.cls} {size} m",
            )
        )
    return ts.types["visualization_msgs/msg/MarkerArray"](markers=markers)
