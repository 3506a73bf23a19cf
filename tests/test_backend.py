"""Isam2Backend on synthetic sequences with exact truth, seeded noisy odometry and planes.

Run as a script for the timing figures: `.venv/bin/python tests/test_backend.py`.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from helpers import assert_pose_close

sys.path.insert(0, str(Path(__file__).parent))
from test_landmarks import (  # noqa: E402
    Observed,
    dead_reckoning,
    noisy_odometry,
    observe,
    translation_rmse,
)

from planeslam.backend.config import BackendConfig
from planeslam.backend.isam2 import Isam2Backend, informative_planes
from planeslam.backend.keyframes import is_keyframe
from planeslam.core.errors import ConfigError  # noqa: E402
from planeslam.core.geometry import angle_between, invert_pose  # noqa: E402
from planeslam.core.types import LoopConstraint, PlaneMeasurement  # noqa: E402
from planeslam.factors import LandmarkConfig, LandmarkKeys, point_on_plane_factor  # noqa: E402
from planeslam.sim.scenes import box_room_circle, room_boxes_loop  # noqa: E402

pytestmark = pytest.mark.unit

ODOM_SIGMAS = (0.003, 0.005)  # rad, m per keyframe


def run_sequence(backend, scene, T_true, odometry, observations, associate: bool):
    """Feed keyframes; the guess is the previous optimised pose moved by the odometry."""
    T_prev = T_true[0]
    ids = []
    for i, obs in enumerate(observations):
        T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
        if associate:
            plane_ids, corner_ids = backend.landmarks.associate(obs, T_guess)
        else:
            plane_ids, corner_ids = obs.plane_truth, obs.corner_truth
        ids.append((plane_ids, corner_ids))
        T_prev = backend.add_keyframe(
            i,
            obs.timestamp,
            T_guess,
            obs,
            plane_ids,
            corner_ids,
            None if i == 0 else odometry[i - 1],
        )
    return ids


@pytest.fixture(scope="module")
def room_loop():
    """40 keyframes of the room-with-boxes loop (the last pose is the first)."""
    scene, trajectory = room_boxes_loop(frames=40)
    rng = np.random.default_rng(5)
    T_true = trajectory.T_world_cam
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    observations = [observe(scene, T, rng, timestamp=float(i)) for i, T in enumerate(T_true)]
    return scene, T_true, odometry, observations


@pytest.fixture(scope="module")
def circle():
    scene, trajectory = box_room_circle(frames=36)
    rng = np.random.default_rng(5)
    T_true = trajectory.T_world_cam
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    observations = [observe(scene, T, rng, timestamp=float(i)) for i, T in enumerate(T_true)]
    return scene, T_true, odometry, observations


def backend_config(**landmarks) -> BackendConfig:
    """Noise models matching the synthetic noise (observe()'s defaults, ODOM_SIGMAS): the
    floors stand for the whole error, no correlated depth term."""
    landmarks = {
        "plane_sigma_floor_rad": 0.002,
        "plane_sigma_floor_m": 0.003,
        "plane_correlated_depth": 0.0,
        "corner_sigma_m": 0.005,
        **landmarks,
    }
    return BackendConfig(
        odometry_sigma_rot_rad=ODOM_SIGMAS[0],
        odometry_sigma_trans_m=ODOM_SIGMAS[1],
        landmarks=LandmarkConfig(**landmarks),
    )


@pytest.mark.integration
@pytest.mark.parametrize("robust_kernel", [None, "huber"])
def test_isam2_beats_odometry_below_1cm(room_loop, robust_kernel):
    scene, T_true, odometry, observations = room_loop
    backend = Isam2Backend(backend_config(robust_kernel=robust_kernel))
    run_sequence(backend, scene, T_true, odometry, observations, associate=False)
    assert backend.optimize_batch() > 0  # the final global optimisation, as SLAM.finish runs it
    poses = backend.keyframe_poses()
    assert list(poses) == list(range(len(T_true)))
    assert [t for t, _ in poses.values()] == [float(i) for i in range(len(T_true))]
    T_opt = np.array([T for _, T in poses.values()])
    ate, ate_odom = (
        translation_rmse(T_opt, T_true),
        translation_rmse(dead_reckoning(T_true[0], odometry), T_true),
    )
    assert ate_odom > 0.03, "odometry drift too small for the test to mean anything"
    assert ate < 0.007 and ate < ate_odom / 5, (ate, ate_odom)
    for T_e, T_ref in zip(T_opt, T_true, strict=True):
        assert_pose_close(T_e, T_ref, 0.01, 0.5)
    planes = backend.plane_estimates()
    assert set(planes) == {j for o in observations for j in o.plane_truth.values()}
    for j, estimate in planes.items():
        n, d = estimate.n_world, estimate.d_world
        assert np.degrees(angle_between(n, scene.planes[j].normal)) < 1.0
        assert abs(d - scene.planes[j].d) < 0.01
    corners = backend.corner_estimates()
    assert len(corners) >= 4
    for k, p in corners.items():
        assert np.linalg.norm(p - scene.corners[k].point) < 0.02
    assert len(backend.update_ms) == len(T_true) and backend.failures == 0


def test_a_plane_budget_takes_the_planes_that_fix_the_pose() -> None:
    """A floor and two walls fix all six directions; a second, more certain horizontal
    surface (a table) adds nothing the floor does not, so it comes last."""

    def plane(k: int, normal: list[float], sigma: float) -> PlaneMeasurement:
        return PlaneMeasurement(k, np.array(normal), 1.0, np.diag([sigma**2] * 3))

    floor = plane(0, [0.0, -1.0, 0.0], 0.002)
    table = plane(1, [0.0, -1.0, 0.0], 0.001)
    wall_a, wall_b = plane(2, [1.0, 0.0, 0.0], 0.004), plane(3, [0.0, 0.0, -1.0], 0.004)
    chosen = informative_planes([floor, table, wall_a, wall_b], 3)
    assert sorted(chosen) == [1, 2, 3]  # the most certain horizontal one, and both walls
    assert informative_planes([floor, table, wall_a, wall_b], 3, first=2) == [1, 0, 2]
    assert informative_planes([], 3) == [] and len(informative_planes([floor], 3)) == 1


def test_a_plane_budget_bounds_the_factors_per_keyframe(room_loop):
    scene, T_true, odometry, observations = room_loop
    budget = dataclasses.replace(backend_config(), max_planes_per_keyframe=3)
    backend = Isam2Backend(budget)
    run_sequence(backend, scene, T_true, odometry, observations, associate=False)
    full = Isam2Backend(backend_config())
    run_sequence(full, scene, T_true, odometry, observations, associate=False)
    graph = backend._graph
    chars = (ord(backend.keys.pose_char), ord(backend.keys.plane_char))
    per_pose = [0] * len(T_true)
    for k in range(graph.size()):
        keys = [gtsam.Symbol(key) for key in graph.at(k).keys()]
        if tuple(key.chr() for key in keys) == chars:  # (pose, plane): an observation
            per_pose[keys[0].index()] += 1
    assert max(per_pose) == 3 and min(per_pose) >= 1
    assert max(len(o.plane_truth) for o in observations) > 3, "the budget must bind"
    assert backend.num_factors < full.num_factors
    assert len(backend.plane_estimates()) < len(full.plane_estimates())
    T_opt = np.array([T for _, T in backend.keyframe_poses().values()])
    assert translation_rmse(T_opt, T_true) < 0.01


def test_loop_closes_through_associated_landmarks(room_loop):
    """Association by the backend's own map: the first planes are recognised at the end."""
    scene, T_true, odometry, observations = room_loop
    backend = Isam2Backend(backend_config())
    ids = run_sequence(backend, scene, T_true, odometry, observations, associate=True)
    scene_of: dict[int, int] = {}  # landmark id -> scene plane id
    for (plane_ids, _), obs in zip(ids, observations, strict=True):
        for o, lm in plane_ids.items():
            assert scene_of.setdefault(lm, obs.plane_truth[o]) == obs.plane_truth[o]
    # one landmark per scene plane: the re-observed planes were matched, not duplicated
    assert sorted(scene_of.values()) == sorted(set(scene_of.values()))
    first, last = ids[0][0], ids[-1][0]
    assert set(first.values()) & set(last.values()), "the loop's last frame saw no first landmark"
    T_opt = np.array([T for _, T in backend.keyframe_poses().values()])
    T_odom = dead_reckoning(T_true[0], odometry)
    end_odom = np.linalg.norm(T_odom[-1, :3, 3] - T_true[-1, :3, 3])
    assert end_odom > 0.03
    assert_pose_close(T_opt[-1], T_true[-1], 0.01, 0.5)
    assert translation_rmse(T_opt, T_true) < 0.007


def test_tied_duplicate_landmarks_close_the_loop(room_loop):
    """The loop's last ten keyframes see every plane as a new landmark (association missed
    the revisit): no loop closes. Joining those duplicates to the first landmarks
    (`joined_planes`, as the map's segment merge sends them) closes it when the backend
    ties them (`tie_joined_planes`, the default), not when told not to."""
    scene, T_true, odometry, observations = room_loop
    late = len(T_true) - 10
    poses = {}
    for join in (False, True):
        backend = Isam2Backend(dataclasses.replace(backend_config(), tie_joined_planes=join))
        T_prev, seen = T_true[0], set()
        for i, obs in enumerate(observations):
            offset = 1000 if i >= late else 0
            plane_ids = {o: s + offset for o, s in obs.plane_truth.items()}
            if i < late:
                seen |= set(plane_ids.values())
            joined = ()
            if i == late + 5:  # after the duplicates exist
                duplicates = set(backend.plane_estimates()) - seen
                joined = tuple((j, j - 1000) for j in sorted(duplicates) if j - 1000 in seen)
                assert joined
            T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
            T_prev = backend.add_keyframe(
                i,
                obs.timestamp,
                T_guess,
                obs,
                plane_ids,
                None,
                None if i == 0 else odometry[i - 1],
                joined_planes=joined,
            )
        poses[join] = np.array([T for _, T in backend.keyframe_poses().values()])
    end_error = {j: np.linalg.norm(poses[j][-1, :3, 3] - T_true[-1, :3, 3]) for j in poses}
    # measured: 1.4 cm without the ties, 0.7 cm with them
    assert end_error[False] > 0.01, "without the ties the loop must stay open"
    assert end_error[True] < 0.008 and end_error[True] < end_error[False] / 1.8, end_error


def test_a_sliding_window_closes_the_loop_and_bounds_the_smoother(room_loop):
    """With `window_keyframes` 6, iSAM2 holds 6 to 9 keyframes; the loop's end observes
    landmarks the window lost long before, which come back with what the held graph says
    of them, so the end pose is as good online as with the whole graph. The final batch
    over the whole graph lands where the whole graph's does."""
    scene, T_true, odometry, observations = room_loop
    results = {}
    for window in (0, 6):
        backend = Isam2Backend(dataclasses.replace(backend_config(), window_keyframes=window))
        online = []
        T_prev = T_true[0]
        for i, obs in enumerate(observations):
            T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
            T_prev = backend.add_keyframe(
                i,
                obs.timestamp,
                T_guess,
                obs,
                obs.plane_truth,
                obs.corner_truth,
                None if i == 0 else odometry[i - 1],
            )
            online.append(T_prev)
            if window:
                assert backend.window_size <= window + window // 2
        assert backend.failures == 0
        assert backend.num_factors > 0 and len(backend.keyframe_poses()) == len(T_true)
        backend.optimize_batch()
        final = np.array([T for _, T in backend.keyframe_poses().values()])
        results[window] = (np.array(online), final, backend.plane_estimates())
    (online_all, final_all, planes_all), (online_win, final_win, planes_win) = (
        results[0],
        results[6],
    )
    T_odom = dead_reckoning(T_true[0], odometry)
    assert np.linalg.norm(T_odom[-1, :3, 3] - T_true[-1, :3, 3]) > 0.03
    # online: the window's last pose closes the loop through the landmarks taken back
    assert_pose_close(online_win[-1], T_true[-1], 0.01, 0.5)
    assert_pose_close(online_all[-1], T_true[-1], 0.01, 0.5)
    # final: the whole graph from either estimate
    assert translation_rmse(final_win, T_true) < 0.007
    for T_w, T_a in zip(final_win, final_all, strict=True):
        assert_pose_close(T_w, T_a, 0.002, 0.1)
    assert set(planes_win) == set(planes_all)


def test_the_last_batch_leaves_the_window_as_it_is_and_gives_the_same_estimates(
    room_loop, monkeypatch
):
    """At a run's end (`optimize_batch(last=True)`, as the worker's finish calls it) the
    windowed smoother is not restarted at the new estimate; what the backend then reports
    is what the full call gives, bit for bit."""
    scene, T_true, odometry, observations = room_loop
    finals, restarts = {}, {}
    for last in (False, True):
        backend = Isam2Backend(dataclasses.replace(backend_config(), window_keyframes=6))
        run_sequence(backend, scene, T_true, odometry, observations, associate=False)
        restarts[last] = 0
        slide = backend._slide_window

        def counted(slide=slide, last=last):
            restarts[last] += 1
            slide()

        monkeypatch.setattr(backend, "_slide_window", counted)
        assert backend.optimize_batch(2, last=last) > 0
        finals[last] = (backend.keyframe_poses(), backend.plane_estimates())
    assert restarts == {False: 1, True: 0}
    (poses, planes), (poses_last, planes_last) = finals[False], finals[True]
    assert list(poses) == list(poses_last) and set(planes) == set(planes_last)
    for i, (t, T) in poses.items():
        assert poses_last[i][0] == t and np.array_equal(poses_last[i][1], T)
    for j, plane in planes.items():
        assert np.array_equal(planes_last[j].n_world, plane.n_world)
        assert planes_last[j].d_world == plane.d_world


@pytest.mark.parametrize("window", [0, 6])
def test_a_loop_constraint_closes_the_loop(room_loop, window: int) -> None:
    """The loop's last ten keyframes see every plane as a new landmark (association missed
    the revisit), so no landmark closes the loop. A loop constraint of the last keyframe
    against the first (its true relative pose, as keypoints would measure it) closes it
    with the whole graph. With a 6-keyframe window (keyframe 0 left it long before and
    comes back held by its own factors) it moves only the window's keyframes, so it takes
    back a part of the drift. A loop against a keyframe the graph does not hold is refused;
    a keyframe's loop found late comes with a later keyframe and ties the one it names."""
    scene, T_true, odometry, observations = room_loop
    late = len(T_true) - 10
    ends = {}
    for with_loop in (False, True):
        config = dataclasses.replace(
            backend_config(),
            window_keyframes=window,
            loop_sigma_rot_rad=0.002,  # an exact relative pose: as sure as a plane
            loop_sigma_trans_m=0.003,
        )
        backend = Isam2Backend(config)
        T_prev = T_true[0]
        for i, obs in enumerate(observations):
            offset = 1000 if i >= late else 0
            loops = ()
            if with_loop and i == len(T_true) - 1:
                T_first_cam = invert_pose(T_true[0]) @ T_true[i]
                loops = (LoopConstraint(i, old_index=0, T_old_cam=T_first_cam, inliers=100),)
            T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
            T_prev = backend.add_keyframe(
                i,
                obs.timestamp,
                T_guess,
                obs,
                {o: s + offset for o, s in obs.plane_truth.items()},
                None,
                None if i == 0 else odometry[i - 1],
                loops=loops,
            )
        ends[with_loop] = np.linalg.norm(T_prev[:3, 3] - T_true[-1, :3, 3])
        assert backend.failures == 0
    assert ends[False] > 0.01, "without the loop constraint the loop must stay open"
    if window:  # only the window's keyframes move: measured 1.15 -> 0.75 cm
        assert ends[True] < ends[False] / 1.4, ends
    else:  # measured 1.42 -> 0.26 cm
        assert ends[True] < 0.005 and ends[True] < ends[False] / 3, ends
    stray = LoopConstraint(len(T_true), old_index=999, T_old_cam=np.eye(4), inliers=100)
    with pytest.raises(ConfigError, match="keyframe 999"):
        backend.add_keyframe(
            len(T_true), 99.0, T_prev, observations[0], {}, None, np.eye(4), loops=(stray,)
        )
    ahead = LoopConstraint(len(T_true) + 1, old_index=0, T_old_cam=np.eye(4), inliers=100)
    with pytest.raises(ConfigError, match=f"keyframe {len(T_true) + 1}: not a keyframe"):
        backend.add_keyframe(
            len(T_true), 99.0, T_prev, observations[0], {}, None, np.eye(4), loops=(ahead,)
        )
    # The last keyframe's loop, found late (as a loop detector beside tracking delivers
    # it): it comes with the next keyframe and ties the keyframe it names.
    T_first_last = invert_pose(T_true[0]) @ T_true[-1]
    late_loop = LoopConstraint(len(T_true) - 1, old_index=0, T_old_cam=T_first_last, inliers=1)
    before = backend.num_factors
    backend.add_keyframe(
        len(T_true), 99.0, T_prev, observations[0], {}, None, np.eye(4), loops=(late_loop,)
    )
    assert backend.failures == 0
    graph = backend._graph  # every committed factor
    keys = {tuple(graph.at(i).keys()) for i in range(before, graph.size())}
    assert (backend.keys.pose(0), backend.keys.pose(len(T_true) - 1)) in keys, keys


def one_plane_observation(scene, T_world_cam, plane_index: int) -> Observed:
    full = observe(scene, T_world_cam, np.random.default_rng(0))
    plane = next(p for p in full.planes if full.plane_truth[p.id] == plane_index)
    plane = dataclasses.replace(plane, id=0)
    return Observed(full.timestamp, (plane,), (), (), {0: plane_index}, {})


def test_under_constrained_keyframes_do_not_raise(circle):
    """Keyframes seeing one plane (or nothing) follow the odometry; planes stay well posed."""
    scene, T_true, odometry, observations = circle
    backend = Isam2Backend(backend_config())
    floor = scene.plane_by_name("room.floor").id
    T_prev = T_true[0]
    for i in range(6):
        obs = one_plane_observation(scene, T_true[i], floor) if i % 3 else observations[i]
        if i == 4:
            obs = Observed(obs.timestamp, (), (), ())
        T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
        T_prev = backend.add_keyframe(
            i, float(i), T_guess, obs, obs.plane_truth, None, None if i == 0 else odometry[i - 1]
        )
    assert backend.failures == 0
    assert len(backend.keyframe_poses()) == 6
    # the floor fixes height and tilt of a one-plane keyframe, odometry the rest
    T1 = backend.keyframe_poses()[1][1]
    assert abs(T1[2, 3] - T_true[1][2, 3]) < 0.005
    assert_pose_close(T1, T_true[1], 0.02, 0.5)


def test_indeterminate_update_is_caught_and_the_landmark_dropped(circle, caplog):
    """A corner tied to one plane only (no observation of its own): the update fails,
    the backend rebuilds iSAM2, drops that landmark, and the sequence goes on."""
    scene, T_true, odometry, observations = circle
    backend = Isam2Backend(backend_config())
    original = backend.landmarks.add_observations
    bad_corner = 999

    def with_a_loose_corner(graph, values, pose_key, T, obs, plane_ids, corner_ids=None):
        added = original(graph, values, pose_key, T, obs, plane_ids, corner_ids)
        if gtsam.Symbol(pose_key).index() != 3:
            return added
        key = backend.keys.corner(bad_corner)
        values.insert(key, T[:3, 3] + np.array([0.0, 0.0, -1.0]))
        plane_key = backend.keys.plane(next(iter(plane_ids.values())))
        factor = point_on_plane_factor(plane_key, key, 0.01)
        graph.add(factor)
        return dataclasses.replace(
            added,
            factors=added.factors + (factor,),
            kinds=added.kinds + ("point_on_plane",),
            new_keys=added.new_keys + (key,),
            new_corners=added.new_corners + (bad_corner,),
        )

    backend.landmarks.add_observations = with_a_loose_corner  # type: ignore[method-assign]
    with caplog.at_level("WARNING", logger="planeslam.backend.isam2"):
        run_sequence(backend, scene, T_true[:8], odometry[:7], observations[:8], associate=False)
    assert backend.failures == 1
    assert "Indeterminate" in caplog.text and "dropped 0 new plane and 1 new corner" in caplog.text
    assert bad_corner not in backend.corner_estimates()
    assert not backend.estimate.exists(backend.keys.corner(bad_corner))
    T_opt = np.array([T for _, T in backend.keyframe_poses().values()])
    assert len(T_opt) == 8
    for T_e, T_ref in zip(T_opt, T_true[:8], strict=True):
        assert_pose_close(T_e, T_ref, 0.01, 0.5)
    # every other factor of keyframe 3 survived the rebuild
    expected = Isam2Backend(backend_config())
    run_sequence(expected, scene, T_true[:8], odometry[:7], observations[:8], associate=False)
    assert backend.num_factors == expected.num_factors


def test_is_keyframe_and_config_validation():
    config = BackendConfig(
        keyframe_min_translation_m=0.1, keyframe_min_rotation_deg=10.0, keyframe_max_frames=5
    )
    T0 = np.eye(4)
    moved = np.eye(4)
    moved[:3, 3] = [0.0, 0.09, 0.0]
    assert not is_keyframe(config, T0, moved, 1)
    moved[1, 3] = 0.11
    assert is_keyframe(config, T0, moved, 1)
    turned = gtsam.Pose3(gtsam.Rot3.Yaw(np.radians(9.0)), np.zeros(3)).matrix()
    assert not is_keyframe(config, T0, turned, 4)
    assert is_keyframe(config, T0, turned, 5)
    turned = gtsam.Pose3(gtsam.Rot3.Yaw(np.radians(11.0)), np.zeros(3)).matrix()
    assert is_keyframe(config, T0, turned, 0)
    with pytest.raises(ConfigError, match="relinearize_skip"):
        BackendConfig(relinearize_skip=0)
    with pytest.raises(ConfigError, match="odometry_sigma_trans_m"):
        BackendConfig(odometry_sigma_trans_m=-1.0)
    obs = Observed(0.0, (), (), ())
    backend = Isam2Backend(config)
    backend.add_keyframe(3, 0.0, T0, obs, {})
    with pytest.raises(ConfigError, match="expected > the previous keyframe 3"):
        backend.add_keyframe(3, 0.1, T0, obs, {})
    with pytest.raises(ConfigError, match="odometry_sigmas"):
        backend.add_keyframe(4, 0.1, T0, obs, {}, odometry_sigmas=(0.1, 0.0))


def test_backend_config_round_trips_through_a_mapping():
    from planeslam.core.config import from_mapping, to_mapping

    config = BackendConfig(
        extra_updates=0, landmarks=LandmarkConfig(robust_kernel="cauchy", use_structure=False)
    )
    assert from_mapping(BackendConfig, to_mapping(config), "test.yaml", "backend") == config
    with pytest.raises(ConfigError, match="valid keys"):
        from_mapping(BackendConfig, {"landmark": {}}, "test.yaml", "backend")


def test_custom_key_characters():
    keys = LandmarkKeys(pose_char="k", plane_char="m", corner_char="n")
    scene, trajectory = box_room_circle(frames=4)
    rng = np.random.default_rng(1)
    backend = Isam2Backend(BackendConfig(keys=keys))
    observations = [observe(scene, T, rng) for T in trajectory.T_world_cam]
    odometry = noisy_odometry(trajectory.T_world_cam, rng, 0.0, 0.0)
    run_sequence(backend, scene, trajectory.T_world_cam, odometry, observations, associate=False)
    chars = {chr(gtsam.Symbol(k).chr()) for k in backend.estimate.keys()}
    assert chars == {"k", "m", "n"}


@pytest.mark.integration
def test_real_front_end_observations_on_rendered_frames():
    """The real FrontEnd on rendered depth (Kinect noise) -> associate -> add_keyframe."""
    from planeslam.config import load_config
    from planeslam.frontend.pipeline import FrontEnd
    from planeslam.sim.render import render_frame

    scene, trajectory = box_room_circle(frames=24)
    config = load_config("synthetic")
    rng = np.random.default_rng(3)
    front_end = FrontEnd(config, seed=3)
    T_true = trajectory.T_world_cam[:8]
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    backend = Isam2Backend(backend_config())
    T_prev = T_true[0]
    for i, T in enumerate(T_true):
        depth_m = render_frame(scene, T, config.camera, rng).depth_m
        obs = front_end.process(depth_m, float(i)).measurements()
        T_guess = T_prev if i == 0 else T_prev @ odometry[i - 1]
        plane_ids, corner_ids = backend.landmarks.associate(obs, T_guess)
        T_prev = backend.add_keyframe(
            i, float(i), T_guess, obs, plane_ids, corner_ids, None if i == 0 else odometry[i - 1]
        )
        assert_pose_close(T_prev, T, 0.01, 0.5)
    assert backend.failures == 0
    T_opt = np.array([T for _, T in backend.keyframe_poses().values()])
    assert translation_rmse(T_opt, T_true) < translation_rmse(
        dead_reckoning(T_true[0], odometry), T_true
    )
    # every estimated plane landmark is close to some true scene plane
    for n, d in ((e.n_world, e.d_world) for e in backend.plane_estimates().values()):
        best = min(
            np.degrees(angle_between(n, p.normal)) + 100 * abs(d - p.d) for p in scene.planes
        )
        assert best < 2.0


# ---------------------------------------------------------------- timing (script only)


def bench(keyframes: int = 100) -> None:
    """Median ms per keyframe of iSAM2 work, built-in vs robust plane factors, same data."""
    scene, trajectory = room_boxes_loop(frames=keyframes)
    rng = np.random.default_rng(0)
    T_true = trajectory.T_world_cam
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    observations = [observe(scene, T, rng, timestamp=float(i)) for i, T in enumerate(T_true)]
    planes = statistics.median(len(o.planes) for o in observations)
    corners = statistics.median(len(o.corners) for o in observations)
    print(
        f"room_boxes_loop, {keyframes} keyframes, median {planes:.0f} planes and "
        f"{corners:.0f} corners observed per keyframe"
    )
    print(
        f"{'plane factor':14s} {'extra':>5s} {'median ms':>10s} {'p90 ms':>8s} {'ATE mm':>8s} "
        f"{'landmarks':>10s}"
    )
    runs = [(None, 1), ("huber", 1), ("cauchy", 1), (None, 0), ("huber", 0)]
    for kernel, extra in runs + runs:  # interleaved twice: noisy shared machine
        config = dataclasses.replace(backend_config(robust_kernel=kernel), extra_updates=extra)
        backend = Isam2Backend(config)
        run_sequence(backend, scene, T_true, odometry, observations, associate=False)
        T_opt = np.array([T for _, T in backend.keyframe_poses().values()])
        ms = np.array(backend.update_ms)
        print(
            f"{kernel or 'built-in':14s} {extra:5d} {np.median(ms):10.2f} "
            f"{np.percentile(ms, 90):8.2f} "
            f"{translation_rmse(T_opt, T_true) * 1e3:8.2f} "
            f"{len(backend.plane_estimates())}p/{len(backend.corner_estimates())}c"
        )


if __name__ == "__main__":
    bench()
