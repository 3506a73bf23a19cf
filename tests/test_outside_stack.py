"""Into an outside GTSAM stack: top-level names, poses as gtsam.Pose3, gates from the
caller's pose covariance, reserved ids, objects from the landmark layer, recovery from an
indeterminate update."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from helpers import assert_pose_close

sys.path.insert(0, str(Path(__file__).parent))
from test_landmarks import (  # noqa: E402
    CALLER_KEYS,
    ODOM_SIGMAS,
    PRIOR,
    caller_pose_noise,
    dead_reckoning,
    noisy_odometry,
    observe,
    translation_rmse,
)

import planeslam  # noqa: E402
from planeslam.core.errors import AssociationError, GeometryError, MapError  # noqa: E402
from planeslam.core.geometry import orthonormalize_pose  # noqa: E402
from planeslam.factors import (  # noqa: E402
    LandmarkConfig,
    LandmarkKeys,
    PlaneLandmarks,
    RecoveringISAM2,
    point_on_plane_factor,
    pose_gate_sigmas,
)
from planeslam.sim.scenes import box_room_circle  # noqa: E402

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def circle():
    """24 noisy frames of the box room circle (another seed than test_landmarks')."""
    scene, trajectory = box_room_circle(frames=24)
    rng = np.random.default_rng(5)
    T_true = trajectory.T_world_cam
    odometry = noisy_odometry(T_true, rng, *ODOM_SIGMAS)
    observations = [observe(scene, T, rng, timestamp=float(i)) for i, T in enumerate(T_true)]
    return scene, T_true, odometry, observations


def perturbed(T: np.ndarray, rot_rad: float, trans_m: float, seed: int) -> np.ndarray:
    """T moved by a rotation of `rot_rad` and a translation of `trans_m`, random directions."""
    rng = np.random.default_rng(seed)
    axis, step = rng.normal(size=3), rng.normal(size=3)
    xi = np.r_[rot_rad * axis / np.linalg.norm(axis), trans_m * step / np.linalg.norm(step)]
    return T @ gtsam.Pose3.Expmap(xi).matrix()


def landmarks_from(observations, T_true, frames) -> PlaneLandmarks:
    """A table built from `frames` at their true poses, with the true associations."""
    landmarks = PlaneLandmarks(LandmarkKeys())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i in frames:
        obs = observations[i]
        landmarks.add_observations(
            graph, values, i, T_true[i], obs, obs.plane_truth, obs.corner_truth
        )
    return landmarks


# ---------------------------------------------------------------- the public surface


@pytest.mark.integration
def test_front_end_and_measurement_types_are_top_level():
    for name in planeslam.__all__:
        assert getattr(planeslam, name) is not None, name
    assert planeslam.FrontEnd.__module__ == "planeslam.frontend.pipeline"
    assert planeslam.FrameMeasurements.__module__ == "planeslam.core.types"
    assert planeslam.PlaneLandmarks is PlaneLandmarks
    code = (
        "import sys, planeslam; planeslam.FrontEnd, planeslam.FrameMeasurements, "
        "planeslam.load_config; print(sorted(m for m in ('gtsam', 'open3d') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", "the front end's names must not load gtsam or Open3D"


def test_poses_are_taken_as_gtsam_pose3_or_arrays(circle):
    _, T_true, _, observations = circle
    results = []
    for as_pose3 in (False, True):
        landmarks = PlaneLandmarks(LandmarkKeys())
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i in range(3):
            T = gtsam.Pose3(T_true[i]) if as_pose3 else T_true[i]
            ids = landmarks.associate(observations[i], T)
            landmarks.add_observations(graph, values, i, T, observations[i], *ids)
        results.append((ids, landmarks.plane_estimates(), graph.size(), values.size()))
    (ids_a, planes_a, *sizes_a), (ids_b, planes_b, *sizes_b) = results
    assert ids_a == ids_b and sizes_a == sizes_b
    for j, estimate in planes_a.items():
        np.testing.assert_allclose(planes_b[j].n_world, estimate.n_world, atol=1e-12)
    with pytest.raises(GeometryError, match="T_world_cam_pred is a str, expected a .4, 4. pose"):
        landmarks.associate(observations[0], "identity")
    with pytest.raises(GeometryError, match=r"T_world_cam has shape \(3, 3\)"):
        landmarks.add_observations(graph, values, 9, gtsam.Rot3(), observations[0], {})


def test_new_ids_are_reserved_when_handed_out(circle):
    _, T_true, _, observations = circle
    landmarks = landmarks_from(observations, T_true, [0])
    known = set(landmarks.plane_ids)
    first = landmarks.associate(observations[6], T_true[6])
    second = landmarks.associate(observations[12], T_true[12])
    new_first = set(first[0].values()) - known
    new_second = set(second[0].values()) - known
    assert new_first and new_second and not new_first & new_second
    assert not set(first[1].values()) & set(second[1].values()) - set(landmarks.corner_ids)
    again = landmarks.associate(observations[6], T_true[6])  # the same frame twice
    assert not (set(again[0].values()) - known) & (new_first | new_second)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i, ids in ((6, first), (12, second)):
        landmarks.add_observations(graph, values, i, T_true[i], observations[i], *ids)
    assert set(landmarks.plane_ids) == known | new_first | new_second


# ---------------------------------------------------------------- gates from the covariance


def true_matches(landmarks, observations, plane_ids, i) -> tuple[int, int]:
    """(observed planes of a known scene plane given its landmark, of them all)."""
    obs = observations[i]
    shared = {o for o, s in obs.plane_truth.items() if s in landmarks.plane_ids}
    right = sum(plane_ids[o] == obs.plane_truth[o] for o in shared)
    return right, len(shared)


def test_pose_covariance_widens_the_gates_to_the_prediction_error(circle):
    """Landmark ids are the scene's (true associations at true poses), so a match is right
    when the landmark id equals the observed plane's scene id."""
    _, T_true, _, observations = circle
    landmarks = landmarks_from(observations, T_true, range(0, 24, 3))
    sigma_rot, sigma_trans = 0.02, 0.04
    cov = np.diag([sigma_rot**2] * 3 + [sigma_trans**2] * 3)
    cases = fixed_all_right = 0
    for i in (i for i in range(24) if i % 3):  # frames that made no landmark
        T_pred = perturbed(T_true[i], 1.5 * sigma_rot, 1.5 * sigma_trans, i)  # 1.7 deg, 6 cm
        fixed, _ = landmarks.associate(observations[i], T_pred)
        gated, _ = landmarks.associate(observations[i], T_pred, cov)
        right_fixed, shared = true_matches(landmarks, observations, fixed, i)
        right_gated, _ = true_matches(landmarks, observations, gated, i)
        assert right_gated == shared >= 4, (i, right_gated, shared)
        cases += 1
        fixed_all_right += right_fixed == shared
    assert cases == 16 and fixed_all_right <= cases // 2, "the fixed gates should miss many"
    # a covariance of nothing leaves the fixed gates (and a good prediction's matches) as they are
    tiny = np.diag([1e-14] * 6)
    for i in (4, 10):
        assert landmarks.associate(observations[i], T_true[i], tiny) == landmarks.associate(
            observations[i], T_true[i]
        )


def test_marginals_give_the_same_gates_as_their_matrix(circle):
    _, T_true, odometry, observations = circle
    landmarks = landmarks_from(observations, T_true, [0, 3])
    x = CALLER_KEYS.pose
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(x(0), gtsam.Pose3(T_true[0]), PRIOR))
    loose = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[0.03] * 3, [0.05] * 3])
    for i in range(1, 6):
        graph.add(gtsam.BetweenFactorPose3(x(i - 1), x(i), gtsam.Pose3(odometry[i - 1]), loose))
    T_odom = dead_reckoning(T_true[0], odometry[:5])
    for i, T in enumerate(T_odom):
        values.insert(x(i), gtsam.Pose3(T))
    marginals = gtsam.Marginals(graph, values)
    from_marginals = landmarks.associate(observations[5], T_odom[5], marginals, x(5))
    from_matrix = landmarks.associate(
        observations[5], T_odom[5], marginals.marginalCovariance(x(5))
    )
    known = set(landmarks.plane_ids)  # new ids differ: each call reserves its own
    assert {o: j for o, j in from_marginals[0].items() if j in known} == {
        o: j for o, j in from_matrix[0].items() if j in known
    }
    right, shared = true_matches(landmarks, observations, from_marginals[0], 5)
    assert right == shared
    with pytest.raises(AssociationError, match="give pose_key"):
        landmarks.associate(observations[5], T_odom[5], marginals)
    with pytest.raises(AssociationError, match="no marginal covariance for key"):
        landmarks.associate(observations[5], T_odom[5], marginals, x(9))


