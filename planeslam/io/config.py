"""Config of dataset reading, a leaf module."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DatasetConfig:
    """How a dataset folder is read."""

    max_time_difference_s: float = 0.02
    """Largest |t_rgb - t_depth| [s] for an RGB and a depth image to form one frame."""
    undistort: bool = False
    """Remove lens distortion (camera.distortion) from RGB and depth before use."""
    use_associations_file: bool = True
    """Use `associations.txt` when present instead of associating timestamps here."""
