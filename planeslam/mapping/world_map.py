"""`Map`: the world-frame plane-object map (paper Section 4.4, Fig. 5) with a sparse
voxel cloud, as one object: read access, and each operation handed to its module.

A `Map` holds planes, real intersections (edges), trihedral corners and plane-based
objects in the world frame (`records`), plus a voxelised sparse cloud for what is not
planar (`sparse_cloud`). `merge` adds one frame under a pose and the correspondences of
data association (`merge`: the paper's merge), then re-aggregates and re-classifies the
objects with the map's up vector (`reaggregation`, `gravity`). `update_geometry`
writes optimised landmarks from the GTSAM backend into the map (`geometry_update`).
`save` / `load` / `to_dict` / `from_dict` use the schema 'planeslam.map/1'
(`json_io`); `write_planes_ply` / `write_points_ply` export the planes as a coloured
mesh and the sparse cloud as a point cloud (`ply_export`); `memory_bytes` sizes
the map (`memory`).

Ids: plane and corner ids are monotonic and never reused (also across a save/load);
object ids are renumbered 0..K-1 at every re-aggregation.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import networkx as nx
import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import MapError
from planeslam.core.geometry import unit
from planeslam.core.types import PlaneEstimate
from planeslam.frontend.config import ObjectConfig
from planeslam.frontend.objects import DEFAULT_PATTERNS, ObjectPattern
from planeslam.mapping import json_io, memory, ply_export, reaggregation
from planeslam.mapping.config import MapConfig
from planeslam.mapping.contents import MapContents
from planeslam.mapping.culling import cull_single_view
from planeslam.mapping.geometry_update import update_geometry
from planeslam.mapping.gravity import UpOrigin, UpSource
from planeslam.mapping.merge import MergeResult, merge_frame
from planeslam.mapping.records import MapCorner, MapEdge, MapObject, MapPlane
from planeslam.mapping.segment_merge import merge_same_segments

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation


class Map:
    """The world-frame plane-object map (paper Section 4.4) with a sparse voxel cloud."""

    def __init__(
        self,
        config: MapConfig | None = None,
        object_config: ObjectConfig | None = None,
        patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    ) -> None:
        """`object_config` gives the orientation tolerance, corner and size parameters of
        re-aggregation (its gravity keys are unused: see `set_gravity`); the depth noise of
        the frames to merge is `sensor` (the default model until set)."""
        self.patterns = tuple(patterns)
        self._contents = MapContents(config or MapConfig(), object_config or ObjectConfig())
        self._revision = 0

    @property
    def revision(self) -> int:
        """Counts the changes to the map's planes, edges, corners, objects and up: views
        derived from it stay valid while it is the same."""
        return self._revision

    # ------------------------------------------------------------------ read access

    @property
    def config(self) -> MapConfig:
        return self._contents.config

    @property
    def object_config(self) -> ObjectConfig:
        return self._contents.object_config

    @property
    def planes(self) -> Mapping[int, MapPlane]:
        """Read-only {plane id: MapPlane}, ids increasing."""
        return MappingProxyType(self._contents.planes)

    @property
    def edges(self) -> Mapping[tuple[int, int], MapEdge]:
        """Read-only {(plane id, plane id) smaller first: MapEdge}."""
        return MappingProxyType(self._contents.edges)

    @property
    def corners(self) -> Mapping[int, MapCorner]:
        """Read-only {corner id: MapCorner}, ids increasing."""
        return MappingProxyType(self._contents.corners)

    @property
    def objects(self) -> list[MapObject]:
        """Objects of the last re-aggregation (a copy)."""
        return list(self._contents.objects)

    @property
    def sensor(self) -> DepthNoiseConfig:
        """Depth noise of the frames being merged (consolidation's gate). Not saved: a
        loaded map takes the one of the run that extends it."""
        return self._contents.sensor

    @sensor.setter
    def sensor(self, sensor: DepthNoiseConfig) -> None:
        self._contents.sensor = sensor

    @property
    def frames_merged(self) -> int:
        """Frames merged so far (also before a save/load)."""
        return self._contents.frames_merged

    @property
    def gravity_up(self) -> np.ndarray | None:
        """(3,) unit world up vector, or None before it is known."""
        up = self._contents.up
        return None if up is None else up.copy()

    @property
    def gravity_source(self) -> UpSource:
        """Where `gravity_up` came from (`str()` of it is what `map.json` stores)."""
        return self._contents.up_source

    def outline(self, plane_id: int) -> np.ndarray:
        """(M, 3) outline of a map plane, world frame [m]."""
        return self._contents.plane(plane_id).outline

    def plane_ids(self) -> np.ndarray:
        """(M,) int64 map plane ids, increasing (the row order of `plane_arrays`)."""
        planes = self._contents.planes
        return np.fromiter(planes, dtype=np.int64, count=len(planes))

    def plane_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (M,) int64, normals (M, 3), d (M,)), world frame, rows by increasing id."""
        return self._contents.plane_arrays()

    def culled_plane_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(normals (C, 3), d (C,) [m], areas (C,) [m^2]) of the planes culled as seen by one
        keyframe only (`MapConfig.cull_single_view_after`), world frame."""
        normals, offsets, _, areas = self._contents.culled_arrays()
        return normals, offsets, areas

    def corner_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (K,) int64, planes (K, 3) int64 ROW INDICES into `plane_arrays`, points (K, 3)
        world frame [m]), rows by increasing corner id."""
        row = {pid: k for k, pid in enumerate(self._contents.planes)}
        corners = list(self._contents.corners.values())
        ids = np.array([c.id for c in corners], dtype=np.int64)
        planes = np.array([[row[p] for p in c.planes] for c in corners], dtype=np.int64)
        points = np.array([c.point for c in corners], dtype=np.float64)
        return ids, planes.reshape(-1, 3), points.reshape(-1, 3)

    @property
    def sparse_points(self) -> np.ndarray:
        """(V, 3) sparse cloud, one mean point per voxel, world frame [m]."""
        return self._contents.cloud.points.copy()

    @property
    def sparse_colors(self) -> np.ndarray:
        """(V, 3) uint8 mean colour per voxel."""
        return self._contents.cloud.colors.copy()

    # ------------------------------------------------------------------ updates

    def set_gravity(self, up_world: np.ndarray) -> None:
        """Set the world up vector (3,) (opposite to gravity) used to classify objects."""
        up = np.asarray(up_world, dtype=np.float64).reshape(-1)
        if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.linalg.norm(up) > 1e-9:
            raise MapError(f"up_world must be a finite non-zero (3,) vector, got {up_world!r}")
        self._contents.up = unit(up)
        self._contents.up_source = UpSource(UpOrigin.SET)
        self._revision += 1

    def merge(
        self,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        plane_pairs: Sequence[tuple[int, int]] = (),
        corner_pairs: Sequence[tuple[int, int]] = (),
        reaggregate: bool = True,
        keep_apart: Collection[int] = (),
    ) -> MergeResult:
        """Merge one frame into the map (paper Fig. 5) and re-aggregate the objects.

        observation: the front end's result, camera frame; T_world_cam (4, 4);
        plane_pairs: (observed plane index, map plane id) and corner_pairs:
        (observed corner index, map corner id), one-to-one, from data
        association. `reaggregate=False` defers `reaggregate` (objects) to the
        caller, e.g. to keyframes. keep_apart: map plane ids no unpaired plane is
        consolidated into (planes another association owns). Returns where every
        observed plane and corner went (`MergeResult`, the association the backend
        uses). AssociationError for pairs naming unknown indices / ids or pairing one
        plane twice.
        """
        merged = merge_frame(
            self._contents, observation, T_world_cam, plane_pairs, corner_pairs, keep_apart
        )
        cull_single_view(self._contents, self.config.cull_single_view_after or 0)
        self._revision += 1
        if reaggregate:
            self.reaggregate()
        return merged

    def graph(self) -> nx.Graph:
        """Plane graph of the map (world frame) used by re-aggregation: planes and edges
        seen at least `min_observations` times, with the attributes of
        `planeslam.frontend.plane_graph.build_plane_graph` (orientation w.r.t. the world up;
        'slanted' for every plane while up is unknown)."""
        return reaggregation.map_graph(self._contents)

    def reaggregate(self) -> list[MapObject]:
        """Recompute the objects (paper 4.2-4.3 on the merged map): corners sharing an edge
        form an object, classified by the pattern table and sized from the edges."""
        self._revision += 1
        return reaggregation.reaggregate(self._contents, self.patterns)

    def update_geometry(
        self,
        planes: Mapping[int, tuple[np.ndarray, float]],
        corners: Mapping[int, np.ndarray],
        reaggregate: bool = True,
    ) -> None:
        """Replace planes' (n (3,), d [m]) and corners' points (3,), world frame (e.g.
        optimised landmarks), then re-aggregate (unless `reaggregate` is False).
        Outlines, statistics, edges and corners follow the new planes (see
        `geometry_update.update_geometry`). MapError for unknown ids or bad values."""
        update_geometry(self._contents, planes, corners)
        self._revision += 1
        if reaggregate:
            self.reaggregate()

    def apply_estimates(
        self,
        planes: Mapping[int, PlaneEstimate],
        corners: Mapping[int, np.ndarray],
        plane_ids: Iterable[int] | None = None,
        corner_ids: Iterable[int] | None = None,
        reaggregate: bool = True,
        min_change: float = 1e-5,
    ) -> None:
        """Move the map's planes and corners onto a backend's landmark estimates (world
        frame): those listed in `plane_ids` / `corner_ids` (all estimates when None) that
        the map has and that moved by more than `min_change` (rad for normals, m for
        offsets and points); then `update_geometry`. The map stays the one owner of plane
        state: the backend only sends it estimates."""
        moved_planes: dict[int, tuple[np.ndarray, float]] = {}
        for pid in planes if plane_ids is None else plane_ids:
            old, new = self._contents.planes.get(pid), planes.get(pid)
            if old is None or new is None:
                continue
            if (
                abs(new.d_world - old.d) > min_change
                or np.max(np.abs(new.n_world - old.normal)) > min_change
            ):
                moved_planes[pid] = (new.n_world, new.d_world)
        moved_corners: dict[int, np.ndarray] = {}
        for cid in corners if corner_ids is None else corner_ids:
            old_corner, point = self._contents.corners.get(cid), corners.get(cid)
            if old_corner is not None and point is not None:
                if np.max(np.abs(point - old_corner.point)) > min_change:
                    moved_corners[cid] = point
        self.update_geometry(moved_planes, moved_corners, reaggregate=reaggregate)

    def merge_same_segments(self, plane_ids: Iterable[int]) -> dict[int, int]:
        """Merge each plane of `plane_ids` with a map plane it came to share a segment with
        (`segment_merge`; nothing when `map.merge_segments` is off); {absorbed plane id:
        surviving plane id}. Objects follow at the next `reaggregate`."""
        if not self.config.merge_segments:
            return {}
        absorbed = merge_same_segments(self._contents, plane_ids)
        if absorbed:
            self._revision += 1
        return absorbed

    def add_sparse_points(self, points_world: np.ndarray, colors: np.ndarray | None = None) -> None:
        """Add (N, 3) world points [m] (and (N, 3) uint8 colours) to the voxelised sparse cloud.

        One running-mean point and colour per voxel of `voxel_m`; non-finite rows are
        dropped. Beyond `sparse_max_points` voxels the least-supported ones go (ties:
        the later voxel in key order).
        """
        self._contents.cloud.add(points_world, colors)

    # ------------------------------------------------------------------ files and size

    def to_dict(self) -> dict[str, Any]:
        """The shared map schema ('planeslam.map/1'), world frame, plain JSON types, with the
        statistics and state needed to continue merging after `from_dict`."""
        return json_io.contents_to_dict(self._contents)

    @classmethod
    def from_dict(
        cls,
        data: Mapping[str, Any],
        source: str = "<dict>",
        patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS,
    ) -> Map:
        """Rebuild a map written by `to_dict` (exactly). MapError naming `source` for a
        missing or unknown schema or malformed content."""
        contents = json_io.contents_from_dict(data, source)
        m = cls(contents.config, contents.object_config, patterns)
        m._contents = contents
        return m

    def save(self, path: str | Path) -> Path:
        """Write the map as JSON (atomically: temp file then os.replace); returns the path."""
        return json_io.save_json(self.to_dict(), path)

    @classmethod
    def load(cls, path: str | Path, patterns: Sequence[ObjectPattern] = DEFAULT_PATTERNS) -> Map:
        """Read a map written by `save`. MapError for a missing / unreadable file or a
        missing or unknown schema version."""
        return cls.from_dict(json_io.load_json(path), source=str(Path(path)), patterns=patterns)

    def plane_colors(self) -> dict[int, np.ndarray]:
        """{plane id: (3,) uint8 colour}: one colour per object (the one with the most
        plane area for a plane in several); grey for planes in no object."""
        return ply_export.plane_colors(self._contents)

    def plane_mesh(self) -> ply_export.PlaneMesh:
        """The plane polygons as triangle fans coloured by object, world frame (see
        `ply_export.plane_mesh`)."""
        return ply_export.plane_mesh(self._contents)

    def write_planes_ply(self, path: str | Path) -> Path:
        """The plane polygons coloured by object as a binary PLY mesh (see
        `ply_export.write_planes_ply`); returns the path."""
        return ply_export.write_planes_ply(self._contents, path)

    def write_points_ply(self, path: str | Path) -> Path:
        """The sparse cloud as a binary PLY point cloud (see `ply_export.write_points_ply`);
        returns the path."""
        return ply_export.write_points_ply(self._contents, path)

    def memory_bytes(self, encoding: Literal["arrays", "json"] = "arrays") -> dict[str, int]:
        """Bytes of the compact map per part: planes, edges, corners, objects, sparse_cloud,
        total; 'arrays' as held in memory, 'json' as saved (see `memory.memory_bytes`)."""
        return memory.memory_bytes(self._contents, encoding)
