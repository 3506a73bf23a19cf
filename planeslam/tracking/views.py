"""What tracking sees of a frame and of the map: planes, corners, edges and objects as arrays.

`FrameView` is one observation in the camera frame, `MapView` the map in the world frame
(built by the orchestrator from its map). Row indices tie them together: a corner's or an
edge's planes are rows of the same view's plane arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.geometry import transform_points
from planeslam.core.plane_fit import patch_covariance

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation


def _zeros(*shape: int, dtype: type = np.float64):
    return field(default_factory=lambda: np.zeros(shape, dtype=dtype))


@dataclass(frozen=True)
class MapView:
    """The map as tracking sees it, world frame."""

    plane_ids: np.ndarray
    """(M,) int map plane ids."""
    normals: np.ndarray
    """(M, 3) unit normals."""
    d: np.ndarray
    """(M,) offsets [m]."""
    corner_ids: np.ndarray = _zeros(0, dtype=np.int64)
    """(K,) int map corner ids."""
    corner_planes: np.ndarray = _zeros(0, 3, dtype=np.int64)
    """(K, 3) ROW indices into plane_ids / normals of each corner's three planes."""
    corner_points: np.ndarray = _zeros(0, 3)
    """(K, 3) corner points [m]."""
    corner_convex_edges: np.ndarray | None = None
    """(K,) how many of each corner's edges are convex (3 box, 0 room); None: unknown."""
    plane_weights: np.ndarray | None = None
    """(M,) plane areas [m^2]: rank planes for relocalisation and gate association."""
    edge_planes: np.ndarray = _zeros(0, 2, dtype=np.int64)
    """(E, 2) ROW indices of each real intersection's two planes."""
    edge_segments: np.ndarray = _zeros(0, 2, 3)
    """(E, 2, 3) end points of each edge [m]."""
    edge_lengths: np.ndarray = _zeros(0)
    """(E,) longest observed length [m]."""
    edge_angles: np.ndarray = _zeros(0)
    """(E,) dihedral angles [rad]."""
    edge_convex: np.ndarray = _zeros(0, dtype=bool)
    """(E,) convexity."""
    object_classes: tuple[str, ...] = ()
    """Class of each object that has corners."""
    object_sizes: tuple[tuple[float, ...], ...] = ()
    """Its sizes [m], largest first."""
    object_centres: np.ndarray = _zeros(0, 3)
    """(O, 3) mean of its corner points [m]."""
    culled_normals: np.ndarray = _zeros(0, 3)
    """(C, 3) unit normals of planes the map culled (seen once): not new when seen again."""
    culled_d: np.ndarray = _zeros(0)
    """(C,) their offsets [m]."""
    culled_areas: np.ndarray = _zeros(0)
    """(C,) their areas [m^2]."""

    @property
    def empty(self) -> bool:
        return len(self.plane_ids) == 0


