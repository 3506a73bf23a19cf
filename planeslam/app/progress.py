"""Progress bars of the command line (tqdm, on stderr). Library code never makes one: it
takes a callback, and the application passes `bar.step` here."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class ProgressBar:
    """A tqdm bar, or nothing when disabled; `step` advances it with a status text."""

    def __init__(self, bar: Any | None) -> None:
        self._bar = bar

    def step(self, status: str = "") -> None:
        if self._bar is not None:
            if status:
                self._bar.set_postfix_str(status, refresh=False)
            self._bar.update(1)


@contextmanager
def progress_bar(total: int, desc: str, unit: str, enabled: bool = True) -> Iterator[ProgressBar]:
    """A bar over `total` steps, closed when the block ends (also on Ctrl-C)."""
    if not enabled:
        yield ProgressBar(None)
        return
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit)
    try:
        yield ProgressBar(bar)
    finally:
        bar.close()
