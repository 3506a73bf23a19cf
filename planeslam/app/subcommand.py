"""How every sub-command parser is made: with the global -v / -q accepted after the
sub-command too. A leaf of the app layer, so that `cli.py` and the command modules it
imports both use it without importing each other."""

from __future__ import annotations

import argparse


def common_options(defaults: bool) -> argparse.ArgumentParser:
    """-v / -q, accepted before and after the sub-command (after it, an absent flag leaves
    what was given before it)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument(
        "-v",
        "--verbose",
        action="count",
        help="more log output",
        default=0 if defaults else argparse.SUPPRESS,
    )
    p.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="only warnings and errors, no progress bars",
        default=False if defaults else argparse.SUPPRESS,
    )
    return p


_SUBCOMMAND_OPTIONS = common_options(defaults=False)


def add_command(
    sub: argparse._SubParsersAction, name: str, **kwargs: object
) -> argparse.ArgumentParser:
    """A sub-command parser that also takes the global -v / -q."""
    return sub.add_parser(name, parents=[_SUBCOMMAND_OPTIONS], **kwargs)  # type: ignore[arg-type]
