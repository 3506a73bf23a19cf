"""The `planeslam` command: argument parsing plus one library call per sub-command.

Any PlaneSlamError or operating-system error (an unwritable folder, a full disk) becomes a
one-line message on stderr and exit code 2; Ctrl-C keeps what was already written and
exits with 130, SIGTERM and SIGHUP likewise with 143 and 129.
"""

from __future__ import annotations

import argparse
import logging
import os
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from planeslam import __version__
from planeslam.app.arg_types import COUNT, SEED, number, sigma_pair, whole
from planeslam.app.calibrate import add_calibrate_command
from planeslam.app.config_command import (
    add_config_command,
    add_config_option,
    add_config_options,
    add_override_option,
    camera_option,
    override_layers,
)
from planeslam.app.dataset_options import TopicOverrides, add_topic_options
from planeslam.app.download import add_download_command
from planeslam.app.relocalise_command import add_relocalise_command
from planeslam.app.signals import Terminated, stop_signals_interrupt
from planeslam.app.subcommand import add_command, common_options
from planeslam.app.synth_command import add_synth_command
from planeslam.app.view_commands import (
    add_mesh_command,
    add_view_command,
    add_viewer_options,
    viewer_from_args,
)
from planeslam.core.errors import ConfigError, PlaneSlamError
from planeslam.core.native_tuning import keep_freed_memory

log = logging.getLogger("planeslam")


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "demo",
        help="render the built-in synthetic scene and run planeslam on it",
        description="Render the built-in synthetic scene (the paper's box in a room, seen "
        "from a circle of 24 poses) and run the main job on it; prints a summary "
        "and where the outputs are.",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument("--seed", type=SEED, default=0, help="noise seed (default 0)")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from planeslam.app.demo import run_demo

    result = run_demo(args.out, seed=args.seed, progress=not args.quiet)
    print(result.summary())
    return 0


def _add_eval(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "eval",
        help="ATE and RPE of a TUM trajectory against ground truth (via evo)",
        description="Absolute trajectory error (translation RMSE, mean, median, max after SE(3) "
        "alignment without scale) and relative pose error per second, computed with evo. "
        "Writes eval.json, frame_errors.csv (per pose: its error and its step's, with the "
        "tracking path from a frames.jsonl beside ESTIMATE), trajectory.png, "
        "ate_over_time.png and report.html. Object size "
        "errors are added when truth.json sits next to GROUNDTRUTH and map.json next to "
        "ESTIMATE (or --truth / --map are given).",
    )
    p.add_argument("groundtruth", type=Path, help="ground-truth TUM trajectory file")
    p.add_argument("estimate", type=Path, help="estimated TUM trajectory file")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: ESTIMATE's)")
    p.add_argument(
        "--max-dt",
        type=number(0, 10, open_low=True),
        default=0.02,
        help="pose association window [s] (default 0.02)",
    )
    p.add_argument(
        "--rpe-delta",
        type=number(0, 1e6, open_low=True),
        default=1.0,
        help="RPE span [s] (default 1.0)",
    )
    p.add_argument("--truth", type=Path, default=None, help="truth.json of a synthetic scene")
    p.add_argument("--map", type=Path, default=None, help="map.json with estimated objects")
    p.set_defaults(func=_cmd_eval)


def _cmd_eval(args: argparse.Namespace) -> int:
    from planeslam.eval.report import evaluate_to_folder
    from planeslam.eval.trajectory_metrics import format_table

    run = evaluate_to_folder(
        args.groundtruth,
        args.estimate,
        args.out,
        args.max_dt,
        args.rpe_delta,
        args.truth,
        args.map,
    )
    print(format_table(run.evaluation))
    print(f"report: {run.paths['report']}")
    return 0


