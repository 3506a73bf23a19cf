"""The `planeslam` command: argument parsing plus one library call per sub-command.

Any PlaneSlamError becomes a one-line message on stderr and exit code 2;
Ctrl-C keeps what was already written and exits with 130.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from planeslam.errors import PlaneSlamError

log = logging.getLogger("planeslam")


def _add_synth(sub: argparse._SubParsersAction) -> None:
    from planeslam.synth import SCENES

    p = sub.add_parser(
        "synth",
        help="render a synthetic RGB-D sequence with exact truth",
        description="Render a synthetic RGB-D sequence in the TUM layout, with camera.yaml "
        "and truth.json (planes, edges, corners, objects and their sizes, trajectory).",
    )
    p.add_argument("scene", choices=sorted(SCENES), help="scene to render")
    p.add_argument("outdir", type=Path, help="output folder (created)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: scene's)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.set_defaults(func=_cmd_synth)


def _cmd_synth(args: argparse.Namespace) -> int:
    from planeslam.synth import synthesize

    result = synthesize(args.scene, args.outdir, frames=args.frames, seed=args.seed)
    print(f"wrote {result.num_frames} frames of '{result.scene_name}' to {result.out_dir}")
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="render the built-in synthetic scene and run planeslam on it",
        description="Render the built-in synthetic scene (the paper's box in a room, seen "
        "from a circle of 24 poses) and run the main job on it; prints a summary "
        "and where the outputs are.",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from planeslam.demo import run_demo

    result = run_demo(args.out, seed=args.seed, progress=True)
    print(result.summary())
    return 0


def _add_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="ATE and RPE of a TUM trajectory against ground truth (via evo)",
        description="Absolute trajectory error (translation RMSE, mean, median, max after SE(3) "
        "alignment without scale) and relative pose error per second, computed with evo. "
        "Writes eval.json, trajectory.png, ate_over_time.png and report.html. Object size "
        "errors are added when truth.json sits next to GROUNDTRUTH and map.json next to "
        "ESTIMATE (or --truth / --map are given).",
    )
    p.add_argument("groundtruth", type=Path, help="ground-truth TUM trajectory file")
    p.add_argument("estimate", type=Path, help="estimated TUM trajectory file")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: ESTIMATE's)")
    p.add_argument(
        "--max-dt", type=float, default=0.02, help="pose association window [s] (default 0.02)"
    )
    p.add_argument("--rpe-delta", type=float, default=1.0, help="RPE span [s] (default 1.0)")
    p.add_argument("--truth", type=Path, default=None, help="truth.json of a synthetic scene")
    p.add_argument("--map", type=Path, default=None, help="map.json with estimated objects")
    p.set_defaults(func=_cmd_eval)


def _cmd_eval(args: argparse.Namespace) -> int:
    from planeslam.eval.report import evaluate_to_folder
    from planeslam.eval.trajectory_metrics import format_table

    run = evaluate_to_folder(
        args.groundtruth, args.estimate, args.out, args.max_dt, args.rpe_delta, args.truth,
        args.map,
    )
    print(format_table(run.evaluation))
    print(f"report: {run.paths['report']}")
    return 0


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_synth,
    _add_demo,
    _add_eval,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="planeslam",
        description="RGB-D SLAM with a plane-object map (planes, real intersections, "
        "trihedral corners, classified objects with sizes) and a GTSAM backend.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.quiet else (logging.DEBUG if args.verbose else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except PlaneSlamError as exc:
        print(f"planeslam: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("planeslam: interrupted; outputs written so far are kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
