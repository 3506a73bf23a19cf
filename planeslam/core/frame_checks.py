"""Checks of one RGB-D frame at the library's boundary (`SLAM.process`, the dataset
readers): each problem becomes one DatasetFormatError that names the image, what it is
and what was expected.

Depth in a wrong unit (raw sensor values or millimetres taken for metres, a wrong
depth scale) is found from the frame's own statistics: the median valid depth of an
RGB-D camera lies within its range, so a median more than `RANGE_FACTOR` times beyond
it, or below `MIN_MEDIAN_DEPTH_M`, cannot be metres. The message names `depth_scale`
and the value that brings the median to a typical indoor depth.
"""

from __future__ import annotations

import numpy as np

from planeslam.core.errors import DatasetFormatError

TYPICAL_DEPTH_M = 2.0
"""A typical median depth of an indoor RGB-D frame [m], for suggesting a depth scale."""
MIN_MEDIAN_DEPTH_M = 0.05
"""A frame's median valid depth below this [m] is not in metres (no RGB-D camera sees
most of its pixels that close)."""
RANGE_FACTOR = 10.0
"""A frame's median valid depth beyond RANGE_FACTOR x the camera's range is not in metres."""
MAX_RANGE_M = 10.0
"""Range of the RGB-D cameras [m] against which a dataset's depth image's unit is checked."""
KNOWN_DEPTH_SCALES = (1000.0, 5000.0)
"""Depth PNG values per metre of common datasets (millimetres: 7-Scenes, RealSense,
Azure Kinect; 1/5 mm: TUM RGB-D, ICL-NUIM)."""
_SAMPLE_STRIDE = 8
"""Depth statistics use every 8th pixel of every 8th row (about 50 us at 640x480)."""
_MIN_SAMPLES = 20


def clean_depth(
    depth_m: np.ndarray,
    shape: tuple[int, int],
    where: str = "depth_m",
    depth_scale: float | None = None,
) -> np.ndarray:
    """Check a depth image [m] and return it with NaN, +-inf and negative values set to 0.

    (H, W) float array of `shape` expected. NaN and +-inf mean "no measurement" (as in
    ROS depth images), like 0; the input is copied only when it holds such values.
    DatasetFormatError for another shape or a non-float dtype (raw integer sensor values
    need dividing by the depth scale first; the message suggests one, `depth_scale` (the
    camera's) when it fits).
    """
    depth = np.asarray(depth_m)
    if depth.dtype.kind in "iub":
        hint = ""
        if depth.dtype.kind in "iu" and depth.ndim == 2:
            median = _median_valid(depth.astype(np.float32))
            if median is not None:
                hint = f" (likely depth_scale {_likely_scales(median, MAX_RANGE_M, depth_scale)})"
        raise DatasetFormatError(
            f"{where} is {depth.dtype}: depth must be float metres; divide raw sensor values by "
            f"the camera's depth_scale{hint}"
        )
    if depth.dtype.kind != "f":
        raise DatasetFormatError(f"{where} is {depth.dtype}: depth must be float metres")
    if depth.shape != tuple(shape):
        raise DatasetFormatError(
            f"{where} has shape {depth.shape}, expected (H, W) = {tuple(shape)} "
            "(the camera's height and width)"
        )
    # Two reductions without temporaries; NaN propagates into min and max.
    if not (depth.min() >= 0 and depth.max() < np.inf):
        valid = (depth >= 0) & (depth < np.inf)  # False for NaN, -inf, +inf, negative
        depth = np.where(valid, depth, depth.dtype.type(0))
    return depth


