"""Native (C++/OpenMP) twins of the hard float32 reprojection on CPU, and the backend selection.

The torch functions in :mod:`stereorepro.reproject` are the reference; the kernels in ``stereorepro._core``
(``cpp_ext/src/reproject.cpp``) do the same maths in one fused pass per pixel and are parity-tested against them
(``tests/test_native.py``). The package imports and works without ``_core``: :func:`available` is then False and
every ``backend="auto"`` call takes the torch path.

Backend selection (:func:`select_backend`), used by :func:`~stereorepro.reproject.stereo_reproject`,
:func:`~stereorepro.reproject.temporal_reproject` and their modules:

* the environment variable ``STEREOREPRO_BACKEND`` (``torch`` | ``native`` | ``auto``), when set, overrides the
  ``backend`` argument;
* ``"torch"`` always runs torch;
* ``"auto"`` runs native when :func:`native_unsupported` finds nothing against it: ``_core`` built, every tensor on
  the CPU, image tensors float32, hard tests (``soft=False``), no autograd (grad disabled or nothing requires
  grad), and not tracing / exporting / compiling;
* ``"native"`` runs native and raises :class:`RuntimeError` saying why when it is not possible;
* tracing, ONNX export and ``torch.compile`` always use torch, whatever was asked (the graph must be torch ops).

Inputs are made contiguous float32 once, here (``x.contiguous()``), then cross to C++ without copies; outputs are
allocated with ``torch.empty`` and written in place (``.noconvert()`` on the C++ side, so a wrong layout raises
instead of silently writing into a temporary copy).
"""

from __future__ import annotations

import os
from typing import Iterable

import torch
from torch import Tensor

from ._checks import _tracing

try:  # optional: the package works without the compiled core
    from . import _core
except ImportError:  # pragma: no cover - depends on the build
    _core = None

__all__ = ["BACKENDS", "ENV_VAR", "available", "native_unsupported", "select_backend", "native_backward_reproject",
           "native_temporal_reproject"]

BACKENDS = ("auto", "torch", "native")
ENV_VAR = "STEREOREPRO_BACKEND"


def available() -> bool:
    """True when ``stereorepro._core`` is importable and has the reprojection kernels."""
    return _core is not None and hasattr(_core, "reproject") and hasattr(_core, "temporal_reproject")


def check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend


def native_unsupported(images: Iterable[Tensor], others: Iterable = (), soft: bool = False) -> str | None:
    """Why the native kernels cannot run these inputs, or None when they can.

    Args:
        images: image tensors (colours, depths, normals, history length): must be float32.
        others: other inputs (cameras, thresholds, alpha): only device and autograd are checked.
        soft: soft accept tests (torch only).
    """
    images = list(images)
    tensors = images + [x for x in others if isinstance(x, Tensor)]
    if not available():
        return "the native core stereorepro._core (with `reproject`) is not built or not importable"
    if _tracing():
        return "tracing / ONNX export / torch.compile need the torch path"
    if soft:
        return "soft=True (differentiable thresholds) is implemented in torch only"
    devices = {str(t.device) for t in tensors if t.device.type != "cpu"}
    if devices:
        return f"the native kernels run on the CPU only, got tensors on {sorted(devices)}"
    dtypes = {t.dtype for t in images if t.dtype != torch.float32}
    if dtypes:
        return f"the native kernels compute in float32 only, got images of dtype {sorted(map(str, dtypes))}"
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return "an input requires grad (autograd needs the torch path; use torch.no_grad() for native)"
    return None


def select_backend(backend: str, images: Iterable[Tensor], others: Iterable = (), soft: bool = False) -> str:
    """Resolve ``backend`` (``"auto"`` | ``"torch"`` | ``"native"``) to ``"torch"`` or ``"native"``.

    ``STEREOREPRO_BACKEND`` overrides ``backend`` when set. Tracing/export always gives ``"torch"``. Raises
    RuntimeError when ``"native"`` is asked for and :func:`native_unsupported` gives a reason.
    """
    check_backend(backend)
    env = os.environ.get(ENV_VAR, "").strip().lower()
    if env == "numpy":  # the variable is shared with the tracer, whose reference path is "numpy"
        env = "torch"
    if env:
        if env not in BACKENDS:
            raise ValueError(f"{ENV_VAR} must be one of {BACKENDS} (or 'numpy' = 'torch'), got {env!r}")
        backend = env
    if backend == "torch" or _tracing():
        return "torch"
    why = native_unsupported(images, others, soft)
    if why is None:
        return "native"
    if backend == "native":
        source = f" (from {ENV_VAR})" if env else ""
        raise RuntimeError(f"backend='native'{source} is not possible: {why}")
    return "torch"


