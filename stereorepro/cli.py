"""Command line: ``stereorepro <command> ...`` (also ``python -m stereorepro``).

Each subsystem registers its own sub-commands through a ``register(subparsers)`` function; this file only
collects them. A command returns an exit code; errors a user can fix (bad file, bad option) print one line to
stderr and exit with code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Modules that provide ``register(subparsers)``. A module that is missing (an optional subsystem not built yet)
# is skipped; any other import error is raised.
_COMMAND_MODULES = [
    "stereorepro.render.cli",
    "stereorepro.experiment",
    "stereorepro.reproject_cli",
    "stereorepro.demo",
]


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


class UserError(Exception):
    """An error caused by the user's input (file, option); printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stereorepro", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name == name:
                continue
            raise
        mod.register(sub)
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
