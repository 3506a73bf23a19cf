"""Fault corpus, whole runs (`run_sequence` in this process): frames missing or unreadable
in the middle, one-frame and two-frame runs, foreign or malformed truth files, Ctrl-C,
the backend worker killed, iSAM2's indeterminate systems, and outputs that are whole,
atomic and of the usual mode whatever happens."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import stat
import time
from pathlib import Path

import gtsam
import pytest

from planeslam.app.runner import run_sequence
from planeslam.core.errors import DatasetFormatError, PlaneSlamError
from planeslam.core.safe_files import LineWriter, atomic_output
from planeslam.slam import SLAM
from tests.corpus.cases import (
    check_run_outputs,
    expect_error,
    expect_handled,
    frame_files,
    rewrite_rows,
    synth_sequence,
    truncate,
    umask,
)

pytestmark = pytest.mark.integration  # the fault corpus on whole runs

FRAMES = 12


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_sequence(tmp_path_factory.mktemp("pristine") / "seq", frames=FRAMES).out_dir


@pytest.fixture
def seq(pristine: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(pristine, tmp_path / "seq"))


def run(seq: Path, out: Path, **kwargs):
    kwargs.setdefault("backend", "merge")
    return run_sequence(seq, out, **kwargs)


def without_groundtruth(seq: Path) -> Path:
    """The sequence without evaluation (its plots take longer than the run)."""
    (seq / "groundtruth.txt").unlink()
    return seq


# ------------------------------------------------------------------ frames that cannot be read


@pytest.mark.parametrize(
    "case, damage",
    [
        ("an image missing in the middle of a run", lambda p: p.unlink()),
        ("a truncated image in the middle of a run", truncate),
    ],
)
def test_unreadable_frames_are_skipped_with_a_warning(
    seq: Path, tmp_path: Path, case: str, damage, caplog: pytest.LogCaptureFixture
) -> None:
    damage(frame_files(without_groundtruth(seq), 3)[1])

    def skipped() -> None:
        with caplog.at_level(logging.WARNING):
            result = run(seq, tmp_path / "out")
        assert result.summary.frames == FRAMES - 1 and result.summary.skipped_frames == 1
        assert "frame 3 skipped: " in caplog.text and "depth/" in caplog.text
        assert "1 frames skipped" in result.text()

    expect_handled(case, skipped)
    check_run_outputs(case, tmp_path / "out", frames=FRAMES - 1)


def test_a_run_with_no_readable_frame_is_a_clean_error(seq: Path, tmp_path: Path) -> None:
    for k in range(FRAMES):
        truncate(frame_files(seq, k)[0])
    case = "no frame of a run can be read"
    expect_error(
        case,
        DatasetFormatError,
        rf"seq: none of the {FRAMES} frames could be read",
        lambda: run(seq, tmp_path / "out"),
    )
    check_run_outputs(case, tmp_path / "out", frames=0)


# ------------------------------------------------------------------ short runs, evaluation


def test_one_frame_and_two_frame_runs_finish_with_a_warning(seq: Path, tmp_path: Path) -> None:
    for frames in (1, 2):
        case = f"a {frames}-frame run"

        def short(frames=frames) -> None:
            result = run(seq, tmp_path / f"out{frames}", max_frames=frames)
            assert result.summary.frames == frames and result.evaluation is None
            (warning,) = result.warnings  # 'no ATE (N of N frames tracked): ...'
            assert warning.endswith(
                f": only {frames} pose(s) of {tmp_path}/out{frames}/trajectory.txt "
                f"within 0.02 s of {seq}/groundtruth.txt (need at least 3 for an SE(3) "
                "alignment)"
            )
            assert (tmp_path / f"out{frames}" / "report.html").is_file()

        expect_handled(case, short)
        check_run_outputs(case, tmp_path / f"out{frames}", frames=frames)


def test_a_foreign_truth_json_is_a_warning(seq: Path, tmp_path: Path) -> None:
    (seq / "truth.json").write_text('{"format": "another tool", "boxes": [[1, 2, 3]]}\n')
    case = "a truth.json of another tool's format"

    def warned() -> None:
        result = run(seq, tmp_path / "out")
        assert result.evaluation is not None and result.evaluation.evaluation.ate_rmse_m < 0.05
        assert result.warnings == (
            f"object sizes not evaluated: {seq}/truth.json: expected a mapping with an "
            "'objects' list",
        )
        assert "warning: object sizes not evaluated" in result.text()

    expect_handled(case, warned)
    check_run_outputs(case, tmp_path / "out", frames=FRAMES)


def test_a_malformed_ground_truth_leaves_the_run_unevaluated(seq: Path, tmp_path: Path) -> None:
    rewrite_rows(seq / "groundtruth.txt", lambda rows: [*rows[:2], "1.0 0 0 0 0 0 0 2", *rows[2:]])
    case = "a ground truth with a bad quaternion beside the data"

    def unevaluated() -> None:
        result = run(seq, tmp_path / "out")
        assert result.evaluation is None
        warning = result.warnings[0]
        assert warning.startswith(f"not evaluated: {seq}/groundtruth.txt:3: quaternion qx qy")
        assert "has norm 2, expected a unit quaternion" in warning

    expect_handled(case, unevaluated)
    check_run_outputs(case, tmp_path / "out", frames=FRAMES)


# ------------------------------------------------------------------ interruptions and failures


def _stop_at(monkeypatch: pytest.MonkeyPatch, frame: int, error: BaseException, hook=None) -> None:
    """SLAM.process raises `error` (or calls `hook(slam)`) when it is given frame `frame`."""
    original = SLAM.process

    def process(self, *args, **kwargs):
        if self.frames == frame:
            if hook is None:
                raise error
            hook(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(SLAM, "process", process)


@pytest.mark.parametrize("backend", ["merge", "isam2"])
def test_ctrl_c_keeps_map_metrics_and_trajectory(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: str
) -> None:
    _stop_at(monkeypatch, 6, KeyboardInterrupt())
    case = f"Ctrl-C after 6 frames ({backend})"
    out = tmp_path / "out"

    def interrupted() -> None:
        with pytest.raises(KeyboardInterrupt):
            run(without_groundtruth(seq), out, backend=backend)

    expect_handled(case, interrupted)
    found = check_run_outputs(case, out, frames=6)
    metrics = found["metrics"]
    assert metrics.fps > 0 and metrics.keyframes >= 1 and sum(metrics.tracking_paths.values()) == 6
    assert found["map"].objects, "the objects of the frames so far are in map.json"


def test_a_killed_backend_worker_ends_the_run_with_a_clear_error(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _stop_at(monkeypatch, 4, KeyboardInterrupt(), hook=lambda slam: _kill(slam.backend._process))
    case = "the backend worker killed during a run"
    start = time.monotonic()
    expect_error(
        case,
        PlaneSlamError,
        r"the iSAM2 backend process (died \(exit code -9\)|is gone)",
        lambda: run(without_groundtruth(seq), tmp_path / "out", backend="isam2"),
    )
    assert time.monotonic() - start < 60, "no hang"
    check_run_outputs(case, tmp_path / "out", frames=4)


def _kill(process) -> None:
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=10)


class _FlakyISAM2(gtsam.ISAM2):
    """An ISAM2 whose updates raise gtsam's indeterminate-system error when told to."""

    fail: list[bool] = []
    """One entry per update with new factors, popped: True raises."""

    def update(self, *args, **kwargs):
        if args and self.fail and self.fail.pop(0):
            raise RuntimeError(
                "Indeterminant linear system detected while working near variable "
                "8646911284551352320 (Symbol: x0)."
            )
        return super().update(*args, **kwargs)


