"""Command-line parts of seeing a run: `planeslam run --viewer / --rrd FILE`,
`planeslam view RUN_DIR` and `planeslam mesh RUN_DIR`. Light to import: the viewer
(rerun) and the mesh (Open3D) load when a command runs."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from planeslam.app.arg_types import COUNT, number
from planeslam.app.subcommand import add_command

if TYPE_CHECKING:
    from planeslam.app.viewer import RerunViewer

log = logging.getLogger(__name__)

MIN_VOXEL_M = 0.001
"""Smallest TSDF voxel [m]: finer grids of a room need more memory than a machine has."""
MAX_VOXEL_M = 1.0


def add_viewer_options(p: argparse.ArgumentParser) -> None:
    """`--viewer` and `--rrd FILE` of `planeslam run`."""
    p.add_argument(
        "--viewer",
        action="store_true",
        help="stream the run live to a rerun viewer window (needs a display; else --rrd)",
    )
    p.add_argument("--rrd", type=Path, default=None, help="record the run to this .rrd file")


@contextmanager
def viewer_from_args(args: argparse.Namespace, name: str) -> Iterator[RerunViewer | None]:
    """The RerunViewer that `--viewer` / `--rrd` ask for (closed at the end), or None."""
    if not (args.viewer or args.rrd is not None):
        yield None
        return
    from planeslam.app.viewer import RerunViewer

    with RerunViewer(name, args.rrd, live=args.viewer) as viewer:
        log.info("viewer: streaming to %s", viewer.where)
        yield viewer


def add_view_command(sub: argparse._SubParsersAction) -> None:
    """The `view` sub-command."""

    p = add_command(
        sub,
        "view",
        help="replay a finished run in the rerun viewer (or record it to .rrd)",
        description="Turn a finished run's outputs (run.json, config.yaml, trajectory.txt, "
        "frames.jsonl, map.json) into a rerun recording: every frame's image with the front "
        "end's planes, edges, corners and objects, its final pose, tracking path and stage "
        "times, the final map and trajectory against the ground truth. Opens the viewer "
        "where a display exists; otherwise (or with --rrd) writes an .rrd file to open with "
        "`rerun FILE`.",
    )
    p.add_argument("run_dir", type=Path, help="output folder of `planeslam run`")
    p.add_argument("--rrd", type=Path, default=None, help="write this .rrd file instead")
    p.add_argument("--every", type=COUNT, default=1, help="log every K-th frame (default 1)")
    p.add_argument("--dataset", type=Path, default=None, help="dataset folder (default: run's)")
    p.set_defaults(func=_cmd_view)


def _cmd_view(args: argparse.Namespace) -> int:
    from planeslam.app.viewer import view_run

    result = view_run(
        args.run_dir, args.rrd, every=args.every, dataset=args.dataset, progress=not args.quiet
    )
    print(f"logged {result.frames} frames to {result.where}")
    if result.rrd is not None:
        print(f"open it with: rerun {result.rrd}")
    return 0


def add_mesh_command(sub: argparse._SubParsersAction) -> None:
    """The `mesh` sub-command."""

    p = add_command(
        sub,
        "mesh",
        help="dense mesh of a finished run (TSDF of its keyframes, optimised poses)",
        description="Fuse a finished run's keyframes (or --all-frames) with the run's final "
        "poses (trajectory.txt) into a TSDF volume (Open3D VoxelBlockGrid) and write "
        "RUN_DIR/mesh.ply with vertex colours and normals. The dataset is the one run.json "
        "names (or --dataset).",
    )
    p.add_argument("run_dir", type=Path, help="output folder of `planeslam run`")
    p.add_argument(
        "--voxel",
        type=number(MIN_VOXEL_M, MAX_VOXEL_M),
        default=0.01,
        help=f"voxel edge [m] (default 0.01; {MIN_VOXEL_M:g} to {MAX_VOXEL_M:g})",
    )
    p.add_argument(
        "--depth-max",
        type=number(0, 100, open_low=True),
        default=3.0,
        help="ignore depth beyond this [m] (default 3)",
    )
    p.add_argument("--all-frames", action="store_true", help="fuse every frame, not keyframes")
    p.add_argument("--dataset", type=Path, default=None, help="dataset folder (default: run's)")
    p.add_argument("--out", type=Path, default=None, help="mesh file (default RUN_DIR/mesh.ply)")
    p.set_defaults(func=_cmd_mesh)


def _cmd_mesh(args: argparse.Namespace) -> int:
    from planeslam.app.mesh import mesh_run
    from planeslam.mapping.dense_mesh import TsdfConfig

    result = mesh_run(
        args.run_dir,
        TsdfConfig(voxel_m=args.voxel, depth_max_m=args.depth_max),
        all_frames=args.all_frames,
        dataset=args.dataset,
        out=args.out,
        progress=not args.quiet,
    )
    print(result.text())
    return 0
