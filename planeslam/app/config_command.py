"""`planeslam config show` and `config docs`, and the config options every dataset
command shares: `--set section.key=value` (repeatable) and `--camera`, turned into
labelled config layers."""

from __future__ import annotations

import argparse
from pathlib import Path

from planeslam.app.subcommand import add_command
from planeslam.config import (
    BASIC_KEYS,
    ConfigLayer,
    ResolvedConfig,
    camera_layer,
    configuration_markdown,
    explain_config,
)
from planeslam.core.config import parse_override
from planeslam.core.errors import ConfigError
from planeslam.core.safe_files import write_text_atomic


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

    p = add_command(
        sub, "config", help="show the resolved configuration and where each value is from"
    )
    config = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    s = add_command(
        config,
        "show",
        help="print the resolved config, each key with its source",
        description="Print the config a command would use, as YAML, each key followed by "
        "where its value came from: default, preset, file (a file overlays the preset it "
        "names with 'base: PRESET' or, without one, the preset guessed from the dataset "
        "folder's name), camera.yaml (the dataset's), --camera, --set. By default the "
        "basic keys and the keys a layer set; --advanced prints every key, as a file that "
        "loads back (--config) as the same config.",
    )
    s.add_argument(
        "--advanced",
        action="store_true",
        help=f"every key, not only the {len(BASIC_KEYS)} basic ones",
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
    d = add_command(
        config,
        "docs",
        help="the configuration reference (every key, its values, default and meaning)",
        description="Write the configuration reference, generated from the config "
        "dataclasses' docstrings, basic keys first (the project keeps it as "
        "docs/configuration.md).",
    )
    d.add_argument(
        "--markdown",
        type=Path,
        default=None,
        metavar="FILE",
        help="write it to this file (default: print it)",
    )
    d.set_defaults(func=_cmd_config_docs)


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
    print(resolved.to_yaml(keys=None if args.advanced else shown_keys(resolved)), end="")
    return 0


def shown_keys(resolved: ResolvedConfig) -> list[str]:
    """What `config show` prints without --advanced: the basic keys, and every other key
    that a layer (preset, file, camera.yaml, --camera, --set) set."""
    chosen = [key for key, source in resolved.sources.items() if source != "default"]
    return list(BASIC_KEYS) + [key for key in chosen if key not in BASIC_KEYS]


DOCS_COMMAND = "planeslam config docs --markdown docs/configuration.md"
"""The command that writes docs/configuration.md, named at the top of the page."""


def _cmd_config_docs(args: argparse.Namespace) -> int:
    text = configuration_markdown(DOCS_COMMAND)
    if args.markdown is None:
        print(text, end="")
        return 0
    write_text_atomic(args.markdown, text)
    print(f"wrote {args.markdown}")
    return 0
