"""The one backend rule, used by the reprojection ops and by the path tracer.

Every implementation choice is between a **reference** path (torch for the ops, numpy for the tracer: the
definition of the results) and the **native** accelerator in ``stereorepro._core`` (the same results, parity-
tested). A request is one of:

* ``"auto"``: native when the caller finds nothing against it, else the reference;
* ``"native"``: native, or RuntimeError saying why not;
* ``"reference"``, or its synonyms ``"torch"`` and ``"numpy"``: the reference path.

The reprojection ops accept :data:`OP_NAMES` and the path tracer :data:`TRACER_NAMES` (each names its reference
path after its library). The environment variable ``STEREOREPRO_BACKEND``, when set, overrides the request of every
op and tracer alike (case-insensitive, any of :data:`NAMES`).
"""

from __future__ import annotations

import os
from typing import Callable

from .errors import ParameterError

__all__ = ["ENV_VAR", "NAMES", "OP_NAMES", "REFERENCE_NAMES", "TRACER_NAMES", "check", "resolve"]

ENV_VAR = "STEREOREPRO_BACKEND"
#: Names of the reference path (the ops call it torch, the tracer numpy).
REFERENCE_NAMES = ("reference", "torch", "numpy")
#: Every name the environment variable accepts.
NAMES = ("auto", "native") + REFERENCE_NAMES
#: The ``backend`` argument of the reprojection ops and modules.
OP_NAMES = ("auto", "torch", "native")
#: The ``backend`` argument of the path tracer (``"torch"`` also names its numpy reference).
TRACER_NAMES = ("auto", "numpy", "native", "torch")


def check(backend: str, choices: tuple[str, ...], who: str = "") -> str:
    """``backend`` itself when it is one of ``choices``, else ValueError (``who`` prefixes the message)."""
    if backend not in choices:
        raise ParameterError(f"{who}backend must be one of {choices}, got {backend!r}")
    return backend


def _canonical(name: str) -> str:
    return "reference" if name in REFERENCE_NAMES else name


def resolve(
    backend: str,
    choices: tuple[str, ...],
    why_not_native: Callable[[], str | None],
    who: str = "",
    reference_only: bool = False,
) -> str:
    """Resolve a backend request to ``"reference"`` or ``"native"``.

    Args:
        backend: the caller's request, one of ``choices``.
        choices: the names this caller accepts (ValueError for others).
        why_not_native: returns why native cannot run this call, or None when it can (called only when needed).
        who: prefix of error messages (e.g. ``"PathTracer: "``).
        reference_only: the call must take the reference path whatever was asked (tracing, ONNX export); the
            request and the environment are still validated.

    Raises:
        ValueError: unknown name in ``backend`` or in ``STEREOREPRO_BACKEND``.
        RuntimeError: native asked for (argument or environment) but ``why_not_native`` gives a reason.
    """
    check(backend, choices, who)
    env = os.environ.get(ENV_VAR, "").strip().lower()
    if env:
        if env not in NAMES:
            raise ParameterError(f"{ENV_VAR} must be one of {NAMES}, got {env!r}")
        backend = env
    backend = _canonical(backend)
    if backend == "reference" or reference_only:
        return "reference"
    why = why_not_native()
    if why is None:
        return "native"
    if backend == "native":
        source = f" (from {ENV_VAR})" if env else ""
        raise RuntimeError(f"{who}backend='native'{source} is not possible: {why}")
    return "reference"
