"""Fault corpus through the command line (child processes): SIGTERM and Ctrl-C at random
points, kill -9, the backend worker killed, a disk that fills (RLIMIT_FSIZE), an
unwritable --out, short runs; and the CLI the README describes (--camera on every
command that reads a dataset, flags after the sub-command, -q, --version, presets)."""

from __future__ import annotations

import re
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from planeslam.app.cli import build_parser, main
from tests.corpus.cases import (
    REPO,
    check_run_outputs,
    child_pids,
    cli,
    exited,
    expect_cli_error,
    expect_handled,
    synth_sequence,
)

pytestmark = pytest.mark.integration  # the fault corpus through the CLI: signals, kills, full disks

FRAMES = 14


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_sequence(tmp_path_factory.mktemp("cli") / "seq", frames=FRAMES).out_dir


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_run(seq: Path, out: Path, *extra: str, **kwargs) -> subprocess.Popen[str]:
    """`planeslam run` in a child with Ctrl-C's default handling: a test run started in the
    background by a shell without job control inherits SIGINT ignored, and Python keeps it
    so (as a shell's background job should)."""
    return subprocess.Popen(
        [sys.executable, "-m", "planeslam.app.cli", "run", str(seq), "--out", str(out), "-q"]
        + list(extra),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        preexec_fn=_default_sigint,
        **kwargs,
    )


def frames_written(out: Path) -> int:
    path = out / "frames.jsonl"
    return path.read_text().count("\n") if path.is_file() else 0


def wait_for(condition, process: subprocess.Popen[str], timeout: float = 120) -> None:
    """Poll `condition()` until true; fail if the process ends first or time runs out."""
    end = time.monotonic() + timeout
    while not condition():
        if process.poll() is not None:
            pytest.fail(f"the run ended (exit {process.returncode}) first: {process.stderr.read()}")
        if time.monotonic() > end:
            process.kill()
            pytest.fail("timed out waiting for the run")
        time.sleep(0.02)


# ------------------------------------------------------------------ signals at random points

SIGNAL_CASES = [
    (signal.SIGTERM, 0, 143, "stopped by SIGTERM"),
    (signal.SIGINT, 1, 130, "interrupted"),
]
"""Two random points here; `make soak` tries many more."""


@pytest.mark.slow
@pytest.mark.parametrize("signum, seed, code, message", SIGNAL_CASES)
def test_a_signal_at_a_random_point_keeps_every_output(
    seq: Path, tmp_path: Path, signum: int, seed: int, code: int, message: str
) -> None:
    rng = np.random.default_rng(seed)
    after_frames = int(rng.integers(1, FRAMES - 4))
    delay_s = float(rng.uniform(0.0, 0.15))
    out = tmp_path / "out"
    process = start_run(seq, out)
    wait_for(lambda: frames_written(out) >= after_frames, process)
    workers = child_pids(process.pid)
    time.sleep(delay_s)
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
    result = subprocess.CompletedProcess(process.args, process.returncode, "", stderr)
    case = f"{signal.Signals(signum).name} after {after_frames} frames + {delay_s:.2f} s"
    expect_cli_error(case, result, rf"planeslam: {message}; outputs written so far are kept", code)
    found = check_run_outputs(case, out)
    assert found["metrics"].frames >= after_frames
    assert all(exited(pid) for pid in workers), "the backend worker exited"


