"""Plane and corner data association, outline overlap, on exact synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planeslam.core.errors import AssociationError
from planeslam.core.geometry import invert_pose, transform_points
from planeslam.tracking.association import (
    Association,
    associate_corners,
    associate_planes,
    associate_with_corners,
    outline_overlap,
    plane_association_cost,
)

pytestmark = pytest.mark.unit

DEG = np.pi / 180


def make_pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def map_planes(T_b_a: np.ndarray, n_a: np.ndarray, d_a: np.ndarray):
    n_b = n_a @ T_b_a[:3, :3].T
    return n_b, d_a - n_b @ T_b_a[:3, 3]


def room_with_box():
    """Map planes (world, normals toward the room centre / camera) and their corners.

    0 floor, 1-4 walls of a 4 x 4 x 2.5 m room, 5-7 top / front / left face of
    a box on the floor, 8 a partition 0.3 m in front of wall 1 (parallel).
    """
    n = np.array(
        [
            [0, 0, 1], [0, -1, 0], [0, 1, 0], [-1, 0, 0], [1, 0, 0],
            [0, 0, 1], [0, -1, 0], [-1, 0, 0], [0, -1, 0],
        ],
        dtype=float,
    )  # fmt: skip
    d = np.array([0.0, 2.0, 2.0, 2.0, 2.0, -0.19, 0.3, 0.2, 1.7])
    # corners: floor-wall1-wall3, floor-wall1-wall4, box top-front-left
    corner_planes = np.array([[0, 1, 3], [0, 1, 4], [5, 6, 7]])
    corner_points = np.array([[2.0, 2.0, 0.0], [-2.0, 2.0, 0.0], [0.2, 0.3, 0.19]])
    return n, d, corner_planes, corner_points


T_WORLD_CAM = make_pose([1.2, 0.3, -0.4], [0.3, -0.8, 1.1])


def observe(perm: np.ndarray, T_world_cam: np.ndarray = T_WORLD_CAM):
    """Observed planes: map planes perm[i] seen in the camera frame, as observation i."""
    n, d, _, _ = room_with_box()
    return map_planes(invert_pose(T_world_cam), n[perm], d[perm])


def test_shuffled_planes_recovered_under_a_perturbed_prediction(rng):
    n_map, d_map, _, _ = room_with_box()
    perm = rng.permutation(len(n_map))
    n_obs, d_obs = observe(perm)
    T_pred = T_WORLD_CAM @ make_pose([0.02, -0.03, 0.01], [0.03, -0.02, 0.01])  # ~2 deg, 4 cm
    pairs = associate_planes(n_map, d_map, n_obs, d_obs, T_pred, 10 * DEG, 0.1)
    assert pairs == [(i, int(perm[i])) for i in range(len(perm))]


def test_parallel_planes_at_different_offsets_are_not_swapped():
    """Two parallel walls 2 m apart facing the same way, seen after a 0.3 m prediction error."""
    n_map = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
    d_map = np.array([2.0, 0.0, 0.0])  # wall at y = 2, partition at y = 0
    T_true = make_pose([0.0, 0.0, 0.3], [0.5, -1.0, 1.2])
    n_obs, d_obs = map_planes(invert_pose(T_true), n_map[[1, 0]], d_map[[1, 0]])
    T_pred = make_pose([0.0, 0.0, 0.0], [0.0, 0.3, 0.0]) @ T_true  # 0.3 m off across the walls
    pairs = associate_planes(n_map, d_map, n_obs, d_obs, T_pred, 10 * DEG, 0.5)
    assert pairs == [(0, 1), (1, 0)]
    # only the near one seen: matched to itself, never to the far one
    pairs = associate_planes(n_map, d_map, n_obs[:1], d_obs[:1], T_pred, 10 * DEG, 0.5)
    assert pairs == [(0, 1)]
    # a plane 1 m from both (y = 1): outside the 0.5 m gate, so unmatched
    n_mid, d_mid = map_planes(invert_pose(T_true), n_map[:1], np.array([1.0]))
    assert associate_planes(n_map, d_map, n_mid, d_mid, T_true, 10 * DEG, 0.5) == []


def test_a_picture_on_a_wall_does_not_take_the_walls_landmark():
    """ICL-NUIM frame 62: the map's wall is at 1.809 m; the frame sees the wall 0.7 cm from
    it (a large plane) and a picture hanging 3.5 cm in front of the wall (small, 1.2 deg
    off). Weighted by size, the picture's cost is the lower, so counting pairs first it
    takes the wall's landmark and the wall is left out; weighing what is left unpaired
    (`weigh_unpaired`), the wall keeps it."""
    n_map = np.array([[-1.0, 0.0, 0.0]])
    d_map = np.array([1.809])
    tilt = 1.2 * DEG
    n_obs = np.array([[-1.0, 0.0, 0.0], [-np.cos(tilt), np.sin(tilt), 0.0]])
    d_obs = np.array([1.816, 1.781])
    weights = np.array([2.4, 0.3])
    args = (n_map, d_map, n_obs, d_obs, np.eye(4), 10 * DEG, 0.1)
    assert associate_planes(*args, weights=weights) == [(1, 0)]
    assert associate_planes(*args, weights=weights, weigh_unpaired=True) == [(0, 0)]
    # alone, each plane still pairs; without weights, the nearer one (the wall) wins
    assert associate_planes(
        *args[:2], n_obs[1:], d_obs[1:], *args[4:], weights=weights[1:], weigh_unpaired=True
    ) == [(0, 0)]
    assert associate_planes(*args, weigh_unpaired=True) == [(0, 0)]


def test_only_the_planes_a_selected_map_plane_could_take_are_weighed():
    """Two contests in one frame: over a wall (map 0, selected: a structure) between the
    wall and a picture, and over a cabinet face (map 1, not selected) between a large and
    a small observation. Selecting map 0 decides the wall's contest by what leaving each
    out loses (the wall keeps it) and leaves the cabinet's count-first (the lower weighted
    cost, the small plane, wins), as True and False decide both."""
    tilt = 1.2 * DEG
    n_map = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    d_map = np.array([1.809, 2.0])
    n_obs = np.array(
        [
            [-1.0, 0.0, 0.0],  # the wall
            [-np.cos(tilt), np.sin(tilt), 0.0],  # the picture, 3.5 cm in front
            [0.0, 0.0, -1.0],  # the cabinet face, large
            [0.0, np.sin(tilt), -np.cos(tilt)],  # a small patch in front of it
        ]
    )
    d_obs = np.array([1.816, 1.781, 2.01, 2.04])
    weights = np.array([2.4, 0.3, 2.0, 0.2])
    args = (n_map, d_map, n_obs, d_obs, np.eye(4), 10 * DEG, 0.1)
    assert associate_planes(*args, weights=weights) == [(1, 0), (3, 1)]
    assert associate_planes(*args, weights=weights, weigh_unpaired=True) == [(0, 0), (2, 1)]
    selected = np.array([True, False])
    assert associate_planes(*args, weights=weights, weigh_unpaired=selected) == [(0, 0), (3, 1)]
    # a plane no selected map plane could take pairs wherever it can, however costly
    assert associate_planes(*args[:2], n_obs[3:], d_obs[3:], *args[4:], weights=weights[3:],
                            weigh_unpaired=selected) == [(0, 1)]  # fmt: skip
    with pytest.raises(AssociationError, match="weigh_unpaired has shape"):
        associate_planes(*args, weights=weights, weigh_unpaired=np.array([True]))


def test_gates_reject_wrong_matches():
    n_map = np.array([[0.0, 0.0, 1.0]])
    d_map = np.array([0.0])
    tilted = np.array([[np.sin(15 * DEG), 0.0, np.cos(15 * DEG)]])
    assert associate_planes(n_map, d_map, tilted, d_map, np.eye(4), 10 * DEG, 0.1) == []
    assert associate_planes(n_map, d_map, tilted, d_map, np.eye(4), 20 * DEG, 0.1) == [(0, 0)]
    # opposite side of the same plane (flipped normal): 180 deg apart, never a match
    assert associate_planes(n_map, d_map, -n_map, -d_map, np.eye(4), 30 * DEG, 1.0) == []
    assert associate_planes(n_map, d_map, n_map, d_map + 0.11, np.eye(4), 10 * DEG, 0.1) == []


def test_one_to_one_prefers_the_closer_of_two_candidates():
    n_map = np.array([[0.0, 0.0, 1.0]])
    d_map = np.array([1.0])
    n_obs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d_obs = np.array([1.08, 1.01])
    pairs = associate_planes(n_map, d_map, n_obs, d_obs, np.eye(4), 10 * DEG, 0.1)
    assert pairs == [(1, 0)]


def test_assignment_maximises_the_number_of_allowed_pairs():
    """Greedy would give obs 0 its best (map 0) and leave obs 1 unmatched."""
    n = np.array([[0.0, 0.0, 1.0]] * 2)
    d_map = np.array([1.0, 1.12])
    d_obs = np.array([1.04, 0.99])  # obs 0 fits both (best: map 0); obs 1 only map 0
    pairs = associate_planes(n, d_map, n, d_obs, np.eye(4), 10 * DEG, 0.1)
    assert pairs == [(0, 1), (1, 0)]


def test_overlap_gate_and_cost():
    n = np.array([[0.0, 0.0, 1.0]] * 2)
    d = np.array([1.0, 1.0])  # two coplanar patches: geometry alone cannot tell them apart
    overlap = np.array([[0.0, 0.9], [0.8, 0.0]])
    pairs = associate_planes(n, d, n, d, np.eye(4), 10 * DEG, 0.1, overlap, min_overlap=0.3)
    assert pairs == [(0, 1), (1, 0)]
    pairs = associate_planes(
        n, d, n, d, np.eye(4), 10 * DEG, 0.1, np.zeros((2, 2)), min_overlap=0.3
    )
    assert pairs == []


def test_cost_matrix_values():
    n_map = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    d_map = np.array([1.0, 2.0])
    n_obs = np.array([[0.0, np.sin(5 * DEG), np.cos(5 * DEG)]])
    d_obs = np.array([1.05])
    cost, allowed = plane_association_cost(n_map, d_map, n_obs, d_obs, np.eye(4), 10 * DEG, 0.1)
    assert cost.shape == (1, 2) and allowed.tolist() == [[True, False]]
    assert cost[0, 0] == pytest.approx(0.5 + 0.5)
    assert cost[0, 1] == pytest.approx(90 / 10 + 0.95 / 0.1)


def test_empty_inputs_give_no_pairs():
    n, d = np.zeros((0, 3)), np.zeros(0)
    assert associate_planes(n, d, np.eye(3), np.ones(3), np.eye(4), 0.1, 0.1) == []
    assert associate_planes(np.eye(3), np.ones(3), n, d, np.eye(4), 0.1, 0.1) == []


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_obs=np.ones((2, 2))), "n_obs has shape"),
        (dict(d_map=np.ones(4)), "d_map has shape"),
        (dict(T_map_obs=np.eye(3)), "T_map_obs"),
        (dict(max_angle_rad=0.0), "max_angle_rad"),
        (dict(overlap=np.ones((3, 3))), "overlap has shape"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = dict(
        n_map=np.eye(3), d_map=np.ones(3), n_obs=np.eye(3)[:2], d_obs=np.ones(2),
        T_map_obs=np.eye(4), max_angle_rad=0.1, max_offset_m=0.1,
    )  # fmt: skip
    args.update(kwargs)
    with pytest.raises(AssociationError, match=match):
        associate_planes(**args)


# ----------------------------------------------------------------------------- outlines


def square(x0, y0, size, z=1.0):
    return np.array(
        [[x0, y0, z], [x0 + size, y0, z], [x0 + size, y0 + size, z], [x0, y0 + size, z]]
    )


@pytest.mark.parametrize(
    "b, expected",
    [
        (square(0.5, 0.0, 1.0), 0.5),  # half shifted
        (square(0.25, 0.25, 0.5), 1.0),  # inside
        (square(-1.0, -1.0, 3.0), 1.0),  # contains (relative to the smaller)
        (square(0.5, 0.5, 1.0), 1.0 / 4),  # quarter of either
        (square(2.0, 0.0, 1.0), 0.0),  # disjoint
        (square(1.0, 0.0, 1.0), 0.0),  # touching edge
    ],
)
def test_outline_overlap_squares(b, expected, rng):
    a = square(0.0, 0.0, 1.0)
    n, d = np.array([0.0, 0.0, 1.0]), -1.0
    assert outline_overlap(a, b, n, d) == pytest.approx(expected, abs=1e-6)
    assert outline_overlap(b, a, n, d) == pytest.approx(expected, abs=1e-6)
    # invariant to a rigid motion of plane and outlines, and to vertex order
    T = make_pose(rng.normal(size=3), rng.uniform(-3, 3, 3))
    n_t, d_t = map_planes(T, n[None], np.array([d]))
    a_t, b_t = transform_points(T, a)[::-1], transform_points(T, b)
    assert outline_overlap(a_t, b_t, n_t[0], d_t[0]) == pytest.approx(expected, abs=1e-5)


def test_outline_overlap_projects_off_plane_points_and_handles_degenerate():
    a = square(0.0, 0.0, 1.0)
    b = square(0.5, 0.0, 1.0, z=1.03)  # 3 cm off the plane: projected
    n, d = np.array([0.0, 0.0, 1.0]), -1.0
    assert outline_overlap(a, b, n, d) == pytest.approx(0.5, abs=1e-6)
    line = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]])
    assert outline_overlap(a, line, n, d) == 0.0
    assert outline_overlap(a, line[:2], n, d) == 0.0
    with pytest.raises(AssociationError):
        outline_overlap(a, b, np.zeros(3), d)


def test_outline_overlap_of_rotated_squares_sharing_an_edge(rng):
    """Random in-plane rotations; a collinear shared edge once broke cv2.intersectConvexConvex."""
    n, d = np.array([0.0, 0.0, 1.0]), -1.0
    for _ in range(50):
        R = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)]).as_matrix()
        a = square(0.0, 0.0, 1.0) @ R.T
        b = square(0.0, 0.5, 1.0) @ R.T
        assert outline_overlap(a, b, n, d) == pytest.approx(0.5, abs=1e-9)


def test_outline_overlap_of_a_concave_outline_uses_its_hull():
    """An L-shape against the unit square filling its notch: exact overlap 0, hull gives 0.5."""
    ell = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], float)
    notch = square(1.0, 1.0, 1.0, z=0.0)
    assert outline_overlap(ell, notch, np.array([0.0, 0.0, 1.0]), 0.0) == pytest.approx(0.5)


# ----------------------------------------------------------------------------- corners


def test_associate_corners_from_plane_pairs():
    _, _, cp_map, _ = room_with_box()
    perm = np.array([4, 7, 0, 6, 1, 3, 5, 2, 8])  # obs i is map perm[i]
    inv = np.argsort(perm)
    cp_obs = inv[cp_map[[2, 0]]][:, ::-1]  # corners 2 and 0, planes listed in another order
    plane_pairs = [(i, int(perm[i])) for i in range(len(perm))]
    assert associate_corners(cp_obs, cp_map, plane_pairs) == [(0, 2), (1, 0)]
    # one plane of corner 0 unassociated -> that corner does not match
    missing = [p for p in plane_pairs if p[1] != 3]
    assert associate_corners(cp_obs, cp_map, missing) == [(0, 2)]


def test_corners_fix_their_planes_where_planes_alone_fail():
    """Prediction 25 cm off: planes alone pair a wall wrongly, the corners fix all of them."""
    n_map, d_map, cp_map, x_map = room_with_box()
    perm = np.array([4, 7, 0, 6, 1, 3, 5, 2, 8])
    inv = np.argsort(perm)
    n_obs, d_obs = observe(perm)
    cp_obs = inv[cp_map][:, [2, 0, 1]]
    x_obs = transform_points(invert_pose(T_WORLD_CAM), x_map)
    T_pred = T_WORLD_CAM @ make_pose([0.01, 0.0, -0.01], [0.15, -0.2, 0.0])

    plain = associate_planes(n_map, d_map, n_obs, d_obs, T_pred, 10 * DEG, 0.1)
    truth = [(i, int(perm[i])) for i in range(len(perm))]
    assert not set(plain) <= set(truth)  # planes alone make a wrong pair under this prediction

    result = associate_with_corners(
        n_map, d_map, cp_map, x_map, n_obs, d_obs, cp_obs, x_obs, T_pred, 10 * DEG, 0.1, 0.4
    )
    assert isinstance(result, Association)
    assert result.corners == [(0, 0), (1, 1), (2, 2)]
    assert result.planes == truth  # the corners fixed their 7 planes, the other 2 followed
    # a selection over the map planes reaches the other 2 as their own (2,) selection
    selected = np.arange(len(n_map)) % 2 == 0
    weighed = associate_with_corners(
        n_map, d_map, cp_map, x_map, n_obs, d_obs, cp_obs, x_obs, T_pred, 10 * DEG, 0.1, 0.4,
        weights=np.ones(len(n_obs)), weigh_unpaired=selected,
    )  # fmt: skip
    assert weighed == result
    with pytest.raises(AssociationError, match="weigh_unpaired has shape"):
        associate_with_corners(
            n_map, d_map, cp_map, x_map, n_obs, d_obs, cp_obs, x_obs, T_pred, 10 * DEG, 0.1,
            0.4, weigh_unpaired=selected[:2],
        )  # fmt: skip


def test_corner_with_mismatching_normals_is_rejected():
    """A corner at the right place whose planes do not pair within the angle gate."""
    n_map, d_map, cp_map, x_map = room_with_box()
    n_obs, d_obs = n_map.copy(), d_map.copy()
    R_bad = Rotation.from_rotvec([0.0, 0.0, 20 * DEG]).as_matrix()
    n_obs[[5, 6, 7]] = n_obs[[5, 6, 7]] @ R_bad.T  # box faces turned 20 deg
    result = associate_with_corners(
        n_map, d_map, cp_map[2:], x_map[2:], n_obs, d_obs, cp_map[2:], x_map[2:],
        np.eye(4), 10 * DEG, 0.1, 0.3,
    )  # fmt: skip
    assert result.corners == []
    assert {p[0] for p in result.planes}.isdisjoint({6, 7})  # turned walls stay unmatched


def test_conflicting_corners_keep_the_better_one():
    """Two observed corners claim the same map planes in contradicting ways."""
    n = np.eye(3)
    d = np.array([1.0, 1.0, 1.0])
    cp = np.array([[0, 1, 2]])
    x = np.array([[-1.0, -1.0, -1.0]])
    n_obs = np.vstack([n, n])  # obs planes 0-2 and 3-5 duplicate the map's
    d_obs = np.concatenate([d, d + 0.05])
    cp_obs = np.array([[0, 1, 2], [3, 4, 5]])
    x_obs = np.vstack([x, x - 0.05])
    result = associate_with_corners(
        n, d, cp, x, n_obs, d_obs, cp_obs, x_obs, np.eye(4), 0.2, 0.1, 0.3
    )
    assert result.corners == [(0, 0)]
    assert result.planes == [(0, 0), (1, 1), (2, 2)]


def test_contradicting_corner_is_dropped():
    """The floor segmented twice: two corners claim map floor 0 with different obs planes."""
    n = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0]], dtype=float)
    d = np.array([0.0, 1.0, 1.0, 1.0])
    cp_map = np.array([[0, 1, 2], [0, 3, 2]])
    x_map = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0]])
    n_obs, d_obs = np.vstack([n, n[:1]]), np.append(d, 0.0)  # obs 4 = floor again
    cp_obs = np.array([[0, 1, 2], [4, 3, 2]])
    result = associate_with_corners(
        n, d, cp_map, x_map, n_obs, d_obs, cp_obs, x_map, np.eye(4), 0.2, 0.1, 0.3
    )
    assert result.corners == [(0, 0)]
    assert result.planes == [(0, 0), (1, 1), (2, 2), (3, 3)]
    # an overlap gate applies to the planes left after the corners, not to corner-fixed ones
    gated = associate_with_corners(
        n, d, cp_map, x_map, n_obs, d_obs, cp_obs, x_map, np.eye(4), 0.2, 0.1, 0.3,
        overlap=np.zeros((5, 4)), min_overlap=0.5,
    )  # fmt: skip
    assert gated.planes == [(0, 0), (1, 1), (2, 2)]


def test_corner_input_validation():
    n, d, cp, x = room_with_box()
    with pytest.raises(AssociationError, match="outside"):
        associate_with_corners(n, d, cp + 10, x, n, d, cp, x, np.eye(4), 0.1, 0.1, 0.1)
    with pytest.raises(AssociationError, match="differ in count"):
        associate_with_corners(n, d, cp, x[:2], n, d, cp, x, np.eye(4), 0.1, 0.1, 0.1)
