"""Your own GTSAM graph and odometry, with planeslam's plane and corner landmarks in it.

The caller keeps its own poses x0, x1, ... and its own odometry (here the true motion
perturbed by seeded noise) in its own graph; planeslam adds plane (P) and corner (C)
landmarks from each depth image. The frames come from planeslam's synthetic scene (a
robot walking a circle around a box in a small room, Kinect-like noise) or, with
`--dataset`, from a TUM-layout folder with ground truth (real Kinect depth). At the end:
the trajectory error with and without the landmarks, the optimised graph's error against
its degrees of freedom, and the objects (class, size) found on the optimised landmarks.

    python examples/own_graph.py [--frames 12] [--odometry-noise 0.5] [--seed 0]
    python examples/own_graph.py --dataset ../shared/data/tum_fr1_desk_9f --odometry-noise 1
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import gtsam
import numpy as np

from planeslam import (
    FrontEnd,
    LandmarkKeys,
    PlaneLandmarks,
    PlaneSlamConfig,
    RecoveringISAM2,
    TumDataset,
    load_config,
)
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle

NOISE_UNIT = np.r_[[0.01] * 3, [0.02] * 3]
"""Odometry noise per step at `--odometry-noise 1`: rotation [rad] x 3, translation [m] x 3
(gtsam's Pose3 tangent order)."""


def frames(
    dataset: str | None, count: int, config_name: str
) -> tuple[PlaneSlamConfig, np.ndarray, Iterator[np.ndarray]]:
    """(config, T_world_cam truth (N, 4, 4), depth images (H, W) [m] one by one)."""
    if dataset is None:
        scene, trajectory = box_room_circle(frames=24)
        config = load_config("synthetic")  # the renderer's camera
        T_true = trajectory.T_world_cam[:count]
        rng = np.random.default_rng(1)
        depths = (render_frame(scene, T, config.camera, rng).depth_m for T in T_true)
        return config, T_true, depths
    config = load_config(config_name)
    sequence = TumDataset(Path(dataset), config.camera, config.dataset)
    if sequence.groundtruth is None:
        raise SystemExit(f"{dataset}: no groundtruth.txt, expected a TUM folder with one")
    count = min(count, len(sequence))
    T_true = np.array([sequence.groundtruth_pose(t) for t in sequence.timestamps[:count]])
    return config, T_true, (sequence[i].depth_m for i in range(count))


def graph_error(smoother: RecoveringISAM2) -> tuple[float, int]:
    """(chi^2: the sum of squared whitened errors before any robust loss, degrees of
    freedom: measurement dimensions minus variable dimensions) of the optimised graph."""
    graph, estimate = smoother.isam.getFactorsUnsafe(), smoother.estimate
    chi2, rows = 0.0, 0
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor is not None:
            whitened = np.asarray(factor.whitenedError(estimate))
            chi2 += float(whitened @ whitened)
            rows += whitened.size
    return chi2, rows - estimate.dim()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="frames (of 24 on the circle)")
    parser.add_argument("--dataset", help="TUM-layout folder with groundtruth.txt")
    parser.add_argument("--config", default="tum_fr1", help="preset of --dataset's camera")
    parser.add_argument(
        "--odometry-noise",
        type=float,
        default=0.5,
        help="odometry noise per step in units of 0.01 rad and 0.02 m (> 0)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the odometry noise")
    args = parser.parse_args(argv)
    if not args.odometry_noise > 0:
        parser.error(f"--odometry-noise {args.odometry_noise}: expected a number > 0")
    config, T_true, depths = frames(args.dataset, args.frames, args.config)
    sigmas = args.odometry_noise * NOISE_UNIT
    rng = np.random.default_rng(args.seed)

    # The caller's odometry: the true motion, perturbed.
    odometry = [
        np.linalg.inv(a) @ b @ gtsam.Pose3.Expmap(rng.normal(0.0, sigmas)).matrix()
        for a, b in zip(T_true[:-1], T_true[1:], strict=True)
    ]
    odometry_cov = np.diag(sigmas**2)
    odometry_noise = gtsam.noiseModel.Gaussian.Covariance(odometry_cov)

    front_end = FrontEnd(config)
    keys = LandmarkKeys(pose_char="x", plane_char="P", corner_char="C")
    landmarks = PlaneLandmarks(keys)
    smoother = RecoveringISAM2(extra_updates=1)  # iSAM2 that survives indeterminate updates
    T_pred, pose_cov = T_true[0], np.diag([1e-8] * 6)
    for i, depth_m in enumerate(depths):  # your depth camera: (H, W) metres, 0 = invalid
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

        observation = front_end.process(depth_m, timestamp=float(i))
        plane_ids, corner_ids = landmarks.associate(observation, T_pred, pose_cov)
        ours, our_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        added = landmarks.add_observations(
            ours, our_values, keys.pose(i), T_pred, observation, plane_ids, corner_ids
        )
        smoother.update(graph, values, added, landmarks)

    count = len(T_true)
    T_odom = [T_true[0]]
    for T_prev_cur in odometry:
        T_odom.append(T_odom[-1] @ T_prev_cur)
    T_opt = [smoother.estimate.atPose3(keys.pose(i)).matrix() for i in range(count)]

    def ate(poses: list[np.ndarray]) -> float:
        """Translation RMSE [m] against the truth (both start at the same pose)."""
        error = np.array(poses)[:, :3, 3] - T_true[:, :3, 3]
        return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))

    print(
        f"{count} frames: translation RMSE, odometry alone {ate(T_odom):.4f} m, "
        f"with planeslam landmarks {ate(T_opt):.4f} m"
    )
    chi2, dof = graph_error(smoother)
    print(f"graph error chi2 {chi2:.1f} over {dof} degrees of freedom ({chi2 / dof:.2f})")
    print(
        f"{len(landmarks.plane_ids)} plane and {len(landmarks.corner_ids)} corner landmarks, "
        f"{smoother.failures} indeterminate updates recovered"
    )
    for obj in landmarks.objects():
        size = " x ".join(f"{s:.3f}" for s in obj.size_m)
        print(f"object {obj.cls}: {size} m, planes {list(obj.planes)}")


if __name__ == "__main__":
    main()
