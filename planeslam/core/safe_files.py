"""Output files that a crash, a kill or a full disk never leaves half written.

- `atomic_output(path)`: a whole file (a map, metrics, a plot) is written beside its
  final name and moved over it in one step (`os.replace`): readers see the old file or
  the new one, never a part. The file is created with `open`, so it gets the usual mode
  (0666 minus the umask: 0644 with the common umask 022).
- `LineWriter`: a log written line by line (a trajectory, frames.jsonl). Each line goes to
  the operating system in one unbuffered write as soon as it is given, so a killed process
  (kill -9) keeps every finished line; a write that fails part way (a full disk) is cut
  back to the last whole line before the error is raised.

Both protect against the process dying, not against the machine losing power (no fsync).
"""

from __future__ import annotations

import errno
import itertools
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, NoReturn

_counter = itertools.count()


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """A temporary path beside `path` to write the whole file to; when the block ends
    without an error it replaces `path` in one step, otherwise it is removed and `path`
    is left as it was. Creates the parent folder."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.{os.getpid()}.{next(_counter)}.tmp")
    try:
        yield tmp
        os.replace(tmp, final)
    except OSError as exc:
        _raise_naming(exc, final, tmp)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` through `atomic_output`; returns the path."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


class LineWriter:
    """Write a text file line by line, each line whole on disk or not at all (see the
    module docstring). Truncates an existing file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO = open(self.path, "wb", buffering=0)
        self._size = 0

    def write_line(self, text: str) -> None:
        """Append `text` and a newline (`text` must not contain one)."""
        data = (text + "\n").encode("utf-8")
        done = 0
        try:
            while done < len(data):  # a raw write may be short (a full disk, a signal)
                written = self._fh.write(data[done:])
                if not written:
                    raise OSError(errno.EIO, "nothing written", str(self.path))
                done += written
        except BaseException as exc:  # a full disk, Ctrl-C: take back what part reached it
            try:
                os.ftruncate(self._fh.fileno(), self._size)
                self._fh.seek(self._size)
            except OSError:
                pass
            if isinstance(exc, OSError):
                _raise_naming(exc, self.path)
            raise
        self._size += len(data)

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> LineWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _raise_naming(exc: OSError, path: Path, tmp: Path | None = None) -> NoReturn:
    """Raise `exc` again, as the same subclass naming `path` (the file its caller knows)
    when it names no file or `tmp`: a write that fails on a full disk names none."""
    if exc.errno is None or exc.filename not in (None, str(tmp), tmp):
        raise exc
    raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
