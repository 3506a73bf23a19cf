"""The fault corpus: small faulty inputs built on the fly (tiny synthetic sequences, cut and
corrupted images, malformed text files), the outcome each case must give, and a tally of
the outcomes that `make test` prints at its end (tests/corpus/tally.py).

Every case is one of
- a clean error: the expected PlaneSlamError (CLI: exit code 2) with a one-line message
  that matches the case's pattern;
- handled: the documented outcome instead of an error (a frame skipped with a warning,
  invalid depth ignored, an evaluation left out with a warning, outputs kept on a signal);
and must never be
- a crash: another exception, a traceback, a hang, or a message other than the expected;
- a run that lost output: a run folder whose files are incomplete or inconsistent
  (`check_run_outputs`).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from planeslam.core.camera import CameraConfig
from planeslam.eval.metrics import read_metrics
from planeslam.io.trajectory import read_tum
from planeslam.mapping.world_map import Map
from tests.corpus.tally import Outcome, record

SMALL_CAMERA = CameraConfig(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
"""The corpus's camera: a quarter of the usual pixels, the usual field of view."""

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ building inputs


def synth_sequence(root: Path, frames: int = 6, scene: str = "box_room_circle", seed: int = 3):
    """A short rendered sequence (TUM layout, truth.json, groundtruth.txt) at SMALL_CAMERA."""
    from planeslam.sim.sequence import synthesize

    return synthesize(scene, root, frames=frames, seed=seed, camera=SMALL_CAMERA)


