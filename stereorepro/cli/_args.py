"""Argument types shared by the command modules: each rejects a bad value with a message naming what it
expected (argparse then prints one line and exits with code 2)."""

from __future__ import annotations

import argparse
import math

__all__ = ["parse_resolution", "positive_int", "nonnegative_int", "positive_float", "alpha_list", "threshold_scale"]


def parse_resolution(s: str) -> tuple[int, int]:
    """``"320x180"`` → ``(320, 180)`` (width, height); an argparse type."""
    try:
        w, h = s.lower().split("x")
        w, h = int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT (e.g. 320x180), got {s!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {s!r}")
    return w, h


def _int(s: str, lo: int, what: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {s!r}") from None
    if v < lo:
        raise argparse.ArgumentTypeError(f"expected {what}, got {v}")
    return v


def positive_int(s: str) -> int:
    """An integer >= 1."""
    return _int(s, 1, "an integer >= 1")


def nonnegative_int(s: str) -> int:
    """An integer >= 0."""
    return _int(s, 0, "an integer >= 0")


def positive_float(s: str) -> float:
    """A finite number > 0."""
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {s!r}")
    return v


def alpha_list(s: str) -> tuple[float, ...]:
    """Comma-separated EMA weights, each a number in (0, 1] (an empty string: none)."""
    out = []
    for part in s.split(","):
        if not part.strip():
            continue
        try:
            a = float(part)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected comma-separated numbers in (0, 1], got {part.strip()!r}"
            ) from None
        if not (math.isfinite(a) and 0.0 < a <= 1.0):
            raise argparse.ArgumentTypeError(f"expected numbers in (0, 1], got {part.strip()!r}")
        out.append(a)
    return tuple(out)


def threshold_scale(s: str) -> float | None:
    """``"auto"`` (None: the resolution rule) or a positive number."""
    return None if s == "auto" else positive_float(s)