def check_depth_units(
    depth_m: np.ndarray,
    where: str,
    max_range_m: float,
    depth_scale: float | None = None,
    camera_depth_scale: float | None = None,
) -> None:
    """DatasetFormatError when the median valid depth of `depth_m` [m] cannot be metres
    (see the module docstring). `max_range_m` is the camera's range; `depth_scale` the
    scale that turned raw values into `depth_m` (None: the caller's own metres), and
    `camera_depth_scale` the configured one, suggested first when it fits."""
    median = _median_valid(depth_m)
    if median is None or MIN_MEDIAN_DEPTH_M <= median <= RANGE_FACTOR * max_range_m:
        return
    raw_median = median * (depth_scale or 1.0)
    likely = _likely_scales(raw_median, max_range_m, camera_depth_scale)
    if median > MIN_MEDIAN_DEPTH_M:
        problem = (
            f"median depth {median:.4g} m over the valid pixels, far beyond the camera's "
            f"range ({max_range_m:g} m)"
        )
    else:
        problem = (
            f"median depth {median:.3g} m over the valid pixels, closer than any RGB-D camera "
            f"sees (below {MIN_MEDIAN_DEPTH_M} m)"
        )
    if depth_scale is None:
        fix = (
            f"depth must be in metres: raw sensor values or millimetres need dividing by the "
            f"depth_scale (likely depth_scale {likely})"
            if median > MIN_MEDIAN_DEPTH_M
            else f"depth must be in metres: about {_power_of_ten(TYPICAL_DEPTH_M / median)}x "
            "too small (divided by the depth_scale twice?)"
        )
    else:
        fix = (
            f"wrong unit: metres = raw / depth_scale, and depth_scale {depth_scale:g} gives "
            f"this; likely depth_scale {likely} (camera.depth_scale in the config or "
            "camera.yaml)"
        )
    raise DatasetFormatError(f"{where}: {problem}; {fix}")


def check_rgb(rgb: np.ndarray, shape: tuple[int, int], where: str = "rgb") -> np.ndarray:
    """Check a colour image: (H, W, 3) uint8 RGB of the depth image's `shape` (H, W).
    Returns it as an array; DatasetFormatError naming the problem (greyscale, RGBA,
    another size or dtype) and the fix."""
    image = np.asarray(rgb)
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        raise DatasetFormatError(
            f"{where} is greyscale {image.shape}: expected (H, W, 3) uint8 RGB "
            "(np.dstack([grey] * 3) makes one)"
        )
    if image.ndim == 3 and image.shape[2] == 4:
        raise DatasetFormatError(
            f"{where} has 4 channels {image.shape} (RGBA?): expected (H, W, 3) uint8 RGB "
            "(rgb[..., :3] drops the alpha channel)"
        )
    if image.ndim != 3 or image.shape[2] != 3:
        raise DatasetFormatError(f"{where} has shape {image.shape}: expected (H, W, 3) uint8 RGB")
    if image.shape[:2] != tuple(shape):
        raise DatasetFormatError(
            f"{where} is {image.shape[1]}x{image.shape[0]} but the depth image is "
            f"{shape[1]}x{shape[0]}: colour and depth must be registered at one size"
        )
    if image.dtype != np.uint8:
        raise DatasetFormatError(f"{where} is {image.dtype}: expected uint8 values 0-255")
    return image


def _median_valid(depth: np.ndarray) -> float | None:
    """Median of the valid (finite, > 0) values of a subsample; None with too few."""
    sample = np.asarray(depth)[::_SAMPLE_STRIDE, ::_SAMPLE_STRIDE]
    values = sample[(sample > 0) & (sample < np.inf)]
    if values.size < _MIN_SAMPLES:
        return None
    return float(np.median(values))


def _likely_scales(raw_median: float, max_range_m: float, preferred: float | None) -> str:
    """The depth scale(s) (values per metre) that put `raw_median` within the camera's
    range: `preferred` alone when it does, else the common ones that do, closest to a
    typical depth first ('1000 or 5000': a factor of 5 cannot be told from one median),
    else the power of ten that gives a typical depth."""

    def fits(scale: float) -> bool:
        return 0.3 <= raw_median / scale <= max_range_m

    if preferred is not None and fits(preferred):
        return f"{preferred:g}"
    common = sorted(
        (s for s in KNOWN_DEPTH_SCALES if fits(s)),
        key=lambda s: abs(np.log(raw_median / s / TYPICAL_DEPTH_M)),
    )
    if common:
        return " or ".join(f"{s:g}" for s in common)
    return _power_of_ten(raw_median / TYPICAL_DEPTH_M)


def _power_of_ten(x: float) -> str:
    return f"{10.0 ** np.round(np.log10(x)):g}"
