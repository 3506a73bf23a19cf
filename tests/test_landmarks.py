"""PlaneLandmarks: our plane / corner landmarks inside a graph owned by an outside stack."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass, field

import gtsam
import numpy as np
import pytest
from helpers import assert_pose_close
from scipy.spatial.transform import Rotation

from planeslam.core.errors import AssociationError, ConfigError
from planeslam.core.geometry import angle_between, invert_pose
from planeslam.core.types import (
    CornerMeasurement,
    EdgeMeasurement,
    FrameMeasurements,
    PlaneMeasurement,
)
from planeslam.factors import LandmarkConfig, LandmarkKeys, PlaneLandmarks
from planeslam.sim.scenes import Scene, box_room_circle

pytestmark = pytest.mark.unit

# ---------------------------------------------------------------- synthetic observations
# FrameMeasurements of a scene seen from a pose, with the truth of which scene plane and
# corner each observed one is.

TAN_HALF_FOV = (0.55, 0.41)  # about 58 x 45 deg, a Kinect-like field of view
MAX_RANGE_M = 6.0


@dataclass(frozen=True)
class Observed(FrameMeasurements):
    plane_truth: dict[int, int] = field(default_factory=dict)
    """Observed plane id -> scene plane id."""
    corner_truth: dict[int, int] = field(default_factory=dict)
    """Observed corner index -> scene corner index."""


def in_view(points_world: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N,) bool inside the camera's frustum."""
    p = (points_world - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (
            (z > 0.2)
            & (z < MAX_RANGE_M)
            & (np.abs(p[:, 0] / z) < TAN_HALF_FOV[0])
            & (np.abs(p[:, 1] / z) < TAN_HALF_FOV[1])
        )


def observe(
    scene: Scene,
    T_world_cam: np.ndarray,
    rng: np.random.Generator,
    sigma_n_rad: float = 0.002,
    sigma_d_m: float = 0.003,
    sigma_corner_m: float = 0.005,
    timestamp: float = 0.0,
) -> Observed:
    """Noisy camera-frame planes, edges and corners of the scene seen from T_world_cam."""
    grid = np.linspace(-0.98, 0.98, 25)
    uv = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    centre = T_world_cam[:3, 3]
    visible = []
    for plane in scene.planes:
        if plane.normal @ centre + plane.d < 0.05:
            continue
        samples = plane.centre + (uv * plane.half_size_m) @ plane.axes
        if in_view(samples, T_world_cam).sum() >= 6:
            visible.append(plane)
    order = rng.permutation(len(visible))  # observed ids differ from scene ids
    R = T_world_cam[:3, :3]
    planes, truth = [], {}
    for obs_id, k in enumerate(order):
        plane = visible[k]
        n_cam = R.T @ plane.normal
        d_cam = plane.d + plane.normal @ centre
        n_cam = Rotation.from_rotvec(rng.normal(scale=sigma_n_rad, size=3)).apply(n_cam)
        cov = np.diag([sigma_n_rad**2, sigma_n_rad**2, sigma_d_m**2])
        planes.append(PlaneMeasurement(obs_id, n_cam, d_cam + rng.normal(scale=sigma_d_m), cov))
        truth[obs_id] = plane.id
    obs_of = {s: o for o, s in truth.items()}
    edges = []
    for edge in scene.edges:
        a, b = edge.plane_ids
        if a in obs_of and b in obs_of:
            line = edge.segment[0] + np.linspace(0, 1, 7)[:, None] * (
                edge.segment[1] - edge.segment[0]
            )
            if in_view(line, T_world_cam).any():
                ids = tuple(sorted((obs_of[a], obs_of[b])))
                angle = math.pi - angle_between(planes[ids[0]].n_cam, planes[ids[1]].n_cam)
                edges.append(EdgeMeasurement(ids, angle, convex=True))
    corners, corner_truth = [], {}
    for k, corner in enumerate(scene.corners):
        if (
            all(j in obs_of for j in corner.plane_ids)
            and in_view(corner.point[None], T_world_cam)[0]
        ):
            p_cam = R.T @ (corner.point - centre) + rng.normal(scale=sigma_corner_m, size=3)
            corner_truth[len(corners)] = k
            corners.append(
                CornerMeasurement(tuple(sorted(obs_of[j] for j in corner.plane_ids)), p_cam, 0)
            )
    return Observed(timestamp, tuple(planes), tuple(edges), tuple(corners), truth, corner_truth)


def noisy_odometry(
    T_world_cam: np.ndarray, rng: np.random.Generator, sigma_rot_rad: float, sigma_trans_m: float
) -> list[np.ndarray]:
    """Relative poses T_prev_cur between consecutive (N, 4, 4) poses, with seeded noise."""
    out = []
    for T_prev, T_cur in zip(T_world_cam[:-1], T_world_cam[1:], strict=True):
        noise = gtsam.Pose3.Expmap(
            np.r_[rng.normal(scale=sigma_rot_rad, size=3), rng.normal(scale=sigma_trans_m, size=3)]
        ).matrix()
        out.append(invert_pose(T_prev) @ T_cur @ noise)
    return out


def dead_reckoning(T_first: np.ndarray, odometry: list[np.ndarray]) -> np.ndarray:
    """(N, 4, 4) poses chained from the first pose by the relative poses."""
    poses = [T_first]
    for T_rel in odometry:
        poses.append(poses[-1] @ T_rel)
    return np.array(poses)


def translation_rmse(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """RMSE [m] of translations of (N, 4, 4) poses, no alignment (the first pose is anchored)."""
    return float(np.sqrt(np.mean(np.sum((T_est[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


def plane_errors(n: np.ndarray, d: float, n_true: np.ndarray, d_true: float) -> tuple[float, float]:
    """(angle [deg], offset [m]) between an estimated and a true world plane."""
    return math.degrees(angle_between(n, n_true)), abs(d - d_true)


# ---------------------------------------------------------------- outside stack

CALLER_KEYS = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")
ODOM_SIGMAS = (0.003, 0.005)  # rad, m per step


PRIOR = gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)  # anchors the gauge: ATE needs no alignment


def caller_pose_noise() -> gtsam.noiseModel.Diagonal:
    rot, trans = ODOM_SIGMAS
    return gtsam.noiseModel.Diagonal.Sigmas(np.r_[[rot] * 3, [trans] * 3])


@pytest.fixture(scope="module")
def circle():
    scene, trajectory = box_room_circle(frames=24)
    rng = np.random.default_rng(11)
    T_true = trajectory.T_world_cam
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    observations = [observe(scene, T, rng, timestamp=float(i)) for i, T in enumerate(T_true)]
    return scene, T_true, odometry, observations


def assert_map_recovered(scene, landmarks: PlaneLandmarks, angle_deg: float, offset_m: float):
    estimates = landmarks.plane_estimates()
    assert len(estimates) >= 8
    for j, estimate in estimates.items():
        n, d = estimate.n_world, estimate.d_world
        true = scene.planes[j]
        angle, offset = plane_errors(n, d, true.normal, true.d)
        assert angle < angle_deg and offset < offset_m, (true.name, angle, offset)
    for k, p in landmarks.corner_estimates().items():
        assert np.linalg.norm(p - scene.corners[k].point) < 0.02, scene.corners[k].plane_ids


def test_outside_stack_batch_levenberg_marquardt(circle):
    """An outside stack: its own 'x' poses, odometry and a 'p' variable; our 'P' / 'C' landmarks."""
    scene, T_true, odometry, observations = circle
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    noise = caller_pose_noise()
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(T_true[0]), PRIOR))
    # a variable of the caller's own under the character our planes would use by default
    graph.add(
        gtsam.PriorFactorPoint3(gtsam.symbol("p", 0), np.ones(3), gtsam.noiseModel.Unit.Create(3))
    )
    values.insert(gtsam.symbol("p", 0), np.ones(3))
    T_odom = dead_reckoning(T_true[0], odometry)
    for i, T in enumerate(T_odom):
        values.insert(X(i), gtsam.Pose3(T))
        if i:
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), gtsam.Pose3(odometry[i - 1]), noise))
    landmarks = PlaneLandmarks(CALLER_KEYS, LandmarkConfig())
    counts = {"structure": 0, "point_on_plane": 0, "corner": 0}
    for i, obs in enumerate(observations):
        added = landmarks.add_observations(
            graph, values, X(i), T_odom[i], obs, obs.plane_truth, obs.corner_truth
        )
        for kind in counts:
            counts[kind] += added.count(kind)
    assert counts["structure"] >= 10 and counts["corner"] >= 24 and counts["point_on_plane"] >= 6
    # every key of every factor has exactly one value; the characters never mix
    factor_keys = {k for i in range(graph.size()) for k in graph.at(i).keys()}
    assert factor_keys == set(values.keys())
    chars = {chr(gtsam.Symbol(k).chr()) for k in values.keys()}
    assert chars == {"x", "p", "P", "C"}
    assert values.atPoint3(gtsam.symbol("p", 0)).tolist() == [1.0, 1.0, 1.0]

    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    T_opt = np.array([result.atPose3(X(i)).matrix() for i in range(len(T_true))])
    for T_est, T_ref in zip(T_opt, T_true, strict=True):
        assert_pose_close(T_est, T_ref, 0.01, 0.5)
    ate_opt, ate_odom = translation_rmse(T_opt, T_true), translation_rmse(T_odom, T_true)
    assert ate_odom > 0.02, "odometry drift too small for the test to mean anything"
    assert ate_opt < 0.008 and ate_opt < ate_odom / 4, (ate_opt, ate_odom)
    landmarks.update_estimates(result)
    assert_map_recovered(scene, landmarks, 1.0, 0.01)


@pytest.mark.parametrize("robust_kernel", [None, "cauchy"])
def test_outside_stack_isam2(circle, robust_kernel):
    """Incremental: each step the caller adds its odometry and our factors, then updates iSAM2."""
    scene, T_true, odometry, observations = circle
    noise = caller_pose_noise()
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = 1
    params.setRelinearizeThreshold(1e-3)
    isam = gtsam.ISAM2(params)
    landmarks = PlaneLandmarks(CALLER_KEYS, LandmarkConfig(robust_kernel=robust_kernel))
    T_est = T_true[0]
    for i, obs in enumerate(observations):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(T_true[0]), PRIOR))
        else:
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), gtsam.Pose3(odometry[i - 1]), noise))
            T_est = T_est @ odometry[i - 1]
        values.insert(X(i), gtsam.Pose3(T_est))
        landmarks.add_observations(
            graph, values, X(i), T_est, obs, obs.plane_truth, obs.corner_truth
        )
        isam.update(graph, values)
        isam.update()
        estimate = isam.calculateEstimate()
        landmarks.update_estimates(estimate)
        T_est = estimate.atPose3(X(i)).matrix()
    T_opt = np.array([estimate.atPose3(X(i)).matrix() for i in range(len(T_true))])
    for T_e, T_ref in zip(T_opt, T_true, strict=True):
        assert_pose_close(T_e, T_ref, 0.01, 0.5)
    ate_opt = translation_rmse(T_opt, T_true)
    ate_odom = translation_rmse(dead_reckoning(T_true[0], odometry), T_true)
    assert ate_opt < 0.008 and ate_opt < ate_odom / 4, (ate_opt, ate_odom)
    assert_map_recovered(scene, landmarks, 1.0, 0.01)


