"""Loop constraints: a keyframe that revisits older ground, placed against an older keyframe.

Tracking follows the map near the last keyframes. After a long way round, the online map
of a revisited place is off the old one by the drift (5-20 cm in places on the five-pass
7-Scenes replay), and frame-to-map tracking joins whichever copy of a surface is nearest.
At each keyframe, the `pool` older keyframes (all but the `skip_recent` last) nearest its
pose vote with their strongest descriptors (`KeypointMap.vote`; ORB-SLAM's place
recognition votes over the whole map with a bag of words, which by brute force cost
0.15 s a keyframe here); the best-voted are matched in full and a point RANSAC
(`ransac_pose`) places the keyframe against each. The one with the most agreeing matches,
its pose refined by other evidence when the caller gives a `Refine` (the tracker's: both
keyframes' planes, corners and edges), gives a `LoopConstraint` (the keyframe's pose in
the older keyframe's camera frame) when it moves the tracked pose by more than the noise
(`min_correction_*`) and less than a false match would (`max_correction_*`). The backend
adds it as a relative-pose factor, so the optimised poses take the revisited map back
onto the old one.

The search runs beside tracking, on one worker thread (`LoopSearch`, as ORB-SLAM's loop
closing runs beside its tracking): at a keyframe the tracking thread takes a `LoopQuery`
(the nearby older keyframes' keypoints and poses as a snapshot, and the new keyframe's
images), the worker detects the keyframe's keypoints and places it (`place_loop`), and
the next keyframe collects the outcome (its keypoints join the keypoint map) and takes
the loop to the graph.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.geometry import invert_pose
from planeslam.core.types import LoopConstraint
from planeslam.tracking.config import LoopConfig, PointConfig, TrackingConfig
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.joint import JointEstimator
from planeslam.tracking.keypoints import (
    KeypointDetector,
    KeypointMap,
    Keypoints,
    PointMatches,
    PointPose,
    inlier_threshold,
    ransac_pose,
)
from planeslam.tracking.views import FrameView, frame_as_map

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

logger = logging.getLogger(__name__)

Refine = Callable[[int, np.ndarray, PointMatches], np.ndarray | None]
"""(older keyframe, (4, 4) T_old_cam of the points, the matches in its camera frame) ->
refined T_old_cam, or None."""


def nearby_older_keyframes(
    keypoint_map: KeypointMap, T_world_cam: np.ndarray, cfg: LoopConfig
) -> np.ndarray:
    """Frame indices (at most `pool`) of the keyframes of `keypoint_map` but the
    `skip_recent` most recent whose camera is within `search_radius_m` of T_world_cam's
    (4, 4) and whose optical axis is within `search_angle_deg` of its, nearest first
    (distance plus `search_radius_m` per `search_angle_deg` of turn): the older keyframes a
    drifted pose can still be revisiting."""
    indices, poses = keypoint_map.poses()
    indices, poses = indices[: -cfg.skip_recent], poses[: -cfg.skip_recent]
    meters = np.linalg.norm(poses[:, :3, 3] - T_world_cam[:3, 3], axis=1)
    cos_angle = np.clip(poses[:, :3, 2] @ T_world_cam[:3, 2], -1.0, 1.0)
    turn = np.degrees(np.arccos(cos_angle)) / cfg.search_angle_deg  # 1 at the limit
    near = np.flatnonzero((meters <= cfg.search_radius_m) & (turn <= 1.0))
    order = np.argsort(meters[near] / cfg.search_radius_m + turn[near], kind="stable")
    return indices[near[order[: cfg.pool]]]


@dataclass(frozen=True)
class LoopQuery:
    """One new keyframe's loop search as taken on the tracking thread (`loop_query`): what
    `place_loop` needs, so that it can run beside tracking, which goes on changing the
    keypoint map."""

    index: int
    """Frame index of the new keyframe."""
    T_world_cam: np.ndarray
    """(4, 4) its tracked pose."""
    candidates: KeypointMap
    """A snapshot of the older keyframes it may revisit (`nearby_older_keyframes`)."""
    keypoints: Keypoints | None = None
    """Its keypoints when tracking computed them ..."""
    images: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    """... else its (H, W, 3) uint8 RGB and (H, W, 3) organised cloud [m] to detect them in."""


@dataclass(frozen=True)
class LoopOutcome:
    """What one keyframe's loop search found."""

    index: int
    """Frame index of the keyframe."""
    keypoints: Keypoints
    """Its keypoints (detected by the search when the query had images only)."""
    loop: LoopConstraint | None
    search_ms: float = 0.0
    """Wall-clock time of the search on its thread [ms] (`LoopSearch`)."""


