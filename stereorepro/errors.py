"""The package's exceptions: one base class, :class:`StereoreproError`, that users can catch.

Each concrete error also derives from the built-in it refines (``ValueError``), so code written against the
built-ins keeps working. Messages name what was wrong and where: the argument, the file, the frame or the key.
"""

from __future__ import annotations

__all__ = ["StereoreproError", "ShapeError", "SceneError", "SequenceError", "CameraError", "UserError"]


class StereoreproError(Exception):
    """Base class of every error this package raises on purpose."""


class ShapeError(StereoreproError, ValueError):
    """A tensor's rank, shape, dtype or device does not fit the operation."""


class SceneError(StereoreproError, ValueError):
    """A scene file is missing, malformed or inconsistent (the message names the file and the key)."""


class SequenceError(StereoreproError, ValueError):
    """A malformed frame-sequence directory; the message names the file (and the frame/key)."""


class CameraError(StereoreproError, ValueError):
    """A camera matrix that breaks the conventions: non-finite, not pinhole, singular, not rigid, or mirrored."""


class UserError(StereoreproError):
    """A command-line mistake (bad file, bad option): printed as one line without a traceback, exit code 2."""
