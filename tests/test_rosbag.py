"""ROS bags as datasets: the shared TUM clip written into ROS 1 and ROS 2 (sqlite3, mcap)
bags reads back frame for frame, with the intrinsics from camera_info and the ground truth
from a file beside the bag or the /tf chain; SLAM on the bags gives the folder's
trajectory; bad bags and options give one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from planeslam.config import load_config, resolve_config
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import DatasetFormatError, FrameReadError
from planeslam.core.geometry import pose_from_quat
from planeslam.io.config import BagConfig, DatasetConfig
from planeslam.io.dataset import TumDataset
from planeslam.io.rosbag import (
    RosBagDataset,
    _TfEdge,
    camera_from_info,
    depth_from_message,
    groundtruth_from_tf,
    rgb_from_message,
)
from planeslam.io.sequence import DatasetKind, dataset_kind, open_dataset
from planeslam.io.trajectory import Trajectory, read_tum, write_tum
from tests.conftest import shared_sequence
from tests.rosbag_writer import BagSpec, write_bag

pytestmark = pytest.mark.unit

CLIP = "tum_fr1_xyz_10f"
FR1 = load_config("tum_fr1").camera
BAGS = {
    "ros1_16UC1_file": BagSpec(ros=1, depth_encoding="16UC1"),
    "ros1_tf": BagSpec(ros=1, depth_encoding="16UC1", tf=True),
    "ros2_sqlite3_32FC1_tf": BagSpec(ros=2, storage="sqlite3", depth_encoding="32FC1", tf=True),
    "ros2_mcap_16UC1_tf": BagSpec(ros=2, storage="mcap", depth_encoding="16UC1", tf=True),
}


@pytest.fixture(scope="module")
def clip() -> TumDataset:
    path = shared_sequence(CLIP)
    cfg = resolve_config(path)
    return TumDataset(path, cfg.camera, cfg.dataset)


def make_bag(clip: TumDataset, folder: Path, name: str, spec: BagSpec) -> Path:
    """The clip as a bag named `name` (no preset in the name: intrinsics come from
    camera_info); a ROS 1 bag without /tf gets TUM's `<stem>-groundtruth.txt` beside it."""
    dest = folder / (f"{name}.bag" if spec.ros == 1 else name)
    write_bag(clip.root, dest, FR1, spec)
    if not spec.tf:
        shutil.copy(clip.root / "groundtruth.txt", folder / f"{name}-groundtruth.txt")
    return dest


