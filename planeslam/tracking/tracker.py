"""Tracking: the pose of a frame against the plane-object map (paper Section 4.4), from
planes, corners, edges and keypoints, with no motion prior required. Per frame, the first
path that gives a pose its evidence supports:

1. `planes` (`plane_path`): the closed-form pose from the planes and corners associated
   under the prediction, taken when they fix all six directions within the residual gates
   and the prediction vouches for it (`motion.near`), or keypoint matches with the last
   keyframe agree with it.
2. `planes` / `planes+points` / `points` (`joint`): one robust estimate over planes,
   corners, edge ends and keypoints with depth, from the partial plane pose, a point
   RANSAC's pose and the prediction; taken near the prediction, or at a plausible motion
   (`motion.plausible`) with enough points or planes; after a loss, on points only.
   A rival nearer the prediction beats the best-supported pose (a repetitive texture
   agrees with poses a period apart: `periodic` adds those copies, matched by projection).
3. `odometry` / `icp` (`dense`, right after a tracked frame only): RGB-D odometry, then
   ICP, against the previous frame, each accepted by its own overlap and colours (a plane
   pose that fixed some directions keeps them: `planes+odometry`, `planes+icp`), started
   with the free directions at the previous frame's pose, at the prediction and where a
   sweep over them lands the frame well (`sweep`: a robot's step and turn), or, no plane
   placing the frame, at the prediction and at the last pose turned as predicted and not;
   taken: the result landing clearly best (`lands_better`), on ties the first start's, or
   across a gap the one nearest the prediction; keypoints agreeing on no pose do not veto it.
4. `relocalised` (`relocalise`): a map-wide search. Right after a tracked frame, among
   the hypotheses a plausible motion reaches (`relocalise_nearby`: no rival within that
   bound; between close frames, the colours must not contradict it); after a loss, over
   the whole map, verified (enough support, no rival anywhere) and confirmed by the
   segment (`segments`: a second relocalisation must agree).
5. `planes+motion` (right after a tracked frame): a partial plane pose near the
   prediction, the constant-velocity motion filling the directions it leaves free.
6. `lost`: the pose is the prediction, and the frame is left out of the trajectory.

Every result says which degrees of freedom the planes fixed and what filled the rest
(`TrackResult.constraints`). Frames: map primitives in the world frame, observations in
the camera frame; every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.types import TrackingPath
from planeslam.tracking import motion
from planeslam.tracking.association import Association
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.dense import ColourCheck, DenseFallback, RgbdPair, parallel_share
from planeslam.tracking.estimator import PoseConstraints, Primitive
from planeslam.tracking.estimator import warm_up as warm_up_estimator
from planeslam.tracking.joint import JointEstimator, JointSolve, estimator_settings
from planeslam.tracking.keypoints import (
    NO_KEYPOINTS,
    KeypointDetector,
    KeypointMap,
    Keypoints,
    LazyKeypoints,
    PointMatches,
)
from planeslam.tracking.plane_path import (
    COMPLETED_PATHS,
    DENSE_PATHS,
    PARTIAL,
    PlanePath,
    PoseSolve,
    plane_constraints,
    trusted,
)
from planeslam.tracking.registration import RegistrationStatus
from planeslam.tracking.relocalise import relocalise, relocalise_nearby
from planeslam.tracking.result import TrackResult, track_result
from planeslam.tracking.views import FrameView, MapView

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

__all__ = ["FrameView", "JointSolve", "MapView", "PoseSolve", "TrackResult", "Tracker"]

logger = logging.getLogger(__name__)


class Tracker:
    """Frame-to-map tracking from planes, corners, edges and keypoints: the paths of the
    module docstring, each in its own module (`plane_path`, `joint`, `relocalise`,
    `dense`), tried in order."""

    def __init__(
        self,
        config: TrackingConfig,
        odometry=None,
        camera: CameraConfig | None = None,
        sensor: DepthNoiseConfig | None = None,
        seed: int = 0,
        empty_map_starts: bool = True,
        every_keyframe_keypoints: bool = False,
    ) -> None:
        """`odometry`: an `odometry.RgbdOdometry` for the dense fallback, or None; `camera`,
        `sensor` enable keypoints (`KeypointMap`) and real edge ends. `empty_map_starts`:
        a frame nothing places in an empty map starts it where predicted (path `first`)."""
        self.config = config
        self.empty_map_starts = empty_map_starts
        self.odometry = odometry
        self.camera = camera
        self.sensor = sensor or DepthNoiseConfig()
        self.rng = np.random.default_rng(seed)
        self.keypoint_map: KeypointMap | None = None
        if config.points.enabled and camera is not None:
            detector = KeypointDetector(camera, self.sensor, config.points)
            self.keypoint_map = KeypointMap(detector, every_keyframe_keypoints)
        self.settings, self.refine_settings, self.thresholds = estimator_settings(config)
        warm_up_estimator()
        self.planes = PlanePath(config, self.thresholds)
        self.joint = JointEstimator(
            config, self.sensor, self.planes, self.settings, self.thresholds, self.rng
        )
        self.dense = DenseFallback(config, odometry, camera)
        self._result = partial(track_result, self.planes, self.sensor, config.final_poses)
        """(frame, view, T, association, path, reason, constraints, keypoints) -> TrackResult."""
        self.prediction_valid = True
        """Whether the previous frame was tracked, so the prediction means something (false
        after a loss, and for the first frame in a loaded map: see `expect_jump`)."""

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

    def move_keyframe(self, index: int, T_world_cam: np.ndarray) -> None:
        """The backend corrected keyframe `index` to T_world_cam (4, 4)."""
        if self.keypoint_map is not None:
            self.keypoint_map.move(index, T_world_cam)

    @property
    def previous_pose(self) -> np.ndarray | None:
        """(4, 4) T_world_cam of the last tracked frame, the dense fallback's reference."""
        return self.dense.previous_pose

    def correct_previous(self, correction: np.ndarray) -> None:
        """The backend moved the map by `correction` (4, 4), T_optimised @ T_online^-1: the
        last tracked frame's pose, against which the dense fallback registers, moves too."""
        self.dense.correct(correction)

    def expect_jump(self) -> None:
        """The next frame's prediction is no evidence (a loaded map, a restart): it must be
        placed by keypoints or whole-map relocalisation, and no dense fallback runs."""
        self.prediction_valid = False

    def relocalise(
        self,
        frame: FrameView,
        view: MapView,
        T_pred: np.ndarray,
        keypoints: Keypoints | None = None,
    ) -> JointSolve | None:
        """A verified whole-map relocalisation (`relocalise.relocalise`), or None."""
        return relocalise(frame, view, T_pred, keypoints, self.keypoint_map, self.joint)

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
        was made from it, also bounds the jump limit (`motion.near`)."""
        frame = FrameView.of(observation, self.camera)
        cloud, rgbd = self.dense.inputs(observation, rgb, depth_m)
        points = NO_KEYPOINTS
        if self.keypoint_map is not None and rgb is not None and observation.cloud is not None:
            detector, image, xyz = self.keypoint_map.detector, rgb, observation.cloud
            points = LazyKeypoints(lambda: detector.detect(image, xyz))
        gap = observation.timestamp - self.dense.previous_stamp

        def slides() -> bool:  # asked only of a dense pose, so no frame pays for it otherwise
            return cloud is not None and parallel_share(observation) >= self.config.icp_min_fitness

        result = self._track(frame, view, T_pred, cloud, rgbd, points, gap, T_last, slides)
        self.prediction_valid = not result.lost
        if not result.lost:
            self.dense.remember(observation.timestamp, cloud, rgbd, result.T_world_cam)
        return result

    def start(
        self,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
    ) -> None:
        """A frame placed without tracking (the first of a run or of a segment) at
        T_world_cam (4, 4): the next frame's prediction and dense fallback start from it,
        as from a tracked frame."""
        cloud, rgbd = self.dense.inputs(observation, rgb, depth_m)
        self.prediction_valid = True
        self.dense.remember(observation.timestamp, cloud, rgbd, T_world_cam)

    def _track(
        self,
        frame: FrameView,
        view: MapView,
        T_pred: np.ndarray,
        cloud: np.ndarray | None,
        rgbd: RgbdPair | None,
        points: LazyKeypoints = NO_KEYPOINTS,
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
        T_from = T_pred if T_last is None else T_last
        # 1. The closed-form plane pose near the prediction.
        solve = self.planes.register(frame, view, T_pred) if not view.empty else None
        good = solve if solve is not None and trusted(solve.registration, cfg) else None
        fast = (  # a full plane pose from a prediction that means something
            good is not None
            and good.registration.status is RegistrationStatus.OK
            and self.prediction_valid  # after a loss the prediction is no evidence
        )
        weak = (  # a direction that only a sliver of the planes' information fixes
            good is not None
            and points is not NO_KEYPOINTS
            and good.registration.translation_observability < cfg.weak_translation_share
        )
        close = frame_gap_s <= cfg.fast_max_gap_s
        if (
            fast
            and good is not None
            and (
                (not weak and motion.near(cfg, good.T, T_pred, close, T_last))
                or self._keypoints_agree(points.get(), good.T)
            )
        ):
            assoc = good.association
            terms = {"planes": len(assoc.planes), "corners": len(assoc.corners)}
            found = plane_constraints(good.registration, terms)
            return self._result(
                frame, view, good.T, assoc, TrackingPath.PLANES, "", found, points.value
            )
        reasons = ["no plane matched the map under the prediction"]
        if solve is not None:
            reasons[0] = f"plane pose {solve.registration.status.value}" + (
                "" if good is not None else " with residuals beyond the gates"
            )
            if weak and fast:
                reasons[0] += " with a weakly fixed translation the keypoints do not confirm"
        # 2. One estimate over every primitive, from every start that needs no plane prior.
        keypoints = points.get()
        matches, match_at = PointMatches.empty(), None
        starts = [] if good is None else [good.T]
        if keypoints is not None and self.keypoint_map is not None and len(keypoints):
            recent = self.keypoint_map.recent(cfg.points.recent_keyframes)
            matches = self.keypoint_map.matches(keypoints, recent)
            match_at = partial(self.keypoint_map.matches, keypoints, recent)
            found_T = self.joint.point_pose(keypoints, matches)
            if found_T is not None:
                starts.append(found_T)
            else:
                reasons.append(f"{len(matches)} point matches agree on no pose")
        starts.append(T_pred)
        best = self.joint.best(
            frame,
            view,
            starts,
            keypoints,
            matches,
            T_pred,
            self.prediction_valid,
            T_from,
            frame_gap_s,
            match_at,
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
        # 3. The dense fallback, free directions at the last pose (else a slide nothing
        # observes keeps the velocity it made, and grows) and at the prediction (a wide step).
        if self.prediction_valid:
            free_at = [self.dense.previous_pose, T_pred]
            starts = (
                self.dense.unplaced_starts(T_pred)
                if good is None
                else [self.planes.free_from(frame, view, good, T) for T in free_at]
            )
            if good is not None:  # a robot step lies beyond the dense methods' reach
                starts = self.dense.with_swept(starts, good.registration, cloud, rgbd)
            starts += [T_pred] if weak else []  # a weakly fixed direction: the prediction's too
            agree = partial(self._keypoints_agree, keypoints)
            prior = None if close else T_pred  # across a gap, the motion decides ties
            dense = self.dense.register(starts, cloud, rgbd, reasons, slides, agree, prior)
            if dense is not None:
                return self._completed(
                    frame, view, good, dense.T, dense.filled_by, reasons, keypoints
                )
        # 4. A map-wide search: right after a tracked frame, among the hypotheses a plausible
        # motion reaches (a symmetric scene's other places lie a quarter turn away); after
        # a loss, over the whole map, and a segment confirms it.
        if cfg.relocalise and not view.empty:
            if self.prediction_valid:
                placed = relocalise_nearby(
                    frame, view, T_from, frame_gap_s, keypoints, matches, self.joint
                )
            else:
                placed = self.relocalise(frame, view, T_pred, keypoints)
            if placed is None:
                reasons.append(
                    "no corner, plane, edge or keypoint hypothesis "
                    + ("within a plausible motion " if self.prediction_valid else "")
                    + "fits the map"
                )
            elif (
                self.prediction_valid
                and close
                and self.dense.colour_check(cloud, rgbd, placed.T) is ColourCheck.CONTRADICTS
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
        # 5. A partial plane pose near the prediction, completed by the motion.
        if (
            self.prediction_valid
            and good is not None
            and good.registration.status in PARTIAL
            and close
            and motion.near(cfg, good.T, T_pred, True, T_last)
        ):
            reasons.append("the planes agree with the motion")
            return self._completed(frame, view, good, T_pred, Primitive.MOTION, reasons, keypoints)
        # 6. Lost.
        reasons.append("no fallback registered the frame")
        if view.empty and self.empty_map_starts:
            return TrackResult(
                T_pred, TrackingPath.FIRST, "empty map: the frame starts it", keypoints=keypoints
            )
        return TrackResult(T_pred, TrackingPath.LOST, "; ".join(reasons), keypoints=keypoints)

    def _completed(
        self,
        frame: FrameView,
        view: MapView,
        planes: PoseSolve | None,
        T_other: np.ndarray,
        filled_by: Primitive,
        reasons: list[str],
        keypoints: Keypoints | None,
    ) -> TrackResult:
        """The result of a fallback's pose T_other (4, 4) (by `filled_by`), completing the
        trusted plane pose `planes` when that left directions free (`PlanePath.completed`)."""
        if planes is None or planes.registration.status not in PARTIAL:
            T, dof, path = T_other, (0, 0), DENSE_PATHS[filled_by]
        else:
            T, dof = self.planes.completed(frame, view, planes, T_other)
            path = COMPLETED_PATHS[filled_by]
        assoc = self.planes.associate(frame, view, T) if not view.empty else Association([], [])
        found = PoseConstraints(*dof, filled_by=(filled_by,), terms={"planes": len(assoc.planes)})
        return self._result(frame, view, T, assoc, path, "; ".join(reasons), found, keypoints)

    def _keypoints_agree(self, keypoints: Keypoints | None, T: np.ndarray) -> bool:
        """Whether at least `points.min_inliers` matches of the keypoints (None: False) with
        the last keyframe's agree with T (4, 4); a wrong wide-baseline plane fit does not."""
        if keypoints is None or self.keypoint_map is None or not len(keypoints):
            return False
        matches = self.keypoint_map.matches(keypoints, self.keypoint_map.recent(1))
        return self.joint.agreeing(T, keypoints, matches) >= self.config.points.min_inliers
