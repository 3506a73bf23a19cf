"""`planeslam config show`, and the config options every dataset command shares: `--set
section.key=value` (repeatable) and `--camera`, turned into labelled config layers."""

from __future__ import annotations

import argparse
from pathlib import Path

from planeslam.config import ConfigLayer, camera_layer, explain_config
from planeslam.core.config import parse_override
from planeslam.core.errors import ConfigError


def add_config_option(p: argparse.ArgumentParser) -> None:
    """--config PRESET_OR_YAML."""
    p.add_argument("--config", default=None, help="preset name or YAML file (default: guessed)")


def add_camera_option(p: argparse.ArgumentParser) -> None:
    """--camera 'fx,fy,cx,cy[,depth_scale]' (read by `camera_option`)."""
    p.add_argument("--camera", default=None, help="intrinsics override 'fx,fy,cx,cy[,depth_scale]'")


def add_config_options(p: argparse.ArgumentParser) -> None:
    """--config, --camera and --set: the config options of the commands that read a dataset."""
    add_config_option(p)
    add_camera_option(p)
    add_override_option(p)


def add_override_option(p: argparse.ArgumentParser) -> None:
    """--set SECTION.KEY=VALUE, repeatable."""
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one config key after --config and --camera, e.g. --set "
        "backend.lag_frames=0 (repeatable; the value in YAML syntax)",
    )


def override_layers(args: argparse.Namespace) -> list[ConfigLayer]:
    """The --set options as config layers, in the order given."""
    return [parse_override(text, "--set") for text in args.set]


def camera_option(args: argparse.Namespace) -> ConfigLayer | None:
    """The --camera option as a config layer (None when absent)."""
    return camera_layer(args.camera, "--camera") if args.camera else None


def add_config_command(sub: argparse._SubParsersAction) -> None:
    from planeslam.app.cli import _command

    p = _command(sub, "config", help="show the resolved configuration and where each value is from")
    config = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    s = _command(
        config,
        "show",
        help="print the resolved config, each key with its source",
        description="Print the config a command would use, as YAML that loads back as a "
        "--config file, each key followed by where its value came from: default, preset, "
        "file (a file overlays the preset it names with 'base: PRESET' or, without one, "
        "the preset guessed from the dataset folder's name), camera.yaml (the dataset's), "
        "--camera, --set.",
    )
    s.add_argument(
        "source",
        nargs="?",
        default=None,
        help="a preset name, a YAML file, or a dataset folder (default: the defaults)",
    )
    s.add_argument(
        "--dataset", type=Path, default=None, help="dataset folder (preset guess, camera.yaml)"
    )
    add_camera_option(s)
    add_override_option(s)
    s.set_defaults(func=_cmd_config_show)


def _cmd_config_show(args: argparse.Namespace) -> int:
    dataset, config = args.dataset, args.source
    if config is not None and Path(config).is_dir():
        if dataset is not None:
            raise ConfigError(
                f"config show: {config} is a folder and --dataset {dataset} another; "
                "give the dataset once"
            )
        dataset, config = Path(config), None
    resolved = explain_config(dataset, config, camera_option(args), override_layers(args))
    print(resolved.to_yaml(), end="")
    return 0
