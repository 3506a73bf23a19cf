"""Plane and corner landmarks for a caller that owns its own GTSAM graph.

`PlaneLandmarks` turns what the front end found in one frame (`FrontEnd.process(...)`, a
`FrameObservation`, or just its `measurements()`) into factors
and new landmark values, added to the caller's `NonlinearFactorGraph` and
`Values` with the caller's pose key and the symbol characters the caller chose
in `LandmarkKeys` (so our variables never collide with theirs):

    keys = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")
    landmarks = PlaneLandmarks(keys, LandmarkConfig(robust_kernel="huber"))
    observation = front_end.process(depth_m, stamp)
    plane_ids, corner_ids = landmarks.associate(observation, T_world_cam_pred, pose_cov)
    added = landmarks.add_observations(
        graph, new_values, keys.pose(i), T_world_cam_pred, observation, plane_ids, corner_ids
    )
    ...  # the caller adds its own odometry / IMU factors, optimises
    landmarks.update_estimates(result)
    landmarks.objects()  # rooms, boxes, ... with their sizes, from the optimised planes

Frames: poses are T_world_cam (a gtsam.Pose3 or a (4, 4) array wherever one is taken),
plane landmarks OrientedPlane3 in the world frame (n . x + d = 0), corner landmarks
Point3 in the world frame [m].

Association gates are the config's fixed `associate_*` ones, widened by the predicted
pose's uncertainty when its covariance is given (a (6, 6) matrix or a `gtsam.Marginals`;
`planeslam.factors.gating`). New landmark ids are reserved when `associate` hands them
out, so two calls never give the same new id. Objects: given whole `FrameObservation`s,
the table keeps the plane-object map of those frames (`planeslam.mapping.Map`, in
landmark ids) and `objects()` re-aggregates and classifies it on the current estimates.
An indeterminate update: `planeslam.factors.recovery`.

Rules kept here so the caller's system stays well posed: a landmark value is
inserted exactly once (the first time its id is seen), only together with the
observation that constrains it (a plane factor: 3 equations for 3 unknowns; a
corner factor: 3 for 3); a factor never refers to a landmark without a value;
each structural pair and each corner-plane tie is added once. The caller must
still give every pose an odometry factor or a prior: a pose seen through fewer
than three independent planes is otherwise indeterminate.

Speed: the robust plane, corner and structural factors are `CustomFactor`s, and
pybind11 hands each call a Python copy of the whole `Values` being linearised
unless a Python object for that very `Values` exists. With iSAM2, keep
`theta = isam.getLinearizationPoint()` alive beside the `ISAM2` and every call
gets it without a copy (`planeslam.backend.isam2` does; on 7-Scenes the copies had made
each update O(map size) per factor and the 5-iteration batch at the end 21 s). gtsam's
batch optimisers linearise at Values of their own: on large graphs prefer iSAM2
updates, or fewer Python factors (`robust_kernel=None` takes the built-in plane factor).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import gtsam
import numpy as np

from planeslam.core.errors import AssociationError, ConfigError, GeometryError
from planeslam.core.geometry import (
    angle_between,
    rigid_pose,
    transform_plane,
    transform_points,
)
from planeslam.core.types import (
    CornerMeasurement,
    FrameMeasurements,
    PlaneEstimate,
    PlaneMeasurement,
)
from planeslam.frontend.config import ObjectConfig
from planeslam.mapping.config import MapConfig
from planeslam.tracking.association import associate_with_corners

from .config import LandmarkConfig, LandmarkKeys
from .corner_observation import corner_factor
from .gating import pose_covariance_matrix, pose_gate_sigmas
from .plane_observation import plane_factor, robust_plane_factor
from .plane_structure import same_plane_factor, structural_factor
from .point_on_plane import point_on_plane_factor

if TYPE_CHECKING:  # imported where used: the backend's process needs none of the front end
    from planeslam.frontend.objects import ObjectPattern
    from planeslam.frontend.pipeline import FrameObservation

    from .landmark_objects import LandmarkObject, LandmarkObjectMap

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class AddedFactors:
    """What one `add_observations` call put into the caller's graph and values."""

    factors: tuple[gtsam.NonlinearFactor, ...]
    """Factors added to the graph, in the order added."""
    kinds: tuple[str, ...]
    """Per factor: 'plane', 'corner', 'point_on_plane', 'structure' or 'same_plane'."""
    new_keys: tuple[int, ...]
    """gtsam keys of the landmark values inserted into `values`."""
    new_planes: tuple[int, ...]
    """Landmark ids of the new plane landmarks."""
    new_corners: tuple[int, ...]
    """Landmark ids of the new corner landmarks."""
    values: gtsam.Values = field(default_factory=gtsam.Values)
    """The initial values of `new_keys` (also inserted into the caller's `values`)."""

    def count(self, kind: str) -> int:
        """Number of factors of one kind."""
        return sum(k == kind for k in self.kinds)


