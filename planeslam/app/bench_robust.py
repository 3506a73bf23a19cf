"""`planeslam bench robust`: the robustness benchmark (`planeslam.eval.robust`) with a
progress bar; its tables go to the output folder and, with `--markdown`, into a section
of a Markdown page (docs/benchmarks.md) headed by the command, commit, date, machine,
load average and the reference workload of `planeslam bench speed` timed before and after
(so the fps columns of two runs compare across hours)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

from planeslam.app.bench_speed import code_commit, cpu_model, load_average, reference_workload
from planeslam.app.progress import progress_bar
from planeslam.core.config import ConfigLayer
from planeslam.core.errors import ConfigError
from planeslam.core.safe_files import write_text_atomic
from planeslam.eval.robust import (
    BenchSequence,
    RobustResult,
    RobustRow,
    benchmark_sequences,
    changes_markdown,
    read_rows,
    rows_markdown,
    run_robust,
    summary_markdown,
)


@dataclass(frozen=True)
class BenchContext:
    """Where and when a benchmark ran: the heading of its Markdown section."""

    command: str
    commit: str
    date_utc: str
    machine: str
    load_average: tuple[float, float, float]
    reference_s: float | None = None
    """`bench_speed.reference_workload` [s] timed at the start (None: not timed)."""

    @classmethod
    def now(cls, command: str, reference: bool = True) -> BenchContext:
        machine = f"{cpu_model()}, {os.cpu_count()} cores"
        timed = reference_workload() if reference else None
        return cls(command, code_commit(), _utc_now(), machine, load_average(), timed)

    def heading_lines(self, seconds: float, reference_after_s: float | None = None) -> str:
        load = " ".join(f"{v:.2f}" for v in self.load_average)
        reference = ""
        if self.reference_s is not None and reference_after_s is not None:
            reference = (
                f" Reference workload (`planeslam bench speed`'s) {self.reference_s:.2f} s "
                f"before, {reference_after_s:.2f} s after: fps compare across hours in "
                "proportion to it.\n"
            )
        return (
            f"Command: `{self.command}`  \n"
            f"Commit {self.commit}, {self.date_utc}, {self.machine}, load average at the "
            f"start {load}, {seconds / 60:.1f} min.\n" + reference
        )


def _utc_now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def replace_section(page: str, label: str, section: str) -> str:
    """`page` with the section between the markers of `label` replaced by `section`, or
    with it appended when the page has no such section."""
    begin, end = f"<!-- bench robust: {label} -->", f"<!-- end bench robust: {label} -->"
    block = f"{begin}\n{section.rstrip()}\n{end}\n"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end) + r"\n?", re.DOTALL)
    if pattern.search(page):
        return pattern.sub(lambda _: block, page, count=1)
    return (page.rstrip() + "\n\n" if page.strip() else "") + block


def robust_section(
    label: str,
    result: RobustResult,
    context: BenchContext,
    reference_after_s: float | None = None,
    changes: str = "",
) -> str:
    """The Markdown section of one benchmark run: heading, summaries, the `changes`
    against an earlier run (`changes_markdown`, when given), per-sequence rows."""
    return (
        f"### Robust benchmark: {label}\n\n"
        + context.heading_lines(result.seconds, reference_after_s)
        + f"{result.jobs} job(s) at once on the {result.executor} executor.\n\n"
        + summary_markdown(result.rows)
        + (f"\n**Against the earlier run**\n\n{changes}" if changes else "")
        + "\n<details><summary>Per sequence</summary>\n\n"
        + rows_markdown(result.rows)
        + "\n</details>\n"
    )


def run_robust_command(
    out_dir: Path,
    command: str,
    jobs: int = 1,
    split: Literal["tuning", "validation", "all"] = "all",
    count: int | None = None,
    executor: Literal["local", "dask"] = "local",
    scheduler: str | None = None,
    overrides: Sequence[ConfigLayer] = (),
    markdown: Path | None = None,
    label: str = "current code",
    with_open3d: bool = True,
    progress: bool = False,
    sequences: Sequence[BenchSequence] | None = None,
    against: Path | None = None,
) -> str:
    """Run the benchmark (`sequences`, default the fixed list or its first `count`), write
    robust.md into `out_dir` (and the section `label` of `markdown`), and return the
    summary tables; with `against` (an earlier run's folder or rows.jsonl, read before
    anything runs) also what moved since that run (`changes_markdown`)."""
    if "-->" in label or "\n" in label:
        raise ConfigError(f"--label {label!r}: use one line without '-->'")
    if against is not None and Path(against).resolve() in (
        Path(out_dir).resolve(),
        (Path(out_dir) / "rows.jsonl").resolve(),
    ):
        raise ConfigError(f"--against {against}: the run's own --out, which it overwrites")
    earlier = None if against is None else read_rows(against)
    if sequences is None:
        sequences = benchmark_sequences() if count is None else benchmark_sequences(count)
    if split != "all":
        sequences = [s for s in sequences if s.split == split]
    context = BenchContext.now(command)
    with progress_bar(len(sequences), "robust", "seq", enabled=progress) as bar:

        def on_row(row: RobustRow) -> None:
            ours = row.planeslam
            status = ours.error or f"tracked {ours.tracked_fraction or 0:.0%}"
            bar.step(f"{row.name}: {status}")

        result = run_robust(
            out_dir,
            sequences,
            jobs=jobs,
            executor=executor,
            scheduler=scheduler,
            overrides=overrides,
            with_open3d=with_open3d,
            on_row=on_row,
        )
    changes = "" if earlier is None else changes_markdown(earlier, result.rows)
    section = robust_section(label, result, context, reference_workload(), changes)
    written = [write_text_atomic(Path(out_dir) / "robust.md", section + "\n")]
    if markdown is not None:
        page = markdown.read_text(encoding="utf-8") if markdown.is_file() else "# Benchmarks\n"
        written.append(write_text_atomic(markdown, replace_section(page, label, section)))
    compared = f"\nAgainst {against}:\n{changes}" if changes else ""
    return (
        summary_markdown(result.rows)
        + compared
        + "\nwritten: "
        + ", ".join(str(p) for p in written)
    )
