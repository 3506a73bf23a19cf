"""`planeslam bench suite`: the benchmark suite of `planeslam.eval.suite` with a progress
bar, its tables written to a folder; jobs run locally or on a Dask cluster."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from planeslam.app.progress import progress_bar
from planeslam.core.safe_files import write_text_atomic
from planeslam.eval.suite import (
    SuiteRow,
    load_suite,
    render_scenes,
    run_suite,
    to_markdown,
    write_csv,
)

log = logging.getLogger(__name__)

DEFAULT_SUITE = "suite.yaml"
"""The bundled default suite (in `planeslam.configs`); data paths are relative to the
current directory, i.e. the repository root."""


def run_suite_command(
    suite: str | Path | None,
    out_dir: str | Path,
    jobs: int | None = None,
    progress: bool = False,
    executor: str | None = None,
    scheduler: str | None = None,
) -> str:
    """`planeslam bench suite [SUITE.yaml] [--jobs N] [--executor local|dask] [--scheduler
    ADDRESS]`: render the synthetic scenes, run the suite with a progress bar, write suite.md
    and suite.csv into out_dir; returns the table.

    Without SUITE the bundled default suite runs from the current directory; its optional
    sequences (../shared/data) are skipped with a note when absent. `executor` and
    `scheduler` override the suite file's (a scheduler alone means dask); jobs get absolute
    paths (a Dask cluster's workers must see the data and the output folder at them).
    """
    if suite is None:
        from importlib import resources

        path = Path(str(resources.files("planeslam.configs") / DEFAULT_SUITE))
        config, _ = load_suite(path)
        base_dir = Path.cwd()
    else:
        config, base_dir = load_suite(suite)
    present = []
    for spec in config.sequences:
        if spec.optional and spec.scene is None and not (base_dir / spec.path).exists():
            log.warning("skipping %s: %s not found", spec.name, base_dir / spec.path)
        else:
            present.append(spec)
    config = dataclasses.replace(
        config,
        sequences=tuple(present),
        jobs=jobs or config.jobs,
        executor=executor or ("dask" if scheduler else config.executor),
        scheduler=scheduler or config.scheduler,
    )
    out = Path(out_dir)
    render_scenes(config, out)
    total = len(config.sequences) * len(config.methods)
    with progress_bar(total, "suite", "run", enabled=progress) as bar:

        def on_row(row: SuiteRow) -> None:
            status = "failed" if row.error else f"ATE {row.ate_rmse_m or 0:.3f} m"
            bar.step(f"{row.sequence} {row.method}: {status}")

        result = run_suite(config, base_dir.resolve(), out.resolve(), on_row)
    table = to_markdown(result)
    write_text_atomic(out / "suite.md", table)
    write_csv(result, out / "suite.csv")
    return table + f"\nwritten: {out / 'suite.md'}, {out / 'suite.csv'}"