@pytest.mark.parametrize(
    "cov",
    [np.eye(5), np.triu(np.ones((6, 6))), -np.eye(6), np.full((6, 6), np.nan), "wide"],
)
def test_bad_pose_covariance_is_rejected(circle, cov):
    _, T_true, _, observations = circle
    with pytest.raises(AssociationError, match="expected a finite symmetric positive semi-def"):
        PlaneLandmarks(LandmarkKeys()).associate(observations[0], T_true[0], cov)


def test_gate_sigmas_match_the_spread_of_sampled_poses():
    """Monte Carlo: planes and corners moved to the world by poses T Exp(xi), xi ~ N(0, cov)."""
    rng = np.random.default_rng(7)
    T = perturbed(np.eye(4), 0.7, 0.0, 3)
    T[:3, 3] = [1.5, -0.8, 0.6]  # a lever arm for the offsets
    A = rng.normal(size=(6, 6)) * np.r_[[0.01] * 3, [0.02] * 3][:, None]
    cov = A @ A.T
    n_cam = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    d_cam = np.array([2.0, 1.0, 0.5])
    p_cam = np.array([[0.3, -0.2, 1.5], [-1.0, 0.5, 3.0]])
    sigmas = pose_gate_sigmas(T, cov, n_cam, p_cam)
    xis = rng.multivariate_normal(np.zeros(6), cov, size=4000)
    T_samples = np.array([T @ gtsam.Pose3.Expmap(xi).matrix() for xi in xis])
    R, t = T_samples[:, :3, :3], T_samples[:, :3, 3]
    for k, (n, d) in enumerate(zip(n_cam, d_cam, strict=True)):
        n_world = R @ n  # (S, 3)
        d_world = d - np.einsum("si,si->s", n_world, t)
        assert np.std(d_world) == pytest.approx(sigmas.offset_m[k], rel=0.05)
        spread = np.cov((n_world - T[:3, :3] @ n).T)
        assert np.sqrt(np.linalg.eigvalsh(spread)[-1]) == pytest.approx(
            sigmas.angle_rad[k], rel=0.05
        )
    for k, p in enumerate(p_cam):
        spread = np.cov((R @ p + t).T)
        assert np.sqrt(np.linalg.eigvalsh(spread)[-1]) == pytest.approx(
            sigmas.corner_m[k], rel=0.05
        )


