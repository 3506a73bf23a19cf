"""Where `SLAM.finish` spends its time at the end of a run (docs/speed.md, "The run's end").

    python docs/scripts/run_end.py [DATASET] [FRAMES] [ROUNDS]

`run_frames` on a fresh SLAM over the first FRAMES (default 300) frames of DATASET
(default the 7-Scenes clip beside the checkout), as `planeslam bench speed` runs the whole
system, ROUNDS times (default 3). Prints per round the wall time of the run per frame and
of `SLAM.finish`, and within it: the backend's final batch (the wait for the worker's
last updates and its batch), stopping the worker process, and the re-estimation of the
frames between keyframes (`AnchoredPoses.reestimate`; its main-thread CPU too).
"""

from __future__ import annotations

import collections
import sys
import time

from _run_probe import thread_cpu, timed_source

from planeslam.backend.worker import Isam2Worker
from planeslam.slam import run_frames, slam_for_dataset
from planeslam.slam.anchors import AnchoredPoses
from planeslam.slam.system import SLAM

WALL: collections.Counter[str] = collections.Counter()
CPU: collections.Counter[str] = collections.Counter()


if __name__ == "__main__":
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 3
    parts = (
        (SLAM, "finish", "SLAM.finish"),
        (Isam2Worker, "finish", "backend finish"),  # the final batch, then close
        (Isam2Worker, "close", "worker stop"),
        (AnchoredPoses, "reestimate", "re-estimation"),
    )
    for cls, name, label in parts:
        setattr(cls, name, thread_cpu(getattr(cls, name), CPU, label, wall=WALL))
    source = timed_source(sys.argv[:3], 300)
    for r in range(rounds):
        WALL.clear()
        CPU.clear()
        slam = slam_for_dataset(source.config, source.dataset, source.indices[0])
        with slam:
            start = time.perf_counter()
            summary = run_frames(slam, source.dataset, source.indices)
            wall = time.perf_counter() - start
        n = summary.frames
        print(
            f"round {r + 1}: run {1e3 * wall / n:.1f} ms/frame; SLAM.finish "
            f"{WALL['SLAM.finish']:.3f} s: final batch "
            f"{WALL['backend finish'] - WALL['worker stop']:.3f} s, worker stop "
            f"{WALL['worker stop']:.3f} s, re-estimation {WALL['re-estimation']:.3f} s "
            f"(CPU {CPU['re-estimation']:.3f} s)",
            flush=True,
        )
