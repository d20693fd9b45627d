"""The package's exceptions: one base class, :class:`StereoreproError`, that users can catch.

Each concrete error also derives from the built-in it refines (``ValueError``, or ``TypeError`` for
:class:`ParameterTypeError`), so code written against the built-ins keeps working. Messages name what was wrong and
where: the argument, the file, the frame or the key.

Examples:
    >>> import stereorepro
    >>> try:
    ...     stereorepro.TemporalReprojection(0.03, 0.2, alpha=1.5)  # alpha must be in (0, 1]
    ... except stereorepro.StereoreproError as e:
    ...     print(type(e).__name__, isinstance(e, ValueError))
    ParameterError True
    >>> try:
    ...     stereorepro.TemporalReprojection(0.03, 0.2, alpha=1.5)
    ... except ValueError:  # code written against the built-in catches it too
    ...     print("caught")
    caught
"""

from __future__ import annotations

__all__ = [
    "StereoreproError",
    "ShapeError",
    "ParameterError",
    "ParameterTypeError",
    "SceneError",
    "SequenceError",
    "CameraError",
    "UserError",
    "MissingDependencyError",
]


class StereoreproError(Exception):
    """Base class of every error this package raises on purpose.

    Examples:
        >>> from stereorepro.errors import StereoreproError
        >>> try:
        ...     raise StereoreproError("not a scene file")
        ... except Exception as e:
        ...     print(type(e).__name__, isinstance(e, Exception))
        StereoreproError True
    """


class ShapeError(StereoreproError, ValueError):
    """A tensor's rank, shape or device does not fit the operation, or tensors that go together disagree.

    Examples:
        >>> from stereorepro.errors import ShapeError
        >>> try:
        ...     raise ShapeError("depth must be (B, 1, H, W)")
        ... except ValueError as e:
        ...     print(type(e).__name__, isinstance(e, ValueError))
        ShapeError True
    """


class ParameterError(StereoreproError, ValueError):
    """A parameter's value is outside what the operation accepts: a threshold that is negative or NaN, ``alpha``
    NaN or ±inf, ``max_history`` below 1 or NaN, a finite number beyond float32's range, a name that is not one of
    the choices (sampling, backend, mode), or arguments that go together given alone (``motion_world`` without
    ``motion``).

    Examples:
        >>> from stereorepro.errors import ParameterError
        >>> try:
        ...     raise ParameterError("alpha must be in (0, 1]")
        ... except ValueError as e:
        ...     print(type(e).__name__, isinstance(e, ValueError))
        ParameterError True
    """


class ParameterTypeError(StereoreproError, TypeError):
    """An argument of the wrong kind: an integer or bool tensor where a floating one is needed, a string where a
    number or a tensor is, a missing input the configuration requires.

    Examples:
        >>> from stereorepro.errors import ParameterTypeError
        >>> try:
        ...     raise ParameterTypeError("depth must be a floating tensor")
        ... except TypeError as e:
        ...     print(type(e).__name__, isinstance(e, TypeError))
        ParameterTypeError True
    """


class SceneError(StereoreproError, ValueError):
    """A scene file is missing, malformed or inconsistent (the message names the file and the key).

    Examples:
        >>> from stereorepro.errors import SceneError
        >>> try:
        ...     raise SceneError("scene.json: missing key 'camera'")
        ... except ValueError as e:
        ...     print(type(e).__name__, isinstance(e, ValueError))
        SceneError True
    """


class SequenceError(StereoreproError, ValueError):
    """A malformed frame-sequence directory; the message names the file (and the frame/key).

    Examples:
        >>> from stereorepro.errors import SequenceError
        >>> try:
        ...     raise SequenceError("frame_0003.npz: missing key 'depth'")
        ... except ValueError as e:
        ...     print(type(e).__name__, isinstance(e, ValueError))
        SequenceError True
    """


class CameraError(StereoreproError, ValueError):
    """A camera matrix that breaks the conventions: non-finite, not pinhole, singular, not rigid, or mirrored.

    Examples:
        >>> from stereorepro.errors import CameraError
        >>> try:
        ...     raise CameraError("cam_from_world is mirrored")
        ... except ValueError as e:
        ...     print(type(e).__name__, isinstance(e, ValueError))
        CameraError True
    """


class UserError(StereoreproError):
    """A command-line mistake (bad file, bad option): printed as one line without a traceback, exit code 2.

    Examples:
        >>> from stereorepro.errors import UserError, StereoreproError
        >>> try:
        ...     raise UserError("no such file: scene.json")
        ... except StereoreproError as e:
        ...     print(type(e).__name__, isinstance(e, StereoreproError))
        UserError True
    """


class MissingDependencyError(StereoreproError, ImportError):
    """An optional dependency is not installed; the message names the package and the extra that brings it
    (``pip install 'stereorepro[render]'``). Raised at first use, by :func:`stereorepro._extras.require`.

    Attributes:
        name: the module that could not be imported (as :class:`ImportError`); ``extra``: the extra to install.

    Examples:
        >>> from stereorepro.errors import MissingDependencyError
        >>> try:
        ...     raise MissingDependencyError("embreex is missing", name="embreex", extra="render")
        ... except ImportError as e:
        ...     print(type(e).__name__, e.name, e.extra)
        MissingDependencyError embreex render
    """

    def __init__(self, message: str, *, name: str, extra: str):
        super().__init__(message, name=name)
        self.extra = extra