# ---------------------------------------------------------------- recovery


def run_with_smoother(observations, T_true, odometry, smoother, landmarks, loose_corner_at=None):
    """The caller's loop: own prior / odometry, our landmark factors in a graph of their own."""
    x = CALLER_KEYS.pose
    T_est, outcomes = T_true[0], []
    for i, obs in enumerate(observations):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            graph.add(gtsam.PriorFactorPose3(x(0), gtsam.Pose3(T_true[0]), PRIOR))
        else:
            T_est = T_est @ odometry[i - 1]
            graph.add(
                gtsam.BetweenFactorPose3(
                    x(i - 1), x(i), gtsam.Pose3(odometry[i - 1]), caller_pose_noise()
                )
            )
        values.insert(x(i), gtsam.Pose3(T_est))
        ours, our_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        added = landmarks.add_observations(
            ours, our_values, x(i), T_est, obs, obs.plane_truth, obs.corner_truth
        )
        if i == loose_corner_at:  # a corner tied to one plane only: nothing fixes it
            key = CALLER_KEYS.corner(999)
            our_values.insert(key, T_est[:3, 3] + np.array([0.0, 0.0, -1.0]))
            factor = point_on_plane_factor(CALLER_KEYS.plane(obs.plane_truth[0]), key, 0.01)
            added = dataclasses.replace(
                added,
                factors=added.factors + (factor,),
                kinds=added.kinds + ("point_on_plane",),
                new_keys=added.new_keys + (key,),
                new_corners=added.new_corners + (999,),
                values=our_values,
            )
        outcomes.append(smoother.update(graph, values, added, landmarks))
        T_est = smoother.estimate.atPose3(x(i)).matrix()
    return outcomes


