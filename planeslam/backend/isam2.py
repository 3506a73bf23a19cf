"""iSAM2 backend: keyframe poses, plane and corner landmarks, incremental smoothing.

Variables: keyframe poses T_world_cam (Pose3, key `keys.pose(index)`), plane
landmarks (OrientedPlane3, world frame) and corner landmarks (Point3, world
frame [m]) from `planeslam.factors.PlaneLandmarks`. Factors per keyframe: a
prior on the first, a BetweenFactorPose3 from the previous keyframe on every
other one (so no pose is ever constrained by planes alone), and the landmark
factors of its observation: its corners and the `max_planes_per_keyframe` of its planes
that best fix its pose (`informative_planes`), a tie between each two plane landmarks
the map joined since the last keyframe (`tie_joined_planes`), and a BetweenFactorPose3
from each older keyframe it revisits (loop constraints from the caller's loop detector).
One `ISAM2.update` per keyframe (plus `extra_updates` relinearising iterations).

With `window_keyframes` N > 0, iSAM2 holds only the last N to 1.5 N keyframes and what
they observe; the rest of the graph is held at its estimate (`planeslam.backend.window`),
and a landmark the window lost is taken back in when a keyframe observes it again. The
final batch optimisation (`optimize_batch`) runs over the whole graph either way.

An indeterminate system ("Indeterminate linear system", a RuntimeError from
gtsam) never escapes: `planeslam.factors.recovery.RecoveringISAM2` rebuilds iSAM2
(it is not exception safe) from the committed factors and the last estimate, drops
the landmark named in the message (or, failing that, every new landmark, then every
landmark factor of the keyframe) for this keyframe and retries the update.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterable, Mapping, Sequence

import gtsam
import numpy as np

from planeslam.backend.base import ConstraintKind, RejectedConstraint
from planeslam.backend.config import BackendConfig
from planeslam.backend.hypotheses import (
    HYPOTHESIS_GATE_DEG,
    HYPOTHESIS_GATE_M,
    WEAK_LINK_SIGMAS,
    Relocalisation,
    agree,
    decide,
    implied_placement,
)
from planeslam.backend.window import FactorHistory, split_factors
from planeslam.core.errors import ConfigError
from planeslam.core.geometry import as_pose, invert_pose, transform_plane, transform_points
from planeslam.core.types import (
    FrameMeasurements,
    LoopConstraint,
    PlaneEstimate,
    PlaneMeasurement,
    RelativePose,
)
from planeslam.factors.landmarks import AddedFactors, PlaneLandmarks
from planeslam.factors.recovery import RecoveringISAM2, new_isam2

logger = logging.getLogger(__name__)


class Isam2Backend:
    """Incremental smoothing of keyframe poses and plane / corner landmarks with iSAM2."""

    def __init__(self, config: BackendConfig | None = None) -> None:
        self.config = config or BackendConfig()
        self.keys = self.config.keys
        self.landmarks = PlaneLandmarks(self.keys, self.config.landmarks)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = self.config.relinearize_skip
        self._smoother = RecoveringISAM2(params, self.config.extra_updates)
        self._history = FactorHistory(self.keys)
        self._window: list[int] = []  # keyframe indices whose poses iSAM2 holds
        self._timestamps: dict[int, float] = {}
        self._last_index: int | None = None
        self.update_ms: list[float] = []
        """Wall-clock ms of the iSAM2 work per keyframe (updates, retries, estimate)."""
        self._groups: list[Relocalisation] = []  # every relocalised keyframe's group
        self._current: Relocalisation | None = None  # the group new keyframes join
        self._loops: list[tuple[LoopConstraint, gtsam.NonlinearFactor]] = []  # in the graph
        self.rejected: list[RejectedConstraint] = []
        """Relocalisations and loops taken out of the graph (or kept out), in order."""
        self.last_rejected: tuple[RejectedConstraint, ...] = ()
        """Those of the last `add_keyframe`."""

    # ------------------------------------------------------------------ queries

    @property
    def failures(self) -> int:
        """Indeterminate updates caught and handled so far."""
        return self._smoother.failures

    @property
    def _estimate(self) -> gtsam.Values:
        """The last estimate of every variable (not a copy)."""
        return self._history.estimate

    @property
    def _graph(self) -> gtsam.NonlinearFactorGraph:
        """Every committed factor."""
        return self._history.graph

    @property
    def window_size(self) -> int:
        """Keyframes whose poses iSAM2 holds now (all with `window_keyframes` 0)."""
        return len(self._window)

    @property
    def num_factors(self) -> int:
        """Factors in the smoother."""
        return int(self._graph.size())

    @property
    def estimate(self) -> gtsam.Values:
        """A copy of the current estimate of every variable."""
        return gtsam.Values(self._estimate)

    def keyframe_poses(self) -> dict[int, tuple[float, np.ndarray]]:
        """Keyframe index -> (timestamp [s], optimised T_world_cam (4, 4)), increasing index."""
        return {
            i: (t, self._estimate.atPose3(self.keys.pose(i)).matrix())
            for i, t in self._timestamps.items()
        }

    def pose_covariance(self, index: int) -> np.ndarray | None:
        """(6, 6) marginal covariance of keyframe `index`'s pose (gtsam's Pose3 tangent
        order, rotation first), or None when iSAM2 does not hold it (outside the window)
        or cannot give it."""
        key = self.keys.pose(index)
        if not self._smoother.estimate.exists(key):
            return None
        try:
            return np.asarray(self._smoother.isam.marginalCovariance(key), dtype=np.float64)
        except RuntimeError as exc:
            logger.debug("no marginal covariance of keyframe %d: %s", index, exc)
            return None

    def plane_estimates(self, ids: Iterable[int] | None = None) -> dict[int, PlaneEstimate]:
        """Plane landmark id -> optimised estimate, world frame (all, or `ids`)."""
        return self.landmarks.plane_estimates(ids)

    def corner_estimates(self, ids: Iterable[int] | None = None) -> dict[int, np.ndarray]:
        """Corner landmark id -> p_world (3,) [m], optimised (all, or `ids`)."""
        return self.landmarks.corner_estimates(ids)

    # ------------------------------------------------------------------ update

    def add_keyframe(
        self,
        index: int,
        timestamp: float,
        T_world_cam_guess: np.ndarray,
        measurements: FrameMeasurements,
        plane_ids: Mapping[int, int],
        corner_ids: Mapping[int, int] | None = None,
        odometry_T_prev_cur: np.ndarray | None = None,
        odometry_sigmas: tuple[float, float] | np.ndarray | None = None,
        joined_planes: Sequence[tuple[int, int]] = (),
        loops: Sequence[LoopConstraint] = (),
        odometry: RelativePose | None = None,
        relocalised: bool = False,
    ) -> np.ndarray:
        """Add keyframe `index` with its measurements, update iSAM2 -> optimised T_world_cam (4, 4).

        index: frame index, strictly increasing; T_world_cam_guess (4, 4): initial
        pose (initialises new landmarks too); plane_ids / corner_ids: association of
        the measurements to landmark ids (see `PlaneLandmarks.add_observations`, or
        `self.landmarks.associate`); of the planes, the `max_planes_per_keyframe` that
        best fix the pose get factors. odometry_T_prev_cur (4, 4): measured pose of
        this keyframe in the previous keyframe's camera frame; None derives it from
        the guess and the previous optimised pose. odometry_sigmas: (rot [rad],
        trans [m]) or (6,) sigmas (rotation first) overriding the config's.
        joined_planes: (absorbed, surviving) plane landmark ids the map found to be one
        plane since the last keyframe; with `tie_joined_planes` each pair gets a tie
        (`PlaneLandmarks.join_planes`). loops: poses of this keyframe or of earlier ones
        (`LoopConstraint.index`: a loop detector beside tracking may deliver a keyframe's
        with a later one) against older keyframes, each a Huber-robust BetweenFactorPose3
        (`loop_sigma_*`); an older keyframe outside the window comes back into it held by
        its own factors. odometry: the caller's own measured motion since the previous
        keyframe (wheel, IMU, VIO), one more BetweenFactorPose3 with its information.
        relocalised: the guess is no measured motion from the previous keyframe (a
        whole-map relocalisation, or frames lost since): with
        `relocalisation_trial_keyframes` > 0 the keyframe gets only a weak link to the
        previous one instead of odometry, and its placement stays revocable
        (`planeslam.backend.hypotheses`; what was taken out: `rejected`).

        A loop whose residual after an update exceeds `HYPOTHESIS_GATE_*` (the rest of the
        graph contradicts it) is taken out of the graph; so is a relocalisation that loops
        outvote.
        """
        if isinstance(index, bool) or int(index) != index:
            raise ConfigError(f"keyframe index {index!r}: expected an integer")
        index = int(index)
        if self._last_index is not None and index <= self._last_index:
            raise ConfigError(
                f"keyframe index {index}: expected > the previous keyframe {self._last_index}"
            )
        T_guess = as_pose(T_world_cam_guess, "T_world_cam_guess")
        pose_key = self.keys.pose(index)
        cfg = self.config
        own: list[gtsam.NonlinearFactor] = []
        opened: Relocalisation | None = None
        if self._last_index is None:
            sigmas = np.r_[[cfg.prior_sigma_rot_rad] * 3, [cfg.prior_sigma_trans_m] * 3]
            own.append(
                gtsam.PriorFactorPose3(
                    pose_key, gtsam.Pose3(T_guess), gtsam.noiseModel.Diagonal.Sigmas(sigmas)
                )
            )
        else:
            prev_key = self.keys.pose(self._last_index)
            T_prev = self._estimate.atPose3(prev_key).matrix()
            if relocalised and cfg.relocalisation_trial_keyframes:
                opened = self._open_group(index, invert_pose(T_prev) @ T_guess)
                own.append(opened.link)
            else:
                if odometry_T_prev_cur is None:
                    T_prev_cur = invert_pose(T_prev) @ T_guess
                else:
                    T_prev_cur = as_pose(odometry_T_prev_cur, "odometry_T_prev_cur")
                own.append(
                    gtsam.BetweenFactorPose3(
                        prev_key,
                        pose_key,
                        gtsam.Pose3(T_prev_cur),
                        gtsam.noiseModel.Diagonal.Sigmas(self._odometry_sigmas(odometry_sigmas)),
                    )
                )
            if odometry is not None:
                own.append(
                    gtsam.BetweenFactorPose3(
                        prev_key,
                        pose_key,
                        gtsam.Pose3(odometry.T_a_b),
                        gtsam.noiseModel.Gaussian.Information(odometry.information),
                    )
                )
        if opened is not None or relocalised:
            self._current = opened
        group = self._current
        if group is not None:
            group.keyframes.append(index)
        held: list[tuple[LoopConstraint, Relocalisation]] = []
        direct: list[tuple[LoopConstraint, gtsam.NonlinearFactor]] = []
        for loop in loops:
            loop_factor = self._loop_factor(loop, index)
            on_trial = self._group_on_trial(loop)
            if on_trial is None:
                direct.append((loop, loop_factor))
                own.append(loop_factor)
            else:
                held.append((loop, on_trial))
        landmark_graph = gtsam.NonlinearFactorGraph()
        landmark_values = gtsam.Values()
        added = self.landmarks.add_observations(
            landmark_graph,
            landmark_values,
            pose_key,
            T_guess,
            measurements,
            self._most_informative(measurements, plane_ids),
            corner_ids,
        )
        joins = self.landmarks.join_planes(
            landmark_graph, joined_planes if self.config.tie_joined_planes else ()
        )
        pose_values = gtsam.Values()
        pose_values.insert(pose_key, gtsam.Pose3(T_guess))
        start = time.perf_counter()
        added = dataclasses.replace(
            added,
            factors=added.factors + joins.factors,
            kinds=added.kinds + joins.kinds,
            values=landmark_values,  # all it inserted
        )
        taken_back, update_values = self._taken_back(own, pose_values, added)
        update_graph = gtsam.NonlinearFactorGraph()
        for factor in own + taken_back:
            update_graph.add(factor)
        outcome = self._smoother.update(update_graph, update_values, added, self.landmarks)
        kept = list(outcome.factors[update_graph.size() :])
        self._history.add(own + kept)
        self._history.take_estimate(self._smoother.estimate)
        self._window.append(index)
        limit = self.config.window_keyframes
        if limit and len(self._window) > limit + max(1, limit // 2):
            self._slide_window()
        self._timestamps[index] = float(timestamp)
        self._last_index = index
        if group is not None and group.on_trial:
            group.ties.extend(f for f in kept if group.old_keys.intersection(f.keys()))
            group.created.update(k for k in added.new_keys if self._estimate.exists(k))
        self._loops.extend(direct)
        rejected_before = len(self.rejected)
        self._judge(index, held, {id(f) for _, f in direct})
        self.last_rejected = tuple(self.rejected[rejected_before:])
        self.update_ms.append((time.perf_counter() - start) * 1e3)
        return self._estimate.atPose3(pose_key).matrix()

    # ------------------------------------------------------------------ hypotheses

    def _open_group(self, index: int, T_prev_cur: np.ndarray) -> Relocalisation:
        """The group of relocalised keyframe `index`, with its weak link from the previous
        keyframe (`T_prev_cur` (4, 4): the guess's pose in it)."""
        assert self._last_index is not None
        link = gtsam.BetweenFactorPose3(
            self.keys.pose(self._last_index),
            self.keys.pose(index),
            gtsam.Pose3(T_prev_cur),
            gtsam.noiseModel.Diagonal.Sigmas(WEAK_LINK_SIGMAS),
        )
        keys = self.landmarks.keys
        old = {keys.plane(j) for j in self.landmarks.plane_ids}
        old |= {keys.corner(k) for k in self.landmarks.corner_ids}
        group = Relocalisation(
            first=index,
            previous=self._last_index,
            opened_at=len(self._timestamps),
            link=link,
            old_keys=frozenset(old),
        )
        self._groups.append(group)
        return group

    def _group_on_trial(self, loop: LoopConstraint) -> Relocalisation | None:
        """The group on trial that `loop` places from outside (its keyframe in the group,
        its older keyframe before it), if any."""
        for group in self._groups:
            if group.on_trial and group.holds(loop.index) and loop.old_index < group.first:
                return group
        return None

    def _judge(
        self, index: int, held: list[tuple[LoopConstraint, Relocalisation]], new: set[int]
    ) -> None:
        """After keyframe `index`'s update: the loops held out (placing a group on trial)
        enter or wait, a group they outvote moves, trials that ran out end, and loops in
        the graph that the rest contradicts (older than this update: not in `new`) leave."""
        cfg = self.config
        gate = (HYPOTHESIS_GATE_M, HYPOTHESIS_GATE_DEG)
        entering: list[tuple[LoopConstraint, gtsam.NonlinearFactor]] = []
        for loop, group in held:
            placed = implied_placement(
                self._pose(loop.old_index), loop, self._pose(group.first), self._pose(loop.index)
            )
            if agree(placed, self._pose(group.first), *gate):
                group.support += 1
                entering.append((loop, self._loop_factor(loop, index)))
            else:
                logger.info(
                    "loop %d-%d puts the group of relocalised keyframe %d elsewhere: it waits",
                    loop.index,
                    loop.old_index,
                    group.first,
                )
                group.waiting.append((loop, placed))
        if entering:
            graph = gtsam.NonlinearFactorGraph()
            for _, factor in entering:
                graph.add(factor)
            self._smoother.update(graph, gtsam.Values())
            self._history.add(f for _, f in entering)
            self._history.take_estimate(self._smoother.estimate)
            self.landmarks.update_estimates(self._smoother.estimate)
            self._loops.extend(entering)
        for group in {id(g): g for _, g in held}.values():
            verdict = decide(group, *gate)
            if verdict is not None:
                self._move_group(group, verdict[0], verdict[1], index)
        trial = cfg.relocalisation_trial_keyframes
        for group in self._groups:
            if group.on_trial and len(self._timestamps) - group.opened_at >= trial:
                group.on_trial = False
                for loop, _ in group.waiting:
                    self._reject(
                        ConstraintKind.LOOP,
                        loop,
                        index,
                        f"puts relocalised keyframe {group.first}'s group elsewhere",
                    )
                group.waiting, group.ties = [], []
        contradicted = [
            (loop, factor)
            for loop, factor in self._loops
            if id(factor) not in new
            and not agree(
                invert_pose(self._pose(loop.old_index)) @ self._pose(loop.index),
                loop.T_old_cam,
                *gate,
            )
        ]
        if contradicted:
            gone = {id(f) for _, f in contradicted}
            self._loops = [(loop, f) for loop, f in self._loops if id(f) not in gone]
            self._history.remove(f for _, f in contradicted)
            for loop, _ in contradicted:
                self._reject(ConstraintKind.LOOP, loop, index, "the optimised poses disagree")
            self._restart_smoother()

    def _move_group(
        self, group: Relocalisation, rows: list[int], T_world_first: np.ndarray, index: int
    ) -> None:
        """Reject `group`'s relocalisation: its ties and weak link leave the graph, its
        keyframes and landmarks move rigidly to put its first keyframe at T_world_first
        (4, 4), weak links to it and from it are re-seeded, the waiting loops `rows` enter,
        and iSAM2 restarts on the result."""
        T_new_old = T_world_first @ invert_pose(self._pose(group.first))
        moved = gtsam.Values()
        for k in group.keyframes:
            moved.insert(self.keys.pose(k), gtsam.Pose3(T_new_old @ self._pose(k)))
        keys = self.landmarks.keys
        for key in group.created:
            if not self._estimate.exists(key):
                continue
            if gtsam.Symbol(key).chr() == ord(keys.plane_char):
                plane = self._estimate.atOrientedPlane3(key)
                n, d = transform_plane(
                    T_new_old, np.asarray(plane.normal().point3()), float(plane.distance())
                )
                moved.insert(key, gtsam.OrientedPlane3(np.r_[n, d]))
            else:
                p = np.asarray(self._estimate.atPoint3(key), dtype=np.float64)
                moved.insert(key, transform_points(T_new_old, p[None])[0])
        self._history.take_estimate(moved)
        self.landmarks.update_estimates(moved)
        relinks = [g for g in self._groups if g is group or group.holds(g.previous)]
        self._history.remove([*group.ties, *(g.link for g in relinks)])
        for g in relinks:
            g.link = gtsam.BetweenFactorPose3(
                g.link.keys()[0],
                g.link.keys()[1],
                gtsam.Pose3(invert_pose(self._pose(g.previous)) @ self._pose(g.first)),
                gtsam.noiseModel.Diagonal.Sigmas(WEAK_LINK_SIGMAS),
            )
        winners = [group.waiting[r][0] for r in rows]
        entering = [(loop, self._loop_factor(loop, index)) for loop in winners]
        self._history.add([*(g.link for g in relinks), *(f for _, f in entering)])
        self._loops.extend(entering)
        self._reject(
            ConstraintKind.RELOCALISATION,
            None,
            index,
            f"{len(rows)} loops agree on a place {np.linalg.norm(T_new_old[:3, 3]):.2f} m away",
            group,
        )
        group.support = len(rows)
        group.waiting = [w for r, w in enumerate(group.waiting) if r not in rows]
        group.ties = []
        group.on_trial = False
        for loop, _ in group.waiting:
            self._reject(ConstraintKind.LOOP, loop, index, "disagrees with the loops that won")
        group.waiting = []
        self._restart_smoother()

    def _reject(
        self,
        kind: ConstraintKind,
        loop: LoopConstraint | None,
        index: int,
        reason: str,
        group: Relocalisation | None = None,
    ) -> None:
        if loop is not None:
            placed, against = loop.index, loop.old_index
        else:
            assert group is not None
            placed, against = group.first, group.previous
        rejected = RejectedConstraint(kind, placed, against, index, reason)
        logger.warning("%s of keyframe %d against %d rejected: %s", kind, placed, against, reason)
        self.rejected.append(rejected)

    def _restart_smoother(self) -> None:
        """iSAM2 anew on the committed factors at the current estimate (after factors left
        the graph and variables moved), relinearised a few times."""
        if self.config.window_keyframes:
            self._restart_window(self._window[-self.config.window_keyframes :], raising=True)
        else:
            self._smoother.restart(self._history.copy_graph(), gtsam.Values(self._estimate))
        self._smoother.relinearise(3)
        self._history.take_estimate(self._smoother.estimate)
        self.landmarks.update_estimates(self._smoother.estimate)

    def _pose(self, index: int) -> np.ndarray:
        """The estimate of keyframe `index`'s T_world_cam (4, 4)."""
        return self._estimate.atPose3(self.keys.pose(index)).matrix()

    def _loop_factor(self, loop: LoopConstraint, index: int) -> gtsam.BetweenFactorPose3:
        """The relative-pose factor of a loop constraint, added with keyframe `index`
        (ConfigError when its keyframes are neither in the graph nor this one)."""
        for name, frame in (("keyframe", loop.index), ("older keyframe", loop.old_index)):
            if frame != index and not self._estimate.exists(self.keys.pose(frame)):
                raise ConfigError(f"loop {name} {frame}: not a keyframe of the graph")
        if loop.old_index >= loop.index or loop.index > index:
            raise ConfigError(
                f"loop of keyframe {loop.index} against {loop.old_index} added with keyframe "
                f"{index}: expected older keyframe < keyframe <= {index}"
            )
        cfg = self.config
        sigmas = np.r_[[cfg.loop_sigma_rot_rad] * 3, [cfg.loop_sigma_trans_m] * 3]
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(cfg.loop_huber_k),
            gtsam.noiseModel.Diagonal.Sigmas(sigmas),
        )
        T_old_cam = as_pose(loop.T_old_cam, "loop.T_old_cam")
        return gtsam.BetweenFactorPose3(
            self.keys.pose(loop.old_index),
            self.keys.pose(loop.index),
            gtsam.Pose3(T_old_cam),
            noise,
        )

    def _taken_back(
        self, own: list[gtsam.NonlinearFactor], values: gtsam.Values, added: AddedFactors
    ) -> tuple[list[gtsam.NonlinearFactor], gtsam.Values]:
        """The landmarks the new factors (`own` with `values`, and `added`) observe again
        after the window lost them: the factors that bring them back, each at its estimate
        with what the held rest of the graph says about it (`FactorHistory.conditioned`),
        and `values` with theirs. None without a window."""
        if not self.config.window_keyframes:
            return [], values
        held = {
            key
            for factor in list(added.factors) + own
            for key in factor.keys()
            if not values.exists(key)
            and not added.values.exists(key)
            and not self._smoother.estimate.exists(key)
        }
        if not held:
            return [], values
        whole, conditioned = split_factors(
            self._history.factors_of(held), held, set(self._smoother.estimate.keys())
        )
        values = gtsam.Values(values)
        values.insert(self._history.values_of(held))
        return whole + list(self._history.conditioned(conditioned, held)), values

    def _slide_window(self) -> None:
        """Restart iSAM2 on the last `window_keyframes` keyframes: their poses, the landmarks
        they observe and the factors among these, with the rest held (`split_factors`)."""
        self._restart_window(self._window[-self.config.window_keyframes :])

    def _restart_window(self, window: list[int], raising: bool = False) -> None:
        """Restart iSAM2 on `window`'s keyframes (see `_slide_window`); when that is
        indeterminate keep the larger window, or with `raising` restart on it."""
        poses = {self.keys.pose(i) for i in window}
        pose_char = ord(self.keys.pose_char)
        free = {
            key
            for key in self._history.neighbours(poses)
            if key in poses or gtsam.Symbol(key).chr() != pose_char
        }
        whole, conditioned = split_factors(self._history.factors_of(free), free)
        graph = gtsam.NonlinearFactorGraph()
        for factor in whole + self._history.conditioned(conditioned, free):
            graph.add(factor)
        try:
            self._smoother.restart(graph, self._history.values_of(free))
        except RuntimeError as exc:  # keep the larger window; try again next keyframe
            logger.warning("window not moved: %s", " ".join(str(exc).split())[:160])
            if raising and window != self._window:
                self._restart_window(self._window, raising=True)
            elif raising:
                raise
            return
        self._window = window

    def _most_informative(
        self, measurements: FrameMeasurements, plane_ids: Mapping[int, int]
    ) -> Mapping[int, int]:
        """The `max_planes_per_keyframe` entries of `plane_ids` (observed plane id ->
        landmark id) that together pin the pose down best (all if 0; `informative_planes`)."""
        limit = self.config.max_planes_per_keyframe
        if not limit or len(plane_ids) <= limit:
            return plane_ids
        planes = {p.id: p for p in measurements.planes}
        known = set(self.landmarks.plane_ids)
        ids = sorted(i for i in plane_ids if i in planes)
        # Re-observed landmarks first: they tie the pose to the map; new ones fill up.
        ids.sort(key=lambda i: plane_ids[i] not in known)
        kept = informative_planes(
            [planes[i] for i in ids], limit, first=sum(plane_ids[i] in known for i in ids)
        )
        return {ids[k]: plane_ids[ids[k]] for k in kept}

    def _odometry_sigmas(self, sigmas: tuple[float, float] | np.ndarray | None) -> np.ndarray:
        if sigmas is None:
            sigmas = (self.config.odometry_sigma_rot_rad, self.config.odometry_sigma_trans_m)
        s = np.asarray(sigmas, dtype=np.float64).reshape(-1)
        if s.shape == (2,):
            s = np.repeat(s, 3)
        if s.shape != (6,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ConfigError(
                f"odometry_sigmas={sigmas!r}: expected (rot [rad], trans [m]) or (6,) "
                "positive sigmas"
            )
        return s

    def optimize_batch(self, max_iterations: int = 20, last: bool = False) -> float:
        """Gauss-Newton on every committed factor from the current estimate (the final
        global optimisation of a run: iSAM2 relinearises lazily online): a fresh iSAM2
        that relinearises every variable on each of its `max_iterations` updates. Updates
        the estimate, the landmark table and the smoother; returns the wall-clock ms.
        `last`: no keyframe follows (a run's end), so the windowed smoother is not
        restarted at the new estimate (a third of the batch's time on 7-Scenes): the
        estimates read afterwards are the same; `pose_covariance` stays the online one.

        Not gtsam's batch optimisers: they hand the Python factors a copy of the whole
        Values per call (O(variables) each), iSAM2 hands them its held linearisation point.
        """
        if not self._graph.size() or max_iterations < 1:
            return 0.0
        start = time.perf_counter()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.0)
        params.relinearizeSkip = 1
        isam, _theta = new_isam2(params)  # the handle lives as long as `isam` here
        try:
            isam.update(self._graph, self._estimate)
            for _ in range(int(max_iterations) - 1):
                isam.update()
            estimate = isam.calculateEstimate()
        except RuntimeError as exc:  # an indeterminate batch keeps the iSAM2 estimate
            logger.warning("batch optimisation failed (%s); keeping the iSAM2 estimate", exc)
            return (time.perf_counter() - start) * 1e3
        self._history.take_estimate(estimate)
        self.landmarks.update_estimates(estimate)
        if self.config.window_keyframes:
            if not last:
                self._slide_window()  # relinearised at the new estimate
        else:
            self._smoother.set_estimate(estimate)  # rebuilt there if another keyframe comes
        return (time.perf_counter() - start) * 1e3


