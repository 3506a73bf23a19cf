"""The robust pose estimator over planes, points and line ends: numerical Jacobians on the
manifold, exact recovery, what fills the directions planes leave free, and robustness."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import assert_pose_close

from planeslam.core.geometry import invert_pose, pose_from_quat, transform_plane
from planeslam.tracking.estimator import (
    ConstraintThresholds,
    EstimatorSettings,
    LineTerms,
    PlaneTerms,
    PointTerms,
    Primitive,
    _plane_bases,
    _point_whiteners,
    _whitener,
    constraints,
    estimate_pose,
    fully_constrained,
    warm_up,
)
from planeslam.tracking.estimator_kernels import (
    gauss_newton_kernel,
    line_term,
    plane_term,
    point_term,
)
from planeslam.tracking.estimator_kernels import retract as _retract

pytestmark = pytest.mark.unit

T_TRUE = pose_from_quat(np.array([0.4, -0.2, 1.1]), np.array([0.1, 0.2, -0.05, 0.97]))


def planes_seen(T_world_cam: np.ndarray, n_world: np.ndarray, d_world: np.ndarray) -> PlaneTerms:
    """Noise-free observations of world planes from T_world_cam, normals facing the camera."""
    T_cam_world = invert_pose(T_world_cam)
    n_cam, d_cam, n_w, d_w = [], [], [], []
    for n, d in zip(n_world, d_world, strict=True):
        nc, dc = transform_plane(T_cam_world, n, d)
        sign = 1.0 if dc > 0 else -1.0
        n_cam.append(sign * nc)
        d_cam.append(sign * dc)
        n_w.append(sign * np.asarray(n))
        d_w.append(sign * d)
    N = len(n_cam)
    return PlaneTerms(
        np.array(n_cam), np.array(d_cam), np.array(n_w), np.array(d_w), np.zeros((N, 3, 3))
    )


def points_seen(T_world_cam: np.ndarray, p_world: np.ndarray, sigma: float = 0.01) -> PointTerms:
    p_cam = (p_world - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    cov = np.broadcast_to(sigma**2 * np.eye(3), (len(p_world), 3, 3)).copy()
    return PointTerms(p_cam, p_world, cov, cov)


ROOM_N = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
ROOM_D = np.array([1.0, 2.0, 1.5, 1.5])


def numeric_jacobian(system, T: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    e0 = system(T)[0]
    J = np.zeros(e0.shape + (6,))
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        J[..., k] = (system(_retract(T, xi))[0] - system(_retract(T, -xi))[0]) / (2 * eps)
    return J


def _whitened(
    T: np.ndarray, term, arguments: list[tuple], W: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(K, r) whitened residuals and (K, r, 6) Jacobians at T of the compiled `term`, called
    once per entry of `arguments`, each whitened by W (K, r, r)."""
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
    e, J = zip(*(term(R, t, *args) for args in arguments), strict=True)
    return (W @ np.array(e)[:, :, None])[:, :, 0], W @ np.array(J)


