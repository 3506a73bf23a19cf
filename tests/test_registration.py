"""Closed-form registration from planes / points and ICP refinement, on exact synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import assert_pose_close
from scipy.spatial.transform import Rotation

from planeslam.core.errors import GeometryError
from planeslam.core.geometry import invert_pose, transform_points
from planeslam.tracking.registration import (
    RegistrationStatus,
    pose_from_planes,
    pose_from_planes_and_points,
    pose_from_points,
    refine_icp,
)

pytestmark = pytest.mark.unit

# ----------------------------------------------------------------------------- synthetic truth


def make_pose(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def random_pose(rng: np.random.Generator, max_angle_rad: float, max_trans_m: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return make_pose(axis * rng.uniform(0, max_angle_rad), rng.uniform(-1, 1, 3) * max_trans_m)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def planes_through(normals: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes with the given normals through the given anchor points: d = -n . c."""
    n = unit(normals)
    return n, -np.einsum("ij,ij->i", n, anchors)


def map_planes(T_dst_src: np.ndarray, n_src: np.ndarray, d_src: np.ndarray):
    """Vectorised geometry.transform_plane."""
    n_dst = n_src @ T_dst_src[:3, :3].T
    return n_dst, d_src - n_dst @ T_dst_src[:3, 3]


def random_planes(rng: np.random.Generator, count: int):
    """Well-spread planes anchored 1-4 m from the origin (a camera's view)."""
    anchors = unit(rng.normal(size=(count, 3))) * rng.uniform(1.0, 4.0, (count, 1))
    return planes_through(rng.normal(size=(count, 3)), anchors), anchors


def perturb_planes(rng, n, anchors, sigma_angle_rad, sigma_offset_m):
    """Tilt each normal about its anchor (rms tilt sigma_angle_rad), add offset noise."""
    rotvec = rng.normal(size=n.shape) * sigma_angle_rad / np.sqrt(2.0)
    rotvec -= np.einsum("ij,ij->i", rotvec, n)[:, None] * n  # tilt axes perpendicular to n
    n_noisy = np.einsum("kij,kj->ki", Rotation.from_rotvec(rotvec).as_matrix(), n)
    n_noisy, d_noisy = planes_through(n_noisy, anchors)
    return n_noisy, d_noisy + rng.normal(size=len(n)) * sigma_offset_m


def corridor():
    """Floor + two facing parallel walls (normals toward a camera in the middle); axis z."""
    n = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])  # y down: floor below
    d = np.array([1.2, 1.0, 1.0])
    return n, d


# ----------------------------------------------------------------------------- planes

LARGE_MOTIONS = [
    make_pose(np.array([0.0, 0.0, np.pi / 2]), np.array([3.0, -2.0, 1.5])),
    make_pose(np.array([np.pi / 2, 0.0, 0.0]), np.array([-5.0, 0.5, 0.0])),
    make_pose(unit([1.0, 1.0, 0.0]) * np.pi, np.array([0.0, 0.0, 4.0])),  # half turn
    make_pose(unit([0.3, -1.0, 0.2]) * 2.5, np.array([1.0, 2.0, -3.0])),
]


@pytest.mark.parametrize("T_true", LARGE_MOTIONS)
def test_planes_noise_free_exact_for_large_motions(rng, T_true):
    (n_src, d_src), _ = random_planes(rng, 5)
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes(n_src, d_src, n_dst, d_dst)
    assert res.status is RegistrationStatus.OK and res.ok
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)
    assert res.rotation_observability > 0.05 and res.translation_observability > 0.01
    np.testing.assert_allclose(res.plane_angle_residual_rad, 0.0, atol=1e-9)
    np.testing.assert_allclose(res.plane_offset_residual_m, 0.0, atol=1e-9)
    assert res.unobservable_rotation_axes.shape == (0, 3)
    assert res.unobservable_translation_dirs.shape == (0, 3)


def test_planes_exact_for_many_random_motions():
    rng = np.random.default_rng(7)
    for _ in range(50):
        T_true = random_pose(rng, np.pi, 5.0)
        (n_src, d_src), _ = random_planes(rng, int(rng.integers(3, 10)))
        res = pose_from_planes(n_src, d_src, *map_planes(T_true, n_src, d_src))
        assert res.ok
        np.testing.assert_allclose(res.T, T_true, atol=1e-9)


