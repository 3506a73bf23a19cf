"""The sweep along a partial plane pose's free direction: a robot step along a wall found
from the colours, never a checkerboard's other period, and no answer where the wall is
bare (nothing observes the slide). Its cost also chooses among the dense fallback's
results: a pose that lands clearly better wins, two that a bare wall fits alike do not
let noise decide (the earliest start's stays, or with a prior, the motion across a robot's
gap, the one nearest it). With the floor alone fixing the pose, the grid over the free
turn and directions offers a robot's step and turn, and the fallback lands it; a robot
turning in place is landed from the last pose turned as predicted."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from planeslam.core.camera import CameraConfig
from planeslam.core.geometry import axis_angle_rotation
from planeslam.frontend.cloud import PixelRays, organized_cloud
from planeslam.sim.render import render_frame
from planeslam.sim.scene_model import Box, Texture, make_scene
from planeslam.sim.scenes import look_at
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.dense import DenseFallback, smooth_grey
from planeslam.tracking.estimator import Primitive
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.odometry import RgbdOdometry
from planeslam.tracking.sweep import (
    LastFrame,
    landing_cost,
    lands_better,
    sweep_free_motion,
    sweep_free_translation,
)

pytestmark = pytest.mark.unit

CAMERA = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
ALONG_WALL = np.array([0.0, 1.0, 0.0])
"""The free direction: along the wall x = 2 (world frame), which the floor and the wall
leave unfixed."""
STEP_M = 0.15
"""A robot step along the wall [m], beyond RGB-D odometry's reach."""
ROBOT_STEP_M = np.array([0.12, 0.08, 0.0])
"""A robot's step on the floor [m, world frame]: toward the wall and along it."""
VERTICAL = np.array([0.0, 0.0, 1.0])
ALONG_FLOOR = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _turned(T: np.ndarray, step_m: np.ndarray, turn_deg: float) -> np.ndarray:
    """T_world_cam (4, 4) moved by `step_m` (3,) [m, world] and turned `turn_deg` about the
    vertical through its centre."""
    moved = T.copy()
    moved[:3, :3] = axis_angle_rotation(VERTICAL, np.radians(turn_deg)) @ T[:3, :3]
    moved[:3, 3] += step_m
    return moved


