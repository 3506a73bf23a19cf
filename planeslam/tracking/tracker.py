"""Tracking: the pose of a frame against the plane-object map (paper Section 4.4).

Per frame, in order, the first path that gives a trustworthy pose wins; the result
says which one was used:

1. `planes`: associate the frame's planes and corners with the map's under the predicted
   pose (`association.associate_with_corners`), then the closed-form pose from plane and
   corner correspondences (`registration.pose_from_planes_and_points`), associated again
   under that pose and solved once more. Trusted when rotation and translation are both
   observable and the residuals are within the gates.
2. `relocalised`: the prediction was off (a jump, frames far apart, tracking lost): every
   observed corner against every map corner of the same convexity (6 pairings of their
   planes), and every triple of independent observed planes against the map triples with
   the same pairwise angles, is a pose hypothesis; the one under which most planes find a
   partner (then the one nearest the prediction) goes through path 1. Corners and plane
   triples are rigid, so this needs no small-motion assumption.
3. `planes+odometry`, `planes+icp`: the planes fixed rotation but left translation
   directions free (a corridor, a box side seen for the first time): Open3D RGB-D
   odometry, else point-to-plane ICP, against the previous frame and started from the
   plane pose, supplies those directions only.
4. `odometry`, then `icp`: planes do not constrain the pose (one wall, nothing planar):
   RGB-D odometry, then ICP, from the prediction.
5. `lost`: nothing worked; the pose is the prediction.

Only poses of paths 1-2 (and the first frame) are merged into the map (see
`planeslam.slam.MAPPING_PATHS`).

Frames: map planes and corners are in the world frame, observations in the camera
frame; every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from planeslam.core.errors import GeometryError
from planeslam.core.geometry import invert_pose
from planeslam.core.types import TrackingPath
from planeslam.tracking.association import (
    Association,
    associate_with_corners,
    plane_association_cost,
)
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.registration import (
    RegistrationResult,
    RegistrationStatus,
    pose_from_planes_and_points,
    refine_icp,
)

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

logger = logging.getLogger(__name__)

_PERMUTATIONS_3 = np.array(list(itertools.permutations(range(3))))


@dataclass(frozen=True)
class MapView:
    """The map as tracking sees it: planes and corners in the world frame."""

    plane_ids: np.ndarray
    """(M,) int map plane ids."""
    normals: np.ndarray
    """(M, 3) unit normals, world frame."""
    d: np.ndarray
    """(M,) offsets [m], world frame."""
    corner_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """(K,) int map corner ids."""
    corner_planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    """(K, 3) ROW indices into plane_ids / normals of each corner's three planes."""
    corner_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(K, 3) corner points, world frame [m]."""
    corner_convex_edges: np.ndarray | None = None
    """(K,) how many of each corner's edges are convex (3 box, 0 room); None: unknown."""
    plane_weights: np.ndarray | None = None
    """(M,) plane areas [m^2]: rank planes for relocalisation and gate association."""

    @property
    def empty(self) -> bool:
        return len(self.plane_ids) == 0


@dataclass(frozen=True)
class FrameView:
    """One observation's planes and corners as arrays, camera frame."""

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

    @classmethod
    def of(cls, observation: FrameObservation) -> FrameView:
        planes = observation.segmentation.planes
        ids = np.array([p.id for p in planes], dtype=np.int64)
        row = {int(i): k for k, i in enumerate(ids)}
        corners = observation.structure.corners
        counts = np.array([p.num_points for p in planes], dtype=np.float64)
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
        )


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


def _trusted(reg: RegistrationResult, cfg: TrackingConfig) -> bool:
    angle_ok = np.all(reg.plane_angle_residual_rad <= np.radians(cfg.max_residual_angle_deg))
    offset_ok = np.all(np.abs(reg.plane_offset_residual_m) <= cfg.max_residual_offset_m)
    return bool(angle_ok and offset_ok)


