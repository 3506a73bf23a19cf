"""Pose hypotheses without a motion prior, from every primitive, and their verification.

Each generator pairs a small rigid set of the frame's primitives with every set of the
map's that has the same shape (angles, convexity, lengths), and solves the pose in closed
form (T_world_cam, (H, 4, 4)):

- `corner_hypotheses`: one trihedral corner (three normals and a point) -> a full pose
  (6 pairings of its planes, same convexity);
- `triple_hypotheses`: three planes whose normals span 3-D -> rotation from the normals,
  translation from the three offsets (map triples with the same pairwise angles);
- `edge_hypotheses`: two non-parallel planes joined by a real intersection (paper eq. 1-6)
  -> rotation from the two normals, translation across the line from the two offsets and
  along it from an end point of the edge (each end of the map edge, so two hypotheses
  per pairing; edges of similar length, dihedral angle and convexity only).

`score_hypotheses` verifies every hypothesis against all of the frame's primitives
(a RANSAC over primitive correspondences): the observed planes (by area) that find a map
plane within the gates, the corners that land on a map corner, the edges whose two planes
land on the two planes of a map edge no shorter than the observed one; objects of the
same class and size add to the score.

Frames: FrameView in the camera frame, MapView in the world frame.
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

import numpy as np

from planeslam.core.geometry import rotation_angle

if TYPE_CHECKING:
    from planeslam.tracking.views import FrameView, MapView

_PERMUTATIONS_3 = np.array(list(itertools.permutations(range(3))))


def rotation_kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations R minimising sum |R src_i - dst_i|^2 for (..., K, 3) row stacks."""
    H = np.swapaxes(src, -1, -2) @ dst
    U, _, Vt = np.linalg.svd(H)
    D = np.ones(H.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    return np.swapaxes(Vt, -1, -2) @ (D[..., :, None] * np.swapaxes(U, -1, -2))


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation [m], rotation [deg]) of T_a^-1 T_b for two (4, 4) poses."""
    angle = rotation_angle(T_a[:3, :3].T @ T_b[:3, :3])
    return float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3])), math.degrees(angle)


def _poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), R.shape[:-2] + (1, 1))
    T[..., :3, :3], T[..., :3, 3] = R, t
    return T


def _angles_of(normals: np.ndarray, sets: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(S, P) angles [rad] between the normals of each set's pairs of members."""
    cos = np.sum(normals[sets[:, pairs[:, 0]]] * normals[sets[:, pairs[:, 1]]], axis=-1)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def independent_triples(
    normals: np.ndarray, weights: np.ndarray | None, limit: int, ordered: bool = False
) -> np.ndarray:
    """(T, 3) row indices of plane triples whose normals are far from coplanar (|det| > 0.2),
    among the `limit` heaviest planes (first rows when weights is None); every ordering of
    each triple when `ordered`."""
    rows = np.arange(len(normals)) if weights is None else np.argsort(-weights, kind="stable")
    rows = rows[:limit]
    if len(rows) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    combos = itertools.permutations(rows, 3) if ordered else itertools.combinations(rows, 3)
    triples = np.array(list(combos), dtype=np.int64)
    det = np.abs(np.linalg.det(normals[triples]))
    return triples[det > 0.2]


