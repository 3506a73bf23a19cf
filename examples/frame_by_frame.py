"""planeslam's whole SLAM, fed one depth image at a time (a live camera, a simulator, a
reader of your own): here the frames are rendered from the synthetic box-in-a-room scene,
or read from a TUM-layout folder with ground truth (`--dataset`, real Kinect depth).

Every frame returns its pose and how tracking found it; `finish` runs the final
optimisation and rebuilds the map, whose objects (class, size) are printed with the
trajectory's error.

    python examples/frame_by_frame.py [--frames 24] [--backend isam2|merge]
    python examples/frame_by_frame.py --dataset ../shared/data/tum_fr1_xyz_10f
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from planeslam import SLAM, Frame, PlaneSlamConfig, Trajectory, TumDataset, load_config
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle


def frames(
    dataset: str | None, count: int, config_name: str
) -> tuple[PlaneSlamConfig, np.ndarray, Iterator[Frame]]:
    """(config, T_world_cam truth (N, 4, 4), frames one by one: depth [m], rgb, time [s])."""
    if dataset is None:
        scene, truth = box_room_circle(frames=count)
        config = load_config("synthetic")
        rng = np.random.default_rng(0)
        rendered = (render_frame(scene, T, config.camera, rng) for T in truth.T_world_cam)
        return (
            config,
            truth.T_world_cam,
            (Frame(i, float(i), f.rgb, f.depth_m) for i, f in enumerate(rendered)),
        )
    config = load_config(config_name)
    sequence = TumDataset(Path(dataset), config.camera, config.dataset)
    if sequence.groundtruth is None:
        raise SystemExit(f"{dataset}: no groundtruth.txt, expected a TUM folder with one")
    count = min(count, len(sequence))
    T_true = np.array([sequence.groundtruth_pose(t) for t in sequence.timestamps[:count]])
    return config, T_true, (sequence[i] for i in range(count))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24, help="frames (on the circle)")
    parser.add_argument("--backend", choices=("isam2", "merge"), default="isam2")
    parser.add_argument("--dataset", help="TUM-layout folder with groundtruth.txt")
    parser.add_argument("--config", default="tum_fr1", help="preset of --dataset's camera")
    args = parser.parse_args(argv)
    config, T_true, source = frames(args.dataset, args.frames, args.config)

    # run.start_pose 'groundtruth' (the default): start at the first true pose, so the
    # estimate and the truth share the world frame; without one, SLAM starts at identity.
    with SLAM(config, backend=args.backend, T_world_first=T_true[0]) as slam:
        for i, frame in enumerate(source):  # your camera here
            result = slam.process(frame.depth_m, frame.timestamp, frame.rgb)
            planes = len(result.observation.segmentation.planes)
            print(
                f"frame {i:2d}: {result.path.value:<12} {planes} planes"
                + (", keyframe" if result.keyframe else "")
            )
        slam.finish()  # final optimisation; the backend stops

    estimate: Trajectory = slam.trajectory()
    error = estimate.T_world_cam[:, :3, 3] - T_true[:, :3, 3]
    rmse = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
    print(f"{len(estimate.timestamps)} poses, translation RMSE {rmse:.4f} m")
    for obj in slam.map.objects:
        print(f"object {obj.cls}: {' x '.join(f'{s:.3f}' for s in obj.size_m)} m")


if __name__ == "__main__":
    main()
