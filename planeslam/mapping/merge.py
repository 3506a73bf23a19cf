"""The paper's frame-by-frame merge (Section 4.4, Fig. 5): one frame's planes, edges and
corners into the map under a pose and the correspondences of data association.

- a matched plane is refit from accumulated sufficient statistics (count, centroid,
  scatter moved to the world frame: c' = R c + t, S' = R S R^T, combined exactly by
  `planeslam.core.plane_fit.merge_moments`), never from stored points; its normal is
  the smallest eigenvector of the scatter, oriented like the map normal, d = -n . c.
  Its outline becomes the convex hull (in the plane) of both outlines and its area that
  hull's area;
- an observed edge between two mapped planes updates the map edge between them and
  keeps the LONGEST of the two lengths (the paper's rule), or is added; segments always
  lie on the current intersection line of the map planes;
- a matched corner averages its point (count-weighted); an unmatched corner whose three
  planes map to three distinct map planes is added (or averaged into the map corner of
  those three planes).

Re-aggregating the objects afterwards is the caller's step (`reaggregation`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from planeslam.core.errors import AssociationError, MapError
from planeslam.core.geometry import (
    rigid_pose,
    tangent_basis,
    transform_plane,
    unit,
)
from planeslam.core.plane_fit import correlated_depth_sigmas, merge_moments, plane_from_moments
from planeslam.frontend.types import Plane
from planeslam.mapping.contents import MapContents
from planeslam.mapping.gravity import UpSource
from planeslam.mapping.records import MapCorner, MapEdge, MapPlane
from planeslam.mapping.seating import hull_on_plane, outline_gap, reseat_edges

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MergeResult:
    """Where one frame's planes and corners went in the map (data association)."""

    planes: dict[int, int]
    """Observed plane index -> map plane id, for every observed plane (matched or new)."""
    corners: dict[int, int]
    """Observed corner index -> map corner id, for every corner merged."""


def merge_frame(
    contents: MapContents,
    observation: FrameObservation,
    T_world_cam: np.ndarray,
    plane_pairs: Sequence[tuple[int, int]] = (),
    corner_pairs: Sequence[tuple[int, int]] = (),
    keep_apart: Collection[int] = (),
) -> MergeResult:
    """Merge one frame (camera frame) into `contents` under T_world_cam (4, 4).

    plane_pairs: (observed plane index, map plane id) and corner_pairs: (observed corner
    index, map corner id), one-to-one. keep_apart: map plane ids that only a pair may
    merge into (an unpaired plane is never consolidated into them). Returns where every
    observed plane and corner went (matched or new). AssociationError for pairs naming
    unknown indices / ids or pairing one plane twice; MapError for a bad pose. Nothing
    changes when it raises.
    """
    T = rigid_pose(T_world_cam, "T_world_cam", MapError)
    structure = observation.structure
    obs_planes = observation.segmentation.planes
    pairs = _checked_pairs(plane_pairs, len(obs_planes), contents.planes, "plane")
    cpairs = _checked_pairs(corner_pairs, len(structure.corners), contents.corners, "corner")
    _take_frame_up(contents, observation, T)
    to_map = _merge_planes(contents, observation, T, pairs, set(keep_apart))
    id_to_map = {int(p.id): to_map[k] for k, p in enumerate(obs_planes)}
    _merge_edges(contents, observation, T, id_to_map, {to_map[k] for k in pairs})
    corners = _merge_corners(contents, observation, T, id_to_map, cpairs)
    contents.frames_merged += 1
    logger.debug(
        "merged frame %s: %d planes (%d matched), map has %d planes, %d edges, %d corners",
        observation.timestamp,
        len(obs_planes),
        len(pairs),
        len(contents.planes),
        len(contents.edges),
        len(contents.corners),
    )
    return MergeResult(planes=to_map, corners=corners)


def _take_frame_up(contents: MapContents, observation: FrameObservation, T: np.ndarray) -> None:
    """The first frame whose up came from a plane (or the config) defines the map's up; a
    frame that only fell back to the camera's -y axis is used until then."""
    structure = observation.structure
    fell_back = structure.gravity_source.is_fallback
    if len(structure.gravity_up_cam) == 3 and (
        contents.up is None or (contents.up_source.is_fallback and not fell_back)
    ):
        contents.up = unit(T[:3, :3] @ np.asarray(structure.gravity_up_cam, dtype=np.float64))
        contents.up_source = UpSource.of_frame(observation.timestamp, structure.gravity_source)


