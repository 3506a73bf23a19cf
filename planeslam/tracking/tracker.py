"""Tracking: the pose of a frame against the plane-object map (paper Section 4.4), from
planes, corners, edges and keypoints, with no motion prior required.

Per frame:

1. `planes` (the fast path of close frames): associate the frame's planes and corners
   with the map's under the predicted pose (`association.associate_with_corners`), solve
   the closed-form pose (`registration.pose_from_planes_and_points`), associate again and
   solve once more (with `refine_planes`, refine it over the same planes and corners with
   each plane weighted by its fit and patch covariance). Taken when the planes
   constrain all six degrees of freedom, every residual is within the gates, and the
   prediction vouches for it: the last tracked frame is at most `fast_max_gap_s` old and
   the pose within `fast_max_jump_*` of the prediction (30 Hz: the motion since is a few
   cm, and a pose somewhat off the prediction reflects the map's own corrections), or the
   pose is within `fast_max_correction_*` of the prediction, or keypoint matches with the
   last keyframe agree with it (with `refine_planes`, "the pose" is the refined one: the
   pose that would be taken, not a differently weighted one beside it).
2. One robust estimate over every primitive (`estimator.estimate_pose`): planes, corners
   and edge ends associated under a start pose, and keypoints with depth matched against
   the most recent keyframes, each weighted by its covariance. Start poses: the partial
   plane pose of step 1, the pose of a point RANSAC (`keypoints.ransac_pose`, no prior)
   and the prediction; each is refined, and the best-supported trusted one wins. The path
   says what fixed the pose: `planes` (planes alone fixed all six directions),
   `planes+points` (the planes fixed some, other primitives the rest) or `points`.
3. `odometry`, then `icp` (right after a tracked frame only): nothing near the
   prediction fits: RGB-D odometry, then ICP against the previous frame, from the
   prediction, each accepted by its own overlap with that frame (not mapped; a plane
   pose that fixed some directions keeps them: `planes+odometry`). Keypoints that agree
   on no pose are no evidence against them: a repetitive texture gives many such.
4. `relocalised`: nothing above gives a pose: whole-map relocalisation
   (`relocalise.relocalisation_candidates`: corner, plane-triple and edge hypotheses and
   the keyframes that share most descriptors, verified against all of the frame's
   primitives), each candidate refined as in step 2. Right after a tracked frame, a
   relocalisation beyond the fast path's jump limit of the last pose is not taken on
   this frame's evidence (a symmetric scene offers one a half-turn off): the frame is
   lost, a segment starts, and two relocalisations that agree place it
   (`planeslam.tracking.segments`).
5. `lost`: nothing worked; the pose is the prediction and the frame is left out of the
   trajectory.

Every result says which degrees of freedom the planes constrained and what filled the
rest (`TrackResult.constraints`).

Frames: map planes and corners are in the world frame, observations in the camera
frame; every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.errors import GeometryError
from planeslam.core.geometry import invert_pose, orthonormalize_pose, transform_points
from planeslam.core.types import TrackingPath
from planeslam.tracking.association import (
    Association,
    associate_with_corners,
    plane_association_cost,
)
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.estimator import (
    ConstraintThresholds,
    EstimatorSettings,
    LineTerms,
    PlaneTerms,
    PointTerms,
    PoseConstraints,
    PoseEstimate,
    Primitive,
    constraints,
    corner_terms,
    estimate_pose,
    fully_constrained,
)
from planeslam.tracking.final_poses import FrameTerms, frame_terms
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.keypoints import (
    KeypointDetector,
    KeypointMap,
    Keypoints,
    PointMatches,
    inlier_threshold,
    point_residuals,
    ransac_pose,
)
from planeslam.tracking.loops import LoopOutcome, LoopQuery, loop_query, place_loop
from planeslam.tracking.registration import (
    RegistrationResult,
    RegistrationStatus,
    pose_from_planes_and_points,
    refine_icp,
)
from planeslam.tracking.relocalise import agreeing_matches, relocalisation_candidates
from planeslam.tracking.views import FrameView, MapView, frame_as_map

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

__all__ = ["FrameView", "MapView", "PoseSolve", "TrackResult", "Tracker"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackResult:
    """Pose of one frame and how it was found."""

    T_world_cam: np.ndarray
    """(4, 4) estimated pose (the prediction when lost)."""
    path: TrackingPath
    reason: str = ""
    """Why a fallback was needed or why the frame is lost; '' on the first path."""
    plane_pairs: list[tuple[int, int]] = field(default_factory=list)
    """(observed plane id, map plane id) correspondences under the final pose."""
    corner_pairs: list[tuple[int, int]] = field(default_factory=list)
    """(observed corner index, map corner id) correspondences under the final pose."""
    new_planes: int = 0
    """Observed planes with no map plane within the association gates under the final pose
    (structure the map does not have yet; an outlier of the pose solve does not count)."""
    constraints: PoseConstraints | None = None
    """Which degrees of freedom the planes fixed and what fixed the rest; None for the
    first frame and lost frames."""
    keypoints: Keypoints | None = field(default=None, repr=False)
    """The frame's keypoints when tracking computed them (a keyframe keeps them)."""
    terms: FrameTerms | None = field(default=None, repr=False)
    """The associated planes and corners with their map ids and covariances, for the
    final re-estimate against the final map (`final_poses`); None when lost or when
    `tracking.final_poses` is off."""

    @property
    def lost(self) -> bool:
        return self.path is TrackingPath.LOST


@dataclass(frozen=True)
class PoseSolve:
    """A closed-form pose and the correspondences it was solved from."""

    registration: RegistrationResult
    association: Association

    @property
    def T(self) -> np.ndarray:
        """(4, 4) T_world_cam."""
        return self.registration.T


@dataclass(frozen=True)
class JointSolve:
    """A robust estimate over every primitive and the correspondences it used."""

    T: np.ndarray
    """(4, 4) T_world_cam, the estimate's."""
    association: Association
    """Plane and corner correspondences kept (within the gates at the solution)."""
    constraints: PoseConstraints
    """Its `terms` count the inlier planes, corners, points and lines."""

    @property
    def point_inliers(self) -> int:
        return self.constraints.terms["points"]

    @property
    def score(self) -> float:
        """Support: inlier planes (1 each), corners (2), point matches (1/10)."""
        terms = self.constraints.terms
        return terms["planes"] + 2.0 * terms["corners"] + terms["points"] / 10.0

    @property
    def path(self) -> TrackingPath:
        c = self.constraints
        if c.planes_full:
            return TrackingPath.PLANES
        if c.plane_rotation_dof == 0 and c.plane_translation_dof == 0:
            return TrackingPath.POINTS
        return TrackingPath.PLANES_POINTS


def _planes_within_gates(reg: RegistrationResult, cfg: TrackingConfig) -> np.ndarray:
    """(N,) bool: plane correspondences of `reg` within the residual gates."""
    return (reg.plane_angle_residual_rad <= np.radians(cfg.max_residual_angle_deg)) & (
        np.abs(reg.plane_offset_residual_m) <= cfg.max_residual_offset_m
    )


def _trusted(reg: RegistrationResult, cfg: TrackingConfig) -> bool:
    return bool(np.all(_planes_within_gates(reg, cfg)))


