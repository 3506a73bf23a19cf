"""Signals of the command line. SIGTERM and SIGHUP stop a command the way Ctrl-C does
(`Terminated` is a KeyboardInterrupt, so every `finally` that keeps outputs runs), and
`deferred_interrupts` holds them and Ctrl-C back while final outputs are written.

Process-wide: only the application (the CLI) installs these, from the main thread.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Signals handled like Ctrl-C (SIGINT)."""


class Terminated(KeyboardInterrupt):
    """A stop signal (SIGTERM, SIGHUP) arrived; handled as Ctrl-C is."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        """128 + the signal number, as a shell reports a process the signal ended."""
        return 128 + self.signum


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated(signum)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def stop_signals_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise `Terminated` in the main thread; the
    previous handlers come back after it. Does nothing outside the main thread."""
    if not _in_main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise_terminated) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP back for the block (a frame being processed and
    written out, the final outputs being written): the first that came is delivered again,
    to the handler from before the block, when the block ends without an error. A second
    one is not held back (a user who insists)."""
    if not _in_main_thread():
        yield
        return
    received: list[int] = []
    previous: dict[int, Any] = {}

    def remember(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        if len(received) > 1:
            _restore(previous)
            signal.raise_signal(signum)

    previous.update({s: signal.signal(s, remember) for s in (signal.SIGINT, *STOP_SIGNALS)})
    try:
        yield
    finally:
        _restore(previous)
    if received:
        signal.raise_signal(received[0])


def _restore(handlers: dict[int, Any]) -> None:
    for signum, handler in handlers.items():
        signal.signal(signum, handler)
