"""The tally of the fault corpus's outcomes, printed at the end of the test session (the
figures of the README's Reliability section)."""

from __future__ import annotations

import enum
from collections import Counter

import pytest


class Outcome(enum.Enum):
    CLEAN_ERROR = "clean error"
    """The expected error, one line, naming the file or value."""
    HANDLED = "handled"
    """The documented outcome instead of an error (skipped with a warning, ...)."""
    CRASH = "crash"
    """Another exception, a traceback, a hang or a wrong message."""
    OUTPUT_KEPT = "output kept"
    """A run folder whose outputs are whole and consistent."""
    LOST_OUTPUT = "lost output"
    """A run folder whose outputs are incomplete or inconsistent."""


_outcomes: dict[str, Outcome] = {}


def record(case: str, outcome: Outcome) -> None:
    """Note the outcome of one corpus case (the last one counts when a case is retried)."""
    _outcomes[case] = outcome


def summary() -> str:
    """One line of figures, '' when no corpus case ran."""
    if not _outcomes:
        return ""
    counts = Counter(_outcomes.values())
    cases = sum(counts[o] for o in (Outcome.CLEAN_ERROR, Outcome.HANDLED, Outcome.CRASH))
    runs = counts[Outcome.OUTPUT_KEPT] + counts[Outcome.LOST_OUTPUT]
    return (
        f"fault corpus: {cases} cases tried, {counts[Outcome.CLEAN_ERROR]} clean errors, "
        f"{counts[Outcome.HANDLED]} handled, {counts[Outcome.CRASH]} crashes; "
        f"{runs} run folders checked, {counts[Outcome.LOST_OUTPUT]} lost output"
    )


def pytest_sessionfinish(session: pytest.Session) -> None:
    """In a pytest-xdist worker: hand the worker's outcomes to the controller."""
    worker_output = getattr(session.config, "workeroutput", None)
    if worker_output is not None:
        worker_output["fault_corpus"] = {case: o.value for case, o in _outcomes.items()}


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: object, error: object) -> None:
    """In the pytest-xdist controller: gather a finished worker's outcomes."""
    for case, value in getattr(node, "workeroutput", {}).get("fault_corpus", {}).items():
        _outcomes[case] = Outcome(value)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    line = summary()
    if line:
        terminalreporter.write_sep("-", "fault corpus")
        terminalreporter.write_line(line)