@pytest.mark.slow
def test_sigterm_while_starting_up_is_clean(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    process = start_run(seq, out)
    wait_for(lambda: (out / "config.yaml").is_file(), process)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    result = subprocess.CompletedProcess(process.args, process.returncode, "", stderr)
    expect_cli_error("SIGTERM while starting up", result, r"stopped by SIGTERM", 143)


@pytest.mark.slow
def test_kill_9_keeps_every_finished_frame(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    process = start_run(seq, out)
    wait_for(lambda: frames_written(out) >= 3, process)
    workers = child_pids(process.pid)
    time.sleep(0.05)
    process.kill()
    process.communicate(timeout=30)
    case = "kill -9 during a run"
    expect_handled(case, lambda: None)
    found = check_run_outputs(case, out, complete=False)
    assert len(found["records"]) >= 3
    assert workers and all(exited(pid) for pid in workers), "the orphaned worker exited"


# ------------------------------------------------------------------ full disk, unwritable out


@pytest.mark.slow
def test_a_disk_that_fills_mid_run_gives_one_line_and_whole_lines(
    seq: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    process = start_run(seq, out, "--backend", "merge")
    wait_for(lambda: frames_written(out) >= 2, process)
    limit = (out / "frames.jsonl").stat().st_size + 700  # room for about one more frame
    resource.prlimit(process.pid, resource.RLIMIT_FSIZE, (limit, limit))  # EFBIG from now on
    _, stderr = process.communicate(timeout=120)
    result = subprocess.CompletedProcess(process.args, process.returncode, "", stderr)
    case = "a disk that fills during a run (per-frame logs)"
    expect_cli_error(case, result, rf"error: {out}/[a-z_.]+: File too large")
    found = check_run_outputs(case, out, complete=False)
    assert 2 <= len(found["records"]) < FRAMES


@pytest.mark.slow
def test_a_disk_that_fills_at_the_end_leaves_no_partial_file(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    limit = 20_000  # above config.yaml and the per-frame logs, below map.json
    result = cli(
        ["run", str(seq), "--out", str(out), "-q", "--backend", "merge"],
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)),
    )
    case = "a disk that fills while the final files are written"
    expect_cli_error(case, result, rf"error: {out}/map.json: File too large")
    found = check_run_outputs(case, out, complete=False, frames=FRAMES)
    tracked = sum(r["path"] != "lost" for r in found["records"])
    assert found["trajectory_rows"] == tracked and not (out / "map.json").exists()


def run_main(args: list[str], capsys: pytest.CaptureFixture[str]):
    """`planeslam ARGS` in this process -> CompletedProcess(code, stdout, stderr)."""
    code = main(args)
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, captured.out, captured.err)


def test_an_unwritable_out_is_one_line(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    run = ["run", str(seq), "--backend", "merge", "--out"]
    expect_cli_error(
        "--out under a file",
        run_main([*run, str(blocker / "out")], capsys),
        rf"error: {blocker}/out: Not a directory",
    )
    expect_cli_error(
        "--out is a file", run_main([*run, str(blocker)], capsys), rf"error: {blocker}: File exists"
    )


# ------------------------------------------------------------------ short runs and the CLI


def test_short_runs_exit_0_with_a_warning_and_q_silences_the_bar(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    quiet = run_main(
        ["run", str(seq), "--out", str(tmp_path / "q"), "--max-frames", "2", "-q"], capsys
    )
    loud = run_main(["run", str(seq), "--out", str(tmp_path / "v"), "--max-frames", "1"], capsys)

    def outcome() -> None:
        assert quiet.returncode == 0 and loud.returncode == 0, quiet.stderr + loud.stderr
        assert re.search(r"warning: .*: only 2 pose\(s\) of .*need at least 3", quiet.stdout)
        assert re.search(r"warning: .*: only 1 pose\(s\) of .*need at least 3", loud.stdout)
        assert "frame/s" not in quiet.stderr and "\r" not in quiet.stderr  # no progress bar
        assert "frame" in loud.stderr  # the bar, for contrast

    expect_handled("--max-frames 2 / 1 through the CLI, -q after the sub-command", outcome)
    check_run_outputs("--max-frames 2 (CLI)", tmp_path / "q", frames=2)


def test_cli_errors_for_bad_inputs(
    seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = Path(shutil.copytree(seq, tmp_path / "bad"))
    (bad / "camera.yaml").write_text("fx: wide\n")
    expect_cli_error(
        "malformed camera.yaml (CLI)",
        run_main(["run", str(bad), "--out", str(tmp_path / "o1")], capsys),
        r"camera.yaml: (camera\.)?fx expects a number, got 'wide'",
    )
    expect_cli_error(
        "unknown preset (CLI)",
        run_main(["run", str(seq), "--config", "tum_fr9", "--out", str(tmp_path / "o2")], capsys),
        r"config 'tum_fr9': neither a preset \(defaults, tum_fr1, .*\) nor a YAML file",
    )
    gt = tmp_path / "gt.txt"
    gt.write_text("1.0 0 0 0 0 0 1\n")
    expect_cli_error(
        "malformed ground truth (planeslam eval)",
        run_main(["eval", str(gt), str(seq / "groundtruth.txt")], capsys),
        r"gt.txt:1: expected 8 numbers",
    )


DATASET_COMMANDS = [
    ["run", "DATA"],
    ["frame", "DATA", "0"],
    ["bench", "frontend", "DATA"],
]


@pytest.mark.parametrize("command", DATASET_COMMANDS, ids=lambda c: " ".join(c[:2]))
def test_every_dataset_command_takes_camera_and_flags_after_it(command: list[str]) -> None:
    def parses() -> None:
        args = build_parser().parse_args([*command, "--camera", "500,500,160,120", "-q", "-v"])
        assert args.camera == "500,500,160,120" and args.quiet and args.verbose == 1

    expect_handled(f"--camera and -q -v after '{' '.join(command[:2])}'", parses)


def test_version_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    def version() -> None:
        with pytest.raises(SystemExit) as info:
            main(["--version"])
        assert info.value.code == 0
        assert capsys.readouterr().out.startswith("planeslam ")

    expect_handled("--version", version)