# --- kernels ---------------------------------------------------------------------------------------------------
def _f32_contiguous(x: Tensor, name: str) -> Tensor:
    if x.device.type != "cpu":
        raise RuntimeError(f"native: {name} must be on the CPU, got {x.device}")
    if x.dtype != torch.float32:
        raise TypeError(f"native: {name} must be float32, got {x.dtype} (use backend='torch' for other dtypes)")
    return x.contiguous()  # the one visible copy, only when x is not C-contiguous


def _cameras(src_K, src_cam_from_world, dst_K, dst_cam_from_world) -> tuple[Tensor, ...]:
    """(P, kt, M, t, Ks_inv) as contiguous float32 (B, 9) / (B, 3), composed exactly as the torch path does."""
    from .reproject import _compose_cameras

    B = src_K.shape[0]
    M, t, P, kt, Ks_inv = _compose_cameras(src_K, src_cam_from_world, dst_K, dst_cam_from_world, torch.float32)
    return tuple(x.reshape(B, -1).contiguous().cpu() for x in (P, kt, M, t, Ks_inv))


def _squared_thresholds(position_threshold, normal_threshold) -> tuple[float, float]:
    """float32 thr·thr of both thresholds, squared by the torch path's own helper."""
    from .reproject import _squared_thresholds as squared

    thr2 = squared(position_threshold, normal_threshold, torch.float32, "cpu").detach().view(2)
    return float(thr2[0]), float(thr2[1])


def _check_native_options(sampling: str, soft: bool) -> None:
    from .reproject import _SAMPLINGS

    if sampling not in _SAMPLINGS:
        raise ValueError(f"sampling must be one of {_SAMPLINGS}, got {sampling!r}")
    if soft:
        raise ValueError("native: soft=True is implemented in torch only (use backend='torch')")
    if not available():
        raise RuntimeError("native: stereorepro._core with the reprojection kernels is not available")


