"""What the map holds, world frame: its records, id counters, up vector and sparse cloud,
with the configs they were made under. The mutable state every map operation works on."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import DepthNoiseConfig
from planeslam.core.errors import MapError
from planeslam.frontend.config import ObjectConfig
from planeslam.mapping.config import MapConfig
from planeslam.mapping.gravity import UpSource
from planeslam.mapping.records import MapCorner, MapEdge, MapObject, MapPlane
from planeslam.mapping.sparse_cloud import SparseCloud


@dataclass(eq=False)
class MapContents:
    """The map's state. Dicts keep insertion order, which is increasing id order: ids are
    monotonic and never reused (also across a save/load)."""

    config: MapConfig
    object_config: ObjectConfig
    """Orientation tolerance, corner and size parameters of re-aggregation (its gravity
    keys are unused: the map's up is `up`)."""
    planes: dict[int, MapPlane] = field(default_factory=dict)
    edges: dict[tuple[int, int], MapEdge] = field(default_factory=dict)
    """Keyed by the two plane ids, smaller first."""
    corners: dict[int, MapCorner] = field(default_factory=dict)
    culled: dict[int, MapPlane] = field(default_factory=dict)
    """Planes culled as seen by one keyframe only (`culling`), as they were then: not in
    the map (nor saved with it), but a later frame that sees one again does not see a plane
    new to the map."""
    objects: list[MapObject] = field(default_factory=list)
    """Of the last re-aggregation; ids 0..K-1."""
    next_plane_id: int = 0
    next_corner_id: int = 0
    up: np.ndarray | None = None
    """(3,) unit world up vector, None before it is known."""
    up_source: UpSource = field(default_factory=UpSource)
    sensor: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise of the frames merged (the consolidation gate's model floor)."""
    cloud: SparseCloud = field(init=False)
    frames_merged: int = 0

    def __post_init__(self) -> None:
        self.cloud = SparseCloud(self.config.voxel_m, self.config.sparse_max_points)

    def plane(self, plane_id: int) -> MapPlane:
        """The plane with that id; MapError when there is none."""
        try:
            return self.planes[int(plane_id)]
        except KeyError:
            raise MapError(f"no map plane with id {plane_id}") from None

    def plane_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (M,) int64, normals (M, 3), d (M,) [m]), world frame, rows by increasing id."""
        planes = list(self.planes.values())
        return (
            np.fromiter(self.planes, dtype=np.int64, count=len(planes)),
            np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3),
            np.array([p.d for p in planes], dtype=np.float64),
        )

    def culled_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Of the `culled` planes: (normals (C, 3), d (C,) [m], centroids (C, 3) [m],
        areas (C,) [m^2]), world frame."""
        planes = list(self.culled.values())
        return (
            np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3),
            np.array([p.d for p in planes], dtype=np.float64),
            np.array([p.centroid for p in planes], dtype=np.float64).reshape(-1, 3),
            np.array([p.area_m2 for p in planes], dtype=np.float64),
        )

    def new_plane_id(self) -> int:
        self.next_plane_id += 1
        return self.next_plane_id - 1

    def new_corner_id(self) -> int:
        self.next_corner_id += 1
        return self.next_corner_id - 1
