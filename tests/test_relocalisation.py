"""The relocalisation benchmark's report: what counts as correct, wrong, consistent."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from planeslam.eval.relocalisation import (
    RelocalisationAttempt,
    RelocalisationReport,
    relocalisation_benchmark,
)
from planeslam.sim.render import synthesize


def test_report_counts_against_truth_and_the_map_run() -> None:
    attempts = [
        RelocalisationAttempt(0, True, 0.01, 0.5, 100.0, 0.01, 0.4, 0.01, 0.5, 0.0, 0.1),  # right
        # the map drifted from its first frame: right once it is aligned to the truth
        RelocalisationAttempt(10, True, 0.07, 1.0, 300.0, 0.02, 0.5, 0.03, 1.0, 0.02, 0.6),
        # wrong place, in a map whose own pose here is off by 3.5 deg
        RelocalisationAttempt(20, True, 0.01, 4.0, 200.0, 0.5, 20.0, 0.4, 18.0, 0.01, 3.5),
        RelocalisationAttempt(30, False, None, None, 50.0),
    ]
    report = RelocalisationReport(attempts, 0.05, 3.0)
    d = report.to_dict()
    assert (d["correct"], d["wrong"], d["not_found"]) == (1, 2, 1)
    assert d["consistent_with_map_run"] == 2 and d["correct_with_map_aligned"] == 2
    assert d["map_run_correct_aligned"] == 2
    assert d["ms_median"] == 150.0 and d["ms_max"] == 300.0
    assert [f["index"] for f in d["frames"]] == [0, 10, 20, 30]
    assert d["frames"][1]["map_translation_error_m"] == 0.02 and not d["frames"][3]["found"]
    json.dumps(d)  # the CLI's --json prints it
    assert "1 of 4 frames relocalised within 5 cm and 3 deg (25.0 %)" in report.to_text()
    assert "2 within them of the map run's own poses" in report.to_text()
    assert "2 of the truth with the map aligned to it" in report.to_text()
    assert "(the map run's own poses of those frames: 2)" in report.to_text()
    without_run = RelocalisationReport([RelocalisationAttempt(0, True, 0.01, 0.5, 1.0)])
    assert without_run.consistent is None and "map run" not in without_run.to_text()
    assert without_run.aligned is None and "aligned" not in without_run.to_text()
    assert without_run.run_aligned is None


@pytest.mark.slow
def test_frames_of_the_paper_circle_are_placed_in_its_map(tmp_path: Path) -> None:
    """Every 4th frame of the built-in box-in-a-room circle placed on its own in the map of
    a full run: all within the tolerances of the truth and of the map run's own poses."""
    seq = synthesize("box_room_circle", tmp_path / "seq", seed=5).out_dir
    report = relocalisation_benchmark(seq, every=4)
    d = report.to_dict()
    assert d["attempts"] == 6
    assert d["correct"] == d["consistent_with_map_run"] == 6 and d["not_found"] == 0
    assert d["correct_with_map_aligned"] == d["map_run_correct_aligned"] == 6
    # the run started at the true pose: the alignment is nearly the identity
    for frame in d["frames"]:
        assert abs(frame["aligned_translation_error_m"] - frame["translation_error_m"]) < 0.005
        assert frame["run_aligned_translation_error_m"] < 0.005
