"""`planeslam bench suite`: synthetic scenes rendered on demand, optional data skipped,
a failing sequence reported in its row, markdown and CSV written."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from planeslam.app.suite import run_suite_command
from planeslam.core.errors import ConfigError
from planeslam.eval.suite import load_suite

pytestmark = pytest.mark.integration  # `planeslam suite`


def write_suite(path: Path, body: str) -> Path:
    path.write_text(body, encoding="utf-8")
    return path


@pytest.mark.slow
def test_suite_renders_scenes_skips_absent_data_and_reports_failures(tmp_path: Path) -> None:
    suite = write_suite(
        tmp_path / "suite.yaml",
        "methods: [merge]\njobs: 1\nsequences:\n"
        "  - scene: box_room_circle\n    max_frames: 4\n"
        "  - path: no_such_folder\n    optional: true\n"
        "  - path: broken\n",
    )
    (tmp_path / "broken").mkdir()  # exists but is not a dataset: its row carries the error
    table = run_suite_command(suite, tmp_path / "out")
    rows = list(csv.DictReader(open(tmp_path / "out" / "suite.csv", encoding="utf-8")))
    assert [(r["sequence"], r["method"]) for r in rows] == [
        ("box_room_circle", "merge"),
        ("broken", "merge"),
    ]
    ok, broken = rows
    assert ok["error"] == "" and float(ok["ate_rmse_m"]) < 0.01
    assert float(ok["memory_ratio"]) > 100
    assert "DatasetFormatError" in broken["error"]
    assert (tmp_path / "out" / "data" / "box_room_circle" / "truth.json").is_file()
    assert "| box_room_circle | merge |" in table
    assert (tmp_path / "out" / "suite.md").read_text().startswith("| sequence | method |")


def test_default_suite_is_valid() -> None:
    from importlib import resources

    path = Path(str(resources.files("planeslam.configs") / "suite.yaml"))
    config, _ = load_suite(path)
    assert {"open3d_odometry", "merge", "isam2"} == set(config.methods)
    assert any(s.scene == "room_boxes_loop" and s.every == 20 for s in config.sequences)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("sequences:\n  - {path: a, scene: box_room_circle}\n", "exactly one of 'path' or 'scene'"),
        ("sequences:\n  - {path: a, every: 0}\n", "every must be >= 1"),
        ("methods: [nope]\nsequences:\n  - {path: a}\n", "unknown method"),
    ],
)
def test_bad_suite_files_are_refused(tmp_path: Path, body: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_suite(write_suite(tmp_path / "s.yaml", body))
