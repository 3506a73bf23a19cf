"""The benchmark suite on its executors: a two-worker Dask LocalCluster on loopback gives
the local executor's table (ATE to 0.1 mm), and every table says where its jobs ran and
how many ran at once."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from planeslam.core.errors import ConfigError
from planeslam.eval import executors
from planeslam.eval.suite import (
    SequenceSpec,
    SuiteConfig,
    SuiteResult,
    SuiteRow,
    jobs_at_once,
    render_scenes,
    run_suite,
    to_markdown,
)
from tests.conftest import SHARED_DATA

pytestmark = pytest.mark.integration  # the suite on a Dask LocalCluster of worker processes


def _row(start: float, end: float) -> SuiteRow:
    return SuiteRow("s", "m", started_at=start, finished_at=end)


def test_jobs_at_once_from_the_rows_times() -> None:
    one_after_another = [_row(0, 1), _row(1, 2), _row(2, 3)]
    assert jobs_at_once(one_after_another) == [1, 1, 1]
    # two workers: a and b together, c starts when a ends and overlaps b
    overlapping = [_row(0, 2), _row(0.5, 3), _row(2, 4), SuiteRow("s", "m")]
    assert jobs_at_once(overlapping) == [2, 2, 2, None]
    assert jobs_at_once([_row(0, 4), _row(1, 2), _row(1.5, 3)]) == [3, 3, 3]


def test_timing_title_says_executor_and_jobs_at_once() -> None:
    rows = [SuiteRow("s", "m", fps=10.0, jobs_at_once=1)]
    assert "| fps (local, 1 at a time) |" in to_markdown(SuiteResult(rows, "local"))
    rows = [SuiteRow("s", "m", fps=10.0, jobs_at_once=2), SuiteRow("t", "m", jobs_at_once=1)]
    assert "| fps (dask, up to 2 at once) |" in to_markdown(SuiteResult(rows, "dask"))


def test_executor_settings_are_checked() -> None:
    spec = (SequenceSpec(scene="box_room_circle"),)
    with pytest.raises(ConfigError, match="needs the dask executor"):
        run_suite(SuiteConfig(sequences=spec, methods=("merge",), scheduler="tcp://x:1"))
    with pytest.raises(ConfigError, match="executor must be 'local' or 'dask'"):
        run_suite(SuiteConfig(sequences=spec, methods=("merge",), executor="spark"))  # type: ignore[arg-type]


def test_unreachable_scheduler(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(executors, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(ConfigError, match=r"dask scheduler 'tcp://127.0.0.1:9': cannot connect"):
        list(executors.run_on_dask([executors.Job(print, ())], "tcp://127.0.0.1:9"))


@pytest.mark.slow
def test_dask_local_cluster_table_equals_the_local_one(tmp_path: Path) -> None:
    sequences = [SequenceSpec(scene="box_room_circle", max_frames=6)]
    clip = SHARED_DATA / "tum_fr1_xyz_10f"
    if clip.is_dir():  # real data when present; the synthetic scene alone otherwise
        sequences.append(SequenceSpec(path=str(clip), max_frames=6))
    config = SuiteConfig(sequences=tuple(sequences), methods=("merge", "isam2"))
    render_scenes(config, tmp_path)  # both runs read the scene from tmp_path/data
    local = run_suite(config, tmp_path, tmp_path)
    on_dask = run_suite(dataclasses.replace(config, executor="dask", jobs=2), tmp_path, tmp_path)
    assert [(r.sequence, r.method) for r in on_dask.rows] == [
        (r.sequence, r.method) for r in local.rows
    ]
    for a, b in zip(local.rows, on_dask.rows, strict=True):
        assert a.error is None and b.error is None, (a.error, b.error)
        assert a.ate_rmse_m is not None and b.ate_rmse_m is not None
        assert b.ate_rmse_m == pytest.approx(a.ate_rmse_m, abs=1e-4)
        assert (a.frames, a.lost_frames) == (b.frames, b.lost_frames)
        assert (a.executor, b.executor) == ("local", "dask")
    assert local.most_jobs_at_once == 1
    timing = [(r.sequence, r.method, r.started_at, r.finished_at) for r in on_dask.rows]
    assert on_dask.most_jobs_at_once == 2, timing  # two workers, jobs waiting for both
    assert "fps (local, 1 at a time)" in to_markdown(local)
    assert "fps (dask, up to 2 at once)" in to_markdown(on_dask)
