"""Linearisation cost of each factor: `python -m planeslam.factors._bench`.

Two figures per factor, medians over repeated batches in one run: one
`factor.linearize(values)` call from Python, and the per-factor share of
`NonlinearFactorGraph.linearize` on a graph of 1000 copies (the C++ loop an
optimiser runs; for a CustomFactor it re-enters Python once per factor).
"""

from __future__ import annotations

import statistics
import time

import gtsam
import numpy as np

from .config import LandmarkKeys
from .corner_observation import corner_factor
from .plane_observation import plane_factor, robust_plane_factor
from .plane_structure import orthogonal_planes_factor, parallel_planes_factor
from .point_on_plane import point_on_plane_factor


def _median_seconds(fn, calls: int, repeats: int) -> float:
    batches = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        batches.append((time.perf_counter() - start) / calls)
    return statistics.median(batches)


def main() -> None:
    rng = np.random.default_rng(0)
    keys = LandmarkKeys()
    x, p, q, c = keys.pose(0), keys.plane(0), keys.plane(1), keys.corner(0)
    T_world_cam = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    z_cam = gtsam.OrientedPlane3(0.0, 0.6, 0.8, 2.0)
    values = gtsam.Values()
    values.insert(x, T_world_cam)
    values.insert(p, z_cam.transform(T_world_cam.inverse()).retract(np.full(3, 0.05)))
    values.insert(q, gtsam.OrientedPlane3(0.8, -0.6, 0.0, 1.0))
    values.insert(c, rng.normal(size=3))
    cov = np.diag([1e-4, 1e-4, 4e-4])
    makers = {
        "OrientedPlane3Factor (built-in)": lambda: plane_factor(z_cam, cov, x, p),
        "robust_plane_factor (Huber)": lambda: robust_plane_factor(z_cam, cov, x, p),
        "corner_factor": lambda: corner_factor(np.array([0.1, 0.2, 2.0]), 1e-4 * np.eye(3), x, c),
        "point_on_plane_factor": lambda: point_on_plane_factor(p, c, 0.01),
        "orthogonal_planes_factor": lambda: orthogonal_planes_factor(p, q, 0.01),
        "parallel_planes_factor": lambda: parallel_planes_factor(p, q, 0.01),
    }
    print(f"{'factor':34s} {'linearize() us':>15s} {'graph share us':>15s}")
    for name, make in makers.items():
        factor = make()
        single = _median_seconds(lambda f=factor: f.linearize(values), calls=200, repeats=25)
        graph = gtsam.NonlinearFactorGraph()
        for _ in range(1000):
            graph.add(make())
        share = _median_seconds(lambda g=graph: g.linearize(values), calls=1, repeats=15) / 1000
        print(f"{name:34s} {single * 1e6:15.2f} {share * 1e6:15.2f}")


if __name__ == "__main__":
    main()
