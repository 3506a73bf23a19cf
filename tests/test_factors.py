"""GTSAM factors: numerical Jacobians on the manifold, oracles against built-ins, optimisation."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11
from helpers import assert_pose_close

from planeslam.core.errors import ConfigError, GeometryError
from planeslam.factors import (
    LandmarkKeys,
    corner_factor,
    orthogonal_planes_factor,
    parallel_planes_factor,
    plane_factor,
    point_on_plane_factor,
    robust_plane_factor,
    same_plane_factor,
    structural_factor,
)

pytestmark = pytest.mark.unit

KEYS = LandmarkKeys()
X0, P0, P1, C0 = KEYS.pose(0), KEYS.plane(0), KEYS.plane(1), KEYS.corner(0)
SEEDS = range(8)
NO_ROBUST = 1e9  # Huber threshold beyond any residual: weight 1, linearisation unwhitened


# ---------------------------------------------------------------- helpers


def random_pose(rng: np.random.Generator) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(scale=2.0, size=3))


def random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_plane(rng: np.random.Generator, d_min: float = 0.5) -> gtsam.OrientedPlane3:
    return gtsam.OrientedPlane3(np.r_[random_unit(rng), rng.uniform(d_min, 4.0)])


def observation_setup(rng: np.random.Generator):
    """Pose, camera-frame measurement (d > 0) and a world landmark a little off it."""
    T_world_cam = random_pose(rng)
    z_cam = random_plane(rng, d_min=1.0)
    plane_world = z_cam.transform(T_world_cam.inverse())
    plane_world = plane_world.retract(rng.normal(scale=0.1, size=3))
    return T_world_cam, z_cam, plane_world


def values_of(*pairs) -> gtsam.Values:
    values = gtsam.Values()
    for key, value in pairs:
        values.insert(key, value)
    return values


def analytic_jacobians(factor, values: gtsam.Values, dims: list[int]) -> list[np.ndarray]:
    """Jacobian blocks of a factor built with unit noise (A of the linearisation)."""
    A, _ = factor.linearize(values).jacobian()
    return np.split(A, np.cumsum(dims)[:-1], axis=1)


def numerical_jacobians(factor, values: gtsam.Values, members: list) -> list[np.ndarray]:
    """Central differences of the unwhitened error through each variable's retract."""
    blocks = []
    for key, value in members:

        def error_at(x, key=key):
            perturbed = gtsam.Values(values)
            perturbed.update(key, x)
            return factor.unwhitenedError(perturbed)

        blocks.append(numericalDerivative11(error_at, value, delta=1e-6))
    return blocks


def assert_jacobians_match(factor, members: list, dims: list[int], atol: float = 1e-7) -> None:
    values = values_of(*members)
    analytic = analytic_jacobians(factor, values, dims)
    numerical = numerical_jacobians(factor, values, members)
    for i, (Ha, Hn) in enumerate(zip(analytic, numerical, strict=True)):
        np.testing.assert_allclose(Ha, Hn, atol=atol, err_msg=f"Jacobian block {i}")


# ---------------------------------------------------------------- keys


def test_keys_use_chosen_characters_and_reject_collisions():
    keys = LandmarkKeys(pose_char="a", plane_char="b", corner_char="q")
    assert gtsam.Symbol(keys.pose(7)).chr() == ord("a")
    assert gtsam.Symbol(keys.plane(3)).index() == 3
    assert gtsam.Symbol(keys.corner(5)).chr() == ord("q")
    assert len({keys.pose(1), keys.plane(1), keys.corner(1)}) == 3
    with pytest.raises(ConfigError, match="distinct"):
        LandmarkKeys(pose_char="x", plane_char="x")
    with pytest.raises(ConfigError, match="one printable"):
        LandmarkKeys(corner_char="cc")
    with pytest.raises(ConfigError, match="index"):
        keys.pose(-1)


# ---------------------------------------------------------------- plane observation