def test_three_orthogonal_planes_are_the_minimum(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    n_src, d_src = np.eye(3), np.array([1.0, 2.0, 0.5])
    res = pose_from_planes(n_src, d_src, *map_planes(T_true, n_src, d_src))
    assert res.ok
    assert res.translation_observability == pytest.approx(1 / 3)
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)


def test_planes_under_noise_within_tolerance():
    """0.5 deg normal tilt about each plane's anchor, 5 mm offset noise, 8 planes."""
    rng = np.random.default_rng(2024)
    rot_err, trans_err = [], []
    for _ in range(200):
        T_true = random_pose(rng, np.pi, 3.0)
        (n_src, d_src), anchors = random_planes(rng, 8)
        n_dst, d_dst = map_planes(T_true, n_src, d_src)
        anchors_dst = transform_points(T_true, anchors)
        n_src, d_src = perturb_planes(rng, n_src, anchors, np.radians(0.5), 0.005)
        n_dst, d_dst = perturb_planes(rng, n_dst, anchors_dst, np.radians(0.5), 0.005)
        res = pose_from_planes(n_src, d_src, n_dst, d_dst)
        assert res.ok
        E = invert_pose(T_true) @ res.T
        rot_err.append(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))
        trans_err.append(np.linalg.norm(E[:3, 3]))
    # measured (seed 2024): median 0.35 deg / 25 mm, 95th pct 0.57 deg / 55 mm; the
    # translation error comes from the lever arm: a 0.5 deg tilt about an anchor 4 m
    # away moves the offset d by 35 mm
    assert np.median(rot_err) < 0.5 and np.percentile(rot_err, 95) < 0.9
    assert np.median(trans_err) < 0.04 and np.percentile(trans_err, 95) < 0.08
    # the noise really acts: a perfect result would mean the test is not testing noise
    assert np.median(rot_err) > 0.05 and np.median(trans_err) > 0.001


def test_weights_downweight_an_outlier(rng):
    T_true = random_pose(rng, np.pi, 2.0)
    (n_src, d_src), _ = random_planes(rng, 6)
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    d_dst[0] += 0.5  # a wrong association
    bad = pose_from_planes(n_src, d_src, n_dst, d_dst)
    w = np.ones(6)
    w[0] = 0.0
    good = pose_from_planes(n_src, d_src, n_dst, d_dst, weights=w)
    assert_pose_close(good.T, T_true, 1e-9, 1e-7)
    assert np.linalg.norm(bad.T[:3, 3] - T_true[:3, 3]) > 0.05
    assert abs(good.plane_offset_residual_m[0]) == pytest.approx(0.5)


