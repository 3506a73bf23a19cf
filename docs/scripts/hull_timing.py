"""The 2-D convex hulls of a run: OpenCV's (`convex_hull_2d`) against scipy's Qhull, on
the very point sets a run asks for (docs/speed.md, "The map merge's hulls").

    python docs/scripts/hull_timing.py [DATASET] [FRAMES] [OUT]

Runs `planeslam run` on the first FRAMES frames (default 100) of DATASET (default
../shared/data/7scenes_redkitchen_1000f) into OUT, keeping every point set passed to
`convex_hull_2d` (the map merge's outlines and plane association's overlap), then times
both hulls over those sets, alternated for five rounds (`time.thread_time`, medians), and
counts the sets whose hull vertices differ (as sets; the ring may start elsewhere).
"""

from __future__ import annotations

import sys
import time

import numpy as np
from _run_probe import HULL_CALLERS, SEVEN_SCENES
from scipy.spatial import ConvexHull, QhullError

from planeslam.app.runner import run_sequence
from planeslam.core.geometry import convex_hull_2d


def qhull_2d(points_uv: np.ndarray) -> np.ndarray:
    """The earlier `convex_hull_2d`: scipy's Qhull, (0, 2) where it finds no area."""
    if len(points_uv) < 3:
        return np.zeros((0, 2))
    try:
        return points_uv[ConvexHull(points_uv).vertices]
    except QhullError:
        return np.zeros((0, 2))


dataset = sys.argv[1] if len(sys.argv) > 1 else SEVEN_SCENES
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 100
out = sys.argv[3] if len(sys.argv) > 3 else "out/hull_timing"
asked: list[np.ndarray] = []


def keeping(points_uv: np.ndarray) -> np.ndarray:
    asked.append(np.array(points_uv, dtype=np.float64))
    return convex_hull_2d(points_uv)


for caller in HULL_CALLERS:
    caller.convex_hull_2d = keeping
run_sequence(dataset, out, max_frames=frames)

spent: dict[str, list[float]] = {"qhull": [], "opencv": []}
for _ in range(5):
    for name, hull in (("qhull", qhull_2d), ("opencv", convex_hull_2d)):
        start = time.thread_time()
        for points in asked:
            hull(points)
        spent[name].append((time.thread_time() - start) / len(asked) * 1e6)
differ = sum(
    {tuple(p) for p in qhull_2d(points)} != {tuple(p) for p in convex_hull_2d(points)}
    for points in asked
)
sizes = [len(points) for points in asked]
print(
    f"{len(asked)} hulls over {frames} frames, {np.median(sizes):.0f} points median "
    f"(max {max(sizes)}); us per hull, median of 5: Qhull {np.median(spent['qhull']):.1f}, "
    f"OpenCV {np.median(spent['opencv']):.1f}; vertex sets differ on {differ}"
)