# ---------------------------------------------------------------- bookkeeping


def test_keys_inserted_once_and_every_factor_has_values(circle):
    scene, T_true, _, observations = circle
    landmarks = PlaneLandmarks(LandmarkKeys())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pairs = set()
    for i in range(4):
        values.insert(gtsam.symbol("x", i), gtsam.Pose3(T_true[i]))
        obs = observations[i]
        added = landmarks.add_observations(
            graph, values, gtsam.symbol("x", i), T_true[i], obs, obs.plane_truth, obs.corner_truth
        )
        assert set(added.new_planes).isdisjoint(pairs)  # ids are new only once
        pairs |= set(added.new_planes)
        assert len(added.new_keys) == len(added.new_planes) + len(added.new_corners)
        for factor, kind in zip(added.factors, added.kinds, strict=True):
            if kind == "structure":
                pair = tuple(sorted(factor.keys()))
                assert pair not in pairs, "structural pair added twice"
                pairs.add(pair)
    factor_keys = {k for i in range(graph.size()) for k in graph.at(i).keys()}
    assert factor_keys == set(values.keys())
    # the same frame again adds observation factors only: no new values, no structure
    again = landmarks.add_observations(
        graph,
        values,
        gtsam.symbol("x", 0),
        T_true[0],
        observations[0],
        observations[0].plane_truth,
        observations[0].corner_truth,
    )
    assert again.new_keys == () and again.count("structure") == 0
    assert again.count("point_on_plane") == 0
    assert again.count("plane") == len(observations[0].planes)


