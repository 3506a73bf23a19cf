"""`planeslam bench frontend`: front-end speed on one core, both segmenters and
Open3D's `segment_plane` (the reference a user would otherwise reach for),
measured in the same run on the same frames held in memory (I/O excluded).

Without a dataset the default synthetic scene (box_room_circle, 640x480) is
rendered once into a cache folder. The process (all its threads) is pinned to
the first allowed core(s) for the measurement and restored afterwards.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.config import ConfigLayer, PlaneSlamConfig, open_configured, resolve_config
from planeslam.core.camera import PixelRays
from planeslam.core.errors import ConfigError, DatasetFormatError
from planeslam.frontend.cloud import organized_cloud
from planeslam.frontend.pipeline import FrontEnd

log = logging.getLogger(__name__)

SYNTH_SCENE = "box_room_circle"
"""Scene rendered when no dataset is given."""
O3D_DISTANCE_M = 0.02
"""Open3D reference: inlier distance threshold [m]."""
O3D_RANSAC_N = 3
"""Open3D reference: points per hypothesis."""
O3D_ITERATIONS = 1000
"""Open3D reference: RANSAC iterations per plane."""
O3D_MAX_PLANES = 8
"""Open3D reference: most planes extracted per frame."""
O3D_MIN_REMAINING = 0.05
"""Open3D reference: stop when fewer than this fraction of the points remain."""


@dataclass(frozen=True)
class MethodResult:
    """Timing of one plane-extraction method over the benchmark frames."""

    name: str
    frames: int
    """Frames timed."""
    fps: float
    """frames / wall-clock seconds for the whole method."""
    frame_ms_median: float
    """Median wall-clock time of one frame [ms]."""
    planes_median: float
    """Median number of planes found per frame."""
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Stage -> median ms (front-end methods only)."""

    def to_dict(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "frames": self.frames,
            "fps": round(self.fps, 3),
            "frame_ms_median": round(self.frame_ms_median, 3),
            "planes_median": self.planes_median,
        }
        if self.stage_ms:
            data["stage_ms"] = {k: round(v, 3) for k, v in self.stage_ms.items()}
        return data


@dataclass(frozen=True)
class BenchResult:
    """Figures of one `bench_frontend` run."""

    dataset: str
    """Dataset folder, or the synthetic scene's cache folder."""
    frames: int
    """Frames timed per front-end method (cycled over `distinct_frames` frames)."""
    distinct_frames: int
    width: int
    height: int
    core: str
    """Core(s) the process was pinned to, e.g. '0', or 'not pinned (...)'."""
    methods: dict[str, MethodResult]
    """'organized' (the default front end), 'msac', 'open3d_segment_plane'."""

    @property
    def default(self) -> MethodResult:
        return self.methods["organized"]

    def to_dict(self) -> dict[str, Any]:
        """The --json output: fps and stage_ms of the default front end at the top level."""
        return {
            "fps": round(self.default.fps, 3),
            "stage_ms": {k: round(v, 3) for k, v in self.default.stage_ms.items()},
            "frame_ms_median": round(self.default.frame_ms_median, 3),
            "frames": self.frames,
            "distinct_frames": self.distinct_frames,
            "width": self.width,
            "height": self.height,
            "core": self.core,
            "dataset": self.dataset,
            "methods": {k: m.to_dict() for k, m in self.methods.items()},
            "open3d_settings": {
                "distance_threshold_m": O3D_DISTANCE_M,
                "ransac_n": O3D_RANSAC_N,
                "num_iterations": O3D_ITERATIONS,
                "max_planes": O3D_MAX_PLANES,
                "stop_remaining_fraction": O3D_MIN_REMAINING,
            },
        }

    def to_text(self) -> str:
        """A readable table: one row per method, one column per stage."""
        stages = list(self.default.stage_ms)
        head = (
            f"planeslam bench frontend: {self.frames} frames ({self.distinct_frames} distinct) "
            f"{self.width}x{self.height} from {self.dataset}\n"
            f"pinned to core {self.core}; frames held in memory (I/O excluded), "
            "1 untimed warm-up frame per method\n"
        )
        cols = ["method", "fps", "ms/frame", "#planes", *stages]
        rows = [cols]
        for key, m in self.methods.items():
            label = "organized (default)" if key == "organized" else key
            if key == "open3d_segment_plane":
                label += f" [{m.frames} fr]"
            rows.append(
                [
                    label,
                    f"{m.fps:.2f}" if m.fps < 10 else f"{m.fps:.1f}",
                    f"{m.frame_ms_median:.1f}",
                    f"{m.planes_median:g}",
                    *[f"{m.stage_ms[s]:.2f}" if s in m.stage_ms else "-" for s in stages],
                ]
            )
        lines = aligned_rows(rows)
        foot = (
            f"stage columns: median ms per frame. open3d_segment_plane: the valid depth points as "
            f"an Open3D PointCloud, segment_plane(distance_threshold={O3D_DISTANCE_M}, "
            f"ransac_n={O3D_RANSAC_N}, num_iterations={O3D_ITERATIONS}) repeated, inliers removed, "
            f"until <{O3D_MIN_REMAINING:.0%} of the points remain or as many planes as the default "
            f"front end found (at most {O3D_MAX_PLANES})."
        )
        return head + "\n".join(lines) + "\n" + foot


