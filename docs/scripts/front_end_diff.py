"""How far two versions of the front end's results are apart (docs/speed.md, "Plane
records, region growing and eigen-solves compiled").

    python docs/scripts/front_end_diff.py dump OUT.npz [DATASET] [FRAMES]
    python docs/scripts/front_end_diff.py compare A.npz B.npz

`dump` runs `FrontEnd.process` on every 5th of the first FRAMES (default 300) frames of
DATASET (default the 7-Scenes clip beside the checkout) with the planeslam on the path
(`PYTHONPATH=<worktree>` for another commit) and keeps each frame's label image, its
planes' normals, d, centroids, scatters, covariances, areas, inlier counts and outlines,
and its edges' end points. `compare` prints, per quantity, the largest difference over
all frames (covariances and scatters relative to each matrix's largest entry) and the
frames whose plane or edge counts differ.
"""

from __future__ import annotations

import sys

import numpy as np
from _run_probe import timed_source

from planeslam.frontend.pipeline import FrontEnd

RELATIVE = ("covariance", "scatter")
"""Quantities compared relative to each matrix's largest entry."""


def dump(out: str, argv: list[str]) -> None:
    source = timed_source(["dump", *argv], 300)
    front_end = FrontEnd(source.config, seed=0)
    arrays: dict[str, np.ndarray] = {}
    for k in range(0, len(source.indices), 5):
        frame = source.dataset[source.indices[k]]
        observation = front_end.process(frame.depth_m, frame.timestamp)
        planes = observation.segmentation.planes
        fields = {
            "normal": [p.normal for p in planes],
            "d": [p.d for p in planes],
            "centroid": [p.centroid for p in planes],
            "scatter": [p.scatter for p in planes],
            "covariance": [p.covariance for p in planes],
            "area": [p.area_m2 for p in planes],
            "count": [p.num_points for p in planes],
        }
        for name, values in fields.items():
            arrays[f"{k}:{name}"] = np.array(values, dtype=np.float64)
        arrays[f"{k}:outline"] = np.concatenate([p.outline for p in planes] or [np.zeros((0, 3))])
        arrays[f"{k}:edges"] = np.array(
            [e.segment for e in observation.structure.edges], dtype=np.float64
        ).reshape(-1, 6)
        arrays[f"{k}:labels"] = observation.segmentation.labels
    np.savez_compressed(out, **arrays)


def compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    worst: dict[str, float] = {}
    differing = []
    for key in a.files:
        frame, name = key.split(":")
        x, y = a[key].astype(np.float64), b[key].astype(np.float64)
        if x.shape != y.shape:
            differing.append(f"frame {frame} {name} {x.shape} vs {y.shape}")
            continue
        if x.size == 0:
            continue
        if name in RELATIVE:
            scale = np.maximum(np.abs(x).max(axis=(1, 2), keepdims=True), 1e-300)
            diff = float(np.max(np.abs(x - y) / scale))
        elif name == "labels":
            diff = float(np.count_nonzero(x != y))
        else:
            diff = float(np.max(np.abs(x - y)))
        worst[name] = max(worst.get(name, 0.0), diff)
    for name, diff in worst.items():
        unit = " pixels differ (most in a frame)" if name == "labels" else ""
        print(f"{name:11s} {diff:.3g}{unit}")
    print("shapes differ:", "; ".join(differing) if differing else "none")


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "dump":
        dump(sys.argv[2], sys.argv[3:])
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        compare(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)
