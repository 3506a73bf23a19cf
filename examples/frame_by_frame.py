"""planeslam's whole SLAM, fed one depth image at a time (a live camera, a simulator, a
reader of your own): here the frames are rendered from the synthetic box-in-a-room scene.

Every frame returns its pose and how tracking found it; `finish` runs the final
optimisation and rebuilds the map, whose objects (class, size) are printed with the
trajectory's error.

    python examples/frame_by_frame.py [--frames 24] [--backend isam2|merge]
"""

from __future__ import annotations

import argparse

import numpy as np

from planeslam import SLAM, Trajectory, load_config
from planeslam.sim.render import render_frame
from planeslam.sim.scenes import box_room_circle


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24, help="frames on the circle")
    parser.add_argument("--backend", choices=("isam2", "merge"), default="isam2")
    args = parser.parse_args(argv)
    scene, truth = box_room_circle(frames=args.frames)
    config = load_config("synthetic")
    rng = np.random.default_rng(0)

    # run.start_pose 'groundtruth' (the default): start at the first true pose, so the
    # estimate and the truth share the world frame; without one, SLAM starts at identity.
    with SLAM(config, backend=args.backend, T_world_first=truth.T_world_cam[0]) as slam:
        for i, T_world_cam in enumerate(truth.T_world_cam):
            frame = render_frame(scene, T_world_cam, config.camera, rng)  # your camera here
            result = slam.process(frame.depth_m, float(i), frame.rgb)
            planes = len(result.observation.segmentation.planes)
            print(
                f"frame {i:2d}: {result.path.value:<12} {planes} planes"
                + (", keyframe" if result.keyframe else "")
            )
        slam.finish()  # final optimisation; the backend stops

    estimate: Trajectory = slam.trajectory()
    error = estimate.T_world_cam[:, :3, 3] - truth.T_world_cam[:, :3, 3]
    rmse = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
    print(f"{len(estimate.timestamps)} poses, translation RMSE {rmse:.4f} m")
    for obj in slam.map.objects:
        print(f"object {obj.cls}: {' x '.join(f'{s:.3f}' for s in obj.size_m)} m")


if __name__ == "__main__":
    main()
