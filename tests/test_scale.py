"""What keeps long runs flat: plane segments consolidated into one landmark, no keyframes
for revisits that see nothing new, the fused point cloud the map is measured against,
and the replayed multi-pass sequences of `planeslam bench long`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from test_map import make_plane, observation, rect_points

from planeslam.app.bench_long import pass_order, replay_sequence
from planeslam.backend.config import BackendConfig
from planeslam.backend.keyframes import is_keyframe, nearest_keyframe
from planeslam.core.geometry import convex_polygon_gap, pose_from_quat
from planeslam.frontend.cloud import sampled_points
from planeslam.io.dataset import TumDataset
from planeslam.io.trajectory import Trajectory, read_tum
from planeslam.mapping.config import MapConfig
from planeslam.mapping.sparse_cloud import FusedCloudSize
from planeslam.mapping.world_map import Map

pytestmark = pytest.mark.unit

WALL_U, WALL_V = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])


def wall_piece(x0: float, width: float, z: float = 2.0):
    """Points of a piece of the wall z = `z` (camera frame), x in [x0, x0 + width]."""
    return rect_points(np.array([x0, -0.5, z]), width * WALL_U, 1.0 * WALL_V)


@pytest.mark.parametrize(
    ("second", "same"),
    [
        (wall_piece(0.8, 1.0), True),  # overlaps the first piece
        (wall_piece(1.05, 1.0), True),  # 5 cm gap: the same wall
        (wall_piece(1.5, 1.0), False),  # 50 cm gap: another segment of that plane
        (wall_piece(0.0, 1.0, z=2.08), False),  # 8 cm in front: another surface
    ],
)
def test_an_unmatched_piece_of_a_mapped_plane_joins_it(second: np.ndarray, same: bool) -> None:
    m = Map()
    m.merge(observation([make_plane(0, wall_piece(0.0, 1.0))]), np.eye(4))
    merged = m.merge(observation([make_plane(0, second)]), np.eye(4))  # no pairs given
    assert (merged.planes[0] == 0) is same
    assert len(m.planes) == (1 if same else 2)
    if same:
        plane = m.planes[0]
        assert plane.observations == 2 and plane.num_points == 2 * len(second)
        assert plane.outline[:, 0].max() == pytest.approx(second[:, 0].max())


def test_consolidation_can_be_switched_off_and_never_takes_a_plane_twice() -> None:
    m = Map(MapConfig(consolidate=False))
    m.merge(observation([make_plane(0, wall_piece(0.0, 1.0))]), np.eye(4))
    m.merge(observation([make_plane(0, wall_piece(0.5, 1.0))]), np.eye(4))
    assert len(m.planes) == 2
    m = Map()
    m.merge(observation([make_plane(0, wall_piece(0.0, 1.0))]), np.eye(4))
    two = observation([make_plane(0, wall_piece(-0.5, 0.6)), make_plane(1, wall_piece(0.9, 0.6))])
    merged = m.merge(two, np.eye(4))
    assert sorted(merged.planes.values()) == [0, 1]  # one joins, the other is new


def test_polygon_gap() -> None:
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert convex_polygon_gap(square, square + 0.5) == 0.0
    assert convex_polygon_gap(square, square + [1.0, 0.0]) == 0.0
    assert convex_polygon_gap(square, square + [1.25, 0.0]) == pytest.approx(0.25)
    assert convex_polygon_gap(square, square + [1.3, 1.4]) == pytest.approx(0.5)


def pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    half = np.radians(yaw_deg) / 2
    return pose_from_quat(np.array([x, 0.0, 0.0]), np.array([0, 0, np.sin(half), np.cos(half)]))


def test_a_revisit_that_sees_nothing_new_is_no_keyframe() -> None:
    config = BackendConfig()
    earlier = np.stack([pose(0.0), pose(0.5)])
    # 20 frames after the last keyframe, 1 cm from an earlier one: a revisit
    assert not is_keyframe(config, pose(1.0), pose(0.01), 20, 0, earlier)
    assert is_keyframe(config, pose(1.0), pose(0.01), 20, config.keyframe_new_planes, earlier)
    assert is_keyframe(config, pose(1.0), pose(0.01, yaw_deg=30.0), 20, 0, earlier)
    assert is_keyframe(config, pose(1.0), pose(2.0), 1, 0, earlier)  # new ground
    assert not is_keyframe(config, pose(1.0), pose(1.01), 1, 0, earlier)  # too close
    off = BackendConfig(keyframe_skip_revisits=False)
    assert is_keyframe(off, pose(1.0), pose(0.01), 20, 0, earlier)


def test_the_nearest_keyframe_weighs_metres_and_degrees_by_the_keyframe_spacing() -> None:
    config = BackendConfig()  # a keyframe every 5 cm or 5 deg
    keyframes = np.stack([pose(0.0), pose(0.5), pose(0.12), pose(0.0, yaw_deg=20.0)])
    assert nearest_keyframe(config, keyframes, pose(0.49)) == 1
    assert nearest_keyframe(config, keyframes, pose(0.02, yaw_deg=4.0)) == 0
    assert nearest_keyframe(config, keyframes, pose(0.1, yaw_deg=2.0)) == 2
    # 12 deg from the first (2.4 spacings), 8 deg from the fourth (1.6)
    assert nearest_keyframe(config, keyframes, pose(0.0, yaw_deg=12.0)) == 3


@pytest.mark.parametrize("background", [False, True])
def test_fused_cloud_counts_occupied_voxels(background: bool) -> None:
    fused = FusedCloudSize(voxel_m=0.01, flush_every=2, background=background)
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10), [0], indexing="ij"), -1)
    points = grid.reshape(-1, 3) * 0.01 + 0.005  # 100 voxel centres
    fused.add(points)
    fused.add(points + 0.001)  # the same voxels
    assert fused.voxels == 100
    fused.add(points + [0.1, 0.0, 0.0])  # 100 new ones
    fused.add(np.array([[np.nan, 0.0, 0.0]]))
    assert fused.voxels == 200
    shift = np.eye(4)
    shift[:3, 3] = [0.0, 0.2, 0.0]
    fused.add(points, shift)  # moved by a pose: 100 more
    assert fused.voxels == 300


def test_fused_cloud_flushes_merge_like_one_count() -> None:
    """Batches merged into the kept keys count what one pass over all points counts."""
    rng = np.random.default_rng(3)
    batches = [rng.integers(-40, 40, size=(rng.integers(1, 200), 3)) * 0.01 for _ in range(9)]
    fused = FusedCloudSize(voxel_m=0.01, flush_every=3, background=False)
    for batch in batches:
        fused.add(batch + 0.005)
    once = FusedCloudSize(voxel_m=0.01, background=False)
    once.add(np.concatenate(batches) + 0.005)
    assert fused.voxels == once.voxels == len(np.unique(np.concatenate(batches), axis=0))


def test_sampled_keyframe_clouds_count_like_their_points() -> None:
    """The compiled sampling (`add_sampled`) keys exactly the voxels `add` keys for the
    same valid pixels, moved by the same pose: invalid depth and far points left out."""
    rng = np.random.default_rng(5)
    cloud = rng.uniform(-2.0, 2.0, size=(61, 83, 3)).astype(np.float32)
    cloud[..., 2] = rng.uniform(-0.5, 4.0, size=(61, 83))  # some z <= 0: invalid
    cloud[3, 4, 0] = np.nan
    cloud[6, 8, 1] = np.inf
    cloud[9, 10] = [1e5, 0.0, 1.0]  # beyond the keys' range at 1 cm
    quat = np.array([0.1, 0.7, -0.2, 0.67])
    T = pose_from_quat(np.array([0.3, -1.2, 0.8]), quat / np.linalg.norm(quat))
    for stride in (1, 2, 3):
        sampled = FusedCloudSize(voxel_m=0.01, background=False)
        sampled.add_sampled(cloud, stride, T)
        points = FusedCloudSize(voxel_m=0.01, background=False)
        points.add(sampled_points(cloud, stride)[0], T)
        assert sampled.voxels == points.voxels > 100
        assert np.array_equal(sampled._keys, points._keys)


def test_pass_order_turns_without_repeating_the_end() -> None:
    assert pass_order(4, 1) == [0, 1, 2, 3]
    assert pass_order(4, 3) == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]


def test_replay_points_at_the_source_and_replays_its_truth(tmp_path: Path) -> None:
    from planeslam.sim.sequence import synthesize

    source = synthesize("box_room_circle", tmp_path / "src", frames=6, seed=0).out_dir
    replay = replay_sequence(source, tmp_path / "replay", passes=3)
    from planeslam.config import resolve_config

    cfg = resolve_config(replay)
    src, rep = TumDataset(source, cfg.camera), TumDataset(replay, cfg.camera)
    assert len(rep) == 6 + 5 + 5 and (replay / "rgb").is_symlink()
    np.testing.assert_array_equal(rep[7].depth_m, src[3].depth_m)  # 0..5, 4, 3, ...
    truth, src_truth = read_tum(replay / "groundtruth.txt"), read_tum(source / "groundtruth.txt")
    np.testing.assert_allclose(truth.T_world_cam[7], src_truth.T_world_cam[3])
    np.testing.assert_allclose(np.diff(truth.timestamps), 1 / 30.0, atol=1e-6)
    # evo reads the replay's truth too (a blank line between rows once made it refuse)
    from evo.tools import file_interface

    evo_truth = file_interface.read_tum_trajectory_file(str(replay / "groundtruth.txt"))
    assert evo_truth.num_poses == len(rep)


def test_a_plane_joins_only_within_its_own_fit_uncertainty() -> None:
    """2 cm in front of a mapped wall 1 m away: a small, noisy patch is the wall (its fit
    allows it), a well-measured surface is not (at 1 m the sensor's own error is 3 mm)."""
    for sigma_m, same in ((0.02, True), (0.001, False)):
        m = Map()
        m.merge(observation([make_plane(0, wall_piece(0.0, 1.0, z=1.0))]), np.eye(4))
        piece = make_plane(0, wall_piece(0.5, 0.3, z=0.98))
        cov = np.diag([np.radians(1.0) ** 2] * 2 + [sigma_m**2])
        m.merge(observation([dataclasses.replace(piece, covariance=cov)]), np.eye(4))
        assert (len(m.planes) == 1) is same, sigma_m


@pytest.mark.integration
@pytest.mark.parametrize(
    "config_text",
    [
        None,
        # the segment merge and the graph's ties on, as README measures them
        "map:\n  merge_segments: true\n",
        # a window of 6 keyframes: iSAM2 slides every few keyframes of the first pass, and
        # the second pass observes landmarks the window lost, all in the backend process
        "backend:\n  window_keyframes: 6\n",
    ],
    ids=["default", "merge_segments", "window_6"],
)
def test_bench_long_reports_blocks_passes_memory_and_ate(
    tmp_path: Path, config_text: str | None
) -> None:
    from planeslam.app.bench_long import run_long
    from planeslam.sim.sequence import synthesize

    source = synthesize("box_room_circle", tmp_path / "src", seed=0).out_dir  # 24 views
    # the views are 18 cm apart, as the paper's robot took them: 2 per second, not 30
    replay = replay_sequence(source, tmp_path / "replay", passes=2, rate_hz=2.0)
    blocks_path = tmp_path / "blocks.jsonl"
    config = None
    if config_text is not None:
        config = tmp_path / "config.yaml"
        config.write_text(config_text)
    result = run_long(replay, frames_per_pass=23, block=20, config=config, blocks_path=blocks_path)
    assert result.frames == 47
    assert [b["frames"] for b in result.blocks] == ["0-19", "20-39", "40-46"]
    written = [json.loads(line) for line in blocks_path.read_text().splitlines()]
    assert [w["frames"] for w in written] == ["0-19", "20-39", "40-46"]  # as each block ended
    assert [w["map_planes"] for w in written] == [b["map_planes"] for b in result.blocks]
    assert len(result.planes_per_pass) == 2
    assert result.planes_per_pass[1] <= result.planes_per_pass[0] + 2  # a revisit adds ~none
    assert all(b["rss_main_mb"] > 0 and b["rss_backend_mb"] > 0 for b in result.blocks)
    keyframes = [b["keyframes"] for b in result.blocks]
    assert sum(keyframes) <= 26 and keyframes[-1] == 0  # the second pass adds (almost) none
    assert result.ate_rmse_m is not None and result.ate_rmse_m < 0.01
    first, second = result.ate_per_pass_m  # 24 frames, then 23, under one alignment
    assert np.sqrt((24 * first**2 + 23 * second**2) / 47) == pytest.approx(result.ate_rmse_m)
    assert "plane landmarks after each pass" in result.to_text()
    assert f"(per pass {100 * first:.2f} / {100 * second:.2f})" in result.to_text()
    [(metres, degrees)] = result.revisit_offsets  # the second pass places each image again
    assert metres < 0.005 and degrees < 0.5
    assert "the same image's pose against its first-pass pose" in result.to_text()
    assert result.glitches_per_pass == [0, 0]  # frames 0.5 s apart are not judged
    assert "pose glitches found per pass (without the truth)" in result.to_text()


@pytest.mark.integration
def test_bench_long_command_runs_each_seed_and_reports_their_median(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`planeslam bench long SCENE --seeds 0 1 --set ...`: one run per seed on one replay,
    every block written with its seed, and the median and range over the seeds."""
    from planeslam.app.cli import main

    out = tmp_path / "long"
    args = ["-q", "bench", "long", "box_room_circle", "--passes", "2", "--block", "20"]
    args += ["--seeds", "0", "1", "--set", "backend.keyframe_max_frames=5", "--out", str(out)]
    assert main([*args, "--set", "backend.no_such_key=1"]) == 2  # the overrides are applied
    assert not (out / "long.md").exists()
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "(seed 0)" in printed and "(seed 1)" in printed
    summary = printed.splitlines()[-1]
    assert summary.startswith("over seeds 0, 1: ATE median ")
    assert "plane landmarks last / first pass median " in summary
    assert (out / "long.md").read_text().strip() == printed.strip()
    rows = [json.loads(line) for line in (out / "blocks.jsonl").read_text().splitlines()]
    assert [(r["seed"], r["frames"]) for r in rows] == [
        (seed, frames) for seed in (0, 1) for frames in ("0-19", "20-39", "40-46")
    ]


def test_seeds_summary_gives_the_median_and_range_over_the_runs() -> None:
    from planeslam.app.bench_long import LongRunResult, seeds_summary

    def run(seed: int, ate_m: float, planes: list[int]) -> LongRunResult:
        return LongRunResult("replay", [], planes, ate_m, 100, 2.0, [ate_m], seed=seed)

    runs = [run(0, 0.039, [325, 406]), run(1, 0.0385, [339, 456]), run(2, 0.0394, [339, 451])]
    runs[1] = dataclasses.replace(runs[1], revisit_offsets=[(0.0173, 0.79), (0.0197, 0.79)])
    text = seeds_summary(runs)
    assert "| 1 | 3.85 | 3.85 | 339, 456 | 1.35x | 1.73 / 1.97 | 50.0 |" in text
    assert "| 0 | 3.90 | 3.90 | 325, 406 | 1.25x | - | 50.0 |" in text
    assert text.splitlines()[-1] == (
        "over seeds 0, 1, 2: ATE median 3.90 cm (3.85-3.94); "
        "plane landmarks last / first pass median 1.33x (1.25-1.35)"
    )
    assert run(0, 0.03, []).plane_growth is None


def test_revisit_offsets_compare_each_image_with_its_first_pass_pose() -> None:
    """Three passes over 4 images; the second pass's poses are 1 cm and 2 deg off the first
    pass's, the third pass's 3 cm and 0 deg; a lost frame is left out."""
    from scipy.spatial.transform import Rotation

    from planeslam.app.bench_long import revisit_offsets

    order = pass_order(4, 3)  # 0 1 2 3 2 1 0 1 2 3
    first = [np.eye(4) for _ in range(4)]
    for k, T in enumerate(first):
        T[:3, 3] = [0.1 * k, 0.0, 1.0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(2.0)]).as_matrix()
    poses = []
    for k, source in enumerate(order):
        T = first[source].copy()
        if 4 <= k <= 6:
            T = T @ turn
            T[:3, 3] += [0.01, 0.0, 0.0]
        elif k >= 7:
            T[:3, 3] += [0.0, 0.03, 0.0]
        poses.append(T)
    timestamps = np.arange(len(order)) / 30.0
    kept = [k for k in range(len(order)) if k != 8]  # frame 8 lost
    estimate = Trajectory(timestamps[kept], np.array(poses)[kept])
    (m2, deg2), (m3, deg3) = revisit_offsets(estimate, timestamps, frames_per_pass=3)
    assert m2 == pytest.approx(0.01) and deg2 == pytest.approx(2.0)
    assert m3 == pytest.approx(0.03) and deg3 == pytest.approx(0.0, abs=1e-6)
    assert revisit_offsets(estimate, timestamps[:4], frames_per_pass=3) == []  # one pass


def test_glitches_are_counted_by_pass() -> None:
    """Three passes of 20 frames at 30 Hz along a line; one pose of the second pass jumps
    8 cm off and back, counted from the run's final trajectory."""
    from types import SimpleNamespace

    from planeslam.app.bench_long import _glitches_per_pass
    from planeslam.tracking.glitches import find_pose_glitches

    order = pass_order(21, 3)
    poses = np.tile(np.eye(4), (len(order), 1, 1))
    poses[:, 0, 3] = 0.01 * np.asarray(order)  # 1 cm per frame, back and forth
    poses[30, 1, 3] += 0.08
    timestamps = np.arange(len(order)) / 30.0
    estimate = Trajectory(timestamps, poses)
    finished = SimpleNamespace(pose_glitches=find_pose_glitches)
    assert _glitches_per_pass(finished, estimate, timestamps, frames_per_pass=20) == [0, 1, 0]


def confident(plane):
    """`plane` with the tight fit covariance of thousands of independent pixels (1 mrad,
    1 mm), which a real sensor's correlated depth error exceeds."""
    return dataclasses.replace(plane, covariance=np.diag([1e-6, 1e-6, 1e-6]))


def tilted_patch(z: float, degrees: float, size: float = 0.2) -> np.ndarray:
    """A size x size patch centred on x = 0.5 of the wall z = `z`, tilted about y."""
    a = np.radians(degrees)
    u = size * np.array([np.cos(a), 0.0, np.sin(a)])
    return rect_points(
        np.array([0.5 - size / 2, -0.1, z]) - u / 2 + size / 2 * WALL_U, u, size * WALL_V
    )


@pytest.mark.parametrize(
    ("z", "piece", "correlated", "same"),
    [
        (3.0, tilted_patch(3.0, 3.0), 1.0, True),  # small and far: 3 deg is within its error
        (3.0, tilted_patch(3.0, 3.0), 0.0, False),  # ... but not of its fit alone
        (1.0, wall_piece(0.2, 0.6, z=0.975), 1.0, False),  # large, near, 2.5 cm in front
    ],
)
def test_the_consolidation_gate_holds_the_sensors_correlated_error(
    z: float, piece: np.ndarray, correlated: float, same: bool
) -> None:
    m = Map(MapConfig(consolidate_correlated_depth=correlated))
    m.merge(observation([confident(make_plane(0, wall_piece(0.0, 1.0, z=z)))]), np.eye(4))
    merged = m.merge(observation([confident(make_plane(0, piece))]), np.eye(4))
    assert (merged.planes[0] == 0) is same
