"""Flat tensor arguments → :class:`~stereorepro.reproject.view.View`: what the modules' ``forward`` (plain tensors,
for ONNX), the deprecated flat forms of the ops and the flat-argument drivers share. The checks run with the flat argument names, so errors
name what the caller passed (``src_depth``, ``prev_K[0]``), then the views are built without checking again.
"""

from __future__ import annotations

import warnings

from torch import Tensor

from .._checks import (
    STEREO_NAMES,
    TEMPORAL_NAMES,
    check_floating,
    check_motion,
    check_reprojection_inputs,
    check_shape,
    tracing,
)
from ..errors import ParameterTypeError
from .view import History, View

__all__ = ["stereo_views", "temporal_views", "warn_flat_form", "given_keywords", "reject_extra_arguments"]


def stereo_views(
    src_values: Tensor, src: tuple[Tensor, ...], dst: tuple[Tensor, ...], names: dict = STEREO_NAMES, check: bool = True
) -> tuple[View, View]:
    """Check a source image ``src_values`` (B, C, Hs, Ws) with the source and destination G-buffers and cameras
    ``(depth, normal, K, cam_from_world)`` under the flat names ``names``; return the two views."""
    if check:
        check_reprojection_inputs(src_values, *src, *dst, names)
    return View.unchecked(*src), View.unchecked(*dst)


def temporal_views(
    current_color: Tensor,
    current: tuple[Tensor, ...],
    history: History,
    previous: tuple[Tensor, ...],
    motion: tuple[Tensor | None, Tensor | None] = (None, None),
) -> tuple[View, View]:
    """Check a temporal step's flat inputs under the flat names (``current_color``, ``depth``, ..., ``history_color``,
    ``prev_depth``, ..., ``motion``); return (this frame's view with its motion, the previous frame's view)."""
    depth, normal = current[:2]
    bind: dict = {}
    check_shape(current_color, ["B", "3", "H", "W"], "current_color", bind)
    check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    bind_p: dict = {"B": bind.get("B")} if bind else {}
    check_shape(history.color, ["B", "3", "H", "W"], "history_color", bind_p)
    check_shape(history.length, ["B", "1", "H", "W"], "history_len", bind_p)
    check_floating(current_color, "current_color")
    check_floating(history.length, "history_len")
    check_reprojection_inputs(history.color, *previous, *current, TEMPORAL_NAMES)
    if not tracing():
        check_motion(*motion, depth, "motion", "motion_world")
    return View.unchecked(*current, *motion), View.unchecked(*previous)


def warn_flat_form(name: str, new: str) -> None:
    """The DeprecationWarning of a flat-argument call of ``name``, naming the ``new`` call (pointing at the caller
    of the public function)."""
    warnings.warn(
        f"{name} with flat tensor arguments is deprecated and will be removed in the next release: call {new}",
        DeprecationWarning,
        stacklevel=3,
    )


def given_keywords(**pairs) -> dict:
    """The keyword arguments of a new-form call that differ from their defaults ``name=(value, default)``, to
    forward to a flat (deprecated) call without clashing with its positional arguments."""
    return {k: v for k, (v, default) in pairs.items() if v is not default and v != default}


def reject_extra_arguments(op: str, args: tuple, kwargs: dict) -> None:
    """ParameterTypeError when a View-form call of ``op`` got arguments only its flat form takes."""
    if args or kwargs:
        extra = [f"{len(args)} more positional argument(s)"] if args else []
        raise ParameterTypeError(f"{op}: unexpected arguments with View inputs: {', '.join(extra + sorted(kwargs))}")
