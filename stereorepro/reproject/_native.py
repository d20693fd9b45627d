"""The native (C++/OpenMP) reprojection kernels of ``stereorepro._core``, wrapped for torch tensors. A leaf: it
imports nothing from the rest of the package but the compiled core.

The kernels (``cpp_ext/src/reproject.cpp``) compute what the torch reference computes, hard tests in float32 on
the CPU, in one fused pass per pixel; they take the warp already composed (:func:`stereorepro.camera.compose_warp`)
and the squared thresholds. Which calls may run here is decided by the op layer
(:mod:`stereorepro.reproject.functional`). Image inputs are float32 or float16, each on its own (a real-time
engine's RGBA16F colour and normals are read as they are, widened exactly in the kernel: no conversion pass); they
are made contiguous once, here, then cross to C++ without copies; outputs are allocated with ``torch.empty`` and
written in place (``.noconvert()`` on the C++ side, so a wrong layout raises instead of silently writing into a
temporary copy). The colour output takes the dtype of the source colour (temporal: of the current colour), rounded
to nearest even as torch's ``.to(dtype)``, so results equal the torch reference on the same inputs.
"""

from __future__ import annotations

import torch
from torch import Tensor

try:  # optional: the package works without the compiled core
    from .. import _core
except ImportError:  # pragma: no cover - depends on the build
    _core = None

__all__ = ["available", "core_constants", "reproject", "temporal_reproject"]


def available() -> bool:
    """True when ``stereorepro._core`` is importable and has the reprojection kernels."""
    return _core is not None and all(
        hasattr(_core, k) for k in ("reproject", "temporal_reproject", "fast_history_clamp")
    )


def _require() -> None:
    if not available():
        raise RuntimeError("native: stereorepro._core with the reprojection kernels is not available")


#: Image dtypes the kernels read (each image on its own; compute is float32).
DTYPES = (torch.float32, torch.float16)


def _image_contiguous(x: Tensor, name: str) -> Tensor:
    if x.device.type != "cpu":
        raise RuntimeError(f"native: {name} must be on the CPU, got {x.device}")
    if x.dtype not in DTYPES:
        raise TypeError(
            f"native: {name} must be float32 or float16, got {x.dtype} (use backend='torch' for other dtypes)"
        )
    return x.contiguous()  # the one visible copy, only when x is not C-contiguous


def _warp_args(warp) -> tuple[Tensor, ...]:
    """A float32 :class:`~stereorepro.camera.Warp` as the kernels' camera arguments (contiguous CPU (B, 9) / (B, 3),
    in their order: ``P`` = pixel_src_from_pixel_dst, ``kt`` = K_src_t, ``M`` = ray_src_from_pixel_dst,
    ``t`` = t_src_from_dst, ``Ks_inv`` = K_src_inv)."""
    B = warp.K_src_inv.shape[0]
    return tuple(
        x.reshape(B, -1).contiguous().cpu()
        for x in (
            warp.pixel_src_from_pixel_dst,
            warp.K_src_t,
            warp.ray_src_from_pixel_dst,
            warp.t_src_from_dst,
            warp.K_src_inv,
        )
    )


