"""Command line: ``stereorepro <command> ...`` (also ``python -m stereorepro``).

Each command module of this package registers its sub-commands through ``register(subparsers)``; this file
collects them and holds the shared argument types. A command returns an exit code; errors a user can fix (bad
file, bad option) raise :class:`~stereorepro.errors.UserError`: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import UserError


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stereorepro", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    from . import demo, experiment, render, reproject  # each imports its heavy dependencies inside its commands

    for module in (render, experiment, reproject, demo):
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"stereorepro {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