@dataclass
class _Corner:
    point_world: np.ndarray
    planes: tuple[int, int, int]  # plane landmark ids, as first observed


@dataclass
class _Additions:
    """What one `add_observations` call will add, built before anything is added."""

    factors: list[gtsam.NonlinearFactor] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    values: list[tuple[int, Any]] = field(default_factory=list)  # (gtsam key, initial value)
    planes: dict[int, PlaneEstimate] = field(default_factory=dict)  # new plane landmarks
    corners: dict[int, _Corner] = field(default_factory=dict)  # new corner landmarks
    structure_pairs: set[tuple[int, int]] = field(default_factory=set)

    def add(self, factor: gtsam.NonlinearFactor, kind: str) -> None:
        self.factors.append(factor)
        self.kinds.append(kind)


class PlaneLandmarks:
    """The landmark table of one map, and the factors tying frames to it.

    Landmark ids are the caller's (or `associate`'s) integers; their gtsam keys
    come from `keys.plane(id)` / `keys.corner(id)`.
    """

    def __init__(
        self,
        keys: LandmarkKeys,
        config: LandmarkConfig | None = None,
        map_config: MapConfig | None = None,
        object_config: ObjectConfig | None = None,
        patterns: tuple[ObjectPattern, ...] | None = None,
    ) -> None:
        """`map_config`, `object_config` and `patterns` (None: the front end's
        `DEFAULT_PATTERNS`) shape the object layer (`objects`): merging, re-aggregation,
        classes."""
        if not isinstance(keys, LandmarkKeys):
            raise ConfigError(f"keys={keys!r}: expected a planeslam.factors.LandmarkKeys")
        self.keys = keys
        self.config = config or LandmarkConfig()
        self._planes: dict[int, PlaneEstimate] = {}
        self._corners: dict[int, _Corner] = {}
        self._structure_pairs: set[tuple[int, int]] = set()
        self._joined: set[int] = set()  # landmarks joined into another one
        self._next_plane = 0
        self._next_corner = 0
        self._object_settings = (map_config, object_config, patterns)
        self._object_map: LandmarkObjectMap | None = None

    # ------------------------------------------------------------------ table

    @property
    def plane_ids(self) -> list[int]:
        """Ids of the plane landmarks that have a value, increasing."""
        return sorted(self._planes)

    @property
    def corner_ids(self) -> list[int]:
        """Ids of the corner landmarks that have a value, increasing."""
        return sorted(self._corners)

    def plane_estimates(self, ids: Iterable[int] | None = None) -> dict[int, PlaneEstimate]:
        """Landmark id -> estimate (world frame) as last known, of every landmark or of
        those `ids` that have a value."""
        ids = sorted(self._planes) if ids is None else [j for j in ids if j in self._planes]
        return {j: self._planes[j] for j in ids}

    def corner_estimates(self, ids: Iterable[int] | None = None) -> dict[int, np.ndarray]:
        """Landmark id -> p_world (3,) [m] as last known, of every landmark or of those
        `ids` that have a value."""
        ids = sorted(self._corners) if ids is None else [k for k in ids if k in self._corners]
        return {k: self._corners[k].point_world.copy() for k in ids}

    def corner_planes(self) -> dict[int, tuple[int, int, int]]:
        """Corner landmark id -> its three plane landmark ids."""
        return {k: c.planes for k, c in sorted(self._corners.items())}

    def covariances(self, marginals: Any) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """(plane landmark id -> (3, 3) covariance in OrientedPlane3 tangent coordinates: two
        normal components [rad^2], then d [m^2]; corner landmark id -> (3, 3) world frame
        [m^2]) of the landmarks `marginals` holds. marginals: a `gtsam.Marginals`, a
        `gtsam.ISAM2` or a `RecoveringISAM2` (its `isam`; tangent spaces at its
        linearisation point, which for OrientedPlane3 sets the normal's basis). Landmarks
        it does not hold (forgotten, or outside a window) are left out."""
        source = getattr(marginals, "isam", marginals)
        if not callable(getattr(source, "marginalCovariance", None)):
            raise ConfigError(
                f"marginals is a {type(marginals).__name__}, expected a gtsam.Marginals, "
                "gtsam.ISAM2 or RecoveringISAM2"
            )

        def covariance(key: int) -> np.ndarray | None:
            try:
                return np.asarray(source.marginalCovariance(key), dtype=np.float64)
            except (RuntimeError, IndexError, KeyError):  # gtsam: not a variable it holds
                return None

        planes = {j: covariance(self.keys.plane(j)) for j in self.plane_ids}
        corners = {k: covariance(self.keys.corner(k)) for k in self.corner_ids}
        return (
            {j: c for j, c in planes.items() if c is not None},
            {k: c for k, c in corners.items() if c is not None},
        )

    def update_estimates(self, values: gtsam.Values) -> None:
        """Refresh the table from optimised values (landmarks absent from `values` keep theirs)."""
        for j in self._planes:
            key = self.keys.plane(j)
            if values.exists(key):
                plane = values.atOrientedPlane3(key)
                self._planes[j] = PlaneEstimate(
                    np.asarray(plane.normal().point3()), float(plane.distance())
                )
        for k, corner in self._corners.items():
            key = self.keys.corner(k)
            if values.exists(key):
                corner.point_world = np.asarray(values.atPoint3(key), dtype=np.float64)

    def forget(self, plane_ids: tuple[int, ...] = (), corner_ids: tuple[int, ...] = ()) -> None:
        """Drop landmarks whose values never reached the caller's system (after a failed update).

        Their structural pairs are forgotten too, so they can be added again later; their
        ids stay used (never handed out again). In the object layer their planes and
        corners stay, as geometry no landmark moves.
        """
        for j in plane_ids:
            self._planes.pop(j, None)
        for k in corner_ids:
            self._corners.pop(k, None)
        gone = set(plane_ids)
        self._structure_pairs = {p for p in self._structure_pairs if not gone.intersection(p)}
        if self._object_map is not None:
            self._object_map.forget(plane_ids, corner_ids)

    def join_planes(
        self, graph: gtsam.NonlinearFactorGraph, pairs: Iterable[tuple[int, int]]
    ) -> AddedFactors:
        """Tie plane landmarks found to be one plane: per (absorbed id, surviving id) a
        `same_plane_factor` (sigmas `same_plane_sigma_*`, robust under `robust_kernel`)
        into `graph`. The absorbed landmark keeps its value and factors, and `associate`
        no longer offers it. Pairs naming a landmark without a value, or one landmark
        twice, are skipped."""
        cfg = self.config
        factors = []
        for gone, keep in pairs:
            gone, keep = int(gone), int(keep)
            if gone == keep or gone not in self._planes or keep not in self._planes:
                continue
            self._joined.add(gone)
            factor = same_plane_factor(
                self.keys.plane(keep),
                self.keys.plane(gone),
                cfg.same_plane_sigma_rad,
                cfg.same_plane_sigma_m,
                cfg.robust_kernel,
            )
            graph.add(factor)
            factors.append(factor)
        return AddedFactors(
            factors=tuple(factors),
            kinds=("same_plane",) * len(factors),
            new_keys=(),
            new_planes=(),
            new_corners=(),
        )

    # ------------------------------------------------------------------ objects

    @property
    def _objects(self) -> LandmarkObjectMap:
        """The object layer, made at first use: it imports the front end's object stages,
        which a caller that adds `FrameMeasurements` only (the backend's process) never
        needs."""
        if self._object_map is None:
            from planeslam.frontend.objects import DEFAULT_PATTERNS

            from .landmark_objects import LandmarkObjectMap

            map_config, object_config, patterns = self._object_settings
            self._object_map = LandmarkObjectMap(
                map_config, object_config, DEFAULT_PATTERNS if patterns is None else patterns
            )
        return self._object_map

    def objects(self) -> list[LandmarkObject]:
        """Plane-based objects (paper 4.2-4.3: class such as 'room' or 'box', size [m]) of
        the frames given as `FrameObservation`s, re-aggregated on the current landmark
        estimates (call `update_estimates` first); their planes and corners as landmark
        ids. MapError when no frame came as a `FrameObservation` (measurements alone carry
        no outlines or edge lengths to size objects with)."""
        return self._objects.objects(self.plane_estimates(), self.corner_estimates())

    def set_gravity_up(self, up_world: np.ndarray) -> None:
        """The world's up direction (3,) (opposite to gravity, e.g. from an IMU) for the
        objects' classes; by default it comes from the frames' floor-like planes."""
        self._objects.set_gravity_up(up_world)

    # ------------------------------------------------------------------ association

    def associate(
        self,
        measurements: FrameMeasurements | FrameObservation,
        T_world_cam_pred: np.ndarray | gtsam.Pose3,
        pose_covariance: np.ndarray | gtsam.Marginals | None = None,
        pose_key: int | None = None,
        *,
        max_angle_deg: float | None = None,
        max_offset_m: float | None = None,
        max_corner_distance_m: float | None = None,
    ) -> tuple[dict[int, int], dict[int, int]]:
        """Match a frame's planes and corners to the landmarks through a predicted pose.

        measurements: the frame's `FrameMeasurements` or `FrameObservation`;
        T_world_cam_pred: (4, 4) or gtsam.Pose3. Uses
        `planeslam.tracking.association.associate_with_corners` against the current landmark
        estimates, with gates (normal angle [deg], offset [m], corner distance [m]; None
        takes the config's `associate_*`) that `pose_covariance` widens by the prediction's
        uncertainty (`LandmarkConfig.associate_pose_sigmas`): a (6, 6) covariance of the
        predicted pose (rotation [rad] first, then translation [m], gtsam's Pose3 order),
        or a `gtsam.Marginals` with `pose_key` the key of the pose whose marginal to take.
        Returns (plane_ids, corner_ids): observed plane id -> landmark id and observed
        corner index -> landmark id. Unmatched observations get fresh landmark ids,
        reserved at once (a later `associate` never hands them out again) and created by
        `add_observations`.
        """
        cfg = self.config
        measurements, _ = _frame_measurements(measurements)
        max_angle_deg = cfg.associate_max_angle_deg if max_angle_deg is None else max_angle_deg
        max_offset_m = cfg.associate_max_offset_m if max_offset_m is None else max_offset_m
        if max_corner_distance_m is None:
            max_corner_distance_m = cfg.associate_max_corner_distance_m
        planes = list(measurements.planes)
        corners = list(measurements.corners) if cfg.use_corners else []
        T = rigid_pose(T_world_cam_pred, "T_world_cam_pred")
        map_ids = [j for j in self.plane_ids if j not in self._joined]
        row_of = {j: r for r, j in enumerate(map_ids)}
        map_corner_ids = [
            k for k in self.corner_ids if all(j in row_of for j in self._corners[k].planes)
        ]
        obs_row = {p.id: r for r, p in enumerate(planes)}
        obs_corner_index = [k for k, c in enumerate(corners) if all(i in obs_row for i in c.planes)]
        obs_corners = [corners[k] for k in obs_corner_index]
        n_map = np.array([self._planes[j].n_world for j in map_ids]).reshape(-1, 3)
        d_map = np.array([self._planes[j].d_world for j in map_ids], dtype=np.float64)
        n_obs = np.array([p.n_cam for p in planes], dtype=np.float64).reshape(-1, 3)
        d_obs = np.array([p.d_cam for p in planes], dtype=np.float64)
        p_obs = np.array([c.p_cam for c in obs_corners], dtype=np.float64).reshape(-1, 3)
        angle_gate: Any = math.radians(max_angle_deg)
        offset_gate: Any = max_offset_m
        corner_gate: Any = max_corner_distance_m
        if pose_covariance is not None:
            cov = pose_covariance_matrix(pose_covariance, pose_key)
            sigmas = pose_gate_sigmas(T, cov, n_obs, p_obs)
            k = cfg.associate_pose_sigmas
            angle_gate = np.hypot(angle_gate, k * sigmas.angle_rad)
            offset_gate = np.hypot(offset_gate, k * sigmas.offset_m)
            corner_gate = np.hypot(corner_gate, k * sigmas.corner_m)
        association = associate_with_corners(
            n_map,
            d_map,
            np.array([[row_of[j] for j in self._corners[k].planes] for k in map_corner_ids])
            .reshape(-1, 3)
            .astype(np.int64),
            np.array([self._corners[k].point_world for k in map_corner_ids]).reshape(-1, 3),
            n_obs,
            d_obs,
            np.array([[obs_row[i] for i in c.planes] for c in obs_corners])
            .reshape(-1, 3)
            .astype(np.int64),
            p_obs,
            T,
            angle_gate,
            offset_gate,
            corner_gate,
        )
        plane_ids = {planes[r].id: map_ids[m] for r, m in association.planes}
        next_plane = max(self._next_plane, max(self._planes, default=-1) + 1)
        for plane in planes:
            if plane.id not in plane_ids:
                plane_ids[plane.id] = next_plane
                next_plane += 1
        matched_corners = {obs_corner_index[r]: map_corner_ids[m] for r, m in association.corners}
        corner_ids: dict[int, int] = {}
        next_corner = max(self._next_corner, max(self._corners, default=-1) + 1)
        for index, corner in enumerate(corners):
            if index in matched_corners:
                corner_ids[index] = matched_corners[index]
            elif all(i in plane_ids for i in corner.planes):
                corner_ids[index] = next_corner
                next_corner += 1
        self._next_plane, self._next_corner = next_plane, next_corner  # reserved
        return plane_ids, corner_ids

    # ------------------------------------------------------------------ factors

    def add_observations(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        pose_key: int,
        T_world_cam: np.ndarray | gtsam.Pose3,
        measurements: FrameMeasurements | FrameObservation,
        plane_ids: Mapping[int, int],
        corner_ids: Mapping[int, int] | None = None,
    ) -> AddedFactors:
        """Add one frame's plane / corner / structural factors and new landmarks.

        graph, values: the caller's (for iSAM2, this update's new factors and new
        values; for `RecoveringISAM2`, a graph and values of their own); pose_key: the
        caller's key of this frame's Pose3 T_world_cam (the caller inserts the pose
        value). T_world_cam ((4, 4) or gtsam.Pose3): current estimate of that pose, used
        to initialise new landmarks in the world frame (and to place the frame in the
        object layer). measurements: the frame's `FrameMeasurements`, or its
        `FrameObservation`, which also goes into the object layer (`objects`).
        plane_ids: observed plane id (`Plane.id`) -> landmark id (observed planes
        missing from it are ignored); corner_ids: index in
        `measurements.corners` -> landmark id (None: no corners).
        A landmark id not yet in the table is created with its initial value (unless
        `values` already holds its key, i.e. the caller created it).

        All or nothing: every input is checked and every factor built before anything
        is added, so on an error the caller's graph, values and this table are as they
        were. T_world_cam within `planeslam.core.geometry.ROTATION_TOLERANCE` of a
        rotation is re-orthonormalised (TUM's 4-decimal quaternions); further off,
        GeometryError. AssociationError when
        two observed planes (or corners) map to one landmark, or ids name observations
        the measurements lack.
        """
        cfg = self.config
        measurements, observation = _frame_measurements(measurements)
        T = rigid_pose(T_world_cam, "T_world_cam")
        plane_ids = {int(i): int(j) for i, j in plane_ids.items()}
        corner_ids = {int(i): int(k) for i, k in (corner_ids or {}).items()}
        _check_one_to_one(plane_ids, "plane_ids")
        _check_one_to_one(corner_ids, "corner_ids")
        planes = {p.id: p for p in measurements.planes}
        unknown = sorted(set(plane_ids) - set(planes))
        if unknown:
            raise AssociationError(
                f"plane_ids names observed planes {unknown} that the measurements do not have "
                f"(its plane ids: {sorted(planes)})"
            )
        corners = list(measurements.corners)
        bad = sorted(k for k in corner_ids if not 0 <= k < len(corners))
        if bad:
            raise AssociationError(
                f"corner_ids names corners {bad}: the measurements have {len(corners)}"
            )
        if not cfg.use_corners:
            corner_ids = {}
        plan = _Additions()
        self._plan_planes(plan, T, pose_key, values, planes, plane_ids)
        self._plan_corners(plan, T, pose_key, values, corners, plane_ids, corner_ids)
        if cfg.use_structure:
            self._plan_structure(plan, measurements, planes, plane_ids)
        # The object layer's merge is atomic too: after it nothing below can fail.
        if observation is not None:
            self._objects.add(observation, T, plane_ids, corner_ids)
        for factor in plan.factors:
            graph.add(factor)
        new_values = gtsam.Values()
        for key, value in plan.values:
            values.insert(key, value)
            new_values.insert(key, value)
        for lm, estimate in plan.planes.items():
            self._planes[lm] = estimate
            self._next_plane = max(self._next_plane, lm + 1)
        for lm, corner in plan.corners.items():
            self._corners[lm] = corner
            self._next_corner = max(self._next_corner, lm + 1)
        self._structure_pairs |= plan.structure_pairs
        logger.debug(
            "pose %s: %d factors (%d planes, %d corners, %d structural), %d new landmarks",
            gtsam.DefaultKeyFormatter(pose_key),
            len(plan.factors),
            plan.kinds.count("plane"),
            plan.kinds.count("corner"),
            plan.kinds.count("structure"),
            len(plan.planes) + len(plan.corners),
        )
        return AddedFactors(
            factors=tuple(plan.factors),
            kinds=tuple(plan.kinds),
            new_keys=tuple(key for key, _ in plan.values),
            new_planes=tuple(plan.planes),
            new_corners=tuple(plan.corners),
            values=new_values,
        )

    def _plan_planes(
        self,
        plan: _Additions,
        T: np.ndarray,
        pose_key: int,
        values: gtsam.Values,
        planes: Mapping[int, PlaneMeasurement],
        plane_ids: Mapping[int, int],
    ) -> None:
        """A plane factor per associated plane; new landmarks initialised through T."""
        cfg = self.config
        for obs_id, lm in sorted(plane_ids.items()):
            plane = planes[obs_id]
            n_cam = np.asarray(plane.n_cam, dtype=np.float64)
            z_cam = np.r_[n_cam, float(plane.d_cam)]
            cov = self._plane_covariance(plane)
            key = self.keys.plane(lm)
            if lm not in self._planes:
                n_world, d_world = transform_plane(T, n_cam, float(plane.d_cam))
                if not values.exists(key):
                    plan.values.append((key, gtsam.OrientedPlane3(np.r_[n_world, d_world])))
                plan.planes[lm] = PlaneEstimate(n_world, d_world)
            if cfg.robust_kernel is None:
                plan.add(plane_factor(z_cam, cov, pose_key, key), "plane")
            else:
                plan.add(
                    robust_plane_factor(z_cam, cov, pose_key, key, cfg.robust_kernel, cfg.robust_k),
                    "plane",
                )

    def _plan_corners(
        self,
        plan: _Additions,
        T: np.ndarray,
        pose_key: int,
        values: gtsam.Values,
        corners: list[CornerMeasurement],
        plane_ids: Mapping[int, int],
        corner_ids: Mapping[int, int],
    ) -> None:
        """A corner factor per associated corner; a new corner landmark also gets a
        point-on-plane tie to each of its planes that has a landmark."""
        cfg = self.config
        corner_cov = cfg.corner_sigma_m**2 * np.eye(3)
        for index, lm in sorted(corner_ids.items()):
            corner = corners[index]
            p_cam = np.asarray(corner.p_cam, dtype=np.float64)
            key = self.keys.corner(lm)
            plan.add(corner_factor(p_cam, corner_cov, pose_key, key), "corner")
            if lm in self._corners:
                continue
            tied = tuple(plane_ids.get(i) for i in corner.planes)
            p_world = transform_points(T, p_cam[None])[0]
            if not values.exists(key):
                plan.values.append((key, p_world))
            plan.corners[lm] = _Corner(p_world, tied)  # type: ignore[arg-type]
            for plane_lm in tied:
                if plane_lm is not None:
                    plan.add(
                        point_on_plane_factor(
                            self.keys.plane(plane_lm), key, cfg.point_on_plane_sigma_m
                        ),
                        "point_on_plane",
                    )

    def _plan_structure(
        self,
        plan: _Additions,
        measurements: FrameMeasurements,
        planes: Mapping[int, PlaneMeasurement],
        plane_ids: Mapping[int, int],
    ) -> None:
        """An orthogonality / parallelism factor per observed edge between two landmarks
        not yet tied."""
        cfg = self.config
        tol = math.radians(cfg.structure_tolerance_deg)
        for edge in measurements.edges:
            a, b = edge.planes
            if a not in plane_ids or b not in plane_ids:
                continue
            pair = tuple(sorted((plane_ids[a], plane_ids[b])))
            if pair[0] == pair[1] or pair in self._structure_pairs | plan.structure_pairs:
                continue
            # The measured angle between the normals (both toward the camera, as are
            # the landmarks'), not the region's dihedral angle `edge.angle_rad`.
            angle = angle_between(planes[a].n_cam, planes[b].n_cam)
            factor = structural_factor(
                self.keys.plane(pair[0]),
                self.keys.plane(pair[1]),
                angle,
                tol,
                cfg.structure_sigma_rad,
            )
            if factor is not None:
                plan.structure_pairs.add(pair)  # type: ignore[arg-type]
                plan.add(factor, "structure")

    def _plane_covariance(self, plane: PlaneMeasurement) -> np.ndarray:
        """(3, 3) noise of a plane factor (tangent normal [rad], d [m]): the fit covariance,
        plus k^2 times the correlated depth covariance (k: `plane_correlated_depth`), plus
        the floor, symmetrised."""
        cfg = self.config
        cov = _finite_3x3(plane.covariance, f"plane {plane.id}: covariance")
        if plane.correlated_covariance is not None and cfg.plane_correlated_depth > 0:
            correlated = _finite_3x3(
                plane.correlated_covariance, f"plane {plane.id}: correlated_covariance"
            )
            cov = cov + cfg.plane_correlated_depth**2 * correlated
        floor = np.array([cfg.plane_sigma_floor_rad] * 2 + [cfg.plane_sigma_floor_m])
        return 0.5 * (cov + cov.T) + np.diag(floor**2)