def corner_hypotheses(frame: FrameView, view: MapView, max_angle_rad: float) -> np.ndarray:
    """(H, 4, 4) from every (observed corner, map corner, pairing of their planes) of the
    same convexity whose normals agree within the angle gate after rotation; translation
    from the two corner points."""
    if not len(frame.corner_planes) or not len(view.corner_planes):
        return np.zeros((0, 4, 4))
    n_obs = frame.normals[frame.corner_planes]  # (Ko, 3, 3)
    n_map = view.normals[view.corner_planes][:, _PERMUTATIONS_3]  # (Km, 6, 3, 3)
    src = np.broadcast_to(n_obs[:, None, None], (len(n_obs),) + n_map.shape)
    dst = np.broadcast_to(n_map[None], src.shape)
    R = rotation_kabsch(src, dst)  # (Ko, Km, 6, 3, 3)
    rotated = np.einsum("...ij,...kj->...ki", R, src)
    cos = np.clip(np.sum(rotated * dst, axis=-1), -1.0, 1.0)
    ok = np.all(cos >= np.cos(max_angle_rad), axis=-1)
    if frame.corner_convex_edges is not None and view.corner_convex_edges is not None:
        same = frame.corner_convex_edges[:, None] == view.corner_convex_edges[None, :]
        ok &= same[:, :, None]
    p_obs = np.broadcast_to(frame.corner_points[:, None, None], R.shape[:-1])
    p_map = np.broadcast_to(view.corner_points[None, :, None], R.shape[:-1])
    t = p_map - np.einsum("...ij,...j->...i", R, p_obs)
    return _poses(R, t)[ok]


def triple_hypotheses(
    frame: FrameView,
    view: MapView,
    max_angle_rad: float,
    max_frame_planes: int,
    max_map_planes: int,
    limit: int | None = None,
) -> np.ndarray:
    """(H, 4, 4) from triples of planes with independent normals against ordered map
    triples with the same pairwise angles: rotation from the normals, translation from the
    three offsets. The `max_frame_planes` heaviest observed and `max_map_planes` largest map
    planes take part; at most `limit` pairings (heaviest observed triples first: in a
    box-shaped world every orthogonal triple matches every other)."""
    obs = independent_triples(frame.normals, frame.weights, max_frame_planes)
    mp = independent_triples(view.normals, view.plane_weights, max_map_planes, ordered=True)
    if not len(obs) or not len(mp):
        return np.zeros((0, 4, 4))
    pair = np.array([[0, 1], [1, 2], [0, 2]])
    angle_obs = _angles_of(frame.normals, obs, pair)  # (To, 3)
    angle_map = _angles_of(view.normals, mp, pair)  # (Tm, 3)
    io, im = np.nonzero(
        np.all(np.abs(angle_obs[:, None] - angle_map[None]) <= max_angle_rad, axis=-1)
    )
    io, im = io[:limit], im[:limit]
    if not len(io):
        return np.zeros((0, 4, 4))
    n_src, n_dst = frame.normals[obs[io]], view.normals[mp[im]]  # (H, 3, 3)
    R = rotation_kabsch(n_src, n_dst)
    A = np.einsum("hij,hkj->hki", R, n_src)  # rows: R n_obs_i
    b = frame.d[obs[io]] - view.d[mp[im]]  # (R n_obs_i) . t = d_obs_i - d_map_i
    t = np.linalg.solve(A, b[..., None])[..., 0]
    return _poses(R, t)


