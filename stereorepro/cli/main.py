"""Command line: ``stereorepro <command> ...`` (also ``python -m stereorepro``).

Each command module of this package registers its sub-commands through ``register(subparsers)``; this file
collects them (the shared argument types are in :mod:`._args`) and applies the error policy, once:

* a mistake the user can fix (bad file, bad option: :class:`~stereorepro.errors.UserError`, raised by the
  commands; argparse's own errors) → one line on stderr naming the file / key / argument, exit code 2;
* the machine refusing a write or a read (disk full, quota, permissions, read-only filesystem: an ``OSError``
  with one of :data:`USER_ERRNOS`) → one line naming the path, exit code 2;
* anything else is an internal error: a traceback, exit code 1.

The commands write through :mod:`stereorepro.io.atomic`, so none of these leaves a partial file behind.
"""

from __future__ import annotations

import argparse
import errno
import sys

from ..errors import UserError
from ._args import parse_resolution  # noqa: F401  (re-exported: the shared argument types live in _args)


class _Parser(argparse.ArgumentParser):
    """argparse with the policy's one-line errors (``PROG: error: argument --x: ...``, exit code 2) instead of
    the usage block; ``--help`` shows the usage."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="stereorepro", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    from . import demo, experiment, render, reproject  # each imports its heavy dependencies inside its commands

    for module in (render, experiment, reproject, demo):
        module.register(sub)
    return parser


#: errno values of an OSError that are the machine's answer to the user, not a bug: exit 2 with one line.
USER_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.EFBIG,
                         errno.ENAMETOOLONG, errno.ENOTDIR, errno.EISDIR, errno.ENOENT, errno.EEXIST})


def _os_error_line(e: OSError) -> str:
    what = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded"}.get(e.errno)
    where = e.filename if e.filename is not None else "a file"
    return f"{where}: {what or e.strerror or e}"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # a bad option (exit 2, one line) or --help (0): returned like the commands' codes
        return e.code if isinstance(e.code, int) else 2
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"stereorepro {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno not in USER_ERRNOS:
            raise
        print(f"stereorepro {args.command}: error: {_os_error_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
