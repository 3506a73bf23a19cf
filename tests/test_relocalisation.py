"""The relocalisation benchmark's report: what counts as correct, wrong, consistent."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from planeslam.eval.relocalisation import (
    RelocalisationAttempt,
    RelocalisationReport,
    keyframe_trajectory,
    relocalisation_benchmark,
)
from planeslam.sim.sequence import synthesize

pytestmark = pytest.mark.unit


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
    # scored in the map's frame (the aligned truth); 1 against the truth as it is
    assert (d["correct"], d["wrong"], d["not_found"]) == (2, 1, 1)
    assert d["scored_in_map_frame"] and d["correct_unaligned"] == 1
    assert d["consistent_with_map_run"] == 2 and d["correct_with_map_aligned"] == 2
    assert d["map_run_correct_aligned"] == 2
    assert d["ms_median"] == 150.0 and d["ms_max"] == 300.0
    assert [f["index"] for f in d["frames"]] == [0, 10, 20, 30]
    assert d["frames"][1]["map_translation_error_m"] == 0.02 and not d["frames"][3]["found"]
    json.dumps(d)  # the CLI's --json prints it
    assert "2 of 4 frames relocalised within 5 cm and 3 deg (50.0 %)" in report.to_text()
    assert "1 against the truth as it is" in report.to_text()
    assert "2 within them of the map run's own poses" in report.to_text()
    assert "(the map run's own poses of those frames: 2)" in report.to_text()
    without_run = RelocalisationReport([RelocalisationAttempt(0, True, 0.01, 0.5, 1.0)])
    assert without_run.correct == 1 and "share the world frame" in without_run.to_text()
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


@pytest.mark.integration
@pytest.mark.slow
def test_a_map_started_at_the_identity_is_scored_in_its_own_frame(tmp_path: Path) -> None:
    """A run started at the identity instead of the first true pose (ICL-NUIM has no truth
    for frame 1): its frames are scored against the truth moved into the map's frame, from
    the run's trajectory or from the keyframes of its map.json (`--map`)."""
    from planeslam.app.runner import run_sequence

    seq = synthesize("box_room_circle", tmp_path / "seq", seed=5).out_dir
    report = relocalisation_benchmark(seq, every=4, overrides=["run.start_pose=identity"])
    d = report.to_dict()
    assert d["scored_in_map_frame"] and d["correct"] == d["attempts"] == 6, report.to_text()
    assert d["correct_unaligned"] == 0  # the circle does not start at the identity
    run_sequence(seq, tmp_path / "run", start_pose="identity")
    keyframes = keyframe_trajectory(tmp_path / "run" / "map.json")
    assert keyframes is not None and len(keyframes) >= 3
    np.testing.assert_allclose(keyframes.T_world_cam[0], np.eye(4), atol=1e-9)
    # (a map.json alone places none of this scene's frames yet: primitives only)
    from_file = relocalisation_benchmark(seq, tmp_path / "run" / "map.json", every=4).to_dict()
    assert from_file["scored_in_map_frame"], from_file
