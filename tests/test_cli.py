"""The command line: help for every sub-command, one-line errors with exit code 2, the demo."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from planeslam.app.cli import main

pytestmark = pytest.mark.integration  # the CLI, in subprocesses, demo included

COMMANDS = ("synth", "demo", "eval", "run", "frame", "bench", "view", "mesh", "calibrate")


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    assert command in capsys.readouterr().out


def test_errors_are_one_line_with_exit_code_2(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "planeslam.app.cli", "eval", str(tmp_path / "gt.txt"), "x.txt"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "gt.txt: trajectory file not found" in result.stderr
    assert "Traceback" not in result.stderr


def test_demo_runs_full_slam_and_measures_the_box(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["-q", "demo", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "box:" in out
    run = tmp_path / "run"
    records = [json.loads(line) for line in (run / "frames.jsonl").read_text().splitlines()]
    assert len(records) == 24 and not any(r["path"] == "lost" for r in records)
    evaluation = json.loads((run / "eval.json").read_text())
    assert evaluation["ate_rmse_m"] < 0.01
    box = next(e for e in evaluation["object_size_errors"] if e["class"] == "box")
    assert box["mean_abs_error_m"] < 0.01