@pytest.mark.parametrize("seed", SEEDS)
def test_robust_plane_factor_matches_builtin(seed):
    rng = np.random.default_rng(seed)
    T_world_cam, z_cam, plane_world = observation_setup(rng)
    values = values_of((X0, T_world_cam), (P0, plane_world))
    builtin = plane_factor(z_cam, np.eye(3), X0, P0)
    ours = robust_plane_factor(z_cam.planeCoefficients(), np.eye(3), X0, P0, k=NO_ROBUST)
    np.testing.assert_allclose(
        ours.unwhitenedError(values), builtin.unwhitenedError(values), atol=1e-9
    )
    assert np.linalg.norm(builtin.unwhitenedError(values)) > 1e-3  # not at the trivial zero
    for Ho, Hb in zip(
        analytic_jacobians(ours, values, [6, 3]),
        analytic_jacobians(builtin, values, [6, 3]),
        strict=True,
    ):
        np.testing.assert_allclose(Ho, Hb, atol=1e-9)
    # with a full covariance both whiten the same way (inlier: robust weight 1)
    L = rng.normal(scale=0.05, size=(3, 3))
    cov = L @ L.T + 1e-4 * np.eye(3)
    Ab, bb = plane_factor(z_cam, cov, X0, P0).linearize(values).jacobian()
    Ao, bo = robust_plane_factor(z_cam, cov, X0, P0, k=NO_ROBUST).linearize(values).jacobian()
    np.testing.assert_allclose(Ao, Ab, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(bo, bb, rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_plane_factors_numerical_jacobians(seed, loss):
    rng = np.random.default_rng(seed)
    T_world_cam, z_cam, plane_world = observation_setup(rng)
    members = [(X0, T_world_cam), (P0, plane_world)]
    assert_jacobians_match(plane_factor(z_cam, np.eye(3), X0, P0), members, [6, 3])
    robust = robust_plane_factor(z_cam, np.eye(3), X0, P0, loss=loss, k=NO_ROBUST)
    assert_jacobians_match(robust, members, [6, 3])


def test_plane_error_definition_and_zero_at_truth(rng):
    T_world_cam = random_pose(rng)
    plane_world = random_plane(rng)
    z_cam = plane_world.transform(T_world_cam)
    if z_cam.distance() < 0:  # orient toward the camera, as the front end does
        plane_world = gtsam.OrientedPlane3(-plane_world.planeCoefficients())
        z_cam = plane_world.transform(T_world_cam)
    values = values_of((X0, T_world_cam), (P0, plane_world))
    factor = robust_plane_factor(z_cam, np.eye(3), X0, P0)
    np.testing.assert_allclose(factor.unwhitenedError(values), np.zeros(3), atol=1e-12)
    # offset error: shifting the landmark by delta along its normal changes d_cam by delta
    shifted = gtsam.OrientedPlane3(plane_world.normal(), plane_world.distance() + 0.3)
    values.update(P0, shifted)
    np.testing.assert_allclose(factor.unwhitenedError(values), [0.0, 0.0, 0.3], atol=1e-12)


def test_robust_plane_factor_downweights_outlier():
    sigma, k = 0.01, 1.345
    cov = sigma**2 * np.eye(3)
    T_world_cam = gtsam.Pose3()
    z_cam = gtsam.OrientedPlane3(0.0, 0.0, 1.0, 2.0)
    gauss = plane_factor(z_cam, cov, X0, P0)
    huber = robust_plane_factor(z_cam, cov, X0, P0, loss="huber", k=k)
    cauchy = robust_plane_factor(z_cam, cov, X0, P0, loss="cauchy", k=k)
    for offset_error in (0.005, 0.5):  # 0.5 sigma inlier, 50 sigma outlier
        landmark = gtsam.OrientedPlane3(0.0, 0.0, 1.0, 2.0 + offset_error)
        values = values_of((X0, T_world_cam), (P0, landmark))
        r = offset_error / sigma  # whitened residual norm
        assert gauss.error(values) == pytest.approx(0.5 * r**2, rel=1e-9)
        huber_loss = 0.5 * r**2 if r <= k else k * r - 0.5 * k**2
        assert huber.error(values) == pytest.approx(huber_loss, rel=1e-9)
        assert cauchy.error(values) == pytest.approx(
            0.5 * k**2 * math.log1p((r / k) ** 2), rel=1e-9
        )
        # IRLS weight on the linearised system: sqrt(w) scales rows, w = k / r beyond k
        A_g, _ = gauss.linearize(values).jacobian()
        A_h, _ = huber.linearize(values).jacobian()
        weight = 1.0 if r <= k else k / r
        np.testing.assert_allclose(A_h, math.sqrt(weight) * A_g, rtol=1e-9, atol=1e-9)
    assert huber.error(values) < 0.06 * gauss.error(values)  # 66.3 vs 1250


def test_plane_factor_rejects_bad_input():
    with pytest.raises(GeometryError, match="d > 0"):
        plane_factor(np.array([0.0, 0.0, 1.0, -2.0]), np.eye(3), X0, P0)
    with pytest.raises(GeometryError, match="positive definite"):
        plane_factor(np.array([0.0, 0.0, 1.0, 2.0]), np.diag([1.0, 1.0, -1.0]), X0, P0)
    with pytest.raises(ConfigError, match="loss"):
        robust_plane_factor(np.array([0.0, 0.0, 1.0, 2.0]), np.eye(3), X0, P0, loss="tukey")
    with pytest.raises(ConfigError, match="distinct"):
        plane_factor(np.array([0.0, 0.0, 1.0, 2.0]), np.eye(3), X0, X0)
    # a non-unit normal is rescaled together with its offset (same plane)
    factor = plane_factor(np.array([0.0, 0.0, 2.0, 4.0]), np.eye(3), X0, P0)
    values = values_of((X0, gtsam.Pose3()), (P0, gtsam.OrientedPlane3(0.0, 0.0, 1.0, 2.0)))
    np.testing.assert_allclose(factor.unwhitenedError(values), np.zeros(3), atol=1e-12)


# ---------------------------------------------------------------- corner observation


@pytest.mark.parametrize("seed", SEEDS)
def test_corner_factor_matches_reference_frame_factor_and_numerics(seed):
    rng = np.random.default_rng(seed)
    T_world_cam = random_pose(rng)
    p_world = rng.normal(size=3)
    p_cam = T_world_cam.transformTo(p_world) + rng.normal(scale=0.1, size=3)
    factor = corner_factor(p_cam, np.eye(3), X0, C0)
    members = [(X0, T_world_cam), (C0, p_world)]
    assert_jacobians_match(factor, members, [6, 3])
    # oracle: ReferenceFrameFactor(global, trans, local) has error trans.transformFrom(global)
    # - local; with trans = T_cam_world it is ours, and d trans / d pose = Pose3.inverse's H
    values = values_of(*members)
    oracle = gtsam.ReferenceFrameFactorPoint3Pose3(C0, X0, 99, gtsam.noiseModel.Unit.Create(3))
    oracle_values = values_of((C0, p_world), (X0, T_world_cam.inverse()), (99, p_cam))
    np.testing.assert_allclose(
        factor.unwhitenedError(values), oracle.unwhitenedError(oracle_values), atol=1e-12
    )
    H_point, H_trans, _ = analytic_jacobians(oracle, oracle_values, [3, 6, 3])
    inv_H_pose = np.zeros((6, 6), order="F")
    T_world_cam.inverse(inv_H_pose)
    H_pose_ours, H_point_ours = analytic_jacobians(factor, values, [6, 3])
    np.testing.assert_allclose(H_pose_ours, H_trans @ inv_H_pose, atol=1e-9)
    np.testing.assert_allclose(H_point_ours, H_point, atol=1e-12)


def test_corner_factor_accepts_robust_noise():
    model = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.0), gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    )
    factor = corner_factor(np.array([0.0, 0.0, 1.0]), model, X0, C0)
    values = values_of((X0, gtsam.Pose3()), (C0, np.array([0.0, 0.0, 2.0])))  # 100 sigma off
    assert factor.error(values) == pytest.approx(100.0 - 0.5, rel=1e-9)
    with pytest.raises(GeometryError, match=r"\(3,\)"):
        corner_factor(np.zeros(2), np.eye(3), X0, C0)


