"""`planeslam mesh RUN_DIR`: a dense mesh of a finished run, its keyframes (or every frame)
fused with the run's final (optimised) poses into a TSDF; writes RUN_DIR/mesh.ply."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from planeslam.app.progress import progress_bar
from planeslam.app.run_folder import open_run
from planeslam.core.errors import EvaluationError
from planeslam.mapping.dense_mesh import PosedFrame, TsdfConfig, fuse_tsdf

MESH_PLY = "mesh.ply"


@dataclass(frozen=True)
class MeshResult:
    """What `mesh_run` fused and wrote."""

    path: Path
    frames: int
    """Frames fused."""
    vertices: int
    triangles: int
    seconds: float
    """Wall-clock time: reading, fusing, extracting and writing."""

    @property
    def bytes(self) -> int:
        return self.path.stat().st_size

    def text(self) -> str:
        return (
            f"mesh of {self.frames} frames: {self.vertices} vertices, {self.triangles} "
            f"triangles, {self.bytes / 1e6:.1f} MB in {self.seconds:.1f} s -> {self.path}"
        )


def mesh_run(
    run_dir: str | Path,
    config: TsdfConfig | None = None,
    all_frames: bool = False,
    dataset: str | Path | None = None,
    out: str | Path | None = None,
    progress: bool = False,
) -> MeshResult:
    """Fuse the run's keyframes (`all_frames`: every frame with a pose) into a TSDF with
    the final poses of trajectory.txt and write the mesh (default RUN_DIR/mesh.ply)."""
    start = time.perf_counter()
    run = open_run(run_dir, dataset)
    chosen = [f for f in run.frames if f.T_world_cam is not None and (all_frames or f.keyframe)]
    if not chosen:
        raise EvaluationError(
            f"{run.run_dir}: no {'frames' if all_frames else 'keyframes'} with a pose to fuse"
        )
    path = Path(out) if out is not None else run.run_dir / MESH_PLY
    with progress_bar(len(chosen), "TSDF", "frame", enabled=progress) as bar:
        posed = (
            PosedFrame(frame.rgb, frame.depth_m, f.T_world_cam)
            for f, frame in run.read(chosen)
            if f.T_world_cam is not None
        )
        mesh = fuse_tsdf(posed, run.camera, config, on_frame=bar.step)
    mesh.write_ply(path)
    return MeshResult(
        path=path,
        frames=mesh.frames,
        vertices=len(mesh.vertices),
        triangles=len(mesh.triangles),
        seconds=time.perf_counter() - start,
    )
