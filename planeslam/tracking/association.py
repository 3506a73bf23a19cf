"""Data association of planes and trihedral corners between a frame and a map.

The paper (Section 4.4) matches planes of two plane-object maps "on the
basis of matching normals as well as distances between the considered
planes". Here a frame's observed planes are moved into the map frame by a
predicted pose, every (observation, map) pair gets a gated cost (normal
angle and offset difference, each divided by its gate, plus an optional
outline-overlap term) and a one-to-one assignment is found by the
Hungarian method (`scipy.optimize.linear_sum_assignment`).

Corners tie three planes together: `associate_with_corners` first matches
corners by position, fixes the three plane pairs of every matched corner,
then associates the remaining planes one by one.

Planes keep the orientation they were observed with (normal toward the
camera), so the two faces of a thin wall, seen from opposite sides, are
180 deg apart and never match.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np

from planeslam.core.errors import AssociationError
from planeslam.core.geometry import (
    as_pose,
    clip_convex_polygon,
    convex_hull_2d,
    cross,
    plane_basis,
    polygon_area,
)

logger = logging.getLogger(__name__)

_FORBIDDEN = 1e6
"""Cost of a gated-out pair: far above any allowed cost (allowed costs are <= 3)."""
_COUNT_FIRST = _FORBIDDEN / 2
"""Cost of leaving out an observed plane that pairs wherever it can: above any sum of
allowed (weighted) costs, below a gated-out pair's."""

_PERMUTATIONS_3 = np.array(list(itertools.permutations(range(3))))
"""(6, 3) the ways of pairing a corner's three planes with another corner's three."""


@dataclass(frozen=True)
class Association:
    """Plane and corner correspondences between a frame (obs) and a map."""

    planes: list[tuple[int, int]]
    """(obs plane index, map plane index), one-to-one, sorted by obs index."""
    corners: list[tuple[int, int]]
    """(obs corner index, map corner index), one-to-one, sorted by obs index."""

    def plane_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(P,) obs plane rows and (P,) map plane rows of `planes`, int64."""
        return pair_rows(self.planes)

    def corner_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(C,) obs corner rows and (C,) map corner rows of `corners`, int64."""
        return pair_rows(self.corners)