def _isam2_inline_config(tmp_path: Path) -> Path:
    path = tmp_path / "inline.yaml"
    path.write_text("backend:\n  separate_process: false\n")
    return path


def test_indeterminate_isam2_updates_are_handled(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(gtsam, "ISAM2", _FlakyISAM2)
    config = _isam2_inline_config(tmp_path)
    monkeypatch.setattr(_FlakyISAM2, "fail", [False, False, True])  # the third keyframe
    case = "an indeterminate system in one iSAM2 update"

    def handled() -> None:
        result = run(seq, tmp_path / "out", backend="isam2", config=config)
        assert result.metrics.backend["failures"] >= 1
        assert result.evaluation is not None and result.evaluation.evaluation.ate_rmse_m < 0.05

    expect_handled(case, handled)
    check_run_outputs(case, tmp_path / "out", frames=FRAMES)
    monkeypatch.setattr(_FlakyISAM2, "fail", [False] + [True] * 50)  # never again
    case = "iSAM2 indeterminate even with odometry only"
    expect_error(
        case,
        PlaneSlamError,
        r"iSAM2.*Indeterminant linear system detected while working near variable",
        lambda: run(seq, tmp_path / "out2", backend="isam2", config=config),
    )
    check_run_outputs(case, tmp_path / "out2")


# ------------------------------------------------------------------ outputs: atomic, mode


def test_outputs_have_the_usual_mode_and_no_temporary_files(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    run(seq, out)
    expected = 0o666 & ~umask()
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in out.iterdir() if p.is_file()}
    assert modes["map.json"] == expected, f"map.json mode {modes['map.json']:o}"
    assert {name: mode for name, mode in modes.items() if mode != expected} == {}
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_a_failed_whole_file_write_leaves_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "map.json"
    path.write_text('{"old": true}')

    def half_written() -> None:
        with atomic_output(path) as tmp:
            tmp.write_text('{"new": ')
            raise OSError(28, "No space left on device")

    exc = expect_error(
        "a whole-file output cut short", OSError, r"No space left on device", half_written
    )
    assert exc.filename == str(path)  # names the file the user knows, not the temporary
    assert path.read_text() == '{"old": true}' and os.listdir(tmp_path) == ["map.json"]


def test_a_line_cut_short_is_taken_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    writer = LineWriter(tmp_path / "frames.jsonl")
    writer.write_line('{"index": 0}')
    raw = writer._fh
    real_write = raw.write

    def full_disk(data) -> int:
        real_write(bytes(data[:5]))  # part of the line reaches the disk, then it is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(writer, "_fh", _Wrapped(raw, full_disk))
    expect_error(
        "a line output cut short by a full disk",
        OSError,
        r"No space left on device",
        lambda: writer.write_line('{"index": 1}'),
    )
    writer.close()
    assert (tmp_path / "frames.jsonl").read_text() == '{"index": 0}\n'


class _Wrapped:
    def __init__(self, raw, write) -> None:
        self._raw, self.write = raw, write

    def __getattr__(self, name):
        return getattr(self._raw, name)


def test_three_dropped_slams_leave_no_worker(seq: Path) -> None:
    from planeslam.config import resolve_config

    cfg = resolve_config(seq)

    def no_worker_left() -> None:
        slams = [SLAM(cfg, "isam2") for _ in range(3)]
        processes = [s.backend._process for s in slams]
        assert all(p.poll() is None for p in processes)
        del slams
        for p in processes:
            assert p.wait(timeout=10) is not None

    expect_handled("three SLAMs dropped without close()", no_worker_left)