def test_landmark_the_caller_already_created_is_not_inserted_again(circle):
    scene, T_true, _, observations = circle
    obs = observations[0]
    keys = LandmarkKeys()
    values = gtsam.Values()
    j = obs.plane_truth[0]
    values.insert(
        keys.plane(j), gtsam.OrientedPlane3(np.r_[scene.planes[j].normal, scene.planes[j].d])
    )
    added = PlaneLandmarks(keys).add_observations(
        gtsam.NonlinearFactorGraph(), values, keys.pose(0), T_true[0], obs, obs.plane_truth
    )
    assert keys.plane(j) not in added.new_keys
    assert j in added.new_planes  # known to the table from now on
    assert len(added.new_keys) == len(obs.planes) - 1


def test_associate_recovers_the_true_landmarks(circle):
    scene, T_true, _, observations = circle
    landmarks = PlaneLandmarks(LandmarkKeys())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    # the first frame creates landmarks with fresh ids 0..N-1
    plane_ids, corner_ids = landmarks.associate(observations[0], T_true[0])
    assert sorted(plane_ids.values()) == list(range(len(observations[0].planes)))
    landmarks.add_observations(graph, values, 0, T_true[0], observations[0], plane_ids, corner_ids)
    scene_of = {lm: observations[0].plane_truth[o] for o, lm in plane_ids.items()}
    corner_scene_of = {lm: observations[0].corner_truth[o] for o, lm in corner_ids.items()}
    # a later frame, predicted with 2 cm / 1 deg error: the shared planes match
    for i in (1, 2, 3):
        obs = observations[i]
        T_pred = T_true[i] @ gtsam.Pose3.Expmap(np.r_[np.full(3, 0.01), np.full(3, 0.012)]).matrix()
        plane_ids, corner_ids = landmarks.associate(obs, T_pred)
        assert set(plane_ids) == {p.id for p in obs.planes}
        for o, lm in plane_ids.items():
            if lm in scene_of:
                assert scene_of[lm] == obs.plane_truth[o]
            else:
                assert obs.plane_truth[o] not in scene_of.values()  # truly new
        for o, lm in corner_ids.items():
            if lm in corner_scene_of:
                assert corner_scene_of[lm] == obs.corner_truth[o]
        landmarks.add_observations(graph, values, i, T_pred, obs, plane_ids, corner_ids)
        for o, lm in plane_ids.items():
            scene_of.setdefault(lm, obs.plane_truth[o])
        for o, lm in corner_ids.items():
            corner_scene_of.setdefault(lm, obs.corner_truth[o])
    assert len(set(scene_of.values())) == len(scene_of)  # one landmark per scene plane