def aligned_rows(rows: Sequence[Sequence[str]]) -> list[str]:
    """Text table lines: the first column left-aligned, the others right-aligned, a rule
    under the first row (the header)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    return lines


_BLAS_SET = (
    "openblas_set_num_threads",
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
)
_BLAS_GET = (
    "openblas_get_num_threads",
    "scipy_openblas_get_num_threads64_",
    "scipy_openblas_get_num_threads",
    "openblas_get_num_threads64_",
)


def _thread_pool_setters() -> list[tuple[Any, Any]]:
    """(get, set) functions of the thread pools loaded in this process: every OpenBLAS copy
    (numpy, scipy and OpenCV each bundle one) and the OpenMP runtime, found in /proc/self/maps."""
    import ctypes

    maps = Path("/proc/self/maps")
    if not maps.is_file():
        return []
    names = {line.split()[-1] for line in maps.read_text().splitlines() if "/" in line}
    pools: list[tuple[Any, Any]] = []
    for name in sorted(names):
        base = Path(name).name
        if "openblas" in base:
            pairs = list(zip(_BLAS_GET, _BLAS_SET, strict=True))
        elif base.startswith(("libgomp", "libomp", "libiomp")):
            pairs = [("omp_get_max_threads", "omp_set_num_threads")]
        else:
            continue
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        for get, set_ in pairs:
            if hasattr(lib, get) and hasattr(lib, set_):
                pools.append((getattr(lib, get), getattr(lib, set_)))
                break
    return pools


@contextmanager
def pinned_to_cores(cores: int | None) -> Iterator[str]:
    """Pin every thread of this process to the first `cores` allowed cores and size the
    BLAS/OpenMP/OpenCV thread pools to match, restoring all on exit. Yields a
    description ('0', '0,1' or 'not pinned').

    Without resizing the pools, OpenBLAS worker threads busy-wait on the same core as
    the main thread and make numpy ~10x slower: that would measure the pinning, not
    the code."""
    if not cores or not hasattr(os, "sched_setaffinity"):
        yield "not pinned"
        return
    import cv2

    allowed = sorted(os.sched_getaffinity(0))
    chosen = set(allowed[: max(1, int(cores))])
    pools = _thread_pool_setters()
    saved_pools = [(set_, int(get())) for get, set_ in pools]
    for _, set_ in pools:
        set_(len(chosen))
    saved_cv = cv2.getNumThreads()
    cv2.setNumThreads(len(chosen))
    # Threads made before pinning (BLAS, OpenMP pools) keep their own mask: pin them all.
    task_dir = Path("/proc/self/task")
    tids = [int(p.name) for p in task_dir.iterdir()] if task_dir.is_dir() else [0]
    saved: dict[int, set[int]] = {}
    for tid in tids:
        try:
            saved[tid] = os.sched_getaffinity(tid)
            os.sched_setaffinity(tid, chosen)
        except OSError:
            continue
    try:
        yield ",".join(str(c) for c in sorted(chosen))
    finally:
        for tid, mask in saved.items():
            try:
                os.sched_setaffinity(tid, mask)
            except OSError:
                continue
        cv2.setNumThreads(saved_cv)
        for set_, n in saved_pools:
            set_(n)


def default_cache_dir() -> Path:
    """Where the default synthetic scene is rendered: $XDG_CACHE_HOME/planeslam/bench."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "planeslam" / "bench"