def _fill_translation(reg: RegistrationResult, T_icp: np.ndarray) -> np.ndarray:
    """The plane pose `reg.T` with its unobservable translation directions taken from the
    ICP pose T_icp (4, 4); rotation and the observed directions stay the planes'."""
    U = reg.unobservable_translation_dirs.reshape(-1, 3)
    T = reg.T.copy()
    T[:3, 3] += U.T @ (U @ (T_icp[:3, 3] - reg.T[:3, 3]))
    return T


def _plane_constraints(reg: RegistrationResult, terms: dict[str, int]) -> PoseConstraints:
    """The constraints of a closed-form plane pose (from its observability)."""
    return PoseConstraints(
        plane_rotation_dof=3 - len(reg.unobservable_rotation_axes),
        plane_translation_dof=3 - len(reg.unobservable_translation_dirs),
        terms=terms,
    )


class _LazyKeypoints:
    """A frame's keypoints, detected on first use."""

    def __init__(self, detect: Callable[[], Keypoints] | None) -> None:
        self._detect = detect
        self.value: Keypoints | None = None

    def get(self) -> Keypoints | None:
        if self.value is None and self._detect is not None:
            self.value = self._detect()
            self._detect = None
        return self.value


_NO_POINTS = _LazyKeypoints(None)


class ColourCheck(enum.Enum):
    """What the colours say of a dense pose against the previous frame."""

    CONFIRMS = "confirms"
    """A textured view whose colours land on the same colours."""
    CONTRADICTS = "contradicts"
    """The colours differ by more than texture and noise explain: the pose is wrong."""
    PLAIN = "plain"
    """Too little texture to tell, and nothing contradicts the pose."""
    UNKNOWN = "unknown"
    """No colour, or too few pixels seen by both frames."""


MAX_SPEED_M_S = 0.6
"""Fastest plausible camera motion between two frames [m/s] (a walking robot, a hand)."""
MAX_TURN_DEG_S = 60.0
"""Fastest plausible camera turn between two frames [deg/s]."""
COLOUR_BLUR_PX = 2.0
"""Gaussian sigma [px] of the blur applied before colours are compared."""
COLOUR_MATCH_SHARE = 0.5
"""A dense pose's colours match the previous frame's when their median grey difference is
within this share of the frame's texture contrast (median absolute deviation)."""
COLOUR_MIN_CONTRAST = 8.0
"""Grey levels of contrast below which colours can neither confirm nor contradict a pose
(sensor noise and shading differences stay below it)."""


