"""Soak test (`make soak`; outside the default suite): many short runs back to back, in this
process (`run_sequence`) and through the CLI, each with a random fault injected, then a
check that the child processes, open files and memory (RSS) of this process are back
where they started (after warm-up runs).

    .venv/bin/python -m tests.soak [--runs 30] [--cli-runs 10] [--seed 0]

Prints one line of figures (runs, faults injected by kind, leaks) and exits 1 on a leak
or a run whose outcome or outputs were not the expected ones.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from planeslam.app.runner import run_sequence
from planeslam.core.errors import PlaneSlamError
from planeslam.slam import SLAM
from tests.corpus.cases import (
    REPO,
    check_run_outputs,
    child_pids,
    exited,
    frame_files,
    synth_sequence,
    truncate,
)

FRAMES = 8
WARM_UP_RUNS = 8
"""Runs before the starting values are taken: the front end keeps the pixel geometry of
its last 8 cameras (PixelRays objects: one per SLAM) in bounded caches."""
RSS_TOLERANCE_MB = 25.0
"""RSS may end this much above its value after the warm-up runs (allocator caches)."""


def open_files() -> int:
    return len(os.listdir("/proc/self/fd"))


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return 0.0


def snapshot() -> tuple[int, int, float]:
    gc.collect()
    return len(child_pids(os.getpid())), open_files(), rss_mb()


# ------------------------------------------------------------------ in-process runs


def _stop_slam_at(frame: int, action: Callable[[SLAM], None]) -> Callable[[], None]:
    """Make SLAM.process call `action(slam)` when given frame `frame`; returns the undo."""
    original = SLAM.process

    def process(self, *args, **kwargs):
        if self.frames == frame:
            action(self)
        return original(self, *args, **kwargs)

    SLAM.process = process  # type: ignore[method-assign]

    def undo() -> None:
        SLAM.process = original  # type: ignore[method-assign]

    return undo


def _interrupt(slam: SLAM) -> None:
    raise KeyboardInterrupt


def _kill_worker(slam: SLAM) -> None:
    process = getattr(slam.backend, "_process", None)
    if process is not None:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10)


IN_PROCESS_FAULTS = ("none", "missing image", "truncated image", "ctrl-c", "worker killed")


def in_process_run(pristine: Path, work: Path, rng: np.random.Generator) -> str:
    """One run with a random fault; raises AssertionError when it did not end as expected."""
    fault = str(rng.choice(IN_PROCESS_FAULTS))
    backend = "isam2" if fault == "worker killed" else str(rng.choice(["isam2", "merge"]))
    seq = Path(shutil.copytree(pristine, work / "seq"))
    out = work / "out"
    frame = int(rng.integers(1, FRAMES - 1))
    undo: Callable[[], None] = lambda: None  # noqa: E731
    expected: type[BaseException] | None = None
    if fault == "missing image":
        frame_files(seq, frame)[int(rng.integers(2))].unlink()
    elif fault == "truncated image":
        truncate(frame_files(seq, frame)[int(rng.integers(2))])
    elif fault == "ctrl-c":
        undo, expected = _stop_slam_at(frame, _interrupt), KeyboardInterrupt
    elif fault == "worker killed":
        undo, expected = _stop_slam_at(frame, _kill_worker), PlaneSlamError
    try:
        run_sequence(seq, out, backend=backend)
        assert expected is None, f"{fault}: the run did not stop"
    except (KeyboardInterrupt, PlaneSlamError) as exc:
        assert expected is not None and isinstance(exc, expected), f"{fault}: {exc!r}"
    finally:
        undo()
    check_run_outputs(f"soak: {fault}", out)
    shutil.rmtree(work / "seq")
    shutil.rmtree(out)
    return fault


# ------------------------------------------------------------------ CLI runs


CLI_FAULTS = ("none", "SIGTERM", "SIGINT", "kill -9")


def cli_run(pristine: Path, work: Path, rng: np.random.Generator) -> str:
    fault = str(rng.choice(CLI_FAULTS))
    out = work / "cli_out"
    process = subprocess.Popen(
        [sys.executable, "-m", "planeslam.app.cli", "run", str(pristine), "--out", str(out)]
        + ["-q", "--backend", str(rng.choice(["isam2", "merge"]))],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    workers: set[int] = set()
    if fault != "none":
        after = int(rng.integers(1, FRAMES - 2))
        end = time.monotonic() + 120
        frames = out / "frames.jsonl"
        while not (frames.is_file() and frames.read_text().count("\n") >= after):
            assert process.poll() is None, f"{fault}: the run ended first"
            assert time.monotonic() < end, f"{fault}: timed out"
            workers.update(child_pids(process.pid))
            time.sleep(0.02)
        workers.update(child_pids(process.pid))
        time.sleep(float(rng.uniform(0.0, 0.1)))
        process.send_signal(
            {"SIGTERM": signal.SIGTERM, "SIGINT": signal.SIGINT, "kill -9": signal.SIGKILL}[fault]
        )
    _, stderr = process.communicate(timeout=180)
    codes = {"none": 0, "SIGTERM": 143, "SIGINT": 130, "kill -9": -9}
    assert process.returncode == codes[fault], f"{fault}: exit {process.returncode}: {stderr}"
    assert "Traceback" not in stderr, stderr
    check_run_outputs(f"soak cli: {fault}", out, complete=fault != "kill -9")
    assert all(exited(pid) for pid in workers), f"{fault}: the backend worker outlived its run"
    shutil.rmtree(out)
    return f"cli {fault}"


# ------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.soak", description=__doc__)
    parser.add_argument("--runs", type=int, default=30, help="in-process runs (default 30)")
    parser.add_argument("--cli-runs", type=int, default=10, help="CLI runs (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="fault seed (default 0)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)  # the injected faults' warnings are expected
    rng = np.random.default_rng(args.seed)
    faults: Counter[str] = Counter()
    with tempfile.TemporaryDirectory(prefix="planeslam-soak-") as tmp:
        work = Path(tmp)
        pristine = synth_sequence(work / "pristine", frames=FRAMES).out_dir
        for k in range(WARM_UP_RUNS):  # imports, the first worker, the front end's caches
            run_sequence(pristine, work / "warm", backend=("isam2", "merge")[k % 2])
            shutil.rmtree(work / "warm")
        start = snapshot()
        t0 = time.monotonic()
        for _ in range(args.runs):
            faults[in_process_run(pristine, work, rng)] += 1
        for _ in range(args.cli_runs):
            faults[cli_run(pristine, work, rng)] += 1
        seconds = time.monotonic() - t0
        end = snapshot()
    leaks = []
    if end[0] > start[0]:
        leaks.append(f"child processes {start[0]} -> {end[0]}")
    if end[1] > start[1]:
        leaks.append(f"open files {start[1]} -> {end[1]}")
    if end[2] > start[2] + RSS_TOLERANCE_MB:
        leaks.append(f"RSS {start[2]:.0f} -> {end[2]:.0f} MB")
    injected = sum(n for kind, n in faults.items() if not kind.endswith("none"))
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(faults.items()))
    print(
        f"soak: {args.runs + args.cli_runs} runs ({args.runs} in-process, {args.cli_runs} CLI) "
        f"in {seconds:.0f} s, {injected} faults injected ({kinds}); leaks {len(leaks)}: "
        f"child processes {start[0]} -> {end[0]}, open files {start[1]} -> {end[1]}, "
        f"RSS {start[2]:.0f} -> {end[2]:.0f} MB"
    )
    for leak in leaks:
        print(f"leak: {leak}", file=sys.stderr)
    return 1 if leaks else 0


if __name__ == "__main__":
    sys.exit(main())
