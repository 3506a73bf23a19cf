"""The main thread's CPU per frame in each part of `SLAM.process` during a CLI command
(docs/speed.md, "The front end in its own process", "Plane records, region growing and
eigen-solves compiled").

    python docs/scripts/main_thread_cpu.py -q run DATASET --max-frames 300 --out OUT

Runs `planeslam` with the given arguments in this process, with the front end, tracking
(its plane path and the association in it, the result's checks, the keypoint check),
keyframes (and `Map.merge` within them), the backend's update and the smaller parts
timed by `time.thread_time` (the main thread's CPU, not the wait for a core or the
GIL), and prints each part's milliseconds per processed frame.
"""

from __future__ import annotations

import collections
import sys

from _run_probe import thread_cpu

from planeslam.app.cli import main
from planeslam.frontend.pipeline import FrontEnd
from planeslam.mapping.world_map import Map
from planeslam.slam.system import SLAM
from planeslam.tracking import tracker as tracker_module
from planeslam.tracking.plane_path import PlanePath
from planeslam.tracking.tracker import Tracker

SECONDS: collections.Counter[str] = collections.Counter()
CALLS: collections.Counter[str] = collections.Counter()


if __name__ == "__main__":
    parts = (
        (SLAM, "process", "SLAM.process (all)"),
        (FrontEnd, "process", "front end"),
        (Tracker, "track", "tracking"),
        (PlanePath, "register", "  plane path"),
        (PlanePath, "associate", "    of which association"),
        (tracker_module, "track_result", "  the result's checks"),
        (Tracker, "_keypoints_agree", "  keypoint check"),
        (SLAM, "_add_keyframe", "keyframes"),
        (Map, "merge", "  of which Map.merge"),
        (SLAM, "_apply_update", "backend update"),
        (SLAM, "map_view", "map view"),
        (SLAM, "_pose_covariance", "pose covariance"),
    )
    for cls, name, label in parts:
        setattr(cls, name, thread_cpu(getattr(cls, name), SECONDS, label, CALLS))
    try:
        main(sys.argv[1:])
    except SystemExit as exc:
        if exc.code:
            raise
    frames = max(CALLS["SLAM.process (all)"], 1)
    for _, _, label in parts:  # in the order above: each part under the one it is in
        seconds = SECONDS[label]
        print(f"{label:26s} {1e3 * seconds / frames:6.2f} ms/frame ({CALLS[label]} calls)")