def native_backward_reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    src_K: Tensor,
    src_cam_from_world: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    dst_K: Tensor,
    dst_cam_from_world: Tensor,
    position_threshold,
    normal_threshold,
    sampling: str = "bilinear",
    soft: bool = False,
    temperature: float = 0.1,
    check: bool = True,
    want_confidence: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Native twin of :func:`stereorepro.reproject.backward_reproject` (hard tests, float32 images, CPU).

    Same arguments and returns: values (B, C, H, W) float32, valid (B, 1, H, W) bool, reason (B, 1, H, W) uint8,
    confidence (B, 1, H, W) float32 (None with ``want_confidence=False``, which saves writing it).
    ``temperature`` is accepted for signature parity and unused (hard tests).
    """
    from .reproject import _STEREO_NAMES, _check_inputs

    _check_native_options(sampling, soft)
    if check:
        _check_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world,
                      dst_depth, dst_normal, dst_K, dst_cam_from_world, dict(_STEREO_NAMES, src_values="src_values"))
    sv = _f32_contiguous(src_values, "src_values")
    sd = _f32_contiguous(src_depth, "src_depth")
    sn = _f32_contiguous(src_normal, "src_normal")
    dd = _f32_contiguous(dst_depth, "dst_depth")
    dn = _f32_contiguous(dst_normal, "dst_normal")
    P, kt, M, t, Ks_inv = _cameras(src_K, src_cam_from_world, dst_K, dst_cam_from_world)
    B, C = sv.shape[:2]
    H, W = dd.shape[-2:]
    values = torch.empty(B, C, H, W, dtype=torch.float32)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool)
    reason = torch.empty(B, 1, H, W, dtype=torch.uint8)
    confidence = torch.empty(B, 1, H, W, dtype=torch.float32) if want_confidence else None
    _core.reproject(sv, sd, sn, P, kt, M, t, Ks_inv, dd, dn, *_squared_thresholds(position_threshold, normal_threshold),
                    sampling == "bilinear", values, valid, reason, confidence)
    return values, valid, reason, confidence


def _blend_scalars(alpha, max_history) -> tuple[float, float]:
    """alpha clamped to [0, 1] and max_history, as float32 values (as :func:`temporal_blend` computes them)."""
    from .reproject import _as_scalar

    like = torch.empty((), dtype=torch.float32)
    a = _as_scalar(alpha.detach() if isinstance(alpha, Tensor) else alpha, like).clamp(0.0, 1.0)
    return float(a), float(_as_scalar(max_history, like))


def native_temporal_reproject(
    current_color: Tensor,
    depth: Tensor,
    normal: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    prev_depth: Tensor,
    prev_normal: Tensor,
    prev_K: Tensor,
    prev_cam_from_world: Tensor,
    position_threshold,
    normal_threshold,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
    sampling: str = "bilinear",
    soft: bool = False,
    temperature: float = 0.1,
) -> tuple[Tensor, Tensor, Tensor]:
    """Native twin of :func:`stereorepro.reproject.temporal_reproject` (hard tests, float32 images, CPU).

    One fused pass (``_core.temporal_reproject``): warp [history_color, history_len] and blend with the current
    frame. Arguments are assumed checked by the caller (:func:`~stereorepro.reproject.temporal_reproject` checks
    them before dispatching here). Returns color (B, 3, H, W), history_len (B, 1, H, W) float32, valid
    (B, 1, H, W) bool.
    """
    _check_native_options(sampling, soft)
    cur = _f32_contiguous(current_color, "current_color")
    hc = _f32_contiguous(history_color, "history_color")
    hl = _f32_contiguous(history_len, "history_len")
    pd = _f32_contiguous(prev_depth, "prev_depth")
    pn = _f32_contiguous(prev_normal, "prev_normal")
    dd = _f32_contiguous(depth, "depth")
    dn = _f32_contiguous(normal, "normal")
    P, kt, M, t, Ks_inv = _cameras(prev_K, prev_cam_from_world, K, cam_from_world)
    a, cap = _blend_scalars(alpha, max_history)
    B, C = hc.shape[:2]
    H, W = dd.shape[-2:]
    color = torch.empty(B, C, H, W, dtype=torch.float32)
    n_out = torch.empty(B, 1, H, W, dtype=torch.float32)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool)
    _core.temporal_reproject(cur, hc, hl, pd, pn, P, kt, M, t, Ks_inv, dd, dn,
                             *_squared_thresholds(position_threshold, normal_threshold), sampling == "bilinear", a,
                             bool(warmup), cap, color, n_out, valid)
    return color, n_out, valid


def _temporal_two_pass(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
                       prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold, alpha=0.2,
                       warmup=True, max_history=255.0, sampling="bilinear"):
    """The alternative to the fused kernel, kept for benchmarks: ``reproject`` with C = 4 ([colour, length],
    concatenated here), then the existing ``_core.temporal_blend``. Slower (an extra copy and an intermediate
    write); see the module notes in ``tests/test_native.py``."""
    values = torch.cat([history_color, history_len], 1)
    warped, valid, _, _ = native_backward_reproject(values, prev_depth, prev_normal, prev_K, prev_cam_from_world,
                                                    depth, normal, K, cam_from_world, position_threshold,
                                                    normal_threshold, sampling, check=False)
    a, cap = _blend_scalars(alpha, max_history)
    cur = _f32_contiguous(current_color, "current_color")
    color = torch.empty_like(cur)
    n_out = torch.empty_like(valid, dtype=torch.float32)
    hist, hlen = warped[:, :-1].contiguous(), warped[:, -1:].contiguous()
    _core.temporal_blend(cur, hist, hlen, valid, a, bool(warmup), cap, color, n_out)
    return color, n_out, valid
