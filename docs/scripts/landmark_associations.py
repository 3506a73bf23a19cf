"""Which plane landmarks of the backend hold more than one physical plane, and which
factors the final graph strains most (docs/experiments.md, "A free turn swept too").

    python docs/scripts/landmark_associations.py SEQUENCE OUT

Runs `planeslam run` on the TUM-layout folder SEQUENCE (with groundtruth.txt, one pose
per frame, as `planeslam synth` writes) into OUT with the backend in this process. For
every plane landmark it prints the plane each of its observations gives in the world
frame when placed at the keyframe's true pose (normal, offset [m]): observations of one
physical plane agree to the sensor's noise, so a spread over 5 cm or 5 deg (marked `<<`)
is a wrong association. Then each keyframe's position error [m, world] as tracking
guessed it and as the final graph has it, and the 15 factors with the largest error at
the final estimate.
"""

from __future__ import annotations

import sys
from collections import defaultdict

import gtsam
import numpy as np

import planeslam.backend.isam2 as isam2
from planeslam.app.runner import run_sequence
from planeslam.core.geometry import angle_between, transform_plane
from planeslam.io.trajectory import read_tum

sequence, out = sys.argv[1], sys.argv[2]
backends: list[isam2.Isam2Backend] = []
guesses: dict[int, np.ndarray] = {}
observations: dict[int, list[tuple[np.ndarray, float, int]]] = {}
"""keyframe -> (normal (3,), offset [m], landmark id) of its associated planes, camera frame."""


def _keeping(init):
    def wrapper(self, *args, **kwargs):
        init(self, *args, **kwargs)
        backends.append(self)

    return wrapper


def _recording(add_keyframe):
    def wrapper(self, index, timestamp, T_world_cam_guess, measurements, plane_ids, *a, **kw):
        guesses[int(index)] = np.array(T_world_cam_guess)
        observations[int(index)] = [
            (p.n_cam, p.d_cam, plane_ids[p.id]) for p in measurements.planes if p.id in plane_ids
        ]
        return add_keyframe(
            self, index, timestamp, T_world_cam_guess, measurements, plane_ids, *a, **kw
        )

    return wrapper


isam2.Isam2Backend.__init__ = _keeping(isam2.Isam2Backend.__init__)
isam2.Isam2Backend.add_keyframe = _recording(isam2.Isam2Backend.add_keyframe)
run_sequence(sequence, out, overrides=["backend.separate_process=false"])
backend = backends[-1]
truth = read_tum(f"{sequence}/groundtruth.txt").T_world_cam
estimate = backend.estimate

seen: dict[int, list[tuple[int, np.ndarray, float]]] = defaultdict(list)
for k, planes in observations.items():
    for n_cam, d_cam, landmark in planes:
        n_world, d_world = transform_plane(truth[k], n_cam, d_cam)
        seen[landmark].append((k, n_world, d_world))
print("plane landmarks: each observation's world plane at the keyframe's true pose")
for landmark, rows in sorted(seen.items()):
    first = rows[0][1]
    offsets = [d for _, _, d in rows]
    turn = max(np.degrees(angle_between(first, n)) for _, n, _ in rows)
    mixed = max(offsets) - min(offsets) > 0.05 or turn > 5.0
    print(
        f"p{landmark}: normal {np.round(first, 2)} offsets {np.round(offsets, 3).tolist()} "
        f"keyframes {[k for k, _, _ in rows]} widest turn {turn:.1f} deg" + (" <<" if mixed else "")
    )

print("keyframe: position error [m, world] guessed by tracking, final")
for k in sorted(guesses):
    final = estimate.atPose3(backend.keys.pose(k)).matrix()
    print(
        k,
        np.round(guesses[k][:3, 3] - truth[k][:3, 3], 3),
        np.round(final[:3, 3] - truth[k][:3, 3], 3),
    )

graph = backend._history.copy_graph()
errors = []
for i in range(graph.size()):
    factor = graph.at(i)
    keys = [gtsam.DefaultKeyFormatter(key) for key in factor.keys()]
    errors.append((factor.error(estimate), type(factor).__name__, keys))
print("largest factor errors at the final estimate")
for error, kind, keys in sorted(errors, key=lambda e: -e[0])[:15]:
    print(f"{error:9.3f} {kind} {keys}")