class Tracker:
    """Frame-to-map tracking from planes, corners, edges and keypoints."""

    def __init__(
        self,
        config: TrackingConfig,
        odometry=None,
        camera: CameraConfig | None = None,
        sensor: DepthNoiseConfig | None = None,
        seed: int = 0,
        empty_map_starts: bool = True,
    ) -> None:
        """`odometry`: an `odometry.RgbdOdometry` for the last fallback, or None. `camera`
        and `sensor` enable keypoints (`config.points`) and real edge ends. With
        `empty_map_starts`, a frame nothing places while the map has no plane starts the
        map where predicted (path `first`); otherwise it is lost."""
        self.config = config
        self.empty_map_starts = empty_map_starts
        self.odometry = odometry
        self.camera = camera
        self.sensor = sensor or DepthNoiseConfig()
        self.rng = np.random.default_rng(seed)
        self.keypoint_map: KeypointMap | None = None
        if config.points.enabled and camera is not None:
            detector = KeypointDetector(camera, self.sensor, config.points)
            self.keypoint_map = KeypointMap(detector)
        self.settings = EstimatorSettings(
            plane_sigma_angle_rad=np.radians(config.sigma_angle_deg),
            plane_sigma_offset_m=config.sigma_offset_m,
            line_sigma_m=config.sigma_line_m,
            huber_k=config.huber_k,
        )
        self.refine_settings = replace(
            self.settings,
            plane_sigma_angle_rad=np.radians(config.refine_floor_deg),
            plane_sigma_offset_m=config.refine_floor_m,
        )
        self.thresholds = ConstraintThresholds(
            max_sigma_rad=np.radians(config.max_sigma_deg), max_sigma_m=config.max_sigma_m
        )
        self._keyframe_frames: dict[int, FrameView] = {}
        """Each keyframe's observation, camera frame (for loops: `search_loop`)."""
        self._loop_rng = np.random.default_rng([seed, 1])
        """The loop search's own draws (it may run beside tracking's)."""
        self._loop_keypoint_detector: KeypointDetector | None = None
        self._previous_cloud: np.ndarray | None = None
        """(H, W, 3) organised cloud of the last tracked frame (ICP fallback)."""
        self._previous_rgbd: tuple[np.ndarray, np.ndarray] | None = None
        self._greys: list[tuple[np.ndarray, np.ndarray]] = []
        """(rgb, its `_smooth_grey`) of the last two images compared by colour."""
        self._T_world_previous: np.ndarray | None = None
        self._previous_stamp = -np.inf
        """Timestamp of the last tracked frame [s]."""
        self.prediction_valid = True
        """Whether the previous frame was tracked, so the prediction means something (false
        after a loss, and for the first frame in a loaded map: see `expect_jump`)."""

    # -------------------------------------------------------------------------- keyframes

    def add_keyframe(
        self,
        index: int,
        T_world_cam: np.ndarray,
        rgb: np.ndarray | None,
        cloud: np.ndarray | None,
        keypoints: Keypoints | None = None,
    ) -> None:
        """Frame `index` became a keyframe at T_world_cam (4, 4): its keypoints (if tracking
        computed them) or its images join the keypoint map."""
        if self.keypoint_map is not None:
            self.keypoint_map.add(index, T_world_cam, rgb, cloud, keypoints)

    def loop_query(
        self,
        index: int,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        keypoints: Keypoints | None,
        images: tuple[np.ndarray, np.ndarray] | None,
    ) -> LoopQuery | None:
        """New keyframe `index`'s loop search (`loops.loop_query`: `observation`, tracked
        at T_world_cam (4, 4), with its keypoints or the (rgb, cloud) `images` to detect
        them in) for `search_loop`, or None (no keypoints, or loops off). The keyframe's
        observation is kept for later loops against it."""
        if self.keypoint_map is None or not self.config.loops.enabled:
            return None
        self._keyframe_frames[index] = FrameView.of(observation, self.camera)
        return loop_query(
            self.keypoint_map, index, T_world_cam, self.config.loops, keypoints, images
        )

    def search_loop(self, query: LoopQuery) -> LoopOutcome:
        """The loop constraint of `query`'s keyframe against an older keyframe it revisits
        (`loops.place_loop`). With `loops.refine_planes` the points' relative pose is
        refined by the robust estimate over both frames' planes, corners and edges and the
        point matches (`joint`, the older keyframe's observation as the map), and taken
        only when that is trusted and within `loops.refine_max_step_*` of it. Safe on
        another thread than tracking's (`loops.LoopSearch`): it uses its own detector and
        random generator and reads kept observations only."""
        cfg = self.config
        keypoints = query.keypoints
        if keypoints is None:
            assert query.images is not None  # loop_query: keypoints or images
            keypoints = self._loop_detector().detect(*query.images)
        frame = self._keyframe_frames[query.index]

        def refine(old: int, T_old_cam: np.ndarray, matches: PointMatches) -> np.ndarray | None:
            old_frame = self._keyframe_frames.get(old)
            if old_frame is None:
                return None
            solve = self.joint(
                frame, frame_as_map(old_frame, np.eye(4)), T_old_cam, keypoints, matches
            )
            if solve is None:
                return None
            meters, degrees = pose_difference(T_old_cam, solve.T)
            if meters > cfg.loops.refine_max_step_m or degrees > cfg.loops.refine_max_step_deg:
                return None
            return solve.T

        loop = place_loop(
            query,
            keypoints,
            cfg.loops,
            cfg.points,
            self.sensor,
            self._loop_rng,
            refine if cfg.loops.refine_planes else None,
        )
        return LoopOutcome(query.index, keypoints, loop)

    def take_loop_keypoints(self, outcome: LoopOutcome) -> None:
        """The keypoints a loop search detected join the keypoint map's keyframe."""
        if self.keypoint_map is not None:
            self.keypoint_map.give_keypoints(outcome.index, outcome.keypoints)

    def _loop_detector(self) -> KeypointDetector:
        """The loop search's own ORB detector (OpenCV's is not shared across threads)."""
        assert self.keypoint_map is not None and self.camera is not None
        if self._loop_keypoint_detector is None:
            self._loop_keypoint_detector = KeypointDetector(
                self.camera, self.sensor, self.config.points
            )
        return self._loop_keypoint_detector

    def move_keyframe(self, index: int, T_world_cam: np.ndarray) -> None:
        """The backend corrected keyframe `index` to T_world_cam (4, 4)."""
        if self.keypoint_map is not None:
            self.keypoint_map.move(index, T_world_cam)

    @property
    def previous_pose(self) -> np.ndarray | None:
        """(4, 4) T_world_cam of the last tracked frame, the dense fallbacks' reference."""
        return self._T_world_previous

    def correct_previous(self, correction: np.ndarray) -> None:
        """The backend moved the map by `correction` (4, 4), T_optimised @ T_online^-1: the
        last tracked frame's pose, against which the dense fallbacks register, moves too."""
        if self._T_world_previous is not None:
            self._T_world_previous = orthonormalize_pose(correction @ self._T_world_previous)

    def expect_jump(self) -> None:
        """The next frame's prediction is no evidence (a loaded map, a restart): it must be
        placed by keypoints or whole-map relocalisation, and no dense fallback runs."""
        self.prediction_valid = False

    # -------------------------------------------------------------------------- planes

    def _associate(self, frame: FrameView, view: MapView, T: np.ndarray) -> Association:
        cfg = self.config
        return associate_with_corners(
            view.normals,
            view.d,
            view.corner_planes,
            view.corner_points,
            frame.normals,
            frame.d,
            frame.corner_planes,
            frame.corner_points,
            T,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            cfg.max_corner_distance_m,
            weights=frame.weights,
            gate=self._size_gate(frame, view.plane_weights),
            weigh_unpaired=self._weighed_map_planes(view),
        )

    def _weighed_map_planes(self, view: MapView) -> bool | np.ndarray:
        """Which map planes' contests `weigh_unpaired` decides (`associate_planes`): all
        (True), or (M,) bool the structures, map planes of at least
        `weigh_unpaired_min_area_m2`; False when map areas are unknown."""
        cfg = self.config
        if cfg.weigh_unpaired:
            return True
        if cfg.weigh_unpaired_min_area_m2 is None or view.plane_weights is None:
            return False
        return np.asarray(view.plane_weights >= cfg.weigh_unpaired_min_area_m2)

    def _size_gate(self, frame: FrameView, areas: np.ndarray | None) -> np.ndarray | None:
        """(N, M) bool: an observed plane may only match a map plane (of these areas (M,)
        [m^2]) at least about its size (map outlines grow as planes merge, so a big
        observation never belongs to a small map plane: a floor is not a box top). None
        when sizes are unknown."""
        if frame.areas is None or areas is None:
            return None
        cfg = self.config
        limit = cfg.size_gate_ratio * areas + cfg.size_gate_margin_m2
        return frame.areas[:, None] <= limit[None, :]

    def _matchable(
        self,
        frame: FrameView,
        normals: np.ndarray,
        d: np.ndarray,
        areas: np.ndarray | None,
        T_world_cam: np.ndarray,
    ) -> np.ndarray:
        """(N,) bool: which observed planes have a world plane (normals (M, 3), d (M,) [m],
        areas (M,) [m^2] or None) within the association gates at T_world_cam (4, 4)."""
        cfg = self.config
        _, allowed = plane_association_cost(
            normals,
            d,
            frame.normals,
            frame.d,
            T_world_cam,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            gate=self._size_gate(frame, areas),
        )
        return np.asarray(allowed.any(axis=1), dtype=bool)

    def _solve(
        self, frame: FrameView, view: MapView, assoc: Association, T_prior: np.ndarray
    ) -> RegistrationResult:
        cfg = self.config
        obs, mp = assoc.plane_rows()
        co, cm = assoc.corner_rows()
        return pose_from_planes_and_points(
            frame.normals[obs],
            frame.d[obs],
            view.normals[mp],
            view.d[mp],
            frame.corner_points[co],
            view.corner_points[cm],
            sigma_angle_rad=np.radians(cfg.sigma_angle_deg),
            sigma_offset_m=cfg.sigma_offset_m,
            sigma_point_m=cfg.sigma_point_m,
            plane_weights=frame.weights[obs],
            T_prior=T_prior,
        )

    def register(self, frame: FrameView, view: MapView, T_pred: np.ndarray) -> PoseSolve | None:
        """Closed-form pose from the planes and corners associated under T_pred.

        Solved, re-associated under the solution and solved again; after each solve the
        correspondences whose residuals exceed the gates (wrong matches, a plane whose
        border was mis-segmented) are dropped and the pose re-solved without them, so one
        outlier does not cost the frame its plane pose. None without correspondences."""
        T = T_pred
        result: PoseSolve | None = None
        for _ in range(2):
            assoc = self._associate(frame, view, T)
            if not assoc.planes:
                return result
            reg = self._solve(frame, view, assoc, T_pred)
            for _ in range(self.config.max_outlier_rounds):
                kept = self._inliers(frame, assoc, reg)
                if kept is None:
                    break
                if not kept.planes:
                    return result
                assoc, reg = kept, self._solve(frame, view, kept, T_pred)
            result, T = PoseSolve(reg, assoc), reg.T
        return result

    def _inliers(
        self, frame: FrameView, assoc: Association, reg: RegistrationResult
    ) -> Association | None:
        """`assoc` without the correspondences beyond the residual gates, or None when all
        are within them. Corners go with any of their planes."""
        corner_ok = reg.point_residual_m <= self.config.max_corner_distance_m
        return _keep(frame, assoc, _planes_within_gates(reg, self.config), corner_ok)

    # -------------------------------------------------------------------------- joint

    def _estimate(
        self,
        frame: FrameView,
        view: MapView,
        assoc: Association,
        T: np.ndarray,
        keypoints: Keypoints | None,
        matches: PointMatches,
    ) -> PoseEstimate | None:
        """`estimate_pose` from T (4, 4) over the terms under T: associated planes and
        corners, the point matches within twice their inlier threshold, and the real ends
        of edges whose two planes are associated with the two planes of a map edge (the
        nearer map end, within `line_gate_m` along the edge); None without plane or point
        terms."""
        cfg = self.config
        obs, mp = assoc.plane_rows()
        cov = (
            frame.covariances[obs] if frame.covariances is not None else np.zeros((len(obs), 3, 3))
        )
        planes = PlaneTerms(frame.normals[obs], frame.d[obs], view.normals[mp], view.d[mp], cov)
        terms = [self._corner_terms(frame, view, assoc)]
        if keypoints is not None and len(matches):
            p_cam = keypoints.points_cam[matches.observed]
            gate = 2.0 * inlier_threshold(p_cam, cfg.points, self.sensor)
            use = point_residuals(T, p_cam, matches.points_world) < gate
            # A keyframe's pose error is common to all its points: spread its variance over
            # them, so one keyframe's points together weigh at most like its pose.
            _, group, count = np.unique(
                matches.keyframes[use], return_inverse=True, return_counts=True
            )
            shared = (count[group] * cfg.points.keyframe_sigma_m**2)[:, None, None] * np.eye(3)
            terms.append(
                PointTerms(
                    p_cam[use],
                    matches.points_world[use],
                    keypoints.covariances[matches.observed[use]],
                    matches.covariances_world[use] + shared,
                )
            )
        if not len(planes) and not sum(len(p) for p in terms):
            return None
        lines = self._line_terms(frame, view, assoc, T)
        return estimate_pose(T, planes, terms, lines, self.settings)

    def _corner_terms(self, frame: FrameView, view: MapView, assoc: Association) -> PointTerms:
        """Point terms of the associated corners (`sigma_point_m`, split between frame and
        map)."""
        co, cm = assoc.corner_rows()
        return corner_terms(
            frame.corner_points[co], view.corner_points[cm], self.config.sigma_point_m
        )

    def _refined(
        self, frame: FrameView, view: MapView, solve: PoseSolve, T_pred: np.ndarray
    ) -> np.ndarray:
        """The closed-form plane pose of `solve` refined by the robust estimate over the
        same planes (each weighted by its fit and patch covariance, `refine_planes`) and
        corners; the closed-form pose when the refinement leaves a direction free, or moves
        it beyond `refine_max_step_*` and away from the prediction T_pred (4, 4)."""
        cfg = self.config
        assoc = solve.association
        obs, mp = assoc.plane_rows()
        cov = frame.plane_covariances(obs, self.sensor)
        if cov is None:
            return solve.T  # a view built without its planes' statistics (tests)
        planes = PlaneTerms(frame.normals[obs], frame.d[obs], view.normals[mp], view.d[mp], cov)
        estimate = estimate_pose(
            solve.T,
            planes,
            [self._corner_terms(frame, view, assoc)],
            None,
            self.refine_settings,
        )
        if not fully_constrained(estimate, self.thresholds):
            return solve.T
        T = estimate.T_world_cam
        meters, degrees = pose_difference(solve.T, T)
        small = meters <= cfg.refine_max_step_m and degrees <= cfg.refine_max_step_deg
        if small or pose_difference(T_pred, T)[0] <= pose_difference(T_pred, solve.T)[0]:
            return T
        return solve.T

    def _line_terms(
        self, frame: FrameView, view: MapView, assoc: Association, T: np.ndarray
    ) -> LineTerms:
        to_map = dict(assoc.planes)
        edge_row = {
            frozenset((int(a), int(b))): k for k, (a, b) in enumerate(view.edge_planes.tolist())
        }
        p, u, e = [], [], []
        for k, (a, b) in enumerate(frame.edge_planes.tolist()):
            if a not in to_map or b not in to_map or not frame.edge_real_ends[k].any():
                continue
            j = edge_row.get(frozenset((to_map[a], to_map[b])))
            if j is None:
                continue
            seg = view.edge_segments[j]
            direction = seg[1] - seg[0]
            length = float(np.linalg.norm(direction))
            if length < 1e-6:
                continue
            direction /= length
            for end in np.flatnonzero(frame.edge_real_ends[k]):
                p_cam = frame.edge_segments[k, end]
                s = float(direction @ (T[:3, :3] @ p_cam + T[:3, 3] - seg[0]))
                target = seg[0] if abs(s) <= abs(s - length) else seg[1]
                if min(abs(s), abs(s - length)) <= self.config.line_gate_m:
                    p.append(p_cam)
                    u.append(direction)
                    e.append(target)
        return LineTerms(
            np.array(p).reshape(-1, 3), np.array(u).reshape(-1, 3), np.array(e).reshape(-1, 3)
        )

    def joint(
        self,
        frame: FrameView,
        view: MapView,
        T_start: np.ndarray,
        keypoints: Keypoints | None,
        matches: PointMatches,
    ) -> JointSolve | None:
        """Robust estimate over every primitive from T_start (4, 4): associate under the
        current pose, estimate, associate again, drop planes and corners beyond the gates
        and estimate once more. None when the result is not trusted: some direction is
        left unconstrained, or it rests on points alone with fewer than
        `points.min_inliers` of them."""
        cfg = self.config
        T = T_start
        assoc = Association([], [])
        estimate: PoseEstimate | None = None
        for _ in range(2):
            assoc = self._associate(frame, view, T) if len(view.plane_ids) else assoc
            estimate = self._estimate(frame, view, assoc, T, keypoints, matches)
            if estimate is None:
                return None
            T = estimate.T_world_cam
        assert estimate is not None
        kept = self._joint_inliers(frame, view, assoc, T)
        if kept is not None:
            assoc = kept
            estimate = self._estimate(frame, view, assoc, T, keypoints, matches)
            if estimate is None:
                return None
        if not fully_constrained(estimate, self.thresholds):
            return None
        point_inliers = (
            int(np.count_nonzero(estimate.point_inliers[1]))
            if len(estimate.point_inliers) > 1
            else 0
        )
        terms = {
            "planes": int(np.count_nonzero(estimate.plane_inliers)),
            "corners": len(assoc.corners),
            "points": point_inliers,
            "lines": int(np.count_nonzero(estimate.line_inliers)),
        }
        found = constraints(estimate, self.thresholds, terms)
        if not found.planes_full and Primitive.POINTS in found.filled_by:
            if point_inliers < cfg.points.min_inliers:
                return None
        return JointSolve(estimate.T_world_cam, assoc, found)

    def _agreeing(self, T: np.ndarray, keypoints: Keypoints | None, matches: PointMatches) -> int:
        """Point matches within their inlier threshold under T (4, 4)."""
        return int(np.count_nonzero(self._agreeing_masks(T[None], keypoints, matches)))

    def _agreeing_masks(
        self, poses: np.ndarray, keypoints: Keypoints | None, matches: PointMatches
    ) -> np.ndarray:
        """(H, M) bool: the point matches within their inlier threshold under each of the
        (H, 4, 4) poses."""
        if keypoints is None or not len(matches):
            return np.zeros((len(poses), len(matches)), dtype=bool)
        p_cam = keypoints.points_cam[matches.observed]
        threshold = inlier_threshold(p_cam, self.config.points, self.sensor)
        return agreeing_matches(poses, p_cam, matches.points_world, threshold)

    def _joint_inliers(
        self, frame: FrameView, view: MapView, assoc: Association, T: np.ndarray
    ) -> Association | None:
        """`assoc` without the planes and corners beyond the residual gates under T."""
        if not assoc.planes:
            return None
        cfg = self.config
        obs, mp = np.array(assoc.planes, dtype=np.int64).T
        n_world = frame.normals[obs] @ T[:3, :3].T
        d_world = frame.d[obs] - n_world @ T[:3, 3]
        cos = np.clip(np.sum(n_world * view.normals[mp], axis=1), -1.0, 1.0)
        ok = (np.arccos(cos) <= np.radians(cfg.max_residual_angle_deg)) & (
            np.abs(d_world - view.d[mp]) <= cfg.max_residual_offset_m
        )
        co, cm = assoc.corner_rows()
        moved = transform_points(T, frame.corner_points[co])
        corner_ok = (
            np.linalg.norm(moved - view.corner_points[cm], axis=1) <= cfg.max_corner_distance_m
        )
        return _keep(frame, assoc, ok, corner_ok)

    def _best_joint(
        self,
        frame: FrameView,
        view: MapView,
        starts: list[np.ndarray],
        keypoints: Keypoints | None,
        matches: PointMatches,
        T_pred: np.ndarray,
        T_last: np.ndarray | None = None,
        frame_gap_s: float = np.inf,
    ) -> JointSolve | None:
        """The best-supported `joint` solution over the start poses that is corroborated.
        While tracking: within the fast path's correction of the prediction, or at a pose a
        plausible motion from the last one T_last (4, 4), `frame_gap_s` seconds ago,
        reaches (`_plausible`) with at least `points.min_inliers` point matches or
        `relocalise_min_planes` inlier planes (a jump is not taken on one frame's
        evidence: aliased keypoints agree on wrong poses too). After a loss: at least
        `points.min_inliers` point matches (planes alone far from a prediction prove
        little: three of them always fit)."""
        cfg = self.config
        best: JointSolve | None = None
        solved: list[np.ndarray] = []
        for T0 in starts:
            differences = (pose_difference(T, T0) for T in solved)
            if any(meters < 0.01 and degrees < 0.5 for meters, degrees in differences):
                continue  # where an earlier start already went
            candidate = self.joint(frame, view, T0, keypoints, matches)
            if candidate is not None:
                solved.append(candidate.T)
            if candidate is None or (best is not None and candidate.score <= best.score):
                continue
            if self.prediction_valid:  # tracking: no jump on one frame's evidence
                corroborated = self._near(candidate.T, T_pred) or (
                    self._plausible(candidate.T, T_last, frame_gap_s)
                    and (
                        candidate.point_inliers >= cfg.points.min_inliers
                        or candidate.constraints.terms["planes"] >= cfg.relocalise_min_planes
                    )
                )
            else:
                corroborated = candidate.point_inliers >= cfg.points.min_inliers
            if corroborated:
                best = candidate
        return best

    # -------------------------------------------------------------------------- relocalise

    def relocalise(
        self,
        frame: FrameView,
        view: MapView,
        T_pred: np.ndarray,
        keypoints: Keypoints | None = None,
    ) -> JointSolve | None:
        """The best candidate of a whole-map search (`relocalisation_candidates`), refined
        by `joint`. Taken only with more support than a minimal set gives (at least
        `relocalise_min_planes` inlier planes that are `relocalise_min_plane_fraction` of the
        frame's, or `relocalise_min_points` inlier point matches) and without a rival
        (`is_rival`): a refined candidate elsewhere with nearly its score and other evidence
        means the map is ambiguous there (a symmetric room), and the frame stays lost. Point
        matches count when they agree with a pose within their inlier threshold."""
        cfg = self.config
        candidates = relocalisation_candidates(
            frame, view, keypoints, self.keypoint_map, cfg, self.sensor, self.rng, T_pred
        )
        solved = [
            s
            for s in (
                self.joint(frame, view, T0, keypoints, candidates.matches)
                for T0 in candidates.poses
            )
            if s is not None
        ]
        if not solved:
            return None
        agreeing = self._agreeing_masks(
            np.array([s.T for s in solved]), keypoints, candidates.matches
        )
        ranked = sorted(
            (_with_point_inliers(s, mask) for s, mask in zip(solved, agreeing, strict=True)),
            key=lambda pair: -pair[0].score,
        )
        best, best_points = ranked[0]
        planes = best.constraints.terms["planes"]
        enough = best.point_inliers >= cfg.relocalise_min_points or (
            planes >= cfg.relocalise_min_planes
            and planes >= cfg.relocalise_min_plane_fraction * len(frame.plane_ids)
        )
        if not enough:
            logger.debug(
                "relocalisation: best candidate has too little support (%s)", best.constraints.terms
            )
            return None
        for rival, rival_points in ranked[1:]:
            if is_rival(best, rival, best_points, rival_points, cfg):
                logger.debug(
                    "relocalisation ambiguous: scores %.1f and %.1f", best.score, rival.score
                )
                return None
        return best

    # -------------------------------------------------------------------------- points

    def _points(self, cloud: np.ndarray) -> np.ndarray:
        """(P, 3) float64 valid camera-frame points of an (H, W, 3) organised cloud for ICP,
        every icp_stride-th pixel in each direction."""
        s, cfg = self.config.icp_stride, self.config
        xyz = cloud[::s, ::s].reshape(-1, 3)
        keep = (xyz[:, 2] > 0) & (xyz[:, 2] < cfg.max_depth_m) & np.all(np.isfinite(xyz), axis=1)
        return np.ascontiguousarray(xyz[keep], dtype=np.float64)

    def _icp(self, cloud: np.ndarray, T_world_cam_init: np.ndarray) -> np.ndarray | None:
        """T_world_cam by ICP of this frame's (H, W, 3) organised cloud against the previous
        frame's, or None. The point sets are only built here: ICP is a rare fallback."""
        cfg = self.config
        if self._previous_cloud is None:
            return None
        source, target = self._points(cloud), self._points(self._previous_cloud)
        if len(source) < 100 or len(target) < 100:
            return None
        assert self._T_world_previous is not None, "set with the previous cloud"
        T_prev_world = invert_pose(self._T_world_previous)
        try:
            icp = refine_icp(
                source,
                target,
                T_prev_world @ T_world_cam_init,
                cfg.icp_max_distance_m,
                cfg.icp_voxel_m,
            )
        except GeometryError as exc:
            logger.debug("ICP failed: %s", exc)
            return None
        if icp.fitness < cfg.icp_min_fitness or icp.inlier_rmse > cfg.icp_max_rmse_m:
            logger.debug("ICP untrusted: fitness %.2f rmse %.4f", icp.fitness, icp.inlier_rmse)
            return None
        return self._T_world_previous @ icp.T

    def _agrees(self, cloud: np.ndarray | None, T_world_cam: np.ndarray) -> bool:
        """Whether this frame's (H, W, 3) cloud, moved by T_world_cam (4, 4) into the
        previous frame, lands on the previous frame's depth: at least `icp_min_fitness` of
        the points that project into its image within `icp_max_distance_m` of its depth
        there. True when it cannot be checked (no camera, no clouds)."""
        if cloud is None or self._previous_cloud is None or self.camera is None:
            return True
        assert self._T_world_previous is not None, "set with the previous cloud"
        cam, cfg = self.camera, self.config
        T = invert_pose(self._T_world_previous) @ T_world_cam
        p = transform_points(T, self._points(cloud))
        p = p[p[:, 2] > 0.1]
        u = np.rint(cam.fx * p[:, 0] / p[:, 2] + cam.cx).astype(np.int64)
        v = np.rint(cam.fy * p[:, 1] / p[:, 2] + cam.cy).astype(np.int64)
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        z_prev = self._previous_cloud[v[inside], u[inside], 2]
        seen = z_prev > 0
        if np.count_nonzero(seen) < 100:
            return False
        close = np.abs(z_prev[seen] - p[inside][seen, 2]) <= cfg.icp_max_distance_m
        return bool(np.mean(close) >= cfg.icp_min_fitness)

    def _colour_check(self, cloud: np.ndarray | None, rgbd, T_world_cam: np.ndarray) -> ColourCheck:
        """Whether this frame's colours, moved by T_world_cam (4, 4) into the previous frame,
        match the colours there where the depths agree (`ColourCheck`): the median grey
        difference against COLOUR_MATCH_SHARE of the frame's texture contrast (the median
        absolute deviation of its grey levels) and COLOUR_MIN_CONTRAST."""
        if cloud is None or rgbd is None or self._previous_rgbd is None or self.camera is None:
            return ColourCheck.UNKNOWN
        assert self._T_world_previous is not None, "set with the previous frame"
        cam, s = self.camera, self.config.icp_stride
        xyz = cloud[::s, ::s].reshape(-1, 3)
        grey = self._grey(rgbd[0])[::s, ::s].reshape(-1)
        keep = (xyz[:, 2] > 0) & np.all(np.isfinite(xyz), axis=1)
        p = transform_points(invert_pose(self._T_world_previous) @ T_world_cam, xyz[keep])
        grey = grey[keep]
        front = p[:, 2] > 0.1
        p, grey = p[front], grey[front]
        u = np.rint(cam.fx * p[:, 0] / p[:, 2] + cam.cx).astype(np.int64)
        v = np.rint(cam.fy * p[:, 1] / p[:, 2] + cam.cy).astype(np.int64)
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        rgb_prev, depth_prev = self._previous_rgbd
        z_prev = depth_prev[v[inside], u[inside]]
        shared = (z_prev > 0) & (np.abs(z_prev - p[inside, 2]) <= self.config.icp_max_distance_m)
        if np.count_nonzero(shared) < 100:
            return ColourCheck.UNKNOWN
        g_cur = grey[inside][shared]
        g_prev = self._grey(rgb_prev)[v[inside][shared], u[inside][shared]]
        difference = float(np.median(np.abs(g_prev - g_cur)))
        contrast = float(np.median(np.abs(g_cur - np.median(g_cur))))
        if difference > max(COLOUR_MATCH_SHARE * contrast, COLOUR_MIN_CONTRAST):
            return ColourCheck.CONTRADICTS
        if contrast < COLOUR_MIN_CONTRAST:
            return ColourCheck.PLAIN
        if difference <= COLOUR_MATCH_SHARE * contrast:
            return ColourCheck.CONFIRMS
        return ColourCheck.UNKNOWN

    def _grey(self, rgb: np.ndarray) -> np.ndarray:
        """`_smooth_grey(rgb)`, computed once per image: a frame's colours are compared for
        each fallback and relocalisation, and again as the previous frame's."""
        for image, grey in self._greys:
            if image is rgb:
                return grey
        grey = _smooth_grey(rgb)
        self._greys = [*self._greys[-1:], (rgb, grey)]
        return grey

    def _rgbd(self, rgbd, T_world_cam_init: np.ndarray) -> np.ndarray | None:
        """T_world_cam by RGB-D odometry against the previous frame, or None. `rgbd` and the
        previous frame are (rgb, depth_m) pairs, turned into Open3D images only here."""
        if self.odometry is None or rgbd is None or self._previous_rgbd is None:
            return None
        assert self._T_world_previous is not None, "set with the previous frame"
        T_prev_cur = self.odometry.motion(
            self.odometry.image(*rgbd),
            self.odometry.image(*self._previous_rgbd),
            invert_pose(self._T_world_previous) @ T_world_cam_init,
        )
        return None if T_prev_cur is None else self._T_world_previous @ T_prev_cur

    # -------------------------------------------------------------------------- main

    def track(
        self,
        observation: FrameObservation,
        view: MapView,
        T_pred: np.ndarray,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
        T_last: np.ndarray | None = None,
    ) -> TrackResult:
        """Pose of `observation` against the map `view`, starting from the prediction
        T_pred (4, 4) T_world_cam; colour enables keypoints, colour and depth the RGB-D
        odometry fallback; T_last (4, 4), the last tracked frame's pose as the prediction
        was made from it, also bounds the jump limit (`_near`)."""
        frame = FrameView.of(observation, self.camera)
        cloud, rgbd = self._dense_inputs(observation, rgb, depth_m)
        points = _NO_POINTS
        if self.keypoint_map is not None and rgb is not None and observation.cloud is not None:
            detector, image, xyz = self.keypoint_map.detector, rgb, observation.cloud
            points = _LazyKeypoints(lambda: detector.detect(image, xyz))
        gap = observation.timestamp - self._previous_stamp

        def slides() -> bool:  # asked only of a dense pose, so no frame pays for it otherwise
            return cloud is not None and parallel_share(observation) >= self.config.icp_min_fitness

        result = self._track(frame, view, T_pred, cloud, rgbd, points, gap, T_last, slides)
        self.prediction_valid = not result.lost
        if not result.lost:
            self._remember_previous(observation.timestamp, cloud, rgbd, result.T_world_cam)
        return result

    def start(
        self,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
    ) -> None:
        """A frame placed without tracking (the first of a run or of a segment) at
        T_world_cam (4, 4): the next frame's prediction and dense fallbacks (RGB-D
        odometry, ICP) start from it, as from a tracked frame."""
        cloud, rgbd = self._dense_inputs(observation, rgb, depth_m)
        self.prediction_valid = True
        self._remember_previous(observation.timestamp, cloud, rgbd, T_world_cam)

    def _dense_inputs(
        self, observation: FrameObservation, rgb: np.ndarray | None, depth_m: np.ndarray | None
    ) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
        """The frame's organised cloud when ICP may run and its (rgb, depth_m) pair when
        RGB-D odometry may (None where the config or the inputs rule them out)."""
        cfg = self.config
        cloud = observation.cloud if cfg.icp else None
        rgbd = None
        if cfg.rgbd_odometry and self.odometry is not None and rgb is not None:
            rgbd = (rgb, depth_m) if depth_m is not None else None
        return cloud, rgbd

    def _remember_previous(
        self,
        timestamp: float,
        cloud: np.ndarray | None,
        rgbd: tuple[np.ndarray, np.ndarray] | None,
        T_world_cam: np.ndarray,
    ) -> None:
        self._previous_cloud, self._previous_rgbd = cloud, rgbd
        self._T_world_previous = np.asarray(T_world_cam, dtype=np.float64)
        self._previous_stamp = timestamp

    def _track(
        self,
        frame: FrameView,
        view: MapView,
        T_pred: np.ndarray,
        cloud: np.ndarray | None,
        rgbd,
        points: _LazyKeypoints = _NO_POINTS,
        frame_gap_s: float = np.inf,
        T_last: np.ndarray | None = None,
        slides: Callable[[], bool] = lambda: False,
    ) -> TrackResult:
        """The steps of the module docstring, in order, on prepared inputs; `frame_gap_s`
        the time since the last tracked frame [s], T_last (4, 4) its pose; `slides()`: whether
        the frame's depth is mostly one family of parallel planes (`parallel_share`)."""
        cfg = self.config
        if view.empty and self.keypoint_map is None and self.empty_map_starts:
            return TrackResult(T_pred, TrackingPath.FIRST, "empty map: the frame starts it")
        reasons: list[str] = []
        solve = self.register(frame, view, T_pred) if not view.empty else None
        trusted = solve if solve is not None and _trusted(solve.registration, cfg) else None
        T_fast = None
        if (
            trusted is not None
            and trusted.registration.status is RegistrationStatus.OK
            and self.prediction_valid  # after a loss the prediction is no evidence
        ):
            T_fast = self._refined(frame, view, trusted, T_pred) if cfg.refine_planes else trusted.T
        weak = (  # a direction that only a sliver of the planes' information fixes
            trusted is not None
            and points is not _NO_POINTS
            and trusted.registration.translation_observability < cfg.weak_translation_share
        )
        if (
            T_fast is not None
            and trusted is not None
            and (
                (not weak and self._near(T_fast, T_pred, frame_gap_s <= cfg.fast_max_gap_s, T_last))
                or self._points_agree(T_fast, points)
            )
        ):
            terms = {
                "planes": len(trusted.association.planes),
                "corners": len(trusted.association.corners),
            }
            return self._result(
                frame,
                view,
                T_fast,
                trusted.association,
                TrackingPath.PLANES,
                "",
                _plane_constraints(trusted.registration, terms),
                points.value,
            )
        reasons.append(
            "no plane matched the map under the prediction"
            if solve is None
            else f"plane pose {solve.registration.status.value}"
            + ("" if trusted is not None else " with residuals beyond the gates")
            + (
                " with a weakly fixed translation the keypoints do not confirm"
                if weak and T_fast is not None
                else ""
            )
        )
        # One estimate over every primitive, from every start that needs no plane prior.
        keypoints = points.get()
        matches = PointMatches.empty()
        starts = []
        if trusted is not None:
            starts.append(trusted.T)
        if keypoints is not None and self.keypoint_map is not None and len(keypoints):
            recent = self.keypoint_map.recent(cfg.points.recent_keyframes)
            matches = self.keypoint_map.matches(keypoints, recent)
            found = self._point_pose(keypoints, matches)
            if found is not None:
                starts.append(found)
            else:
                reasons.append(f"{len(matches)} point matches agree on no pose")
        starts.append(T_pred)
        best = self._best_joint(
            frame,
            view,
            starts,
            keypoints,
            matches,
            T_pred,
            T_pred if T_last is None else T_last,
            frame_gap_s,
        )
        if best is not None:
            return self._result(
                frame,
                view,
                best.T,
                best.association,
                best.path,
                "; ".join(reasons),
                best.constraints,
                keypoints,
            )
        # A whole-map search, taken right after a tracked frame only where a plausible
        # motion since then explains it and, between close frames, the colours do not
        # contradict it (a symmetric scene offers places a half-turn off); after a loss, a
        # segment confirms it.
        if cfg.relocalise and not view.empty:
            placed = self.relocalise(frame, view, T_pred, keypoints)
            if placed is None:
                reasons.append("no corner, plane, edge or keypoint hypothesis fits the map")
            elif self.prediction_valid and not self._plausible(
                placed.T, T_pred if T_last is None else T_last, frame_gap_s
            ):
                reasons.append("a relocalisation no plausible motion explains is not taken")
            elif (
                self.prediction_valid
                and frame_gap_s <= cfg.fast_max_gap_s
                and self._colour_check(cloud, rgbd, placed.T) is ColourCheck.CONTRADICTS
            ):
                reasons.append("a relocalisation whose colours contradict the last frame")
            else:
                return self._result(
                    frame,
                    view,
                    placed.T,
                    placed.association,
                    TrackingPath.RELOCALISED,
                    "; ".join(reasons),
                    placed.constraints,
                    keypoints,
                )
        # Keypoints that agree on no pose (a repetitive texture gives many) are no evidence
        # of a jump: the dense fallbacks against the last frame still run.
        if self.prediction_valid:
            dense = self._dense(
                frame, view, T_pred, trusted, cloud, rgbd, reasons, keypoints, slides
            )
            if dense is not None:
                return dense
        reasons.append("no fallback registered the frame")
        if view.empty and self.empty_map_starts:
            return TrackResult(
                T_pred, TrackingPath.FIRST, "empty map: the frame starts it", keypoints=keypoints
            )
        return TrackResult(T_pred, TrackingPath.LOST, "; ".join(reasons), keypoints=keypoints)

    def _dense(
        self,
        frame: FrameView,
        view: MapView,
        T_pred: np.ndarray,
        planes: PoseSolve | None,
        cloud: np.ndarray | None,
        rgbd,
        reasons: list[str],
        keypoints: Keypoints | None,
        slides: Callable[[], bool] = lambda: False,
    ) -> TrackResult | None:
        """Last resort, right after a tracked frame only (across a loss the prediction is
        stale): RGB-D odometry, then ICP, against the previous frame from the trusted plane
        pose `planes` or the prediction, taken when the result overlaps the previous frame's
        depth. A plane pose that fixed rotation keeps it and its translation directions.
        When the frame `slides()` (its depth mostly on parallel planes, which any slide along
        them still overlaps), the frame's keypoints must agree with the result too."""
        methods: list[tuple[TrackingPath, Primitive, Callable[[np.ndarray], np.ndarray | None]]]
        methods = [(TrackingPath.ODOMETRY, Primitive.ODOMETRY, lambda T0: self._rgbd(rgbd, T0))]
        if cloud is not None:
            methods.append((TrackingPath.ICP, Primitive.ICP, lambda T0: self._icp(cloud, T0)))
        for path, kind, method in methods:
            T = method(T_pred if planes is None else planes.T)
            if T is None:
                continue
            if not self._agrees(cloud, T):
                reasons.append(f"{path.value} result does not overlap the previous frame")
                continue
            colours = self._colour_check(cloud, rgbd, T)
            if colours is ColourCheck.CONTRADICTS:
                reasons.append(f"{path.value} result: the colours contradict the previous frame")
                continue
            if (
                colours is ColourCheck.UNKNOWN
                and slides()
                and not self._keypoints_agree(T, keypoints)
            ):
                reasons.append(
                    f"{path.value} result unconfirmed: the frame's depth is parallel planes "
                    "and its keypoints do not agree"
                )
                continue
            dof = (0, 0)
            reg = None if planes is None else planes.registration
            if reg is not None and reg.status is RegistrationStatus.DEGENERATE_TRANSLATION:
                T = _fill_translation(reg, T)
                path = (
                    TrackingPath.PLANES_ODOMETRY
                    if path is TrackingPath.ODOMETRY
                    else TrackingPath.PLANES_ICP
                )
                dof = (3, 3 - len(reg.unobservable_translation_dirs))
            assoc = self._associate(frame, view, T) if not view.empty else Association([], [])
            found = PoseConstraints(*dof, filled_by=(kind,), terms={"planes": len(assoc.planes)})
            return self._result(frame, view, T, assoc, path, "; ".join(reasons), found, keypoints)
        return None

    def _points_agree(self, T: np.ndarray, points: _LazyKeypoints) -> bool:
        """Whether at least `points.min_inliers` matches of the frame's keypoints with the
        last keyframe's agree with T (4, 4): the cheap check of a plane pose that moved the
        prediction more than the fast path allows (online poses jitter by several cm even
        at 30 Hz; a wrong plane fit at a wide baseline does not agree with the points)."""
        return self._keypoints_agree(T, points.get())

    def _keypoints_agree(self, T: np.ndarray, keypoints: Keypoints | None) -> bool:
        """`_points_agree` on keypoints already detected (None: no keypoints, False)."""
        if keypoints is None or self.keypoint_map is None or not len(keypoints):
            return False
        matches = self.keypoint_map.matches(keypoints, self.keypoint_map.recent(1))
        return self._agreeing(T, keypoints, matches) >= self.config.points.min_inliers

    def _near(
        self,
        T: np.ndarray,
        T_pred: np.ndarray,
        close_frames: bool = False,
        T_last: np.ndarray | None = None,
    ) -> bool:
        """Whether T (4, 4) is within the fast path's correction of the prediction, or with
        `close_frames` (at most `fast_max_gap_s` apart) within its jump limit of the
        prediction or of the last frame's pose T_last (4, 4): the constant-velocity
        prediction overshoots when the camera stops or turns back, the last pose does not."""
        meters, degrees = pose_difference(T_pred, T)
        cfg = self.config
        if meters <= cfg.fast_max_correction_m and degrees <= cfg.fast_max_correction_deg:
            return True
        if not close_frames:
            return False
        jumps = [(meters, degrees)] + ([] if T_last is None else [pose_difference(T_last, T)])
        return any(m <= cfg.fast_max_jump_m and d <= cfg.fast_max_jump_deg for m, d in jumps)

    def _plausible(self, T: np.ndarray, T_last: np.ndarray | None, gap_s: float) -> bool:
        """Whether a motion from T_last (4, 4) to T (4, 4) in `gap_s` seconds is one a
        hand-held or robot-borne camera makes: within the fast path's jump limit, or within
        MAX_SPEED_M_S and MAX_TURN_DEG_S over the gap (True without a last pose or time)."""
        if T_last is None or not np.isfinite(gap_s):  # no last pose or time: no bound
            return True
        meters, degrees = pose_difference(T_last, T)
        cfg = self.config
        return meters <= max(cfg.fast_max_jump_m, MAX_SPEED_M_S * gap_s) and degrees <= max(
            cfg.fast_max_jump_deg, MAX_TURN_DEG_S * gap_s
        )

    def _point_pose(self, keypoints: Keypoints, matches: PointMatches) -> np.ndarray | None:
        """T_world_cam (4, 4) of a point RANSAC over `matches`, or None."""
        cfg = self.config.points
        if len(matches) < cfg.min_inliers:
            return None
        p_cam = keypoints.points_cam[matches.observed]
        found = ransac_pose(
            p_cam,
            matches.points_world,
            inlier_threshold(p_cam, cfg, self.sensor),
            cfg.ransac_iterations,
            self.rng,
            cfg.min_inliers,
        )
        return None if found is None else found.T_world_cam

    def _result(
        self,
        frame: FrameView,
        view: MapView,
        T_final: np.ndarray,
        assoc: Association,
        path: TrackingPath,
        reason: str,
        found: PoseConstraints | None,
        keypoints: Keypoints | None,
    ) -> TrackResult:
        """TrackResult with the correspondences of the final pose and the count of planes
        the map does not have yet (nor culled as seen once: clutter seen again)."""
        new = np.ones(len(frame.plane_ids), dtype=bool)
        for normals, d, areas in (
            (view.normals, view.d, view.plane_weights),
            (view.culled_normals, view.culled_d, view.culled_areas),
        ):
            if new.any() and len(d):
                new &= ~self._matchable(frame, normals, d, areas, T_final)
        return TrackResult(
            T_world_cam=T_final,
            path=path,
            reason=reason,
            plane_pairs=[
                (int(frame.plane_ids[i]), int(view.plane_ids[j])) for i, j in assoc.planes
            ],
            corner_pairs=[(int(i), int(view.corner_ids[j])) for i, j in assoc.corners],
            new_planes=int(np.count_nonzero(new)),
            constraints=found,
            keypoints=keypoints,
            terms=(
                frame_terms(frame, view, assoc, self.sensor) if self.config.final_poses else None
            ),
        )