def informative_planes(
    planes: Sequence[PlaneMeasurement], limit: int, first: int | None = None
) -> list[int]:
    """Indices of at most `limit` of `planes` chosen greedily to maximise the log-determinant
    of the pose information they give together (a D-optimal choice): a plane with normal n
    (camera frame) and fit variances fixes the rotation about the two axes across n (1 /
    its normal variance) and the translation along n (1 / its offset variance). So a floor
    and two walls come before another horizontal surface, however certain that one is.
    With `first`, the first `first` planes are chosen from before any of the others."""
    information = []
    for plane in planes:
        n = np.asarray(plane.n_cam, dtype=np.float64)
        cov = np.asarray(plane.covariance, dtype=np.float64)
        var_normal = max(0.5 * (cov[0, 0] + cov[1, 1]), 1e-12)
        var_offset = max(cov[2, 2], 1e-12)
        info = np.zeros((6, 6))
        info[:3, :3] = (np.eye(3) - np.outer(n, n)) / var_normal
        info[3:, 3:] = np.outer(n, n) / var_offset
        information.append(info)
    if not information:
        return []
    # A small floor per block (rotation, translation), so that the log-determinant is
    # finite from the first pick.
    largest = np.max([np.diag(i) for i in information], axis=0)
    total = np.diag(1e-6 * np.repeat([largest[:3].max(), largest[3:].max()], 3))
    chosen: list[int] = []
    split = len(planes) if first is None else first
    for left in (list(range(split)), list(range(split, len(planes)))):
        while left and len(chosen) < limit:
            gains = [np.linalg.slogdet(total + information[k])[1] for k in left]
            best = left.pop(int(np.argmax(gains)))
            chosen.append(best)
            total = total + information[best]
    return chosen
