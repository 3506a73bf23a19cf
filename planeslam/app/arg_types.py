"""Range-checked numeric argument types for argparse: a value out of range is a usage
error (exit 2, one line naming the flag and the range) before any work starts."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

MAX_SEED = 2**63 - 1
"""Largest seed accepted (numpy generators take any non-negative int; 63 bits is plenty)."""


def whole(low: int, high: int | None = None) -> Callable[[str], int]:
    """A type for whole numbers in [low, high] (no upper bound when `high` is None)."""
    span = f">= {low}" if high is None else f"in {low}..{high}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a whole number {span}, got {text!r}"
            ) from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected a whole number {span}, got {value}")
        return value

    parse.__name__ = "whole number"  # argparse names the type in its messages
    return parse


def number(low: float, high: float, open_low: bool = False) -> Callable[[str], float]:
    """A type for finite numbers in [low, high] ((low, high] with `open_low`)."""
    span = f"{'(' if open_low else '['}{low:g}, {high:g}]"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {span}, got {text!r}") from None
        inside = (low < value if open_low else low <= value) and value <= high
        if not (math.isfinite(value) and inside):
            raise argparse.ArgumentTypeError(f"expected a finite number in {span}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


SEED = whole(0, MAX_SEED)
COUNT = whole(1)
"""A count of frames, passes, jobs or a step (at least 1)."""


def sigma_pair(text: str) -> tuple[float, float]:
    """'M,DEG' -> (metres, degrees), both positive and finite: the noise of one step of
    odometry (argparse type)."""
    try:
        sigma_m, sigma_deg = (float(v) for v in text.split(","))
    except ValueError:
        sigma_m = sigma_deg = math.nan
    if not all(0 < v < math.inf for v in (sigma_m, sigma_deg)):
        raise argparse.ArgumentTypeError(
            "expected 'M,DEG', two positive numbers (translation [m], rotation [deg]), "
            f"got {text!r}"
        )
    return sigma_m, sigma_deg
