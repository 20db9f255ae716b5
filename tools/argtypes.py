"""argparse value types shared by the command-line modules."""

from __future__ import annotations

import argparse
import math


def positive_int(text: str) -> int:
    """An integer >= 1 (argparse ``type=``)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def _positive_float(text: str, what: str) -> float:
    """A finite number > 0; ``what`` names it in the message (``"number of seconds"``)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a {what}, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive {what}, got {text!r}")
    return v


def positive_seconds(text: str) -> float:
    """A duration > 0 [s] (argparse ``type=``)."""
    return _positive_float(text, "number of seconds")


def positive_hz(text: str) -> float:
    """A rate > 0 [Hz] (argparse ``type=``)."""
    return _positive_float(text, "rate in Hz")


def positive_factor(text: str) -> float:
    """A multiplier > 0, e.g. of a recording's rate (argparse ``type=``)."""
    return _positive_float(text, "factor")