def _frames(
    pattern: str, robot_turn_deg: float | None = None, robot_step_m: np.ndarray | None = None
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Two frames of a 4 x 4 m room, the camera 1.2 m from the wall x = 2 looking at it and
    down at the floor, the second STEP_M along the wall (with `robot_turn_deg`: a robot's
    step, `robot_step_m` or ROBOT_STEP_M, turned that much about the vertical): pose, cloud,
    grey and depth."""
    room = Box("room", np.array((0.0, 0.0, 1.25)), np.array((4.0, 4.0, 2.5)), kind="room")
    scene = make_scene("wall", (room,), texture=Texture(seed=3, pattern=pattern))
    frames = []
    poses = [
        look_at(np.array([0.8, y, 1.0]), np.array([2.0, y + 0.1, 0.4]))[0] for y in (0.0, STEP_M)
    ]
    if robot_turn_deg is not None:
        step = ROBOT_STEP_M if robot_step_m is None else robot_step_m
        poses[1] = _turned(poses[0], step, robot_turn_deg)
    for T in poses:
        rendered = render_frame(scene, T, CAMERA, np.random.default_rng(len(frames)))
        frames.append(
            {
                "T": T,
                "rgb": rendered.rgb,
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


def _slid(current: dict[str, np.ndarray], by_m: float) -> np.ndarray:
    """The current pose moved `by_m` along the wall (-STEP_M: the step missed, at the last
    pose's place; +STEP_M: a prediction that overshot by a step)."""
    T = current["T"].copy()
    T[:3, 3] += by_m * ALONG_WALL
    return T


def _landing(previous: dict[str, np.ndarray], current: dict[str, np.ndarray], T) -> float:
    last = LastFrame(previous["T"], previous["depth"], previous["grey"])
    return landing_cost(T, current["cloud"], current["grey"], last, CAMERA, stride=4)


@pytest.mark.parametrize("by_m", [-STEP_M, STEP_M])
def test_on_a_textured_wall_the_true_pose_lands_clearly_better(by_m: float) -> None:
    previous, current = _frames("noise")
    true_cost = _landing(previous, current, current["T"])
    slid_cost = _landing(previous, current, _slid(current, by_m))
    assert lands_better(true_cost, slid_cost)
    assert not lands_better(slid_cost, true_cost)


def test_on_a_bare_wall_the_true_pose_does_not_land_better() -> None:
    """Nothing observes the slide: the costs differ by noise only."""
    previous, current = _frames("none")
    true_cost = _landing(previous, current, current["T"])
    for by_m in (-STEP_M, STEP_M):
        assert not lands_better(true_cost, _landing(previous, current, _slid(current, by_m)))
    assert not lands_better(_landing(previous, current, _slid(current, STEP_M)), true_cost)


class _ReturnsItsStart:
    """RGB-D odometry that converges where it starts: the dense fallback's choice among
    its starts' results is what is tested."""

    def image(self, rgb: np.ndarray, depth_m: np.ndarray) -> None:
        return None

    def motion(self, image, previous_image, T_prev_cur_init: np.ndarray) -> np.ndarray:
        return T_prev_cur_init


def _dense_choice(
    pattern: str, true_first: bool, prior_by_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(the pose the dense fallback takes, the true pose) from two starts: the true pose
    and one a step further along the wall, the true one first or second; with
    `prior_by_m`, the prior that decides ties is the true pose moved that much [m] along
    the wall."""
    previous, current = _frames(pattern)
    dense = DenseFallback(TrackingConfig(icp=False), _ReturnsItsStart(), CAMERA)
    dense.remember(0.0, previous["cloud"], (previous["rgb"], previous["depth"]), previous["T"])
    starts = [current["T"], _slid(current, STEP_M)]
    rgbd = (current["rgb"], current["depth"])
    prior = None if prior_by_m is None else _slid(current, prior_by_m)
    ordered = starts if true_first else starts[::-1]
    taken = dense.register(ordered, current["cloud"], rgbd, [], T_prior=prior)
    assert taken is not None and taken.filled_by is Primitive.ODOMETRY
    return taken.T, current["T"]


def test_the_dense_fallback_takes_the_start_that_lands_better() -> None:
    """A textured wall: the true start comes second and lands clearly better."""
    taken, truth = _dense_choice("noise", true_first=False)
    np.testing.assert_allclose(taken, truth, atol=1e-12)


def test_the_dense_fallback_keeps_the_first_start_where_nothing_tells_them_apart() -> None:
    """A bare wall: both land alike, so the first start stays (noise does not choose)."""
    taken, truth = _dense_choice("none", true_first=True)
    np.testing.assert_allclose(taken, truth, atol=1e-12)
    taken, truth = _dense_choice("none", true_first=False)
    np.testing.assert_allclose(taken[:3, 3] - truth[:3, 3], STEP_M * ALONG_WALL, atol=1e-12)


@pytest.mark.parametrize("true_first", [True, False])
def test_where_nothing_tells_the_results_apart_the_one_nearest_the_prior_is_taken(
    true_first: bool,
) -> None:
    """A bare wall: both land alike, so the result nearest the prior (across a robot's
    gap, the constant-velocity prediction) is taken, in either order of the starts."""
    taken, truth = _dense_choice("none", true_first, prior_by_m=0.03)
    np.testing.assert_allclose(taken, truth, atol=1e-12)
    taken, truth = _dense_choice("none", true_first, prior_by_m=STEP_M - 0.03)
    np.testing.assert_allclose(taken[:3, 3] - truth[:3, 3], STEP_M * ALONG_WALL, atol=1e-12)


def test_the_prior_does_not_overrule_a_result_that_lands_clearly_better() -> None:
    """A textured wall and a prior at the overshooting start: the true pose lands clearly
    better and is taken."""
    taken, truth = _dense_choice("noise", true_first=False, prior_by_m=STEP_M)
    np.testing.assert_allclose(taken, truth, atol=1e-12)


def _robot_sweep(pattern: str, turn_deg: float) -> tuple[list[np.ndarray], np.ndarray]:
    """(the poses the sweep over the floor's free turn and directions offers, the true
    pose), from the last pose's place and heading (the step and the turn missed)."""
    previous, current = _frames(pattern, robot_turn_deg=turn_deg)
    last = LastFrame(previous["T"], previous["depth"], previous["grey"])
    offered = sweep_free_motion(
        previous["T"],
        VERTICAL[None],
        ALONG_FLOOR,
        current["cloud"],
        current["grey"],
        last,
        CAMERA,
    )
    return offered, current["T"]


def _near(T: np.ndarray, truth: np.ndarray, meters: float, degrees: float) -> bool:
    m, d = pose_difference(truth, T)
    return m <= meters and d <= degrees


@pytest.mark.parametrize("turn_deg", [-9.0, 3.0, 13.0])
def test_a_robot_step_and_turn_seen_with_the_floor_alone_is_offered(turn_deg: float) -> None:
    """One plane (the floor) leaves the turn about it and the two directions along it
    free: one of the grid's basins is within what RGB-D odometry refines."""
    offered, truth = _robot_sweep("noise", turn_deg)
    assert 1 <= len(offered) <= 2
    assert any(_near(T, truth, 0.04, 2.0) for T in offered)


def test_the_dense_fallback_lands_a_robot_step_and_turn_from_the_grid() -> None:
    """With Open3D's RGB-D odometry: started at the last pose alone it misses a 14 cm
    step and a 13 deg turn; the grid's starts, refined by it and chosen by how they land,
    give the true pose."""
    previous, current = _frames("noise", robot_turn_deg=13.0)
    odometry = RgbdOdometry(CAMERA)
    dense = DenseFallback(TrackingConfig(), odometry, CAMERA)
    dense.remember(0.0, previous["cloud"], (previous["rgb"], previous["depth"]), previous["T"])
    rgbd = (current["rgb"], current["depth"])
    alone = dense.register([previous["T"]], current["cloud"], rgbd, [])
    assert alone is None or not _near(alone.T, current["T"], 0.02, 1.0)
    registration = SimpleNamespace(
        unobservable_rotation_axes=VERTICAL[None], unobservable_translation_dirs=ALONG_FLOOR
    )
    starts = dense.with_swept([previous["T"]], registration, current["cloud"], rgbd)
    assert len(starts) > 1 and np.array_equal(starts[0], previous["T"])
    taken = dense.register(starts, current["cloud"], rgbd, [])
    assert taken is not None and _near(taken.T, current["T"], 0.01, 0.5)


def test_nothing_free_or_too_much_free_is_not_swept() -> None:
    previous, current = _frames("noise")
    last = LastFrame(previous["T"], previous["depth"], previous["grey"])
    for axes, directions in ((np.zeros((0, 3)), np.zeros((0, 3))), (np.eye(3)[:2], np.eye(3)[:2])):
        offered = sweep_free_motion(
            current["T"], axes, directions, current["cloud"], current["grey"], last, CAMERA
        )
        assert offered == []


def test_a_robot_turning_in_place_is_found_from_the_last_pose_turned_as_predicted() -> None:
    """No plane placed the frame, and the constant-velocity prediction (the last step and
    turn again) overshoots a robot that stopped to turn in place by 22 cm: Open3D's RGB-D
    odometry started there finds nothing good; started at the last pose turned as
    predicted, it lands the turn."""
    previous, current = _frames("noise", robot_turn_deg=12.0, robot_step_m=np.zeros(3))
    T_pred = _turned(previous["T"], 1.5 * ROBOT_STEP_M, 12.0)
    dense = DenseFallback(TrackingConfig(), RgbdOdometry(CAMERA), CAMERA)
    dense.remember(0.0, previous["cloud"], (previous["rgb"], previous["depth"]), previous["T"])
    rgbd = (current["rgb"], current["depth"])
    from_prediction = dense.register([T_pred], current["cloud"], rgbd, [])
    assert from_prediction is None or not _near(from_prediction.T, current["T"], 0.02, 1.0)
    starts = dense.unplaced_starts(T_pred)
    assert len(starts) == 3 and np.array_equal(starts[1][:3, 3], previous["T"][:3, 3])
    taken = dense.register(starts, current["cloud"], rgbd, [])
    assert taken is not None and _near(taken.T, current["T"], 0.01, 0.5)
