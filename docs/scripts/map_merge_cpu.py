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
import time
from pathlib import Path

import planeslam.mapping.seating as seating
import planeslam.tracking.association as association
from planeslam.app.bench_speed import _open_source, _time_whole_system
from planeslam.mapping.world_map import Map
from planeslam.slam.system import SLAM

spent = {"process": 0.0, "merge": 0.0, "hulls": 0.0}


def _timed(function, figure):
    def wrapper(*args, **kwargs):
        start = time.thread_time()
        try:
            return function(*args, **kwargs)
        finally:
            spent[figure] += time.thread_time() - start

    return wrapper


SLAM.process = _timed(SLAM.process, "process")
Map.merge = _timed(Map.merge, "merge")
seating.convex_hull_2d = _timed(seating.convex_hull_2d, "hulls")
association.convex_hull_2d = _timed(association.convex_hull_2d, "hulls")

dataset = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/7scenes_redkitchen_1000f")
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 300
seconds, n, cpu = _time_whole_system(_open_source(dataset, frames, None, ()))
print(
    f"{n} frames: {seconds:.1f} s wall, {cpu / n * 1e3:.1f} CPU ms/frame; main thread: "
    f"SLAM.process {spent['process'] / n * 1e3:.2f} ms/frame, of which Map.merge "
    f"{spent['merge'] / n * 1e3:.2f}, convex hulls {spent['hulls'] / n * 1e3:.2f}"
)
