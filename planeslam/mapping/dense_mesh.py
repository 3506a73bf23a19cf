"""A dense triangle mesh of a scene: RGB-D frames fused with their poses into a truncated
signed distance volume (Open3D's `VoxelBlockGrid`: hashed blocks of voxels, integrated on
all cores), then marching cubes.

This is what Open3D's reconstruction system and RTAB-Map export; the plane-object map
stays the compact representation. Open3D is imported on first use.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from planeslam.core.camera import CameraConfig
from planeslam.core.errors import ConfigError, MapError
from planeslam.core.geometry import invert_pose
from planeslam.core.safe_files import atomic_output

BLOCK_RESOLUTION = 16
"""Voxels along each edge of a hashed block."""
INITIAL_BLOCKS = 1000
"""Blocks the hash map is made for (it grows beyond)."""


@dataclass(frozen=True)
class TsdfConfig:
    """The volume a mesh is fused in."""

    voxel_m: float = 0.01
    """Voxel edge [m]."""
    sdf_trunc_voxels: float = 4.0
    """Truncation distance of the signed distance, in voxels."""
    depth_max_m: float = 3.0
    """Depth beyond this is left out [m] (noisy on structured-light sensors)."""
    min_weight: float = 3.0
    """A surface needs voxels integrated at least this many times (frames), or by every
    frame when fewer were fused."""

    def __post_init__(self) -> None:
        for name in ("voxel_m", "sdf_trunc_voxels", "depth_max_m", "min_weight"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ConfigError(f"mesh {name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class PosedFrame:
    """One RGB-D frame with its pose."""

    rgb: np.ndarray
    """(H, W, 3) uint8 RGB."""
    depth_m: np.ndarray
    """(H, W) float32 depth [m], 0 where invalid."""
    T_world_cam: np.ndarray
    """(4, 4) camera-to-world pose."""


@dataclass(frozen=True)
class DenseMesh:
    """A fused mesh, world frame."""

    vertices: np.ndarray
    """(V, 3) float64 [m]."""
    triangles: np.ndarray
    """(F, 3) int64 vertex indices."""
    colors: np.ndarray
    """(V, 3) float64 RGB in [0, 1]."""
    normals: np.ndarray
    """(V, 3) float64 unit vertex normals."""
    frames: int
    """Frames fused."""

    def to_open3d(self) -> Any:
        """As an `open3d.geometry.TriangleMesh`."""
        o3d = _open3d()
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.colors)
        mesh.vertex_normals = o3d.utility.Vector3dVector(self.normals)
        return mesh

    def write_ply(self, path: str | Path) -> Path:
        """Binary PLY with vertex colours and normals; returns the path."""
        o3d = _open3d()
        path = Path(path)
        with atomic_output(path, keep_suffix=True) as tmp:  # never through a link at `path`
            if not o3d.io.write_triangle_mesh(str(tmp), self.to_open3d(), write_ascii=False):
                raise MapError(f"{path}: Open3D could not write the mesh")
        return path


def fuse_tsdf(
    frames: Iterable[PosedFrame],
    camera: CameraConfig,
    config: TsdfConfig | None = None,
    on_frame: Callable[[], None] | None = None,
) -> DenseMesh:
    """Fuse `frames` (undistorted, depth registered to colour, intrinsics `camera`) into a
    TSDF and extract its mesh with vertex colours and normals. `on_frame` is called after
    each frame (a progress bar). MapError when nothing was fused or nothing was seen often
    enough (`min_weight`, at most the frames fused) to make a surface."""
    o3d = _open3d()
    o3c = o3d.core
    config = config or TsdfConfig()
    cpu = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=config.voxel_m,
        block_resolution=BLOCK_RESOLUTION,
        block_count=INITIAL_BLOCKS,
        device=cpu,
    )
    K = o3c.Tensor(camera.K, o3c.float64)
    count = 0
    for frame in frames:
        depth = o3d.t.geometry.Image(np.ascontiguousarray(frame.depth_m, dtype=np.float32))
        color = o3d.t.geometry.Image(
            np.ascontiguousarray(np.asarray(frame.rgb, dtype=np.float32) / 255.0)
        )
        T_cam_world = o3c.Tensor(invert_pose(np.asarray(frame.T_world_cam)), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(
            depth, K, T_cam_world, 1.0, config.depth_max_m, config.sdf_trunc_voxels
        )
        grid.integrate(
            blocks, depth, color, K, T_cam_world, 1.0, config.depth_max_m, config.sdf_trunc_voxels
        )
        count += 1
        if on_frame is not None:
            on_frame()
    if count == 0:
        raise MapError("no frames to fuse into a mesh")
    min_weight = min(config.min_weight, count)
    # Open3D keeps voxels whose weight exceeds the threshold; each frame adds 1.
    mesh = grid.extract_triangle_mesh(weight_threshold=min_weight - 0.5).to_legacy()
    if not len(mesh.vertices):
        raise MapError(
            f"the TSDF of {count} frames has no surface seen {min_weight:g} times "
            "(depth beyond depth_max_m, or poses that do not overlap?)"
        )
    mesh.compute_vertex_normals()
    return DenseMesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        triangles=np.asarray(mesh.triangles, dtype=np.int64),
        colors=np.clip(np.asarray(mesh.vertex_colors, dtype=np.float64), 0.0, 1.0),
        normals=np.asarray(mesh.vertex_normals, dtype=np.float64),
        frames=count,
    )


def _open3d() -> Any:
    """Open3D, imported on first use (typed loosely: its stubs miss overloads we use)."""
    import open3d

    return open3d
