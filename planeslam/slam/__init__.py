"""The orchestrator (`SLAM`, in `system`): frame -> front end -> tracking -> map / backend;
every frame's pose on its anchor keyframe (`anchors`); the map as tracking's view
(`map_view`); what it made of a frame and of a run (`records`); SLAM over a dataset
(`runs`)."""

from planeslam.slam.map_view import map_view
from planeslam.slam.records import FrameResult, RunSummary, RunTally
from planeslam.slam.runs import frame_indices, run_frames, slam_for_dataset
from planeslam.slam.system import SLAM

__all__ = [
    "SLAM",
    "FrameResult",
    "RunSummary",
    "RunTally",
    "frame_indices",
    "map_view",
    "run_frames",
    "slam_for_dataset",
]
