"""Command line: ``stereorepro <command> ...`` (also ``python -m stereorepro``).

Each command module of this package registers its sub-commands through ``register(subparsers)``; this file
collects them (the shared argument types are in :mod:`._args`). A command returns an exit code; errors a user can fix (bad
file, bad option) raise :class:`~stereorepro.errors.UserError`: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import UserError
from ._args import parse_resolution  # noqa: F401  (re-exported: the shared argument types live in _args)


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