def _rotation_kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations R minimising sum |R src_i - dst_i|^2 for (..., 3, 3) row stacks."""
    H = np.swapaxes(src, -1, -2) @ dst
    U, _, Vt = np.linalg.svd(H)
    D = np.ones(H.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    return np.swapaxes(Vt, -1, -2) @ (D[..., :, None] * np.swapaxes(U, -1, -2))


def _independent_triples(
    normals: np.ndarray, weights: np.ndarray | None, limit: int, ordered: bool = False
) -> np.ndarray:
    """(T, 3) row indices of plane triples whose normals are far from coplanar (|det| > 0.2),
    among the `limit` heaviest planes (first rows when weights is None); every ordering of
    each triple when `ordered`."""
    rows = np.arange(len(normals)) if weights is None else np.argsort(-weights, kind="stable")
    rows = rows[:limit]
    if len(rows) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    combos = itertools.permutations(rows, 3) if ordered else itertools.combinations(rows, 3)
    triples = np.array(list(combos), dtype=np.int64)
    det = np.abs(np.linalg.det(normals[triples]))
    return triples[det > 0.2]


def _fill_translation(reg: RegistrationResult, T_icp: np.ndarray) -> np.ndarray:
    """The plane pose `reg.T` with its unobservable translation directions taken from the
    ICP pose T_icp (4, 4); rotation and the observed directions stay the planes'."""
    U = reg.unobservable_translation_dirs.reshape(-1, 3)
    T = reg.T.copy()
    T[:3, 3] += U.T @ (U @ (T_icp[:3, 3] - reg.T[:3, 3]))
    return T