# ---------------------------------------------------------------- plane structure


@pytest.mark.parametrize("seed", SEEDS)
def test_structure_factors_numerical_jacobians_and_values(seed):
    rng = np.random.default_rng(seed)
    plane_a, plane_b = random_plane(rng), random_plane(rng)
    members = [(P0, plane_a), (P1, plane_b)]
    values = values_of(*members)
    n_a, n_b = plane_a.normal().point3(), plane_b.normal().point3()
    ortho = orthogonal_planes_factor(P0, P1, 1.0)
    parallel = parallel_planes_factor(P0, P1, 1.0)
    assert_jacobians_match(ortho, members, [3, 3])
    assert_jacobians_match(parallel, members, [3, 3])
    np.testing.assert_allclose(ortho.unwhitenedError(values), [n_a @ n_b], atol=1e-12)
    sin_angle = np.linalg.norm(np.cross(n_a, n_b))
    assert np.linalg.norm(parallel.unwhitenedError(values)) == pytest.approx(sin_angle, rel=1e-9)
    # the offset does not enter either error: zero third column
    for factor in (ortho, parallel):
        for H in analytic_jacobians(factor, values, [3, 3]):
            np.testing.assert_allclose(H[:, 2], 0.0, atol=1e-15)


@pytest.mark.parametrize("seed", SEEDS)
def test_same_plane_factor_numerical_jacobians_and_values(seed):
    rng = np.random.default_rng(seed)
    plane_a = random_plane(rng)
    plane_b = plane_a.retract(rng.normal(scale=0.05, size=3))
    members = [(P0, plane_a), (P1, plane_b)]
    factor = same_plane_factor(P0, P1, 1.0, 1.0, loss=None)
    assert_jacobians_match(factor, members, [3, 3])
    error = factor.unwhitenedError(values_of(*members))
    np.testing.assert_allclose(error, plane_a.errorVector(plane_b), atol=1e-12)
    assert np.linalg.norm(error) > 1e-3  # the two differ, and the error says so
    assert factor.error(values_of((P0, plane_a), (P1, plane_a))) < 1e-20