def edge_hypotheses(
    frame: FrameView,
    view: MapView,
    max_angle_rad: float,
    limit: int | None = None,
) -> np.ndarray:
    """(H, 4, 4) from each observed edge against each map edge of the same convexity and a
    dihedral angle within the gate: rotation from the two normals (both pairings),
    translation across the line from the offsets and along it from one observed end placed
    on either map end. At most `limit` (observed edge, map edge) pairs (the longest map
    edges first)."""
    if not len(frame.edge_planes) or not len(view.edge_planes):
        return np.zeros((0, 4, 4))
    io, im = np.nonzero(
        (np.abs(frame.edge_angles[:, None] - view.edge_angles[None, :]) <= max_angle_rad)
        & (frame.edge_convex[:, None] == view.edge_convex[None, :])
    )
    order = np.argsort(-view.edge_lengths[im], kind="stable")[:limit]
    io, im = io[order], im[order]
    if not len(io):
        return np.zeros((0, 4, 4))
    swap = np.array([[0, 1], [1, 0]])
    obs_rows = frame.edge_planes[io]  # (P, 2)
    map_rows = view.edge_planes[im][:, swap]  # (P, 2 pairings, 2)
    n_src = frame.normals[obs_rows]  # (P, 2, 3)
    n_dst = view.normals[map_rows]  # (P, 2, 2, 3)
    src = np.broadcast_to(n_src[:, None], n_dst.shape)
    # The cross product makes the 2-normal Kabsch problem well posed and orientation-true.
    src3 = np.concatenate([src, np.cross(src[..., 0, :], src[..., 1, :])[..., None, :]], -2)
    dst3 = np.concatenate([n_dst, np.cross(n_dst[..., 0, :], n_dst[..., 1, :])[..., None, :]], -2)
    R = rotation_kabsch(src3, dst3)  # (P, 2, 3, 3)
    rotated = np.einsum("pqij,pqkj->pqki", R, src)
    ok = np.all(np.sum(rotated * n_dst, axis=-1) >= np.cos(max_angle_rad), axis=-1)  # (P, 2)
    u = view.edge_segments[im, 1] - view.edge_segments[im, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)  # (P, 3) map edge direction
    ends = view.edge_segments[im]  # (P, 2, 3): place the observed end on either map end
    p_obs = frame.edge_segments[io]  # (P, 2, 3)
    # Rows of the 3x3 system: R n_a . t = d_a - d_A, R n_b . t = d_b - d_B, u . t = s.
    A = np.concatenate(
        [rotated, np.broadcast_to(u[:, None, None, :], rotated.shape[:2] + (1, 3))], axis=2
    )  # (P, 2, 3, 3)
    d_obs = frame.d[obs_rows]  # (P, 2)
    d_map = view.d[map_rows]  # (P, 2, 2)
    solvable = np.abs(np.linalg.det(A)) > 1e-3  # (P, 2)
    keep = ok & solvable
    hyps = []
    for k_end in range(2):  # which observed end (the ends' order along u is unknown)
        u_p_rot = np.einsum("pi,pqi->pq", u, np.einsum("pqij,pj->pqi", R, p_obs[:, k_end]))
        for m_end in range(2):  # which map end it sits on
            s = np.einsum("pi,pi->p", u, ends[:, m_end])[:, None] - u_p_rot
            b = np.concatenate([d_obs[:, None, :] - d_map, s[..., None]], axis=-1)  # (P, 2, 3)
            t = np.zeros(b.shape)
            t[solvable] = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]
            hyps.append(_poses(R[keep], t[keep]))
    return np.concatenate(hyps)


def score_hypotheses(
    frame: FrameView,
    view: MapView,
    T: np.ndarray,
    max_angle_rad: float,
    max_offset_m: float,
    max_corner_m: float,
) -> np.ndarray:
    """(H,) support of each hypothesis T (H, 4, 4) from all of the frame's primitives:
    planes (each counts 1 + its share of the visible area), corners (2 each), edges whose
    planes both land on a map edge's planes (1 each, when the map edge is not shorter) and
    objects whose class and size match a map object near them (2 each). Scored `_CHUNK`
    hypotheses at a time: the (H, N, M) plane tests of a large map stay small."""
    area = frame.areas if frame.areas is not None else frame.weights
    share = area / max(float(area.sum()), 1e-12)
    score = np.zeros(len(T))
    for k in range(0, len(T), _CHUNK):
        chunk, part = T[k : k + _CHUNK], slice(k, k + _CHUNK)
        partners = _plane_partners(frame, view, chunk, max_angle_rad, max_offset_m)
        score[part] = partners.any(axis=2) @ (1.0 + share)
        if len(frame.corner_points) and len(view.corner_points):
            moved = moved_points(chunk, frame.corner_points)
            dist = np.linalg.norm(moved[:, :, None] - view.corner_points[None, None], axis=-1)
            score[part] += 2.0 * np.count_nonzero((dist <= max_corner_m).any(axis=2), axis=1)
        if len(frame.edge_planes) and len(view.edge_planes):
            score[part] += _edge_support(frame, view, partners)
        if len(frame.object_sizes) and len(view.object_sizes):
            score[part] += 2.0 * _object_support(frame, view, chunk, max_corner_m)
    return score


