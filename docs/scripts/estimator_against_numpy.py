"""The compiled robust pose estimate against the numpy code it replaced (docs/speed.md,
"The run's end").

    python docs/scripts/estimator_against_numpy.py [COMMIT] [PROBLEMS]

Loads `planeslam/tracking/estimator.py` as it was at COMMIT (default eda4028, the last
numpy one; read with `git show`) beside this checkout's `estimate_pose`, and solves
PROBLEMS (default 300) seeded random problems with both: 0-7 planes seen from a random
pose with noise (sometimes one offset 30 cm off), 0-4 corners in two point sets, and on
every second problem 0-3 line ends drawn at random (inconsistent on purpose), from a
start 5 cm off, with 0 or 10 iterations. Prints the largest pose difference (without and
with line ends), the largest relative information difference, how many inlier flags
differ, and each one's mean time per call.
"""

from __future__ import annotations

import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

from planeslam.core.geometry import pose_from_quat
from planeslam.tracking import estimator as new


def numpy_estimator(commit: str) -> types.ModuleType:
    """The estimator module's source at `commit`, as a module."""
    root = Path(__file__).resolve().parents[2]
    source = subprocess.run(
        ["git", "show", f"{commit}:planeslam/tracking/estimator.py"],
        cwd=root,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    module = types.ModuleType("estimator_at_" + commit)
    sys.modules[module.__name__] = module  # dataclasses look their module up
    exec(compile(source, f"{commit}:estimator.py", "exec"), module.__dict__)
    return module


def problem(rng: np.random.Generator, lines: bool):
    """(T_start, planes, points, lines) as plain arrays."""
    T_true = pose_from_quat(rng.normal(0, 1, 3), rng.normal(0, 1, 4))
    R, t = T_true[:3, :3], T_true[:3, 3]
    N, M, L = rng.integers(0, 8), rng.integers(0, 5), rng.integers(0, 4) if lines else 0
    n_w = rng.normal(size=(N, 3))
    n_w /= np.linalg.norm(n_w, axis=1, keepdims=True)
    d_w = rng.uniform(0.5, 3, N)
    n_c = n_w @ R + rng.normal(0, 0.01, (N, 3))
    n_c /= np.linalg.norm(n_c, axis=1, keepdims=True)
    d_c = d_w + n_w @ t + rng.normal(0, 0.01, N)
    if N > 2:
        d_c[0] += rng.choice([0.0, 0.3])
    A = rng.normal(0, 1e-2, (N, 3, 3))
    cov = A @ np.swapaxes(A, 1, 2) + 1e-5 * np.eye(3)
    p_w = rng.uniform(-2, 2, (M, 3))
    p_c = (p_w - t) @ R + rng.normal(0, 0.01, (M, 3))
    c = np.broadcast_to(1e-4 * np.eye(3), (M, 3, 3))
    T_start = T_true.copy()
    T_start[:3, 3] += rng.normal(0, 0.05, 3)
    ends = [rng.normal(size=(L, 3)) for _ in range(3)]
    return T_start, (n_c, d_c, n_w, d_w, cov), (p_c, p_w, c), ends


def solve(module: types.ModuleType, T_start, planes, points, ends, iterations: int):
    p_c, p_w, c = points
    sets = (
        [
            module.PointTerms(p_c, p_w, c, c, module.Primitive.CORNERS),
            module.PointTerms(p_c[:1], p_w[:1], c[:1], c[:1]),
        ]
        if len(p_c)
        else []
    )
    return module.estimate_pose(
        T_start,
        module.PlaneTerms(*planes) if len(planes[1]) else None,
        sets,
        module.LineTerms(*ends) if len(ends[0]) else None,
        module.EstimatorSettings(iterations=iterations),
    )


if __name__ == "__main__":
    old = numpy_estimator(sys.argv[1] if len(sys.argv) > 1 else "eda4028")
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 300
    rng = np.random.default_rng(0)
    new.estimate_pose(np.eye(4), None, [], None, new.EstimatorSettings())  # compile first
    pose = {False: 0.0, True: 0.0}  # without, with the random line ends
    info, flags, solved = 0.0, 0, 0
    seconds = {"numpy": 0.0, "compiled": 0.0}
    for k in range(count):
        T_start, planes, points, ends = problem(rng, lines=bool(k % 2))
        iterations = int(rng.choice([0, 10]))
        if len(planes[1]) + len(points[0]) + len(ends[0]) == 0:
            continue
        try:
            t0 = time.perf_counter()
            a = solve(old, T_start, planes, points, ends, iterations)
            t1 = time.perf_counter()
        except np.linalg.LinAlgError:
            continue
        b = solve(new, T_start, planes, points, ends, iterations)
        seconds["numpy"] += t1 - t0
        seconds["compiled"] += time.perf_counter() - t1
        solved += 1
        with_lines = bool(len(ends[0]))
        difference = float(np.abs(a.T_world_cam - b.T_world_cam).max())
        pose[with_lines] = max(pose[with_lines], difference)
        assert [str(kind) for kind in a.information] == [str(kind) for kind in b.information]
        for H_a, H_b in zip(a.information.values(), b.information.values(), strict=True):
            info = max(info, float(np.abs(H_a - H_b).max() / max(np.abs(H_a).max(), 1e-300)))
        pairs = [(a.plane_inliers, b.plane_inliers), (a.line_inliers, b.line_inliers)]
        pairs += list(zip(a.point_inliers, b.point_inliers, strict=True))
        flags += sum(int(not np.array_equal(x, y)) for x, y in pairs)
    print(
        f"{solved} problems: largest pose difference {pose[False]:.2e} without line ends, "
        f"{pose[True]:.2e} with the random ones; information {info:.2e} "
        f"(relative), inlier flags differing {flags}; per call numpy "
        f"{1e3 * seconds['numpy'] / solved:.3f} ms, compiled "
        f"{1e3 * seconds['compiled'] / solved:.3f} ms"
    )
