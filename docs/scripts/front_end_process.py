"""The whole system with the front end in-process against the front end one frame ahead in
a child process (docs/speed.md, "The front end in its own process (tried, not kept)").

    git apply docs/patches/front-end-process.patch
    python docs/scripts/front_end_process.py [DATASET] [FRAMES] [ROUNDS]

Needs the patch (it adds `run_frames(..., front_end_process=...)`). Runs `run_frames` on
the first FRAMES (default 300) frames of DATASET (default
../shared/data/7scenes_redkitchen_1000f) in ROUNDS (default 2) rounds, in-process then in
the worker, and prints per run: fps, this process's CPU ms per frame (main thread, reader
and reply threads), the children's (the backend's and the front-end worker's) and the
time the main thread waited for observations. Checks that both give the same
trajectory, bit for bit.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from _run_probe import timed_source

from planeslam.core.native_tuning import keep_freed_memory
from planeslam.frontend import worker
from planeslam.slam import run_frames, slam_for_dataset

WAITED = [0.0]


def _timed_result(self: worker.FrontEndWorker, _result=worker.FrontEndWorker.result) -> object:
    t0 = time.perf_counter()
    try:
        return _result(self)
    finally:
        WAITED[0] += time.perf_counter() - t0


def main() -> None:
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 2
    keep_freed_memory()  # as the CLI does
    worker.FrontEndWorker.result = _timed_result  # type: ignore[method-assign]
    source = timed_source(sys.argv, 300)
    trajectories = {}
    for _ in range(rounds):
        for in_worker in (False, True):
            WAITED[0] = 0.0
            slam = slam_for_dataset(source.config, source.dataset, source.indices[0])
            with slam:
                t0 = os.times()
                summary = run_frames(
                    slam, source.dataset, source.indices, front_end_process=in_worker
                )
                t1 = os.times()
            n = summary.frames
            own = t1.user + t1.system - t0.user - t0.system
            children = t1.children_user + t1.children_system - t0.children_user - t0.children_system
            print(
                f"front end {'in its process' if in_worker else 'in-process   '}: "
                f"{n / summary.seconds:5.1f} fps; CPU ms/frame: this process "
                f"{1e3 * own / n:.1f}, children {1e3 * children / n:.1f}; waited for "
                f"observations {1e3 * WAITED[0] / n:.1f} ms/frame; load {os.getloadavg()[0]:.2f}",
                flush=True,
            )
            trajectories[in_worker] = slam.trajectory().T_world_cam
    same = np.array_equal(trajectories[False], trajectories[True])
    print(f"trajectories bit-identical: {same}")


if __name__ == "__main__":
    main()
