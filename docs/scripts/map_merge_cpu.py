"""CPU time of the map's keyframe merge and of the main thread's frames over a whole run
(docs/speed.md, "The map merge's hulls").

    python docs/scripts/map_merge_cpu.py [DATASET] [FRAMES]

Runs the whole system (as `planeslam bench speed` does: `run_frames` on a fresh SLAM)
and prints its wall time and CPU ms per frame, and the CPU time (`time.thread_time` of
the main thread) of `SLAM.process`, of `Map.merge` (the keyframe's map update) and of the
2-D convex hulls (`convex_hull_2d`, in the merge and in plane association).
"""

from __future__ import annotations

import sys

from _run_probe import HULL_CALLERS, thread_cpu, time_whole_run

from planeslam.mapping.world_map import Map
from planeslam.slam.system import SLAM

spent = {"process": 0.0, "merge": 0.0, "hulls": 0.0}
SLAM.process = thread_cpu(SLAM.process, spent, "process")
Map.merge = thread_cpu(Map.merge, spent, "merge")
for caller in HULL_CALLERS:
    caller.convex_hull_2d = thread_cpu(caller.convex_hull_2d, spent, "hulls")

seconds, n, cpu = time_whole_run(sys.argv, 300)
print(
    f"{n} frames: {seconds:.1f} s wall, {cpu / n * 1e3:.1f} CPU ms/frame; main thread: "
    f"SLAM.process {spent['process'] / n * 1e3:.2f} ms/frame, of which Map.merge "
    f"{spent['merge'] / n * 1e3:.2f}, convex hulls {spent['hulls'] / n * 1e3:.2f}"
)
