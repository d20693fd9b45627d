"""Command line: ``stereorepro <command> ...`` (also ``python -m stereorepro``).

Each command module of this package registers its sub-commands through ``register(subparsers)``; this file
collects them (the shared argument types are in :mod:`._args`) and applies the error policy, once:

* a mistake the user can fix (bad file, bad option: :class:`~stereorepro.errors.UserError`, raised by the
  commands; argparse's own errors) → one line on stderr naming the file / key / argument, exit code 2;
* a command whose optional dependencies are not installed (:class:`~stereorepro.errors.MissingDependencyError`)
  → one line naming the extra to install, exit code 2;
* the machine refusing a write or a read (disk full, quota, permissions, read-only filesystem: an ``OSError``
  with one of :data:`USER_ERRNOS`) → one line naming the path, exit code 2;
* anything else is an internal error: a traceback, exit code 1.

The commands write through :mod:`stereorepro.io.atomic`, so none of these leaves a partial file behind.

Help is plain text (:class:`_HelpFormatter` drops reST markup) and every option shows its default
(:func:`_show_defaults`).
"""

from __future__ import annotations

import argparse
import errno
import re
import sys

from .._version import __version__
from ..errors import MissingDependencyError, UserError
from ._args import parse_resolution  # noqa: F401  (re-exported: the shared argument types live in _args)

DESCRIPTION = (
    "stereorepro: spatiotemporal sample reprojection for stereoscopic path tracing (also: python -m stereorepro)."
)
EPILOG = "Run 'stereorepro COMMAND --help' for a command's options and their defaults."
#: reST / Markdown markup in help texts: ``literal``, `literal`, :role:`target`.
_MARKUP = re.compile(r":[a-z]+:`~?([^`]*)`|``([^`]*)``|`([^`]*)`")


def _plain(text: str) -> str:
    """``text`` without reST markup (the content of each marked span kept)."""
    return _MARKUP.sub(lambda m: next(g for g in m.groups() if g is not None), text)


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, printing descriptions and help texts as plain text."""

    def _format_text(self, text: str) -> str:
        return super()._format_text(_plain(text))

    def _expand_help(self, action) -> str:
        return _plain(super()._expand_help(action))


class _Parser(argparse.ArgumentParser):
    """argparse with the policy's one-line errors (``PROG: error: argument --x: ...``, exit code 2) instead of
    the usage block; ``--help`` shows the usage. Sub-command parsers are of this class too."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


class _VersionAction(argparse.Action):
    """``--version``: the package version and whether the native core is installed, then exit 0."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            from .. import _core  # noqa: F401

            native = "native core: built"
        except ImportError:
            native = "native core: not built (torch / numpy paths)"
        print(f"stereorepro {__version__} ({native})")
        parser.exit(0)


def _shown_default(action: argparse.Action) -> str | None:
    """How an option's default reads in its help, or None where there is nothing to show (no default, a flag)."""
    d = action.default
    if d is None or d is argparse.SUPPRESS or action.nargs == 0 or not action.option_strings:
        return None
    if isinstance(d, tuple) and len(d) == 2 and all(isinstance(v, int) for v in d):
        return f"{d[0]}x{d[1]}"  # a resolution
    if isinstance(d, (tuple, list)):
        return ",".join(str(v) for v in d) or "none"
    return str(d)


def _show_defaults(parser: argparse.ArgumentParser) -> None:
    """Append ``(default: X)`` to the help of every option of ``parser`` and its sub-commands that has a default
    its help does not already state."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in set(action.choices.values()):
                _show_defaults(sub)
            continue
        shown = _shown_default(action)
        text = action.help or ""
        if shown is None or text is argparse.SUPPRESS or "default" in text.lower():
            continue
        shown = shown.replace("%", "%%")
        action.help = f"{text} (default: {shown})" if text else f"default: {shown}"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="stereorepro", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument(
        "--version", action=_VersionAction, help="print the version and whether the native core is built, and exit"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    # each command module imports its heavy dependencies inside its commands
    from . import demo, experiment, render, reproject

    for module in (render, experiment, reproject, demo):
        module.register(sub)
    _show_defaults(parser)
    return parser


#: errno values of an OSError that are the machine's answer to the user, not a bug: exit 2 with one line.
USER_ERRNOS = frozenset(
    {
        errno.ENOSPC,
        errno.EDQUOT,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.EFBIG,
        errno.ENAMETOOLONG,
        errno.ENOTDIR,
        errno.EISDIR,
        errno.ENOENT,
        errno.EEXIST,
    }
)


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
    except (UserError, MissingDependencyError) as e:
        print(f"stereorepro {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno not in USER_ERRNOS:
            raise
        print(f"stereorepro {args.command}: error: {_os_error_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
