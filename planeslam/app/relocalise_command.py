"""`planeslam relocalise`: how well frames are placed in a finished map on their own
(arguments + one call to `planeslam.eval.relocalisation.relocalisation_benchmark`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from planeslam.app.arg_types import COUNT
from planeslam.app.config_command import add_config_options, camera_option, override_layers
from planeslam.app.subcommand import add_command


def add_relocalise_command(sub: argparse._SubParsersAction) -> None:
    """The `relocalise` sub-command."""

    p = add_command(
        sub,
        "relocalise",
        help="place every n-th frame in a finished map on its own, against ground truth",
        description="Build the map of a dataset with a full run (or load --map MAP.json), "
        "then place every n-th frame in it on its own, with no prior (whole-map search over "
        "corners, plane triples, edges, objects and keypoints), and count the frames within "
        "the tolerances of their ground truth, with the time per attempt.",
    )
    p.add_argument("dataset", type=Path, help="TUM-layout folder with groundtruth.txt")
    p.add_argument("--map", type=Path, default=None, help="map.json to place frames in")
    p.add_argument("--every", type=COUNT, default=10, help="every n-th frame (default 10)")
    add_config_options(p)
    p.add_argument(
        "--json", action="store_true", help="print one JSON object (the summary and every attempt)"
    )
    p.set_defaults(func=_cmd_relocalise)


def _cmd_relocalise(args: argparse.Namespace) -> int:
    from planeslam.core.native_tuning import single_native_threads
    from planeslam.eval.relocalisation import relocalisation_benchmark

    with single_native_threads():
        report = relocalisation_benchmark(
            args.dataset,
            args.map,
            args.every,
            args.config,
            camera_option(args),
            override_layers(args),
        )
    print(json.dumps(report.to_dict(), indent=2) if args.json else report.to_text())
    return 0
