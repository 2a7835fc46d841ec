"""argparse types for numeric options: a bad value is an argparse error (usage, one line, exit 2).

``float("nan")`` and ``float("inf")`` parse, and NaN passes every ``<= 0`` check: without these types a
``--square-mm nan`` reached the solver and ended in a LinAlgError traceback.
"""

from __future__ import annotations

import argparse
import math


def _number(text: str, kind: type) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text[:40]!r}"
                                         ) from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text[:40]!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (sizes, durations)."""
    value = _number(text, float)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be greater than 0, got {text[:40]!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (counts, limits)."""
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text[:40]!r}")
    return value


def pixel_count(text: str) -> int:
    """A number of pixels >= 1, written as an integer or in scientific notation (``64e6``)."""
    value = _number(text, float)
    if value < 1 or value != int(value):
        raise argparse.ArgumentTypeError(f"expected a whole number of pixels >= 1, e.g. 67108864 or 64e6, "
                                         f"got {text[:40]!r}")
    return int(value)
