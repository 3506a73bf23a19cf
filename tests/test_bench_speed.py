"""`planeslam bench speed` (bench_speed): the table's columns are computed as documented,
checked on a tiny run with a stand-in reference workload (figures, not speed)."""

from __future__ import annotations

import statistics

import pytest

from planeslam.app import bench_speed as speed
from planeslam.app.cli import main
from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError
from planeslam.sim.sequence import synthesize

SMALL = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
# Whole SLAM runs with the backend worker process: integration, as test_bench.py.
pytestmark = pytest.mark.integration

REFERENCE_S = (1.0, 2.0, 4.0, 8.0, 16.0)  # stand-in reference timings, one before each run
AROUND = {"front end": (1.5, 6.0), "whole system": (3.0, 12.0)}  # means around each run


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("speed") / "box"
    synthesize("box_room_circle", folder, frames=3, seed=1, camera=SMALL)
    return folder


@pytest.fixture(scope="module")
def tiny_result(tiny_dataset):
    timings = iter(REFERENCE_S)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(speed, "reference_workload", lambda: next(timings))
        return speed.bench_speed([tiny_dataset], frames=2, repeats=2, synthetic=False)


def _parse(table: str) -> list[dict[str, str]]:
    lines = table.strip().splitlines()
    head = [c.strip() for c in lines[0].strip("|").split(" | ")]
    assert set(lines[1].replace("|", "").split()) == {"---"}
    return [
        dict(zip(head, (c.strip() for c in row.strip("|").split(" | ")), strict=True))
        for row in lines[2:]
    ]


def test_runs_use_the_mean_of_the_references_around_them(tiny_result):
    assert tiny_result.reference_s == REFERENCE_S
    assert [(w.kind, w.dataset, w.frames) for w in tiny_result.workloads] == [
        (speed.FRONT_END, "box", 2),
        (speed.WHOLE_SYSTEM, "box", 2),
    ]
    for w in tiny_result.workloads:
        assert w.reference_s == AROUND[w.kind]
        assert len(w.seconds) == 2 and all(s > 0 for s in w.seconds)


def test_markdown_columns_are_the_documented_medians(tiny_result, tmp_path):
    rows = _parse(tiny_result.to_markdown())
    assert list(rows[0]) == list(speed.MARKDOWN_COLUMNS)
    m = tiny_result.machine
    for row, w in zip(rows, tiny_result.workloads, strict=True):
        per_frame = [s / w.frames for s in w.seconds]
        assert row["workload"] == w.kind and row["dataset"] == "box" and row["frames"] == "2"
        assert row["fps"] == f"{statistics.median(1 / p for p in per_frame):.2f}"
        assert row["ms/frame"] == f"{statistics.median(1e3 * p for p in per_frame):.2f}"
        assert row["reference s"] == f"{statistics.median(AROUND[w.kind]):.3f}"
        ref_units = statistics.median(p / r for p, r in zip(per_frame, AROUND[w.kind], strict=True))
        assert row["ref units/frame"] == f"{ref_units:.5f}"
        cpu_ms = statistics.median(1e3 * c / w.frames for c in w.cpu_s)
        assert row["CPU ms/frame"] == f"{cpu_ms:.2f}" and all(c > 0 for c in w.cpu_s)
        assert row["commit"] == m.commit and row["machine"] == f"{m.cpu_model}, {m.cores} cores"
        assert row["load before"] == " ".join(f"{x:.2f}" for x in m.load_before)
    # Appending again grows the same table: one header, twice the rows.
    path = tmp_path / "speed.md"
    path.write_text("# Speed\n")
    speed.append_markdown(tiny_result, path)
    speed.append_markdown(tiny_result, path)
    text = path.read_text()
    assert text.count("| date (UTC) |") == 1
    assert len(_parse(text.split("\n", 2)[2])) == 2 * len(tiny_result.workloads)
    assert "ref units/frame" in tiny_result.to_text()


def test_reference_workload_is_a_positive_duration():
    assert speed.reference_workload() > 0


@pytest.mark.parametrize("kwargs", [{"frames": 0}, {"repeats": 0}, {"synthetic": False}])
def test_bad_arguments_are_config_errors(kwargs):
    with pytest.raises(ConfigError):
        speed.bench_speed(**kwargs)


def test_cli_help_lists_speed(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "speed", "--help"])
    assert "reference" in capsys.readouterr().out