def _add_run(sub: argparse._SubParsersAction) -> None:
    from planeslam.backend.base import BackendKind  # planeslam.slam loads Open3D: 1.4 s

    p = add_command(
        sub,
        "run",
        help="full SLAM on a TUM-layout folder or a ROS bag (trajectory, map, metrics, evaluation)",
        description="Run SLAM on a dataset: a TUM-layout folder, a ROS 1 .bag or a ROS 2 bag "
        "folder (sqlite3 or mcap; colour, depth and camera_info topics, TUM's names by "
        "default; ground truth from a TUM file beside the bag or /tf). Writes trajectory.txt "
        "(row by row as frames are tracked, final poses at the end), frames.jsonl, map.json, "
        "map.ply, config.yaml, metrics.json and, with ground truth, eval.json, plots and "
        "report.html. Ctrl-C stops and keeps everything computed so far.",
    )
    p.add_argument(
        "dataset",
        type=Path,
        help="TUM-layout folder (rgb/, depth/, rgb.txt, depth.txt), ROS 1 .bag or ROS 2 bag folder",
    )
    add_config_options(p)
    add_topic_options(p)
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default out/<dataset name>); a previous run's files there are "
        "moved into previous-<time>/",
    )
    p.add_argument(
        "--backend",
        choices=tuple(k.value for k in BackendKind),
        default=None,
        help="isam2: GTSAM factor graph (default); merge: the paper's frame-by-frame merging",
    )
    p.add_argument("--max-frames", type=COUNT, default=None, help="process at most N frames")
    p.add_argument("--every", type=COUNT, default=None, help="use every K-th frame (default 1)")
    p.add_argument("--seed", type=SEED, default=None, help="random seed (default 0)")
    p.add_argument(
        "--start-pose",
        choices=("groundtruth", "identity"),
        default=None,
        help="first frame's pose, which fixes the world frame: groundtruth (default: its "
        "ground-truth pose when the dataset has one, else the identity) or identity",
    )
    p.add_argument("--map", type=Path, default=None, help="map.json to track in (relocalised)")
    p.add_argument("--localize", action="store_true", help="with --map: leave the map unchanged")
    p.add_argument(
        "--out-bag",
        type=Path,
        default=None,
        help="also write the results as a ROS 2 bag (mcap) in this new folder: /tf, the "
        "path, plane and object markers",
    )
    p.add_argument(
        "--odometry",
        type=Path,
        default=None,
        metavar="FILE",
        help="the camera's odometry (wheel, IMU) as a TUM trajectory file, on the frames' "
        "clock and in the camera frame: its motion between frames predicts tracking and "
        "joins the factor graph",
    )
    p.add_argument(
        "--odometry-sigma",
        type=sigma_pair,
        default=(0.02, 1.0),
        metavar="M,DEG",
        help="noise of one step of --odometry: translation [m] and rotation [deg] per axis "
        "(default 0.02,1)",
    )
    add_viewer_options(p)
    p.set_defaults(func=_cmd_run)


def _cmd_run(args: argparse.Namespace) -> int:
    from planeslam.app.run_folder import default_out_dir
    from planeslam.app.runner import run_sequence
    from planeslam.io.odometry import OdometryFile

    out = args.out if args.out is not None else default_out_dir(args.dataset)
    with viewer_from_args(args, default_out_dir(args.dataset).name) as viewer:
        result = run_sequence(
            args.dataset,
            out,
            args.config,
            camera_option(args),
            args.backend,
            args.max_frames,
            args.every,
            progress=not args.quiet,
            seed=args.seed,
            observer=viewer,
            command=args.command_line,
            topics=TopicOverrides.from_args(args),
            overrides=override_layers(args),
            start_pose=args.start_pose,
            map_path=args.map,
            localize=args.localize,
            out_bag=args.out_bag,
            odometry=(
                None
                if args.odometry is None
                else OdometryFile.load(args.odometry, *args.odometry_sigma)
            ),
        )
    print(result.text())
    return 0


def _add_frame(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "frame",
        help="the front end on one frame: frame.json and overlay.png",
        description="Run the per-frame front end (planes, real intersections, plane graph, "
        "trihedral corners, objects with classes and sizes) on frame INDEX of a dataset and "
        "write frame.json (camera frame) and overlay.png.",
    )
    p.add_argument("dataset", type=Path, help="TUM-layout folder, ROS 1 .bag or ROS 2 bag folder")
    p.add_argument("index", type=whole(0), help="frame index (0-based, in association order)")
    add_config_options(p)
    add_topic_options(p)
    p.add_argument("--out", type=Path, default=None, help="output folder (default out/frame)")
    p.set_defaults(func=_cmd_frame)