def test_recovering_isam2_is_plain_isam2_when_nothing_fails(circle):
    """The same caller's loop through RecoveringISAM2 and through a plain ISAM2."""
    _, T_true, odometry, observations = circle
    params = gtsam.ISAM2Params()
    smoother = RecoveringISAM2(params, extra_updates=1)
    isam = gtsam.ISAM2(params)
    theta = isam.getLinearizationPoint()  # noqa: F841  (no copies into Python factors)
    ours_a, ours_b = PlaneLandmarks(CALLER_KEYS), PlaneLandmarks(CALLER_KEYS)
    x = CALLER_KEYS.pose
    T_a = T_b = T_true[0]
    for i, obs in enumerate(observations[:8]):
        if i:
            T_a, T_b = T_a @ odometry[i - 1], T_b @ odometry[i - 1]
        graph = gtsam.NonlinearFactorGraph()
        if i == 0:
            graph.add(gtsam.PriorFactorPose3(x(0), gtsam.Pose3(T_true[0]), PRIOR))
        else:
            step = gtsam.Pose3(odometry[i - 1])
            graph.add(gtsam.BetweenFactorPose3(x(i - 1), x(i), step, caller_pose_noise()))
        values_a, values_b = gtsam.Values(), gtsam.Values()
        values_a.insert(x(i), gtsam.Pose3(T_a))
        values_b.insert(x(i), gtsam.Pose3(T_b))
        graph_a, landmark_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        added = ours_a.add_observations(
            graph_a, landmark_values, x(i), T_a, obs, obs.plane_truth, obs.corner_truth
        )
        outcome = smoother.update(graph, values_a, added, ours_a)
        assert outcome.failures == outcome.dropped_factors == 0
        ours_b.add_observations(graph, values_b, x(i), T_b, obs, obs.plane_truth, obs.corner_truth)
        isam.update(graph, values_b)
        isam.update()
        estimate = isam.calculateEstimate()
        ours_b.update_estimates(estimate)
        T_a = smoother.estimate.atPose3(x(i)).matrix()
        T_b = estimate.atPose3(x(i)).matrix()
        np.testing.assert_allclose(T_a, T_b, atol=1e-9)
    assert smoother.failures == 0 and smoother.graph.size() == isam.getFactorsUnsafe().size()
    for j, plane in ours_a.plane_estimates().items():
        np.testing.assert_allclose(plane.n_world, ours_b.plane_estimates()[j].n_world, atol=1e-9)
    T_opt = np.array([smoother.estimate.atPose3(x(i)).matrix() for i in range(8)])
    assert translation_rmse(T_opt, T_true[:8]) < translation_rmse(
        dead_reckoning(T_true[0], odometry[:7]), T_true[:8]
    )
    # landmark covariances from the smoother: the batch marginals of the same graph
    planes, corners = ours_a.covariances(smoother)
    assert set(planes) == set(ours_a.plane_ids) and set(corners) == set(ours_a.corner_ids)
    batch = gtsam.Marginals(smoother.graph, smoother.isam.getLinearizationPoint())
    for key, cov in [(CALLER_KEYS.plane(j), c) for j, c in planes.items()] + [
        (CALLER_KEYS.corner(k), c) for k, c in corners.items()
    ]:
        np.testing.assert_allclose(cov, batch.marginalCovariance(key), rtol=0.05, atol=1e-9)
    with pytest.raises(planeslam.ConfigError, match="expected a gtsam.Marginals"):
        ours_a.covariances(smoother.estimate)


def test_an_indeterminate_landmark_is_dropped_and_the_run_goes_on(circle, caplog):
    scene, T_true, odometry, observations = circle
    smoother = RecoveringISAM2(extra_updates=1)
    landmarks = PlaneLandmarks(CALLER_KEYS, LandmarkConfig())
    with caplog.at_level("WARNING", logger="planeslam.factors.recovery"):
        outcomes = run_with_smoother(
            observations[:8], T_true, odometry, smoother, landmarks, loose_corner_at=3
        )
    assert smoother.failures == 1 and outcomes[3].failures == 1
    assert outcomes[3].dropped_corners == (999,) and outcomes[3].dropped_factors == 1
    assert "Indeterminate" in caplog.text and "dropped 0 new plane and 1 new corner" in caplog.text
    assert 999 not in landmarks.corner_ids
    assert not smoother.estimate.exists(CALLER_KEYS.corner(999))
    for i in range(8):
        assert_pose_close(
            smoother.estimate.atPose3(CALLER_KEYS.pose(i)).matrix(), T_true[i], 0.01, 0.5
        )
    # the other landmarks of frame 3 made it in
    assert set(observations[3].plane_truth.values()) <= set(landmarks.plane_ids)


