"""Full SLAM from Python, one frame at a time (the README's first example).

Frames are rendered from the synthetic box-in-a-room scene; put your camera's frames in
their place: depth (H, W) float32 metres (0 = invalid), colour (H, W, 3) uint8, time [s].

    python examples/slam_quickstart.py
"""

import numpy as np

from planeslam import SLAM, load_config
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle

scene, truth = box_room_circle(frames=24)  # stand-in for your camera
config = load_config("synthetic")  # or a preset / YAML file with your camera's intrinsics
rng = np.random.default_rng(0)
with SLAM(config, backend="isam2", T_world_first=truth.T_world_cam[0]) as slam:
    for i, T_world_cam in enumerate(truth.T_world_cam):
        frame = render_frame(scene, T_world_cam, config.camera, rng)
        result = slam.process(frame.depth_m, i / 30.0, frame.rgb)  # pose, tracking path
    slam.finish()  # final optimisation; the backend process stops
trajectory = slam.trajectory()  # T_world_cam per tracked frame
error_m = trajectory.T_world_cam[:, :3, 3] - truth.T_world_cam[:, :3, 3]
print(f"{len(trajectory.timestamps)} poses, RMSE {np.sqrt((error_m**2).sum(1).mean()):.4f} m")
for obj in slam.map.objects:
    print(obj.cls, " x ".join(f"{s:.3f}" for s in obj.size_m), "m")
