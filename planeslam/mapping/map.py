"""The world-frame plane-object map and the paper's frame-by-frame merging (Section 4.4, Fig. 5).

A `Map` holds planes, real intersections (edges), trihedral corners and
plane-based objects in the world frame, plus a voxelised sparse cloud for what
is not planar. `Map.merge` adds one frame's `FrameObservation` under a pose
`T_world_cam` and the plane / corner correspondences found by data
association:

- a matched plane is refit from accumulated sufficient statistics (count,
  centroid, scatter moved to the world frame: c' = R c + t, S' = R S R^T,
  combined exactly by `planeslam.core.plane_fit.merge_moments`), never from stored
  points; its normal is the smallest eigenvector of the scatter, oriented like
  the map normal, d = -n . c. Its outline becomes the convex hull (in the
  plane) of both outlines and its area that hull's area;
- an observed edge between two mapped planes updates the map edge between
  them and keeps the LONGEST of the two lengths (the paper's rule), or is
  added; segments always lie on the current intersection line of the map
  planes;
- a matched corner averages its point (count-weighted); an unmatched corner
  whose three planes map to three distinct map planes is added;
- objects are then re-aggregated and re-classified (`reaggregate`): corners
  that share an edge form an object (`aggregate_corners`), classified with the
  pattern table (`classify_object`) and sized from the edges, with the world
  up vector the map knows (`set_gravity`, else the first frame's estimate).

`update_geometry` replaces plane parameters (e.g. optimised landmarks from
the GTSAM backend) and re-seats outlines, edges and corners on them.

Persistence: `to_dict` / `from_dict` / `save` / `load` use the shared schema
'planeslam.map/1' (world frame) with the extra statistics needed to continue
merging after a reload; a save/load round trip is exact. `write_ply` writes
the plane polygons coloured by object plus the sparse cloud as one binary PLY.

Ids: plane and corner ids are monotonic and never reused (also across a
save/load); object ids are renumbered 0..K-1 at every re-aggregation.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import networkx as nx
import numpy as np

from planeslam.core.errors import AssociationError, GeometryError, PlaneSlamError
from planeslam.core.geometry import (
    as_pose,
    convex_hull_2d,
    intersect_three_planes,
    plane_basis,
    polygon_area,
    rotation_between,
    transform_plane,
    unit,
)
from planeslam.core.plane_fit import merge_moments, plane_from_moments
from planeslam.frontend.config import ObjectConfig
from planeslam.frontend.objects import (
    DEFAULT_PATTERNS,
    MAP_SCHEMA,
    ObjectPattern,
    classify_object,
    convex_part,
    measure_extent,
    measure_size,
)
from planeslam.frontend.plane_graph import aggregate_corners, find_corners, plane_orientation
from planeslam.mapping.config import MapConfig

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

logger = logging.getLogger(__name__)

_KEY_BITS = 21
"""Bits per axis of a packed voxel key: +-2^20 voxels (+-52 km at 5 cm)."""
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_GREY = np.array([160, 160, 160], dtype=np.uint8)


class MapError(PlaneSlamError):
    """Bad input to the map (shapes, unknown ids) or an unreadable / unknown map file."""


@dataclass(frozen=True, eq=False)
class MapPlane:
    """A plane of the map, world frame, n . x + d = 0 (n oriented as first observed)."""

    id: int
    normal: np.ndarray
    """(3,) unit normal, world frame."""
    d: float
    """Offset [m]."""
    centroid: np.ndarray
    """(3,) mean of all inliers merged so far, world frame [m]."""
    scatter: np.ndarray = field(repr=False)
    """(3, 3) centred sum of outer products of all inliers, world frame [m^2]."""
    num_points: int
    """Inliers merged so far (over all observations)."""
    area_m2: float
    """Area of the outline [m^2] (the frame's visible area until merged once)."""
    outline: np.ndarray = field(repr=False)
    """(M, 3) polygon on the plane, world frame [m]; the convex hull once merged."""
    observations: int
    """Frames that observed it."""


@dataclass(frozen=True, eq=False)
class MapEdge:
    """A real intersection of two map planes, world frame."""

    planes: tuple[int, int]
    """Map plane ids, smaller first."""
    segment: np.ndarray = field(repr=False)
    """(2, 3) end points on the planes' intersection line, world frame [m]."""
    length_m: float
    """Longest length observed [m] (the paper's merge rule)."""
    angle_rad: float
    """Dihedral angle between the regions [rad] (pi - angle between the normals)."""
    convex: bool
    """Convexity of the longest observation."""
    observations: int


@dataclass(frozen=True, eq=False)
class MapCorner:
    """A trihedral corner of three map planes, world frame."""

    id: int
    planes: tuple[int, int, int]
    """Map plane ids, increasing."""
    point: np.ndarray
    """(3,) corner point, world frame [m] (count-weighted mean of the observed points)."""
    convex_edges: int
    """How many of its three edges are convex (3: box corner, 0: room corner)."""
    observations: int
    """Frames that observed it; 0 for a corner derived from the merged map graph."""


@dataclass(frozen=True)
class MapObject:
    """A plane-based object of the map: corners sharing edges, with class and size."""

    id: int
    cls: str
    """Class from the pattern table ('box', 'room', ...) or 'unknown'."""
    planes: tuple[int, ...]
    """Map plane ids, increasing."""
    corners: tuple[int, ...]
    """Map corner ids, increasing."""
    size_m: tuple[float, ...]
    """Extents along up to three orthogonal directions, largest first [m]."""


# ----------------------------------------------------------------------------- helpers


def project_to_plane(points: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Orthogonal projection of (K, 3) points onto the plane n . x + d = 0 (unit n)."""
    return points - np.outer(points @ n + d, n)


def hull_on_plane(points: np.ndarray, n: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    """Convex hull of (K, 3) points projected onto the plane (unit n, d): ((H, 3) polygon on
    the plane, counter-clockwise about n, and its area [m^2]). Degenerate input (fewer than
    3 points, collinear) gives the projected points and area 0."""
    foot = -d * n
    axes = plane_basis(n)
    ring = convex_hull_2d((points - foot) @ axes.T)  # counter-clockwise in (u, v), u x v = n
    if len(ring) == 0:
        return project_to_plane(points, n, d), 0.0
    return foot + ring @ axes, polygon_area(ring)


def seat_segments(
    segments: np.ndarray,
    lengths_m: np.ndarray,
    n1: np.ndarray,
    d1: np.ndarray,
    n2: np.ndarray,
    d2: np.ndarray,
    min_sin: float = 0.1,
) -> np.ndarray:
    """(E, 2, 3) segments of `lengths_m` (E,) on the intersection lines of the plane pairs
    (n1 (E, 3), d1 (E,)) and (n2, d2): centred on the projection of each old segment's
    midpoint and pointing like it. Pairs closer to parallel than `min_sin` keep their old
    segment (as `planeslam.core.geometry.plane_line` refuses them)."""
    u = np.cross(n1, n2)
    s = np.linalg.norm(u, axis=1)
    ok = s >= min_sin
    out = np.array(segments, dtype=np.float64, copy=True)
    if not ok.any():
        return out
    u = u[ok] / s[ok, None]
    A = np.stack([n1[ok], n2[ok], u], axis=1)  # (E', 3, 3)
    b = np.stack([-d1[ok], -d2[ok], np.zeros(int(ok.sum()))], axis=1)
    p0 = np.linalg.solve(A, b[..., None])[..., 0]  # the line's point closest to the origin
    seg = out[ok]
    u = u * np.where(np.einsum("ei,ei->e", u, seg[:, 1] - seg[:, 0]) < 0, -1.0, 1.0)[:, None]
    mid = p0 + np.einsum("ei,ei->e", seg.mean(axis=1) - p0, u)[:, None] * u
    half = 0.5 * np.asarray(lengths_m, dtype=np.float64)[ok, None] * u
    out[ok] = np.stack([mid - half, mid + half], axis=1)
    return out


def _floats(a: Any) -> list[Any]:
    return np.asarray(a, dtype=np.float64).tolist()


def _pose(T: np.ndarray) -> np.ndarray:
    T = as_pose(T, "T_world_cam", MapError)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise MapError("T_world_cam's rotation block is not a rotation matrix")
    return T


def _palette(k: int) -> np.ndarray:
    """Distinct uint8 RGB colour for object index k (golden-ratio hues)."""
    import colorsys

    r, g, b = colorsys.hsv_to_rgb((0.07 + 0.618034 * k) % 1.0, 0.75, 0.95)
    return np.array([round(255 * r), round(255 * g), round(255 * b)], dtype=np.uint8)


# ----------------------------------------------------------------------------- the map


class Map:
    """The world-frame plane-object map (paper Section 4.4) with a sparse voxel cloud."""

    def __init__(
        self,
        config: MapConfig | None = None,
        object_config: ObjectConfig | None = None,
        patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    ) -> None:
        """`object_config` gives the orientation tolerance, corner and size parameters of
        re-aggregation (its gravity keys are unused: see `set_gravity`)."""
        self.config = config or MapConfig()
        self.object_config = object_config or ObjectConfig()
        self.patterns = tuple(patterns)
        self._planes: dict[int, MapPlane] = {}
        self._edges: dict[tuple[int, int], MapEdge] = {}
        self._corners: dict[int, MapCorner] = {}
        self._objects: list[MapObject] = []
        self._next_plane = 0
        self._next_corner = 0
        self._up: np.ndarray | None = None
        self.gravity_source = ""
        """'set' (set_gravity), 'frame <timestamp>' (that frame's estimate, then refined
        to the normal of the largest horizontal map plane at each re-aggregation),
        'frame <timestamp> (fallback)' (that frame saw no horizontal plane) or ''."""
        self._vox_keys = np.zeros((0, 3), dtype=np.int64)
        self._vox_points = np.zeros((0, 3))
        self._vox_counts = np.zeros(0, dtype=np.int64)
        self._vox_colors = np.zeros((0, 3), dtype=np.uint8)
        self.frames_merged = 0

    # ------------------------------------------------------------------ read access

    @property
    def planes(self) -> Mapping[int, MapPlane]:
        """Read-only {plane id: MapPlane}, ids increasing."""
        return MappingProxyType(self._planes)

    @property
    def edges(self) -> Mapping[tuple[int, int], MapEdge]:
        """Read-only {(plane id, plane id) smaller first: MapEdge}."""
        return MappingProxyType(self._edges)

    @property
    def corners(self) -> Mapping[int, MapCorner]:
        """Read-only {corner id: MapCorner}, ids increasing."""
        return MappingProxyType(self._corners)

    @property
    def objects(self) -> list[MapObject]:
        """Objects of the last re-aggregation (a copy)."""
        return list(self._objects)

    @property
    def gravity_up(self) -> np.ndarray | None:
        """(3,) unit world up vector, or None before it is known."""
        return None if self._up is None else self._up.copy()

    def outline(self, plane_id: int) -> np.ndarray:
        """(M, 3) outline of a map plane, world frame [m]."""
        return self._plane(plane_id).outline

    def plane_ids(self) -> np.ndarray:
        """(M,) int64 map plane ids, increasing (the row order of `plane_arrays`)."""
        return np.fromiter(self._planes, dtype=np.int64, count=len(self._planes))

    def plane_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (M,) int64, normals (M, 3), d (M,)), world frame, rows by increasing id."""
        planes = list(self._planes.values())
        normals = np.array([p.normal for p in planes]).reshape(-1, 3)
        return self.plane_ids(), normals, np.array([p.d for p in planes], dtype=np.float64)

    def corner_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (K,) int64, planes (K, 3) int64 ROW INDICES into `plane_arrays`, points (K, 3)
        world frame [m]), rows by increasing corner id."""
        row = {pid: k for k, pid in enumerate(self._planes)}
        corners = list(self._corners.values())
        ids = np.array([c.id for c in corners], dtype=np.int64)
        planes = np.array([[row[p] for p in c.planes] for c in corners], dtype=np.int64)
        points = np.array([c.point for c in corners], dtype=np.float64)
        return ids, planes.reshape(-1, 3), points.reshape(-1, 3)

    @property
    def sparse_points(self) -> np.ndarray:
        """(V, 3) sparse cloud, one mean point per voxel, world frame [m]."""
        return self._vox_points.copy()

    @property
    def sparse_colors(self) -> np.ndarray:
        """(V, 3) uint8 mean colour per voxel."""
        return self._vox_colors.copy()

    def _plane(self, plane_id: int) -> MapPlane:
        try:
            return self._planes[int(plane_id)]
        except KeyError:
            raise MapError(f"no map plane with id {plane_id}") from None

    # ------------------------------------------------------------------ gravity

    def set_gravity(self, up_world: np.ndarray) -> None:
        """Set the world up vector (3,) (opposite to gravity) used to classify objects."""
        up = np.asarray(up_world, dtype=np.float64).reshape(-1)
        if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.linalg.norm(up) > 1e-9:
            raise MapError(f"up_world must be a finite non-zero (3,) vector, got {up_world!r}")
        self._up = unit(up)
        self.gravity_source = "set"

    # ------------------------------------------------------------------ merging

    def merge(
        self,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        plane_pairs: Sequence[tuple[int, int]] = (),
        corner_pairs: Sequence[tuple[int, int]] = (),
        reaggregate: bool = True,
    ) -> dict[int, int]:
        """Merge one frame into the map (paper Fig. 5) and re-aggregate the objects.

        observation: the front end's result, camera frame; T_world_cam (4, 4);
        plane_pairs: (observed plane index, map plane id) and corner_pairs:
        (observed corner index, map corner id), one-to-one, from data
        association. `reaggregate=False` defers `reaggregate` (objects) to the
        caller, e.g. to keyframes. Returns {observed plane index: map plane id} for every
        observed plane (matched or new). AssociationError for pairs naming
        unknown indices / ids or pairing one plane twice.
        """
        T = _pose(T_world_cam)
        R, t = T[:3, :3], T[:3, 3]
        obs_planes = observation.segmentation.planes
        structure = observation.structure
        pairs = self._check_pairs(plane_pairs, len(obs_planes), self._planes, "plane")
        cpairs = self._check_pairs(corner_pairs, len(structure.corners), self._corners, "corner")
        from_plane = not str(structure.gravity_source).startswith("camera")
        if len(structure.gravity_up_cam) == 3 and (
            self._up is None or (from_plane and self.gravity_source.endswith("(fallback)"))
        ):
            # The first frame whose up came from a plane (or the config) defines it; a
            # frame that only fell back to the camera's -y axis is used until then.
            self._up = unit(R @ np.asarray(structure.gravity_up_cam, dtype=np.float64))
            self.gravity_source = f"frame {observation.timestamp}" + (
                "" if from_plane else " (fallback)"
            )

        cos_gate = math.cos(math.radians(self.config.merge_max_angle_deg))
        to_map: dict[int, int] = {}
        for k, p in enumerate(obs_planes):
            n_w, d_w = transform_plane(T, np.asarray(p.normal, dtype=np.float64), float(p.d))
            c_w = R @ p.centroid + t
            S_w = R @ p.scatter @ R.T
            outline_w = p.outline @ R.T + t
            target = pairs.get(k)
            if target is not None and float(self._planes[target].normal @ n_w) < cos_gate:
                logger.warning(
                    "plane pair (%d, %d): normals %.1f deg apart, above merge_max_angle_deg; "
                    "added as a new plane",
                    k,
                    target,
                    math.degrees(
                        math.acos(float(np.clip(self._planes[target].normal @ n_w, -1, 1)))
                    ),
                )
                target = None
            if target is None:
                pid = self._next_plane
                self._next_plane += 1
                self._planes[pid] = MapPlane(
                    id=pid,
                    normal=n_w,
                    d=d_w,
                    centroid=c_w,
                    scatter=S_w,
                    num_points=int(p.num_points),
                    area_m2=float(p.area_m2),
                    outline=outline_w,
                    observations=1,
                )
            else:
                pid = target
                self._planes[pid] = self._merged_plane(
                    self._planes[pid], int(p.num_points), c_w, S_w, outline_w
                )
            to_map[k] = pid

        id_to_index = {int(p.id): k for k, p in enumerate(obs_planes)}
        touched: set[int] = {to_map[k] for k in pairs if k in to_map}
        for e in structure.edges:
            a, b = (to_map[id_to_index[i]] for i in e.planes)
            if a == b:
                continue
            key = (min(a, b), max(a, b))
            seg_w = np.asarray(e.segment, dtype=np.float64) @ R.T + t
            old = self._edges.get(key)
            if old is None:
                self._edges[key] = MapEdge(
                    planes=key,
                    segment=seg_w,
                    length_m=float(e.length_m),
                    angle_rad=float(e.angle_rad),
                    convex=bool(e.convex),
                    observations=1,
                )
            else:
                longer = float(e.length_m) > old.length_m
                self._edges[key] = MapEdge(
                    planes=key,
                    segment=seg_w if longer else old.segment,
                    length_m=float(e.length_m) if longer else old.length_m,
                    angle_rad=(old.angle_rad * old.observations + float(e.angle_rad))
                    / (old.observations + 1),
                    convex=bool(e.convex) if longer else old.convex,
                    observations=old.observations + 1,
                )
            touched.update(key)
        self._reseat_edges(touched)

        by_triple = {c.planes: c.id for c in self._corners.values()}
        for k, c in enumerate(structure.corners):
            x_w = R @ np.asarray(c.point, dtype=np.float64) + t
            triple = tuple(sorted(to_map[id_to_index[i]] for i in c.planes))
            cid = cpairs.get(k)
            if cid is None:
                if len(set(triple)) != 3:
                    continue
                cid = by_triple.get(triple)  # type: ignore[arg-type]
            if cid is None:
                cid = self._next_corner
                self._next_corner += 1
                self._corners[cid] = MapCorner(
                    id=cid,
                    planes=triple,  # type: ignore[arg-type]
                    point=x_w,
                    convex_edges=int(c.convex_edges),
                    observations=1,
                )
                by_triple[self._corners[cid].planes] = cid
            else:
                old_c = self._corners[cid]
                w = old_c.observations
                self._corners[cid] = replace(
                    old_c, point=(old_c.point * w + x_w) / (w + 1), observations=w + 1
                )
        self.frames_merged += 1
        if reaggregate:
            self.reaggregate()
        logger.debug(
            "merged frame %s: %d planes (%d matched), map has %d planes, %d edges, %d corners",
            observation.timestamp,
            len(obs_planes),
            len(pairs),
            len(self._planes),
            len(self._edges),
            len(self._corners),
        )
        return to_map

    @staticmethod
    def _check_pairs(
        pairs: Sequence[tuple[int, int]], num_obs: int, targets: Mapping[int, Any], what: str
    ) -> dict[int, int]:
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

    @staticmethod
    def _merged_plane(
        old: MapPlane,
        count: int,
        centroid_w: np.ndarray,
        scatter_w: np.ndarray,
        outline_w: np.ndarray,
    ) -> MapPlane:
        """Exact moment merge, refit, orient like the map normal, hull of both outlines."""
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
        )

    def _reseat_edges(self, plane_ids: set[int], update_angles: bool = False) -> None:
        """Put the segments of edges touching `plane_ids` on the current intersection lines
        (lengths kept); optionally recompute their dihedral angles from the normals."""
        keys = [k for k in self._edges if k[0] in plane_ids or k[1] in plane_ids]
        if not keys:
            return
        edges = [self._edges[k] for k in keys]
        a = [self._planes[k[0]] for k in keys]
        b = [self._planes[k[1]] for k in keys]
        n1, n2 = np.stack([p.normal for p in a]), np.stack([p.normal for p in b])
        segs = seat_segments(
            np.stack([e.segment for e in edges]),
            np.array([e.length_m for e in edges]),
            n1,
            np.array([p.d for p in a]),
            n2,
            np.array([p.d for p in b]),
        )
        angles = np.arctan2(
            np.linalg.norm(np.cross(n1, n2), axis=1), -np.einsum("ei,ei->e", n1, n2)
        )
        for k, key in enumerate(keys):
            e = edges[k]
            angle = float(angles[k]) if update_angles else e.angle_rad
            self._edges[key] = replace(e, segment=segs[k], angle_rad=angle)

    # ------------------------------------------------------------------ objects

    def graph(self) -> nx.Graph:
        """Plane graph of the map (world frame) used by re-aggregation: planes and edges
        seen at least `min_observations` times, with the attributes of
        `planeslam.frontend.plane_graph.build_plane_graph` (orientation w.r.t. the world up;
        'slanted' for every plane while up is unknown)."""
        min_obs = self.config.min_observations
        tol = self.object_config.orientation_tol_deg
        g = nx.Graph()
        for p in self._planes.values():
            if p.observations < min_obs:
                continue
            if self._up is None:
                orientation, facing = "slanted", ""
            else:
                orientation, facing = plane_orientation(p.normal, self._up, tol)
            g.add_node(
                p.id,
                normal=p.normal,
                d=p.d,
                area_m2=p.area_m2,
                orientation=orientation,
                facing=facing,
            )
        for (i, j), e in self._edges.items():
            if e.observations >= min_obs and i in g and j in g:
                g.add_edge(
                    i,
                    j,
                    length_m=e.length_m,
                    segment=e.segment,
                    angle_rad=e.angle_rad,
                    convex=e.convex,
                    observations=e.observations,
                )
        return g

    def reaggregate(self) -> list[MapObject]:
        """Recompute the objects (paper 4.2-4.3 on the merged map): corners sharing an edge
        form an object, classified by the pattern table and sized from the edges."""
        ocfg = self.object_config
        self._refine_gravity()
        graph = self.graph()
        if self.config.derive_corners:
            known = {c.planes for c in self._corners.values()}
            for c in find_corners(graph, ocfg.corner_min_det, ocfg.corner_tol_m):
                if c.planes not in known:
                    cid = self._next_corner
                    self._next_corner += 1
                    self._corners[cid] = MapCorner(
                        id=cid,
                        planes=c.planes,
                        point=c.point,
                        convex_edges=c.convex_edges,
                        observations=0,
                    )
                    logger.debug("corner %s derived from the merged map graph", c.planes)
        live = [
            c
            for c in self._corners.values()
            if all(p in graph for p in c.planes)
            and graph.has_edge(c.planes[0], c.planes[1])
            and graph.has_edge(c.planes[0], c.planes[2])
            and graph.has_edge(c.planes[1], c.planes[2])
        ]
        up = self._up if self._up is not None else np.array([0.0, 0.0, 1.0])
        objects: list[MapObject] = []
        for group in aggregate_corners([c.planes for c in live]):
            object_planes = {p for k in group for p in live[k].planes}
            sub = graph.subgraph(object_planes).copy()
            cls, pattern, mapping = classify_object(sub, self.patterns)
            size_from = pattern.size_from if pattern is not None else "extent"
            if size_from == "extent":
                size = measure_extent(graph, object_planes, up)
            else:
                measured, within = object_planes, object_planes
                if size_from == "convex_edges" and mapping is not None:
                    # Unlike the per-frame sizing, only edges among the convex part count:
                    # the concave contact edges with the support (box on floor) come out
                    # longer than the object, and the longest-edge rule keeps the worst.
                    measured = convex_part(graph, list(mapping), object_planes)
                    within = measured
                size = measure_size(
                    graph,
                    measured,
                    within,
                    ocfg.axis_tol_deg,
                    up,
                    pattern is not None and pattern.height_needs_bound,
                )
            objects.append(
                MapObject(
                    id=len(objects),
                    cls=cls,
                    planes=tuple(sorted(object_planes)),
                    corners=tuple(sorted(live[k].id for k in group)),
                    size_m=tuple(sorted((float(s) for s in size), reverse=True)),
                )
            )
        self._objects = objects
        return list(objects)

    def _refine_gravity(self) -> None:
        """An estimated up follows the merged map: the normal (signed to point up) of the
        largest plane within `orientation_tol_deg` of horizontal. A set up is kept."""
        if self._up is None or not self.gravity_source.startswith("frame"):
            return
        cos_tol = math.cos(math.radians(self.object_config.orientation_tol_deg))
        best: MapPlane | None = None
        for p in self._planes.values():
            if abs(float(p.normal @ self._up)) >= cos_tol and (
                best is None or p.area_m2 > best.area_m2
            ):
                best = p
        if best is not None:
            self._up = best.normal * np.sign(float(best.normal @ self._up))

    # ------------------------------------------------------------------ backend

    def update_geometry(
        self,
        planes: Mapping[int, tuple[np.ndarray, float]],
        corners: Mapping[int, np.ndarray],
        reaggregate: bool = True,
    ) -> None:
        """Replace planes' (n (3,), d [m]) and corners' points (3,), world frame (e.g.
        optimised landmarks), then re-aggregate (unless `reaggregate` is False).

        Each updated plane's centroid and outline are projected onto the new plane, its
        scatter rotated by the smallest rotation from the old to the new normal (so a
        later merge refits consistently); a normal given opposite to the map's is
        flipped with its d. Edges touching updated planes are re-seated on the new
        intersection lines with their lengths kept, and their dihedral angles recomputed.
        Corners of updated planes not in `corners` are re-intersected from their three
        planes (kept when ill-conditioned). MapError for unknown ids or bad values.
        """
        new_planes: dict[int, MapPlane] = {}
        for pid, (n_in, d_in) in planes.items():
            old = self._plane(pid)
            n = np.asarray(n_in, dtype=np.float64).reshape(-1)
            norm = float(np.linalg.norm(n)) if n.shape == (3,) else 0.0
            if not (norm > 1e-9 and np.all(np.isfinite(n)) and np.isfinite(float(d_in))):
                raise MapError(f"plane {pid}: expected a finite non-zero (3,) normal and d")
            n, d = n / norm, float(d_in) / norm
            if float(n @ old.normal) < 0:
                n, d = -n, -d
            R = rotation_between(old.normal, n)
            new_planes[int(pid)] = replace(
                old,
                normal=n,
                d=d,
                centroid=project_to_plane(old.centroid[None], n, d)[0],
                scatter=R @ old.scatter @ R.T,
                outline=project_to_plane(old.outline, n, d),
            )
        new_points: dict[int, np.ndarray] = {}
        for cid, x in corners.items():
            if int(cid) not in self._corners:
                raise MapError(f"no map corner with id {cid}")
            x = np.asarray(x, dtype=np.float64).reshape(-1)
            if x.shape != (3,) or not np.all(np.isfinite(x)):
                raise MapError(f"corner {cid}: expected a finite (3,) point, got {x!r}")
            new_points[int(cid)] = x
        self._planes.update(new_planes)
        changed = set(new_planes)
        self._reseat_edges(changed, update_angles=True)
        for cid, c in self._corners.items():
            if cid in new_points:
                self._corners[cid] = replace(c, point=new_points[cid])
            elif changed.intersection(c.planes):
                ps = [self._planes[p] for p in c.planes]
                try:
                    x = intersect_three_planes(
                        np.stack([p.normal for p in ps]),
                        np.array([p.d for p in ps]),
                        min_sin=self.object_config.corner_min_det,
                    )
                except GeometryError:
                    logger.debug("corner %d: planes ill-conditioned, point kept", cid)
                    continue
                self._corners[cid] = replace(c, point=x)
        if reaggregate:
            self.reaggregate()

    # ------------------------------------------------------------------ sparse cloud

    def add_sparse_points(self, points_world: np.ndarray, colors: np.ndarray | None = None) -> None:
        """Add (N, 3) world points [m] (and (N, 3) uint8 colours) to the voxelised sparse cloud.

        One running-mean point and colour per voxel of `voxel_m`; non-finite rows are
        dropped. Beyond `sparse_max_points` voxels the least-supported ones go (ties:
        the later voxel in key order).
        """
        pts = np.asarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"points_world has shape {pts.shape}, expected (N, 3)")
        if colors is None:
            cols = np.broadcast_to(_GREY, pts.shape)
        else:
            cols = np.asarray(colors)
            if cols.shape != pts.shape:
                raise MapError(f"colors has shape {cols.shape}, expected {pts.shape} uint8")
        finite = np.all(np.isfinite(pts), axis=1)
        pts, cols = pts[finite], cols[finite].astype(np.float64)
        if len(pts) == 0:
            return
        keys = np.floor(pts / self.config.voxel_m).astype(np.int64)
        if np.abs(keys).max() >= _KEY_OFFSET:
            raise MapError(
                f"points beyond +-{_KEY_OFFSET * self.config.voxel_m:.0f} m cannot be voxelised"
            )
        n_old = len(self._vox_keys)
        all_keys = np.concatenate([self._vox_keys, keys])
        packed = self._pack(all_keys)
        uniq, first, inv = np.unique(packed, return_index=True, return_inverse=True)
        w = np.concatenate([self._vox_counts.astype(np.float64), np.ones(len(pts))])
        sums = np.concatenate([self._vox_points * w[:n_old, None], pts])
        csums = np.concatenate([self._vox_colors.astype(np.float64) * w[:n_old, None], cols])
        counts = np.bincount(inv, weights=w, minlength=len(uniq))
        mean = (
            np.stack(
                [np.bincount(inv, weights=sums[:, i], minlength=len(uniq)) for i in range(3)],
                axis=1,
            )
            / counts[:, None]
        )
        cmean = (
            np.stack(
                [np.bincount(inv, weights=csums[:, i], minlength=len(uniq)) for i in range(3)],
                axis=1,
            )
            / counts[:, None]
        )
        keep = np.arange(len(uniq))
        cap = self.config.sparse_max_points
        if len(uniq) > cap:
            order = np.argsort(-counts, kind="stable")
            keep = np.sort(order[:cap])
            logger.debug("sparse cloud capped: %d of %d voxels kept", cap, len(uniq))
        self._vox_keys = all_keys[first[keep]]
        self._vox_points = mean[keep]
        self._vox_counts = np.rint(counts[keep]).astype(np.int64)
        self._vox_colors = np.clip(np.rint(cmean[keep]), 0, 255).astype(np.uint8)

    @staticmethod
    def _pack(keys: np.ndarray) -> np.ndarray:
        k = keys + _KEY_OFFSET
        return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]

    # ------------------------------------------------------------------ persistence

    def to_dict(self) -> dict[str, Any]:
        """The shared map schema ('planeslam.map/1'), world frame, plain JSON types, with the
        statistics and state needed to continue merging after `from_dict`."""
        return {
            "schema": MAP_SCHEMA,
            "frame": "world",
            "gravity_up": None if self._up is None else _floats(self._up),
            "gravity_source": self.gravity_source,
            "frames_merged": self.frames_merged,
            "next_plane_id": self._next_plane,
            "next_corner_id": self._next_corner,
            "config": {"map": asdict(self.config), "objects": asdict(self.object_config)},
            "planes": [
                {
                    "id": p.id,
                    "normal": _floats(p.normal),
                    "d": float(p.d),
                    "area_m2": float(p.area_m2),
                    "outline": _floats(p.outline),
                    "centroid": _floats(p.centroid),
                    "scatter": _floats(p.scatter),
                    "num_points": int(p.num_points),
                    "observations": int(p.observations),
                }
                for p in self._planes.values()
            ],
            "edges": [
                {
                    "planes": [int(e.planes[0]), int(e.planes[1])],
                    "length_m": float(e.length_m),
                    "segment": _floats(e.segment),
                    "convex": bool(e.convex),
                    "angle_rad": float(e.angle_rad),
                    "observations": int(e.observations),
                }
                for e in self._edges.values()
            ],
            "corners": [
                {
                    "id": c.id,
                    "planes": [int(k) for k in c.planes],
                    "point": _floats(c.point),
                    "convex_edges": int(c.convex_edges),
                    "observations": int(c.observations),
                }
                for c in self._corners.values()
            ],
            "objects": [
                {
                    "id": o.id,
                    "class": o.cls,
                    "planes": list(o.planes),
                    "corners": list(o.corners),
                    "size_m": list(o.size_m),
                }
                for o in self._objects
            ],
            "sparse_cloud": {
                "voxel_m": float(self.config.voxel_m),
                "keys": self._vox_keys.tolist(),
                "points": _floats(self._vox_points),
                "counts": self._vox_counts.tolist(),
                "colors": self._vox_colors.tolist(),
            },
        }

    @classmethod
    def from_dict(
        cls,
        data: Mapping[str, Any],
        source: str = "<dict>",
        patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    ) -> Map:
        """Rebuild a map written by `to_dict` (exactly). MapError naming `source` for a
        missing or unknown schema or malformed content."""
        schema = data.get("schema") if isinstance(data, Mapping) else None
        if schema != MAP_SCHEMA:
            raise MapError(f"{source}: map schema {schema!r}, expected {MAP_SCHEMA!r}")
        if data.get("frame") != "world":
            raise MapError(f"{source}: map frame {data.get('frame')!r}, expected 'world'")
        from planeslam.core.config import from_mapping

        try:
            cfg = data.get("config", {})
            m = cls(
                from_mapping(MapConfig, cfg.get("map", {}), source, "config.map"),
                from_mapping(ObjectConfig, cfg.get("objects", {}), source, "config.objects"),
                patterns,
            )
            up = data.get("gravity_up")
            m._up = None if up is None else np.asarray(up, dtype=np.float64)
            m.gravity_source = str(data.get("gravity_source", ""))
            m.frames_merged = int(data.get("frames_merged", 0))
            for p in data["planes"]:
                m._planes[int(p["id"])] = MapPlane(
                    id=int(p["id"]),
                    normal=np.asarray(p["normal"], dtype=np.float64),
                    d=float(p["d"]),
                    centroid=np.asarray(p["centroid"], dtype=np.float64),
                    scatter=np.asarray(p["scatter"], dtype=np.float64).reshape(3, 3),
                    num_points=int(p["num_points"]),
                    area_m2=float(p["area_m2"]),
                    outline=np.asarray(p["outline"], dtype=np.float64).reshape(-1, 3),
                    observations=int(p["observations"]),
                )
            for e in data["edges"]:
                key = (int(e["planes"][0]), int(e["planes"][1]))
                m._edges[key] = MapEdge(
                    planes=key,
                    segment=np.asarray(e["segment"], dtype=np.float64).reshape(2, 3),
                    length_m=float(e["length_m"]),
                    angle_rad=float(e["angle_rad"]),
                    convex=bool(e["convex"]),
                    observations=int(e["observations"]),
                )
            for c in data["corners"]:
                m._corners[int(c["id"])] = MapCorner(
                    id=int(c["id"]),
                    planes=tuple(int(k) for k in c["planes"]),  # type: ignore[arg-type]
                    point=np.asarray(c["point"], dtype=np.float64),
                    convex_edges=int(c["convex_edges"]),
                    observations=int(c["observations"]),
                )
            m._objects = [
                MapObject(
                    id=int(o["id"]),
                    cls=str(o["class"]),
                    planes=tuple(int(k) for k in o["planes"]),
                    corners=tuple(int(k) for k in o.get("corners", ())),
                    size_m=tuple(float(s) for s in o["size_m"]),
                )
                for o in data["objects"]
            ]
            cloud = data.get("sparse_cloud") or {}
            m._vox_keys = np.asarray(cloud.get("keys", []), dtype=np.int64).reshape(-1, 3)
            m._vox_points = np.asarray(cloud.get("points", []), dtype=np.float64).reshape(-1, 3)
            m._vox_counts = np.asarray(cloud.get("counts", []), dtype=np.int64).reshape(-1)
            m._vox_colors = np.asarray(cloud.get("colors", []), dtype=np.uint8).reshape(-1, 3)
            m._next_plane = int(data.get("next_plane_id", max(m._planes, default=-1) + 1))
            m._next_corner = int(data.get("next_corner_id", max(m._corners, default=-1) + 1))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise MapError(
                f"{source}: malformed map content ({type(exc).__name__}: {exc})"
            ) from None
        if not len(m._vox_keys) == len(m._vox_points) == len(m._vox_counts) == len(m._vox_colors):
            raise MapError(f"{source}: sparse_cloud arrays differ in length")
        return m

    def save(self, path: str | Path) -> Path:
        """Write the map as JSON (atomically: temp file then os.replace); returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                json.dump(self.to_dict(), fh, separators=(",", ":"))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path, patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS) -> Map:
        """Read a map written by `save`. MapError for a missing / unreadable file or a
        missing or unknown schema version."""
        path = Path(path)
        try:
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
        except FileNotFoundError:
            raise MapError(f"{path}: map file not found") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MapError(f"{path}: not a readable JSON map ({exc})") from None
        if not isinstance(data, dict):
            raise MapError(f"{path}: map schema None, expected {MAP_SCHEMA!r}")
        return cls.from_dict(data, source=str(path), patterns=patterns)

    # ------------------------------------------------------------------ export and size

    def plane_colors(self) -> dict[int, np.ndarray]:
        """{plane id: (3,) uint8 colour}: one colour per object; a plane in several objects
        (a floor under a box) takes the colour of the object with the most plane area;
        grey for planes in no object."""
        area = {o.id: sum(self._planes[p].area_m2 for p in o.planes) for o in self._objects}
        colors = {pid: _GREY for pid in self._planes}
        owner: dict[int, int] = {}
        for o in self._objects:
            for p in o.planes:
                if p not in owner or area[o.id] > area[owner[p]]:
                    owner[p] = o.id
        for p, oid in owner.items():
            colors[p] = _palette(oid)
        return colors

    def write_ply(self, path: str | Path) -> Path:
        """One binary little-endian PLY: each plane's outline as a triangle fan about its
        mean vertex, coloured by object (`plane_colors`), followed by the sparse cloud as
        unreferenced vertices with their colours. Open3D reads it as a TriangleMesh
        (read_triangle_mesh) or as a point cloud of all vertices (read_point_cloud)."""
        colors = self.plane_colors()
        verts, vcols, faces = [], [], []
        base = 0
        for p in self._planes.values():
            ring = p.outline
            if len(ring) < 3:
                continue
            m = len(ring)
            verts.append(np.concatenate([ring, ring.mean(axis=0)[None]]))
            vcols.append(np.broadcast_to(colors[p.id], (m + 1, 3)))
            k = np.arange(m)
            faces.append(base + np.stack([np.full(m, m), k, (k + 1) % m], axis=1))
            base += m + 1
        verts.append(self._vox_points)
        vcols.append(self._vox_colors)
        v = np.concatenate(verts) if verts else np.zeros((0, 3))
        c = np.concatenate(vcols).astype(np.uint8)
        f = np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64)
        vtype = np.dtype(
            [
                ("x", "<f4"),
                ("y", "<f4"),
                ("z", "<f4"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
            ]
        )
        vrec = np.empty(len(v), dtype=vtype)
        for name, col in zip(("x", "y", "z"), v.T, strict=True):
            vrec[name] = col
        for name, col in zip(("red", "green", "blue"), c.T, strict=True):
            vrec[name] = col
        frec = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
        frec["n"] = 3
        frec["v"] = f
        header = (
            "ply\nformat binary_little_endian 1.0\n"
            "comment planeslam map: plane polygons coloured by object, then the sparse cloud\n"
            f"element vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(vrec.tobytes())
            fh.write(frec.tobytes())
        return path

    def memory_bytes(self, encoding: Literal["arrays", "json"] = "arrays") -> dict[str, int]:
        """Bytes of the compact map per part: planes, edges, corners, objects, sparse_cloud, total.

        'arrays' (default): numpy nbytes of every stored value as held in memory
        (float64 / int64, uint8 colours, bool convexity, utf-8 class names): planes
        = id, normal, d, centroid, scatter, num_points, area, observations, outline;
        edges = ids, segment, length, angle, convex, observations; corners = id,
        ids, point, convex_edges, observations; objects = id, class, plane ids,
        corner ids, sizes; sparse_cloud = keys, points, counts, colours.
        'json': length of each part's compact JSON in `save`'s encoding.
        """
        if encoding == "json":
            d = self.to_dict()
            parts = {
                k: len(json.dumps(d[k], separators=(",", ":")).encode())
                for k in ("planes", "edges", "corners", "objects", "sparse_cloud")
            }
        elif encoding == "arrays":
            f8, i8 = 8, 8
            parts = {
                "planes": sum(
                    i8 + 3 * f8 + f8 + 3 * f8 + 9 * f8 + i8 + f8 + i8 + p.outline.size * f8
                    for p in self._planes.values()
                ),
                "edges": len(self._edges) * (2 * i8 + 6 * f8 + f8 + f8 + 1 + i8),
                "corners": len(self._corners) * (i8 + 3 * i8 + 3 * f8 + i8 + i8),
                "objects": sum(
                    i8
                    + len(o.cls.encode())
                    + i8 * (len(o.planes) + len(o.corners))
                    + f8 * len(o.size_m)
                    for o in self._objects
                ),
                "sparse_cloud": self._vox_keys.nbytes
                + self._vox_points.nbytes
                + self._vox_counts.nbytes
                + self._vox_colors.nbytes,
            }
        else:
            raise MapError(f"memory_bytes encoding {encoding!r}, expected 'arrays' or 'json'")
        parts["total"] = sum(parts.values())
        return parts