def test_the_callers_own_indeterminate_pose_is_a_named_error(circle):
    """A second pose with neither odometry nor a prior, seeing too few planes."""
    _, T_true, _, observations = circle
    smoother = RecoveringISAM2()
    landmarks = PlaneLandmarks(CALLER_KEYS)
    x = CALLER_KEYS.pose
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(x(0), gtsam.Pose3(T_true[0]), PRIOR))
    values.insert(x(0), gtsam.Pose3(T_true[0]))
    smoother.update(graph, values)
    obs = observations[1]
    two = dict(list(obs.plane_truth.items())[:2])  # two planes: a pose is not fixed by them
    ours, our_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    added = landmarks.add_observations(ours, our_values, x(1), T_true[1], obs, two)
    values = gtsam.Values()
    values.insert(x(1), gtsam.Pose3(T_true[1]))
    with pytest.raises(GeometryError, match="odometry factor or a prior"):
        smoother.update(gtsam.NonlinearFactorGraph(), values, added, landmarks)
    assert smoother.failures >= 1


# ---------------------------------------------------------------- objects


def test_objects_need_whole_observations(circle):
    _, T_true, _, observations = circle
    landmarks = landmarks_from(observations, T_true, [0])
    with pytest.raises(MapError, match="give add_observations the front end's FrameObservation"):
        landmarks.objects()


@pytest.mark.integration
def test_objects_from_the_landmark_layer_on_rendered_frames():
    """The real front end on rendered depth, the caller's own poses: the landmark layer
    finds the paper's box and room with their sizes, in landmark ids."""
    from planeslam import FrontEnd, load_config
    from planeslam.sim.render import render_frame

    scene, trajectory = box_room_circle(frames=24)
    config = load_config("synthetic")
    front_end = FrontEnd(config)
    rng = np.random.default_rng(2)
    landmarks = PlaneLandmarks(CALLER_KEYS)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i in range(0, 24, 2):
        T = trajectory.T_world_cam[i]
        observation = front_end.process(render_frame(scene, T, config.camera, rng).depth_m, i)
        ids = landmarks.associate(observation, gtsam.Pose3(T))
        landmarks.add_observations(graph, values, CALLER_KEYS.pose(i), T, observation, *ids)
    objects = {o.cls: o for o in landmarks.objects()}
    assert {"box", "room"} <= set(objects), landmarks.objects()
    true = {o.name: np.array(sorted(o.size_m, reverse=True)) for o in scene.objects}
    box_err = np.abs(np.array(objects["box"].size_m) - true["box"])
    assert box_err.mean() < 0.02, objects["box"]
    room_err = np.abs(np.array(objects["room"].size_m[:2]) - true["room"][:2])
    assert room_err.mean() < 0.03, objects["room"]
    for obj in objects.values():
        assert set(obj.planes) <= set(landmarks.plane_ids) and len(obj.planes) >= 3
        assert set(obj.corners) <= set(landmarks.corner_ids)


def test_a_landmark_missed_by_association_keeps_its_own_map_plane():
    """Association hands out new landmarks for planes that already have one (a prediction
    off by more than the gates); the object layer keeps them apart instead of consolidating
    them into the old landmarks' map planes, so a frame seeing an old and a new landmark of
    one plane merges (TUM fr1/desk frames 7-8 had failed with 'plane pairs are not
    one-to-one')."""
    from planeslam import FrontEnd, load_config
    from planeslam.sim.render import render_frame

    scene, trajectory = box_room_circle(frames=24)
    config = load_config("synthetic")
    front_end = FrontEnd(config)
    rng = np.random.default_rng(3)
    T = trajectory.T_world_cam[0]
    observations = [
        front_end.process(render_frame(scene, T, config.camera, rng).depth_m, float(i))
        for i in range(3)
    ]
    planes = [p.id for p in observations[0].segmentation.planes]
    assert len(planes) >= 2
    landmarks = PlaneLandmarks(CALLER_KEYS)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    landmarks.add_observations(graph, values, 0, T, observations[0], {p: p for p in planes})
    missed = {p: 100 + p for p in planes}  # the same planes again, as new landmarks
    landmarks.add_observations(graph, values, 1, T, observations[1], missed)
    one_of_each = {planes[0]: planes[0], planes[1]: 100 + planes[0]}
    landmarks.add_observations(graph, values, 2, T, observations[2], one_of_each)
    owners = landmarks._objects._map_plane
    assert len(set(owners.values())) == len(owners), owners