def test_same_plane_factor_joins_two_landmarks_between_their_observations():
    # Two landmarks of one plane, each seen once (a plane factor per landmark at a fixed
    # pose): the tie pulls each toward the other, to their covariance-weighted mean.
    truth = gtsam.OrientedPlane3(0.0, 0.0, 1.0, 1.0)
    lifted = gtsam.OrientedPlane3(0.0, 0.0, 1.0, 1.02)  # seen 2 cm off
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    graph.add(plane_factor(truth.planeCoefficients(), 1e-4 * np.eye(3), X0, P0))
    graph.add(plane_factor(lifted.planeCoefficients(), 1e-4 * np.eye(3), X0, P1))
    graph.add(same_plane_factor(P0, P1, 1e-3, 1e-3, loss=None))
    values = values_of((P0, truth), (P1, lifted))
    values.insert(X0, gtsam.Pose3())
    result = gtsam.GaussNewtonOptimizer(graph, values).optimize()
    d0, d1 = result.atOrientedPlane3(P0).distance(), result.atOrientedPlane3(P1).distance()
    assert abs(d0 - d1) < 1e-3 and d0 == pytest.approx(1.01, abs=1e-3)


def test_same_plane_factor_rejects_bad_sigmas():
    with pytest.raises(ConfigError, match="sigma_m"):
        same_plane_factor(P0, P1, 0.01, 0.0)
    with pytest.raises(ConfigError, match="distinct"):
        same_plane_factor(P0, P0, 0.01, 0.01)


@pytest.mark.parametrize("seed", SEEDS)
def test_parallel_factor_matches_direction_prior(seed):
    # oracle: OrientedPlane3DirectionPrior(z) has error z.normal.errorVector(plane.normal)
    rng = np.random.default_rng(seed)
    plane_a, plane_b = random_plane(rng), random_plane(rng)
    values = values_of((P0, plane_a), (P1, plane_b))
    prior = gtsam.OrientedPlane3DirectionPrior(
        P1, plane_a.planeCoefficients(), gtsam.noiseModel.Unit.Create(2)
    )
    factor = parallel_planes_factor(P0, P1, 1.0)
    np.testing.assert_allclose(
        factor.unwhitenedError(values), prior.unwhitenedError(values), atol=1e-12
    )
    H_b_prior = prior.linearize(values).jacobian()[0]
    np.testing.assert_allclose(analytic_jacobians(factor, values, [3, 3])[1], H_b_prior, atol=1e-12)


