"""Every sub-command of the CLI, in process: its --help, and a tiny run where one takes
seconds (a 3-frame synthetic sequence). A sub-command added without an entry here fails
`test_every_sub_command_has_a_smoke_run`."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from planeslam.app.cli import build_parser, main

pytestmark = pytest.mark.integration  # the CLI end to end, in process

HELP_ONLY = {
    "demo": "renders 24 frames and runs SLAM: tests/test_cli.py runs it",
    "bench": "a group",
    "bench suite": "minutes: tests/test_suite_command.py",
    "bench long": "minutes: tests/test_scale.py",
    "bench robust": "minutes: tests/test_robust_bench.py",
    "bench speed": "three rounds: tests/test_bench_speed.py",
    "view": "rerun recording of a run: tests/test_run_views.py",
    "config": "a group",
    "download": "a group",
    "relocalise": "a full map run first: tests/test_relocalisation.py",
}
"""Sub-commands smoke-tested by --help alone here, and why."""


def sub_commands() -> list[str]:
    """Every sub-command path of the parser ('run', 'bench frontend', ...)."""
    found: list[str] = []

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    found.append(f"{prefix}{name}")
                    walk(sub, f"{prefix}{name} ")

    walk(build_parser(), "")
    return found


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-frame synthetic sequence with ground truth, written by `planeslam synth`."""
    out = tmp_path_factory.mktemp("smoke") / "seq"
    assert main(["-q", "synth", "box_room_circle", str(out), "--frames", "3"]) == 0
    return out


@pytest.fixture(scope="module")
def tiny_run(tiny: Path) -> Path:
    out = tiny.parent / "run"
    argv = ["-q", "run", str(tiny), "--out", str(out), "--backend", "merge"]
    assert main(argv) == 0
    return out


def runs(tiny: Path, tiny_run: Path, tmp: Path) -> dict[str, list[str]]:
    """A tiny run of each sub-command that takes seconds."""
    return {
        "synth": ["synth", "box_room_circle", str(tmp / "synth"), "--frames", "2"],
        "run": ["run", str(tiny), "--out", str(tmp / "run"), "--max-frames", "2"],
        "eval": ["eval", str(tiny / "groundtruth.txt"), str(tiny / "groundtruth.txt")],
        "frame": ["frame", str(tiny), "1", "--out", str(tmp / "frame")],
        "bench frontend": ["bench", "frontend", str(tiny), "--frames", "2"],
        "mesh": ["mesh", str(tiny_run), "--voxel", "0.05"],
        "config show": ["config", "show", str(tiny), "--advanced"],
        "config docs": ["config", "docs"],
        "download tum": ["download", "tum", "--list"],
        "calibrate": ["calibrate", str(tiny), "--out", str(tmp / "sensor.yaml")],
    }


def test_every_sub_command_has_a_smoke_run(tiny: Path, tiny_run: Path, tmp_path: Path) -> None:
    covered = set(runs(tiny, tiny_run, tmp_path)) | set(HELP_ONLY)
    assert set(sub_commands()) == covered


@pytest.mark.parametrize("command", sub_commands())
def test_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main([*command.split(), "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: planeslam {command}")


@pytest.mark.parametrize("command", [c for c in sub_commands() if c not in HELP_ONLY])
def test_tiny_run(
    command: str, tiny: Path, tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["-q", *runs(tiny, tiny_run, tmp_path)[command]]) == 0, capsys.readouterr().err
    assert capsys.readouterr().out or command in ("synth", "mesh", "calibrate")
