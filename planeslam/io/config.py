"""Config of dataset reading, a leaf module."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class BagConfig:
    """How a ROS bag (ROS 1 `.bag` file, ROS 2 bag folder) is read. The topic defaults are
    the names in TUM RGB-D's bags."""

    rgb_topic: str = "/camera/rgb/image_color"
    """Colour images (sensor_msgs/Image rgb8, bgr8, rgba8, bgra8, mono8, or CompressedImage)."""
    depth_topic: str = "/camera/depth/image"
    """Depth images registered to colour (sensor_msgs/Image 16UC1 / mono16: value /
    camera.depth_scale = metres; 32FC1: metres, NaN = invalid)."""
    camera_info_topic: str = "/camera/rgb/camera_info"
    """sensor_msgs/CameraInfo of the colour camera (its first message is used)."""
    intrinsics: Literal["camera_info", "config"] = "camera_info"
    """Where fx fy cx cy, the image size and the distortion come from: the bag's camera_info,
    or the config's camera section (TUM's bags carry the driver's default intrinsics
    525 525 319.5 239.5 in camera_info, not TUM's calibration)."""
    groundtruth: Literal["auto", "file", "tf", "none"] = "auto"
    """Ground truth: 'file' a TUM trajectory beside the bag (`<bag stem>-groundtruth.txt`,
    as TUM names it, or `groundtruth.txt`), 'tf' the /tf chain from `tf_world_frame` to
    `tf_camera_frame`, 'auto' the file when there is one, else the /tf chain when the bag
    has one, else none."""
    tf_world_frame: str = ""
    """World frame of the /tf ground truth; '' = the root of the camera frame's tf tree."""
    tf_camera_frame: str = ""
    """Camera frame of the /tf ground truth; '' = the colour images' header frame_id."""


@dataclass(frozen=True)
class DatasetConfig:
    """How a dataset folder or bag is read."""

    max_time_difference_s: float = 0.02
    """Largest |t_rgb - t_depth| [s] for an RGB and a depth image to form one frame."""
    undistort: bool = False
    """Remove lens distortion (camera.distortion) from RGB and depth before use."""
    use_associations_file: bool = True
    """Use `associations.txt` when present instead of associating timestamps here."""
    bag: BagConfig = field(default_factory=BagConfig)
    """Topics, intrinsics and ground truth of a ROS bag."""
