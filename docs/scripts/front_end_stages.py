"""The front end's CPU per frame and each stage's wall time, the organised segmentation's
inner steps included (docs/speed.md, "Plane records, region growing and eigen-solves
compiled").

    python docs/scripts/front_end_stages.py [DATASET] [FRAMES] [ROUNDS]

FRAMES (default 100) evenly spread frames of the first 300 of DATASET (default the
7-Scenes clip beside the checkout), preloaded, go through one `FrontEnd` ROUNDS times
(default 3), on one native thread as `planeslam bench speed` runs it. Per round: the main
thread's CPU per frame (`time.thread_time`), the mean of each `FrontEnd.process` stage
(`FrameObservation.stage_ms`) and of the segmentation's steps (its debug log: cells from
the cloud, cell fits, regions, pixels, plane records).
"""

from __future__ import annotations

import logging
import sys
import time

import numpy as np
from _run_probe import timed_source

from planeslam.core.native_tuning import single_native_threads
from planeslam.frontend.pipeline import STAGES, FrontEnd

POOL = 300
"""The timed frames are spread over this many first frames of the dataset."""
SEGMENTATION_STEPS = ("cloud", "cells", "regions", "pixels", "planes")
"""The steps the organised segmentation's debug line times, in its order."""


class _StepTimes(logging.Handler):
    """Collects the segmentation's per-step milliseconds from its debug line."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.ms: dict[str, list[float]] = {k: [] for k in SEGMENTATION_STEPS}

    def emit(self, record: logging.LogRecord) -> None:
        if str(record.msg).startswith("organized segmentation") and record.args:
            for key, value in zip(SEGMENTATION_STEPS, record.args, strict=False):
                self.ms[key].append(float(value))  # type: ignore[arg-type]


if __name__ == "__main__":
    source = timed_source([sys.argv[0], *sys.argv[1:2], str(POOL)], POOL)
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 3
    pick = np.linspace(0, len(source.indices) - 1, n).round().astype(int)
    frames = [source.dataset[source.indices[int(i)]] for i in pick]
    front_end = FrontEnd(source.config, seed=0)
    segmentation_log = logging.getLogger("planeslam.frontend.organized")
    segmentation_log.setLevel(logging.DEBUG)
    with single_native_threads():
        front_end.process(frames[0].depth_m)
        for r in range(rounds):
            steps = _StepTimes()
            segmentation_log.addHandler(steps)
            stage: dict[str, list[float]] = {s: [] for s in STAGES}
            t0 = time.thread_time()
            for frame in frames:
                observation = front_end.process(frame.depth_m, frame.timestamp)
                for s in STAGES:
                    stage[s].append(observation.stage_ms[s])
            cpu_ms = 1e3 * (time.thread_time() - t0) / n
            segmentation_log.removeHandler(steps)
            print(
                f"round {r + 1}: CPU {cpu_ms:.2f} ms/frame | stages "
                + " ".join(f"{s} {np.mean(v):.2f}" for s, v in stage.items())
                + " | segmentation "
                + " ".join(f"{k} {np.mean(v):.2f}" for k, v in steps.ms.items() if v)
            )
