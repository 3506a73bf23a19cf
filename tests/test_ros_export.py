"""`planeslam run --out-bag`: the results as a ROS 2 bag, read back with rosbags: /tf at
every pose, the path, plane markers with map.json's plane ids, object labels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from planeslam.app.runner import run_sequence
from planeslam.core.errors import ConfigError
from planeslam.core.geometry import pose_from_quat
from planeslam.io.trajectory import read_tum
from planeslam.sim.sequence import synthesize

pytestmark = pytest.mark.unit


def read_bag(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    messages: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for connection, ns, raw in reader.messages():
            messages.setdefault(connection.topic, []).append(
                (ns, reader.deserialize(raw, connection.msgtype))
            )
    return messages


@pytest.mark.integration
def test_results_bag_holds_tf_path_and_markers(tmp_path: Path) -> None:
    seq = synthesize("box_room_circle", tmp_path / "seq", seed=3).out_dir
    out, bag = tmp_path / "run", tmp_path / "bag"
    run_sequence(seq, out, max_frames=10, out_bag=bag)
    messages = read_bag(bag)
    trajectory = read_tum(out / "trajectory.txt")
    tf = messages["/tf"]
    assert len(tf) == len(trajectory)
    for (ns, msg), t, T in zip(tf, trajectory.timestamps, trajectory.T_world_cam, strict=True):
        (stamped,) = msg.transforms
        assert abs(ns * 1e-9 - t) < 1e-6 and stamped.header.frame_id == "world"
        r, p = stamped.transform.rotation, stamped.transform.translation
        T_bag = pose_from_quat(np.array([p.x, p.y, p.z]), np.array([r.x, r.y, r.z, r.w]))
        np.testing.assert_allclose(T_bag, T, atol=1e-6)
    _, path = messages["/planeslam/path"][-1]
    assert len(path.poses) == len(trajectory)
    data = json.loads((out / "map.json").read_text())
    _, planes = messages["/planeslam/planes"][-1]
    drawn = {p["id"] for p in data["planes"] if len(p["outline"]) >= 3}
    assert {m.id for m in planes.markers} == drawn
    assert all(len(m.points) % 3 == 0 and m.points for m in planes.markers)
    _, objects = messages["/planeslam/objects"][-1]
    assert {m.id for m in objects.markers} == {o["id"] for o in data["objects"]}
    assert any(m.text.startswith("box ") for m in objects.markers), [
        m.text for m in objects.markers
    ]
    with pytest.raises(ConfigError, match="already exists"):
        run_sequence(seq, tmp_path / "again", max_frames=2, out_bag=bag)