def _smooth_grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an (H, W, 3) uint8 image, blurred by COLOUR_BLUR_PX:
    colours compared across a wide baseline then differ by the surfaces' colours, not by
    which pixel of a fine texture each sample hit."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return cv2.GaussianBlur(grey, (0, 0), COLOUR_BLUR_PX)


def parallel_share(observation: FrameObservation, max_angle_deg: float = 10.0) -> float:
    """Share of the frame's valid depth pixels on its planes when they are all parallel
    (within max_angle_deg, either side), else 0. When it reaches `icp_min_fitness`, a pose
    slid along those planes or turned about their normal still lands that share of the
    frame on the previous frame's depth, and the planes fix neither, so the dense
    fallbacks' overlap check (`_agrees`) could not reject it: a dense pose of such a frame
    must also agree with its keypoints."""
    planes = observation.segmentation.planes
    cloud = observation.cloud
    if not planes or cloud is None:
        return 0.0
    normals = np.array([p.normal for p in planes], dtype=np.float64)
    if np.min(np.abs(normals @ normals[0])) < np.cos(np.radians(max_angle_deg)):
        return 0.0  # two directions of planes: they fix the rotation
    valid = np.isfinite(cloud[..., 2]) & (cloud[..., 2] > 0)
    total = int(np.count_nonzero(valid))
    on_planes = (observation.segmentation.labels >= 0) & valid
    return float(np.count_nonzero(on_planes)) / total if total else 0.0


