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

Neither follows a symbolic link planted in the output folder: files are created with
`O_NOFOLLOW` (a temporary file with `O_EXCL` under a random name), so a link at a
final name is replaced, never written through. `open_output` and `read_regular_file`
do the same for other writers and readers, and `FolderLock` keeps one writer per folder.
"""

from __future__ import annotations

import errno
import fcntl
import os
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, NoReturn

from planeslam.core.errors import OutputFolderError

_NO_FOLLOW = os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK  # NONBLOCK: a FIFO never hangs us


def _open_fd(path: Path, flags: int) -> int:
    """os.open with `flags` and `_NO_FOLLOW`, checked to be a regular file (then blocking
    again). OSError naming `path` for a symbolic link or anything but a regular file."""
    try:
        fd = os.open(path, flags | _NO_FOLLOW, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise OSError(exc.errno, "is a symbolic link (not followed)", str(path)) from None
        if exc.errno == errno.ENXIO:  # a FIFO without a reader
            raise OSError(exc.errno, "not a regular file", str(path)) from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    os.set_blocking(fd, True)
    return fd


def open_output(path: str | Path, append: bool = False, buffering: int = -1) -> BinaryIO:
    """`path` opened for binary writing (truncated, or appended to with `append`), never
    through a symbolic link (`buffering` as `open`'s). OSError naming `path` for a link, a
    FIFO or a folder at that name."""
    mode = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
    fd = _open_fd(Path(path), mode)
    return open(fd, "ab" if append else "wb", buffering=buffering)


def resolve_path(path: str | Path) -> Path:
    """`path` made absolute with every symbolic link resolved; OSError (ELOOP) naming it
    for a link loop (pathlib raises RuntimeError there)."""
    try:
        return Path(path).resolve()
    except RuntimeError:
        raise OSError(errno.ELOOP, "symbolic link loop", str(path)) from None


def regular_file_size(path: str | Path) -> int | None:
    """The size [bytes] of `path` when it is a regular file itself (not a link), else None."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_size if stat.S_ISREG(st.st_mode) else None


def read_regular_file(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of `path`, a regular file of at most `max_bytes`, read without following a
    symbolic link. OSError naming `path` otherwise."""
    fd = _open_fd(Path(path), os.O_RDONLY)
    with open(fd, "rb") as fh:
        size = os.fstat(fd).st_size
        if size > max_bytes:
            raise OSError(errno.EFBIG, f"{size} bytes, more than {max_bytes}", str(path))
        return fh.read(max_bytes + 1)[:max_bytes]


@contextmanager
def atomic_output(path: str | Path, keep_suffix: bool = False) -> Iterator[Path]:
    """A temporary path beside `path` to write the whole file to; when the block ends
    without an error it replaces `path` in one step, otherwise it is removed and `path`
    is left as it was. Creates the parent folder. `keep_suffix`: the temporary name ends
    in `path`'s suffix (for writers that choose the format by it: OpenCV, Open3D)."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    suffix = final.suffix if keep_suffix else ""
    tmp = final.with_name(f".{final.name}.{secrets.token_hex(6)}.tmp{suffix}")
    try:
        os.close(_open_fd(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL))  # ours, not a link
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
    module docstring). Truncates an existing file; never writes through a link."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO = open_output(self.path, buffering=0)
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


LOCK_NAME = ".planeslam.lock"
"""The lock file a writer holds in its output folder (`FolderLock`)."""


class FolderLock:
    """An exclusive `fcntl.flock` on `folder`/.planeslam.lock, held while a run writes
    there: a second writer gets OutputFolderError naming the holder's process id. The
    lock goes with the process (a killed run leaves no stale lock); the file stays."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / LOCK_NAME
        fd = _open_fd(path, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise OutputFolderError(
                f"{self.folder}: another run (pid {holder}) is writing there; wait for it "
                "or choose another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