def test_two_planes_leave_their_line_direction_unobservable(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    n_src = unit([[0.0, 0.0, -1.0], [1.0, 0.2, 0.1]])
    d_src = np.array([2.0, 1.5])
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes(n_src, d_src, n_dst, d_dst)
    assert res.status is RegistrationStatus.DEGENERATE_TRANSLATION and not res.ok
    assert res.translation_observability < 1e-12
    line_dst = unit(np.cross(n_dst[0], n_dst[1]))
    (u,) = res.unobservable_translation_dirs
    assert abs(u @ line_dst) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(res.T[:3, :3], T_true[:3, :3], atol=1e-9)
    # no prior: the unobservable component is zero, the observable part is exact
    assert res.T[:3, 3] @ line_dst == pytest.approx(0.0, abs=1e-9)
    P = np.eye(3) - np.outer(line_dst, line_dst)
    np.testing.assert_allclose(P @ res.T[:3, 3], P @ T_true[:3, 3], atol=1e-9)
    # with the true pose as prior the gap is filled exactly
    filled = pose_from_planes(n_src, d_src, n_dst, d_dst, T_prior=T_true)
    np.testing.assert_allclose(filled.T, T_true, atol=1e-9)
    assert np.all(np.isfinite(res.T))


def test_corridor_leaves_its_axis_unobservable(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    n_src, d_src = corridor()
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes(n_src, d_src, n_dst, d_dst)
    assert res.status is RegistrationStatus.DEGENERATE_TRANSLATION
    axis_dst = T_true[:3, :3] @ np.array([0.0, 0.0, 1.0])
    (u,) = res.unobservable_translation_dirs
    assert abs(u @ axis_dst) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(res.T[:3, :3], T_true[:3, :3], atol=1e-9)
    T_prior = T_true.copy()
    T_prior[:3, :3] = Rotation.from_rotvec([0.1, 0.0, 0.0]).as_matrix()  # rotation ignored
    res = pose_from_planes(n_src, d_src, n_dst, d_dst, T_prior=T_prior)
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)


def test_nearly_coplanar_normals_are_flagged_under_noise():
    rng = np.random.default_rng(3)
    n_src, d_src = corridor()
    T_true = random_pose(rng, np.pi, 1.0)
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    n_src = unit(n_src + rng.normal(size=n_src.shape) * np.radians(0.5))
    res = pose_from_planes(n_src, d_src, n_dst, d_dst)
    assert res.status is RegistrationStatus.DEGENERATE_TRANSLATION
    assert 0.0 < res.translation_observability < 1e-3
    assert np.all(np.isfinite(res.T))


def test_single_plane_leaves_rotation_about_its_normal(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    n_src, d_src = unit([[0.2, -1.0, 0.1]]), np.array([1.3])
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes(n_src, d_src, n_dst, d_dst)
    assert res.status is RegistrationStatus.DEGENERATE_ROTATION
    (axis,) = res.unobservable_rotation_axes
    assert abs(axis @ n_dst[0]) == pytest.approx(1.0, abs=1e-9)
    assert len(res.unobservable_translation_dirs) == 2
    np.testing.assert_allclose(res.T[:3, :3] @ n_src[0], n_dst[0], atol=1e-9)
    np.testing.assert_allclose(res.plane_offset_residual_m, 0.0, atol=1e-9)
    filled = pose_from_planes(n_src, d_src, n_dst, d_dst, T_prior=T_true)
    np.testing.assert_allclose(filled.T, T_true, atol=1e-9)


def test_no_planes_is_too_few():
    T_prior = make_pose(np.array([0.0, 0.1, 0.0]), np.array([1.0, 0.0, 0.0]))
    empty = np.zeros((0, 3))
    res = pose_from_planes(empty, np.zeros(0), empty, np.zeros(0), T_prior=T_prior)
    assert res.status is RegistrationStatus.TOO_FEW
    np.testing.assert_array_equal(res.T, T_prior)
    res = pose_from_planes(np.eye(3), np.ones(3), np.eye(3), np.ones(3), weights=np.zeros(3))
    assert res.status is RegistrationStatus.TOO_FEW
    np.testing.assert_array_equal(res.T, np.eye(4))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_src=np.ones((3, 2))), "n_src has shape"),
        (dict(d_dst=np.ones(2)), "d_dst has shape"),
        (dict(weights=-np.ones(3)), "negative"),
        (dict(n_dst=np.zeros((3, 3))), "zero-length"),
        (dict(d_src=np.array([1.0, np.nan, 1.0])), "non-finite"),
    ],
)
def test_bad_plane_input_raises(kwargs, match):
    args = dict(n_src=np.eye(3), d_src=np.ones(3), n_dst=np.eye(3), d_dst=np.ones(3))
    args.update(kwargs)
    with pytest.raises(GeometryError, match=match):
        pose_from_planes(**args)


# ----------------------------------------------------------------------------- points


@pytest.mark.parametrize("T_true", LARGE_MOTIONS)
def test_points_noise_free_exact(rng, T_true):
    src = rng.uniform(-3, 3, (6, 3))
    res = pose_from_points(src, transform_points(T_true, src))
    assert res.ok
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)
    np.testing.assert_allclose(res.point_residual_m, 0.0, atol=1e-9)


