"""Seeing what a run built: the self-contained report (and its map picture in a real
browser), the rerun recording of a run (live and replayed, read back with rerun's own
reader), and the dense TSDF mesh from the run's poses."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_sequence
from test_report import embedded_images

from planeslam.app.cli import main
from planeslam.app.mesh import mesh_run
from planeslam.app.runner import run_sequence
from planeslam.core.errors import ConfigError, EvaluationError
from planeslam.core.types import TrackingPath
from planeslam.eval.report import write_report
from planeslam.eval.run_info import read_run_info
from planeslam.mapping.dense_mesh import TsdfConfig
from planeslam.mapping.ply_export import _palette
from planeslam.mapping.world_map import Map
from planeslam.sim.sequence import load_truth, synthesize

pytestmark = pytest.mark.integration  # a short run, then its report, rerun recordings and mesh

CHROMIUM = Path("/usr/bin/chromium")
FRAMES = 8


@pytest.fixture(scope="module")
def box_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper's box in a room, 24 rendered poses on a circle."""
    return synthesize("box_room_circle", tmp_path_factory.mktemp("brc") / "seq", seed=3).out_dir


@pytest.fixture(scope="module")
def run_dir(box_room: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished `planeslam run` of the first FRAMES frames (merge backend: every frame a
    keyframe, so the map has the box and the room)."""
    out = tmp_path_factory.mktemp("run") / "out"
    run_sequence(box_room, out, backend="merge", max_frames=FRAMES, command="planeslam run x")
    return out


# --- figures and run.json ---------------------------------------------------------------------


def test_run_records_what_it_was_made_from(run_dir: Path, box_room: Path) -> None:
    info = read_run_info(run_dir)
    assert Path(info.dataset) == box_room.resolve()
    assert info.backend == "merge" and info.command == "planeslam run x"
    assert info.version and info.started_utc.endswith("+00:00")
    for name in ("map_planes.ply", "map_points.ply"):
        assert (run_dir / name).is_file()
    assert not (run_dir / "map.ply").exists()


def test_missing_run_json_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match=r"run\.json: not found"):
        read_run_info(tmp_path)


# --- report -----------------------------------------------------------------------------------


def test_report_stands_alone_with_header_and_map(run_dir: Path, tmp_path: Path) -> None:
    alone = tmp_path / "elsewhere" / "report.html"
    alone.parent.mkdir()
    shutil.copy(run_dir / "report.html", alone)  # copied without its folder
    page = alone.read_text(encoding="utf-8")
    pngs = embedded_images(page)
    assert all(p[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    assert len(pngs) >= 4  # map, trajectory, ATE over time, per-frame timeline
    assert (run_dir / "map.png").read_bytes() in pngs
    assert re.search(r"""(src|href)=["'](?!data:)""", page) is None  # no other resource
    info = read_run_info(run_dir)
    for text in (info.dataset, "merge", "planeslam run x", info.version, info.started_utc):
        assert text in page, text
    assert "Top-down map" in page and "Tracking" in page and "tracking path" in page
    metrics = json.loads((run_dir / "metrics.json").read_text())
    fps = re.search(r"<th>frames per second</th><td>([^<]*)</td>", page)
    assert fps is not None and fps.group(1) == f"{metrics['fps']:.1f}"
    assert f"{metrics['fps']:.4f}" not in page


def test_map_picture_shows_the_objects(run_dir: Path) -> None:
    """The top-down picture draws the box's planes in the box's colour."""
    import cv2

    world_map = Map.load(run_dir / "map.json")
    classes = {o.cls for o in world_map.objects}
    assert {"box", "room"} <= classes, classes
    image = cv2.cvtColor(cv2.imread(str(run_dir / "map.png")), cv2.COLOR_BGR2RGB)
    box = next(o for o in world_map.objects if o.cls == "box")
    colour = _palette(box.id).astype(int)
    hits = np.all(np.abs(image.astype(int) - colour) <= 3, axis=-1).sum()
    assert hits > 50, hits


def test_report_reads_fields_it_does_not_know(run_dir: Path, tmp_path: Path) -> None:
    """Fields other issues add to metrics.json (tracked_fraction, memory figures) show."""
    folder = tmp_path / "copy"
    shutil.copytree(run_dir, folder)
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics |= {"tracked_fraction": 0.875, "rss_after_map_mb": 301.26}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    page = write_report(folder).read_text(encoding="utf-8")
    assert "87.5" in page and "301.3" in page and "rss after map mb" in page


@pytest.mark.browser
def test_report_in_headless_chromium_shows_the_map(run_dir: Path, tmp_path: Path) -> None:
    """A real browser renders the page copied alone; the screenshot holds the map
    picture's box colour (a page whose images did not load would not)."""
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} is absent (Debian: apt-get install chromium)")
    import cv2

    page = tmp_path / "alone" / "report.html"
    page.parent.mkdir()
    shutil.copy(run_dir / "report.html", page)
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            str(CHROMIUM),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={tmp_path / 'profile'}",
            "--hide-scrollbars",
            "--window-size=1280,2000",
            f"--screenshot={shot}",
            page.as_uri(),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    image = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
    assert image.shape[:2] == (2000, 1280)
    world_map = Map.load(run_dir / "map.json")
    box = next(o for o in world_map.objects if o.cls == "box")
    colour = _palette(box.id).astype(int)
    hits = np.all(np.abs(image.astype(int) - colour) <= 6, axis=-1).sum()
    assert hits > 30, hits