class Tracker:
    """Frame-to-map tracking with plane, corner, ICP and RGB-D odometry paths."""

    def __init__(self, config: TrackingConfig, odometry=None) -> None:
        """`odometry`: an `odometry.RgbdOdometry` for the last fallback, or None."""
        self.config = config
        self.odometry = odometry
        self._previous_cloud: np.ndarray | None = None
        """(H, W, 3) organised cloud of the last tracked frame (ICP fallback)."""
        self._previous_rgbd: tuple[np.ndarray, np.ndarray] | None = None
        self._T_world_previous: np.ndarray | None = None
        self.lost_streak = 0
        """Frames lost in a row up to now."""

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
            gate=self._size_gate(frame, view),
        )

    def _size_gate(self, frame: FrameView, view: MapView) -> np.ndarray | None:
        """(N, M) bool: an observed plane may only match a map plane at least about its size
        (map outlines grow as planes merge, so a big observation never belongs to a small
        map plane: a floor is not a box top). None when sizes are unknown."""
        if frame.areas is None or view.plane_weights is None:
            return None
        cfg = self.config
        limit = cfg.size_gate_ratio * view.plane_weights + cfg.size_gate_margin_m2
        return frame.areas[:, None] <= limit[None, :]

    def _solve(
        self, frame: FrameView, view: MapView, assoc: Association, T_prior: np.ndarray
    ) -> RegistrationResult:
        cfg = self.config
        obs, mp = np.array(assoc.planes, dtype=np.int64).reshape(-1, 2).T
        co, cm = np.array(assoc.corners, dtype=np.int64).reshape(-1, 2).T
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
                kept = self._inliers(frame, view, assoc, reg)
                if kept is None:
                    break
                if not kept.planes:
                    return result
                assoc, reg = kept, self._solve(frame, view, kept, T_pred)
            result, T = PoseSolve(reg, assoc), reg.T
        return result

    def _inliers(
        self, frame: FrameView, view: MapView, assoc: Association, reg: RegistrationResult
    ) -> Association | None:
        """`assoc` without the correspondences beyond the residual gates, or None when all
        are within them. Corners go with any of their planes."""
        cfg = self.config
        ok = (reg.plane_angle_residual_rad <= np.radians(cfg.max_residual_angle_deg)) & (
            np.abs(reg.plane_offset_residual_m) <= cfg.max_residual_offset_m
        )
        corner_ok = reg.point_residual_m <= cfg.max_corner_distance_m
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

    def corner_hypotheses(self, frame: FrameView, view: MapView) -> np.ndarray:
        """(H, 4, 4) T_world_cam hypotheses from every (observed corner, map corner, pairing of
        their planes) of the same convexity whose normals agree within the angle gate after
        rotation; translation from the two corner points."""
        if not len(frame.corner_planes) or not len(view.corner_planes):
            return np.zeros((0, 4, 4))
        n_obs = frame.normals[frame.corner_planes]  # (Ko, 3, 3)
        n_map = view.normals[view.corner_planes][:, _PERMUTATIONS_3]  # (Km, 6, 3, 3)
        src = np.broadcast_to(n_obs[:, None, None], (len(n_obs),) + n_map.shape)
        dst = np.broadcast_to(n_map[None], src.shape)
        R = _rotation_kabsch(src, dst)  # (Ko, Km, 6, 3, 3)
        rotated = np.einsum("...ij,...kj->...ki", R, src)
        cos = np.clip(np.sum(rotated * dst, axis=-1), -1.0, 1.0)
        ok = np.all(cos >= np.cos(np.radians(self.config.max_angle_deg)), axis=-1)
        if frame.corner_convex_edges is not None and view.corner_convex_edges is not None:
            same = frame.corner_convex_edges[:, None] == view.corner_convex_edges[None, :]
            ok &= same[:, :, None]
        p_obs = np.broadcast_to(frame.corner_points[:, None, None], R.shape[:-1])
        p_map = np.broadcast_to(view.corner_points[None, :, None], R.shape[:-1])
        t = p_map - np.einsum("...ij,...j->...i", R, p_obs)
        T = np.tile(np.eye(4), R.shape[:-2] + (1, 1))
        T[..., :3, :3], T[..., :3, 3] = R, t
        return T[ok]

    def triple_hypotheses(self, frame: FrameView, view: MapView) -> np.ndarray:
        """(H, 4, 4) T_world_cam hypotheses from triples of planes with independent normals,
        observed against ordered map triples with the same pairwise angles (within the
        angle gate): rotation from the normals, translation from the three offsets. The
        `max_triple_planes` largest observed and `max_triple_map_planes` largest map planes
        take part."""
        cfg = self.config
        obs = _independent_triples(frame.normals, frame.weights, cfg.max_triple_planes)
        mp = _independent_triples(
            view.normals, view.plane_weights, cfg.max_triple_map_planes, ordered=True
        )
        if not len(obs) or not len(mp):
            return np.zeros((0, 4, 4))
        pair = np.array([[0, 1], [1, 2], [0, 2]])
        cos_obs = np.sum(frame.normals[obs[:, pair[:, 0]]] * frame.normals[obs[:, pair[:, 1]]], -1)
        cos_map = np.sum(view.normals[mp[:, pair[:, 0]]] * view.normals[mp[:, pair[:, 1]]], -1)
        angle_obs = np.arccos(np.clip(cos_obs, -1, 1))  # (To, 3)
        angle_map = np.arccos(np.clip(cos_map, -1, 1))  # (Tm, 3)
        gate = np.radians(cfg.max_angle_deg)
        io, im = np.nonzero(np.all(np.abs(angle_obs[:, None] - angle_map[None]) <= gate, -1))
        if not len(io):
            return np.zeros((0, 4, 4))
        n_src, n_dst = frame.normals[obs[io]], view.normals[mp[im]]  # (H, 3, 3)
        R = _rotation_kabsch(n_src, n_dst)
        A = np.einsum("hij,hkj->hki", R, n_src)  # rows: R n_obs_i
        b = frame.d[obs[io]] - view.d[mp[im]]  # (R n_obs_i) . t = d_obs_i - d_map_i
        t = np.linalg.solve(A, b[..., None])[..., 0]
        T = np.tile(np.eye(4), (len(io), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, t
        return T

    def hypotheses(self, frame: FrameView, view: MapView) -> np.ndarray:
        """All pose hypotheses: corners first, then plane triples ((H, 4, 4) T_world_cam)."""
        return np.concatenate(
            [self.corner_hypotheses(frame, view), self.triple_hypotheses(frame, view)]
        )

    def support(self, frame: FrameView, view: MapView, T: np.ndarray) -> np.ndarray:
        """(H,) number of observed planes that have a map plane within the angle and offset
        gates under each hypothesis T (H, 4, 4)."""
        R, t = T[:, :3, :3], T[:, :3, 3]
        n_world = np.einsum("hij,nj->hni", R, frame.normals)  # (H, N, 3)
        d_world = frame.d[None, :] - np.einsum("hni,hi->hn", n_world, t)
        cos = np.einsum("hni,mi->hnm", n_world, view.normals)
        offset = np.abs(d_world[:, :, None] - view.d[None, None, :])
        cfg = self.config
        close = (cos >= np.cos(np.radians(cfg.max_angle_deg))) & (offset <= cfg.max_offset_m)
        return np.count_nonzero(close.any(axis=2), axis=1)

    def relocalise(self, frame: FrameView, view: MapView, T_pred: np.ndarray) -> PoseSolve | None:
        """Best hypothesis, refined by `register`; None when none is trusted.

        Hypotheses are ranked by how many observed planes find a partner under them (then
        by distance to the prediction T_pred); the `relocalise_candidates` best are each
        refined, and the trusted one with the most associated planes, then corners, then
        the smallest residuals wins."""
        cfg = self.config
        T = self.hypotheses(frame, view)
        distance = np.linalg.norm(T[:, :3, 3] - T_pred[:3, 3], axis=1)
        if self.lost_streak < cfg.relocalise_anywhere_after:
            R_delta = np.einsum("ji,hjk->hik", T_pred[:3, :3], T[:, :3, :3])
            cos = (np.trace(R_delta, axis1=1, axis2=2) - 1.0) / 2.0
            near = (cos >= np.cos(np.radians(cfg.relocalise_max_rotation_deg))) & (
                distance <= cfg.relocalise_max_translation_m
            )
            T, distance = T[near], distance[near]
        if not len(T):
            return None
        count = self.support(frame, view, T)
        order = np.lexsort((distance, -count))
        best, best_key = None, None
        for k in order[: cfg.relocalise_candidates]:
            if count[k] < 3:
                break
            candidate = self.register(frame, view, T[k])
            if candidate is None or not _trusted(candidate.registration, cfg):
                continue
            reg = candidate.registration
            residual = (
                float(np.mean(reg.plane_angle_residual_rad)) / np.radians(cfg.sigma_angle_deg)
                + float(np.mean(np.abs(reg.plane_offset_residual_m))) / cfg.sigma_offset_m
            )
            key = (
                -len(candidate.association.planes),
                -len(candidate.association.corners),
                residual,
            )
            if best_key is None or key < best_key:
                best, best_key = candidate, key
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
    ) -> TrackResult:
        """Pose of `observation` against the map `view`, starting from the prediction
        T_pred (4, 4) T_world_cam; colour and depth enable the RGB-D odometry fallback."""
        cfg = self.config
        frame = FrameView.of(observation)
        cloud = observation.cloud if cfg.icp else None
        rgbd = None
        if cfg.rgbd_odometry and self.odometry is not None and rgb is not None:
            rgbd = (rgb, depth_m) if depth_m is not None else None
        result = self._track(frame, view, T_pred, cloud, rgbd)
        self.lost_streak = self.lost_streak + 1 if result.lost else 0
        if not result.lost:
            self._previous_cloud, self._previous_rgbd = cloud, rgbd
            self._T_world_previous = result.T_world_cam
        return result

    def _track(self, frame, view, T_pred, cloud, rgbd) -> TrackResult:
        """The paths of the module docstring, in order, on prepared inputs."""
        cfg = self.config
        if view.empty:
            return TrackResult(T_pred, TrackingPath.FIRST, "empty map: the frame starts it")
        reasons = []
        solve = self.register(frame, view, T_pred)
        path = TrackingPath.PLANES
        if (
            solve is None
            or not _trusted(solve.registration, cfg)
            or solve.registration.status
            in (RegistrationStatus.TOO_FEW, RegistrationStatus.DEGENERATE_ROTATION)
        ):
            reasons.append(
                "no plane matched the map under the prediction"
                if solve is None
                else f"plane pose {solve.registration.status.value}"
                + ("" if _trusted(solve.registration, cfg) else " with residuals beyond the gates")
            )
            relocalised = self.relocalise(frame, view, T_pred) if cfg.relocalise else None
            if relocalised is not None:
                solve, path = relocalised, TrackingPath.RELOCALISED
            else:
                if cfg.relocalise:
                    reasons.append("no corner or plane-triple hypothesis fits three planes")
                solve = None if solve is None or not _trusted(solve.registration, cfg) else solve
        if solve is not None and solve.registration.status is RegistrationStatus.OK:
            return self._result(frame, view, solve, path, "; ".join(reasons))
        # Point-based fallbacks, best first: RGB-D odometry (photometric + geometric, very
        # accurate from a good start), then ICP.
        fallbacks: list[tuple[TrackingPath, TrackingPath, Callable[[np.ndarray], Any]]] = [
            (TrackingPath.ODOMETRY, TrackingPath.PLANES_ODOMETRY, lambda T0: self._rgbd(rgbd, T0))
        ]
        if cloud is not None:
            fallbacks.append(
                (TrackingPath.ICP, TrackingPath.PLANES_ICP, lambda T0: self._icp(cloud, T0))
            )
        if (
            solve is not None
            and solve.registration.status is RegistrationStatus.DEGENERATE_TRANSLATION
        ):
            reasons.append("translation not observable from planes")
            for _, with_planes, method in fallbacks:
                T = method(solve.T)
                if T is not None:
                    T = _fill_translation(solve.registration, T)
                    return self._result(frame, view, solve, with_planes, "; ".join(reasons), T)
            reasons.append("no fallback filled it")
        T_init = solve.T if solve is not None else T_pred
        for alone, _, method in fallbacks:
            T = method(T_init)
            if T is not None:
                return self._result(frame, view, solve, alone, "; ".join(reasons), T)
        reasons.append("no fallback registered the frame")
        return TrackResult(T_pred, TrackingPath.LOST, "; ".join(reasons))

    def _result(
        self,
        frame: FrameView,
        view: MapView,
        solve: PoseSolve | None,
        path: TrackingPath,
        reason: str,
        T: np.ndarray | None = None,
    ) -> TrackResult:
        """TrackResult with the correspondences of the final pose: those the plane pose was
        solved from (outliers dropped), or, when a fallback moved the pose to T, those
        under T."""
        if T is None:
            assert solve is not None, "a pose without a fallback comes from the planes"
            T_final, assoc = solve.T, solve.association
        else:
            T_final, assoc = T, self._associate(frame, view, T)
        cfg = self.config
        _, allowed = plane_association_cost(
            view.normals,
            view.d,
            frame.normals,
            frame.d,
            T_final,
            np.radians(cfg.max_angle_deg),
            cfg.max_offset_m,
            gate=self._size_gate(frame, view),
        )
        return TrackResult(
            T_world_cam=T_final,
            path=path,
            reason=reason,
            plane_pairs=[
                (int(frame.plane_ids[i]), int(view.plane_ids[j])) for i, j in assoc.planes
            ],
            corner_pairs=[(int(i), int(view.corner_ids[j])) for i, j in assoc.corners],
            new_planes=int(np.count_nonzero(~allowed.any(axis=1))),
        )
