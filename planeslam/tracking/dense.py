"""The dense fallback of tracking: RGB-D odometry, then ICP, against the previous frame.

Runs right after a tracked frame only (across a loss the prediction is stale), when
nothing near the prediction fits the map. Each result is accepted by its own evidence:
the frame's depth, moved by it, lands on the previous frame's (`agrees`), and its
colours do not contradict the previous frame's (`colour_check`). The previous frame (its
pose, cloud, colour and depth) is kept here.

Frames: clouds in their camera frame; every pose is T_world_cam (4, 4).
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from planeslam.core.camera import CameraConfig, nearest_pixels
from planeslam.core.errors import GeometryError
from planeslam.core.geometry import invert_pose, orthonormalize_pose, transform_points
from planeslam.frontend.cloud import sampled_points
from planeslam.tracking.config import TrackingConfig
from planeslam.tracking.estimator import Primitive
from planeslam.tracking.hypotheses import pose_difference
from planeslam.tracking.registration import RegistrationResult, refine_icp
from planeslam.tracking.sweep import (
    LastFrame,
    landing_cost,
    lands_better,
    sweep_free_motion,
    sweep_free_translation,
)

if TYPE_CHECKING:
    from planeslam.frontend.pipeline import FrameObservation

logger = logging.getLogger(__name__)

RgbdPair = tuple[np.ndarray, np.ndarray]
"""(rgb (H, W, 3) uint8, depth (H, W) float [m]) of one frame."""


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


COLOUR_BLUR_PX = 2.0
"""Gaussian sigma [px] of the blur applied before colours are compared."""
COLOUR_MATCH_SHARE = 0.5
"""A dense pose's colours match the previous frame's when their median grey difference is
within this share of the frame's texture contrast (median absolute deviation)."""
COLOUR_MIN_CONTRAST = 8.0
"""Grey levels of contrast below which colours can neither confirm nor contradict a pose
(sensor noise and shading differences stay below it)."""


def colour_verdict(measured: tuple[float, float] | None) -> ColourCheck:
    """What a (median grey difference, texture contrast) pair in grey levels says
    (`DenseFallback.colour_difference`; None: UNKNOWN): the difference against
    COLOUR_MATCH_SHARE of the contrast and COLOUR_MIN_CONTRAST."""
    if measured is None:
        return ColourCheck.UNKNOWN
    difference, contrast = measured
    if difference > max(COLOUR_MATCH_SHARE * contrast, COLOUR_MIN_CONTRAST):
        return ColourCheck.CONTRADICTS
    if contrast < COLOUR_MIN_CONTRAST:
        return ColourCheck.PLAIN
    if difference <= COLOUR_MATCH_SHARE * contrast:
        return ColourCheck.CONFIRMS
    return ColourCheck.UNKNOWN


@dataclass(frozen=True)
class DensePose:
    """A pose the dense fallback registered."""

    T: np.ndarray
    """(4, 4) T_world_cam."""
    filled_by: Primitive
    """ODOMETRY or ICP."""