@pytest.fixture(scope="module")
def bags(clip: TumDataset, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("bags")
    return {key: make_bag(clip, folder, key, spec) for key, spec in BAGS.items()}


def open_bag(path: Path, **bag: object) -> RosBagDataset:
    config = DatasetConfig(bag=BagConfig(**bag))  # type: ignore[arg-type]
    return RosBagDataset(path, CameraConfig(), config)


def test_dataset_kind(tmp_path: Path) -> None:
    (tmp_path / "x.bag").write_bytes(b"")
    (tmp_path / "ros2").mkdir()
    (tmp_path / "ros2" / "metadata.yaml").write_text("{}")
    (tmp_path / "ros2" / "x.mcap").write_bytes(b"")
    assert dataset_kind(tmp_path / "x.bag") is DatasetKind.ROS1_BAG
    assert dataset_kind(tmp_path / "ros2") is DatasetKind.ROS2_BAG
    assert dataset_kind(tmp_path) is DatasetKind.FOLDER
    with pytest.raises(DatasetFormatError, match="read as its folder"):
        dataset_kind(tmp_path / "ros2" / "x.mcap")
    with pytest.raises(DatasetFormatError, match="dataset not found"):
        dataset_kind(tmp_path / "nothing.bag")


@pytest.mark.data
@pytest.mark.parametrize("key", sorted(BAGS))
def test_bag_frames_equal_the_folder(clip: TumDataset, bags: dict[str, Path], key: str) -> None:
    bag = open_dataset(bags[key], CameraConfig(), DatasetConfig())
    assert isinstance(bag, RosBagDataset)
    # camera_info replaced the defaults' intrinsics; the depth scale stays the config's
    assert bag.camera == FR1
    np.testing.assert_array_equal(bag.timestamps, clip.timestamps)
    for i in range(len(clip)):
        a, b = clip[i], bag[i]
        assert b.index == i and b.timestamp == a.timestamp
        np.testing.assert_array_equal(b.rgb, a.rgb)
        assert b.depth_m.dtype == np.float32
        np.testing.assert_array_equal(b.depth_m, a.depth_m)
    assert clip.groundtruth is not None and bag.groundtruth is not None
    np.testing.assert_array_equal(bag.groundtruth.timestamps, clip.groundtruth.timestamps)
    np.testing.assert_allclose(
        bag.groundtruth.T_world_cam, clip.groundtruth.T_world_cam, atol=1e-12
    )
    if BAGS[key].tf:
        assert bag.groundtruth_path is None  # from /tf
    else:
        assert bag.groundtruth_path == bags[key].parent / f"{key}-groundtruth.txt"
    bag.close()
    with pytest.raises(DatasetFormatError, match="the bag was closed"):
        bag[0]


@pytest.mark.data
def test_ros1_groundtruth_from_tf_when_asked_although_a_file_is_there(
    clip: TumDataset, bags: dict[str, Path], tmp_path: Path
) -> None:
    path = shutil.copy(bags["ros1_tf"], tmp_path / "rec.bag")
    wrong = read_tum(clip.root / "groundtruth.txt")
    shifted = np.array(wrong.T_world_cam)
    shifted[:, 0, 3] += 1.0
    write_tum(tmp_path / "rec-groundtruth.txt", Trajectory(wrong.timestamps, shifted))
    auto = open_bag(Path(path))
    assert auto.groundtruth_path == tmp_path / "rec-groundtruth.txt"  # the file wins in auto
    tf = open_bag(Path(path), groundtruth="tf")
    assert tf.groundtruth_path is None and tf.groundtruth is not None
    assert clip.groundtruth is not None
    np.testing.assert_allclose(tf.groundtruth.T_world_cam, clip.groundtruth.T_world_cam, atol=1e-12)
    assert open_bag(Path(path), groundtruth="none").groundtruth is None


@pytest.mark.data
def test_topics_intrinsics_and_missing_topics(bags: dict[str, Path], tmp_path: Path) -> None:
    path = bags["ros1_16UC1_file"]
    with pytest.raises(DatasetFormatError) as info:
        open_bag(path, rgb_topic="/camera/rgb/image_raw")
    message = str(info.value)
    assert "/camera/rgb/image_raw" in message and "dataset.bag.rgb_topic" in message
    assert "/camera/rgb/image_color" in message  # the bag's topics are listed
    # intrinsics from the config: the camera_info topic need not exist
    cfg = open_bag(path, intrinsics="config", camera_info_topic="/none")
    assert cfg.camera == CameraConfig()
    with pytest.raises(DatasetFormatError, match="no ground-truth file"):
        open_bag(bags["ros2_mcap_16UC1_tf"], groundtruth="file")
    with pytest.raises(DatasetFormatError, match="no /tf topic"):
        open_bag(path, groundtruth="tf")
    data = path.read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])  # a recording cut short
    with pytest.raises(DatasetFormatError, match=r"cut.bag: (not a readable ROS bag|damaged)"):
        open_dataset(tmp_path / "cut.bag", CameraConfig())
    with pytest.raises(DatasetFormatError, match="no moving /tf chain"):
        open_bag(bags["ros2_mcap_16UC1_tf"], groundtruth="tf", tf_camera_frame="elsewhere")


def test_not_a_bag(tmp_path: Path) -> None:
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V1.2\nnot really")
    with pytest.raises(DatasetFormatError, match="not a readable ROS bag"):
        open_dataset(tmp_path / "x.bag", CameraConfig())


