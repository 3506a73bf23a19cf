"""Progress bars of the command line (tqdm, on stderr). Library code never makes one: it
takes a callback, and the application passes `bar.step` here."""

from __future__ import annotations

from collections.abc import Callable, Iterator
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


@contextmanager
def byte_progress(desc: str, enabled: bool = True) -> Iterator[Callable[[int, int | None], None]]:
    """A bar over a transfer: yields `update(bytes so far, total bytes or None)`, the
    callback library downloads take; closed when the block ends (also on Ctrl-C)."""
    if not enabled:
        yield lambda done, total: None
        return
    from tqdm import tqdm

    bars: list[Any] = []  # made on the first update: nothing shows when nothing is fetched

    def update(done: int, total: int | None) -> None:
        if not bars:
            bars.append(tqdm(desc=desc, unit="B", unit_scale=True, unit_divisor=1024))
        bar = bars[0]
        if total is not None and bar.total != total:
            bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        for bar in bars:
            bar.close()
