"""Open3D's RGB-D odometry (the dense fallback's first method) on one thread against the
machine's CPUs, on consecutive frame pairs (docs/speed.md, "Open3D on one thread").

    python docs/scripts/open3d_threads.py [DATASET] [PAIRS]

Times `RgbdOdometry.motion` on the first PAIRS (default 30) consecutive pairs of DATASET
(default ../shared/data/7scenes_redkitchen_1000f) with `open3d.utility.set_max_threads`
1 and with every CPU, alternated over three rounds, alone and beside a process that keeps
one core busy (as the backend worker does): median wall and CPU (all threads) ms per
call. Then counts, per setting, the pairs whose five repeated calls gave more than one
result (bit for bit).
"""

from __future__ import annotations

import multiprocessing
import os
import statistics
import sys
import time

import numpy as np
import open3d as o3d
from _run_probe import first_frames

from planeslam.tracking.odometry import RgbdOdometry


def _spin(stop: multiprocessing.synchronize.Event) -> None:
    while not stop.is_set():
        sum(range(10_000))


def _timed(odometry: RgbdOdometry, pairs: list, threads: int) -> tuple[float, float]:
    """(wall, CPU) ms per call over `pairs` with Open3D held to `threads`."""
    o3d.utility.set_max_threads(threads)
    wall, cpu = time.perf_counter(), time.process_time()
    for current, previous in pairs:
        odometry.motion(current, previous)
    n = len(pairs)
    return 1e3 * (time.perf_counter() - wall) / n, 1e3 * (time.process_time() - cpu) / n


def main() -> None:
    dataset, camera, frames = first_frames(sys.argv, 30)
    count = len(frames) - 1
    odometry = RgbdOdometry(camera)
    images = [odometry.image(f.rgb, f.depth_m) for f in frames]
    pairs = list(zip(images[1:], images[:-1], strict=True))
    cpus = len(os.sched_getaffinity(0))
    print(f"{dataset.root.name}: {count} pairs, {cpus} CPUs, load average {os.getloadavg()[0]:.2f}")
    for beside in ("alone", "beside a busy core"):
        stop = multiprocessing.Event()
        spinner = None
        if beside != "alone":
            spinner = multiprocessing.Process(target=_spin, args=(stop,), daemon=True)
            spinner.start()
        figures: dict[int, list[tuple[float, float]]] = {1: [], cpus: []}
        for _ in range(3):
            for threads in figures:
                figures[threads].append(_timed(odometry, pairs, threads))
        if spinner is not None:
            stop.set()
            spinner.join()
        for threads, rounds in figures.items():
            wall = statistics.median(w for w, _ in rounds)
            cpu = statistics.median(c for _, c in rounds)
            print(f"  {beside}, {threads} thread(s): {wall:.1f} ms wall, {cpu:.1f} ms CPU per call")
    for threads in (1, cpus):
        o3d.utility.set_max_threads(threads)
        varied = 0
        for current, previous in pairs:
            results = {np.asarray(odometry.motion(current, previous)).tobytes() for _ in range(5)}
            varied += len(results) > 1
        print(f"  {threads} thread(s): {varied} of {count} pairs gave more than one result")
    o3d.utility.set_max_threads(0)


if __name__ == "__main__":
    main()