class DenseFallback:
    """RGB-D odometry and ICP against the previous tracked frame, which it keeps."""

    def __init__(self, config: TrackingConfig, odometry=None, camera: CameraConfig | None = None):
        """`odometry`: an `odometry.RgbdOdometry`, or None; `camera` enables the checks
        that project one frame into the other."""
        self.config = config
        self.odometry = odometry
        self.camera = camera
        self.previous_cloud: np.ndarray | None = None
        """(H, W, 3) organised cloud of the last tracked frame (ICP fallback)."""
        self.previous_rgbd: RgbdPair | None = None
        self.previous_pose: np.ndarray | None = None
        """(4, 4) T_world_cam of the last tracked frame."""
        self.previous_stamp = -np.inf
        """Timestamp of the last tracked frame [s]."""
        self._greys: list[tuple[np.ndarray, np.ndarray]] = []
        """(rgb, its `smooth_grey`) of the last two images compared by colour."""

    def remember(
        self,
        timestamp: float,
        cloud: np.ndarray | None,
        rgbd: RgbdPair | None,
        T_world_cam: np.ndarray,
    ) -> None:
        """The last tracked frame: its time [s], cloud, images and pose (4, 4)."""
        self.previous_cloud, self.previous_rgbd = cloud, rgbd
        self.previous_pose = np.asarray(T_world_cam, dtype=np.float64)
        self.previous_stamp = timestamp

    def inputs(
        self, observation: FrameObservation, rgb: np.ndarray | None, depth_m: np.ndarray | None
    ) -> tuple[np.ndarray | None, RgbdPair | None]:
        """The frame's organised cloud when ICP may run and its (rgb, depth_m) pair when
        RGB-D odometry may (None where the config or the inputs rule them out)."""
        cfg = self.config
        cloud = observation.cloud if cfg.icp else None
        rgbd = None
        if cfg.rgbd_odometry and self.odometry is not None and rgb is not None:
            rgbd = (rgb, depth_m) if depth_m is not None else None
        return cloud, rgbd

    def correct(self, correction: np.ndarray) -> None:
        """The backend moved the map by `correction` (4, 4): the previous pose moves too."""
        if self.previous_pose is not None:
            self.previous_pose = orthonormalize_pose(correction @ self.previous_pose)

    def register(
        self,
        starts: list[np.ndarray],
        cloud: np.ndarray | None,
        rgbd: RgbdPair | None,
        reasons: list[str],
        slides: Callable[[], bool] = lambda: False,
        keypoints_agree: Callable[[np.ndarray], bool] = lambda T: False,
        T_prior: np.ndarray | None = None,
    ) -> DensePose | None:
        """RGB-D odometry, then ICP, against the previous frame from each of the (4, 4)
        `starts` (one equal to an earlier start is skipped): per start the first result
        taken (`_acceptable`); of those, the one that lands best on the previous frame
        (`sweep.landing_cost`: depth and grey residuals beyond the noise; a later start must
        land clearly better, `sweep.lands_better`), or None. With `T_prior` (4, 4), of the
        results that land about as well as that one (none clearly better), the one nearest
        T_prior: where the images cannot tell them apart, the motion decides."""
        methods: list[tuple[Primitive, Callable[[np.ndarray], np.ndarray | None]]]
        methods = [(Primitive.ODOMETRY, lambda T0: self._rgbd(rgbd, T0))]
        if cloud is not None:
            methods.append((Primitive.ICP, lambda T0: self._icp(cloud, T0)))
        landed: list[tuple[float, DensePose]] = []
        best: tuple[float, DensePose] | None = None
        for k, T_start in enumerate(starts):
            if any(np.array_equal(T_start, earlier) for earlier in starts[:k]):
                continue
            for kind, method in methods:
                T = method(T_start)
                if T is None:
                    continue
                if self._acceptable(kind, T, cloud, rgbd, reasons, slides, keypoints_agree):
                    cost = self._landing_cost(cloud, rgbd, T)
                    landed.append((cost, DensePose(T, kind)))
                    if best is None or lands_better(cost, best[0]):
                        best = landed[-1]
                    break
        if best is None:
            return None
        if T_prior is None:
            return best[1]
        tied = [pose for cost, pose in landed if not lands_better(best[0], cost)]
        return min(tied, key=lambda pose: pose_difference(T_prior, pose.T))

    def unplaced_starts(self, T_pred: np.ndarray) -> list[np.ndarray]:
        """Starts (4, 4) for a frame no plane placed: the prediction T_pred (4, 4), then
        the last pose turned as predicted but not moved, then the last pose: the
        constant-velocity prediction overshoots where a robot stops to turn in place or
        the camera stops."""
        if self.previous_pose is None:
            return [T_pred]
        turned = self.previous_pose.copy()
        turned[:3, :3] = T_pred[:3, :3]
        return [T_pred, turned, self.previous_pose]

    def with_swept(
        self,
        starts: list[np.ndarray],
        registration: RegistrationResult,
        cloud: np.ndarray | None,
        rgbd: RgbdPair | None,
    ) -> list[np.ndarray]:
        """`starts` (4, 4 each; the first with the free directions at the last pose) with
        the sweep's poses along the directions `registration` left free: one free direction
        with the rotation fixed is a line whose distinct best goes first
        (`sweep_free_translation`); a free turn, or two free directions, a grid whose basins
        go last (`sweep_free_motion`), so they win only by landing clearly better (on a
        bare floor any of them lands as well as the last pose). Unchanged without a cloud."""
        if not starts or cloud is None or self.previous_cloud is None or self.camera is None:
            return starts
        grey, last = self._landing_inputs(rgbd)
        axes = registration.unobservable_rotation_axes
        directions = registration.unobservable_translation_dirs
        if not len(axes) and len(directions) == 1:
            found = sweep_free_translation(starts[0], directions[0], cloud, grey, last, self.camera)
            return starts if found is None else [found, *starts]
        return [
            *starts,
            *sweep_free_motion(starts[0], axes, directions, cloud, grey, last, self.camera),
        ]

    def _landing_inputs(self, rgbd: RgbdPair | None) -> tuple[np.ndarray | None, LastFrame]:
        """This frame's grey levels (None without both frames' colours) and the previous
        frame to land it on, for the sweep's cost."""
        assert self.previous_pose is not None and self.previous_cloud is not None
        grey = grey_prev = None
        if rgbd is not None and self.previous_rgbd is not None:
            grey, grey_prev = self._grey(rgbd[0]), self._grey(self.previous_rgbd[0])
        return grey, LastFrame(self.previous_pose, self.previous_cloud[..., 2], grey_prev)

    def _landing_cost(
        self, cloud: np.ndarray | None, rgbd: RgbdPair | None, T_world_cam: np.ndarray
    ) -> float:
        """`sweep.landing_cost` of this frame at T_world_cam (4, 4), every `icp_stride`-th
        pixel; inf without a cloud, the previous frame's or a camera."""
        if cloud is None or self.previous_cloud is None or self.camera is None:
            return float("inf")
        grey, last = self._landing_inputs(rgbd)
        return landing_cost(T_world_cam, cloud, grey, last, self.camera, self.config.icp_stride)

    def _acceptable(
        self,
        kind: Primitive,
        T: np.ndarray,
        cloud: np.ndarray | None,
        rgbd: RgbdPair | None,
        reasons: list[str],
        slides: Callable[[], bool],
        keypoints_agree: Callable[[np.ndarray], bool],
    ) -> bool:
        """Whether the dense pose T (4, 4) by `kind` overlaps the previous frame's depth
        and its colours do not contradict it. When the frame `slides()` (its depth mostly on
        parallel planes, which any slide along them still overlaps) and the colours cannot
        tell, `keypoints_agree(T)` must hold. Why a result was refused is appended to
        `reasons`."""
        if not self.agrees(cloud, T):
            reasons.append(f"{kind.value} result does not overlap the previous frame")
            return False
        measured = self.colour_difference(cloud, rgbd, T)
        colours = colour_verdict(measured)
        if colours is ColourCheck.CONTRADICTS:
            reasons.append(f"{kind.value} result: the colours contradict the previous frame")
            return False
        if colours is ColourCheck.UNKNOWN and slides() and not keypoints_agree(T):
            reasons.append(
                f"{kind.value} result unconfirmed: the frame's depth is parallel planes "
                "and its keypoints do not agree"
            )
            return False
        return True

    def _points(self, cloud: np.ndarray) -> np.ndarray:
        """(P, 3) float64 valid camera-frame points of an (H, W, 3) organised cloud for ICP,
        every icp_stride-th pixel in each direction."""
        xyz, _ = sampled_points(cloud, self.config.icp_stride)
        return np.ascontiguousarray(xyz[xyz[:, 2] < self.config.max_depth_m], dtype=np.float64)

    def _icp(self, cloud: np.ndarray, T_world_cam_init: np.ndarray) -> np.ndarray | None:
        """T_world_cam by ICP of this frame's (H, W, 3) organised cloud against the previous
        frame's, or None. The point sets are only built here: ICP is a rare fallback."""
        cfg = self.config
        if self.previous_cloud is None:
            return None
        source, target = self._points(cloud), self._points(self.previous_cloud)
        if len(source) < 100 or len(target) < 100:
            return None
        assert self.previous_pose is not None, "set with the previous cloud"
        T_prev_world = invert_pose(self.previous_pose)
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
        return self.previous_pose @ icp.T

    def agrees(self, cloud: np.ndarray | None, T_world_cam: np.ndarray) -> bool:
        """Whether this frame's (H, W, 3) cloud, moved by T_world_cam (4, 4) into the
        previous frame, lands on the previous frame's depth: at least `icp_min_fitness` of
        the points that project into its image within `icp_max_distance_m` of its depth
        there. True when it cannot be checked (no camera, no clouds)."""
        if cloud is None or self.previous_cloud is None or self.camera is None:
            return True
        assert self.previous_pose is not None, "set with the previous cloud"
        cam, cfg = self.camera, self.config
        T = invert_pose(self.previous_pose) @ T_world_cam
        p = transform_points(T, self._points(cloud))
        u, v, inside = nearest_pixels(cam, p)
        z_prev = self.previous_cloud[v[inside], u[inside], 2]
        seen = z_prev > 0
        if np.count_nonzero(seen) < 100:
            return False
        close = np.abs(z_prev[seen] - p[inside][seen, 2]) <= cfg.icp_max_distance_m
        return bool(np.mean(close) >= cfg.icp_min_fitness)

    def colour_check(
        self, cloud: np.ndarray | None, rgbd: RgbdPair | None, T_world_cam: np.ndarray
    ) -> ColourCheck:
        """Whether this frame's colours, moved by T_world_cam (4, 4) into the previous frame,
        match the colours there where the depths agree (`colour_verdict` of
        `colour_difference`)."""
        return colour_verdict(self.colour_difference(cloud, rgbd, T_world_cam))

    def colour_difference(
        self, cloud: np.ndarray | None, rgbd: RgbdPair | None, T_world_cam: np.ndarray
    ) -> tuple[float, float] | None:
        """(median grey difference, texture contrast) in grey levels of this frame's colours
        moved by T_world_cam (4, 4) into the previous frame, where the depths agree (every
        `icp_stride`-th pixel, at least 100); None without colours or overlap."""
        if cloud is None or rgbd is None or self.previous_rgbd is None or self.camera is None:
            return None
        assert self.previous_pose is not None, "set with the previous frame"
        xyz, grey = sampled_points(cloud, self.config.icp_stride, self._grey(rgbd[0]))
        p = transform_points(invert_pose(self.previous_pose) @ T_world_cam, xyz)
        u, v, inside = nearest_pixels(self.camera, p)
        rgb_prev, depth_prev = self.previous_rgbd
        z_prev = depth_prev[v[inside], u[inside]]
        shared = (z_prev > 0) & (np.abs(z_prev - p[inside, 2]) <= self.config.icp_max_distance_m)
        if np.count_nonzero(shared) < 100:
            return None
        g_cur = grey[inside][shared]
        g_prev = self._grey(rgb_prev)[v[inside][shared], u[inside][shared]]
        difference = float(np.median(np.abs(g_prev - g_cur)))
        return difference, float(np.median(np.abs(g_cur - np.median(g_cur))))

    def _grey(self, rgb: np.ndarray) -> np.ndarray:
        """`smooth_grey(rgb)`, computed once per image: a frame's colours are compared for
        each fallback and relocalisation, and again as the previous frame's."""
        for image, grey in self._greys:
            if image is rgb:
                return grey
        grey = smooth_grey(rgb)
        self._greys = [*self._greys[-1:], (rgb, grey)]
        return grey

    def _rgbd(self, rgbd: RgbdPair | None, T_world_cam_init: np.ndarray) -> np.ndarray | None:
        """T_world_cam by RGB-D odometry against the previous frame, or None. `rgbd` and the
        previous frame are (rgb, depth_m) pairs, turned into Open3D images only here."""
        if self.odometry is None or rgbd is None or self.previous_rgbd is None:
            return None
        assert self.previous_pose is not None, "set with the previous frame"
        T_prev_cur = self.odometry.motion(
            self.odometry.image(*rgbd),
            self.odometry.image(*self.previous_rgbd),
            invert_pose(self.previous_pose) @ T_world_cam_init,
        )
        return None if T_prev_cur is None else self.previous_pose @ T_prev_cur


def smooth_grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an (H, W, 3) uint8 image, blurred by COLOUR_BLUR_PX:
    colours compared across a wide baseline then differ by the surfaces' colours, not by
    which pixel of a fine texture each sample hit."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return cv2.GaussianBlur(grey, (0, 0), COLOUR_BLUR_PX)


def parallel_share(observation: FrameObservation, max_angle_deg: float = 10.0) -> float:
    """Share of the frame's valid depth pixels on its planes when they are all parallel
    (within max_angle_deg, either side), else 0. When it reaches `icp_min_fitness`, a pose
    slid along those planes or turned about their normal still lands that share of the
    frame on the previous frame's depth, and the planes fix neither, so the overlap check
    (`agrees`) could not reject it: a dense pose of such a frame must also agree with its
    keypoints."""
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
