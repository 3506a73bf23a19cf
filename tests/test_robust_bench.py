"""The procedural generator and the robustness benchmark's figures (`planeslam bench
robust`): seeds repeat, every kind is drawn in both sets, and the columns are computed as
documented, checked on planted jumps and planted wrong relocalisations."""

from __future__ import annotations

import csv
import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planeslam.app.bench_robust import replace_section
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.eval.robust import (
    BenchSequence,
    MethodFigures,
    RobustRow,
    benchmark_sequences,
    blind_frame_count,
    changes_markdown,
    false_jump_m,
    method_figures,
    read_rows,
    rows_markdown,
    run_sequence,
    summaries,
    summary_markdown,
    wrong_relocalisations,
)
from planeslam.eval.trajectory_metrics import evaluate_trajectory
from planeslam.io.trajectory import Trajectory, read_tum
from planeslam.sim.observability import frame_sight
from planeslam.sim.procedural import (
    DEPTH_MODELS,
    FURNITURE_KINDS,
    TEXTURE_KINDS,
    TRAJECTORY_KINDS,
    build_sequence,
    draw_recipe,
    write_procedural,
)
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import Box, Texture, make_scene
from planeslam.sim.sequence import load_truth

pytestmark = pytest.mark.unit


def _poses(n: int, step_m: float = 0.05) -> np.ndarray:
    """(n, 4, 4) poses along a curve (not a line: the ATE alignment needs that)."""
    k = np.arange(n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.column_stack([step_m * k, 0.1 * np.sin(k / 3), 0.05 * np.cos(k / 4)])
    return T


# --------------------------------------------------------------------------- generator


def test_a_seed_gives_the_same_sequence_and_another_seed_another() -> None:
    a, b, c = draw_recipe(11), draw_recipe(11), draw_recipe(12)
    assert a == b and a != c
    (scene_a, path_a), (scene_b, path_b) = build_sequence(a), build_sequence(b)
    assert np.array_equal(path_a.T_world_cam, path_b.T_world_cam)
    assert [p.d for p in scene_a.planes] == [p.d for p in scene_b.planes]
    assert not np.array_equal(path_a.T_world_cam[:2], build_sequence(c)[1].T_world_cam[:2])


def test_a_rendered_sequence_repeats_byte_for_byte(tmp_path: Path) -> None:
    recipe = draw_recipe(3, trajectory="orbit", texture="posters", depth_model="tof")
    first = write_procedural(recipe, tmp_path / "a", max_frames=2)
    second = write_procedural(recipe, tmp_path / "b", max_frames=2)
    for p, q in zip(
        first.depth_paths + first.rgb_paths, second.depth_paths + second.rgb_paths, strict=True
    ):
        assert p.read_bytes() == q.read_bytes()
    truth = load_truth(first.out_dir)
    assert truth["rendering"]["recipe"]["seed"] == 3
    assert truth["rendering"]["noise_model"] == "tof"
    assert any(o["class"] == "box" for o in truth["objects"])  # the orbit's box, with its size
    assert len(read_tum(first.groundtruth_path)) == 2


def test_every_kind_is_drawn_in_both_sets() -> None:
    sequences = benchmark_sequences()
    assert len(sequences) >= 40
    for split in ("tuning", "validation"):
        recipes = [s.recipe for s in sequences if s.split == split]
        assert len(recipes) == len(sequences) // 2
        assert {r.trajectory for r in recipes} == set(TRAJECTORY_KINDS)
        assert {r.texture for r in recipes} == set(TEXTURE_KINDS)
        assert {r.depth_model for r in recipes} == set(DEPTH_MODELS)
        for kind in TRAJECTORY_KINDS:
            assert sum(r.trajectory == kind for r in recipes) == 3
    recipes = [s.recipe for s in sequences]
    assert {f for r in recipes for f in r.furniture} == set(FURNITURE_KINDS)
    assert {r.square_room for r in recipes} == {True, False}
    assert {r.open_room for r in recipes} == {True, False}
    assert any(r.symmetric for r in recipes) and not all(r.symmetric for r in recipes)


@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
def test_each_path_is_what_its_kind_says(kind: str) -> None:
    scene, path = build_sequence(draw_recipe(5, trajectory=kind))
    t, xyz = path.timestamps, path.positions
    dt = np.diff(t)
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    assert np.all(dt > 0)
    room = scene.object_by_name("room")
    assert room.object_class == "room"
    if kind in ("handheld", "rotation", "wall", "loop"):
        assert np.allclose(dt, 1 / 30)
        turns = np.linalg.inv(path.T_world_cam[:-1]) @ path.T_world_cam[1:]
        angles = np.degrees(
            np.arccos(np.clip((np.trace(turns[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
        )
        assert angles.max() < 4.0  # smooth: no turn of the view between two frames
    if kind == "robot_steps":
        assert np.all((dt >= 0.5) & (dt <= 1.0))
        assert np.all((steps > 0.05) & (steps <= 0.2 + 1e-9))
    if kind == "orbit":
        assert np.all((dt >= 0.9) & (dt <= 1.1))
        assert 24 <= len(path) <= 36
        assert scene.objects[1].object_class == "box"  # the circled box
    if kind == "keyframes":
        assert np.all((dt >= 0.2 - 1e-9) & (dt <= 1.0 + 1e-9))  # 1-5 Hz
    if kind == "rotation":
        assert np.allclose(steps, 0.0)
    if kind == "loop":
        assert np.allclose(xyz[0], xyz[-1], atol=0.03)
    if kind == "wall":  # close to one wall
        walls = [p for p in scene.planes if p.name.startswith("room.wall")]
        nearest = min(abs(float(p.normal @ xyz[0] + p.d)) for p in walls)
        assert 0.55 <= nearest <= 1.05


def test_textures_render_as_named() -> None:
    room = Box("room", np.array([0.0, 0.0, 1.25]), np.array([4.0, 4.0, 2.5]), kind="room")
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looks +x
    T[:3, 3] = [0.5, 0.0, 1.25]
    camera = CameraConfig()
    spread = {}
    for pattern in ("none", "repetitive", "noise"):
        scene = make_scene("wall", (room,), texture=Texture(seed=1, pattern=pattern))
        frame = render_frame(scene, T, camera, np.random.default_rng(0), noise=False)
        wall = frame.plane_id == scene.plane_by_name("room.wall_+x").id
        grey = frame.rgb.astype(float).mean(axis=2)[wall]
        spread[pattern] = float(np.std(grey))
        if pattern == "repetitive":  # two levels only: a checkerboard
            assert len(np.unique(np.round(grey))) <= 60
    assert spread["none"] < 2.0 < spread["repetitive"]
    assert spread["noise"] > 2.0
    with pytest.raises(ConfigError, match="pattern"):
        Texture(pattern="marble")


def test_a_bare_wall_filling_the_view_leaves_the_camera_blind_along_it() -> None:
    room = Box("room", np.array([0.0, 0.0, 1.25]), np.array([4.0, 4.0, 2.5]), kind="room")
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looks +x
    T[:3, 3] = [1.4, 0.0, 1.25]  # 0.6 m from the wall at x = 2: nothing else in view
    camera = CameraConfig()
    bare = make_scene("wall", (room,), texture=Texture(seed=1, pattern="none"))
    sight = frame_sight(bare, T, camera)
    assert sight.blind_axes == "yz"  # along the wall; the depth places x
    assert sight.changed_share[0] > 0.9
    textured = make_scene("wall", (room,), texture=Texture(seed=1, pattern="noise"))
    assert frame_sight(textured, T, camera).blind_axes == ""
    T[:3, 3] = [-1.4, 0.0, 1.25]  # 3.4 m back: floor, ceiling and side walls in view too
    assert frame_sight(bare, T, camera).blind_axes == ""


def test_a_sequence_s_blind_frames_are_counted_once_and_kept_beside_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import planeslam.eval.robust as robust
    import planeslam.sim.observability as observability

    recipe = draw_recipe(40, trajectory="wall", texture="none", depth_model="disparity")
    root = robust.ensure_rendered(recipe, tmp_path, max_frames=2)
    assert blind_frame_count(recipe, root, 2) == 2  # every frame: one bare wall
    kept = json.loads((root / "sight.json").read_text(encoding="utf-8"))
    assert kept["frames"] == [[0, "xz"], [1, "xz"]]

    def fails(*args: object) -> None:
        raise AssertionError("counted again")

    monkeypatch.setattr(observability, "blind_frames", fails)
    assert blind_frame_count(recipe, root, 2) == 2  # read back
    with pytest.raises(AssertionError, match="counted again"):
        blind_frame_count(recipe, root, 1)  # another count, counted afresh


def test_tof_noise_grows_with_depth_and_drops_dark_faces() -> None:
    from planeslam.sim.noise import SurfaceTruth
    from planeslam.sim.tof import TofNoise

    model = TofNoise()
    H, W = 60, 80
    rng = np.random.default_rng(0)
    spreads = []
    for z in (1.0, 3.0):
        truth = SurfaceTruth(
            np.ones((H, W), bool),
            np.full((H, W), z),
            np.zeros((H, W)),
            np.full((H, W), 0.5, np.float32),
        )
        depth = model.measure_depth(truth, CameraConfig(), rng)
        spreads.append(float(np.std(depth[depth > 0])))
    assert spreads[1] > 2 * spreads[0]
    dark = SurfaceTruth(
        np.ones((H, W), bool),
        np.full((H, W), 4.0),
        np.zeros((H, W)),
        np.full((H, W), 0.1, np.float32),
    )
    assert (model.measure_depth(dark, CameraConfig(), rng) > 0).mean() < 0.05


# --------------------------------------------------------------------------- figures


def test_a_planted_jump_is_the_false_jump() -> None:
    truth = _poses(20)
    estimate = truth.copy()
    estimate[12:, 1, 3] += 0.3  # a 30 cm sideways jump between frames 11 and 12
    stamps = np.arange(20, dtype=float)

    def jump(T_world_est: np.ndarray) -> float:
        evaluation = evaluate_trajectory(
            Trajectory(stamps, truth), Trajectory(stamps, T_world_est), align=False
        )
        return false_jump_m(evaluation)

    assert jump(estimate) == pytest.approx(0.3)
    assert jump(truth) == pytest.approx(0.0)
    # A rigid offset of the whole estimate is no jump.
    offset = np.eye(4)
    offset[:3, 3] = [1.0, -2.0, 0.5]
    assert jump(offset @ truth) == pytest.approx(0.0, abs=1e-12)


def test_a_planted_wrong_relocalisation_is_counted() -> None:
    truth = _poses(3)
    reloc = truth.copy()
    reloc[1, :3, 3] += [0.0, 0.5, 0.0]  # 50 cm off
    turned = truth[2].copy()
    c, s = np.cos(np.deg2rad(8.0)), np.sin(np.deg2rad(8.0))
    turned[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # 8 deg off
    reloc[2] = turned
    assert wrong_relocalisations(np.eye(4), reloc, truth) == 2
    assert wrong_relocalisations(np.eye(4), truth, truth) == 0


def test_method_figures_on_a_run_with_a_jump_a_wrong_relocalisation_and_lost_frames() -> None:
    n = 30
    stamps = np.arange(n) / 30.0
    truth = Trajectory(stamps, _poses(n))
    est_poses = _poses(n)
    est_poses[20:, 1, 3] += 0.4  # a jump at frame 20 that stays
    keep = np.r_[0:10, 12:n]  # frames 10 and 11 lost
    estimate = Trajectory(stamps[keep], est_poses[keep])
    relocalised = Trajectory(stamps[[20, 25]], np.stack([est_poses[20], truth.T_world_cam[25]]))
    figures = method_figures(truth, estimate, n, 30.0, relocalised=relocalised)
    assert figures.tracked_fraction == pytest.approx(28 / 30)
    assert figures.false_jump_m == pytest.approx(0.4)
    assert figures.relocalisations == 2
    # The ATE alignment puts the truth between the two halves: frame 20's pose is off by
    # about 0.4 m minus the shift, frame 25's by about the shift; one of them is wrong.
    assert figures.wrong_relocalisations >= 1
    assert figures.ate_m is not None and figures.ate_m > 0.1
    assert not figures.passed
    clean = method_figures(truth, Trajectory(stamps, _poses(n)), n, 30.0)
    assert clean.passed and clean.ate_m == pytest.approx(0.0, abs=1e-9)


def test_the_furniture_size_error_leaves_the_room_out() -> None:
    """A room seen in part measures metres off; the box beside it 1 cm: the object size
    error mixes both, the furniture's is the box's alone."""
    n = 10
    stamps = np.arange(n) / 30.0
    truth = Trajectory(stamps, _poses(n))
    truth_objects = {
        "objects": [
            {"id": 0, "class": "room", "size_m": [8.0, 4.0, 2.5]},
            {"id": 1, "class": "box", "size_m": [0.5, 0.4, 0.3]},
        ]
    }
    objects = [
        {"id": 7, "class": "room", "planes": [0, 1, 2], "size_m": [3.0, 1.5]},
        {"id": 8, "class": "box", "planes": [3, 4, 5], "size_m": [0.51, 0.41, 0.31]},
    ]
    figures = method_figures(truth, truth, n, 30.0, objects=objects, truth_objects=truth_objects)
    assert figures.furniture_size_error_m == pytest.approx(0.01)
    assert figures.object_size_error_m == pytest.approx(((5.0 + 2.5) / 2 + 0.01) / 2)
    alone = method_figures(truth, truth, n, 30.0, objects=objects[:1], truth_objects=truth_objects)
    assert alone.furniture_size_error_m is None  # no box found: nothing to measure


def test_a_camera_turning_in_place_gets_an_unaligned_ate() -> None:
    n = 20
    truth_poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.radians(np.linspace(0.0, 60.0, n))
    truth_poses[:, 0, 0], truth_poses[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    truth_poses[:, 1, 0], truth_poses[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    estimate = truth_poses.copy()
    estimate[:, 0, 3] = 0.01  # 1 cm off everywhere
    stamps = np.arange(n) / 30.0
    figures = method_figures(Trajectory(stamps, truth_poses), Trajectory(stamps, estimate), n, 30.0)
    assert figures.error is None and figures.ate_m == pytest.approx(0.01)


def _row(name: str, split: str, ours: MethodFigures, theirs: MethodFigures) -> RobustRow:
    return RobustRow(name, split, "orbit", "none", "tof", True, 30, ours, theirs)  # type: ignore[arg-type]


def test_summaries_count_passes_and_wins_per_set_and_kind() -> None:
    good = MethodFigures(1.0, 0.01, 0.02, 1, 0, 0.01, 20.0)
    jumpy = MethodFigures(1.0, 0.01, 0.30, 2, 1, 0.01, 20.0)
    o3d = MethodFigures(1.0, 0.015, 0.01, 0, 0, None, 30.0)
    rows = [
        _row("a", "tuning", good, o3d),
        _row("b", "validation", good, o3d),
        _row("c", "validation", jumpy, o3d),
        _row("d", "validation", MethodFigures(error="RuntimeError: x"), o3d),
    ]
    groups = summaries(rows)
    val = groups["validation"][0]
    assert (val.sequences, val.passed, val.ahead, val.open3d_passed) == (3, 1, 2, 3)
    assert (val.false_jumps, val.relocalisations, val.wrong_relocalisations) == (1, 3, 1)
    assert groups["tuning"][0].passed == 1
    labels = [g.label for g in groups["validation"]]
    assert "trajectory orbit" in labels and "symmetric scene" in labels
    text = summary_markdown(rows)
    assert "**tuning set**" in text and "**validation set**" in text
    assert RobustRow.from_dict(json.loads(json.dumps(rows[2].to_dict()))) == rows[2]
    blind = [replace(rows[1], blind_frames=30), replace(rows[2], blind_frames=4), rows[3]]
    val = summaries(blind)["validation"][0]
    assert (val.blind, val.all_blind) == (2, 1)  # 30 of 30 frames blind, 4 of 30
    assert "| 2 (1) |" in summary_markdown(blind)
    assert "| 30 | yes |" in rows_markdown(blind)  # blind on every frame, and still passed
    older = {k: v for k, v in rows[1].to_dict().items() if k != "blind_frames"}
    assert RobustRow.from_dict(older).blind_frames == 0  # rows written before the count


def test_an_earlier_run_is_read_back_and_what_moved_is_listed(tmp_path: Path) -> None:
    good = MethodFigures(1.0, 0.01, 0.02, 0, 0, None, 20.0)
    o3d = MethodFigures(1.0, 0.015, 0.01, 0, 0, None, 30.0)
    before = [
        _row("steady", "validation", good, o3d),
        _row("worse", "validation", good, o3d),
        _row("better", "tuning", MethodFigures(0.9, 0.05, 0.3), o3d),
        _row("gone", "tuning", good, o3d),
    ]
    (tmp_path / "rows.jsonl").write_text(
        "".join(json.dumps(r.to_dict()) + "\n" for r in before), encoding="utf-8"
    )
    assert read_rows(tmp_path) == before  # the folder or the file itself
    after = [
        _row("steady", "validation", MethodFigures(1.0, 0.010001, 0.02), o3d),  # rounds equal
        _row("worse", "validation", MethodFigures(0.97, 0.03, 0.02), o3d),
        _row("better", "tuning", good, o3d),
        _row("new", "tuning", good, o3d),  # not in the earlier run: not compared
    ]
    sized = [_row("box", "validation", replace(good, object_size_error_m=0.003), o3d)]
    resized = [_row("box", "validation", replace(good, object_size_error_m=0.27), o3d)]
    assert "| box | validation | 100.0% -> 100.0% | 1.00 -> 1.00 | 2.0 -> 2.0 | 0.3 -> 27.0 |" in (
        changes_markdown(sized, resized)
    )
    text = changes_markdown(read_rows(tmp_path / "rows.jsonl"), after)
    assert "- tuning set: 0 -> 1 of 1 pass" in text
    assert "- validation set: 2 -> 1 of 2 pass" in text
    worse = "| worse | validation | 100.0% -> 97.0% | 1.00 -> 3.00 | 2.0 -> 2.0 | - -> - | yes"
    better = "| better | tuning | 90.0% -> 100.0% | 5.00 -> 1.00 | 30.0 -> 2.0 | - -> - | no -> yes"
    assert worse in text and better in text
    assert "steady" not in text and "new" not in text and "gone" not in text
    assert "No sequence's figures moved." in changes_markdown(before, before)


def test_an_earlier_run_that_cannot_be_read_is_a_one_line_error(tmp_path: Path) -> None:
    from planeslam.app.bench_robust import run_robust_command

    with pytest.raises(ConfigError, match=r"rows\.jsonl.*not found"):
        read_rows(tmp_path / "nowhere")
    rows = tmp_path / "rows.jsonl"
    rows.write_text(
        json.dumps(_row("a", "tuning", MethodFigures(), MethodFigures()).to_dict())
        + '\n{"name": 1}\n',
        encoding="utf-8",
    )
    with pytest.raises(ConfigError, match=r"rows\.jsonl:2: not a bench robust row"):
        read_rows(rows)
    rows.write_text("[1,\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"rows\.jsonl:1: not JSON"):
        read_rows(tmp_path)
    with pytest.raises(ConfigError, match="the run's own --out"):  # before anything runs
        run_robust_command(tmp_path, "cmd", against=tmp_path, sequences=[])


def test_a_section_is_replaced_not_repeated() -> None:
    page = replace_section("# Benchmarks\n", "baseline", "one")
    page = replace_section(page, "new", "two")
    page = replace_section(page, "baseline", "three")
    assert page.count("bench robust: baseline -->") == 2  # its begin and end markers
    assert "three" in page and "one" not in page and "two" in page


@pytest.mark.integration
@pytest.mark.slow
def test_one_sequence_runs_both_methods(tmp_path: Path) -> None:
    recipe = draw_recipe(2, trajectory="orbit", texture="noise", depth_model="kinect")
    row = run_sequence(
        BenchSequence(recipe, "tuning"), str(tmp_path), runs_dir=str(tmp_path / "runs")
    )
    assert row.frames >= 24 and row.planeslam.error is None and row.open3d.error is None
    with (tmp_path / "runs" / recipe.name / "frame_errors.csv").open() as f:
        errors = list(csv.DictReader(f))  # one row per tracked frame, with its path
    assert len(errors) == round(row.planeslam.tracked_fraction * row.frames)
    assert errors[0]["path"] == "first" and errors[-1]["frame"] == str(row.frames - 1)
    steps = [float(e["step_error_m"]) for e in errors[1:]]
    assert max(steps) == pytest.approx(row.planeslam.false_jump_m, abs=1e-6)  # one definition
    assert row.planeslam.tracked_fraction is not None and row.planeslam.ate_m is not None
    assert row.open3d.ate_m is not None and row.planeslam.fps and row.open3d.fps
    # Rendered once: a second run finds the folder and keeps it.
    stamp = (tmp_path / recipe.name / "truth.json").stat().st_mtime_ns
    from planeslam.eval.robust import ensure_rendered

    ensure_rendered(recipe, tmp_path)
    assert (tmp_path / recipe.name / "truth.json").stat().st_mtime_ns == stamp


@pytest.mark.integration
@pytest.mark.slow
def test_the_benchmark_runs_on_dask_and_writes_its_page(tmp_path: Path) -> None:
    """Two short sequences on a Dask LocalCluster through the command's library call: rows
    in order, rows.jsonl written as they come, the page's section written."""
    from dataclasses import replace

    from planeslam.app.bench_robust import run_robust_command

    sequences = [replace(s, max_frames=4) for s in benchmark_sequences(9)[7:9]]
    page = tmp_path / "benchmarks.md"
    page.write_text("# Benchmarks\n\nkept\n", encoding="utf-8")
    text = run_robust_command(
        tmp_path / "out",
        "planeslam bench robust",
        executor="dask",
        markdown=page,
        label="test",
        with_open3d=False,
        sequences=sequences,
    )
    rows = (tmp_path / "out" / "rows.jsonl").read_text(encoding="utf-8").splitlines()
    assert len(rows) == 2
    for s in sequences:  # each sequence's own outputs, from the Dask workers too
        assert (tmp_path / "out" / "runs" / s.recipe.name / "frame_errors.csv").is_file()
    assert "**validation set**" in text
    written = page.read_text(encoding="utf-8")
    assert "kept" in written and "Robust benchmark: test" in written
    assert "s007-handheld" in written and "s008-robot_steps" in written
    assert re.search(r"Reference workload \(.*\) \d+\.\d\d s before, \d+\.\d\d s after", written)


@pytest.mark.integration
def test_synth_renders_a_procedural_sequence_a_user_can_run(tmp_path: Path) -> None:
    """`planeslam synth procedural` draws the recipe of --seed as the benchmark does, with
    the parts the options set: a held-out sequence of a benchmark kind, through the CLI."""
    from planeslam.app.cli import main

    out = tmp_path / "seq"
    args = ["synth", "procedural", str(out), "--seed", "102", "--frames", "2"]
    options = ["--trajectory", "robot_steps", "--texture", "repetitive", "--room", "square"]
    assert main([*args, *options, "--noise-model", "kinect", "--furniture", "cube"]) == 0
    recipe = load_truth(out)["rendering"]["recipe"]
    drawn = draw_recipe(102, "robot_steps", "repetitive", "kinect")
    assert recipe == {
        **json.loads(json.dumps(drawn.__dict__)),
        "square_room": True,
        "furniture": ["cube"],
    }
    assert len(read_tum(out / "groundtruth.txt")) == 2
    # Without options the seed decides everything; a scene option on a named scene is refused.
    assert (
        main(["synth", "procedural", str(tmp_path / "drawn"), "--seed", "5", "--frames", "1"]) == 0
    )
    assert load_truth(tmp_path / "drawn")["rendering"]["recipe"]["seed"] == 5
    named = ["synth", "box_room_circle", str(tmp_path / "x"), "--texture", "none"]
    assert main(named) == 2
    with pytest.raises(SystemExit) as exc:
        main([*args[:2], str(tmp_path / "y"), "--furniture", "sofa"])
    assert exc.value.code == 2