def test_points_under_noise(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    src = rng.uniform(-2, 2, (20, 3))
    dst = transform_points(T_true, src) + rng.normal(size=src.shape) * 0.01
    res = pose_from_points(src, dst)
    assert res.ok
    assert_pose_close(res.T, T_true, 0.01, 0.5)
    assert 0.005 < np.sqrt(np.mean(res.point_residual_m**2)) < 0.025


def test_collinear_points_leave_rotation_about_the_line(rng):
    T_true = random_pose(rng, np.pi, 2.0)
    direction = unit([1.0, 2.0, -0.5])
    src = np.array([0.5, 0.0, 1.0]) + np.outer([0.0, 0.7, 1.5], direction)
    dst = transform_points(T_true, src)
    res = pose_from_points(src, dst)
    assert res.status is RegistrationStatus.DEGENERATE_ROTATION
    (axis,) = res.unobservable_rotation_axes
    assert abs(axis @ (T_true[:3, :3] @ direction)) == pytest.approx(1.0, abs=1e-9)
    assert res.unobservable_translation_dirs.shape == (0, 3)
    np.testing.assert_allclose(res.point_residual_m, 0.0, atol=1e-9)
    filled = pose_from_points(src, dst, T_prior=T_true)
    np.testing.assert_allclose(filled.T, T_true, atol=1e-9)


# ----------------------------------------------------------------------------- planes + points


def test_combined_noise_free_exact_and_consistent_with_single_kinds(rng):
    T_true = random_pose(rng, np.pi, 4.0)
    (n_src, d_src), _ = random_planes(rng, 4)
    pts = rng.uniform(-2, 2, (4, 3))
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes_and_points(
        n_src, d_src, n_dst, d_dst, pts, transform_points(T_true, pts)
    )
    assert res.ok
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)
    # with only one kind present it reduces to the single-kind solvers
    none = np.zeros((0, 3))
    only_planes = pose_from_planes_and_points(n_src, d_src, n_dst, d_dst, none, none)
    np.testing.assert_allclose(only_planes.T, pose_from_planes(n_src, d_src, n_dst, d_dst).T)
    empty_planes = (none, np.zeros(0), none, np.zeros(0))
    only_points = pose_from_planes_and_points(*empty_planes, pts, transform_points(T_true, pts))
    np.testing.assert_allclose(only_points.T, T_true, atol=1e-9)


def test_corridor_is_observable_with_one_corner_point(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    n_src, d_src = corridor()
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    corner_src = np.array([[1.0, 1.2, 2.5]])  # a doorway corner on wall and floor
    corner_dst = transform_points(T_true, corner_src)
    res = pose_from_planes_and_points(n_src, d_src, n_dst, d_dst, corner_src, corner_dst)
    assert res.status is RegistrationStatus.OK
    assert res.translation_observability > 0.01
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)
    assert pose_from_planes(n_src, d_src, n_dst, d_dst).status is (
        RegistrationStatus.DEGENERATE_TRANSLATION
    )


def test_collinear_points_made_observable_by_a_plane(rng):
    T_true = random_pose(rng, np.pi, 3.0)
    src = np.outer([0.0, 1.0, 2.0], [1.0, 0.0, 0.0])
    n_src, d_src = unit([[0.0, 1.0, 0.0]]), np.array([0.5])
    n_dst, d_dst = map_planes(T_true, n_src, d_src)
    res = pose_from_planes_and_points(
        n_src, d_src, n_dst, d_dst, src, transform_points(T_true, src)
    )
    assert res.ok
    np.testing.assert_allclose(res.T, T_true, atol=1e-9)


def test_combined_corridor_under_noise():
    """Corridor + 2 noisy corners: planes 0.5 deg / 5 mm, points 2 cm."""
    rng = np.random.default_rng(11)
    n_src, d_src = corridor()
    anchors = np.array([[0.0, 1.2, 3.0], [-1.0, 0.0, 3.0], [1.0, 0.0, 3.0]])
    corners = np.array([[1.0, 1.2, 2.5], [-1.0, 1.2, 4.0]])
    errs = []
    for _ in range(100):
        T_true = random_pose(rng, np.pi, 2.0)
        n_dst, d_dst = map_planes(T_true, n_src, d_src)
        a_dst = transform_points(T_true, anchors)
        ns, ds = perturb_planes(rng, n_src, anchors, np.radians(0.5), 0.005)
        nd, dd = perturb_planes(rng, n_dst, a_dst, np.radians(0.5), 0.005)
        c_src = corners + rng.normal(size=corners.shape) * 0.02
        c_dst = transform_points(T_true, corners) + rng.normal(size=corners.shape) * 0.02
        res = pose_from_planes_and_points(
            ns, ds, nd, dd, c_src, c_dst, np.radians(0.5), 0.005, 0.02 * np.sqrt(2)
        )
        assert res.ok
        E = invert_pose(T_true) @ res.T
        errs.append((Rotation.from_matrix(E[:3, :3]).magnitude(), np.linalg.norm(E[:3, 3])))
    rot_deg, trans_m = np.degrees(np.array(errs)[:, 0]), np.array(errs)[:, 1]
    # measured (seed 11): median 0.60 deg / 36 mm; 95th pct 1.03 deg / 63 mm
    assert np.median(rot_deg) < 0.9 and np.percentile(rot_deg, 95) < 1.6
    assert np.median(trans_m) < 0.05 and np.percentile(trans_m, 95) < 0.1