def synthetic_dataset(cache_dir: Path | None = None) -> Path:
    """Render SYNTH_SCENE (seed 0, default camera) once into the cache -> its folder."""
    from planeslam.sim.sequence import synthesize

    folder = Path(cache_dir or default_cache_dir()) / SYNTH_SCENE
    if not (folder / "truth.json").is_file():
        log.info("rendering %s into %s (once)", SYNTH_SCENE, folder)
        # Rendered beside the folder and renamed into place, so processes that render it
        # at once (test workers, bench jobs) never read a half-written scene.
        partial = folder.with_name(f".{SYNTH_SCENE}.{os.getpid()}.partial")
        synthesize(SYNTH_SCENE, partial, seed=0)
        if folder.is_dir() and not (folder / "truth.json").is_file():
            shutil.rmtree(folder)  # a scene left half-written by an interrupted render
        try:
            partial.rename(folder)
        except OSError:  # another process renamed its copy into place first
            shutil.rmtree(partial, ignore_errors=True)
            if not (folder / "truth.json").is_file():
                raise
    return folder


def _time_front_end(
    config: PlaneSlamConfig, depths: Sequence[np.ndarray], stamps: Sequence[float], progress: bool
) -> tuple[MethodResult, list[int]]:
    """Run FrontEnd over the frames (one untimed warm-up first) -> timing, planes per frame."""
    from planeslam.frontend.pipeline import STAGES

    front_end = FrontEnd(config, seed=0)
    front_end.process(depths[0], stamps[0])
    frame_ms: list[float] = []
    stage_ms: dict[str, list[float]] = {s: [] for s in STAGES}
    planes: list[int] = []
    indices: Any = range(len(depths))
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc=config.segmentation.method, unit="frame", leave=False)
    start = time.perf_counter()
    for i in indices:
        t0 = time.perf_counter()
        obs = front_end.process(depths[i], stamps[i])
        frame_ms.append((time.perf_counter() - t0) * 1e3)
        for s in STAGES:
            stage_ms[s].append(float(obs.stage_ms.get(s, np.nan)))
        planes.append(len(obs.segmentation.planes))
    wall = time.perf_counter() - start
    result = MethodResult(
        name=config.segmentation.method,
        frames=len(depths),
        fps=len(depths) / wall,
        frame_ms_median=float(np.median(frame_ms)),
        planes_median=float(np.median(planes)),
        stage_ms={s: float(np.median(v)) for s, v in stage_ms.items() if np.isfinite(v).all()},
    )
    missing = [s for s in STAGES if s not in result.stage_ms]
    if missing:
        log.warning("front end reported no time for stage(s) %s", ", ".join(missing))
    return result, planes


