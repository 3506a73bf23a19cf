"""Where the whole system's CPU goes during a run, by thread and process (docs/speed.md,
"The front end on the reader thread (tried, not kept)").

    python docs/scripts/whole_system_threads.py [DATASET] [FRAMES] [SWITCH_INTERVAL_S]

`run_frames` on a fresh SLAM over the first FRAMES (default 300) frames of DATASET
(default the 7-Scenes clip beside the checkout), as `planeslam bench speed` runs the whole
system, with Python's thread switch interval set to SWITCH_INTERVAL_S (default Python's
0.005 s). Prints the wall time per frame, `SLAM.finish`'s share, and the CPU per frame of
the main thread, of the process's other threads (the reader, the fused-cloud thread) and
of the backend worker process.
"""

from __future__ import annotations

import collections
import os
import sys
import time

from _run_probe import thread_cpu, timed_source

from planeslam.slam import run_frames, slam_for_dataset
from planeslam.slam.system import SLAM

if __name__ == "__main__":
    if len(sys.argv) > 3:
        sys.setswitchinterval(float(sys.argv[3]))
    source = timed_source(sys.argv[:3], 300)
    finish_cpu: collections.Counter[str] = collections.Counter()
    finish_wall: collections.Counter[str] = collections.Counter()
    SLAM.finish = thread_cpu(  # type: ignore[method-assign]
        SLAM.finish, finish_cpu, "finish", wall=finish_wall
    )
    children0 = os.times()
    slam = slam_for_dataset(source.config, source.dataset, source.indices[0])
    with slam:
        p0, t0, w0 = time.process_time(), time.thread_time(), time.perf_counter()
        summary = run_frames(slam, source.dataset, source.indices)
        p1, t1, w1 = time.process_time(), time.thread_time(), time.perf_counter()
    children1 = os.times()
    worker = children1.children_user + children1.children_system
    worker -= children0.children_user + children0.children_system
    n = summary.frames
    print(
        f"wall {1e3 * (w1 - w0) / n:.1f} ms/frame (of which SLAM.finish "
        f"{1e3 * finish_wall['finish'] / n:.1f}); CPU ms/frame: main thread "
        f"{1e3 * (t1 - t0) / n:.1f}, "
        f"other threads {1e3 * ((p1 - p0) - (t1 - t0)) / n:.1f}, worker {1e3 * worker / n:.1f}"
    )
