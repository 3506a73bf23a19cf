"""Keypoints with depth: the point primitive of tracking and relocalisation.

ORB keypoints (OpenCV) of the colour image whose pixel has valid depth become 3-D
points in the camera frame (read from the front end's organised cloud, so they share its
units, undistortion and depth conventions). Pixels on a depth discontinuity (the depth
in a small window varies by more than a fraction of the depth) are left out: a corner
in the colour image often lies on an object's silhouette, where a pixel's depth belongs
to either side.

Noise model: a point at depth z has sigma(z) = a + b z^2 along its viewing ray (the
sensor's depth noise, `DepthNoiseConfig`) and z * sigma_px / f across it, plus an
isotropic floor (colour-to-depth registration, keypoint localisation on blur). The
covariances are (N, 3, 3), camera frame [m^2].

`KeypointMap` keeps the keypoints of the map's keyframes with their poses (world frame
through T_world_cam, moved when the backend corrects a keyframe), computes a keyframe's
keypoints only when a later frame needs them (a keyframe's images are kept for the
`window` most recent keyframes), and answers two questions: which keypoints of recent
keyframes match a frame's (`match_recent`), and which keyframes anywhere in the map share
most descriptors with it (`vote`, for relocalisation). `ransac_pose` finds the pose of a
frame from 3-D point matches (3-point samples, Kabsch, no prior).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from planeslam.core.camera import CameraConfig, DepthNoiseConfig
from planeslam.core.geometry import invert_pose, transform_points
from planeslam.tracking.config import PointConfig
from planeslam.tracking.hypotheses import rotation_kabsch

logger = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32
"""ORB descriptors are 256 bits."""


@dataclass(frozen=True)
class Keypoints:
    """Keypoints with depth of one frame, camera frame."""

    pixels: np.ndarray
    """(N, 2) float32 pixel coordinates (u, v)."""
    points_cam: np.ndarray
    """(N, 3) float64 points [m], camera frame."""
    descriptors: np.ndarray
    """(N, 32) uint8 ORB descriptors (rows: strongest corner response first)."""
    covariances: np.ndarray = field(repr=False)
    """(N, 3, 3) point covariances [m^2], camera frame."""

    def __len__(self) -> int:
        return len(self.points_cam)

    @classmethod
    def empty(cls) -> Keypoints:
        return cls(
            np.zeros((0, 2), np.float32),
            np.zeros((0, 3)),
            np.zeros((0, DESCRIPTOR_BYTES), np.uint8),
            np.zeros((0, 3, 3)),
        )


def point_covariances(
    points_cam: np.ndarray, sensor: DepthNoiseConfig, focal_px: float, cfg: PointConfig
) -> np.ndarray:
    """(N, 3, 3) covariances [m^2] of (N, 3) camera-frame points: sigma(z) along the ray,
    z * sigma_px / f across it, plus the isotropic floor `cfg.sigma_floor_m`."""
    z = points_cam[:, 2]
    ray = points_cam / np.linalg.norm(points_cam, axis=1, keepdims=True)
    along = sensor.sigma_m(z) / np.maximum(ray[:, 2], 0.1)  # depth noise measured along z
    across = z * cfg.sigma_px / focal_px
    outer = np.einsum("ni,nj->nij", ray, ray)
    cov = (across**2)[:, None, None] * np.eye(3) + (along**2 - across**2)[:, None, None] * outer
    return cov + cfg.sigma_floor_m**2 * np.eye(3)


class KeypointDetector:
    """ORB keypoints with depth for one camera (`detect`)."""

    def __init__(self, camera: CameraConfig, sensor: DepthNoiseConfig, config: PointConfig):
        import cv2

        self.camera, self.sensor, self.config = camera, sensor, config
        self._orb = cv2.ORB.create(
            nfeatures=config.max_keypoints,
            scaleFactor=1.2,
            nlevels=config.pyramid_levels,
            fastThreshold=config.fast_threshold,
        )
        self._window = np.ones((5, 5), np.uint8)

    def detect(self, rgb: np.ndarray, cloud: np.ndarray) -> Keypoints:
        """Keypoints of an (H, W, 3) uint8 RGB image whose pixel in the (H, W, 3) organised
        cloud (camera frame [m], invalid (0, 0, 0)) has a valid point off depth edges."""
        import cv2

        cfg = self.config
        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        keypoints, descriptors = self._orb.detectAndCompute(gray, None)
        if descriptors is None or not len(keypoints):
            return Keypoints.empty()
        order = np.argsort([-k.response for k in keypoints], kind="stable")  # strongest first
        keypoints, descriptors = [keypoints[i] for i in order], descriptors[order]
        uv = np.array([k.pt for k in keypoints], dtype=np.float32)
        h, w = gray.shape
        col = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
        row = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
        z_img = np.ascontiguousarray(cloud[..., 2], dtype=np.float32)
        z_far = np.where(z_img > 0, z_img, np.float32(1e3))
        spread = cv2.dilate(z_img, self._window) - cv2.erode(z_far, self._window)
        points = cloud[row, col].astype(np.float64)
        z = points[:, 2]
        keep = (
            (z > 0)
            & (z < cfg.max_depth_m)
            & np.all(np.isfinite(points), axis=1)
            & (spread[row, col] < cfg.max_depth_step * z)
        )
        points = points[keep]
        return Keypoints(
            pixels=uv[keep],
            points_cam=points,
            descriptors=np.ascontiguousarray(descriptors[keep]),
            covariances=point_covariances(points, self.sensor, self.camera.fx, cfg),
        )


@dataclass(frozen=True)
class PointMatches:
    """Matches of a frame's keypoints with keyframe keypoints, the latter in the world frame."""

    observed: np.ndarray
    """(M,) row of each match in the frame's `Keypoints`."""
    points_world: np.ndarray
    """(M, 3) the matched keyframe points, world frame [m]."""
    covariances_world: np.ndarray = field(repr=False)
    """(M, 3, 3) their covariances, world frame [m^2]."""
    keyframes: np.ndarray = field(repr=False)
    """(M,) frame index of the keyframe each match came from."""

    def __len__(self) -> int:
        return len(self.observed)

    @classmethod
    def empty(cls) -> PointMatches:
        return cls(
            np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)
        )

    @classmethod
    def concatenate(cls, parts: list[PointMatches]) -> PointMatches:
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.observed for p in parts]),
            np.concatenate([p.points_world for p in parts]),
            np.concatenate([p.covariances_world for p in parts]),
            np.concatenate([p.keyframes for p in parts]),
        )

    def moved(self, T_new_world: np.ndarray) -> PointMatches:
        """The same matches with the keyframe points in another frame, (4, 4) T_new_world."""
        R = T_new_world[:3, :3]
        return PointMatches(
            observed=self.observed,
            points_world=transform_points(T_new_world, self.points_world),
            covariances_world=np.einsum("ij,njk,lk->nil", R, self.covariances_world, R),
            keyframes=self.keyframes,
        )


