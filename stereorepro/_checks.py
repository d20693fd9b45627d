"""Boundary checks with errors that name the argument, the expected and the actual shape.

Checks run only at public entry points. They are skipped while tracing for ONNX export (the graph must not
carry Python-side asserts) but shapes are already fixed by then.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .errors import ShapeError

__all__ = ["check_shape", "check_floating", "check_device", "check_camera", "check_same_hw", "check_sampling",
           "check_reprojection_inputs", "tracing", "ShapeError", "SAMPLINGS", "STEREO_NAMES", "TEMPORAL_NAMES"]

#: Tap sampling of the reprojection: 2×2 bilinear taps (the paper's) or the one nearest tap.
SAMPLINGS = ("bilinear", "nearest")

#: Argument names of the reprojection roles, as the stereo and the temporal functions call them.
STEREO_NAMES = dict(src_values="src_color", src_depth="src_depth", src_normal="src_normal", src="src",
                    dst_depth="dst_depth", dst_normal="dst_normal", dst="dst")
TEMPORAL_NAMES = dict(src_values="history_color", src_depth="prev_depth", src_normal="prev_normal", src="prev",
                      dst_depth="depth", dst_normal="normal", dst="current")


def tracing() -> bool:
    """True while torch.jit traces, torch.compile compiles or ONNX exports: the graph must be plain torch ops (no
    data-dependent Python checks, no native kernels). The one definition the package uses."""
    return torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


_tracing = tracing  # the name the package used before


def _skip(is_tracing: bool | None) -> bool:
    """Whether a check is skipped: ``is_tracing`` as the caller found it (callers running many checks ask once:
    the question costs microseconds), or asked now."""
    return tracing() if is_tracing is None else is_tracing


def check_sampling(sampling: str) -> str:
    """``sampling`` if it is one of :data:`SAMPLINGS`, else ValueError naming the choices."""
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    return sampling


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


def check_reprojection_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world,
                              dst_depth, dst_normal, dst_K, dst_cam_from_world, names: dict) -> None:
    """Boundary checks of a backward reprojection; ``names`` maps roles to the caller's argument names
    (:data:`STEREO_NAMES`, :data:`TEMPORAL_NAMES`) so errors name what the user passed."""
    if tracing():
        return
    tr = False  # asked once for all the checks below
    bind_src: dict = {}
    check_shape(src_values, ["B", "C", "H", "W"], names["src_values"], bind_src, tr)
    check_shape(src_depth, ["B", "1", "H", "W"], names["src_depth"], bind_src, tr)
    check_shape(src_normal, ["B", "3", "H", "W"], names["src_normal"], bind_src, tr)
    bind_b = {"B": bind_src["B"]} if "B" in bind_src else {}
    check_shape(dst_depth, ["B", "1", "H", "W"], names["dst_depth"], dict(bind_b), tr)
    check_shape(dst_normal, ["B", "3", "H", "W"], names["dst_normal"], {**bind_b, "H": dst_depth.shape[-2],
                                                                         "W": dst_depth.shape[-1]}, tr)
    check_camera(src_K, src_cam_from_world, names["src"], dict(bind_b), tr)
    check_camera(dst_K, dst_cam_from_world, names["dst"], dict(bind_b), tr)
    for role, t in (("src_values", src_values), ("src_depth", src_depth), ("src_normal", src_normal),
                    ("dst_depth", dst_depth), ("dst_normal", dst_normal)):
        check_floating(t, names[role], tr)
    check_device({names["src_values"]: src_values, names["src_depth"]: src_depth,
                  names["src_normal"]: src_normal, names["src"] + "_K": src_K,
                  names["src"] + "_cam_from_world": src_cam_from_world, names["dst_depth"]: dst_depth,
                  names["dst_normal"]: dst_normal, names["dst"] + "_K": dst_K,
                  names["dst"] + "_cam_from_world": dst_cam_from_world}, "reprojection", tr)