def test_a_failed_add_leaves_the_graph_values_and_table_as_they_were(circle):
    _, T_true, _, observations = circle
    landmarks = landmarks_from(observations, T_true, [0])
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    before = (graph.size(), values.size(), landmarks.plane_ids, landmarks.corner_ids)
    obs = observations[5]
    plane_ids, corner_ids = landmarks.associate(obs, T_true[5])
    assert set(plane_ids.values()) - set(landmarks.plane_ids), "the frame should add landmarks"
    bad_corner = {**corner_ids, len(obs.corners) + 3: 999}
    with pytest.raises(AssociationError, match=r"corner_ids names corners \[\d+\]"):
        landmarks.add_observations(graph, values, 5, T_true[5], obs, plane_ids, bad_corner)
    off = T_true[5].copy()
    off[:3, :3] = off[:3, :3] @ (np.eye(3) + 1e-3 * np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0]]))
    with pytest.raises(GeometryError, match="rotation block is .* from orthonormal"):
        landmarks.add_observations(graph, values, 5, off, obs, plane_ids, corner_ids)
    bad_plane = dataclasses.replace(obs.planes[0], covariance=np.full((3, 3), np.nan))
    broken = dataclasses.replace(obs, planes=(bad_plane, *obs.planes[1:]))
    with pytest.raises(GeometryError, match="covariance of shape"):
        landmarks.add_observations(graph, values, 5, T_true[5], broken, plane_ids, corner_ids)
    assert (graph.size(), values.size(), landmarks.plane_ids, landmarks.corner_ids) == before


def test_poses_from_four_decimal_quaternions_are_re_orthonormalised(circle):
    """A rotation made from a quaternion of a TUM file as written (4 decimals, not unit:
    |R R^T - I| = 4.5e-5) passes both `associate` and `add_observations` (with the object
    layer), giving the landmarks of the re-orthonormalised pose."""
    _, T_true, _, observations = circle
    R_tum = _unnormalised_matrix(np.array([0.7907, 0.4393, -0.1770, -0.3879]))  # fr1/desk row 1
    T = T_true[3].copy()
    T[:3, :3] = T[:3, :3] @ R_tum @ orthonormalize_pose(np.pad(R_tum, (0, 1)))[:3, :3].T
    off = np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max()
    assert 1e-6 < off < 1e-4
    results = []
    for pose in (T, orthonormalize_pose(T)):
        landmarks = PlaneLandmarks(LandmarkKeys())
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        ids = landmarks.associate(observations[3], pose)
        landmarks.add_observations(graph, values, 3, pose, observations[3], *ids)
        results.append(landmarks.plane_estimates())
    for j, estimate in results[0].items():
        np.testing.assert_allclose(results[1][j].n_world, estimate.n_world, atol=1e-15)


def _unnormalised_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """The rotation formula applied to a quaternion that is not exactly unit (as a reader
    that does not normalise it would), |R R^T - I| ~ 2 |1 - |q|^2|."""
    x, y, z, w = q_xyzw
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_front_end_from_a_bare_camera_config_or_a_clear_error():
    from planeslam.sim.render import render_frame

    scene, trajectory = box_room_circle(frames=24)
    camera = planeslam.load_config("synthetic").camera
    front_end = planeslam.FrontEnd(camera)  # the other sections at their defaults
    assert isinstance(front_end.config, planeslam.FrontEndConfig)
    depth_m = render_frame(scene, trajectory.T_world_cam[0], camera, np.random.default_rng(0))
    assert len(front_end.process(depth_m.depth_m).segmentation.planes) >= 4
    with pytest.raises(planeslam.ConfigError, match="a dict without camera, sensor"):
        planeslam.FrontEnd({"camera": camera})


def test_the_dataset_readers_are_top_level():
    from planeslam.io.rosbag import RosBagDataset
    from planeslam.io.sequence import open_dataset

    assert planeslam.RosBagDataset is RosBagDataset and planeslam.open_dataset is open_dataset
    assert planeslam.TumDataset.__module__ == "planeslam.io.dataset"