def _image_msg(encoding: str, data: np.ndarray, bigendian: bool = False) -> SimpleNamespace:
    height, width = data.shape[:2]
    raw = np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    return SimpleNamespace(
        encoding=encoding,
        is_bigendian=int(bigendian),
        height=height,
        width=width,
        step=raw.size // height,
        data=raw,
    )


def test_depth_encodings_byte_order_and_errors() -> None:
    camera = CameraConfig(width=4, height=2, depth_scale=1000.0)
    raw = np.array([[1000, 2000, 0, 1500], [1200, 1300, 1400, 1600]], dtype=np.uint16)
    metres = raw.astype(np.float32) / 1000
    out = depth_from_message(_image_msg("16UC1", raw), "sensor_msgs/msg/Image", camera, "d")
    np.testing.assert_array_equal(out, metres)
    big = _image_msg("16UC1", raw.astype(">u2"), bigendian=True)
    np.testing.assert_array_equal(
        depth_from_message(big, "sensor_msgs/msg/Image", camera, "d"), metres
    )
    floats = metres.copy()
    floats[0, 2], floats[1, 0] = np.nan, -1.0  # no measurement in ROS: NaN; never negative
    out = depth_from_message(_image_msg("32FC1", floats), "sensor_msgs/msg/Image", camera, "d")
    assert out[0, 2] == 0 and out[1, 0] == 0 and out[0, 1] == np.float32(2.0)
    with pytest.raises(DatasetFormatError, match="encoding '8UC1' not supported"):
        depth_from_message(_image_msg("8UC1", raw.astype(np.uint8)), "x", camera, "d")
    short = _image_msg("16UC1", raw)
    short.data = short.data[:-2]
    with pytest.raises(DatasetFormatError, match="needs 16 bytes, the message has 14"):
        depth_from_message(short, "sensor_msgs/msg/Image", camera, "d")
    with pytest.raises(DatasetFormatError, match="depth is 4x2, the camera config says 640x480"):
        depth_from_message(_image_msg("16UC1", raw), "x", CameraConfig(), "d")


def test_camera_info_names_and_bad_intrinsics() -> None:
    ros1 = SimpleNamespace(
        K=np.array([500.0, 0, 320, 0, 510, 240, 0, 0, 1]),
        D=np.zeros(5),
        distortion_model="plumb_bob",
        width=640,
        height=480,
    )
    cam = camera_from_info(ros1, CameraConfig(depth_scale=1000.0), "info")
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (500, 510, 320, 240, 1000)
    assert cam.distortion == ()
    ros2 = SimpleNamespace(
        k=np.zeros(9), d=np.zeros(5), distortion_model="plumb_bob", width=640, height=480
    )
    with pytest.raises(DatasetFormatError, match="camera_info holds no intrinsics"):
        camera_from_info(ros2, CameraConfig(), "info")
    fisheye = SimpleNamespace(**{**vars(ros1), "D": np.ones(4), "distortion_model": "equidistant"})
    with pytest.raises(DatasetFormatError, match="'equidistant' is not supported"):
        camera_from_info(fisheye, CameraConfig(), "info")


def _quat_z(deg: float) -> tuple[float, float, float, float]:
    half = np.radians(deg) / 2
    return (0.0, 0.0, float(np.sin(half)), float(np.cos(half)))