def _with_point_inliers(solve: JointSolve, agreeing: np.ndarray) -> tuple[JointSolve, np.ndarray]:
    """`solve` with its point term counting the matches `agreeing` ((M,) bool: within their
    inlier threshold at its pose), and that mask. The estimate's own point gate is wide (a
    keyframe's pose error is shared by its points), so refined poses a few cm apart would
    look equally supported."""
    terms = {**solve.constraints.terms, "points": int(np.count_nonzero(agreeing))}
    return replace(solve, constraints=replace(solve.constraints, terms=terms)), agreeing


def is_rival(
    best: JointSolve,
    other: JointSolve,
    best_points: np.ndarray,
    other_points: np.ndarray,
    cfg: TrackingConfig,
) -> bool:
    """Whether `other` makes a relocalisation to `best` ambiguous: it scores at least
    `relocalise_ambiguity` of the best, lies elsewhere (beyond 10 cm or 5 deg) and is not the
    same place fitted worse, which explains the same point matches (the (M,) bool masks of
    the matches agreeing with each: half of the other's, and at least `points.min_inliers`,
    are the best's too). A symmetric room's other corners match other keypoints, or none."""
    if other.score < cfg.relocalise_ambiguity * best.score or _same_pose(other.T, best.T):
        return False
    shared = np.count_nonzero(other_points & best_points)
    return bool(shared < max(cfg.points.min_inliers, 0.5 * np.count_nonzero(other_points)))


def _same_pose(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """Whether two (4, 4) poses are within 10 cm and 5 deg of each other."""
    meters, degrees = pose_difference(T_a, T_b)
    return meters <= 0.10 and degrees <= 5.0


def _keep(
    frame: FrameView, assoc: Association, ok: np.ndarray, corner_ok: np.ndarray
) -> Association | None:
    """`assoc` with the planes `ok` (and the corners `corner_ok` whose planes all stay), or
    None when all are ok."""
    if ok.all() and corner_ok.all():
        return None
    planes = [p for p, keep in zip(assoc.planes, ok, strict=True) if keep]
    kept_obs = {i for i, _ in planes}
    corners = [
        c
        for c, keep in zip(assoc.corners, corner_ok, strict=True)
        if keep and all(int(i) in kept_obs for i in frame.corner_planes[c[0]])
    ]
    return Association(planes=planes, corners=corners)