def _merge_planes(
    contents: MapContents,
    observation: FrameObservation,
    T: np.ndarray,
    pairs: dict[int, int],
    keep_apart: set[int],
) -> dict[int, int]:
    """Refit matched planes, add the others (consolidated into a map plane not in
    `keep_apart` when one is the same plane); {observed plane index: map plane id}."""
    R, t = T[:3, :3], T[:3, 3]
    cos_gate = math.cos(math.radians(contents.config.merge_max_angle_deg))
    to_map: dict[int, int] = {}
    targets: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # when needed: the
    # map's planes before this frame
    for k, p in enumerate(observation.segmentation.planes):
        n_w, d_w = transform_plane(T, np.asarray(p.normal, dtype=np.float64), float(p.d))
        c_w = R @ p.centroid + t
        S_w = R @ p.scatter @ R.T
        outline_w = p.outline @ R.T + t
        target = pairs.get(k)
        if target is not None and float(contents.planes[target].normal @ n_w) < cos_gate:
            logger.warning(
                "plane pair (%d, %d): normals %.1f deg apart, above merge_max_angle_deg; "
                "added as a new plane",
                k,
                target,
                math.degrees(
                    math.acos(float(np.clip(contents.planes[target].normal @ n_w, -1, 1)))
                ),
            )
            target = None
        if target is None and contents.config.consolidate:
            targets = targets or contents.plane_arrays()
            taken = set(to_map.values()) | set(pairs.values()) | keep_apart
            target = _same_plane_segment(contents, targets, p, T, n_w, c_w, outline_w, taken)
        if target is None:
            pid = contents.new_plane_id()
            contents.planes[pid] = MapPlane(
                id=pid,
                normal=n_w,
                d=d_w,
                centroid=c_w,
                scatter=S_w,
                num_points=int(p.num_points),
                area_m2=float(p.area_m2),
                outline=outline_w,
                observations=1,
                seen_in=frozenset({contents.frames_merged}),
            )
        else:
            pid = target
            contents.planes[pid] = _refit_plane(
                contents.planes[pid], int(p.num_points), c_w, S_w, outline_w, contents.frames_merged
            )
        to_map[k] = pid
    return to_map


def _same_plane_segment(
    contents: MapContents,
    targets: tuple[np.ndarray, np.ndarray, np.ndarray],
    plane: Plane,
    T: np.ndarray,
    n_w: np.ndarray,
    c_w: np.ndarray,
    outline_w: np.ndarray,
    taken: set[int],
) -> int | None:
    """The map plane of `targets` ((ids, normals, offsets), `MapContents.plane_arrays`; not
    in `taken`) that the observed `plane` (camera frame; seen from T_world_cam `T`; n_w,
    centroid c_w (3,) and outline (K, 3) in the world frame) is a part of, or None. Same
    plane: the map plane, moved to the camera, within `consolidate_max_sigmas` of the
    observation in its fit covariance (tangent normal, offset; widened by `_gate_floor`),
    within the angle and offset caps; then the outlines overlapping or nearest within
    `consolidate_max_gap_m`."""
    cfg = contents.config
    ids, normals, offsets = targets
    cos_cap = math.cos(math.radians(cfg.consolidate_max_angle_deg))
    close = (normals @ n_w >= cos_cap) & (
        np.abs(normals @ c_w + offsets) <= cfg.consolidate_max_offset_m
    )
    close &= ~np.isin(ids, list(taken))
    rows = np.flatnonzero(close)
    if not len(rows):
        return None
    n_cam = normals[rows] @ T[:3, :3]  # rows R^T n: the map planes in the camera frame
    d_cam = offsets[rows] + normals[rows] @ T[:3, 3]
    error = np.column_stack([n_cam @ tangent_basis(plane.normal), d_cam - plane.d])
    information = np.linalg.inv(np.asarray(plane.covariance) + _gate_floor(contents, plane))
    mahalanobis2 = np.einsum("mi,ij,mj->m", error, information, error)
    rows = rows[mahalanobis2 <= cfg.consolidate_max_sigmas**2]
    best, best_gap = None, cfg.consolidate_max_gap_m
    for row in rows:
        candidate = contents.planes[int(ids[row])]
        gap = outline_gap(candidate.outline, outline_w, candidate.normal, candidate.d)
        if gap <= best_gap:
            best, best_gap = int(ids[row]), gap
    return best


def _gate_floor(contents: MapContents, plane: Plane) -> np.ndarray:
    """(3, 3) diagonal covariance (tangent normal [rad^2] x 2, offset [m^2]) added to an
    observed plane's fit covariance in the consolidation gate. The fit covariance counts
    every pixel as independent, but a depth sensor's error is correlated across a patch
    (calibration, quantisation): a patch of half-width r [m] at depth z [m] is off by about
    k sigma(z) and tilted by k sigma(z) / r (k: `consolidate_correlated_depth`). Small far
    patches get the wide gate their real error needs; large near planes keep a tight one.
    Plus the pose uncertainty `consolidate_pose_sigma_*`."""
    cfg = contents.config
    tilt, sigma_z = correlated_depth_sigmas(
        contents.sensor,
        float(plane.centroid[2]),
        float(plane.area_m2),
        cfg.consolidate_correlated_depth,
    )
    angle = math.hypot(cfg.consolidate_pose_sigma_rad, tilt)
    offset = math.hypot(cfg.consolidate_pose_sigma_m, sigma_z)
    return np.diag([angle**2, angle**2, offset**2])