def pair_rows(pairs: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """The two columns of index `pairs` as (K,) int64 arrays (empty for no pairs)."""
    first, second = np.array(pairs, dtype=np.int64).reshape(-1, 2).T
    return first, second


# ----------------------------------------------------------------------------- validation


def _vectors(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise AssociationError(f"{name} has shape {a.shape}, expected (N, 3)")
    if not np.all(np.isfinite(a)):
        raise AssociationError(f"{name} contains non-finite values")
    return a


def _offsets(name: str, d: np.ndarray, n: int) -> np.ndarray:
    d = np.asarray(d, dtype=np.float64)
    if d.shape != (n,) or not np.all(np.isfinite(d)):
        raise AssociationError(f"{name} has shape {d.shape} or non-finite values, expected ({n},)")
    return d


Gate = float | np.ndarray
"""A gate: one value for every observation, or (N,) values, one per observation."""


def _gate(name: str, value: Gate, n: int | None = None) -> Gate:
    """A positive scalar gate as a float, or a (n,) array of positive per-observation gates."""
    if np.ndim(value) == 0:
        scalar = float(value)
        if not scalar > 0:
            raise AssociationError(f"{name} = {scalar}, expected a positive gate")
        return scalar
    gates = np.asarray(value, dtype=np.float64)
    if gates.shape != (n,) or not np.all(np.isfinite(gates)) or not np.all(gates > 0):
        raise AssociationError(
            f"{name} has shape {gates.shape}, expected a positive number or ({n},) positive "
            "gates (one per observation)"
        )
    return gates


def _per_row(gate: Gate) -> Gate:
    """A gate broadcast over the rows (observations) of an (N, M) matrix."""
    return gate[:, None] if isinstance(gate, np.ndarray) else gate


def _take(gate: Gate, rows: np.ndarray) -> Gate:
    """The gates of the observations `rows` (a scalar gate is everyone's)."""
    return gate[rows] if isinstance(gate, np.ndarray) else gate


def _corner_planes(name: str, ids: np.ndarray, num_planes: int) -> np.ndarray:
    ids = np.asarray(ids)
    if (
        ids.ndim != 2
        or ids.shape[1] != 3
        or (ids.size and not np.issubdtype(ids.dtype, np.integer))
    ):
        raise AssociationError(
            f"{name} has shape {ids.shape} / dtype {ids.dtype}, expected (K, 3) int"
        )
    ids = ids.astype(np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= num_planes):
        raise AssociationError(f"{name} refers to planes outside 0..{num_planes - 1}")
    return ids


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle [rad] between unit vectors a (..., 3) and b (..., 3), broadcast; robust near 0, pi."""
    return np.arctan2(np.linalg.norm(cross(a, b), axis=-1), np.einsum("...i,...i->...", a, b))


# ----------------------------------------------------------------------------- planes


def plane_association_cost(
    n_map: np.ndarray,
    d_map: np.ndarray,
    n_obs: np.ndarray,
    d_obs: np.ndarray,
    T_map_obs: np.ndarray,
    max_angle_rad: Gate,
    max_offset_m: Gate,
    overlap: np.ndarray | None = None,
    min_overlap: float = 0.0,
    overlap_weight: float = 1.0,
    weights: np.ndarray | None = None,
    gate: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Gated cost of pairing each observed plane with each map plane.

    n_map (M, 3), d_map (M,) in the map frame; n_obs (N, 3), d_obs (N,) in
    the observation (camera) frame; T_map_obs (4, 4) predicted pose.
    max_angle_rad, max_offset_m: one gate, or (N,) gates, one per observed plane.
    cost = angle / max_angle + |d_obs_in_map - d_map| / max_offset
    (+ overlap_weight * (1 - overlap) when an (N, M) overlap in [0, 1] is
    given). Returns cost (N, M) and allowed (N, M) bool: angle <= max_angle,
    offset difference <= max_offset and overlap >= min_overlap. `weights` (N,) > 0 scale
    each observed plane's row (e.g. inlier counts): the assignment then gets the large
    planes right first, so a floor never yields to a small plane that prefers its partner.
    `gate` (N, M) bool: an extra gate of the caller's (e.g. size compatibility).
    """
    n_map, n_obs = _vectors("n_map", n_map), _vectors("n_obs", n_obs)
    d_map, d_obs = _offsets("d_map", d_map, len(n_map)), _offsets("d_obs", d_obs, len(n_obs))
    T = as_pose(T_map_obs, "T_map_obs", AssociationError)
    max_angle = _per_row(_gate("max_angle_rad", max_angle_rad, len(n_obs)))
    max_offset = _per_row(_gate("max_offset_m", max_offset_m, len(n_obs)))
    n_obs = n_obs / np.linalg.norm(n_obs, axis=1, keepdims=True)
    n_map = n_map / np.linalg.norm(n_map, axis=1, keepdims=True)
    n_in_map = n_obs @ T[:3, :3].T
    d_in_map = d_obs - n_in_map @ T[:3, 3]
    angle = _angles(n_in_map[:, None, :], n_map[None, :, :])
    offset = np.abs(d_in_map[:, None] - d_map[None, :])
    cost = angle / max_angle + offset / max_offset
    allowed = (angle <= max_angle) & (offset <= max_offset)
    if overlap is not None:
        overlap = np.asarray(overlap, dtype=np.float64)
        if overlap.shape != cost.shape or not np.all(np.isfinite(overlap)):
            raise AssociationError(
                f"overlap has shape {overlap.shape}, expected {cost.shape} in [0, 1]"
            )
        cost = cost + overlap_weight * (1.0 - overlap)
        allowed &= overlap >= min_overlap
    if gate is not None:
        gate = np.asarray(gate, dtype=bool)
        if gate.shape != cost.shape:
            raise AssociationError(f"gate has shape {gate.shape}, expected {cost.shape}")
        allowed &= gate
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(n_obs),) or not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise AssociationError(f"weights has shape {w.shape}, expected ({len(n_obs)},) > 0")
        cost = cost * w[:, None]
    return cost, allowed


def _map_selection(weigh_unpaired: bool | np.ndarray, num_map: int) -> bool | np.ndarray:
    """`weigh_unpaired` checked: a bool, or a (num_map,) bool array (one per map plane)."""
    if isinstance(weigh_unpaired, bool | np.bool_):
        return bool(weigh_unpaired)
    selected = np.asarray(weigh_unpaired)
    if selected.dtype != bool or selected.shape != (num_map,):
        raise AssociationError(
            f"weigh_unpaired has shape {selected.shape} ({selected.dtype}), expected a bool or "
            f"({num_map},) bool, one per map plane"
        )
    return selected


def _weighed_rows(weigh_unpaired: bool | np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """(N,) bool: the observed planes whose leaving out costs their weight
    (`associate_planes`): every one (True), none (False), or those `allowed` (N, M) to pair
    with a map plane that the (M,) bool `weigh_unpaired` selects."""
    selected = _map_selection(weigh_unpaired, allowed.shape[1])
    if isinstance(selected, bool):
        return np.full(len(allowed), selected)
    return np.asarray((allowed & selected[None, :]).any(axis=1))


def _assign(
    cost: np.ndarray, allowed: np.ndarray, miss: np.ndarray | None = None
) -> list[tuple[int, int]]:
    """One-to-one minimum-cost pairs among allowed ones (rows, cols). Without `miss` the
    number of pairs comes first; with `miss` (R,), the cost of leaving each row unpaired,
    a row is paired only where that lowers the total (an extra column per row)."""
    from scipy.optimize import linear_sum_assignment  # 0.3 s to import: not at start-up

    if cost.size == 0 or not allowed.any():
        return []
    full = np.where(allowed, cost, _FORBIDDEN)
    if miss is not None:
        unpaired = np.full((len(cost), len(cost)), _FORBIDDEN)
        np.fill_diagonal(unpaired, miss)
        full = np.hstack([full, unpaired])
    rows, cols = linear_sum_assignment(full)
    keep = cols < cost.shape[1]
    keep[keep] = allowed[rows[keep], cols[keep]]
    return sorted(zip(rows[keep].tolist(), cols[keep].tolist(), strict=True))


def associate_planes(
    n_map: np.ndarray,
    d_map: np.ndarray,
    n_obs: np.ndarray,
    d_obs: np.ndarray,
    T_map_obs: np.ndarray,
    max_angle_rad: Gate,
    max_offset_m: Gate,
    overlap: np.ndarray | None = None,
    min_overlap: float = 0.0,
    overlap_weight: float = 1.0,
    weights: np.ndarray | None = None,
    gate: np.ndarray | None = None,
    weigh_unpaired: bool | np.ndarray = False,
) -> list[tuple[int, int]]:
    """One-to-one (obs index, map index) plane pairs under a predicted pose T_map_obs (4, 4).

    Shapes, frames and the cost as in `plane_association_cost`; pairs outside
    the gates are never returned. The Hungarian assignment maximises the
    number of allowed pairs first, then minimises their total cost. With
    `weights` and `weigh_unpaired`, a plane left unpaired costs its weight times
    the largest cost the gates allow instead: two planes that both fit one map
    plane (a wall and a picture hanging on it) leave out the one that loses
    less, so a small plane does not take a large one's partner because its
    weighted cost is lower. `weigh_unpaired`
    (M,) bool instead of True: only the observed planes the gates allow to pair with
    one of the selected map planes (walls and floors:
    `TrackingConfig.weigh_unpaired_min_area_m2`) are weighed so; the others pair
    wherever they can, as without it.
    """
    cost, allowed = plane_association_cost(
        n_map,
        d_map,
        n_obs,
        d_obs,
        T_map_obs,
        max_angle_rad,
        max_offset_m,
        overlap,
        min_overlap,
        overlap_weight,
        weights,
        gate,
    )
    weighed = _weighed_rows(weigh_unpaired, allowed)
    miss = None
    if weights is not None and weighed.any():  # weights checked by plane_association_cost
        # inside the gates the angle and offset terms are each at most 1 (cost docstring)
        largest = 2.0 + (overlap_weight * (1.0 - min_overlap) if overlap is not None else 0.0)
        # the others are left out only where no allowed pair is left (count first)
        miss = np.where(weighed, largest * np.asarray(weights, dtype=np.float64), _COUNT_FIRST)
    pairs = _assign(cost, allowed, miss)
    logger.debug("associated %d of %d observed planes (%d map planes)", len(pairs), *cost.shape)
    return pairs


# ----------------------------------------------------------------------------- outlines


def outline_overlap(outline_a: np.ndarray, outline_b: np.ndarray, n: np.ndarray, d: float) -> float:
    """Overlap in [0, 1] of two plane outlines (K, 3), (L, 3) [m] on the plane (n, d).

    Both are projected orthogonally onto the plane (2-D coordinates about
    its foot point -d n), replaced by their convex hulls (`convex_hull_2d`) and
    intersected by Sutherland-Hodgman clipping in float64; the result is
    intersection area / smaller hull area. Convex hulls make it exact for
    convex regions (wall, table top, box face) and an over-estimate for
    concave ones (a floor around an obstacle), which errs toward keeping a
    match; an outline with no area (fewer than 3 points, collinear)
    overlaps nothing (0.0). Express both outlines in the plane's frame
    first. (cv2.intersectConvexConvex was tried and rejected: it returns
    the full area for two squares sharing a nearly collinear edge.)
    """
    a, b = _vectors("outline_a", outline_a), _vectors("outline_b", outline_b)
    n = np.asarray(n, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(n)) if n.shape == (3,) else 0.0
    if not norm > 1e-9 or not np.isfinite(d):
        raise AssociationError(f"plane ({n}, {d}) is not a finite (3,) normal and offset")
    n = n / norm
    basis, foot = plane_basis(n), -float(d) / norm * n
    hull_a = convex_hull_2d((a - foot) @ basis.T)
    hull_b = convex_hull_2d((b - foot) @ basis.T)
    smaller = min(polygon_area(hull_a), polygon_area(hull_b))
    if smaller <= 1e-12:
        return 0.0
    inter = polygon_area(clip_convex_polygon(hull_a, hull_b))
    return float(np.clip(inter / smaller, 0.0, 1.0))


# ----------------------------------------------------------------------------- corners


def associate_corners(
    corner_planes_obs: np.ndarray,
    corner_planes_map: np.ndarray,
    plane_pairs: list[tuple[int, int]],
) -> list[tuple[int, int]]:
    """(obs corner, map corner) pairs whose three planes are associated with each other.

    corner_planes_obs (Ko, 3), corner_planes_map (Km, 3): plane indices of
    each corner (any order); plane_pairs: (obs plane, map plane) pairs from
    `associate_planes`. A corner matches when its three planes map onto
    exactly the three planes of a map corner.
    """
    obs = np.asarray(corner_planes_obs).reshape(-1, 3)
    to_map = dict(plane_pairs)
    map_corner_of: dict[frozenset[int], int] = {}
    for k, ids in enumerate(np.asarray(corner_planes_map).reshape(-1, 3).tolist()):
        map_corner_of.setdefault(frozenset(ids), k)
    pairs = []
    for k, ids in enumerate(obs.tolist()):
        if all(i in to_map for i in ids):
            match = map_corner_of.get(frozenset(to_map[i] for i in ids))
            if match is not None:
                pairs.append((k, match))
    return pairs


def associate_with_corners(
    n_map: np.ndarray,
    d_map: np.ndarray,
    corner_planes_map: np.ndarray,
    corner_points_map: np.ndarray,
    n_obs: np.ndarray,
    d_obs: np.ndarray,
    corner_planes_obs: np.ndarray,
    corner_points_obs: np.ndarray,
    T_map_obs: np.ndarray,
    max_angle_rad: Gate,
    max_offset_m: Gate,
    max_corner_distance_m: Gate,
    overlap: np.ndarray | None = None,
    min_overlap: float = 0.0,
    weights: np.ndarray | None = None,
    gate: np.ndarray | None = None,
    weigh_unpaired: bool | np.ndarray = False,
) -> Association:
    """Associate corners first, fix their three plane pairs together, then the other planes.

    Map: planes n_map (M, 3), d_map (M,); corners as plane indices
    corner_planes_map (Km, 3) and points corner_points_map (Km, 3) [m], map
    frame. Observation: the same in the camera frame ((N, 3), (N,), (Ko, 3),
    (Ko, 3)). T_map_obs (4, 4) predicted pose. Gates: one value each, or one per
    observation: max_angle_rad and max_offset_m (N,) per observed plane,
    max_corner_distance_m (Ko,) per observed corner.

    1. A corner pair is allowed when the observed point, moved by T_map_obs,
       is within max_corner_distance_m of the map point and the three
       observed normals pair with the three map normals (best of the 6
       pairings) each within max_angle_rad. Offsets are not gated here: the
       corner distance gate plays that role, so a corner can recover planes
       whose offsets drifted beyond max_offset_m under a poor prediction.
    2. Hungarian assignment on distance / gate + mean angle / gate.
    3. Matched corners, best first, fix their three plane pairs; a corner
       contradicting pairs fixed before it is dropped.
    4. The remaining planes go through `associate_planes` (with the
       matching rows / columns of `overlap`, `gate` and entries of `weights`, if
       given, and `weigh_unpaired`: True, or (M,) bool over the map planes). `gate`
       (N, M) bool also restricts the corners' plane pairings.
    5. Corners whose three planes ended up associated are added
       (`associate_corners`).
    """
    n_map, n_obs = _vectors("n_map", n_map), _vectors("n_obs", n_obs)
    d_map, d_obs = _offsets("d_map", d_map, len(n_map)), _offsets("d_obs", d_obs, len(n_obs))
    cp_map = _corner_planes("corner_planes_map", corner_planes_map, len(n_map))
    cp_obs = _corner_planes("corner_planes_obs", corner_planes_obs, len(n_obs))
    x_map, x_obs = (
        _vectors("corner_points_map", corner_points_map),
        _vectors("corner_points_obs", corner_points_obs),
    )
    if len(x_map) != len(cp_map) or len(x_obs) != len(cp_obs):
        raise AssociationError(
            f"corner points ({len(x_obs)} obs, {len(x_map)} map) and corner planes "
            f"({len(cp_obs)} obs, {len(cp_map)} map) differ in count"
        )
    T = as_pose(T_map_obs, "T_map_obs", AssociationError)
    selected = _map_selection(weigh_unpaired, len(n_map))
    max_angle_rad = _gate("max_angle_rad", max_angle_rad, len(n_obs))
    max_offset_m = _gate("max_offset_m", max_offset_m, len(n_obs))
    max_corner_distance_m = _gate("max_corner_distance_m", max_corner_distance_m, len(cp_obs))
    n_map_u = n_map / np.linalg.norm(n_map, axis=1, keepdims=True)
    n_obs_in_map = (n_obs / np.linalg.norm(n_obs, axis=1, keepdims=True)) @ T[:3, :3].T

    fixed_obs: dict[int, int] = {}
    fixed_map: dict[int, int] = {}
    corner_pairs: list[tuple[int, int]] = []
    if len(cp_obs) and len(cp_map):
        dist = np.linalg.norm(
            (x_obs @ T[:3, :3].T + T[:3, 3])[:, None, :] - x_map[None, :, :], axis=-1
        )
        # angle[ko, km, i, j]: obs plane i of corner ko against map plane j of corner km
        angle = _angles(
            n_obs_in_map[cp_obs][:, None, :, None, :], n_map_u[cp_map][None, :, None, :, :]
        )
        ko, km = (
            np.arange(len(cp_obs))[:, None, None, None],
            np.arange(len(cp_map))[None, :, None, None],
        )
        per_perm = angle[ko, km, np.arange(3), _PERMUTATIONS_3[None, None]]  # (Ko, Km, 6, 3)
        best = np.argmin(per_perm.sum(-1), axis=-1)  # (Ko, Km)
        best_angles = np.take_along_axis(per_perm, best[..., None, None], axis=2)[:, :, 0]
        if isinstance(max_angle_rad, np.ndarray):  # per observed plane: (Ko, 1, 3)
            corner_angle_gate = max_angle_rad[cp_obs][:, None, :]
            angles_ok = np.all(best_angles <= corner_angle_gate, axis=-1)
            angle_cost = np.mean(best_angles / corner_angle_gate, axis=-1)
        else:
            angles_ok = best_angles.max(-1) <= max_angle_rad
            angle_cost = best_angles.mean(-1) / max_angle_rad
        allowed = (dist <= _per_row(max_corner_distance_m)) & angles_ok
        if gate is not None:
            perm = _PERMUTATIONS_3[best]  # (Ko, Km, 3)
            map_rows = np.take_along_axis(np.broadcast_to(cp_map[None], perm.shape), perm, axis=2)
            obs_rows = np.broadcast_to(cp_obs[:, None, :], perm.shape)
            allowed &= np.asarray(gate, dtype=bool)[obs_rows, map_rows].all(-1)
        cost = dist / _per_row(max_corner_distance_m) + angle_cost
        matched = _assign(cost, allowed)
        for k_obs, k_map in sorted(matched, key=lambda p: cost[p]):
            perm = _PERMUTATIONS_3[best[k_obs, k_map]]
            trio = list(zip(cp_obs[k_obs].tolist(), cp_map[k_map][perm].tolist(), strict=True))
            if all(fixed_obs.get(i, j) == j and fixed_map.get(j, i) == i for i, j in trio):
                fixed_obs.update(trio)
                fixed_map.update((j, i) for i, j in trio)
                corner_pairs.append((k_obs, k_map))
            else:
                logger.debug(
                    "corner pair (%d, %d) contradicts earlier corners, dropped", k_obs, k_map
                )

    free_obs = np.array([i for i in range(len(n_obs)) if i not in fixed_obs], dtype=np.int64)
    free_map = np.array([j for j in range(len(n_map)) if j not in fixed_map], dtype=np.int64)
    sub_overlap = None
    if overlap is not None:
        overlap = np.asarray(overlap, dtype=np.float64)
        if overlap.shape != (len(n_obs), len(n_map)):
            raise AssociationError(
                f"overlap has shape {overlap.shape}, expected {(len(n_obs), len(n_map))}"
            )
        sub_overlap = overlap[np.ix_(free_obs, free_map)]
    rest = associate_planes(
        n_map[free_map],
        d_map[free_map],
        n_obs[free_obs],
        d_obs[free_obs],
        T,
        _take(max_angle_rad, free_obs),
        _take(max_offset_m, free_obs),
        sub_overlap,
        min_overlap,
        weights=None if weights is None else np.asarray(weights, dtype=np.float64)[free_obs],
        gate=None if gate is None else np.asarray(gate, dtype=bool)[np.ix_(free_obs, free_map)],
        weigh_unpaired=selected if isinstance(selected, bool) else selected[free_map],
    )
    plane_pairs = sorted(
        list(fixed_obs.items()) + [(int(free_obs[i]), int(free_map[j])) for i, j in rest]
    )
    seen = {k for k, _ in corner_pairs}
    seen_map = {k for _, k in corner_pairs}
    for k_obs, k_map in associate_corners(cp_obs, cp_map, plane_pairs):
        if k_obs not in seen and k_map not in seen_map:
            corner_pairs.append((k_obs, k_map))
            seen.add(k_obs)
            seen_map.add(k_map)
    logger.debug(
        "associated %d corners and %d planes (%d fixed by corners)",
        len(corner_pairs),
        len(plane_pairs),
        len(fixed_obs),
    )
    return Association(planes=plane_pairs, corners=sorted(corner_pairs))