def test_parallel_factor_is_sign_agnostic():
    a = gtsam.OrientedPlane3(1.0, 0.0, 0.0, 2.0)
    tilt = 0.1
    b_same = gtsam.OrientedPlane3(math.cos(tilt), math.sin(tilt), 0.0, 2.0)
    b_facing = gtsam.OrientedPlane3(-math.cos(tilt), -math.sin(tilt), 0.0, 2.0)
    factor = parallel_planes_factor(P0, P1, 0.05)
    e_same = factor.error(values_of((P0, a), (P1, b_same)))
    e_facing = factor.error(values_of((P0, a), (P1, b_facing)))
    assert e_same == pytest.approx(0.5 * (math.sin(tilt) / 0.05) ** 2, rel=1e-9)
    assert e_facing == pytest.approx(e_same, rel=1e-9)
    exactly_facing = gtsam.OrientedPlane3(-1.0, 0.0, 0.0, 2.0)
    assert factor.error(values_of((P0, a), (P1, exactly_facing))) < 1e-20


@pytest.mark.parametrize(
    ("angle_deg", "expected_dim"),
    [
        (90.0, 1),
        (87.5, 1),
        (93.0, 1),
        (0.0, 2),
        (2.0, 2),
        (178.0, 2),
        (180.0, 2),
        (45.0, None),
        (80.0, None),
        (170.0, None),
    ],
)
def test_structural_factor_selection(angle_deg, expected_dim):
    factor = structural_factor(P0, P1, math.radians(angle_deg), math.radians(5.0), 0.01)
    if expected_dim is None:
        assert factor is None
    else:
        assert factor.dim() == expected_dim


def test_structural_factor_rejects_bad_input():
    with pytest.raises(ConfigError, match="tolerance"):
        structural_factor(P0, P1, math.pi / 2, math.radians(50.0), 0.01)
    with pytest.raises(GeometryError, match="angle"):
        structural_factor(P0, P1, 4.0, 0.1, 0.01)
    with pytest.raises(ConfigError, match="sigma"):
        orthogonal_planes_factor(P0, P1, 0.0)


# ---------------------------------------------------------------- point on plane


@pytest.mark.parametrize("seed", SEEDS)
def test_point_on_plane_numerics_and_oracle(seed):
    rng = np.random.default_rng(seed)
    plane = random_plane(rng)
    p_world = rng.normal(scale=2.0, size=3)
    members = [(P0, plane), (C0, p_world)]
    values = values_of(*members)
    factor = point_on_plane_factor(P0, C0, 1.0)
    assert_jacobians_match(factor, members, [3, 3])
    # oracle: the built-in plane factor at pose (I, p) measuring (n, 0) has third error
    # component n . p + d, and (R = I) its translation Jacobian is the point Jacobian
    coeffs = plane.planeCoefficients()
    builtin = gtsam.OrientedPlane3Factor(
        np.r_[coeffs[:3], 0.0], gtsam.noiseModel.Unit.Create(3), X0, P0
    )
    builtin_values = values_of((X0, gtsam.Pose3(gtsam.Rot3(), p_world)), (P0, plane))
    expected = coeffs[:3] @ p_world + coeffs[3]
    np.testing.assert_allclose(factor.unwhitenedError(values), [expected], atol=1e-12)
    assert builtin.unwhitenedError(builtin_values)[2] == pytest.approx(expected, abs=1e-12)
    H_pose_b, H_plane_b = analytic_jacobians(builtin, builtin_values, [6, 3])
    H_plane, H_point = analytic_jacobians(factor, values, [3, 3])
    np.testing.assert_allclose(H_plane, H_plane_b[2:3], atol=1e-12)
    np.testing.assert_allclose(H_point, H_pose_b[2:3, 3:], atol=1e-12)


# ---------------------------------------------------------------- optimisation


ROOM_WORLD = {  # floor + 3 walls, normals into the room (toward every camera)
    0: np.array([0.0, 0.0, 1.0, 0.0]),  # floor z = 0
    1: np.array([1.0, 0.0, 0.0, 2.0]),  # wall x = -2
    2: np.array([0.0, 1.0, 0.0, 2.0]),  # wall y = -2
    3: np.array([-1.0, 0.0, 0.0, 2.0]),  # wall x = +2
}
CORNER_WORLD = np.array([-2.0, -2.0, 0.0])  # floor, wall x = -2, wall y = -2
CORNER_PLANES = (0, 1, 2)