def _refit_plane(
    old: MapPlane,
    count: int,
    centroid_w: np.ndarray,
    scatter_w: np.ndarray,
    outline_w: np.ndarray,
    frame: int,
) -> MapPlane:
    """Exact moment merge, refit, orient like the map normal, hull of both outlines; seen
    in merge number `frame` too."""
    total, c, S = merge_moments(
        np.array([old.num_points, count]),
        np.stack([old.centroid, centroid_w]),
        np.stack([old.scatter, scatter_w]),
    )
    n, _, _ = plane_from_moments(c, S)
    if float(n @ old.normal) < 0:
        n = -n
    d = -float(n @ c)
    outline, area = hull_on_plane(np.concatenate([old.outline, outline_w]), n, d)
    return MapPlane(
        id=old.id,
        normal=n,
        d=d,
        centroid=c,
        scatter=S,
        num_points=total,
        area_m2=area,
        outline=outline,
        observations=old.observations + 1,
        seen_in=old.seen_in | {frame},
    )


def _merge_edges(
    contents: MapContents,
    observation: FrameObservation,
    T: np.ndarray,
    id_to_map: dict[int, int],
    matched: set[int],
) -> None:
    """Add or update the map edge of each observed edge (longest length kept), then seat
    the edges of every matched or touched plane on the current intersection lines."""
    R, t = T[:3, :3], T[:3, 3]
    touched = set(matched)
    for e in observation.structure.edges:
        a, b = (id_to_map[i] for i in e.planes)
        if a == b:
            continue
        key = (min(a, b), max(a, b))
        seg_w = np.asarray(e.segment, dtype=np.float64) @ R.T + t
        old = contents.edges.get(key)
        if old is None:
            contents.edges[key] = MapEdge(
                planes=key,
                segment=seg_w,
                length_m=float(e.length_m),
                angle_rad=float(e.angle_rad),
                convex=bool(e.convex),
                observations=1,
            )
        else:
            longer = float(e.length_m) > old.length_m
            contents.edges[key] = MapEdge(
                planes=key,
                segment=seg_w if longer else old.segment,
                length_m=float(e.length_m) if longer else old.length_m,
                angle_rad=(old.angle_rad * old.observations + float(e.angle_rad))
                / (old.observations + 1),
                convex=bool(e.convex) if longer else old.convex,
                observations=old.observations + 1,
            )
        touched.update(key)
    reseat_edges(contents, touched)


def _merge_corners(
    contents: MapContents,
    observation: FrameObservation,
    T: np.ndarray,
    id_to_map: dict[int, int],
    cpairs: dict[int, int],
) -> dict[int, int]:
    """Average matched corners' points (count-weighted); add the others whose three planes
    map to three distinct map planes (averaged into the map corner of those planes).
    Returns {observed corner index: map corner id} of the corners merged."""
    R, t = T[:3, :3], T[:3, 3]
    by_triple = {c.planes: c.id for c in contents.corners.values()}
    merged: dict[int, int] = {}
    for k, c in enumerate(observation.structure.corners):
        x_w = R @ np.asarray(c.point, dtype=np.float64) + t
        triple = tuple(sorted(id_to_map[i] for i in c.planes))
        cid = cpairs.get(k)
        if cid is None:
            if len(set(triple)) != 3:
                continue
            cid = by_triple.get(triple)  # type: ignore[arg-type]
        if cid is None:
            cid = contents.new_corner_id()
            contents.corners[cid] = MapCorner(
                id=cid,
                planes=triple,  # type: ignore[arg-type]
                point=x_w,
                convex_edges=int(c.convex_edges),
                observations=1,
            )
            by_triple[contents.corners[cid].planes] = cid
        else:
            old = contents.corners[cid]
            w = old.observations
            contents.corners[cid] = replace(
                old, point=(old.point * w + x_w) / (w + 1), observations=w + 1
            )
        merged[k] = cid
    return merged


def _checked_pairs(
    pairs: Sequence[tuple[int, int]], num_obs: int, targets: Mapping[int, Any], what: str
) -> dict[int, int]:
    """{observed index: map id} of one-to-one pairs naming existing indices and ids."""
    out: dict[int, int] = {}
    used: set[int] = set()
    for pair in pairs:
        k, j = (int(v) for v in pair)
        if not 0 <= k < num_obs:
            raise AssociationError(
                f"{what} pair {tuple(pair)}: observed index {k} outside 0..{num_obs - 1}"
            )
        if j not in targets:
            raise AssociationError(f"{what} pair {tuple(pair)}: no map {what} with id {j}")
        if k in out or j in used:
            raise AssociationError(f"{what} pairs are not one-to-one at {tuple(pair)}")
        out[k] = j
        used.add(j)
    return out
