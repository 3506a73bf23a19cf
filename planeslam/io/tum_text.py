"""The text format shared by TUM RGB-D files (trajectories, rgb.txt / depth.txt lists,
associations.txt): one row per line, '#' comments and blank lines skipped."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from planeslam.core.bounded_parse import read_text
from planeslam.core.errors import DatasetFormatError

MAX_TEXT_BYTES = 1 << 30
"""Largest list or trajectory file read [bytes] (a long sequence's are a few MB)."""


def tum_rows(
    path: Path, kind: str, expected: str, entries: str = "entries"
) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields split on white space and commas) of every row of `path`.

    For the errors (DatasetFormatError naming the file when it is missing or holds no
    rows): `kind` names the file ('trajectory'), `expected` a row ('timestamp path'),
    `entries` what rows hold ('poses'); also when it is not UTF-8 text. Readers check the
    fields and raise `row_error`."""
    if not path.is_file():
        raise DatasetFormatError(f"{path}: {kind} file not found (expected rows '{expected}')")
    count = 0
    for lineno, line in enumerate(
        read_text(path, DatasetFormatError, MAX_TEXT_BYTES).split("\n"), 1
    ):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        count += 1
        yield lineno, text.replace(",", " ").split()
    if not count:
        raise DatasetFormatError(f"{path}: no {entries} (expected rows '{expected}')")


def row_error(path: Path, lineno: int, expected: str, fields: list[str]) -> DatasetFormatError:
    """The error for a malformed row: `expected` says what a row holds ("'timestamp path'"),
    the start of the row is quoted."""
    text = " ".join(fields)
    return DatasetFormatError(f"{path}:{lineno}: expected {expected}, got {text[:80]!r}")
