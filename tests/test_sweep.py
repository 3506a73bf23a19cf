"""The sweep along a partial plane pose's free direction: a robot step along a wall found
from the colours, never a checkerboard's other period, and no answer where the wall is
bare (nothing observes the slide)."""

from __future__ import annotations

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig
from planeslam.frontend.cloud import PixelRays, organized_cloud
from planeslam.sim.render import render_frame
from planeslam.sim.scene_model import Box, Texture, make_scene
from planeslam.sim.scenes import look_at
from planeslam.tracking.dense import smooth_grey
from planeslam.tracking.sweep import LastFrame, sweep_free_translation

pytestmark = pytest.mark.unit

CAMERA = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
ALONG_WALL = np.array([0.0, 1.0, 0.0])
"""The free direction: along the wall x = 2 (world frame), which the floor and the wall
leave unfixed."""
STEP_M = 0.15
"""A robot step along the wall [m], beyond RGB-D odometry's reach."""


def _frames(pattern: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Two frames of a 4 x 4 m room, the camera 1.2 m from the wall x = 2 looking at it and
    down at the floor, the second STEP_M along the wall: pose, cloud, grey and depth."""
    room = Box("room", np.array((0.0, 0.0, 1.25)), np.array((4.0, 4.0, 2.5)), kind="room")
    scene = make_scene("wall", (room,), texture=Texture(seed=3, pattern=pattern))
    frames = []
    for y in (0.0, STEP_M):
        T = look_at(np.array([0.8, y, 1.0]), np.array([2.0, y + 0.1, 0.4]))[0]
        rendered = render_frame(scene, T, CAMERA, np.random.default_rng(len(frames)))
        frames.append(
            {
                "T": T,
                "cloud": organized_cloud(rendered.depth_m, PixelRays.for_camera(CAMERA)),
                "grey": smooth_grey(rendered.rgb),
                "depth": rendered.depth_m,
            }
        )
    return frames[0], frames[1]


def _sweep(previous: dict[str, np.ndarray], current: dict[str, np.ndarray]) -> np.ndarray | None:
    T_center = current["T"].copy()
    T_center[:3, 3] -= STEP_M * ALONG_WALL  # the slide at the last pose: the step missed
    last = LastFrame(previous["T"], previous["depth"], previous["grey"])
    return sweep_free_translation(
        T_center, ALONG_WALL, current["cloud"], current["grey"], last, CAMERA
    )


def test_a_step_along_a_textured_wall_is_found_from_the_colours() -> None:
    previous, current = _frames("noise")
    found = _sweep(previous, current)
    assert found is not None
    np.testing.assert_allclose(found[:3, 3], current["T"][:3, 3], atol=0.011)
    np.testing.assert_array_equal(found[:3, :3], current["T"][:3, :3])


def test_a_repetitive_texture_gives_the_step_or_no_answer() -> None:
    """A checkerboard's period leaves other basins: never one of them."""
    previous, current = _frames("repetitive")
    found = _sweep(previous, current)
    assert found is None or np.allclose(found[:3, 3], current["T"][:3, 3], atol=0.011)


def test_a_bare_wall_gives_no_answer() -> None:
    """Depth and colour are the same wherever the camera slides: the sweep says nothing
    (its profile is flat), so the caller keeps its own starts."""
    previous, current = _frames("none")
    assert _sweep(previous, current) is None