def loop_query(
    keypoint_map: KeypointMap,
    index: int,
    T_world_cam: np.ndarray,
    cfg: LoopConfig,
    keypoints: Keypoints | None = None,
    images: tuple[np.ndarray, np.ndarray] | None = None,
) -> LoopQuery | None:
    """The loop search of new keyframe `index` tracked at T_world_cam (4, 4), with its
    `keypoints` or the `images` to detect them in, against the older keyframes of
    `keypoint_map` it may revisit (none: the search only detects its keypoints); None
    with neither keypoints nor images."""
    if keypoints is None and images is None:
        return None
    nearby = nearby_older_keyframes(keypoint_map, T_world_cam, cfg)
    return LoopQuery(index, np.array(T_world_cam), keypoint_map.snapshot(nearby), keypoints, images)


def place_loop(
    query: LoopQuery,
    keypoints: Keypoints,
    cfg: LoopConfig,
    points: PointConfig,
    sensor: DepthNoiseConfig,
    rng: np.random.Generator,
    refine: Refine | None = None,
) -> LoopConstraint | None:
    """The loop constraint of `query`'s keyframe (its `keypoints`) against its candidates,
    or None. `refine(old, T_old_cam, matches)`: the points' pose in the older keyframe's
    camera frame refined by other evidence (its matches given in that frame), or None to
    drop it."""
    if len(keypoints) < cfg.min_inliers:
        return None
    candidates, T_world_cam = query.candidates, query.T_world_cam
    best: tuple[int, PointPose, PointMatches] | None = None
    for old in candidates.vote(keypoints, cfg.candidates, strongest=points.vote_descriptors):
        matches = candidates.matches(keypoints, [old])
        if len(matches) < cfg.min_inliers:
            continue
        p_cam = keypoints.points_cam[matches.observed]
        found = ransac_pose(
            p_cam,
            matches.points_world,
            inlier_threshold(p_cam, points, sensor),
            points.ransac_iterations,
            rng,
            cfg.min_inliers,
        )
        if found is None or found.count < cfg.min_inlier_fraction * len(matches):
            continue
        if best is None or found.count > best[1].count:
            best = (old, found, matches)
    if best is None:
        return None
    old, found, matches = best
    T_world_old = candidates.pose(old)
    T_old_world = invert_pose(T_world_old)
    T_old_cam = T_old_world @ found.T_world_cam
    if refine is not None:
        refined = refine(old, T_old_cam, matches.moved(T_old_world))
        if refined is None:
            return None
        T_old_cam = refined
    meters, degrees = pose_difference(T_world_cam, T_world_old @ T_old_cam)
    if meters < cfg.min_correction_m and degrees < cfg.min_correction_deg:
        return None
    if meters > cfg.max_correction_m or degrees > cfg.max_correction_deg:
        logger.debug(
            "loop against keyframe %d dropped: %.2f m / %.1f deg off the tracked pose",
            old,
            meters,
            degrees,
        )
        return None
    logger.debug(
        "loop against keyframe %d: %.3f m / %.2f deg, %d matches agree",
        old,
        meters,
        degrees,
        found.count,
    )
    return LoopConstraint(
        index=query.index, old_index=old, T_old_cam=T_old_cam, inliers=found.count
    )