def test_joined_landmarks_are_tied_and_only_the_survivor_is_associated(circle):
    _, T_true, _, observations = circle
    landmarks = PlaneLandmarks(LandmarkKeys())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    first, second = observations[0], observations[1]
    landmarks.add_observations(graph, values, 0, T_true[0], first, first.plane_truth)
    # the second frame sees one scene plane as a new landmark (id 100): a duplicate
    scene_plane = next(first.plane_truth[p.id] for p in second.planes if p.id in second.plane_truth)
    duplicate = {
        o: (100 if s == scene_plane else s)
        for o, s in second.plane_truth.items()
        if o in {p.id for p in second.planes}
    }
    landmarks.add_observations(graph, values, 1, T_true[1], second, duplicate)
    size = graph.size()
    joined = landmarks.join_planes(graph, [(100, scene_plane), (100, 100), (7777, scene_plane)])
    assert joined.kinds == ("same_plane",) and graph.size() == size + 1
    assert set(joined.factors[0].keys()) == {
        LandmarkKeys().plane(100),
        LandmarkKeys().plane(scene_plane),
    }
    plane_ids, _ = landmarks.associate(observations[2], T_true[2])
    assert 100 not in plane_ids.values()
    assert scene_plane in plane_ids.values()


def test_bad_input_is_rejected(circle):
    _, T_true, _, observations = circle
    obs = observations[0]
    landmarks = PlaneLandmarks(LandmarkKeys())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    with pytest.raises(AssociationError, match="both map to landmark 7"):
        landmarks.add_observations(graph, values, 0, T_true[0], obs, {0: 7, 1: 7})
    with pytest.raises(AssociationError, match="do not have"):
        landmarks.add_observations(graph, values, 0, T_true[0], obs, {99: 1})
    assert graph.size() == 0 and values.size() == 0
    with pytest.raises(ConfigError, match="robust_kernel"):
        LandmarkConfig(robust_kernel="tukey")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="structure_tolerance_deg"):
        LandmarkConfig(structure_tolerance_deg=60.0)
    with pytest.raises(ConfigError, match="corner_sigma_m"):
        LandmarkConfig(corner_sigma_m=0.0)


@pytest.mark.integration
def test_keys_equal_gtsams_symbols_without_importing_gtsam():
    keys = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")
    for index in (0, 1, 12345, 2**56 - 1):
        assert keys.pose(index) == gtsam.symbol("x", index)
        assert keys.plane(index) == gtsam.symbol("P", index)
        assert keys.corner(index) == gtsam.symbol("C", index)
    code = "import sys, planeslam.factors.config; print('gtsam' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