def match_descriptors(query: np.ndarray, train: np.ndarray, ratio: float) -> np.ndarray:
    """(M, 2) (query row, train row) pairs of (Q, 32) and (T, 32) uint8 ORB descriptors:
    nearest neighbours by Hamming distance that pass Lowe's ratio test and are mutual
    best matches (a train descriptor is used once)."""
    import cv2

    if len(query) < 2 or len(train) < 2:
        return np.zeros((0, 2), np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    rows = [
        (m[0].queryIdx, m[0].trainIdx, m[0].distance)
        for m in matcher.knnMatch(query, train, k=2)
        if len(m) == 2 and m[0].distance < ratio * m[1].distance
    ]
    if not rows:
        return np.zeros((0, 2), np.int64)
    pairs = np.array(rows, dtype=np.float64)
    # Mutual: for every train row keep the query with the smallest distance.
    order = np.lexsort((pairs[:, 2], pairs[:, 1]))
    pairs = pairs[order]
    first = np.r_[True, pairs[1:, 1] != pairs[:-1, 1]]
    return pairs[first][:, :2].astype(np.int64)


def guided_pairs(
    keypoints: Keypoints,
    ref: Keypoints,
    T_cam_ref: np.ndarray,
    camera: CameraConfig,
    cfg: PointConfig,
) -> np.ndarray:
    """(M, 2) (keypoints row, ref row) pairs found by projection (ORB-SLAM's search by
    projection): each ref point (ref camera frame), moved by T_cam_ref (4, 4), is projected
    into the frame and matched with the frame keypoint of nearest descriptor within
    `guided_radius_px` of it (0: none), when that passes Lowe's ratio test against the
    other keypoints there and lies within `vote_max_distance` bits; a frame keypoint is
    used once (the nearest descriptor). Keypoint pixels are the colour image's,
    unrectified: the radius absorbs a lens's few pixels as well as the pose's error."""
    from scipy.spatial import cKDTree

    if not len(keypoints) or not len(ref) or cfg.guided_radius_px <= 0:
        return np.zeros((0, 2), np.int64)
    p = transform_points(T_cam_ref, ref.points_cam)
    front = np.flatnonzero(p[:, 2] > 0.1)
    uv = np.column_stack(
        [
            camera.fx * p[front, 0] / p[front, 2] + camera.cx,
            camera.fy * p[front, 1] / p[front, 2] + camera.cy,
        ]
    )
    k = min(8, len(keypoints))
    _, near = cKDTree(keypoints.pixels).query(uv, k=k, distance_upper_bound=cfg.guided_radius_px)
    near = near.reshape(len(front), k)
    found = near < len(keypoints)  # missing neighbours come back as len(keypoints)
    safe = np.where(found, near, 0)
    xor = keypoints.descriptors[safe] ^ ref.descriptors[front][:, None, :]
    bits = _POPCOUNT[xor].sum(axis=2, dtype=np.int64)
    none = np.full((len(front), 1), 1 << 16)  # a second candidate where there is one only
    bits = np.hstack([np.where(found, bits, none), none])
    order = np.argsort(bits, axis=1, kind="stable")
    best, second = np.take_along_axis(bits, order[:, :2], axis=1).T
    ok = (best <= cfg.vote_max_distance) & (best < cfg.match_ratio * second)
    nearest = np.take_along_axis(safe, np.minimum(order[:, :1], k - 1), axis=1)[:, 0]
    rows = np.column_stack([nearest, front, best])[ok]
    # Mutual: for every frame keypoint keep the ref point of the nearest descriptor.
    rows = rows[np.lexsort((rows[:, 2], rows[:, 0]))]
    first = np.r_[True, rows[1:, 0] != rows[:-1, 0]] if len(rows) else np.zeros(0, bool)
    return rows[first][:, :2].astype(np.int64)


_POPCOUNT = np.array([bin(b).count("1") for b in range(256)], dtype=np.uint8)
"""Set bits of each byte value (Hamming distances of ORB descriptors)."""


@dataclass
class _Keyframe:
    index: int
    T_world_cam: np.ndarray
    keypoints: Keypoints | None = None
    images: tuple[np.ndarray, np.ndarray] | None = None
    """(rgb, cloud) until the keypoints are computed or the keyframe leaves the window."""


class KeypointMap:
    """Keypoints of the map's keyframes, world frame through each keyframe's pose."""

    def __init__(self, detector: KeypointDetector, every_keyframe: bool = False) -> None:
        """With `every_keyframe`, the keypoints of every keyframe are detected as it leaves
        the window (so a later search can relocalise anywhere in the map: a map made to
        relocalise in); without, only of the keyframes a frame needed (no cost while planes
        suffice)."""
        self.detector = detector
        self.every_keyframe = every_keyframe
        self._keyframes: OrderedDict[int, _Keyframe] = OrderedDict()
        self._stack: tuple[np.ndarray, np.ndarray] | None = None
        """(descriptors (D, 32), keyframe index per row) of every keyframe with keypoints,
        rebuilt after a change (for `vote`)."""

    def __len__(self) -> int:
        return len(self._keyframes)

    def add(
        self,
        index: int,
        T_world_cam: np.ndarray,
        rgb: np.ndarray | None,
        cloud: np.ndarray | None,
        keypoints: Keypoints | None = None,
    ) -> None:
        """A new keyframe at T_world_cam (4, 4): its keypoints if already computed, else its
        images (not copied) to compute them when needed; neither without colour."""
        images = None if keypoints is not None or rgb is None or cloud is None else (rgb, cloud)
        self._keyframes[index] = _Keyframe(index, np.array(T_world_cam), keypoints, images)
        window = self.detector.config.window
        for kf in list(self._keyframes.values())[:-window]:
            if kf.images is not None and self.every_keyframe:
                self._keypoints(kf)
            kf.images = None  # out of the window: its images are released
        if keypoints is not None:
            self._stack = None

    def move(self, index: int, T_world_cam: np.ndarray) -> None:
        """The keyframe `index` has a new pose (4, 4) (the backend's correction)."""
        kf = self._keyframes.get(index)
        if kf is not None:
            kf.T_world_cam = np.array(T_world_cam)

    def _keypoints(self, kf: _Keyframe) -> Keypoints | None:
        if kf.keypoints is None and kf.images is not None:
            kf.keypoints = self.detector.detect(*kf.images)
            kf.images = None
            self._stack = None
        return kf.keypoints

    def recent(self, count: int) -> list[int]:
        """Indices of the `count` most recent keyframes that have or can have keypoints."""
        usable = [i for i, kf in self._keyframes.items() if kf.keypoints or kf.images]
        return usable[-count:]

    def matches(
        self, keypoints: Keypoints, indices: list[int], T_guide: np.ndarray | None = None
    ) -> PointMatches:
        """Matches of `keypoints` with the keyframes `indices` (each matched on its own, so
        a point seen by several keyframes matches each), world frame. With a pose T_guide
        (4, 4) T_world_cam, also the matches by projection under it (`guided_pairs`): a
        repetitive texture's nearest descriptors may lie a period away; under a pose near
        the truth, projection finds the copy there."""
        cfg = self.detector.config
        parts = []
        for index in indices:
            kf = self._keyframes[index]
            ref = self._keypoints(kf)
            if ref is None or not len(ref):
                continue
            pairs = match_descriptors(keypoints.descriptors, ref.descriptors, cfg.match_ratio)
            if T_guide is not None:
                T_cam_ref = invert_pose(T_guide) @ kf.T_world_cam
                guided = guided_pairs(keypoints, ref, T_cam_ref, self.detector.camera, cfg)
                pairs = np.unique(np.concatenate([pairs, guided]), axis=0)
            if not len(pairs):
                continue
            rows = pairs[:, 1]
            in_keyframe = PointMatches(
                observed=pairs[:, 0],
                points_world=ref.points_cam[rows],
                covariances_world=ref.covariances[rows],
                keyframes=np.full(len(pairs), index, np.int64),
            )
            parts.append(in_keyframe.moved(kf.T_world_cam))
        return PointMatches.concatenate(parts)

    def vote(self, keypoints: Keypoints, count: int) -> list[int]:
        """The `count` keyframes anywhere in the map holding the most nearest neighbours of
        `keypoints`' descriptors within `vote_max_distance` bits, best first."""
        import cv2

        stack = self._descriptor_stack()
        if stack is None or not len(keypoints):
            return []
        descriptors, owner = stack
        matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(keypoints.descriptors, descriptors)
        rows = [m.trainIdx for m in matches if m.distance <= self.detector.config.vote_max_distance]
        if not rows:
            return []
        keyframes = np.unique(owner)
        votes = np.bincount(np.searchsorted(keyframes, owner[rows]))
        order = np.argsort(-votes, kind="stable")[:count]
        return [int(keyframes[k]) for k in order if votes[k] > 0]

    def _descriptor_stack(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self._stack is None:
            parts = [(i, kf.keypoints) for i, kf in self._keyframes.items() if kf.keypoints]
            if not parts:
                return None
            n = self.detector.config.vote_descriptors  # the strongest of each keyframe
            self._stack = (
                np.concatenate([k.descriptors[:n] for _, k in parts]),
                np.concatenate([np.full(min(len(k), n), i, np.int64) for i, k in parts]),
            )
        return self._stack


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched rigid fit: (S, k, 3) point sets -> R (S, 3, 3), t (S, 3) with dst = R src + t."""
    c_src, c_dst = src.mean(axis=1), dst.mean(axis=1)
    R = rotation_kabsch(src - c_src[:, None], dst - c_dst[:, None])
    return R, c_dst - np.einsum("sij,sj->si", R, c_src)


@dataclass(frozen=True)
class PointPose:
    """A pose from point matches alone, and which matches agree with it."""

    T_world_cam: np.ndarray
    """(4, 4)"""
    inliers: np.ndarray
    """(M,) bool over the matches."""

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.inliers))


def point_residuals(T_world_cam: np.ndarray, p_cam: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """(M,) distances [m] between (M, 3) camera points moved by T_world_cam and (M, 3)
    world points."""
    return np.linalg.norm(transform_points(T_world_cam, p_cam) - p_world, axis=1)


def inlier_threshold(p_cam: np.ndarray, cfg: PointConfig, sensor: DepthNoiseConfig) -> np.ndarray:
    """(M,) distance [m] within which a match of camera point p_cam (M, 3) agrees with a
    pose: `inlier_sigmas` times the depth noise of both ends (taken at the same depth),
    plus the floor."""
    sigma = np.hypot(np.sqrt(2.0) * sensor.sigma_m(p_cam[:, 2]), cfg.sigma_floor_m)
    return cfg.inlier_sigmas * sigma + cfg.inlier_margin_m


def ransac_pose(
    p_cam: np.ndarray,
    p_world: np.ndarray,
    threshold_m: np.ndarray,
    iterations: int,
    rng: np.random.Generator,
    min_inliers: int,
) -> PointPose | None:
    """T_world_cam from (M, 3) camera / world point matches: `iterations` random 3-point
    samples (far from collinear), each a Kabsch fit scored by the matches within their
    (M,) thresholds [m]; the best refitted on its inliers (twice). None with fewer than
    `min_inliers` agreeing matches."""
    m = len(p_cam)
    if m < max(3, min_inliers):
        return None
    samples = np.array([rng.choice(m, 3, replace=False) for _ in range(iterations)])
    a, b = p_cam[samples], p_world[samples]  # (S, 3, 3)
    spread = np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
    a, b = a[spread > 1e-3], b[spread > 1e-3]  # twice the triangle's area [m^2]
    if not len(a):
        return None
    R, t = _kabsch(a, b)
    moved = np.einsum("sij,mj->smi", R, p_cam) + t[:, None, :]
    inliers = np.linalg.norm(moved - p_world[None], axis=2) < threshold_m[None, :]
    best = inliers[np.argmax(inliers.sum(axis=1))]
    for _ in range(2):
        if np.count_nonzero(best) < 3:
            return None
        R1, t1 = _kabsch(p_cam[best][None], p_world[best][None])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R1[0], t1[0]
        best = point_residuals(T, p_cam, p_world) < threshold_m
    if np.count_nonzero(best) < min_inliers:
        return None
    return PointPose(T, best)


class LazyKeypoints:
    """A frame's keypoints, detected on first use."""

    def __init__(self, detect: Callable[[], Keypoints] | None) -> None:
        self._detect = detect
        self.value: Keypoints | None = None

    def get(self) -> Keypoints | None:
        if self.value is None and self._detect is not None:
            self.value = self._detect()
            self._detect = None
        return self.value


NO_KEYPOINTS = LazyKeypoints(None)