def open3d_planes(depth_m: np.ndarray, rays: PixelRays, max_planes: int, max_depth_m: float) -> int:
    """The obvious Open3D way: valid depth points -> PointCloud -> segment_plane, remove
    inliers, repeat. (H, W) depth [m] -> number of planes extracted."""
    import open3d as o3d

    cloud = organized_cloud(depth_m, rays, max_depth_m)
    points = cloud[cloud[..., 2] > 0].astype(np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    stop = O3D_MIN_REMAINING * len(points)
    found = 0
    while found < max_planes and len(pcd.points) >= max(stop, O3D_RANSAC_N):
        _, inliers = pcd.segment_plane(O3D_DISTANCE_M, O3D_RANSAC_N, O3D_ITERATIONS)
        if len(inliers) < O3D_RANSAC_N:
            break
        found += 1
        pcd = pcd.select_by_index(inliers, invert=True)
    return found


def _time_open3d(
    config: PlaneSlamConfig,
    depths: Sequence[np.ndarray],
    planes_default: Sequence[int],
    frames: int,
) -> MethodResult:
    import open3d as o3d

    o3d.utility.random.seed(0)
    rays = PixelRays.for_camera(config.camera)
    n = max(1, min(frames, len(depths)))
    pick = np.linspace(0, len(depths) - 1, n).round().astype(int)
    frame_ms: list[float] = []
    planes: list[int] = []
    start = time.perf_counter()
    for i in pick:
        cap = int(np.clip(planes_default[i], 1, O3D_MAX_PLANES))
        t0 = time.perf_counter()
        planes.append(open3d_planes(depths[i], rays, cap, config.segmentation.max_depth_m))
        frame_ms.append((time.perf_counter() - t0) * 1e3)
    wall = time.perf_counter() - start
    return MethodResult(
        name="open3d_segment_plane",
        frames=n,
        fps=n / wall,
        frame_ms_median=float(np.median(frame_ms)),
        planes_median=float(np.median(planes)),
    )


def bench_frontend(
    dataset_dir: str | Path | None = None,
    frames: int = 30,
    config: str | Path | None = None,
    camera: str | ConfigLayer | None = None,
    cores: int | None = 1,
    progress: bool = False,
    reference_frames: int = 3,
    cache_dir: str | Path | None = None,
    overrides: Sequence[str | ConfigLayer] = (),
) -> BenchResult:
    """Time the front end per stage with both segmenters and Open3D's segment_plane.

    dataset_dir: TUM-layout folder or ROS bag; None renders SYNTH_SCENE once into `cache_dir`
    (default `default_cache_dir()`). `frames` frames evenly spread over the
    sequence are loaded into memory first (cycled when the sequence is shorter).
    `cores` pins the process to that many of its allowed cores (None: no pinning).
    The Open3D reference runs on `reference_frames` of them (it takes seconds
    per frame at 640x480). Times are wall-clock; fps = frames / seconds.
    """
    if frames < 1:
        raise ConfigError(f"bench: --frames must be >= 1, got {frames}")
    if reference_frames < 0:
        raise ConfigError(f"bench: reference_frames must be >= 0, got {reference_frames}")
    cache = None if cache_dir is None else Path(cache_dir)
    folder = Path(dataset_dir) if dataset_dir is not None else synthetic_dataset(cache)
    cfg = resolve_config(folder, config, camera, overrides)
    dataset, cfg = open_configured(folder, cfg)
    if len(dataset) == 0:
        raise DatasetFormatError(f"{folder}: no frames")
    distinct = min(frames, len(dataset))
    indices = np.linspace(0, len(dataset) - 1, distinct).round().astype(int)
    loaded = [dataset[int(i)] for i in indices]
    depths = [loaded[k % distinct].depth_m for k in range(frames)]
    stamps = [loaded[k % distinct].timestamp for k in range(frames)]
    with pinned_to_cores(cores) as core:
        log.info("bench on %d frames of %s, core %s", frames, folder, core)
        organized_cfg = dataclasses.replace(
            cfg, segmentation=dataclasses.replace(cfg.segmentation, method="organized")
        )
        msac_cfg = dataclasses.replace(
            cfg, segmentation=dataclasses.replace(cfg.segmentation, method="msac")
        )
        organized, planes_default = _time_front_end(organized_cfg, depths, stamps, progress)
        msac, _ = _time_front_end(msac_cfg, depths, stamps, progress)
        methods = {"organized": organized, "msac": msac}
        if reference_frames > 0:
            methods["open3d_segment_plane"] = _time_open3d(
                cfg, depths[:distinct], planes_default[:distinct], reference_frames
            )
    return BenchResult(
        dataset=str(folder),
        frames=frames,
        distinct_frames=distinct,
        width=int(depths[0].shape[1]),
        height=int(depths[0].shape[0]),
        core=core,
        methods=methods,
    )