# --- dense mesh -------------------------------------------------------------------------------


def test_mesh_lies_on_the_true_planes(run_dir: Path, box_room: Path) -> None:
    o3d = pytest.importorskip("open3d")
    result = mesh_run(run_dir, TsdfConfig(voxel_m=0.02))
    assert result.path == run_dir / "mesh.ply" and result.frames == FRAMES  # all keyframes
    mesh = o3d.io.read_triangle_mesh(str(result.path))
    vertices = np.asarray(mesh.vertices)
    assert len(vertices) == result.vertices > 1000 and len(mesh.triangles) == result.triangles
    assert mesh.has_vertex_colors() and mesh.has_vertex_normals()
    planes = load_truth(box_room)["planes"]
    normals = np.array([p["normal"] for p in planes])
    offsets = np.array([p["d"] for p in planes])
    distance = np.min(np.abs(vertices @ normals.T + offsets), axis=1)
    assert np.quantile(distance, 0.95) < 0.02, np.quantile(distance, [0.5, 0.95])


def test_mesh_command_prints_time_and_size(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m.ply"
    assert main(["-q", "mesh", str(run_dir), "--voxel", "0.03", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert re.search(rf"mesh of {FRAMES} frames: \d+ vertices, \d+ triangles, [\d.]+ MB in", text)
    assert out.is_file()


@pytest.mark.data
def test_mesh_of_a_short_real_run(tmp_path: Path) -> None:
    """TUM fr1/desk, 9 frames: 3 keyframes, each surface seen by at most 3 of them (the
    TSDF had kept only voxels seen more than `min_weight` times: nothing)."""
    from planeslam.app.runner import run_sequence

    run_sequence(shared_sequence("tum_fr1_desk_9f"), tmp_path, backend="isam2")
    keyframes = json.loads((tmp_path / "metrics.json").read_text())["keyframes"]
    assert keyframes <= TsdfConfig().min_weight
    result = mesh_run(tmp_path, TsdfConfig(voxel_m=0.02))
    assert result.frames == keyframes and result.vertices > 1000


def test_mesh_errors(run_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="voxel_m must be a positive number"):
        TsdfConfig(voxel_m=0.0)
    with pytest.raises(EvaluationError, match="run.json: not found"):
        mesh_run(tmp_path)
    folder = tmp_path / "moved"
    shutil.copytree(run_dir, folder)
    info = json.loads((folder / "run.json").read_text())
    (folder / "run.json").write_text(json.dumps(info | {"dataset": str(tmp_path / "gone")}))
    with pytest.raises(Exception, match="pass --dataset DIR"):
        mesh_run(folder)


# --- rerun recording --------------------------------------------------------------------------


def read_recording(path: Path) -> dict[str, list]:
    """{entity path: its chunks} of an .rrd, read with rerun's own reader."""
    from rerun.chunk import RrdReader

    entities: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        entities.setdefault(chunk.entity_path, []).append(chunk)
    return entities


def rows(chunks: list, static: bool = False) -> int:
    return sum(c.num_rows for c in chunks if c.is_static == static)


def column(chunks: list, component: str) -> list:
    """Every temporal row's value of `component` (e.g. 'Scalars:scalars'), by frame."""
    found: dict[int, object] = {}
    for c in chunks:
        if c.is_static:
            continue
        batch = c.to_record_batch()
        if component in batch.schema.names:
            frames = batch.column("frame").to_pylist()
            for f, v in zip(frames, batch.column(component).to_pylist(), strict=True):
                found[f] = v
    return [found[f] for f in sorted(found)]


FRAME_ENTITIES = (
    "/world/camera",
    "/world/camera/image",
    "/world/camera/image/edges/convex",
    "/world/camera/image/edges/concave",
    "/world/camera/image/corners",
    "/world/camera/image/objects",
    "/world/trajectory/estimate",
    "/world/trajectory/groundtruth",
    "/tracking/path",
    "/tracking/planes",
)
MAP_ENTITIES = (
    "/world/map/planes",
    "/world/map/outlines",
    "/world/map/edges",
    "/world/map/corners",
    "/world/map/objects",
    "/world/map/sparse",
)


def check_recording(rrd: Path, run: Path, frames: int) -> dict[str, list]:
    """What both the live and the replayed recordings hold: one row per frame of every
    per-frame entity, the tracking paths of frames.jsonl, the final map of map.json, the
    ground truth, keyframes as in metrics.json."""
    entities = read_recording(rrd)
    for name in FRAME_ENTITIES:
        assert rows(entities.get(name, [])) == frames, (name, sorted(entities))
    for name in MAP_ENTITIES:
        assert rows(entities.get(name, [])) >= 1, name
    assert rows(entities["/world/camera/image"], static=True) == 1  # the Pinhole
    records = [json.loads(line) for line in (run / "frames.jsonl").read_text().splitlines()]
    codes = {p.value: k for k, p in enumerate(TrackingPath)}
    paths = column(entities["/tracking/path"], "Scalars:scalars")
    assert paths == [[float(codes[r["path"]])] for r in records][:frames]
    world_map = Map.load(run / "map.json")
    final = column(entities["/world/map/planes"], "Mesh3D:vertex_positions")[-1]
    np.testing.assert_allclose(np.array(final), world_map.plane_mesh().vertices, atol=1e-5)
    labels = column(entities["/world/map/objects"], "Points3D:labels")[-1]
    assert sorted(label.split()[0] for label in labels) == sorted(o.cls for o in world_map.objects)
    keyframes = sum(r["keyframe"] for r in records)
    assert len(column(entities["/world/keyframes"], "Points3D:positions")[-1]) == keyframes
    return entities


def test_live_run_recorded_to_rrd_reads_back(box_room: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from planeslam.app.viewer import RerunViewer

    rrd, out = tmp_path / "live.rrd", tmp_path / "out"
    with RerunViewer("test", rrd, map_every=1) as viewer:
        run_sequence(box_room, out, backend="merge", max_frames=FRAMES, observer=viewer)
    entities = check_recording(rrd, out, FRAMES)
    import cv2

    blob = column(entities["/world/camera/image"], "EncodedImage:blob")[0]
    shown = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)
    raw = cv2.imread(str(sorted((box_room / "rgb").iterdir())[0]), cv2.IMREAD_COLOR)
    assert shown.shape == raw.shape
    assert np.abs(shown.astype(float) - raw).mean() > 10  # the planes are tinted on it
    # the live map grows keyframe by keyframe, then the final map after the optimisation
    assert rows(entities["/world/map/planes"]) == FRAMES + 1
    assert rows(entities["/world/trajectory/final"]) == 1
    # the ground truth of the frames so far (the synthetic truth has a pose per frame)
    strips = column(entities["/world/trajectory/groundtruth"], "LineStrips3D:strips")
    assert [len(s[0]) for s in strips] == list(range(1, FRAMES + 1))


def test_a_growing_trajectory_sends_each_point_once_per_chunk(tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun")
    from planeslam.app.viewer import TIMELINE, GrowingPoints

    rrd = tmp_path / "strip.rrd"
    rec = rr.RecordingStream("test")
    rec.save(str(rrd))
    strip = GrowingPoints("strip", lambda p: rr.LineStrips3D([p]), chunk=4)
    points = np.arange(30, dtype=float).reshape(10, 3)
    for k, p in enumerate(points):
        rec.set_time(TIMELINE, sequence=k)
        strip.add(rec, p[None])
    rec.flush()
    del rec
    entities = read_recording(rrd)
    current = column(entities["/strip"], "LineStrips3D:strips")
    assert len(current) == 10 and max(len(s[0]) for s in current) <= 4
    past = [column(entities[f"/strip/past/{k}"], "LineStrips3D:strips") for k in range(2)]
    assert all(len(rows_) == 1 for rows_ in past)  # each full chunk logged once
    drawn = [np.array(c[0][0]) for c in past] + [np.array(current[-1][0])]
    # the chunks share their end points and together are the whole strip
    joined = np.concatenate([drawn[0]] + [d[1:] for d in drawn[1:]])
    np.testing.assert_array_equal(joined, points)


def test_view_replays_a_finished_run(run_dir: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    rrd = tmp_path / "replay.rrd"
    assert main(["-q", "view", str(run_dir), "--rrd", str(rrd)]) == 0
    entities = check_recording(rrd, run_dir, FRAMES)
    assert rows(entities["/world/map/planes"]) == 1  # only the final map is known


@pytest.fixture
def no_display(monkeypatch: pytest.MonkeyPatch) -> None:
    """A machine without a display (as CI)."""
    pytest.importorskip("rerun")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


def test_view_without_display_records_into_the_run_folder(
    run_dir: Path, tmp_path: Path, no_display: None, capsys
) -> None:
    folder = tmp_path / "run"
    shutil.copytree(run_dir, folder)
    assert main(["-q", "view", str(folder), "--every", "4"]) == 0
    assert f"open it with: rerun {folder / 'run.rrd'}" in capsys.readouterr().out
    assert rows(read_recording(folder / "run.rrd")["/world/camera"]) == FRAMES // 4


@pytest.mark.data
def test_tum_run_recorded_and_viewed(tmp_path: Path) -> None:
    """The issue's check on real data: `planeslam run tum_fr1_desk_9f --rrd`, then
    `planeslam view` of the run, both read back."""
    pytest.importorskip("rerun")
    sequence = shared_sequence("tum_fr1_desk_9f")
    out, live, replay = tmp_path / "out", tmp_path / "live.rrd", tmp_path / "replay.rrd"
    assert main(["-q", "run", str(sequence), "--out", str(out), "--rrd", str(live)]) == 0
    frames = len((out / "frames.jsonl").read_text().splitlines())
    assert frames == 9
    check_recording(live, out, frames)
    assert main(["-q", "view", str(out), "--rrd", str(replay)]) == 0
    check_recording(replay, out, frames)


def test_live_viewer_without_display_is_a_one_line_error(
    box_room: Path, tmp_path: Path, no_display: None, capsys
) -> None:
    out = tmp_path / "out"
    assert main(["-q", "run", str(box_room), "--viewer", "--out", str(out)]) == 2
    assert "no display to open the rerun viewer in" in capsys.readouterr().err
    assert not out.exists()  # refused before the run started
