"""Your own GTSAM graph and odometry, with planeslam's plane and corner landmarks in it.

A robot walks a circle around a box in a small room (planeslam's synthetic scene, depth
rendered with Kinect-like noise). It keeps its own poses x0, x1, ... and its own drifting
odometry in its own graph; planeslam adds plane (P) and corner (C) landmarks from each
depth image. At the end: the trajectory error with and without the landmarks, and the
objects (class, size) found on the optimised landmarks.

    python examples/own_graph.py [--frames 12]
"""

from __future__ import annotations

import argparse

import gtsam
import numpy as np

from planeslam import FrontEnd, LandmarkKeys, PlaneLandmarks, RecoveringISAM2, load_config
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle

ODOMETRY_SIGMAS = np.r_[[0.005] * 3, [0.01] * 3]  # per step: rotation [rad], translation [m]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="frames (of 24 on the circle)")
    frames = parser.parse_args(argv).frames
    scene, trajectory = box_room_circle(frames=24)
    T_true = trajectory.T_world_cam[:frames]
    config = load_config("synthetic")  # the renderer's camera
    rng = np.random.default_rng(0)

    # The caller's odometry: the true motion, perturbed.
    odometry = [
        np.linalg.inv(a) @ b @ gtsam.Pose3.Expmap(rng.normal(0.0, ODOMETRY_SIGMAS)).matrix()
        for a, b in zip(T_true[:-1], T_true[1:], strict=True)
    ]
    odometry_cov = np.diag(ODOMETRY_SIGMAS**2)
    odometry_noise = gtsam.noiseModel.Gaussian.Covariance(odometry_cov)

    front_end = FrontEnd(config)
    keys = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")
    landmarks = PlaneLandmarks(keys)
    smoother = RecoveringISAM2(extra_updates=1)  # iSAM2 that survives indeterminate updates
    T_pred, pose_cov = T_true[0], np.diag([1e-8] * 6)
    for i, T in enumerate(T_true):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()  # the caller's own
        if i == 0:
            graph.add(
                gtsam.PriorFactorPose3(
                    keys.pose(0), gtsam.Pose3(T_pred), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)
                )
            )
        else:
            step = gtsam.Pose3(odometry[i - 1])
            graph.add(
                gtsam.BetweenFactorPose3(keys.pose(i - 1), keys.pose(i), step, odometry_noise)
            )
            # predicted pose and its covariance: last estimate moved by the odometry
            previous = smoother.estimate.atPose3(keys.pose(i - 1))
            T_pred = previous.compose(step).matrix()
            adjoint = step.inverse().AdjointMap()
            prior = smoother.isam.marginalCovariance(keys.pose(i - 1))
            pose_cov = adjoint @ prior @ adjoint.T + odometry_cov
        values.insert(keys.pose(i), gtsam.Pose3(T_pred))

        depth_m = render_frame(scene, T, config.camera, rng).depth_m  # your depth camera
        observation = front_end.process(depth_m, timestamp=float(i))
        plane_ids, corner_ids = landmarks.associate(observation, T_pred, pose_cov)
        ours, our_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        added = landmarks.add_observations(
            ours, our_values, keys.pose(i), T_pred, observation, plane_ids, corner_ids
        )
        smoother.update(graph, values, added, landmarks)

    T_odom = [T_true[0]]
    for T_prev_cur in odometry:
        T_odom.append(T_odom[-1] @ T_prev_cur)
    T_opt = [smoother.estimate.atPose3(keys.pose(i)).matrix() for i in range(frames)]

    def ate(poses: list[np.ndarray]) -> float:
        """Translation RMSE [m] against the truth (both start at the same pose)."""
        error = np.array(poses)[:, :3, 3] - T_true[:, :3, 3]
        return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))

    print(
        f"{frames} frames: translation RMSE, odometry alone {ate(T_odom):.4f} m, "
        f"with planeslam landmarks {ate(T_opt):.4f} m"
    )
    print(
        f"{len(landmarks.plane_ids)} plane and {len(landmarks.corner_ids)} corner landmarks, "
        f"{smoother.failures} indeterminate updates recovered"
    )
    for obj in landmarks.objects():
        size = " x ".join(f"{s:.3f}" for s in obj.size_m)
        print(f"object {obj.cls}: {size} m, planes {list(obj.planes)}")


if __name__ == "__main__":
    main()
