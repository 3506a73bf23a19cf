"""The closed-form plane pose's correspondences, frame by frame, against the truth
(docs/experiments.md, "Three planes and a tilted wall").

    python docs/scripts/plane_pairs.py SEQUENCE OUT [FRAMES] [INDICES]

Runs `planeslam run` on the TUM-layout folder SEQUENCE (with groundtruth.txt, one pose
per frame, as `planeslam synth` writes) into OUT, the first FRAMES frames (default all).
For every frame (or only the comma-separated INDICES) the plane path solves, it prints
the pose's error and the prediction's against the true pose [cm, deg], the residuals
of each plane pair (angle [deg], offset [mm]) and each frame plane moved into the world
by the true pose beside the map plane it was paired with: the angle between their
normals [deg] and the difference of their offsets [cm].
"""

from __future__ import annotations

import math
import sys

from _run_probe import count_frames, watched_run

import planeslam.tracking.plane_path as plane_path
from planeslam.app.runner import run_sequence
from planeslam.core.geometry import angle_between, transform_plane
from planeslam.tracking.hypotheses import pose_difference

run = watched_run(sys.argv)
current = count_frames()


def _showing_register(register):
    def wrapper(self, frame, view, T_pred):
        solved = register(self, frame, view, T_pred)
        i = current["frame"]
        if solved is None or not run.shown(i):
            return solved
        reg = solved.registration
        metres, degrees = pose_difference(run.truth[i], solved.T)
        pred_m, pred_deg = pose_difference(run.truth[i], T_pred)
        print(
            f"frame {i}: pose off {100 * metres:.2f} cm {degrees:.2f} deg, prediction off "
            f"{100 * pred_m:.2f} cm {pred_deg:.2f} deg"
        )
        for k, (f, m) in enumerate(solved.association.planes):
            n_world, d_world = transform_plane(run.truth[i], frame.normals[f], frame.d[f])
            tilt = math.degrees(angle_between(n_world, view.normals[m]))
            print(
                f"  frame plane {f} -> map plane {m}: residual "
                f"{math.degrees(reg.plane_angle_residual_rad[k]):.2f} deg "
                f"{1000 * reg.plane_offset_residual_m[k]:.1f} mm; by the true pose "
                f"{tilt:.2f} deg and {100 * (d_world - view.d[m]):.2f} cm off the map plane"
            )
        return solved

    return wrapper


plane_path.PlanePath.register = _showing_register(plane_path.PlanePath.register)
run_sequence(run.sequence, run.out, max_frames=run.frames)