def _finite_3x3(matrix: np.ndarray, name: str) -> np.ndarray:
    cov = np.asarray(matrix, dtype=np.float64)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise GeometryError(f"{name} of shape {cov.shape} is not a finite (3, 3)")
    return cov


def _check_one_to_one(ids: dict[int, int], name: str) -> None:
    seen: dict[int, int] = {}
    for obs, lm in ids.items():
        if lm < 0:
            raise AssociationError(f"{name}[{obs}] = {lm}: expected a landmark id >= 0")
        if lm in seen:
            raise AssociationError(
                f"{name}: observations {seen[lm]} and {obs} both map to landmark {lm}; "
                "expected one observation per landmark and frame"
            )
        seen[lm] = obs


def _frame_measurements(
    measurements: FrameMeasurements | FrameObservation,
) -> tuple[FrameMeasurements, FrameObservation | None]:
    """(the frame's `FrameMeasurements`, the whole `FrameObservation` or None) of what the
    caller gave; `FrameMeasurements` are recognised first, so they never import the front
    end. AssociationError for anything else."""
    if isinstance(measurements, FrameMeasurements):
        return measurements, None
    from planeslam.frontend.pipeline import FrameObservation

    if isinstance(measurements, FrameObservation):
        return measurements.measurements(), measurements
    raise AssociationError(
        f"measurements is a {type(measurements).__name__}, expected the front end's "
        "FrameObservation or its FrameMeasurements"
    )


__all__ = ["AddedFactors", "LandmarkConfig", "PlaneLandmarks"]
