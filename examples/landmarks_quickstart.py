"""planeslam's plane and corner landmarks in your own GTSAM graph (the README's second
example): your poses and odometry, our landmarks, your optimiser.

Here the odometry is the true motion of the synthetic box-in-a-room scene; use yours.

    python examples/landmarks_quickstart.py
"""

import gtsam
import numpy as np

from planeslam import FrontEnd, LandmarkKeys, PlaneLandmarks, RecoveringISAM2, load_config
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle

scene, truth = box_room_circle(frames=24)
config = load_config("synthetic")  # your camera: config.camera
front_end = FrontEnd(config)  # per frame: planes, edges, corners, objects (camera frame)
keys = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")  # never collide with yours
landmarks = PlaneLandmarks(keys)
smoother = RecoveringISAM2()  # iSAM2 that survives indeterminate updates
rng = np.random.default_rng(0)
odometry_noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
for i, T_world_cam in enumerate(truth.T_world_cam[:12]):
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()  # your own factors
    if i == 0:
        graph.add(gtsam.PriorFactorPose3(keys.pose(0), gtsam.Pose3(T_world_cam), odometry_noise))
    else:
        T_prev_cur = np.linalg.inv(truth.T_world_cam[i - 1]) @ T_world_cam  # your odometry
        graph.add(
            gtsam.BetweenFactorPose3(
                keys.pose(i - 1), keys.pose(i), gtsam.Pose3(T_prev_cur), odometry_noise
            )
        )
    T_pred = T_world_cam  # your prediction of this pose (T_world_cam, 4x4)
    values.insert(keys.pose(i), gtsam.Pose3(T_pred))
    depth_m = render_frame(scene, T_world_cam, config.camera, rng).depth_m
    observation = front_end.process(depth_m, timestamp=float(i))
    plane_ids, corner_ids = landmarks.associate(observation, T_pred)
    added = landmarks.add_observations(
        gtsam.NonlinearFactorGraph(), gtsam.Values(), keys.pose(i), T_pred, observation,
        plane_ids, corner_ids,
    )  # fmt: skip
    smoother.update(graph, values, added, landmarks)  # landmarks take the new estimate
print(f"{len(landmarks.plane_ids)} plane and {len(landmarks.corner_ids)} corner landmarks")
for obj in landmarks.objects():  # objects on the optimised landmarks
    print(obj.cls, " x ".join(f"{s:.3f}" for s in obj.size_m), "m, planes", list(obj.planes))