def room_poses() -> list[gtsam.Pose3]:
    """Cameras 1.5 m above the floor, z forward, turning toward the walls."""
    poses = []
    for i, yaw in enumerate(np.linspace(0.0, 1.2, 4)):
        # camera z (forward) horizontal, camera y (down) = world -z
        R = (
            gtsam.Rot3.Rz(math.pi + yaw)
            .compose(gtsam.Rot3.Ry(math.pi / 2))
            .compose(gtsam.Rot3.Rz(-math.pi / 2))
        )
        poses.append(gtsam.Pose3(R, np.array([0.3 * i - 0.5, 0.2 * i, 1.5])))
    return poses


def build_room_graph(keys: LandmarkKeys, poses: list[gtsam.Pose3], odometry: bool = True):
    odo_noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    plane_cov = np.diag([0.01, 0.01, 0.02]) ** 2
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(keys.pose(0), poses[0], odo_noise))
    for i, T_world_cam in enumerate(poses):
        if odometry and i > 0:
            graph.add(
                gtsam.BetweenFactorPose3(
                    keys.pose(i - 1), keys.pose(i), poses[i - 1].between(T_world_cam), odo_noise
                )
            )
        for j, coeffs in ROOM_WORLD.items():
            z_cam = gtsam.OrientedPlane3(coeffs).transform(T_world_cam)
            make = robust_plane_factor if (i + j) % 2 else plane_factor
            graph.add(make(z_cam, plane_cov, keys.pose(i), keys.plane(j)))
        graph.add(
            corner_factor(
                T_world_cam.transformTo(CORNER_WORLD),
                0.01**2 * np.eye(3),
                keys.pose(i),
                keys.corner(0),
            )
        )
    for j in CORNER_PLANES:
        graph.add(point_on_plane_factor(keys.plane(j), keys.corner(0), 0.01))
    for a, b in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]:
        n_a, n_b = ROOM_WORLD[a][:3], ROOM_WORLD[b][:3]
        angle = math.atan2(np.linalg.norm(np.cross(n_a, n_b)), n_a @ n_b)
        factor = structural_factor(keys.plane(a), keys.plane(b), angle, math.radians(5.0), 0.01)
        assert factor is not None
        graph.add(factor)
    return graph


def perturbed_values(keys: LandmarkKeys, poses, rng: np.random.Generator) -> gtsam.Values:
    values = gtsam.Values()
    for i, T_world_cam in enumerate(poses):
        values.insert(keys.pose(i), T_world_cam.retract(rng.normal(scale=0.05, size=6)))
    for j, coeffs in ROOM_WORLD.items():
        values.insert(
            keys.plane(j), gtsam.OrientedPlane3(coeffs).retract(rng.normal(scale=0.05, size=3))
        )
    values.insert(keys.corner(0), CORNER_WORLD + rng.normal(scale=0.1, size=3))
    return values


def assert_room_recovered(keys, poses, result, trans_tol_m, plane_tol):
    for i, T_world_cam in enumerate(poses):
        assert_pose_close(
            result.atPose3(keys.pose(i)).matrix(),
            T_world_cam.matrix(),
            trans_tol_m,
            math.degrees(trans_tol_m),
        )
    for j, coeffs in ROOM_WORLD.items():
        np.testing.assert_allclose(
            result.atOrientedPlane3(keys.plane(j)).planeCoefficients(), coeffs, atol=plane_tol
        )
    np.testing.assert_allclose(result.atPoint3(keys.corner(0)), CORNER_WORLD, atol=plane_tol)


def test_room_converges_with_levenberg_marquardt_and_isam2():
    keys = LandmarkKeys(pose_char="X", plane_char="P", corner_char="K")  # caller's characters
    poses = room_poses()
    for T_world_cam in poses:  # every camera sees every plane from the front
        for coeffs in ROOM_WORLD.values():
            assert gtsam.OrientedPlane3(coeffs).transform(T_world_cam).distance() > 0.1
    graph = build_room_graph(keys, poses)
    initial = perturbed_values(keys, poses, np.random.default_rng(7))
    assert graph.error(initial) > 1e3

    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert graph.error(result) < 1e-12
    assert_room_recovered(keys, poses, result, 1e-6, 1e-6)

    isam_params = gtsam.ISAM2Params()
    isam_params.relinearizeSkip = 1  # default 10: relinearise on every update here
    isam_params.setRelinearizeThreshold(1e-9)
    isam = gtsam.ISAM2(isam_params)
    isam.update(graph, initial)
    for _ in range(6):
        isam.update()
    estimate = isam.calculateEstimate()
    assert_room_recovered(keys, poses, estimate, 1e-4, 1e-4)


