"""`planeslam bench frontend` (bench_frontend) on tiny synthetic sequences."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from planeslam.app.bench import bench_frontend, open3d_planes, pinned_to_cores
from planeslam.core.camera import CameraConfig, PixelRays
from planeslam.core.errors import ConfigError
from planeslam.frontend import pipeline as frontend
from planeslam.sim.sequence import synthesize

pytestmark = pytest.mark.integration  # `planeslam bench`: front end over rendered sequences

SMALL = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bench") / "box"
    synthesize("box_room_circle", folder, frames=3, seed=1, camera=SMALL)
    return folder


def _check_figures(data: dict, width: int, height: int, frames: int) -> None:
    assert data["fps"] > 0 and data["frame_ms_median"] > 0
    assert list(data["stage_ms"]) == list(frontend.STAGES)
    assert all(v >= 0 for v in data["stage_ms"].values())
    assert (data["width"], data["height"], data["frames"]) == (width, height, frames)
    assert set(data["methods"]) == {"organized", "msac", "open3d_segment_plane"}
    for name in ("organized", "msac"):
        m = data["methods"][name]
        assert m["fps"] > 0 and list(m["stage_ms"]) == list(frontend.STAGES)
        assert m["planes_median"] >= 3  # the box room shows floor, walls and box faces
    assert data["methods"]["organized"]["fps"] == data["fps"]
    o3d = data["methods"]["open3d_segment_plane"]
    assert o3d["fps"] > 0 and o3d["frames"] == 1 and 1 <= o3d["planes_median"] <= 8
    # Whole front end >= the sum of stage medians is not guaranteed frame by frame,
    # but the median frame cannot be faster than its slowest stage's median.
    assert data["frame_ms_median"] >= 0.9 * max(data["stage_ms"].values())
    json.dumps(data)  # plain JSON types


def test_bench_on_tiny_dataset(tiny_dataset):
    result = bench_frontend(tiny_dataset, frames=2, reference_frames=1)
    data = result.to_dict()
    _check_figures(data, SMALL.width, SMALL.height, 2)
    if hasattr(os, "sched_setaffinity"):
        assert data["core"] == str(min(os.sched_getaffinity(0)))
    text = result.to_text()
    assert "organized (default)" in text and "msac" in text and "open3d_segment_plane" in text
    assert all(stage in text for stage in frontend.STAGES)


def test_frames_cycle_when_the_sequence_is_short(tiny_dataset):
    result = bench_frontend(tiny_dataset, frames=5, reference_frames=0, cores=None)
    assert result.frames == 5 and result.distinct_frames == 3
    assert "open3d_segment_plane" not in result.methods
    assert result.core == "not pinned"


def test_pinning_is_restored():
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no sched_setaffinity on this platform")
    before = os.sched_getaffinity(0)
    with pinned_to_cores(1) as core:
        assert os.sched_getaffinity(0) == {int(core)}
    assert os.sched_getaffinity(0) == before


def test_open3d_reference_counts_planes():
    """A fronto-parallel wall filling the image is one plane; nothing is left after it."""
    depth = np.full((SMALL.height, SMALL.width), 2.0, np.float32)
    rays = PixelRays.for_camera(SMALL)
    assert open3d_planes(depth, rays, max_planes=5, max_depth_m=6.0) == 1
    depth[:, : SMALL.width // 2] = 3.0  # two walls at different depths
    assert open3d_planes(depth, rays, max_planes=5, max_depth_m=6.0) == 2


@pytest.mark.parametrize("kwargs", [{"frames": 0}, {"reference_frames": -1}])
def test_bad_arguments(tiny_dataset, kwargs):
    with pytest.raises(ConfigError):
        bench_frontend(tiny_dataset, **kwargs)


@pytest.mark.slow
def test_bench_default_synthetic_scene(tmp_path):
    """No dataset: the default scene is rendered once into the cache and reused."""
    result = bench_frontend(frames=3, reference_frames=1, cache_dir=tmp_path)
    _check_figures(result.to_dict(), 640, 480, 3)
    truth = tmp_path / "box_room_circle" / "truth.json"
    stamp = truth.stat().st_mtime_ns
    bench_frontend(frames=1, reference_frames=0, cache_dir=tmp_path)
    assert truth.stat().st_mtime_ns == stamp
