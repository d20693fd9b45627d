"""The command line (``stereorepro``): :func:`main` dispatches to the command modules of this package
(``render``: scenes and render; ``reproject``: reproject and export-sequence; ``experiment``; ``demo``)."""

from ..errors import UserError
from ._args import parse_resolution
from .main import build_parser, main

__all__ = ["main", "build_parser", "parse_resolution", "UserError"]
