"""How long the sweep over a partial plane pose's free directions takes on real frames
(docs/experiments.md, "A free turn swept too").

    python docs/scripts/sweep_timing.py SEQUENCE OUT FRAMES INDICES

Runs `planeslam run` on the TUM-layout folder SEQUENCE into OUT, its first FRAMES frames.
On each frame of the comma-separated INDICES that reaches the dense fallback with a
partial plane pose, it times the sweep of the directions the planes left free 15 times
(`sweep_free_motion` for a free turn or two free directions, `sweep_free_translation`
for one) and prints the median [ms] and how many poses it offered.
"""

from __future__ import annotations

import statistics
import sys
import time

from _run_probe import count_frames

import planeslam.tracking.dense as dense
from planeslam.app.runner import run_sequence

sequence, out, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
indices = {int(i) for i in sys.argv[4].split(",")}
current = count_frames()


def _timing(with_swept):
    def wrapper(self, starts, registration, cloud, rgbd):
        if current["frame"] in indices and cloud is not None and self.previous_cloud is not None:
            grey, last = self._landing_inputs(rgbd)
            axes = registration.unobservable_rotation_axes
            directions = registration.unobservable_translation_dirs
            line = not len(axes) and len(directions) == 1
            seconds = []
            for _ in range(15):
                start = time.perf_counter()
                if line:
                    found = dense.sweep_free_translation(
                        starts[0], directions[0], cloud, grey, last, self.camera
                    )
                    offered = [] if found is None else [found]
                else:
                    offered = dense.sweep_free_motion(
                        starts[0], axes, directions, cloud, grey, last, self.camera
                    )
                seconds.append(time.perf_counter() - start)
            print(
                f"frame {current['frame']}: free turns {len(axes)}, directions "
                f"{len(directions)}: median {1e3 * statistics.median(seconds):.1f} ms, "
                f"{len(offered)} poses offered"
            )
        return with_swept(self, starts, registration, cloud, rgbd)

    return wrapper


dense.DenseFallback.with_swept = _timing(dense.DenseFallback.with_swept)
run_sequence(sequence, out, max_frames=frames)