class LoopSearch:
    """Loop searches on one worker thread beside tracking. `submit` hands over a keyframe's
    `LoopQuery`; `collect`, at the next keyframe, waits for that search and returns its
    outcome, so the loops a run finds and the keyframe that carries each to the graph do
    not depend on timing. `search(query)` runs on the worker: it must touch nothing the
    tracking thread changes (the query holds snapshots)."""

    def __init__(self, search: Callable[[LoopQuery], LoopOutcome]) -> None:
        self._search = search
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="planeslam-loops")
        self._pending: Future[LoopOutcome] | None = None

    def submit(self, query: LoopQuery) -> None:
        """Start `query`'s search (after collecting the previous one)."""
        if self._pending is not None:
            raise RuntimeError("collect the previous loop search before submitting another")
        self._pending = self._executor.submit(self._timed_search, query)

    def _timed_search(self, query: LoopQuery) -> LoopOutcome:
        start = time.perf_counter()
        outcome = self._search(query)
        return replace(outcome, search_ms=1e3 * (time.perf_counter() - start))

    def collect(self) -> LoopOutcome | None:
        """The outcome of the search submitted last (waiting for it; its error re-raised
        here), or None when none is pending."""
        pending, self._pending = self._pending, None
        return None if pending is None else pending.result()

    def close(self) -> None:
        """Drop a pending search and stop the worker once it is idle (idempotent)."""
        self._pending = None
        self._executor.shutdown(wait=False, cancel_futures=True)


class KeyframeLoops:
    """The tracker's loop search: queries at keyframes (`query`), the search itself
    (`search`, on the loop thread) with the joint estimate refining a loop's pose."""

    def __init__(
        self,
        config: TrackingConfig,
        keypoint_map: KeypointMap,
        camera: CameraConfig,
        sensor: DepthNoiseConfig,
        joint: JointEstimator,
        seed: int,
    ) -> None:
        self.config = config
        self.keypoint_map = keypoint_map
        self.camera = camera
        self.sensor = sensor
        self.joint = joint
        self._keyframe_frames: dict[int, FrameView] = {}
        """Each keyframe's observation, camera frame (the older side of later loops)."""
        self._rng = np.random.default_rng([seed, 1])
        """The loop search's own draws (it runs beside tracking's)."""
        self._detector: KeypointDetector | None = None

    def query(
        self,
        index: int,
        observation: FrameObservation,
        T_world_cam: np.ndarray,
        keypoints: Keypoints | None,
        images: tuple[np.ndarray, np.ndarray] | None,
    ) -> LoopQuery | None:
        """New keyframe `index`'s loop search (`loop_query`: `observation`, tracked at
        T_world_cam (4, 4), with its keypoints or the (rgb, cloud) `images` to detect them
        in), or None when loops are off. The keyframe's observation is kept for later loops
        against it."""
        if not self.config.loops.enabled:
            return None
        self._keyframe_frames[index] = FrameView.of(observation, self.camera)
        return loop_query(
            self.keypoint_map, index, T_world_cam, self.config.loops, keypoints, images
        )

    def search(self, query: LoopQuery) -> LoopOutcome:
        """The loop constraint of `query`'s keyframe against an older keyframe it revisits
        (`place_loop`). With `loops.refine_planes` the points' relative pose is refined by
        the joint estimate over both frames' planes, corners and edges and the point
        matches (the older keyframe's observation as the map), and taken only when that is
        trusted and within `loops.refine_max_step_*` of it. Safe on another thread than
        tracking's (`LoopSearch`): it uses its own detector and random generator and reads
        kept observations only."""
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
            solve = self.joint.solve(
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
            self._rng,
            refine if cfg.loops.refine_planes else None,
        )
        return LoopOutcome(query.index, keypoints, loop)

    def take_keypoints(self, outcome: LoopOutcome) -> None:
        """The keypoints a loop search detected join the keypoint map's keyframe."""
        self.keypoint_map.give_keypoints(outcome.index, outcome.keypoints)

    def _loop_detector(self) -> KeypointDetector:
        """The loop search's own ORB detector (OpenCV's is not shared across threads)."""
        if self._detector is None:
            self._detector = KeypointDetector(self.camera, self.sensor, self.config.points)
        return self._detector