def truncate(path: Path, keep: float = 0.5) -> Path:
    """Cut the file to `keep` of its bytes (a copy interrupted part way)."""
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def corrupt(path: Path, seed: int = 0) -> Path:
    """Overwrite bytes in the middle third of the file with noise (its end kept)."""
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    lo, hi = len(data) // 3, 2 * len(data) // 3
    data[lo:hi] = rng.integers(0, 256, hi - lo, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    return path


def list_rows(path: Path) -> list[str]:
    """The data rows of a TUM text file (comments dropped)."""
    return [r for r in path.read_text().splitlines() if r.strip() and not r.startswith("#")]


def rewrite_rows(path: Path, change: Callable[[list[str]], list[str]]) -> Path:
    """Replace the data rows of a TUM text file by `change(rows)`."""
    path.write_text("\n".join(change(list_rows(path))) + "\n")
    return path


def frame_files(root: Path, index: int) -> tuple[Path, Path]:
    """(rgb, depth) image paths of frame `index` of a synthetic sequence."""
    fields = list_rows(root / "associations.txt")[index].split()
    return root / fields[1], root / fields[3]


def write_png(path: Path, image: np.ndarray) -> Path:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")
    return path


# ------------------------------------------------------------------ expecting outcomes


def one_line(message: str) -> bool:
    return "\n" not in message.strip() and "Traceback" not in message


def expect_error(
    case: str, error: type[BaseException], pattern: str, call: Callable[[], Any]
) -> BaseException:
    """Run `call`; it must raise `error` with a one-line message matching `pattern`.
    Records a clean error, or a crash (and fails the test)."""
    try:
        call()
    except error as exc:
        if re.search(pattern, str(exc)) and one_line(str(exc)):
            record(case, Outcome.CLEAN_ERROR)
            return exc
        record(case, Outcome.CRASH)
        pytest.fail(f"{case}: message {str(exc)!r} does not match {pattern!r} in one line")
    except BaseException as exc:
        record(case, Outcome.CRASH)
        raise AssertionError(f"{case}: expected {error.__name__}, got {exc!r}") from exc
    record(case, Outcome.CRASH)
    pytest.fail(f"{case}: expected {error.__name__} matching {pattern!r}, nothing raised")


def expect_handled(case: str, call: Callable[[], Any]) -> Any:
    """Run `call` (which asserts the case's documented outcome); any exception (a failed
    assertion included) is a crash."""
    try:
        value = call()
    except BaseException:
        record(case, Outcome.CRASH)
        raise
    record(case, Outcome.HANDLED)
    return value


def cli(
    args: list[str],
    timeout: float = 180,
    **kwargs: Any,
) -> subprocess.CompletedProcess[str]:
    """`planeslam ARGS` in a child interpreter (text output captured)."""
    return subprocess.run(
        [sys.executable, "-m", "planeslam.app.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
        **kwargs,
    )


def expect_cli_error(
    case: str, result: subprocess.CompletedProcess[str], pattern: str, code: int = 2
) -> None:
    """A finished `cli` call must have exited with `code` and one stderr line (besides
    log lines) 'planeslam: ...' matching `pattern`, without a traceback."""
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("planeslam:")]
    ok = (
        result.returncode == code
        and "Traceback" not in result.stderr
        and len(lines) == 1
        and re.search(pattern, lines[0]) is not None
    )
    record(
        case, Outcome.CLEAN_ERROR if ok and code == 2 else Outcome.HANDLED if ok else Outcome.CRASH
    )
    assert ok, f"{case}: exit {result.returncode}, stderr:\n{result.stderr[-3000:]}"


# ------------------------------------------------------------------ checking run folders


def check_run_outputs(
    case: str, out: Path, complete: bool = True, frames: int | None = None
) -> dict[str, Any]:
    """Every output of a `planeslam run` folder is whole and they agree: config.yaml parses,
    every frames.jsonl line is a JSON record, trajectory.txt reads, and when `complete`
    (the run wrote its final files) map.json loads, metrics.json counts the frames of
    frames.jsonl and every trajectory row is one of theirs (frames without a final pose
    are left out); when not, the trajectory has a row per tracked frame (and perhaps the
    next: a kill between the two writes); no temporary file is left.
    Records a run that lost output (and fails the test) otherwise. Returns what it read."""
    problems: list[str] = []
    found: dict[str, Any] = {}
    try:
        yaml.safe_load((out / "config.yaml").read_text())
        records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
        found["records"] = records
        if frames is not None and len(records) != frames:
            problems.append(f"frames.jsonl has {len(records)} records, expected {frames}")
        tracked = sum(r["path"] != "lost" for r in records)  # lost frames have no pose
        stamps = read_tum(out / "trajectory.txt").timestamps if tracked else np.zeros(0)
        rows = found["trajectory_rows"] = len(stamps)
        recorded = {round(r["timestamp"], 6) for r in records}
        unknown = [t for t in np.round(stamps, 6).tolist() if t not in recorded]
        if complete:
            found["map"] = Map.load(out / "map.json")
            metrics = read_metrics(out / "metrics.json")
            found["metrics"] = metrics
            # Final poses: frames without one (lost, or in a segment never joined) are left out.
            if metrics.frames != len(records) or unknown or (tracked and not rows):
                problems.append(
                    f"metrics.json counts {metrics.frames} frames, trajectory.txt has {rows} "
                    f"rows ({len(unknown)} of frames not in frames.jsonl), frames.jsonl "
                    f"{len(records)} records ({tracked} tracked)"
                )
        elif unknown[1:] or not tracked <= rows <= tracked + 1:  # killed between two writes
            problems.append(f"trajectory.txt has {rows} rows for {tracked} tracked frames")
    except Exception as exc:  # unreadable or missing: lost
        problems.append(f"{type(exc).__name__}: {exc}")
    leftovers = [p.name for p in out.glob(".*.tmp")] + [p.name for p in out.glob("*.tmp")]
    if leftovers:
        problems.append(f"temporary files left: {leftovers}")
    record(f"{case} (outputs)", Outcome.LOST_OUTPUT if problems else Outcome.OUTPUT_KEPT)
    assert not problems, f"{case}: {out}: " + "; ".join(problems)
    return found


# ------------------------------------------------------------------ processes


def child_pids(pid: int) -> list[int]:
    """Ids of the live (not zombie) processes whose parent is `pid`."""
    found = []
    for stat_file in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat_file.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(stat_file.parent.name))
    return found


def exited(pid: int, timeout: float = 15) -> bool:
    """Whether process `pid` has exited (or is a zombie) within `timeout` seconds."""
    end = time.monotonic() + timeout
    while True:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return True
        if state == "Z":  # exited, not reaped yet by its (new) parent
            return True
        if time.monotonic() > end:
            return False
        time.sleep(0.05)


def umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
