"""Boundary checks with errors that name the argument, the expected and the actual shape.

Checks run only at public entry points. They are skipped while tracing for ONNX export (the graph must not
carry Python-side asserts) but shapes are already fixed by then.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

__all__ = ["check_shape", "check_floating", "check_camera", "check_same_hw", "ShapeError"]


class ShapeError(ValueError):
    """A tensor's rank, shape, dtype or device does not fit the operation."""


def _tracing() -> bool:
    """True while torch.jit traces, torch.compile compiles or ONNX exports: the graph must be plain torch ops (no
    data-dependent Python checks, no native kernels). The one definition the package uses."""
    return torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


def _skip(tracing: bool | None) -> bool:
    """Whether a check is skipped: ``tracing`` as the caller found it (callers running many checks ask once: the
    question costs microseconds), or asked now."""
    return _tracing() if tracing is None else tracing


def check_shape(x, shape: Sequence[str], name: str, bind: dict | None = None, tracing: bool | None = None) -> dict:
    """Check ``x`` against a symbolic shape such as ``["B", "3", "H", "W"]``.

    Digits must match exactly; letters bind to the first size seen (in ``bind``, shared across calls so that
    e.g. all ``H`` agree). Returns the binding. ``tracing``: see :func:`_skip` (all checks take it).
    """
    bind = {} if bind is None else bind
    if _skip(tracing):
        return bind
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor of shape ({', '.join(shape)}), got {type(x).__name__}")
    if x.dim() != len(shape):
        raise ShapeError(f"{name}: expected {len(shape)}-D tensor of shape ({', '.join(shape)}), "
                         f"got {x.dim()}-D with shape {tuple(x.shape)}")
    for i, (want, got) in enumerate(zip(shape, x.shape)):
        if want.isdigit():
            if int(want) != got:
                raise ShapeError(f"{name}: expected shape ({', '.join(shape)}), got {tuple(x.shape)} "
                                 f"(dim {i} must be {want})")
        else:
            if want in bind and bind[want] != got:
                raise ShapeError(f"{name}: expected shape ({', '.join(shape)}) with {want}={bind[want]}, "
                                 f"got {tuple(x.shape)}")
            bind.setdefault(want, got)
    return bind


def check_floating(x: Tensor, name: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def check_device(tensors: dict, name: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    devices = {k: v.device for k, v in tensors.items() if isinstance(v, Tensor)}
    if len(set(devices.values())) > 1:
        raise ShapeError(f"{name}: all tensors must be on one device, got "
                         + ", ".join(f"{k}={d}" for k, d in devices.items()))


def check_camera(K: Tensor, cam_from_world: Tensor, name: str, bind: dict | None = None,
                 tracing: bool | None = None) -> dict:
    tracing = _skip(tracing)
    bind = check_shape(K, ["B", "3", "3"], f"{name} K", bind, tracing)
    bind = check_shape(cam_from_world, ["B", "4", "4"], f"{name} cam_from_world", bind, tracing)
    check_floating(K, f"{name} K", tracing)
    check_floating(cam_from_world, f"{name} cam_from_world", tracing)
    return bind


def check_same_hw(a: Tensor, b: Tensor, name_a: str, name_b: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    if a.shape[-2:] != b.shape[-2:]:
        raise ShapeError(f"{name_a} and {name_b} must have the same H, W: got {tuple(a.shape)} and {tuple(b.shape)}")
