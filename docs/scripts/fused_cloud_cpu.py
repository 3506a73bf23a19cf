"""CPU time of the fused-cloud figure's worker thread over a whole run (docs/speed.md).

    python docs/scripts/fused_cloud_cpu.py [DATASET] [FRAMES]

Runs the whole system (as `planeslam bench speed` does: `run_frames` on a fresh SLAM)
and prints its wall time and CPU ms per frame, and the CPU seconds (`time.thread_time`
of the thread that ran them) of `FusedCloudSize`'s keyframe additions and of its merges
of new voxel keys into the kept ones.
"""

from __future__ import annotations

import sys

from _run_probe import thread_cpu, time_whole_run

import planeslam.mapping.sparse_cloud as sparse_cloud

spent = {"additions": 0.0, "merges": 0.0}
size = sparse_cloud.FusedCloudSize
size._add_sampled = thread_cpu(size._add_sampled, spent, "additions")  # merges included
size._flush = thread_cpu(size._flush, spent, "merges")

seconds, n, cpu = time_whole_run(sys.argv, 1000)
print(
    f"{n} frames: {seconds:.1f} s wall, {cpu / n * 1e3:.1f} CPU ms/frame; fused cloud: "
    f"additions {spent['additions']:.2f} s CPU (merges {spent['merges']:.2f} s of them)"
)