def _cmd_frame(args: argparse.Namespace) -> int:
    from planeslam.app.frame import process_frame

    out = args.out if args.out is not None else Path("out") / "frame"
    result = process_frame(
        args.dataset,
        args.index,
        args.config,
        camera_option(args),
        out,
        topics=TopicOverrides.from_args(args),
        overrides=override_layers(args),
    )
    print(result.summary())
    return 0


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "bench", help="benchmarks: the front end's speed, or a suite of runs")
    bench = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    f = add_command(
        bench,
        "frontend",
        help="per-stage speed of the front end on one core, with Open3D segment_plane",
        description="Per-stage median milliseconds per frame and frames per second of the "
        "front end (organized and msac segmenters) and of Open3D's segment_plane applied "
        "plane after plane, on one core, frames preloaded. Default data: the built-in "
        "synthetic scene.",
    )
    f.add_argument("dataset", type=Path, nargs="?", default=None, help="dataset folder")
    f.add_argument("--frames", type=COUNT, default=30, help="frames to time (default 30)")
    add_config_options(f)
    f.add_argument(
        "--reference-frames",
        type=whole(0),
        default=3,
        help="frames for the slow Open3D segment_plane reference (default 3)",
    )
    f.add_argument("--json", action="store_true", help="print one JSON object")
    f.set_defaults(func=_cmd_bench_frontend)
    s = add_command(
        bench,
        "suite",
        help="run methods on sequences; one table (markdown + CSV)",
        description="Run every method of a suite on every sequence (one at a time by "
        "default, --jobs N at once, or on a Dask cluster with --executor dask) and print "
        "one table: ATE, RPE, fps, memory ratio, object size error. Default suite: the "
        "synthetic scenes plus ../shared/data when present, with Open3D RGB-D odometry, "
        "the paper's merging and the iSAM2 backend.",
    )
    s.add_argument("suite", type=Path, nargs="?", default=None, help="suite YAML")
    s.add_argument(
        "--jobs",
        type=COUNT,
        default=None,
        help="runs at once (default 1: fps figures need the machine to themselves)",
    )
    s.add_argument("--out", type=Path, default=Path("out/suite"), help="output folder")
    s.add_argument(
        "--executor",
        choices=("local", "dask"),
        default=None,
        help="where jobs run: local (default) or dask (a Dask distributed cluster)",
    )
    s.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="Dask scheduler address, e.g. tcp://host:8786 (default with --executor dask: "
        "a LocalCluster of --jobs workers on this machine)",
    )
    s.set_defaults(func=_cmd_bench_suite)
    long = add_command(
        bench,
        "long",
        help="long sequences that revisit: fps, backend, landmarks and memory per block",
        description="Replay a sequence in passes (forward, backward, forward, ...: the camera "
        "revisits what it mapped) and report per block of frames the fps, the iSAM2 update "
        "time, the plane landmarks and the resident memory of both processes, then the ATE. "
        "SOURCE: a TUM folder with associations.txt and groundtruth.txt, or a synthetic scene.",
    )
    long.add_argument("source", help="dataset folder or synthetic scene name")
    long.add_argument(
        "--passes", type=COUNT, default=5, help="passes over the sequence (default 5)"
    )
    long.add_argument("--block", type=COUNT, default=1000, help="frames per block (default 1000)")
    add_config_option(long)
    add_override_option(long)
    long.add_argument(
        "--seeds",
        type=SEED,
        nargs="+",
        default=[0],
        metavar="SEED",
        help="run the replay once per seed (run.seed) and print the median and range of the "
        "ATE and the plane growth over them (default: 0)",
    )
    long.add_argument("--out", type=Path, default=Path("out/long"), help="output folder")
    long.set_defaults(func=_cmd_bench_long)
    robust = add_command(
        bench,
        "robust",
        help="robustness on generated sequences: a tuning and a validation set",
        description="Render the benchmark's procedural sequences (rooms, furniture, "
        "textures, depth models, camera paths drawn from fixed seeds; half a tuning set, "
        "half a validation set) and run planeslam and Open3D RGB-D odometry on each: "
        "tracked fraction, ATE, false jumps, relocalisations (and wrong ones), object size "
        "error, fps, blind frames (whose images do not place the camera along some axis); "
        "a summary per set and per kind (OUT/rows.jsonl), and per sequence "
        "planeslam's trajectory.txt and frame_errors.csv (each frame's error and its "
        "step's, beside its tracking path: OUT/runs/NAME/). Tune on the tuning set; "
        "accept a tracking change by the validation set's summary.",
    )
    robust.add_argument("--out", type=Path, default=Path("out/robust"), help="output folder")
    robust.add_argument(
        "--jobs", type=_positive_int, default=1, help="sequences at once (default 1)"
    )
    robust.add_argument(
        "--split",
        choices=("tuning", "validation", "all"),
        default="all",
        help="which set to run (default: both)",
    )
    robust.add_argument(
        "--count",
        type=_positive_int,
        default=None,
        help="only the first N sequences of the list (a quick look; default all 42)",
    )
    robust.add_argument("--executor", choices=("local", "dask"), default="local")
    robust.add_argument("--scheduler", default=None, metavar="ADDRESS")
    robust.add_argument(
        "--markdown",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the tables into a section of this Markdown page (e.g. "
        "docs/benchmarks.md), replacing the section of the same --label",
    )
    robust.add_argument(
        "--label", default="current code", help="the section's name (default 'current code')"
    )
    robust.add_argument(
        "--no-open3d", action="store_true", help="skip the Open3D odometry baseline"
    )
    robust.add_argument(
        "--against",
        type=Path,
        default=None,
        metavar="DIR",
        help="an earlier run's output folder (or its rows.jsonl): also print and write "
        "each set's pass count before and after and every sequence whose figures moved "
        "(judge a change or a --set by the validation set, run before and after)",
    )
    add_override_option(robust)
    robust.set_defaults(func=_cmd_bench_robust)

    speed = add_command(
        bench,
        "speed",
        help="front end and whole system fps, 3 rounds, normalised by a reference workload",
        description="Time the front end (frames in memory) and the whole system (as "
        "`planeslam run`, outputs not written) on each DATASET and on the built-in synthetic "
        "scene, in rounds within one sitting, with a fixed numpy/OpenCV reference workload "
        "timed before the first run and after every run. Prints medians over the rounds, the "
        "load average before and after, and reference units per frame (seconds per frame / "
        "reference seconds), which compare across hours. Default DATASET: "
        "../shared/data/7scenes_redkitchen_1000f when present.",
    )
    speed.add_argument("dataset", type=Path, nargs="*", help="TUM-layout dataset folder(s)")
    speed.add_argument(
        "--frames", type=int, default=300, help="first N frames of each dataset (default 300)"
    )
    speed.add_argument("--repeats", type=int, default=3, help="rounds (default 3)")
    speed.add_argument(
        "--no-synthetic", action="store_true", help="leave out the built-in synthetic scene"
    )
    add_config_option(speed)
    add_override_option(speed)
    speed.add_argument(
        "--markdown", type=Path, default=None, metavar="FILE", help="append the table to FILE"
    )
    speed.set_defaults(func=_cmd_bench_speed)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {value}")
    return value


def _cmd_bench_frontend(args: argparse.Namespace) -> int:
    import json

    from planeslam.app.bench import bench_frontend

    result = bench_frontend(
        args.dataset,
        frames=args.frames,
        config=args.config,
        camera=camera_option(args),
        progress=not (args.json or args.quiet) and sys.stderr.isatty(),
        reference_frames=args.reference_frames,
        overrides=override_layers(args),
    )
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.to_text())
    return 0