_CHUNK = 128
"""Hypotheses scored at once (`score_hypotheses`)."""


def moved_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(H, K, 3): the (K, 3) points moved by each of the (H, 4, 4) poses (batched matmul)."""
    return np.swapaxes(T[:, :3, :3] @ points.T, 1, 2) + T[:, None, :3, 3]


def _plane_partners(frame, view, T, max_angle_rad, max_offset_m) -> np.ndarray:
    """(H, N, M) bool: observed plane n lies within the gates of map plane m under T."""
    n_world = np.swapaxes(T[:, :3, :3] @ frame.normals.T, 1, 2)  # (H, N, 3)
    d_world = frame.d[None, :] - np.sum(n_world * T[:, None, :3, 3], axis=2)
    cos = n_world @ view.normals.T  # (H, N, M)
    offset = np.abs(d_world[:, :, None] - view.d[None, None, :])
    return (cos >= np.cos(max_angle_rad)) & (offset <= max_offset_m)


def _edge_support(frame, view, partner: np.ndarray) -> np.ndarray:
    """(H,) observed edges whose two planes land (`partner`, (H, N, M) bool) on the two
    planes of a map edge that is at least as long (within 20 % and 5 cm)."""
    a, b = frame.edge_planes[:, 0], frame.edge_planes[:, 1]  # (Eo,)
    A, B = view.edge_planes[:, 0], view.edge_planes[:, 1]  # (Em,)
    same = partner[:, a][:, :, A] & partner[:, b][:, :, B]  # (H, Eo, Em)
    crossed = partner[:, a][:, :, B] & partner[:, b][:, :, A]
    long_enough = frame.edge_lengths[:, None] <= 1.2 * view.edge_lengths[None, :] + 0.05
    return np.count_nonzero(((same | crossed) & long_enough[None]).any(axis=2), axis=1)


def _object_support(frame, view, T, max_distance_m) -> np.ndarray:
    """(H,) observed objects with a map object of the same class whose sizes agree (each
    observed size within 20 % and 5 cm of a map size at most as large) and whose centre is
    within max_distance_m of the moved observed centre plus the map object's size."""
    moved = moved_points(T, frame.object_centres)
    dist = np.linalg.norm(moved[:, :, None] - view.object_centres[None, None], axis=-1)
    reach = max_distance_m + np.array([max(s) if len(s) else 0.0 for s in view.object_sizes])
    near = dist <= reach[None, None, :]  # (H, Oo, Om)
    fits = np.zeros((len(frame.object_sizes), len(view.object_sizes)), dtype=bool)
    for i, (cls_o, size_o) in enumerate(zip(frame.object_classes, frame.object_sizes, strict=True)):
        for j, (cls_m, size_m) in enumerate(
            zip(view.object_classes, view.object_sizes, strict=True)
        ):
            if cls_o != cls_m or cls_o == "unknown" or not len(size_o) or not len(size_m):
                continue
            fits[i, j] = all(any(s <= 1.2 * m + 0.05 for m in size_m) for s in size_o)
    return np.count_nonzero((near & fits[None]).any(axis=2), axis=1)


def agreeing_matches(
    poses: np.ndarray, p_cam: np.ndarray, p_world: np.ndarray, threshold: np.ndarray
) -> np.ndarray:
    """(H, M) bool: the matches (camera (M, 3) -> world (M, 3)) within their (M,)
    thresholds [m] under each of the (H, 4, 4) poses."""
    dist = np.linalg.norm(moved_points(poses, p_cam) - p_world[None], axis=2)
    return dist < threshold[None]