def test_two_planes_without_odometry_is_indeterminate_and_odometry_fixes_it():
    keys = LandmarkKeys()
    poses = room_poses()[:2]
    plane_cov = np.diag([0.01, 0.01, 0.02]) ** 2
    noise6 = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)

    def graph_and_values(odometry: bool):
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(keys.pose(0), poses[0], noise6))
        for j, coeffs in ROOM_WORLD.items():  # pose 0 fixes all four planes
            z_cam = gtsam.OrientedPlane3(coeffs).transform(poses[0])
            graph.add(plane_factor(z_cam, plane_cov, keys.pose(0), keys.plane(j)))
        for j in (0, 1):  # pose 1 sees only the floor and one wall
            z_cam = gtsam.OrientedPlane3(ROOM_WORLD[j]).transform(poses[1])
            graph.add(robust_plane_factor(z_cam, plane_cov, keys.pose(1), keys.plane(j)))
        if odometry:
            graph.add(
                gtsam.BetweenFactorPose3(
                    keys.pose(0), keys.pose(1), poses[0].between(poses[1]), noise6
                )
            )
        values = gtsam.Values()
        for i, T_world_cam in enumerate(poses):
            values.insert(keys.pose(i), T_world_cam)
        for j, coeffs in ROOM_WORLD.items():
            values.insert(keys.plane(j), gtsam.OrientedPlane3(coeffs))
        return graph, values

    graph, values = graph_and_values(odometry=False)
    with pytest.raises(RuntimeError, match="Indeterminate linear system"):
        gtsam.ISAM2().update(graph, values)
    with pytest.raises(RuntimeError, match="Indeterminate linear system"):
        gtsam.GaussNewtonOptimizer(graph, values).optimize()

    graph, values = graph_and_values(odometry=True)
    isam = gtsam.ISAM2()
    isam.update(graph, values)
    assert_pose_close(
        isam.calculateEstimate().atPose3(keys.pose(1)).matrix(), poses[1].matrix(), 1e-9, 1e-7
    )


def test_fit_covariance_matches_the_factor_error_statistics() -> None:
    """Monte Carlo: fit a plane to noisy points of a patch far off the optical axis (so the
    normal/offset cross terms are large); the spread of the built-in factor's error at the
    true pose and plane must match `error_covariance(fit covariance)`, cross-term signs
    included (the fit covariance itself has them the other way round)."""
    from planeslam.core.plane_fit import moments_of, plane_covariance, plane_from_moments
    from planeslam.factors.plane_observation import error_covariance

    rng = np.random.default_rng(7)
    n_true = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    d_true = 2.0
    u = np.cross(n_true, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n_true, u)
    centre = -d_true * n_true + 1.2 * u + 0.8 * v  # the patch sits 1.4 m off the axis
    errors, covs = [], []
    for _ in range(400):
        a, b = rng.uniform(-0.3, 0.3, size=(2, 200))
        pts = centre + np.outer(a, u) + np.outer(b, v) + rng.normal(0, 0.01, (200, 1)) * n_true
        count, centroid, scatter = moments_of(pts)
        n_fit, d_fit, rss = plane_from_moments(centroid, scatter)
        covs.append(plane_covariance(n_fit, centroid, scatter, count, rss))
        factor = plane_factor(np.r_[n_fit, d_fit], np.eye(3), X0, P0)
        values = gtsam.Values()
        values.insert(X0, gtsam.Pose3())
        values.insert(P0, gtsam.OrientedPlane3(np.r_[n_true, d_true]))
        errors.append(factor.unwhitenedError(values))
    empirical = np.cov(np.array(errors).T)
    predicted = error_covariance(np.mean(covs, axis=0))
    corr = empirical[:2, 2] / np.sqrt(np.diag(empirical)[:2] * empirical[2, 2])
    assert np.all(np.abs(corr) > 0.3)  # the cross terms matter for this patch
    np.testing.assert_allclose(empirical, predicted, rtol=0.3, atol=0.15 * np.abs(predicted).max())
    assert np.all(np.sign(empirical[:2, 2]) == np.sign(predicted[:2, 2]))