# ----------------------------------------------------------------------------- ICP

ROOM_LO, ROOM_HI = np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 2.5])
BOX_LO, BOX_HI = np.array([0.2, 0.3, 0.0]), np.array([0.58, 0.59, 0.19])


def camera_pose(position, yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """T_world_cam for a camera (x right, y down, z forward) in a z-up world."""
    R_level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # cols: cam axes
    R = (
        Rotation.from_rotvec([0.0, 0.0, yaw_rad]).as_matrix()
        @ R_level
        @ Rotation.from_rotvec([-pitch_rad, 0.0, 0.0]).as_matrix()
    )
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, position
    return T


def render_box_in_room(T_world_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """Organised (H*W, 3) camera-frame cloud of a box on the floor of a room, by ray casting."""
    f = 525.0 * width / 640.0
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    rays = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u, float)], -1)
    rays = rays.reshape(-1, 3)
    dirs = rays @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        exit_t = np.where(dirs > 0, (ROOM_HI - o) / dirs, (ROOM_LO - o) / dirs)
        depth = np.min(np.where(np.isfinite(exit_t), exit_t, np.inf), axis=1)
        t1, t2 = (BOX_LO - o) / dirs, (BOX_HI - o) / dirs
        near = np.max(np.nan_to_num(np.minimum(t1, t2), nan=-np.inf), axis=1)
        far = np.min(np.nan_to_num(np.maximum(t1, t2), nan=np.inf), axis=1)
    hit_box = (near <= far) & (near > 0)
    depth = np.where(hit_box, np.minimum(depth, near), depth)
    return rays * depth[:, None]


def two_views_of_box_in_room():
    """Clouds of cameras b (source, 2 mm noise) and a (target), T_a_b, a start 4 deg / 7 cm off."""
    rng = np.random.default_rng(5)
    T_world_a = camera_pose([0.0, -1.5, 1.2], 0.0, np.radians(25))
    T_world_b = camera_pose([0.25, -1.4, 1.15], np.radians(8), np.radians(22))
    target = render_box_in_room(T_world_a, 320, 240)
    source = render_box_in_room(T_world_b, 320, 240)
    source += rng.normal(size=source.shape) * 0.002
    T_true = invert_pose(T_world_a) @ T_world_b
    T_init = T_true @ make_pose(unit([1.0, -0.5, 0.3]) * np.radians(4), [0.05, -0.04, 0.03])
    assert_pose_close(T_init, T_true, 1.0, 5.0)  # the start really is off ...
    with pytest.raises(AssertionError):
        assert_pose_close(T_init, T_true, 0.03, 1.0)  # ... by more than ICP's tolerance below
    return source, target, T_true, T_init


@pytest.mark.parametrize(
    "method, trans_tol_m, rot_tol_deg",
    # measured: point-to-plane 5.1 mm / 0.08 deg (the wide 15 cm gate admits pairs from
    # parts only one camera sees); point-to-point slides along the planes and stops at
    # 25 mm / 0.7 deg
    [("point_to_plane", 0.01, 0.2), ("point_to_point", 0.04, 1.2)],
)
def test_icp_converges_on_box_in_room(method, trans_tol_m, rot_tol_deg):
    source, target, T_true, T_init = two_views_of_box_in_room()
    T, fitness, rmse = refine_icp(source, target, T_init, 0.15, 0.03, method=method)
    assert_pose_close(T, T_true, trans_tol_m, rot_tol_deg)
    assert fitness > 0.9 and rmse < 0.035


def test_icp_second_pass_with_a_tight_gate_is_millimetric():
    source, target, T_true, T_init = two_views_of_box_in_room()
    coarse = refine_icp(source, target, T_init, 0.15, 0.03)
    fine = refine_icp(source, target, coarse.T, 0.05, 0.03)
    assert_pose_close(fine.T, T_true, 0.002, 0.03)  # measured 0.7 mm / 0.004 deg
    assert fine.inlier_rmse < coarse.inlier_rmse


def test_icp_bad_input():
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(GeometryError, match="method"):
        refine_icp(pts, pts, np.eye(4), 0.1, 0.0, method="gicp")  # type: ignore[arg-type]
    with pytest.raises(GeometryError, match="T_init"):
        refine_icp(pts, pts, np.eye(3), 0.1, 0.0)
    with pytest.raises(GeometryError, match=">= 3 points"):
        refine_icp(pts[:2], pts, np.eye(4), 0.1, 0.0)