def test_tf_chain_interpolates_slow_links_and_composes() -> None:
    """world -> body moves at 100 Hz; body -> head moves at 10 Hz (linearly interpolated);
    head -> camera is static: the truth is their product at the 100 Hz stamps."""
    fast_t = np.arange(0.0, 1.0001, 0.01)
    slow_t = np.arange(0.0, 1.0001, 0.1)
    q_id = (0.0, 0.0, 0.0, 1.0)
    q_body = _quat_z(30.0)
    edges = {
        "body": _TfEdge(
            "world", list(fast_t), [(t, 0.0, 0.0) for t in fast_t], [q_body] * len(fast_t)
        ),
        "head": _TfEdge(
            "body", list(slow_t), [(0.0, 2 * t, 0.0) for t in slow_t], [q_id] * len(slow_t)
        ),
        "cam": _TfEdge("head", [0.0], [(0.0, 0.0, 0.5)], [q_id], static=True),
    }
    truth = groundtruth_from_tf(edges, "", "cam", "bag")
    assert truth is not None
    np.testing.assert_allclose(truth.timestamps, fast_t)
    R = pose_from_quat(np.zeros(3), np.array(q_body))[:3, :3]
    expected = np.stack([t * np.array([1.0, 0, 0]) + R @ np.array([0, 2 * t, 0.5]) for t in fast_t])
    np.testing.assert_allclose(truth.positions, expected, atol=1e-12)
    assert groundtruth_from_tf(edges, "elsewhere", "cam", "bag") is None
    static_only = {"cam": edges["cam"]}
    assert groundtruth_from_tf(static_only, "", "cam", "bag") is None


@pytest.mark.data
@pytest.mark.slow
def test_trajectory_from_ros1_and_ros2_bags_equals_the_folder_run(
    clip: TumDataset, bags: dict[str, Path], tmp_path: Path
) -> None:
    """`planeslam run` on the folder, on a ROS 1 bag (truth from the TUM file beside it) and
    on a ROS 2 mcap bag (truth from /tf): the same trajectory, and the same evaluation."""
    from planeslam.app.cli import main

    runs = {
        "folder": clip.root,
        "ros1": bags["ros1_16UC1_file"],
        "ros2": bags["ros2_mcap_16UC1_tf"],
    }
    for name, path in runs.items():
        assert main(["-q", "run", str(path), "--out", str(tmp_path / name)]) == 0
    ref = read_tum(tmp_path / "folder" / "trajectory.txt")
    assert len(ref) == len(clip)
    for name in ("ros1", "ros2"):
        got = read_tum(tmp_path / name / "trajectory.txt")
        np.testing.assert_array_equal(got.timestamps, ref.timestamps)
        np.testing.assert_allclose(got.T_world_cam, ref.T_world_cam, atol=1e-9)
    ate = {
        name: json.loads((tmp_path / name / "eval.json").read_text())["ate_rmse_m"] for name in runs
    }
    assert ate["ros1"] == pytest.approx(ate["folder"], abs=1e-9)
    assert ate["ros2"] == pytest.approx(ate["folder"], abs=1e-9)
    assert (tmp_path / "ros2" / "groundtruth.txt").is_file()  # the /tf truth, kept for eval


def test_colour_encodings_and_compressed_images() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 255, (4, 6, 3), dtype=np.uint8)
    image = "sensor_msgs/msg/Image"
    for encoding, data in (
        ("rgb8", rgb),
        ("bgr8", rgb[..., ::-1]),
        ("bgra8", np.dstack([rgb[..., ::-1], np.full((4, 6), 255, np.uint8)])),
    ):
        np.testing.assert_array_equal(rgb_from_message(_image_msg(encoding, data), image, "c"), rgb)
    mono = rgb_from_message(_image_msg("mono8", rgb[..., 0]), image, "c")
    assert mono.shape == (4, 6, 3) and np.all(mono[..., 1] == rgb[..., 0])
    ok, png = cv2.imencode(".png", rgb[..., ::-1])
    compressed = SimpleNamespace(format="png", data=png.reshape(-1))
    out = rgb_from_message(compressed, "sensor_msgs/msg/CompressedImage", "c")
    np.testing.assert_array_equal(out, rgb)
    with pytest.raises(FrameReadError, match="does not decode"):
        rgb_from_message(
            SimpleNamespace(format="jpeg", data=np.zeros(10, np.uint8)),
            "sensor_msgs/msg/CompressedImage",
            "c",
        )
    with pytest.raises(DatasetFormatError, match="compressedDepth images are not supported"):
        depth_from_message(
            SimpleNamespace(format="16UC1; compressedDepth", data=png.reshape(-1)),
            "sensor_msgs/msg/CompressedImage",
            CameraConfig(),
            "d",
        )
