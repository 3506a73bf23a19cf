"""Fault corpus, hostile inputs and careless use: code planted in the working directory or
the dataset, symbolic links planted in the output folder, two runs in one folder, a run
into a used folder, and small crafted files that would hang or exhaust memory."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from planeslam.app.cli import build_parser
from planeslam.app.run_folder import claim_run_folder
from planeslam.config import explain_config
from planeslam.core.camera import CameraConfig
from planeslam.core.config import parse_override
from planeslam.core.errors import (
    ConfigError,
    DatasetFormatError,
    EvaluationError,
    FrameReadError,
    MapError,
    OutputFolderError,
)
from planeslam.core.safe_files import FolderLock, LineWriter, atomic_output, open_output
from planeslam.eval.report import read_frame_records
from planeslam.io.dataset import TumDataset
from planeslam.io.rosbag import RosBagDataset, camera_from_info
from planeslam.mapping.world_map import Map
from tests.corpus.cases import (
    SMALL_CAMERA,
    check_run_outputs,
    expect_cli_error,
    expect_error,
    expect_handled,
    frame_files,
    synth_sequence,
)
from tests.corpus.tally import Outcome, record

pytestmark = pytest.mark.unit

PLANTED = ("gtsam", "numpy", "scipy", "cv2", "open3d", "yaml")
"""Modules the run or its worker imports: a file of each name is planted."""
PLANETSLAM_BIN = Path(sys.executable).parent / "planeslam"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_sequence(tmp_path_factory.mktemp("safety") / "seq", frames=4).out_dir


def planeslam_cli(args: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """The installed `planeslam` script (as a user starts it: its own folder, not the
    working directory, first on sys.path) run in `cwd`."""
    return subprocess.run(
        [str(PLANETSLAM_BIN), *args], capture_output=True, text=True, timeout=timeout, cwd=cwd
    )


# ------------------------------------------------------------------ code from the working dir


@pytest.mark.integration
def test_no_code_from_the_working_directory_or_the_dataset_runs(
    pristine: Path, tmp_path: Path
) -> None:
    """`cd DATASET/inner && planeslam run ..`: modules named like dependencies in the working
    directory and in the dataset never run (the worker started `python -c`, which put the
    working directory first on its path), and the default output folder is out/<dataset
    name>, not `..` (which replaced the user's config.yaml there)."""
    import shutil

    dataset = tmp_path / "seq"
    shutil.copytree(pristine, dataset)
    inner = dataset / "inner"
    inner.mkdir()
    marker = tmp_path / "planted-code-ran"
    for folder in (dataset, inner):
        for name in PLANTED:
            (folder / f"{name}.py").write_text(
                f"open({str(marker)!r}, 'a').write({name!r} + '\\n')\nraise SystemExit(97)\n"
            )
    (inner / "config.yaml").write_text("mine: true\n")

    def isolated() -> None:
        result = planeslam_cli(["run", "..", "-q", "--backend", "isam2"], cwd=inner)
        assert result.returncode == 0, result.stderr[-2000:]
        assert not marker.exists(), f"planted modules ran: {marker.read_text()}"
        assert (inner / "config.yaml").read_text() == "mine: true\n"
        assert (inner / "out" / "seq" / "run.json").is_file()

    expect_handled("modules planted in the working directory and the dataset", isolated)


def test_spawned_workers_of_the_cli_skip_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """multiprocessing's spawn starts `python -c ...`: the working directory came first on
    the worker's path, so a planted multiprocessing.py ran in every suite worker."""
    from planeslam.app.cli import main
    from planeslam.eval.executors import Job, run_in_processes

    marker = tmp_path / "planted-code-ran"
    (tmp_path / "multiprocessing.py").write_text(
        f"open({str(marker)!r}, 'a').write('ran')\nraise SystemExit(97)\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PYTHONSAFEPATH", raising=False)  # restored after the test
    with pytest.raises(SystemExit):
        main(["--version"])

    def isolated() -> None:
        ((_, pid),) = list(run_in_processes([Job(os.getpid, ())], 1))
        assert isinstance(pid, int) and pid != os.getpid() and not marker.exists()

    expect_handled("multiprocessing.py planted where the suite runs", isolated)


# ------------------------------------------------------------------ links in the output folder


def test_writers_never_follow_a_planted_link(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "out"
    out.mkdir()
    for name in ("frames.jsonl", "map.json", "part"):
        (out / name).symlink_to(victim)

    expect_error(
        "frames.jsonl a link to another file",
        OSError,
        r"frames\.jsonl",
        lambda: LineWriter(out / "frames.jsonl"),
    )
    expect_error(
        "download .part a link", OSError, "symbolic link", lambda: open_output(out / "part", True)
    )

    def replaced_not_followed() -> None:
        with atomic_output(out / "map.json") as tmp:
            tmp.write_text("{}")
        assert not (out / "map.json").is_symlink() and (out / "map.json").read_text() == "{}"

    expect_handled("map.json a link to another file", replaced_not_followed)
    assert victim.read_text() == "precious\n"


@pytest.mark.integration
def test_a_run_writes_inside_its_folder_and_reports_only_its_pictures(
    pristine: Path, tmp_path: Path
) -> None:
    """Links planted under a run's file names are moved aside, never written through; the
    report embeds the run's own pictures, not every *.png of the folder."""
    victims = {}
    out = tmp_path / "out"
    out.mkdir()
    for name in ("trajectory.txt", "frames.jsonl", "metrics.json", "report.html", "map.png"):
        victims[name] = tmp_path / f"victim-{name}"
        victims[name].write_text("precious\n")
        (out / name).symlink_to(victims[name])
    secret = tmp_path / "secret.txt"
    secret.write_bytes(b"SECRET-BYTES-" * 8)
    (out / "stolen.png").symlink_to(secret)
    (out / "holiday.png").write_bytes(b"\x89PNG\r\n\x1a\nNOT-OURS" * 4)

    def inside() -> None:
        result = planeslam_cli(["run", str(pristine), "--out", str(out), "-q"], cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-2000:]
        assert all(v.read_text() == "precious\n" for v in victims.values())
        page = (out / "report.html").read_text()
        for foreign in (secret.read_bytes(), (out / "holiday.png").read_bytes()):
            assert base64.b64encode(foreign).decode()[:40] not in page
        assert "map.png" not in {p.name for p in out.iterdir() if p.is_symlink()}

    expect_handled("links planted in the output folder", inside)
    check_run_outputs("links planted in the output folder", out)


# ------------------------------------------------------------------ one run per folder


@pytest.mark.integration
def test_a_live_run_holds_its_folder(pristine: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    with FolderLock(out):
        result = planeslam_cli(["run", str(pristine), "--out", str(out)], cwd=tmp_path)
    expect_cli_error(
        "second run into a live run's folder", result, rf"another run \(pid {os.getpid()}\)"
    )
    assert not (out / "run.json").exists()
    with FolderLock(out):  # released with its holder
        pass


@pytest.mark.integration
def test_a_new_run_moves_the_previous_one_aside_after_checking_its_inputs(
    pristine: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    first = planeslam_cli(["run", str(pristine), "--out", str(out), "-q"], cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    kept = {n: (out / n).read_bytes() for n in ("run.json", "config.yaml", "trajectory.txt")}
    bad_map = tmp_path / "bad.json"
    bad_map.write_text('{"schema": "planeslam.map/1", "frame": "world", "planes": [' * 40)
    refused = planeslam_cli(
        ["run", str(pristine), "--out", str(out), "--map", str(bad_map)], cwd=tmp_path
    )
    expect_cli_error("a run into a used folder with a bad --map", refused, r"bad\.json")
    assert {n: (out / n).read_bytes() for n in kept} == kept  # nothing replaced

    def moved_aside() -> None:
        second = planeslam_cli(["run", str(pristine), "--out", str(out), "-q"], cwd=tmp_path)
        assert second.returncode == 0, second.stderr[-2000:]
        (aside,) = out.glob("previous-*")
        assert {n: (aside / n).read_bytes() for n in kept} == kept
        assert (aside / "metrics.json").is_file() and (aside / "report.html").is_file()

    expect_handled("a run into a used folder", moved_aside)
    check_run_outputs("a run into a used folder", out)


def test_claim_moves_only_run_files(tmp_path: Path) -> None:
    (tmp_path / "frames.jsonl").write_text("{}\n")
    (tmp_path / "notes.txt").write_text("mine\n")
    with claim_run_folder(tmp_path) as aside:
        assert aside is not None and (aside / "frames.jsonl").is_file()
    assert (tmp_path / "notes.txt").read_text() == "mine\n"
    with claim_run_folder(tmp_path) as again:
        assert again is None
    (tmp_path / "groundtruth.txt").write_text("# the dataset's\n")  # --out is the dataset
    with claim_run_folder(tmp_path, [tmp_path / "groundtruth.txt"]) as kept:
        assert kept is None and (tmp_path / "groundtruth.txt").is_file()


@pytest.mark.integration
def test_synth_refuses_a_folder_in_use(tmp_path: Path) -> None:
    (tmp_path / "rgb.txt").write_text("# someone's list\n")
    result = planeslam_cli(["synth", "box_room_circle", str(tmp_path), "--frames", "2"], tmp_path)
    expect_cli_error("synth into a non-empty folder", result, r"not empty.*--overwrite")
    assert (tmp_path / "rgb.txt").read_text() == "# someone's list\n"


# ------------------------------------------------------------------ bounded parsing


def _alias_bomb(levels: int = 9) -> str:
    text = 'fx: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    previous = "a"
    for name in "bcdefghijk"[: levels - 1]:
        text += f"{name}: &{name} [{', '.join([f'*{previous}'] * 9)}]\n"
        previous = name
    return text


def test_a_yaml_alias_bomb_is_refused_at_once(pristine: Path, tmp_path: Path) -> None:
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(pristine, seq)
    (seq / "camera.yaml").write_text(_alias_bomb())
    start = time.perf_counter()
    expect_error(
        "camera.yaml alias bomb",
        ConfigError,
        r"camera\.yaml.*alias bomb",
        lambda: explain_config(seq),
    )
    assert time.perf_counter() - start < 2.0


DEEP = 5000


@pytest.mark.parametrize(
    "case, call, error, pattern",
    [
        (
            "--set nested deeply",
            lambda p: parse_override("camera.fx=" + "[" * DEEP),
            ConfigError,
            "nested deeper",
        ),
        (
            "config nested deeply",
            lambda p: explain_config(config=_write(p / "c.yaml", "run: " + "[" * DEEP)),
            ConfigError,
            "nested deeper",
        ),
        (
            "map.json nested deeply",
            lambda p: Map.load(_write(p / "m.json", "[" * DEEP + "]" * DEEP)),
            MapError,
            "nested deeper",
        ),
        (
            "map.json with 1e400",
            lambda p: Map.load(_write(p / "m.json", '{"schema": 1, "planes": [{"d": 1e400}]}')),
            MapError,
            r"planes\[0\]\.d: expected a finite",
        ),
        (
            "map.json with NaN",
            lambda p: Map.load(_write(p / "m.json", '{"a": NaN}')),
            MapError,
            "NaN is not a JSON number",
        ),
        (
            "map.json with a huge int",
            lambda p: Map.load(_write(p / "m.json", '{"a": ' + "9" * 5000 + "}")),
            MapError,
            r"m\.json",
        ),
        (
            "map.json not UTF-8",
            lambda p: Map.load(_write(p / "m.json", b'{"a": "\xff"}')),
            MapError,
            "not UTF-8",
        ),
        (
            "camera.yaml 100000 wide",
            lambda p: CameraConfig(width=100_000, height=480),
            ConfigError,
            "100000x480 outside",
        ),
        (
            "frames.jsonl index not a number",
            lambda p: read_frame_records(
                _write(p / "f.jsonl", '{"index": "x", "path": "odometry"}\n')
            ),
            EvaluationError,
            r"f\.jsonl:1: index must be a whole number",
        ),
        (
            "frames.jsonl timestamp 1e999",
            lambda p: read_frame_records(
                _write(p / "f.jsonl", '{"index": 0, "path": "lost", "timestamp": 1e999}\n')
            ),
            EvaluationError,
            "timestamp: expected a finite",
        ),
        (
            "frames.jsonl not UTF-8",
            lambda p: read_frame_records(_write(p / "f.jsonl", b"\xfe\xff\n")),
            EvaluationError,
            "not UTF-8",
        ),
    ],
)
def test_crafted_files_are_refused_in_one_line(tmp_path: Path, case, call, error, pattern) -> None:
    expect_error(case, error, pattern, lambda: call(tmp_path))


def _write(path: Path, content: str | bytes) -> Path:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path


def test_camera_info_of_a_huge_image_is_refused() -> None:
    msg = SimpleNamespace(
        k=[525, 0, 320, 0, 525, 240, 0, 0, 1],
        d=[],
        width=2**31,
        height=2**31,
        distortion_model="plumb_bob",
    )
    expect_error(
        "camera_info 2^31 pixels a side",
        DatasetFormatError,
        "outside 1..8192",
        lambda: camera_from_info(msg, SMALL_CAMERA, "bag /camera_info"),
    )


def test_images_too_large_are_refused_before_decoding(pristine: Path, tmp_path: Path) -> None:
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(pristine, seq)
    _, depth0 = frame_files(seq, 0)
    rgb1, _ = frame_files(seq, 1)
    data = bytearray(depth0.read_bytes())
    data[16:24] = (200_000).to_bytes(4, "big") * 2  # IHDR width and height
    depth0.write_bytes(bytes(data))
    with open(rgb1, "r+b") as fh:  # a sparse file of 8 GiB: nothing to read, much to allocate
        fh.truncate(8 << 30)
    dataset = TumDataset(seq, SMALL_CAMERA)
    expect_error("PNG header 200000x200000", FrameReadError, "outside 1..8192", lambda: dataset[0])
    expect_error("sparse 8 GiB image", FrameReadError, "bytes, more than", lambda: dataset[1])


def test_text_files_that_are_not_utf8_are_named(pristine: Path, tmp_path: Path) -> None:
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(pristine, seq)
    (seq / "groundtruth.txt").write_bytes(b"# \xff\xfe\n1.0 0 0 0 0 0 0 1\n")

    def warned() -> None:
        assert "not UTF-8" in TumDataset(seq, SMALL_CAMERA).groundtruth_error

    expect_handled("groundtruth.txt not UTF-8", warned)
    (seq / "associations.txt").write_bytes(b"\xc3\x28 rgb/x.png\n")
    expect_error(
        "associations.txt not UTF-8",
        DatasetFormatError,
        r"associations\.txt: not UTF-8 text \(byte 0xc3 at offset 0\)",
        lambda: TumDataset(seq, SMALL_CAMERA),
    )


def test_a_bag_of_random_bytes_is_named(tmp_path: Path) -> None:
    bag = tmp_path / "random.bag"
    bag.write_bytes(np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    expect_error(
        "bag of random bytes",
        DatasetFormatError,
        r"random\.bag: not a readable ROS bag",
        lambda: RosBagDataset(bag, SMALL_CAMERA),
    )


# ------------------------------------------------------------------ command-line values


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["demo", "--seed", "-1"], "--seed"),
        (["run", "x", "--seed", "-5"], "--seed"),
        (["run", "x", "--every", "0"], "--every"),
        (["eval", "a", "b", "--rpe-delta", "inf"], "--rpe-delta"),
        (["eval", "a", "b", "--max-dt", "nan"], "--max-dt"),
        (["mesh", "r", "--voxel", "1e-9"], "--voxel"),
        (["synth", "box_room_circle", "o", "--frames", "0"], "--frames"),
        (["view", "r", "--every", "-2"], "--every"),
    ],
)
def test_numeric_flags_are_range_checked(argv, flag, capsys) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err.strip().splitlines()[-1]
    ok = info.value.code == 2 and f"argument {flag}: expected" in err
    record(f"flag {' '.join(argv[-2:])}", Outcome.CLEAN_ERROR if ok else Outcome.CRASH)
    assert ok, err


@pytest.mark.integration
def test_rrd_naming_a_folder_and_a_dataset_link_loop(pristine: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    result = planeslam_cli(["run", "loop", "--out", "o"], cwd=tmp_path)
    expect_cli_error("dataset a symbolic link loop", result, r"loop: symbolic link loop")
    result = planeslam_cli(
        ["run", str(pristine), "--out", "o", "--rrd", str(tmp_path), "-q"], cwd=tmp_path
    )
    expect_cli_error("--rrd naming a folder", result, r"is a folder; the recording needs a file")


def test_run_json_naming_an_impossible_path(tmp_path: Path) -> None:
    from planeslam.eval.run_info import read_run_info

    (tmp_path / "run.json").write_text(
        json.dumps({"schema": "planeslam.run/1", "dataset": "a\u0000b", "backend": "isam2"})
    )
    expect_error(
        "run.json dataset with a NUL", EvaluationError, "NUL", lambda: read_run_info(tmp_path)
    )


def test_report_frames_records_stay_json(tmp_path: Path) -> None:
    """frames.jsonl lines written by a run read back (the reader's checks accept them)."""
    path = tmp_path / "frames.jsonl"
    path.write_text(json.dumps({"index": 0, "timestamp": 1.5, "path": "first"}) + "\n")
    assert read_frame_records(path)[0]["timestamp"] == 1.5


def test_folder_lock_names_the_holder(tmp_path: Path) -> None:
    with FolderLock(tmp_path):
        expect_error(
            "folder lock held by this process",
            OutputFolderError,
            rf"pid {os.getpid()}",
            lambda: FolderLock(tmp_path).acquire(),
        )
