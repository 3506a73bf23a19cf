"""Keypoints with depth: detection off depth edges, mutual ratio-test matching, the point
RANSAC, the keyframe store (lazy detection, corrections, votes) and two rendered views
15 degrees apart registered from keypoints alone."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import assert_pose_close
from test_tracking import camera_pose, map_view, observe

from planeslam.core.camera import CameraConfig, DepthNoiseConfig, PixelRays
from planeslam.core.geometry import invert_pose, pose_from_quat
from planeslam.frontend.cloud import organized_cloud
from planeslam.tracking.config import PointConfig, TrackingConfig
from planeslam.tracking.keypoints import (
    KeypointDetector,
    KeypointMap,
    inlier_threshold,
    match_descriptors,
    ransac_pose,
)
from planeslam.tracking.relocalise import relocalisation_candidates

pytestmark = pytest.mark.unit

CAMERA = CameraConfig()
SENSOR = DepthNoiseConfig()


def textured(rng: np.random.Generator) -> np.ndarray:
    """(480, 640, 3) uint8 blobs of random grey levels: plenty of ORB corners."""
    import cv2

    small = rng.integers(0, 255, (60, 80), dtype=np.uint8)
    grey = cv2.resize(small, (640, 480), interpolation=cv2.INTER_NEAREST)
    return np.repeat(grey[..., None], 3, axis=2)


def cloud_of(depth_m: np.ndarray) -> np.ndarray:
    return organized_cloud(depth_m.astype(np.float32), PixelRays.for_camera(CAMERA), 8.0)


def test_detected_points_lie_on_their_rays_and_avoid_depth_edges(rng: np.random.Generator):
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:, 320:] = 3.0  # a step: pixels beside it have no single depth
    found = KeypointDetector(CAMERA, SENSOR, PointConfig()).detect(textured(rng), cloud_of(depth))
    assert len(found) > 200
    u = found.pixels[:, 0]
    z = found.points_cam[:, 2]
    assert np.all(np.abs(u - 320) > 2)
    np.testing.assert_allclose(z, np.where(np.rint(u) >= 320, 3.0, 2.0), atol=1e-6)
    # the point is the pixel's ray at its depth (pixels rounded to the nearest centre)
    np.testing.assert_allclose(found.points_cam[:, 0], (np.rint(u) - CAMERA.cx) / CAMERA.fx * z)
    assert found.covariances.shape == (len(found), 3, 3)
    along = np.einsum("ni,nij,nj->n", found.points_cam, found.covariances, found.points_cam)
    across = found.covariances[:, 0, 0]
    assert np.all(along / np.sum(found.points_cam**2, axis=1) > across)  # depth noise dominates


def test_matching_is_mutual_and_passes_the_ratio_test(rng: np.random.Generator) -> None:
    train = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    order = rng.permutation(300)
    query = train[order].copy()
    query[:, 0] ^= 1  # one bit off: still the nearest
    pairs = match_descriptors(query, train, 0.8)
    assert len(pairs) == 300
    np.testing.assert_array_equal(order[pairs[:, 0]], pairs[:, 1])
    duplicated = np.concatenate([train, train[:10]])  # ambiguous twins fail the ratio test
    pairs = match_descriptors(query, duplicated, 0.8)
    assert not np.isin(pairs[:, 1], np.arange(10)).any()
    assert len(np.unique(pairs[:, 1])) == len(pairs)


def test_ransac_finds_the_pose_among_outliers(rng: np.random.Generator) -> None:
    T = pose_from_quat(np.array([0.5, -0.3, 0.2]), np.array([0.2, -0.1, 0.3, 0.93]))
    p_cam = rng.uniform([-1, -1, 1], [1, 1, 4], (200, 3))
    p_world = p_cam @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.002, (200, 3))
    bad = rng.random(200) < 0.4
    p_world[bad] = rng.uniform(-3, 3, (int(bad.sum()), 3))
    threshold = inlier_threshold(p_cam, PointConfig(), SENSOR)
    found = ransac_pose(p_cam, p_world, threshold, 200, rng, 12)
    assert found is not None
    assert_pose_close(found.T_world_cam, T, 0.003, 0.2)
    assert not found.inliers[bad].any() and found.inliers[~bad].mean() > 0.95
    assert ransac_pose(p_cam[:5], p_world[:5], threshold[:5], 50, rng, 12) is None


def test_keypoint_map_detects_lazily_moves_and_votes(rng: np.random.Generator) -> None:
    depth = np.full((480, 640), 2.0, np.float32)
    images = [textured(rng) for _ in range(3)]
    detector = KeypointDetector(CAMERA, SENSOR, PointConfig(window=2))
    store = KeypointMap(detector)
    for k, rgb in enumerate(images):
        store.add(10 * k, np.eye(4), rgb, cloud_of(depth))
    assert store.recent(5) == [10, 20]  # keyframe 0 left the window before use: no images
    query = detector.detect(images[2], cloud_of(depth))
    T = pose_from_quat(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    store.move(20, T)
    matches = store.matches(query, [20])
    assert len(matches) > 100 and set(matches.keyframes) == {20}
    moved = query.points_cam[matches.observed] + [1.0, 0.0, 0.0]
    np.testing.assert_allclose(matches.points_world, moved, atol=1e-9)
    assert store.vote(query, 1) == [20]


def test_a_map_made_to_relocalise_in_keeps_every_keyframes_keypoints(
    rng: np.random.Generator,
) -> None:
    """With `every_keyframe`, a keyframe's keypoints are detected as it leaves the window,
    so a later search can match it; without, it leaves with nothing (none were needed)."""
    depth = np.full((480, 640), 2.0, np.float32)
    images = [textured(rng) for _ in range(3)]
    detector = KeypointDetector(CAMERA, SENSOR, PointConfig(window=2))
    query = detector.detect(images[0], cloud_of(depth))
    for every, expected in ((True, [0, 10, 20]), (False, [10, 20])):
        store = KeypointMap(detector, every_keyframe=every)
        for k, rgb in enumerate(images):
            store.add(10 * k, np.eye(4), rgb, cloud_of(depth))
        assert store.recent(5) == expected
        assert (len(store.matches(query, [0])) > 100) is every


@pytest.mark.parametrize("noise_model", ["kinect", "disparity"])
def test_two_rendered_views_register_from_keypoints(noise_model: str) -> None:
    """Two views of the box-in-a-room 15 deg and 18 cm apart (one step of the paper's
    circle): keypoints of the second matched with the first give the relative pose."""
    from planeslam.sim.render import render_frame
    from planeslam.sim.scenes import box_room_circle

    scene, path = box_room_circle()
    rng = np.random.default_rng(5)
    views = [
        render_frame(scene, path.T_world_cam[k], CAMERA, rng, noise_model=noise_model)
        for k in (0, 1)
    ]
    detector = KeypointDetector(CAMERA, SENSOR, PointConfig())
    store = KeypointMap(detector)
    store.add(0, path.T_world_cam[0], views[0].rgb, cloud_of(views[0].depth_m))
    query = detector.detect(views[1].rgb, cloud_of(views[1].depth_m))
    matches = store.matches(query, [0])
    p_cam = query.points_cam[matches.observed]
    found = ransac_pose(
        p_cam, matches.points_world, inlier_threshold(p_cam, PointConfig(), SENSOR), 200, rng, 12
    )
    assert found is not None and found.count >= 30, len(matches)
    assert_pose_close(found.T_world_cam, path.T_world_cam[1], 0.02, 1.0)
    baseline = invert_pose(path.T_world_cam[0]) @ path.T_world_cam[1]
    assert np.linalg.norm(baseline[:3, 3]) > 0.15  # a wide baseline indeed


def test_point_evidence_that_no_rival_could_match_is_the_only_candidate(
    rng: np.random.Generator,
) -> None:
    """A frame whose keypoints match a keyframe by the hundred needs no primitive
    hypotheses: a pose elsewhere could fit at most its few planes and the other matches,
    far below the points' support. Without that margin the primitives are tried too."""
    rgb, cloud = textured(rng), cloud_of(np.full((480, 640), 2.0, np.float32))
    detector = KeypointDetector(CAMERA, SENSOR, PointConfig())
    store = KeypointMap(detector)
    T = pose_from_quat(np.array([1.0, 0.5, 0.2]), np.array([0.0, 0.0, 0.38, 0.925]))
    query = detector.detect(rgb, cloud)
    store.add(0, T, None, None, keypoints=query)  # the same view, taken at T
    frame = observe(camera_pose(), list(range(6)), rng)  # 6 planes, 2 corners to try
    found = relocalisation_candidates(
        frame, map_view(), query, store, TrackingConfig(), SENSOR, rng, np.eye(4)
    )
    assert len(found.poses) == 1 and len(found.matches) > 100
    assert_pose_close(found.poses[0], T, 1e-3, 0.05)
    undecided = TrackingConfig(relocalise_min_points=10 * len(found.matches))
    tried = relocalisation_candidates(
        frame, map_view(), query, store, undecided, SENSOR, rng, np.eye(4)
    )
    assert len(tried.poses) > 1
    assert_pose_close(tried.poses[0], T, 1e-3, 0.05)
