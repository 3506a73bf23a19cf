"""The run report's pieces without a run: figures with sensible precision, byte sizes,
and a report made from frames.jsonl and metrics.json alone (lost frames and their
reasons); `embedded_images` is shared with tests/test_run_views.py."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import pytest

from planeslam.core.errors import EvaluationError
from planeslam.eval.report import format_bytes, format_figure, write_report

pytestmark = pytest.mark.unit


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("fps", 12.2842, ("12.3", "Hz")),
        ("peak_rss_mb", 448.0508, ("448.1", "MiB")),
        ("ate_rmse_m", 0.048712, ("0.0487", "m")),
        ("frame_ms_median", 28.456, ("28.5", "ms")),
        ("map_bytes", 1690000, ("1.69 MB", "")),
        ("memory_ratio", 2424.9, ("2425", "x")),
        ("tracked_fraction", 0.98765, ("98.8", "%")),
        ("lost_frames", 3, ("3", "")),
        ("rpe_rot_deg_per_s", 2.41034, ("2.410", "deg/s")),
        ("whatever", 0.123456789, ("0.1235", "")),
        ("memory_ratio", None, ("n/a", "")),
    ],
)
def test_figures_have_sensible_precision(key: str, value: object, expected: tuple) -> None:
    assert format_figure(key, value) == expected


def test_format_bytes() -> None:
    assert format_bytes(999) == "999 bytes"
    assert format_bytes(13188) == "13.2 KB"
    assert format_bytes(4_100_000_000) == "4.1 GB"


def embedded_images(page: str) -> list[bytes]:
    """The decoded PNGs of every <img> of the page; fails on an image that is not embedded."""
    sources = re.findall(r'<img src="([^"]*)"', page)
    assert sources
    found = []
    for src in sources:
        assert src.startswith("data:image/png;base64,"), src[:60]
        found.append(base64.b64decode(src.split(",", 1)[1]))
    return found


def test_report_lists_lost_frames_with_their_reasons(tmp_path: Path) -> None:
    """Without run.json or a map: the tracking breakdown from frames.jsonl, lost frames
    with their reasons, and the generic header."""
    records = [
        {"index": 0, "timestamp": 1.0, "path": "first", "reason": "", "keyframe": True},
        {"index": 1, "timestamp": 1.5, "path": "lost", "reason": "2 planes, no corner"},
        {"index": 2, "timestamp": 2.0, "path": "planes", "reason": "", "keyframe": True},
    ]
    (tmp_path / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    (tmp_path / "metrics.json").write_text(json.dumps({"frames": 3, "lost_frames": 1}))
    page = write_report(tmp_path).read_text(encoding="utf-8")
    assert "<td>lost</td><td>1</td><td>33.3 %</td>" in page
    assert "<h3>Lost frames</h3>" in page
    assert "<td>1</td><td>1.500</td><td>2 planes, no corner</td>" in page
    assert "planeslam version" in page and "Top-down map" not in page
    assert len(embedded_images(page)) == 1  # the per-frame timeline
    (tmp_path / "frames.jsonl").write_text('{"index": 0}\n')
    with pytest.raises(EvaluationError, match=r"frames.jsonl:1: expected an object with"):
        write_report(tmp_path)