@dataclass(frozen=True)
class FrameView:
    """One observation's planes, corners, edges and objects as arrays, camera frame."""

    plane_ids: np.ndarray
    """(N,) observed plane ids."""
    normals: np.ndarray
    """(N, 3) unit normals toward the camera."""
    d: np.ndarray
    """(N,) offsets [m]."""
    weights: np.ndarray
    """(N,) relative plane weights (inlier counts / their mean)."""
    corner_planes: np.ndarray
    """(K, 3) ROW indices into plane_ids of each corner's planes."""
    corner_points: np.ndarray
    """(K, 3) corner points [m]."""
    corner_convex_edges: np.ndarray | None = None
    """(K,) how many of each corner's edges are convex; None: unknown."""
    areas: np.ndarray | None = None
    """(N,) visible plane areas [m^2]; None: unknown."""
    covariances: np.ndarray | None = None
    """(N, 3, 3) fit covariances in OrientedPlane3 local coordinates; None: unknown (the
    estimator then uses its floors alone)."""
    centroids: np.ndarray | None = None
    """(N, 3) plane centroids [m]; None: unknown."""
    edge_planes: np.ndarray = _zeros(0, 2, dtype=np.int64)
    """(E, 2) ROW indices of each real intersection's two planes."""
    edge_segments: np.ndarray = _zeros(0, 2, 3)
    """(E, 2, 3) end points [m]."""
    edge_lengths: np.ndarray = _zeros(0)
    """(E,) lengths [m]."""
    edge_angles: np.ndarray = _zeros(0)
    """(E,) dihedral angles [rad]."""
    edge_convex: np.ndarray = _zeros(0, dtype=bool)
    """(E,) convexity."""
    edge_real_ends: np.ndarray = _zeros(0, 2, dtype=bool)
    """(E, 2) whether each end is a real end: it projects at least `border_px` inside the
    image (an end on the border is where the view, not the edge, stops)."""
    object_classes: tuple[str, ...] = ()
    object_sizes: tuple[tuple[float, ...], ...] = ()
    object_centres: np.ndarray = _zeros(0, 3)
    """(O, 3) mean of each object's corner points [m] (objects with corners only)."""

    def plane_covariances(self, rows: np.ndarray, sensor: DepthNoiseConfig) -> np.ndarray | None:
        """(R, 3, 3) covariance of the planes in `rows` (OrientedPlane3 local coordinates):
        the fit's plus the sensor's depth error correlated across each patch
        (`core.plane_fit.patch_covariance`: large near planes count most, small far patches
        little); None for a view built without its planes' statistics (tests)."""
        if self.covariances is None or self.centroids is None or self.areas is None:
            return None
        patches = [
            patch_covariance(sensor, self.normals[i], self.centroids[i], self.areas[i])
            for i in rows
        ]
        return self.covariances[rows] + np.array(patches).reshape(-1, 3, 3)

    @classmethod
    def of(
        cls, observation: FrameObservation, camera: CameraConfig | None = None, border_px: float = 8
    ) -> FrameView:
        """The arrays of a front-end observation; without `camera` no edge end counts as
        real."""
        planes = observation.segmentation.planes
        ids = np.array([p.id for p in planes], dtype=np.int64)
        row = {int(i): k for k, i in enumerate(ids)}
        structure = observation.structure
        corners = structure.corners
        counts = np.array([p.num_points for p in planes], dtype=np.float64)
        edges = structure.edges
        segments = np.array([e.segment for e in edges], dtype=np.float64).reshape(-1, 2, 3)
        if camera is not None and len(edges):
            z = np.maximum(segments[..., 2], 1e-6)
            u = camera.fx * segments[..., 0] / z + camera.cx
            v = camera.fy * segments[..., 1] / z + camera.cy
            real = (
                (u >= border_px)
                & (u <= camera.width - 1 - border_px)
                & (v >= border_px)
                & (v <= camera.height - 1 - border_px)
            )
        else:
            real = np.zeros((len(edges), 2), dtype=bool)
        objects = [o for o in structure.objects if o.corners]
        return cls(
            plane_ids=ids,
            normals=np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3),
            d=np.array([p.d for p in planes], dtype=np.float64),
            weights=counts / counts.mean() if len(counts) else counts,
            corner_planes=np.array(
                [[row[i] for i in c.planes] for c in corners], dtype=np.int64
            ).reshape(-1, 3),
            corner_points=np.array([c.point for c in corners], dtype=np.float64).reshape(-1, 3),
            corner_convex_edges=np.array([c.convex_edges for c in corners], dtype=np.int64),
            areas=np.array([p.area_m2 for p in planes], dtype=np.float64),
            covariances=np.array([p.covariance for p in planes], dtype=np.float64).reshape(
                -1, 3, 3
            ),
            centroids=np.array([p.centroid for p in planes], dtype=np.float64).reshape(-1, 3),
            edge_planes=np.array(
                [[row[a], row[b]] for a, b in (e.planes for e in edges)], dtype=np.int64
            ).reshape(-1, 2),
            edge_segments=segments,
            edge_lengths=np.array([e.length_m for e in edges], dtype=np.float64),
            edge_angles=np.array([e.angle_rad for e in edges], dtype=np.float64),
            edge_convex=np.array([e.convex for e in edges], dtype=bool),
            edge_real_ends=real,
            object_classes=tuple(o.cls for o in objects),
            object_sizes=tuple(tuple(o.size_m) for o in objects),
            object_centres=np.array(
                [np.mean([corners[c].point for c in o.corners], axis=0) for o in objects]
            ).reshape(-1, 3),
        )


def frame_as_map(frame: FrameView, T_world_cam: np.ndarray) -> MapView:
    """A frame's planes, corners, edges and objects moved into the world by T_world_cam
    (4, 4): the map of one keyframe."""
    normals = frame.normals @ T_world_cam[:3, :3].T
    return MapView(
        plane_ids=frame.plane_ids,
        normals=normals,
        d=frame.d - normals @ T_world_cam[:3, 3],
        corner_ids=np.arange(len(frame.corner_points), dtype=np.int64),
        corner_planes=frame.corner_planes,
        corner_points=transform_points(T_world_cam, frame.corner_points),
        corner_convex_edges=frame.corner_convex_edges,
        plane_weights=frame.areas,
        edge_planes=frame.edge_planes,
        edge_segments=transform_points(T_world_cam, frame.edge_segments),
        edge_lengths=frame.edge_lengths,
        edge_angles=frame.edge_angles,
        edge_convex=frame.edge_convex,
        object_classes=frame.object_classes,
        object_sizes=frame.object_sizes,
        object_centres=transform_points(T_world_cam, frame.object_centres),
    )