@pytest.mark.parametrize("kind", ["plane", "point", "line"])
def test_jacobians_match_numerical_derivatives(kind: str, rng: np.random.Generator) -> None:
    """Analytic Jacobians of the compiled terms against central differences on the
    manifold, away from the truth (non-zero residuals) so every term of the derivative
    matters."""
    T = T_TRUE @ _retract(np.eye(4), rng.normal(0, 0.05, 6))
    if kind == "plane":
        terms = planes_seen(T_TRUE, ROOM_N[:3], ROOM_D[:3])
        cov = np.broadcast_to(np.diag([1e-4, 2e-4, 1e-5]), (3, 3, 3))
        terms = PlaneTerms(terms.n_cam, terms.d_cam, terms.n_world, terms.d_world, cov)
        bases, W = _plane_bases(terms), _whitener(terms.covariance)
        arguments = [
            (terms.n_cam[i], terms.d_cam[i], terms.n_world[i], terms.d_world[i], bases[i])
            for i in range(len(terms))
        ]
        term = plane_term
    elif kind == "point":
        terms = points_seen(T_TRUE, rng.uniform(-1, 1, (5, 3)) + [0, 0, 3])
        W = _point_whiteners(T, terms)
        arguments = list(zip(terms.p_cam, terms.p_world, strict=True))
        term = point_term
    else:
        p_cam = rng.uniform(-1, 1, (4, 3)) + [0, 0, 2]
        u = rng.normal(size=(4, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        arguments = list(zip(p_cam, u, rng.normal(size=(4, 3)), strict=True))
        W = np.full((4, 1, 1), 1 / 0.03)
        term = line_term

    def system(X):
        return _whitened(X, term, arguments, W)

    _, J = system(T)
    assert np.abs(J).max() > 0.1, "the Jacobian must not be zero for the test to mean anything"
    np.testing.assert_allclose(J, numeric_jacobian(system, T), atol=1e-5)


def test_planes_and_points_recover_the_pose_exactly(rng: np.random.Generator) -> None:
    start = T_TRUE @ _retract(np.eye(4), np.r_[0.1, -0.05, 0.08, 0.2, 0.1, -0.15])
    points = points_seen(T_TRUE, rng.uniform(-2, 2, (30, 3)))
    est = estimate_pose(
        start, planes_seen(T_TRUE, ROOM_N, ROOM_D), [points], None, EstimatorSettings()
    )
    assert_pose_close(est.T_world_cam, T_TRUE, 1e-8, 1e-6)
    assert est.plane_inliers.all() and est.point_inliers[0].all()


def test_corridor_planes_leave_one_direction_to_points(rng: np.random.Generator) -> None:
    """Floor and two parallel walls fix rotation and two translation directions; the
    corridor's axis comes from the keypoints, and the report says so."""
    corridor = planes_seen(T_TRUE, ROOM_N[[0, 2, 3]], ROOM_D[[0, 2, 3]])
    points = points_seen(T_TRUE, rng.uniform(-1, 1, (40, 3)) + [3.0, 0.0, 0.0])
    start = T_TRUE @ _retract(np.eye(4), np.r_[0.02, 0.01, -0.02, 0.1, -0.05, 0.05])
    thresholds = ConstraintThresholds()
    est = estimate_pose(start, corridor, [points], None, EstimatorSettings())
    found = constraints(est, thresholds, {})
    assert (found.plane_rotation_dof, found.plane_translation_dof) == (3, 2)
    assert found.filled_by == (Primitive.POINTS,)
    assert not found.free and fully_constrained(est, thresholds)
    assert_pose_close(est.T_world_cam, T_TRUE, 1e-8, 1e-6)
    alone = estimate_pose(start, corridor, [], None, EstimatorSettings())
    assert not fully_constrained(alone, thresholds)
    assert constraints(alone, thresholds, {}).free == ("translation",)


def test_line_end_fills_the_corridor_axis() -> None:
    """Two walls meeting in a vertical edge fix rotation and the two horizontal directions;
    the edge's end point (where it meets the floor) fixes the height."""
    walls = planes_seen(T_TRUE, ROOM_N[[1, 2]], ROOM_D[[1, 2]])
    edge_point_world = np.array([-2.0, -1.5, 0.3])  # on both walls
    p_cam = (edge_point_world - T_TRUE[:3, 3]) @ T_TRUE[:3, :3]
    line = LineTerms(p_cam[None], np.array([[0.0, 0.0, 1.0]]), edge_point_world[None])
    start = T_TRUE @ _retract(np.eye(4), np.r_[0.01, 0.0, 0.01, 0.05, 0.05, -0.05])
    est = estimate_pose(start, walls, [], line, EstimatorSettings())
    found = constraints(est, ConstraintThresholds(), {})
    assert (found.plane_rotation_dof, found.plane_translation_dof) == (3, 2)
    assert Primitive.LINES in found.filled_by
    assert_pose_close(est.T_world_cam, T_TRUE, 1e-8, 1e-6)


def test_outlier_points_do_not_move_the_pose(rng: np.random.Generator) -> None:
    points = points_seen(T_TRUE, rng.uniform(-2, 2, (60, 3)) + [0, 0, 2])
    bad = np.arange(0, 60, 5)  # 20 % of the matches 0.3-0.6 m off
    p_world = points.p_world.copy()
    p_world[bad] += rng.uniform(0.3, 0.6, (len(bad), 3))
    points = PointTerms(points.p_cam, p_world, points.cov_cam, points.cov_world)
    est = estimate_pose(
        T_TRUE, planes_seen(T_TRUE, ROOM_N, ROOM_D), [points], None, EstimatorSettings()
    )
    assert_pose_close(est.T_world_cam, T_TRUE, 0.005, 0.3)
    assert not est.point_inliers[0][bad].any()


def test_every_estimate_uses_one_compiled_signature(rng: np.random.Generator) -> None:
    """`estimate_pose` hands the kernel the same argument types whatever it is given (no
    terms, strided or float32 arrays, several point sets, line ends), so the kernel that
    `warm_up` compiles at start-up is the only one: no compilation mid-run."""
    warm_up()
    planes = planes_seen(T_TRUE, ROOM_N, ROOM_D)
    strided = PlaneTerms(
        np.asfortranarray(planes.n_cam),
        planes.d_cam.astype(np.float32),
        planes.n_world[::1],
        list(planes.d_world),
        np.full((len(ROOM_D), 3, 3), 1e-4 * np.eye(3)),
    )
    points = points_seen(T_TRUE, rng.uniform(-1, 1, (6, 3)) + [0, 0, 3])
    lines = LineTerms(*(rng.normal(size=(6, 3))[::2] for _ in range(3)))
    for terms in ((None, [], None), (strided, [points, points], lines), (None, [points], None)):
        estimate_pose(T_TRUE, *terms, EstimatorSettings())
    assert len(gauss_newton_kernel.signatures) == 1, gauss_newton_kernel.signatures