def _motion_args(
    motion: Tensor | None, motion_world: Tensor | None, src_rotation: Tensor | None, plane: bool = False
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """The kernels' motion arguments: the motion planes as they are (float32 or float16, contiguous) and the source
    camera's rotation (B, 9) float32, rounded as the torch reference rounds it (with ``motion_world``, and for the
    plane test)."""
    mo = None if motion is None else _image_contiguous(motion, "motion")
    mw = None if motion is None or motion_world is None else _image_contiguous(motion_world, "motion_world")
    if mw is None and not plane:
        return mo, None, None
    R = src_rotation.detach().to(torch.float32).reshape(src_rotation.shape[0], 9).contiguous().cpu()
    return mo, mw, R


def core_constants() -> dict | None:
    """The constants the kernels were compiled with (``_core.reproject_constants``: their copies of
    :data:`stereorepro.reproject._constants.MIRRORED_IN_CORE`), or None without the core."""
    return dict(_core.reproject_constants) if available() and hasattr(_core, "reproject_constants") else None


def reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    warp,
    dst_depth: Tensor,
    dst_normal: Tensor,
    thr2: tuple[float, float],
    bilinear: bool,
    want_confidence: bool = True,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    src_rotation: Tensor | None = None,
    cubic: bool = False,
    plane: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Backward reprojection with hard tests.

    Args:
        src_values: (B, C, Hs, Ws), src_depth: (B, 1, Hs, Ws), src_normal: (B, 3, Hs, Ws), float32 or float16.
        warp: the float32 :class:`~stereorepro.camera.Warp` from the destination into the source camera.
        dst_depth: (B, 1, H, W), dst_normal: (B, 3, H, W), float32 or float16.
        thr2: squared position and normal thresholds (float32 values).
        bilinear: 2×2 taps, else the nearest one.
        want_confidence: also write the accepted weight (else None: saves writing it).
        motion: optional (B, 2, H, W) screen motion of the destination pixels to the source instant (taps at
            ``pixel + motion``); motion_world: optional (B, 3, H, W) world motion of their points (the position
            test against ``P + motion_world``), with src_rotation (B, 3, 3) the source ``cam_from_world``'s
            rotation. float32 or float16.
        cubic: ``sampling="catmull_rom"``: the bilinear pass, then the 4×4 Catmull-Rom sum (clamped at 0) where
            all 16 footprint taps pass.
        plane: the plane test (``Thresholds(position_test="plane")``; needs ``src_rotation``), ``thr2[0]`` being
            the squared relative threshold.

    Returns:
        values (B, C, H, W) of src_values' dtype, valid (B, 1, H, W) bool, reason (B, 1, H, W) uint8, confidence
        (B, 1, H, W) float32 or None.
    """
    _require()
    sv = _image_contiguous(src_values, "src_values")
    sd = _image_contiguous(src_depth, "src_depth")
    sn = _image_contiguous(src_normal, "src_normal")
    dd = _image_contiguous(dst_depth, "dst_depth")
    dn = _image_contiguous(dst_normal, "dst_normal")
    B, C = sv.shape[:2]
    H, W = dd.shape[-2:]
    values = torch.empty(B, C, H, W, dtype=sv.dtype)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool)
    reason = torch.empty(B, 1, H, W, dtype=torch.uint8)
    confidence = torch.empty(B, 1, H, W, dtype=torch.float32) if want_confidence else None
    _core.reproject(
        sv,
        sd,
        sn,
        *_warp_args(warp),
        dd,
        dn,
        float(thr2[0]),
        float(thr2[1]),
        bool(bilinear),
        values,
        valid,
        reason,
        confidence,
        *_motion_args(motion, motion_world, src_rotation, plane),
        **({"cubic": True} if cubic else {}),  # a core built before the option serves the other samplings
        **({"plane": True} if plane else {}),
    )
    return values, valid, reason, confidence


def temporal_reproject(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    prev_depth: Tensor,
    prev_normal: Tensor,
    warp,
    depth: Tensor,
    normal: Tensor,
    thr2: tuple[float, float],
    bilinear: bool,
    alpha: float,
    warmup: bool,
    max_history: float,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    src_rotation: Tensor | None = None,
    round_history: bool = False,
    cubic: bool = False,
    footprint: bool = False,
    plane: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Temporal reprojection in one fused pass: warp [history_color, history_len] and blend with the current frame.

    Args:
        current_color: (B, 3, H, W); history_color: (B, 3, Hp, Wp); history_len: (B, 1, Hp, Wp);
            prev_depth: (B, 1, Hp, Wp); prev_normal: (B, 3, Hp, Wp); depth: (B, 1, H, W); normal: (B, 3, H, W),
            each float32 or float16.
        warp: the float32 :class:`~stereorepro.camera.Warp` from this frame's camera into the previous one.
        thr2, bilinear: as :func:`reproject`.
        alpha: minimum weight of the current frame, already clamped to [0, 1]; warmup: ``max(1/(n+1), alpha)``;
            max_history: cap of n.
        motion, motion_world, src_rotation: this frame's motion to the previous one, as :func:`reproject`
            (src_rotation: the previous camera's).
        round_history: store ``min(round_half_even(n) + 1, max_history)`` instead of ``min(n + 1, max_history)``
            where the history is kept (``history_rounding="bmfr"``; the caller passes BMFR's cap, 1 where
            ``alpha >= 1``).
        cubic: ``sampling="catmull_rom"`` for the history colour and length, as :func:`reproject`.
        footprint: scale the warped n by ``0.5 + 0.5·min(den, 1)`` before the blend, ``den`` the accepted
            bilinear weight (``Blend.footprint_weighting``).
        plane: the plane test, as :func:`reproject`.

    Returns:
        color (B, 3, H, W) of current_color's dtype, history_len (B, 1, H, W) float32, valid (B, 1, H, W) bool.
    """
    _require()
    cur = _image_contiguous(current_color, "current_color")
    hc = _image_contiguous(history_color, "history_color")
    hl = _image_contiguous(history_len, "history_len")
    pd = _image_contiguous(prev_depth, "prev_depth")
    pn = _image_contiguous(prev_normal, "prev_normal")
    dd = _image_contiguous(depth, "depth")
    dn = _image_contiguous(normal, "normal")
    B, C = hc.shape[:2]
    H, W = dd.shape[-2:]
    color = torch.empty(B, C, H, W, dtype=cur.dtype)
    n_out = torch.empty(B, 1, H, W, dtype=torch.float32)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool)
    _core.temporal_reproject(
        cur,
        hc,
        hl,
        pd,
        pn,
        *_warp_args(warp),
        dd,
        dn,
        float(thr2[0]),
        float(thr2[1]),
        bool(bilinear),
        float(alpha),
        bool(warmup),
        float(max_history),
        color,
        n_out,
        valid,
        *_motion_args(motion, motion_world, src_rotation, plane),
        **({"round_history": True} if round_history else {}),  # a core built before the option serves "none"
        **({"cubic": True} if cubic else {}),
        **({"footprint": True} if footprint else {}),
        **({"plane": True} if plane else {}),
    )
    return color, n_out, valid


def fast_history_clamp(color: Tensor, fast_color: Tensor, sigma: float, radius: int) -> Tensor:
    """:func:`stereorepro.reproject.fast_history_clamp` in the native core: the same bytes.

    Args:
        color, fast_color: (B, C, H, W) float32 or float16 (each on its own; computed in float32).
        sigma: the box's half width in standard deviations (rounded to float32 as torch does).
        radius: the window's radius, >= 0.

    Returns:
        (B, C, H, W) the clamped colour, dtype of ``color``.
    """
    _require()
    c = _image_contiguous(color, "color")
    f = _image_contiguous(fast_color, "fast_color")
    out = torch.empty_like(c)
    _core.fast_history_clamp(c, f, float(sigma), int(radius), out)
    return out