def _cmd_bench_long(args: argparse.Namespace) -> int:
    from planeslam.app.bench_long import bench_long, long_text

    results = bench_long(
        args.source,
        args.out,
        args.passes,
        args.block,
        args.config,
        progress=not args.quiet,
        overrides=override_layers(args),
        seeds=args.seeds,
    )
    print(long_text(results))
    return 0


def _cmd_bench_robust(args: argparse.Namespace) -> int:
    from planeslam.app.bench_robust import run_robust_command

    if args.scheduler and args.executor != "dask":
        raise ConfigError("--scheduler needs --executor dask")
    print(
        run_robust_command(
            args.out,
            args.command_line,
            jobs=args.jobs,
            split=args.split,
            count=args.count,
            executor=args.executor,
            scheduler=args.scheduler,
            overrides=override_layers(args),
            markdown=args.markdown,
            label=args.label,
            with_open3d=not args.no_open3d,
            progress=not args.quiet,
            against=args.against,
        )
    )
    return 0


def _cmd_bench_speed(args: argparse.Namespace) -> int:
    from planeslam.app.bench_speed import DEFAULT_DATASET, append_markdown, bench_speed

    datasets = list(args.dataset)
    if not datasets and DEFAULT_DATASET.is_dir():
        datasets = [DEFAULT_DATASET]
    elif not datasets:
        log.warning("%s not found: timing the synthetic scene only", DEFAULT_DATASET)
    result = bench_speed(
        datasets,
        frames=args.frames,
        repeats=args.repeats,
        synthetic=not args.no_synthetic,
        config=args.config,
        overrides=override_layers(args),
        command=args.command_line,
        progress=not args.quiet,
    )
    print(result.to_text())
    if args.markdown is not None:
        print(f"table appended to {append_markdown(result, args.markdown)}")
    return 0


