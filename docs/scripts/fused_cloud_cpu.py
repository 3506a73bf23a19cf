"""CPU time of the fused-cloud figure's worker thread over a whole run (docs/speed.md).

    python docs/scripts/fused_cloud_cpu.py [DATASET] [FRAMES]

Runs the whole system (as `planeslam bench speed` does: `run_frames` on a fresh SLAM)
and prints its wall time and CPU ms per frame, and the CPU seconds (`time.thread_time`
of the thread that ran them) of `FusedCloudSize`'s keyframe additions and of its merges
of new voxel keys into the kept ones.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import planeslam.mapping.sparse_cloud as sparse_cloud
from planeslam.app.bench_speed import _open_source, _time_whole_system

spent = {"additions": 0.0, "merges": 0.0}


def _timed(method, figure):
    def wrapper(self, *args):
        start = time.thread_time()
        method(self, *args)
        spent[figure] += time.thread_time() - start

    return wrapper


size = sparse_cloud.FusedCloudSize
size._add_sampled = _timed(size._add_sampled, "additions")  # includes the merges it runs
size._flush = _timed(size._flush, "merges")

dataset = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/7scenes_redkitchen_1000f")
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 1000
seconds, n, cpu = _time_whole_system(_open_source(dataset, frames, None, ()))
print(
    f"{n} frames: {seconds:.1f} s wall, {cpu / n * 1e3:.1f} CPU ms/frame; fused cloud: "
    f"additions {spent['additions']:.2f} s CPU (merges {spent['merges']:.2f} s of them)"
)
