"""The object layer of `PlaneLandmarks`: the plane-object map of the frames a caller's
landmarks saw, kept in landmark ids, so that an outside stack gets rooms and boxes with
their sizes (the paper's 4.2-4.3 on the merged map) from its own optimised landmarks.

It is `planeslam.mapping.Map` (the paper's merge of outlines, edges and corners; objects
re-aggregated, classified and sized by `planeslam.frontend.objects.classify_and_size`)
with a two-way table between landmark ids and the map's own plane and corner ids.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from planeslam.core.errors import MapError
from planeslam.core.types import PlaneEstimate
from planeslam.frontend.config import ObjectConfig
from planeslam.frontend.objects import DEFAULT_PATTERNS, ObjectPattern
from planeslam.frontend.pipeline import FrameObservation
from planeslam.mapping.config import MapConfig
from planeslam.mapping.world_map import Map


@dataclass(frozen=True)
class LandmarkObject:
    """A plane-based object of the landmark map, world frame."""

    id: int
    """Index in the list `PlaneLandmarks.objects` returns (renumbered at every call)."""
    cls: str
    """Class from the pattern table ('box', 'room', 'structure', ...) or 'unknown'."""
    size_m: tuple[float, ...]
    """Extents along up to three orthogonal directions, largest first [m]."""
    planes: tuple[int, ...]
    """Plane landmark ids, increasing."""
    corners: tuple[int, ...]
    """Corner landmark ids, increasing (corners the map graph implies have none)."""


class LandmarkObjectMap:
    """A `Map` fed with the frames given as `FrameObservation`s, in landmark ids."""

    def __init__(
        self,
        map_config: MapConfig | None = None,
        object_config: ObjectConfig | None = None,
        patterns: tuple[ObjectPattern, ...] = DEFAULT_PATTERNS,
    ) -> None:
        self.map = Map(map_config, object_config, patterns)
        self._map_plane: dict[int, int] = {}
        """Plane landmark id -> the map plane its last observation went to."""
        self._plane_landmark: dict[int, int] = {}
        """Map plane id -> plane landmark id."""
        self._map_corner: dict[int, int] = {}
        self._corner_landmark: dict[int, int] = {}

    def add(
        self,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        plane_ids: Mapping[int, int],
        corner_ids: Mapping[int, int],
    ) -> None:
        """Merge one frame (camera frame) under T_world_cam (4, 4); plane_ids: observed
        plane id -> landmark id, corner_ids: observed corner index -> landmark id (as
        `PlaneLandmarks.add_observations` takes them). Observed planes without a landmark
        id join the map as planes no landmark moves.

        The landmarks' association is the authority: a landmark's plane merges only into
        that landmark's map plane, and a new landmark's plane is never consolidated into a
        map plane another landmark owns, so map planes and landmarks stay one-to-one (the
        map's own consolidation had joined two landmarks of TUM fr1/desk into one map
        plane, and the next frame seeing both failed). Nothing changes when it raises."""
        planes, corners = self.map.planes, self.map.corners
        row = {int(p.id): k for k, p in enumerate(observation.segmentation.planes)}
        plane_pairs = [
            (row[i], self._map_plane[lm])
            for i, lm in plane_ids.items()
            if self._map_plane.get(lm) in planes
        ]
        corner_pairs: dict[int, int] = {}  # map corner -> observed index, first pair kept
        for k, lm in sorted(corner_ids.items()):
            if self._map_corner.get(lm) in corners:
                corner_pairs.setdefault(self._map_corner[lm], k)
        merged = self.map.merge(
            observation,
            T_world_cam,
            plane_pairs,
            [(k, m) for m, k in corner_pairs.items()],
            reaggregate=False,
            keep_apart=set(self._plane_landmark),
        )
        for i, lm in plane_ids.items():
            map_id = merged.planes[row[i]]
            self._map_plane[lm] = map_id
            self._plane_landmark[map_id] = lm
        for k, lm in corner_ids.items():
            if k in merged.corners:
                self._map_corner[lm] = merged.corners[k]
                self._corner_landmark[merged.corners[k]] = lm

    def forget(self, plane_ids: Iterable[int], corner_ids: Iterable[int]) -> None:
        """Unlink landmarks (their map planes and corners stay, moved by no landmark)."""
        gone_planes, gone_corners = set(plane_ids), set(corner_ids)
        for lm in gone_planes:
            self._map_plane.pop(lm, None)
        for lm in gone_corners:
            self._map_corner.pop(lm, None)
        self._plane_landmark = {
            m: j for m, j in self._plane_landmark.items() if j not in gone_planes
        }
        self._corner_landmark = {
            m: k for m, k in self._corner_landmark.items() if k not in gone_corners
        }

    def set_gravity_up(self, up_world: np.ndarray) -> None:
        """World up (3,) for the objects' classes (see `Map.set_gravity`)."""
        self.map.set_gravity(up_world)

    def objects(
        self, planes: Mapping[int, PlaneEstimate], corners: Mapping[int, np.ndarray]
    ) -> list[LandmarkObject]:
        """The map's planes and corners moved onto the landmark estimates (world frame),
        then its objects re-aggregated, classified and sized, in landmark ids."""
        if not self.map.frames_merged:
            raise MapError(
                "no objects: no frame came as a FrameObservation; give add_observations the "
                "front end's FrameObservation (FrontEnd.process(...)), not its measurements()"
            )
        self.map.apply_estimates(
            {m: planes[j] for m, j in self._plane_landmark.items() if j in planes},
            {m: corners[k] for m, k in self._corner_landmark.items() if k in corners},
            reaggregate=True,
        )
        return [
            LandmarkObject(
                id=obj.id,
                cls=obj.cls,
                size_m=obj.size_m,
                planes=_landmark_ids(obj.planes, self._plane_landmark),
                corners=_landmark_ids(obj.corners, self._corner_landmark),
            )
            for obj in self.map.objects
        ]


def _landmark_ids(map_ids: Iterable[int], landmark_of: Mapping[int, int]) -> tuple[int, ...]:
    """The landmark ids of those map ids that have one, increasing, each once."""
    return tuple(sorted({landmark_of[m] for m in map_ids if m in landmark_of}))