def _cmd_bench_suite(args: argparse.Namespace) -> int:
    from planeslam.app.suite import run_suite_command

    table = run_suite_command(
        args.suite,
        args.out,
        jobs=args.jobs,
        progress=not args.quiet,
        executor=args.executor,
        scheduler=args.scheduler,
    )
    print(table)
    return 0


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    add_synth_command,
    _add_demo,
    _add_eval,
    _add_run,
    _add_frame,
    _add_bench,
    add_view_command,
    add_mesh_command,
    add_config_command,
    add_download_command,
    add_relocalise_command,
    add_calibrate_command,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="planeslam",
        description="RGB-D SLAM with a plane-object map (planes, real intersections, "
        "trihedral corners, classified objects with sizes) and a GTSAM backend.",
        parents=[common_options(defaults=True)],
    )
    parser.add_argument("--version", action="version", version=f"planeslam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in COMMANDS:
        add(sub)
    return parser


def isolate_child_interpreters() -> None:
    """Every Python this process starts (the suite's and Dask's spawned workers) leaves the
    working directory off its `sys.path` (PYTHONSAFEPATH, Python >= 3.11), so a module
    planted there never runs; the iSAM2 worker starts with `-I` itself."""
    os.environ["PYTHONSAFEPATH"] = "1"


def main(argv: Sequence[str] | None = None) -> int:
    isolate_child_interpreters()  # the application's choice, as the allocator below
    parser = build_parser()
    args = parser.parse_args(argv)
    args.command_line = shlex.join(["planeslam", *(sys.argv[1:] if argv is None else argv)])
    level = logging.WARNING if args.quiet else (logging.DEBUG if args.verbose else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    keep_freed_memory()  # the application's choice: about 15 % faster front end
    try:
        with stop_signals_interrupt():  # SIGTERM / SIGHUP stop a command as Ctrl-C does
            return int(args.func(args) or 0)
    except PlaneSlamError as exc:
        print(f"planeslam: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable --out, a full disk, an unreadable file
        print(f"planeslam: error: {os_error_text(exc)}", file=sys.stderr)
        return 2
    except Terminated as exc:
        print(f"planeslam: stopped by {exc}; outputs written so far are kept", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("planeslam: interrupted; outputs written so far are kept", file=sys.stderr)
        return 130


def os_error_text(exc: OSError) -> str:
    """'PATH: reason' for an operating-system error (one line, no traceback)."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    if exc.filename2 is not None:
        return f"{exc.filename} -> {exc.filename2}: {reason}"
    return f"{exc.filename}: {reason}"


if __name__ == "__main__":
    sys.exit(main())
