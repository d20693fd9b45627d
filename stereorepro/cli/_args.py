"""Argument types shared by the command modules."""

from __future__ import annotations

import argparse

__all__ = ["parse_resolution"]


def parse_resolution(s: str) -> tuple[int, int]:
    """``"320x180"`` → ``(320, 180)`` (width, height); an argparse type."""
    try:
        w, h = s.lower().split("x")
        w, h = int(w), int(h)
        if w < 1 or h < 1:
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT (e.g. 320x180), got {s!r}") from None
