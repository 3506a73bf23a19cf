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
    Keypoints,
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


def loop_views():
    """The box-in-a-room circle's path and its views 0, 1 and 12 (rendered with seed 5),
    and a keypoint detector."""
    from planeslam.sim.render import render_frame
    from planeslam.sim.scenes import box_room_circle

    scene, path = box_room_circle()
    rng = np.random.default_rng(5)
    views = {k: render_frame(scene, path.T_world_cam[k], CAMERA, rng) for k in (0, 1, 12)}
    return path, views, KeypointDetector(CAMERA, SENSOR, PointConfig())


def drifted(T_world_cam: np.ndarray) -> np.ndarray:
    """The pose (4, 4) tracked 8 cm off sideways and 2 cm along the depth."""
    T = T_world_cam.copy()
    T[:3, 3] += [0.08, 0.0, -0.02]
    return T


def find_loop(store, index, keypoints, T_world_cam, cfg, points, sensor, rng):
    """Keyframe `index`'s loop searched in place: `loop_query`, then `place_loop`."""
    from planeslam.tracking.loops import loop_query, place_loop

    query = loop_query(store, index, T_world_cam, cfg, keypoints)
    assert query is not None
    return place_loop(query, keypoints, cfg, points, sensor, rng)


def test_a_drifted_keyframe_finds_its_loop_against_the_older_keyframe() -> None:
    """Keyframe 0 of the box-in-a-room circle, then one far round the circle (the recent
    one); view 1 (15 deg and 18 cm from view 0) tracked 8 cm off its true pose: its
    keypoints place it against keyframe 0 (`find_loop`) within 2 cm / 1 deg of the true
    relative pose. Tracked where it is, it needs no loop; with keyframe 0 among the recent
    ones, none is looked for."""
    from planeslam.tracking.config import LoopConfig

    path, views, detector = loop_views()
    rng = np.random.default_rng(5)
    store = KeypointMap(detector)
    for k in (0, 12):
        keypoints = detector.detect(views[k].rgb, cloud_of(views[k].depth_m))
        store.add(k, path.T_world_cam[k], None, None, keypoints)
    query = detector.detect(views[1].rgb, cloud_of(views[1].depth_m))
    T_true = path.T_world_cam[1]
    T_drifted = drifted(T_true)
    cfg = LoopConfig(skip_recent=1)

    loop = find_loop(store, 1, query, T_drifted, cfg, PointConfig(), SENSOR, rng)
    assert loop is not None and (loop.index, loop.old_index) == (1, 0)
    assert loop.inliers >= cfg.min_inliers
    T_old_cam_true = invert_pose(path.T_world_cam[0]) @ T_true
    assert_pose_close(loop.T_old_cam, T_old_cam_true, 0.02, 1.0)
    assert find_loop(store, 1, query, T_true, cfg, PointConfig(), SENSOR, rng) is None
    recent = LoopConfig(skip_recent=2)
    assert find_loop(store, 1, query, T_drifted, recent, PointConfig(), SENSOR, rng) is None


def test_the_loop_search_beside_tracking_finds_the_same_loop_on_a_snapshot() -> None:
    """The drifted view of the test above, searched by `LoopSearch` on its worker thread
    from its images (the search detects the keypoints): the outcome collected later is the
    loop `find_loop` finds in place, although the keypoint map changed after the query
    was taken (keyframe 0 moved by 30 cm, a keyframe added that makes keyframe 12 a
    candidate): the query holds a snapshot. A second query before collecting is refused;
    the worker's error reaches the collector."""
    from planeslam.tracking.config import LoopConfig
    from planeslam.tracking.loops import LoopOutcome, LoopSearch, loop_query, place_loop

    path, views, detector = loop_views()
    store = KeypointMap(detector)
    for k in (0, 12):
        store.add(k, path.T_world_cam[k], views[k].rgb, cloud_of(views[k].depth_m))
    images = (views[1].rgb, cloud_of(views[1].depth_m))
    T_drifted = drifted(path.T_world_cam[1])
    cfg = LoopConfig(skip_recent=1)
    query = loop_query(store, 1, T_drifted, cfg, images=images)
    assert query is not None and query.keypoints is None

    def search(q):
        keypoints = KeypointDetector(CAMERA, SENSOR, PointConfig()).detect(*q.images)
        loop = place_loop(q, keypoints, cfg, PointConfig(), SENSOR, np.random.default_rng(7))
        return LoopOutcome(q.index, keypoints, loop)

    loops = LoopSearch(search)
    loops.submit(query)
    with pytest.raises(RuntimeError, match="collect the previous"):
        loops.submit(query)
    T_moved = path.T_world_cam[0].copy()
    T_moved[:3, 3] += 0.3
    store.move(0, T_moved)
    store.add(13, path.T_world_cam[12], None, None, Keypoints.empty())
    np.testing.assert_array_equal(query.candidates.pose(0), path.T_world_cam[0])
    assert len(query.candidates) == 1
    outcome = loops.collect()
    assert outcome is not None and outcome.index == 1 and outcome.loop is not None
    assert outcome.search_ms > 0
    assert loops.collect() is None
    store.move(0, path.T_world_cam[0])
    in_place = find_loop(
        store, 1, outcome.keypoints, T_drifted, cfg, PointConfig(), SENSOR, np.random.default_rng(7)
    )
    assert in_place is not None
    assert (
        (outcome.loop.index, outcome.loop.old_index)
        == (in_place.index, in_place.old_index)
        == (1, 0)
    )
    np.testing.assert_allclose(outcome.loop.T_old_cam, in_place.T_old_cam, atol=1e-9)

    def broken(q):
        raise ValueError("search failed")

    failing = LoopSearch(broken)
    failing.submit(query)
    with pytest.raises(ValueError, match="search failed"):
        failing.collect()
    loops.close()
    failing.close()
