"""Backward reprojection with discard masks (paper §4.1), stereo and temporal, as pure tensor functions and
nn.Modules.

For every destination pixel: unproject it with the destination depth, move it into the source camera, project
it, and read the 2×2 bilinear taps around that point in the source image (or the one nearest tap). A tap is
**accepted** only if

1. it lies inside the source frame,
2. the source pixel has a surface (see :func:`stereorepro.camera.has_surface`),
3. ``|P_src − P_dst| <= position_threshold`` (scene units; both points in the source camera's frame),
4. ``|N_src − N_dst| <= normal_threshold`` (unit world-space shading normals), and
5. its values are finite (policy: a NaN/Inf sample is rejected like an occluded one, so it never leaks).
   Non-finite *normals* (source or destination) are read as zero vectors, so they fail the normal test for any
   ``normal_threshold < 1`` and are reported as ``NORMAL``.

Accepted bilinear weights are renormalised by their sum; a pixel is ``valid`` when the accepted weight is > 0.
The same-instant stereo case and the temporal case are the same operation with different cameras
(paper §2.2: "stereo reprojection can be thought of as a special case of temporal reprojection").

Discard reasons (:class:`Reason`, uint8 map, 0 = kept) are ordered by the test that failed; a tap's code is the
first test it failed, and an invalid pixel reports the largest code among its taps of non-zero bilinear weight
(the test at which its most nearly accepted tap failed). That is what the paper's Figure 1 colours.

Precision: positions are compared in the source camera frame after composing ``src_from_dst`` in float64, so
results do not degrade with distance from the world origin; they degrade with distance from the camera as
fp32 does (relative 6e-8). Camera matrices are used in float64 whatever their dtype: pass float64 cameras for
scenes far (≥ 1e3 units) from the origin.

Dtypes: images may be float16/bfloat16/float32/float64; computation is float32 (float64 if any image input is
float64) and the colour output takes the dtype of the source colour.
"""

from __future__ import annotations

import enum
import math

import torch
from torch import Tensor, nn

from . import native as _native
from ._checks import _tracing, check_camera, check_device, check_floating, check_shape
from .camera import has_surface, invert_rigid
from .camera import inverse_intrinsics as _inverse_intrinsics

__all__ = [
    "Reason",
    "backward_reproject",
    "stereo_reproject",
    "temporal_blend",
    "temporal_reproject",
    "reason_to_rgb",
    "StereoReprojection",
    "TemporalReprojection",
]


class Reason(enum.IntEnum):
    """Why a destination pixel was discarded (values of the uint8 ``reason`` map)."""

    KEPT = 0
    NO_SURFACE_DST = 1  #: the destination pixel has no surface: nothing to reproject
    BEHIND_CAMERA = 2  #: the destination point is not in front of the source camera
    OUT_OF_FRAME = 3  #: the tap lies outside the source image
    NO_SURFACE_SRC = 4  #: the source tap has no surface
    POSITION = 5  #: |P_src − P_dst| > position_threshold (occlusion / disocclusion)
    NORMAL = 6  #: |N_src − N_dst| > normal_threshold
    NONFINITE = 7  #: the source tap's values are NaN or Inf
    NO_HISTORY = 8  #: no previous frame to reproject from (first frame of an accumulation)


#: Figure 1 colours (RGB in [0, 1]) by reason: green = position, cyan = normal, red = out of frame.
REASON_COLORS = {
    Reason.KEPT: (0.0, 0.0, 0.0),
    Reason.NO_SURFACE_DST: (0.25, 0.25, 0.25),
    Reason.BEHIND_CAMERA: (1.0, 0.0, 1.0),
    Reason.OUT_OF_FRAME: (1.0, 0.0, 0.0),
    Reason.NO_SURFACE_SRC: (0.0, 0.0, 1.0),
    Reason.POSITION: (0.0, 1.0, 0.0),
    Reason.NORMAL: (0.0, 1.0, 1.0),
    Reason.NONFINITE: (1.0, 1.0, 0.0),
    Reason.NO_HISTORY: (1.0, 1.0, 1.0),
}

_SAMPLINGS = ("bilinear", "nearest")


def _compute_dtype(*tensors: Tensor) -> torch.dtype:
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


_STEREO_NAMES = dict(src_values="src_color", src_depth="src_depth", src_normal="src_normal", src="src",
                     dst_depth="dst_depth", dst_normal="dst_normal", dst="dst")
_TEMPORAL_NAMES = dict(src_values="history_color", src_depth="prev_depth", src_normal="prev_normal", src="prev",
                       dst_depth="depth", dst_normal="normal", dst="current")


def _check_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world,
                  dst_depth, dst_normal, dst_K, dst_cam_from_world, names: dict) -> None:
    """Boundary checks; ``names`` maps roles to the caller's argument names so errors name what the user passed."""
    if _tracing():
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


def _as_scalar(x, like: Tensor) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(device=like.device, dtype=like.dtype).reshape(())
    return torch.full((), float(x), device=like.device, dtype=like.dtype)


def _snap(A: Tensor, tol: float = 1e-12) -> Tensor:
    """Round entries within ``tol`` (relative) of an integer to it (float64 camera compositions)."""
    r = torch.round(A)
    return torch.where((A - r).abs() <= tol * (1.0 + A.abs()), r, A)


def _finite_or_zero(x: Tensor) -> Tensor:
    return torch.where(torch.isfinite(x), x, torch.zeros((), dtype=x.dtype, device=x.device))


def _compose_cameras(src_K: Tensor, src_cam_from_world: Tensor, dst_K: Tensor, dst_cam_from_world: Tensor,
                     dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Per-batch warp matrices, composed in float64 and cast to ``dtype``; shared by the torch and native paths.

    ``q = z · M @ [u, v, 1] + t`` is the destination point in the source camera frame and
    ``uvw = P @ [u, v, 1] + kt / z`` its homogeneous source pixel, with M = R K_dst^-1, P = K_src M, kt = K_src t.

    CPU cameras that need no gradient and are not being traced are composed in numpy (the same formulas: some
    40 tiny torch ops cost 0.3 ms a call, 4 % of a native 1280x720 warp); otherwise in torch ops (autograd,
    ONNX export, other devices).

    Returns:
        M: (B, 3, 3), t: (B, 3, 1), P: (B, 3, 3), kt: (B, 3, 1), Ks_inv: (B, 3, 3) = K_src^-1.
    """
    cams = (src_K, src_cam_from_world, dst_K, dst_cam_from_world)
    if not _tracing() and all(c.device.type == "cpu" and not (c.requires_grad and torch.is_grad_enabled())
                              for c in cams):
        return _compose_cameras_numpy(*cams, dtype)
    src_from_dst = _snap(src_cam_from_world.double() @ invert_rigid(dst_cam_from_world.double()))
    M64 = src_from_dst[:, :3, :3] @ _inverse_intrinsics(dst_K.double())
    t64 = src_from_dst[:, :3, 3:]
    P = _snap(src_K.double() @ M64).to(dtype)
    kt = (src_K.double() @ t64).to(dtype)
    Ks_inv = _inverse_intrinsics(src_K.double()).to(dtype)
    return M64.to(dtype), t64.to(dtype), P, kt, Ks_inv


def _compose_cameras_numpy(src_K: Tensor, src_cam_from_world: Tensor, dst_K: Tensor, dst_cam_from_world: Tensor,
                           dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`_compose_cameras` in float64 numpy: invert_rigid, the closed-form K^-1 and _snap written out."""
    import numpy as np

    def f64(x):
        return x.detach().to(torch.float64).numpy()

    def snap(A, tol=1e-12):
        r = np.round(A)  # half to even, as torch.round
        return np.where(np.abs(A - r) <= tol * (1.0 + np.abs(A)), r, A)

    def k_inv(K):  # camera.inverse_intrinsics
        fx, s, cx, fy, cy = K[:, 0, 0], K[:, 0, 1], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2]
        out = np.zeros_like(K)
        out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = 1.0 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)
        out[:, 1, 1], out[:, 1, 2], out[:, 2, 2] = 1.0 / fy, -cy / fy, 1.0
        return out

    sK, sT, dK, dT = f64(src_K), f64(src_cam_from_world), f64(dst_K), f64(dst_cam_from_world)
    Rt = dT[:, :3, :3].transpose(0, 2, 1)
    dst_inv = np.concatenate([np.concatenate([Rt, -(Rt @ dT[:, :3, 3:])], 2), dT[:, 3:, :]], 1)  # invert_rigid
    src_from_dst = snap(sT @ dst_inv)
    M64 = src_from_dst[:, :3, :3] @ k_inv(dK)
    t64 = src_from_dst[:, :3, 3:]
    P = snap(sK @ M64)
    out = (M64, t64, P, sK @ t64, k_inv(sK))
    if dtype in (torch.float32, torch.float64):  # numpy's cast rounds to nearest, as torch's
        npd = np.float32 if dtype == torch.float32 else np.float64
        return tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=npd)) for a in out)
    return tuple(torch.from_numpy(np.ascontiguousarray(a)).to(dtype) for a in out)


def backward_reproject(
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
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Backward-warp ``src_values`` into the destination view with per-tap discard tests.

    Args:
        src_values: (B, C, Hs, Ws) values to carry (colour; extra channels such as history length ride along).
        src_depth: (B, 1, Hs, Ws) camera-z depth of the source view.
        src_normal: (B, 3, Hs, Ws) unit world-space shading normals of the source view.
        src_K: (B, 3, 3) source intrinsics.
        src_cam_from_world: (B, 4, 4) source extrinsics (rigid).
        dst_depth: (B, 1, H, W) camera-z depth of the destination view.
        dst_normal: (B, 3, H, W) unit world-space shading normals of the destination view.
        dst_K: (B, 3, 3) destination intrinsics.
        dst_cam_from_world: (B, 4, 4) destination extrinsics (rigid).
        position_threshold: max |P_src − P_dst| in scene units (float or 0-d tensor).
        normal_threshold: max |N_src − N_dst| between unit normals (float or 0-d tensor).
        sampling: ``"bilinear"`` (2×2 taps, the paper's choice) or ``"nearest"`` (one tap).
        soft: replace the position and normal step functions by sigmoids
            ``sigmoid((thr² − d²) / (2·temperature·thr²))`` (≈ a sigmoid in (thr − d) / (temperature·thr)), so
            that the output is differentiable in the thresholds. ``valid`` and ``reason`` still report the hard
            decision at the current thresholds.
        temperature: softness relative to the threshold (dimensionless), used when ``soft``. Soft colours are
            renormalised by ``max(accepted weight, SOFT_DEN_FLOOR)`` so that gradients stay bounded.
        check: validate shapes/dtypes (public boundary).

    Returns:
        values: (B, C, H, W) warped values (0 where nothing was accepted), dtype of ``src_values``.
        valid: (B, 1, H, W) bool, accepted bilinear weight > 0.
        reason: (B, 1, H, W) uint8 :class:`Reason` codes (0 where valid).
        confidence: (B, 1, H, W) accepted bilinear weight in [0, 1] before renormalisation (soft weights when
            ``soft``), in the compute dtype.

    Hard tests without autograd or tracing (and with finite squared thresholds) take a faster path with
    identical outputs (see the notes above ``_PAD``); gradients, tracing, ONNX export and soft tests take the
    general one.
    """
    if sampling not in _SAMPLINGS:
        raise ValueError(f"sampling must be one of {_SAMPLINGS}, got {sampling!r}")
    if check:
        _check_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world,
                      dst_depth, dst_normal, dst_K, dst_cam_from_world, dict(_STEREO_NAMES, src_values="src_values"))
    cd = _compute_dtype(src_values, src_depth, src_normal, dst_depth, dst_normal)
    dev = dst_depth.device
    B, C, Hs, Ws = src_values.shape
    H, W = dst_depth.shape[-2:]

    # --- cameras, composed once per batch item in float64:
    #   q   = z · M @ [u, v, 1] + t          the destination point in the source camera frame (position test)
    #   uvw = P @ [u, v, 1] + (K_src t) / z  its source pixel, homogeneous (u_s = uvw_x / uvw_z)
    # with M = R K_dst^-1 and P = K_src M. Entries within 1e-12 of an integer are snapped, so identical cameras
    # give P = I and t = 0 exactly: identity warps and integer-pixel shifts are bit-exact.
    M, t, P, kt, Ks_inv = _compose_cameras(src_K, src_cam_from_world, dst_K, dst_cam_from_world, cd)
    cams = (M, t, P, kt, Ks_inv)
    inputs = (src_values, src_depth, src_normal, dst_depth, dst_normal, src_K, dst_K, src_cam_from_world,
              dst_cam_from_world, position_threshold, normal_threshold)
    inference = _inference_only(inputs)
    if inference and not soft:  # the usual inference case: same results, a fraction of the memory traffic
        thr2 = _squared_thresholds(position_threshold, normal_threshold, cd, dev)
        if bool(torch.isfinite(thr2).all()):
            return _fast_reproject(src_values, src_depth, src_normal, dst_depth, dst_normal, cams, thr2,
                                   position_threshold, normal_threshold, sampling)
    feats = _source_features(src_values, src_depth, src_normal, cd)
    warp = dict(read_taps=_feature_reader(feats), C=C, Hs=Hs, Ws=Ws, cams=cams,
                position_threshold=position_threshold, normal_threshold=normal_threshold, sampling=sampling,
                soft=soft, temperature=temperature, out_dtype=src_values.dtype)
    rows = max(1, BLOCK_PIXELS // max(1, B * W)) if inference else None
    if rows is None or rows >= H:  # gradients or tracing need one graph; small images need no blocking
        return _warp_pixels(dst_depth=dst_depth, dst_normal=dst_normal, **_pixel_centres(0, H, W, cd, dev), **warp)
    # Inference on large images (soft tests; hard ones take the fast path): destination rows in blocks, so that
    # the per-tap intermediates stay in cache (the op is memory-bound). Results are bit-identical to one block.
    values = torch.empty(B, C, H, W, dtype=src_values.dtype, device=dev)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=dev)
    reason = torch.empty(B, 1, H, W, dtype=torch.uint8, device=dev)
    den = torch.empty(B, 1, H, W, dtype=cd, device=dev)
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        out = _warp_pixels(dst_depth=dst_depth[:, :, r0:r1], dst_normal=dst_normal[:, :, r0:r1],
                           **_pixel_centres(r0, r1, W, cd, dev), **warp)
        for buf, o in zip((values, valid, reason, den), out):
            buf[:, :, r0:r1] = o
    return values, valid, reason, den


#: Smallest accepted weight the soft path divides by (see :func:`backward_reproject`).
SOFT_DEN_FLOOR = 1e-3

#: Destination pixels per block in blocked inference (see :func:`backward_reproject`).
BLOCK_PIXELS = 1 << 16

#: Destination pixels per block in the fast path (its per-block working set is larger).
FAST_BLOCK_PIXELS = 1 << 15


def _inference_only(inputs) -> bool:
    """True when no autograd graph is needed and nothing traces/exports/compiles the call: the row-blocked and
    fast paths apply (tracing and ONNX export always take the single-block general path)."""
    if _tracing():
        return False
    return not (torch.is_grad_enabled() and any(isinstance(x, Tensor) and x.requires_grad for x in inputs))


def _squared_thresholds(position_threshold, normal_threshold, cd: torch.dtype, dev) -> Tensor:
    """(1, 2, 1, 1, 1) = (thr_p², thr_n²) in the compute dtype, squared exactly as the general path does."""
    like = torch.empty((), dtype=cd, device=dev)
    thr_p, thr_n = _as_scalar(position_threshold, like), _as_scalar(normal_threshold, like)
    return torch.stack([thr_p * thr_p, thr_n * thr_n]).view(1, 2, 1, 1, 1)


def _pixel_centres(r0: int, r1: int, W: int, cd: torch.dtype, dev) -> dict:
    """Pixel centres of destination rows r0 .. r1 - 1 for :func:`_warp_pixels`: u_c (1, 1, 1, W), v_c (1, 1, h, 1)."""
    return dict(u_c=torch.arange(W, device=dev, dtype=cd).view(1, 1, 1, W) + 0.5,
                v_c=torch.arange(r1 - r0, device=dev, dtype=cd).view(1, 1, r1 - r0, 1) + (r0 + 0.5))


def _source_features(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, cd: torch.dtype) -> Tensor:
    """The source, sanitised once, as gatherable rows: (B, C+5, Hs·Ws) = values, depth, normal, flags.

    Non-finite values and missing surfaces become finite placeholders that the flags reject, so a rejected tap
    can never leak NaN/Inf (0 · NaN = NaN). Flags: bit 0 = has a surface, bit 1 = finite values. Purely per
    pixel, so it may equally be applied to already gathered pixels (B, ·, 1, M).
    """
    B, C = src_values.shape[:2]
    zero = torch.zeros((), dtype=cd, device=src_values.device)
    one = torch.ones((), dtype=cd, device=src_values.device)
    sv = src_values.to(cd)
    sv_finite = torch.isfinite(sv.sum(1, keepdim=True))  # any NaN/Inf in a pixel makes its sum non-finite
    sz = src_depth.to(cd)
    s_ok = has_surface(sz)
    flags = s_ok.to(cd) + 2.0 * sv_finite.to(cd)
    return torch.cat([torch.where(sv_finite, sv, zero), torch.where(s_ok, sz, one),
                      _finite_or_zero(src_normal.to(cd)), flags], 1).reshape(B, C + 5, -1)


def _feature_reader(feats: Tensor):
    """``read_taps`` for :func:`_warp_pixels` over the whole source: index (B, T, ...) -> (B, C+5, T·...)."""
    def read_taps(index: Tensor) -> Tensor:
        B, Fg = feats.shape[:2]
        return torch.gather(feats, 2, index.reshape(B, 1, -1).expand(B, Fg, index[0].numel()))
    return read_taps


def _raw_reader(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, b: int, cd: torch.dtype):
    """``read_taps`` for :func:`_warp_pixels` that sanitises only the gathered pixels of batch item ``b`` (the
    fast path's reason pass touches few pixels; building the whole feature table would cost more)."""
    Ws = src_values.shape[-1]

    def read_taps(index: Tensor) -> Tensor:
        flat = index.reshape(-1)
        yy, xx = flat // Ws, flat % Ws  # (C, Hs, Ws) inputs of any strides, indexed without a copy
        take = [x[b][:, yy, xx][None, :, None] for x in (src_values, src_depth, src_normal)]  # (1, ·, 1, M)
        return _source_features(*take, cd)
    return read_taps


def _warp_pixels(read_taps, C: int, Hs: int, Ws: int, cams, dst_depth: Tensor, dst_normal: Tensor, u_c: Tensor,
                 v_c: Tensor, position_threshold, normal_threshold, sampling: str, soft: bool, temperature: float,
                 out_dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The general path (differentiable, traceable): reproject destination pixels; see :func:`backward_reproject`.

    Args:
        read_taps: index (B, T, *S) into the source pixels -> (B, C+5, T·prod(S)) :func:`_source_features` rows.
        dst_depth: (B, 1, *S), dst_normal: (B, 3, *S) with S = (h, W) rows or (1, K) a list of pixels.
        u_c, v_c: their pixel centres, broadcastable to (1, 1, *S) (see :func:`_pixel_centres`).

    Returns:
        values (B, C, *S), valid, reason, confidence (B, 1, *S).
    """
    M, t, P, kt, Ks_inv = cams
    cd = Ks_inv.dtype
    dev = dst_depth.device
    B = Ks_inv.shape[0]
    H, W = dst_depth.shape[-2:]
    m = M.reshape(B, 3, 3, 1, 1)  # m[:, :, j] is column j as (B, 3, 1, 1)
    t = t.reshape(B, 3, 1, 1)
    p = P.reshape(B, 9, 1, 1)  # p[:, 3*i+j : 3*i+j+1] is P[i, j]
    kt = kt.reshape(B, 3, 1, 1)
    # --- destination pixels → source pixels and source-camera points.
    z_dst = dst_depth.to(cd)
    dst_ok = has_surface(z_dst)  # Bx1xHxW
    one = torch.ones((), dtype=cd, device=dev)
    z_dst = torch.where(dst_ok, z_dst, one)
    inv_z = 1.0 / z_dst
    wx = p[:, 0:1] * u_c + p[:, 1:2] * v_c + p[:, 2:3] + kt[:, 0:1] * inv_z  # Bx1xHxW
    wy = p[:, 3:4] * u_c + p[:, 4:5] * v_c + p[:, 5:6] + kt[:, 1:2] * inv_z
    wz = p[:, 6:7] * u_c + p[:, 7:8] * v_c + p[:, 8:9] + kt[:, 2:3] * inv_z  # = q_z / z
    front = wz > 0
    wz = torch.where(front, wz, one)
    u = wx / wz
    v = wy / wz
    q = (m[:, :, 0] * u_c + m[:, :, 1] * v_c + m[:, :, 2]) * z_dst + t  # Bx3xHxW
    qz = q[:, 2:3]
    front = front & torch.isfinite(u) & torch.isfinite(v)
    # Keep coordinates finite and in a small range: anything clamped is out of frame anyway.
    u = torch.where(front, u, torch.full((), -4.0, dtype=cd, device=dev)).clamp(-4.0, Ws + 4.0)
    v = torch.where(front, v, torch.full((), -4.0, dtype=cd, device=dev)).clamp(-4.0, Hs + 4.0)

    # --- taps (T = 4 or 1) and their bilinear weights, shapes BxTxHxW.
    if sampling == "bilinear":
        x = u - 0.5
        y = v - 0.5
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = x - x0  # gradient 1 w.r.t. u
        fy = y - y0
        xi = torch.cat([x0, x0 + 1, x0, x0 + 1], 1)
        yi = torch.cat([y0, y0, y0 + 1, y0 + 1], 1)
        wts = torch.cat([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    else:
        xi = torch.floor(u)
        yi = torch.floor(v)
        wts = torch.ones_like(u)
    T = xi.shape[1]
    in_frame = (xi >= 0) & (xi <= Ws - 1) & (yi >= 0) & (yi <= Hs - 1)
    # integer arithmetic: float32 would be exact only below 2^24 source pixels
    index = yi.clamp(0, Hs - 1).to(torch.int64) * Ws + xi.clamp(0, Ws - 1).to(torch.int64)  # BxTxHxW

    zero = torch.zeros((), dtype=cd, device=dev)
    g = read_taps(index).reshape(B, C + 5, T, H, W)
    g_val = g[:, :C]
    z_src = g[:, C]  # BxTxHxW, 1 where no surface
    n_src = g[:, C + 1:C + 4]  # Bx3xTxHxW
    g_flags = g[:, C + 4]
    src_ok = (g_flags == 1.0) | (g_flags == 3.0)
    finite = g_flags >= 2.0

    ki = Ks_inv.reshape(B, 9, 1, 1)
    ut = xi + 0.5
    vt = yi + 0.5
    px = z_src * (ki[:, 0:1] * ut + ki[:, 1:2] * vt + ki[:, 2:3])
    py = z_src * (ki[:, 4:5] * vt + ki[:, 5:6])
    d_pos2 = (q[:, 0:1] - px).square() + (q[:, 1:2] - py).square() + (qz - z_src).square()
    n_dst = _finite_or_zero(dst_normal.to(cd)).unsqueeze(2)  # Bx3x1xHxW
    d_n2 = (n_src - n_dst).square().sum(1)  # BxTxHxW

    thr_p = _as_scalar(position_threshold, d_pos2)
    thr_n = _as_scalar(normal_threshold, d_n2)
    pos_ok = d_pos2 <= thr_p * thr_p
    nrm_ok = d_n2 <= thr_n * thr_n

    pixel_ok = dst_ok & front  # Bx1xHxW
    base_ok = pixel_ok & in_frame & src_ok & finite  # BxTxHxW: the tests that stay hard
    hard = base_ok & pos_ok & nrm_ok
    if soft:
        tau = float(temperature)
        tp2 = (thr_p * thr_p).clamp_min(torch.finfo(cd).tiny)
        tn2 = (thr_n * thr_n).clamp_min(torch.finfo(cd).tiny)
        a_soft = torch.sigmoid((tp2 - d_pos2) / (2 * tau * tp2)) * torch.sigmoid((tn2 - d_n2) / (2 * tau * tn2))
        accept_w = torch.where(base_ok, a_soft, zero)
    else:
        accept_w = hard.to(cd)

    ws = wts * accept_w  # BxTxHxW
    den = ws.sum(1, keepdim=True)  # Bx1xHxW
    num = (ws.unsqueeze(1) * g_val).sum(2)  # BxCxHxW (g_val is finite: sanitised above)
    has_w = den > 0
    # Soft weights can be tiny but positive; dividing by them gives gradients of ~num/den² that overflow. The soft
    # path renormalises by max(den, SOFT_DEN_FLOOR): a pixel that is all but rejected fades to 0 instead.
    den_safe = den.clamp_min(SOFT_DEN_FLOOR) if soft else torch.where(has_w, den, one)
    values = torch.where(has_w, num / den_safe, zero)
    valid = (wts * hard.to(cd)).sum(1, keepdim=True) > 0

    # --- reason codes (uint8): first failing test per tap; invalid pixel -> max over taps with weight > 0.
    def u8(r: Reason) -> Tensor:
        return torch.full((), int(r), dtype=torch.uint8, device=dev)

    code = torch.where(finite, u8(Reason.KEPT), u8(Reason.NONFINITE))
    code = torch.where(nrm_ok, code, u8(Reason.NORMAL))
    code = torch.where(pos_ok, code, u8(Reason.POSITION))
    code = torch.where(src_ok, code, u8(Reason.NO_SURFACE_SRC))
    code = torch.where(in_frame & (wts > 0), code, torch.where(wts > 0, u8(Reason.OUT_OF_FRAME), u8(Reason.KEPT)))
    reason = code.amax(1, keepdim=True)
    reason = torch.where(front, reason, u8(Reason.BEHIND_CAMERA))
    reason = torch.where(dst_ok, reason, u8(Reason.NO_SURFACE_DST))
    reason = torch.where(valid, u8(Reason.KEPT), reason)
    return values.to(out_dtype), valid, reason, den


# --- fast path: hard tests in inference ---------------------------------------------------------------------
# backward_reproject's fast path for hard tests when no autograd graph is needed and nothing traces the call
# (and the squared thresholds are finite). Wherever a result depends on it, it performs the per-element float
# arithmetic of _warp_pixels, so values, valid, reason and confidence are identical to the general path
# (tests/test_reproject.py::TestFastPath); what changes is the memory traffic, which bounds this op on a CPU:
#
# * the source is sanitised once into a padded gather table (_fast_source_table) holding, per pixel, the values,
#   the source-camera point (px, py, z) (the per-tap formula of _warp_pixels evaluated once per pixel: the same
#   bits) and the normal. A pixel no tap may accept (no surface, non-finite values, the _PAD border) has a NaN or
#   infinite point, which fails the position test: no per-tap frame, surface or finiteness tests, no index
#   clamping. Invalid destination pixels are sent to the border the same way;
# * accept tests are float arithmetic (a comparison into a float tensor is vectorised, into a bool one it is not);
# * one gather of all taps' table rows per row block; one pass of float ops over (channel, tap, pixel) arrays;
# * reasons only for invalid pixels (_fast_reasons): no surface / behind the camera / every tap out of frame
#   directly, the rest (occlusions, ...) through _warp_pixels on those pixels alone;
# * destination rows in blocks of FAST_BLOCK_PIXELS, with scratch buffers reused across blocks (out= / in-place).

#: Border of the fast path's source table: taps of coordinates clamped to [-4, Ws + 4] read pixels -5 .. Ws + 4.
_PAD = 5

#: Integers up to this are exact in float32 (larger source tables get float64 index arithmetic).
_F32_EXACT = 2 ** 24


class _Scratch:
    """Named scratch buffers of the fast path, reused across row blocks (multi-MB temporaries allocated afresh
    by every op cost page faults and cache misses). ``views(key, spec)`` returns a dict name -> view of the given
    shape for ``spec`` = [(name, shape, dtype), ...], cached per key; different names never alias."""

    def __init__(self, device):
        self.device, self._bufs, self._views = device, {}, {}

    def views(self, key, spec) -> dict:
        if key not in self._views:
            views = {}
            for name, shape, dtype in spec:
                n = math.prod(shape)
                buf = self._bufs.get((name, dtype))
                if buf is None or buf.numel() < n:
                    buf = self._bufs[(name, dtype)] = torch.empty(n, dtype=dtype, device=self.device)
                views[name] = buf[:n].view(shape)
            self._views[key] = views
        return self._views[key]


def _fast_source_table(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, Ks_inv: Tensor,
                       cd: torch.dtype) -> Tensor:
    """The fast path's gather table: (B, C+6, Hp·Wp) with Hp, Wp = Hs + 2·_PAD, Ws + 2·_PAD.

    Channels: values (all 0 for a pixel with any non-finite value), the pixel's point in the source camera frame
    px, py, z (NaN or ±inf where no tap may be accepted: no surface, non-finite values, the border), normal
    (non-finite components 0, as _finite_or_zero).
    """
    B, C, Hs, Ws = src_values.shape
    dev = src_values.device
    p = _PAD
    tab = torch.empty(B, C + 6, Hs + 2 * p, Ws + 2 * p, dtype=cd, device=dev)
    for border in (tab[:, :, :p], tab[:, :, p + Hs:], tab[:, :, p:p + Hs, :p], tab[:, :, p:p + Hs, p + Ws:]):
        border.fill_(0.0)
        border[:, C:C + 3].fill_(math.nan)
    inner = tab[:, :, p:p + Hs, p:p + Ws]
    sv = src_values.to(cd)
    s0 = sv.sum(1, keepdim=True)
    s0 = torch.sub(s0, s0, out=s0)  # 0 where all values of the pixel are finite, NaN elsewhere
    torch.sub(sv, s0, out=inner[:, :C]).nan_to_num_(0.0, 0.0, 0.0)  # x - 0 = x, bit for bit (-0 included)
    sz = src_depth.to(cd)
    surface = torch.gt(sz, 0.0, out=torch.empty_like(sz))  # 1.0 / 0.0
    zm = torch.sub(sz, s0).div_(surface)  # z where z > 0 and the values are finite; NaN or ±inf elsewhere
    ki = Ks_inv.reshape(B, 9, 1, 1)
    ut = torch.arange(Ws, dtype=cd, device=dev).view(1, 1, 1, Ws) + 0.5
    vt = torch.arange(Hs, dtype=cd, device=dev).view(1, 1, Hs, 1) + 0.5
    torch.mul(zm, ki[:, 0:1] * ut + ki[:, 1:2] * vt + ki[:, 2:3], out=inner[:, C:C + 1])  # px, as in _warp_pixels
    torch.mul(zm, ki[:, 4:5] * vt + ki[:, 5:6], out=inner[:, C + 1:C + 2])  # py
    inner[:, C + 2:C + 3] = zm
    torch.nan_to_num(src_normal.to(cd), 0.0, 0.0, 0.0, out=inner[:, C + 3:])
    return tab.view(B, C + 6, -1)


def _fast_geometry(geo, z: Tensor, n: Tensor, r0: int, r1: int, uv_raw: Tensor, sc: _Scratch):
    """Destination rows r0 .. r1 - 1 -> taps: the fast path's share of the projection and tap weights of
    :func:`_warp_pixels` (same arithmetic for every pixel that can have an accepted tap).

    Args:
        geo: see :func:`_fast_reproject`.
        z: (B, 1, N) depth, n: (B, 3, N) normal of the N = (r1 - r0)·W pixels (any float dtype and strides).
        uv_raw: (B, 2, N), written: the source pixel (u, v) before clamping; non-finite where the pixel has a
            surface but is behind the source camera or projects to infinity (``front`` False in _warp_pixels).

    Returns:
        qn: (B, 6, N) the destination point in the source camera frame and the sanitised destination normal.
        wts: (B, 2, 2, N) bilinear weights of the taps (y0 | y0 + 1, x0 | x0 + 1), None for nearest sampling.
        corner: (B, 1, N) y0·Wp + x0 for tap (x0, y0) (nearest: the tap), exact in its float dtype; the table
            index of a tap is this plus _PAD·Wp + _PAD plus its offset from (x0, y0).

    Invalid pixels need no flag: no surface (z <= 0 -> 1/z = inf, NaN z) or behind the camera (wz <= 0 ->
    w / 0) make u, v non-finite, sanitised to the border, so every tap is rejected; z = +inf gives an infinite q.
    """
    R, ru, v_c, kt, t, lo, hi, one, sampling, Wp, idx_dtype = geo
    B, h, W = z.shape[0], r1 - r0, ru.shape[-1]
    N, cd = h * W, R.dtype
    v = sc.views(("geometry", N), [("zc", (B, 1, N), cd), ("inv", (B, 1, N), cd), ("base", (B, 6, h, W), cd),
                                   ("w", (B, 3, N), cd), ("qn", (B, 6, N), cd), ("uv", (B, 2, N), cd),
                                   ("xy0", (B, 2, N), cd), ("wa", (B, 2, 2, N), cd), ("wts", (B, 2, 2, N), cd),
                                   ("corner", (B, 1, N), idx_dtype)])
    zc = torch.clamp_min(z.to(cd), 0.0, out=v["zc"])
    inv = torch.reciprocal(zc, out=v["inv"])
    # [P; M] @ [u, v, 1] as in _warp_pixels: (R0·u + R1·v) + R2, R0·u precomputed
    base = torch.add(ru, R[:, :, 1, None, None] * v_c[:, :, r0:r1], out=v["base"])
    base = base.add_(R[:, :, 2, None, None]).view(B, 6, N)
    w = torch.mul(kt, inv, out=v["w"]).add_(base[:, :3])  # P @ [u, v, 1] + (K_src t) / z
    qn = v["qn"]
    torch.mul(base[:, 3:], zc, out=qn[:, :3]).add_(t)  # (M @ [u, v, 1]) z + t
    torch.nan_to_num(n.to(cd), 0.0, 0.0, 0.0, out=qn[:, 3:])
    torch.div(w[:, :2], torch.clamp_min(w[:, 2:3], 0.0, out=inv), out=uv_raw)  # wz <= 0: ±inf or NaN
    # the taps' x = clamp(u, -4, Ws + 4) - 0.5 in _warp_pixels; here u - 0.5 clamped to [-5, Ws + 3] (with integer
    # bounds, so that pixels off the frame have f = 0): the same bits wherever a tap can be in the frame
    uv = torch.sub(uv_raw, 0.5 if sampling == "bilinear" else 0.0, out=v["uv"])
    uv.nan_to_num_(-5.0, -5.0, -5.0).clamp_(lo, hi)
    xy0 = torch.floor(uv, out=v["xy0"])
    wts = None
    if sampling == "bilinear":
        wa = v["wa"]  # (B, axis x|y, 1 - f | f, N)
        f = torch.sub(uv, xy0, out=wa[:, :, 1])
        torch.sub(one, f, out=wa[:, :, 0])
        wts = torch.mul(wa[:, 1, :, None], wa[:, 0, None, :], out=v["wts"])
    xy0 = xy0.to(idx_dtype)  # (float64 for tables of 2^24 pixels or more)
    corner = torch.mul(xy0[:, 1:2], Wp, out=v["corner"]).add_(xy0[:, 0:1])
    return qn, wts, corner


def _fast_accept(taps: Tensor, qn: Tensor, wts: Tensor | None, thr2: Tensor, sc: _Scratch, key,
                 values: Tensor, valid: Tensor, den: Tensor) -> None:
    """Accept tests and the renormalised sum over the taps of N destination pixels (the tail of _warp_pixels).

    Args:
        taps: (B, C+6, Ty, Tx, N) gathered table rows (any strides); Ty = Tx = 2 (bilinear) or 1 (nearest).
        qn: (B, 6, N), wts: (B, Ty, Tx, N) or None (a single tap of weight 1), thr2: (1, 2, 1, 1, 1).
        values: (B, C, N), valid, den: (B, 1, N), written. Where nothing is accepted ``values`` is ±0 (the
            sign of a sum of zeros); the caller writes +0 there.
    """
    B, F, Ty, Tx, N = taps.shape
    C, T, cd = F - 6, Ty * Tx, taps.dtype
    v = sc.views(("accept", key), [("d", (B, 6, Ty, Tx, N), cd), ("s", (B, 2, Ty, Tx, N), cd),
                                   ("a", (B, 2, Ty, Tx, N), cd), ("ws", (B, Ty, Tx, N), cd),
                                   ("prod", (B, C, Ty, Tx, N), cd), ("num", (B, C, N), cd),
                                   ("den_safe", (B, 1, N), cd)])
    # (p_src - q)², (n_src - n_dst)² in one pass (mse_loss without reduction: exactly the square of the difference)
    d = torch.ops.aten.mse_loss.out(taps[:, C:], qn[:, :, None, None], 0, out=v["d"]).view(B, 2, 3, Ty, Tx, N)
    s = torch.add(d[:, :, 0], d[:, :, 1], out=v["s"]).add_(d[:, :, 2])  # d_pos2, d_n2 summed as _warp_pixels
    a = torch.le(s, thr2, out=v["a"])  # 1.0 / 0.0, NaN -> 0.0
    ws = torch.mul(a[:, 0], a[:, 1], out=v["ws"])
    if wts is not None:
        ws.mul_(wts)  # = wts · hard
    torch.sum(ws.view(B, T, N), 1, keepdim=True, out=den)
    prod = torch.mul(taps[:, :C], ws[:, None], out=v["prod"])
    num = torch.sum(prod.view(B, C, T, N), 2, out=v["num"])
    torch.gt(den, 0.0, out=valid)
    # den > 0 is a sum of products of two weights >= 2^-24 (fractions of coordinates < 2^23), so it is above
    # `tiny`: clamping divides by den itself where valid
    torch.div(num, torch.clamp_min(den, torch.finfo(cd).tiny, out=v["den_safe"]), out=values)


def _take(x: Tensor, b: int, p: Tensor, yy: Tensor, xx: Tensor) -> Tensor:
    """(1, C, K): pixels ``p`` (flat; rows yy, columns xx) of batch item ``b`` of a (B, C, H, W) tensor."""
    xb = x[b]
    if xb.is_contiguous():  # (index_select along the last dim is much slower than this gather)
        return torch.gather(xb.view(1, xb.shape[0], -1), 2, p.view(1, 1, -1).expand(1, xb.shape[0], -1))
    return xb[:, yy, xx][None]


def _fast_reasons(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, dst_depth: Tensor, dst_normal: Tensor,
                  cams, position_threshold, normal_threshold, sampling: str, b: int, p: Tensor,
                  uv: Tensor) -> Tensor:
    """Reason codes (K,) uint8 of the invalid destination pixels ``p`` (flat indices) of batch item ``b``.

    ``uv`` (2, K) is their unclamped source pixel from :func:`_fast_geometry`. No surface, behind the camera and
    "every tap out of frame" (the image border: most invalid pixels) follow from it and the depth as in
    :func:`_warp_pixels`; the others (occlusions, ...) go through :func:`_warp_pixels` on those pixels only.
    """
    C, Hs, Ws = src_values.shape[1:]
    cd, dev = cams[0].dtype, dst_depth.device
    W, K = dst_depth.shape[-1], p.numel()
    yy, xx = p // W, p % W
    z = _take(dst_depth, b, p, yy, xx).to(cd).view(K)
    dst_ok = has_surface(z)
    front = torch.isfinite(uv).all(0)  # with a surface: as `front` in _warp_pixels
    u, v = uv[0].clamp(-4.0, Ws + 4.0), uv[1].clamp(-4.0, Hs + 4.0)
    if sampling == "bilinear":  # taps x0, x0 + 1 (y0, y0 + 1) all outside [0, Ws - 1] ([0, Hs - 1])
        x0, y0 = torch.floor(u - 0.5), torch.floor(v - 0.5)
        outside = (x0 < -1) | (x0 > Ws - 1) | (y0 < -1) | (y0 > Hs - 1)
    else:
        xi, yi = torch.floor(u), torch.floor(v)
        outside = (xi < 0) | (xi > Ws - 1) | (yi < 0) | (yi > Hs - 1)
    code = torch.full((K,), int(Reason.OUT_OF_FRAME), dtype=torch.uint8, device=dev)
    code.masked_fill_(~outside, int(Reason.KEPT))  # undecided
    code.masked_fill_(~front, int(Reason.BEHIND_CAMERA))
    code.masked_fill_(~dst_ok, int(Reason.NO_SURFACE_DST))
    rest = torch.nonzero(code == int(Reason.KEPT)).squeeze(1)
    if rest.numel():
        k, p, yy, xx = rest.numel(), p[rest], yy[rest], xx[rest]
        _, _, reason, _ = _warp_pixels(
            _raw_reader(src_values, src_depth, src_normal, b, cd), C, Hs, Ws, tuple(c[b:b + 1] for c in cams),
            z[rest].view(1, 1, 1, k), _take(dst_normal, b, p, yy, xx).view(1, 3, 1, k),
            (xx.to(cd) + 0.5).view(1, 1, 1, k), (yy.to(cd) + 0.5).view(1, 1, 1, k), position_threshold,
            normal_threshold, sampling, False, 0.1, cd)
        code[rest] = reason.view(k)
    return code


def _fast_reproject(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, dst_depth: Tensor,
                    dst_normal: Tensor, cams, thr2: Tensor, position_threshold, normal_threshold,
                    sampling: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`backward_reproject` for hard tests without autograd or tracing (see the notes above _PAD)."""
    M, t, P, kt, Ks_inv = cams
    cd, dev = M.dtype, dst_depth.device
    B, C, Hs, Ws = src_values.shape
    H, W = dst_depth.shape[-2:]
    F, Wp = C + 6, Ws + 2 * _PAD
    bilinear = sampling == "bilinear"
    tab = _fast_source_table(src_values, src_depth, src_normal, Ks_inv, cd)
    Np = tab.shape[-1]
    # table indices are computed in floating point: exact below 2^24 in float32
    idx_dtype = cd if cd == torch.float64 or Np + Wp < _F32_EXACT else torch.float64
    off = -1.0 if bilinear else 0.0  # see _fast_geometry
    lo = torch.full((1, 2, 1), -4.0 + off, dtype=cd, device=dev)
    hi = torch.tensor([Ws + 4.0 + off, Hs + 4.0 + off], dtype=cd, device=dev).view(1, 2, 1)
    R = torch.cat([P, M], 1)  # (B, 6, 3)
    centres = _pixel_centres(0, H, W, cd, dev)
    geo = (R, R[:, :, 0, None, None] * centres["u_c"], centres["v_c"], kt, t, lo, hi, torch.ones((), dtype=cd, device=dev), sampling, Wp,
           idx_dtype)
    sc = _Scratch(dev)

    values = torch.empty(B, C, H, W, dtype=cd, device=dev)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=dev)
    den = torch.empty(B, 1, H, W, dtype=cd, device=dev)
    uv_raw = torch.empty(B, 2, H * W, dtype=cd, device=dev)  # for the reasons of invalid pixels
    offsets = torch.tensor([[0.0, 1.0], [Wp, Wp + 1.0]] if bilinear else [[0.0]], dtype=idx_dtype, device=dev)
    offsets += _PAD * Wp + _PAD  # (0, 0) of the source image in the padded table
    # v_s = v + P[1, 2] for every pixel (P[1] = (0, 1, ·), P[2] = (0, 0, 1), kt_y = kt_z = 0): bilinear taps may all
    # have fy = 0 (rectified stereo), checked per block; otherwise the check would only cost time
    rectified = bilinear and bool((P[:, 1, :2] == torch.tensor([0.0, 1.0], dtype=cd, device=dev)).all()
                                  & (P[:, 2] == torch.tensor([0.0, 0.0, 1.0], dtype=cd, device=dev)).all()
                                  & (kt[:, 1:] == 0).all())
    rows = max(1, FAST_BLOCK_PIXELS // max(1, B * W))
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        N = (r1 - r0) * W
        qn, wts, corner = _fast_geometry(geo, dst_depth[:, :, r0:r1].reshape(B, 1, N),
                                         dst_normal[:, :, r0:r1].reshape(B, 3, N), r0, r1,
                                         uv_raw[:, :, r0 * W:r1 * W], sc)
        offs = offsets
        if rectified and not torch.count_nonzero(wts[:, 1, 0]):  # (1 - fx)·fy, 1 - fx > 0
            # fy = 0 for every pixel (rectified stereo): the y0 + 1 taps weigh 0, the y0 taps give the same sums
            offs, wts = offsets[:1], wts[:, :1]
        T = offs.numel()
        v = sc.views(("taps", N, T), [("fidx", (B, T, N), idx_dtype), ("idx", (B, T, N), torch.int64),
                                      ("taps", (B, F, T * N), cd)])
        idx = v["idx"].copy_(torch.add(corner, offs.view(1, T, 1), out=v["fidx"]))
        taps = torch.gather(tab, 2, idx.view(B, 1, T * N).expand(B, F, T * N), out=v["taps"])
        _fast_accept(taps.view(B, F, *offs.shape, N), qn, wts, thr2, sc, (N, T), values[:, :, r0:r1].view(B, C, N),
                     valid[:, :, r0:r1].view(B, 1, N), den[:, :, r0:r1].view(B, 1, N))

    reason = torch.zeros(B, 1, H, W, dtype=torch.uint8, device=dev)
    for b in range(B):
        p = torch.nonzero(~valid[b].view(H * W)).squeeze(1)
        if p.numel():
            values[b].view(C, H * W).index_fill_(1, p, 0.0)  # +0 where nothing is accepted, as the general path
            reason[b].view(H * W).index_copy_(0, p, _fast_reasons(
                src_values, src_depth, src_normal, dst_depth, dst_normal, cams, position_threshold,
                normal_threshold, sampling, b, p, uv_raw[b].index_select(1, p)))
    return values.to(src_values.dtype), valid, reason, den


def stereo_reproject(
    src_color: Tensor,
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
    backend: str = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """Reproject one eye into the other at the same instant (paper §4.1: right → left).

    Args: as :func:`backward_reproject`, with ``src_color`` (B, 3, Hs, Ws), and ``backend``: ``"auto"`` |
        ``"torch"`` | ``"native"`` (see :mod:`stereorepro.native`; ``STEREOREPRO_BACKEND`` overrides it).

    Returns:
        color: (B, 3, H, W) reprojected colour, 0 where discarded.
        valid: (B, 1, H, W) bool.
        reason: (B, 1, H, W) uint8 :class:`Reason`.

    Example:
        >>> import torch
        >>> from stereorepro import stereo_reproject, intrinsics_from_fov
        >>> K = intrinsics_from_fov(60.0, 8, 6); T = torch.eye(4)[None]
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> color = torch.rand(1, 3, 6, 8)
        >>> out, valid, reason = stereo_reproject(color, depth, normal, K, T, depth, normal, K, T, 0.01, 0.1)
        >>> bool(torch.equal(out, color)), bool(valid.all()), int(reason.max())
        (True, True, 0)
    """
    check_shape(src_color, ["B", "3", "H", "W"], "src_color")
    _check_inputs(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                  dst_cam_from_world, _STEREO_NAMES)
    if _native.select_backend(backend, (src_color, src_depth, src_normal, dst_depth, dst_normal),
                              (src_K, src_cam_from_world, dst_K, dst_cam_from_world, position_threshold,
                               normal_threshold), soft) == "native":
        color, valid, reason, _ = _native.native_backward_reproject(
            src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
            dst_cam_from_world, position_threshold, normal_threshold, sampling, check=False, want_confidence=False)
        return color, valid, reason
    color, valid, reason, _ = backward_reproject(
        src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
        dst_cam_from_world, position_threshold, normal_threshold, sampling, soft, temperature, check=False)
    return color, valid, reason


def temporal_blend(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    confidence: Tensor,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
) -> tuple[Tensor, Tensor]:
    """Blend a (reprojected) history into the current frame: the paper's 20 % exponential moving average.

    ``a = max(1 / (n + 1), alpha)`` with ``warmup`` (a running mean until the EMA weight is reached, as in BMFR,
    the paper's group's code), else ``a = alpha``; ``out = (1 − a)·history + a·current``. Where the history is
    discarded the output restarts from the current sample with ``n = 1``. With hard tests ``confidence`` is the
    valid mask (0/1); with soft tests it is the accepted weight and the output mixes
    ``confidence·blend + (1 − confidence)·current``.

    Args:
        current_color: (B, C, H, W) this frame's samples.
        history_color: (B, C, H, W) history already warped into this frame.
        history_len: (B, 1, H, W) accumulated sample count n of the warped history (float).
        confidence: (B, 1, H, W) bool valid mask, or float in [0, 1].
        alpha: minimum weight of the current frame, in (0, 1] (float or 0-d tensor; learnable).
        warmup: use ``max(1/(n+1), alpha)`` instead of a fixed ``alpha``.
        max_history: cap of n.

    Returns:
        color: (B, C, H, W), dtype of ``current_color``.
        history_len: (B, 1, H, W) float, the new n (1 where restarted, capped at ``max_history``).
    """
    cd = _compute_dtype(current_color, history_color)
    cur = current_color.to(cd)
    hist = history_color.to(cd)
    n = history_len.to(cd).clamp_min(0.0)
    one = torch.ones((), dtype=cd, device=cur.device)
    a_min = _as_scalar(alpha, n).clamp(0.0, 1.0)
    a = torch.maximum(1.0 / (n + 1.0), a_min) if warmup else a_min.expand_as(n)
    # a == 1 gives exactly the current sample, even where the history is not finite
    blended = torch.where(a >= 1.0, cur, (1.0 - a) * hist + a * cur)
    n_next = torch.minimum(n + 1.0, _as_scalar(max_history, n))
    if confidence.dtype == torch.bool:
        out = torch.where(confidence, blended, cur)
        n_out = torch.where(confidence, n_next, one)
    else:
        s = confidence.to(cd)
        keep = s > 0
        out = torch.where(keep, s * torch.where(keep, blended, cur) + (1.0 - s) * cur, cur)
        n_out = torch.where(keep, s * n_next + (1.0 - s), one)
    return out.to(current_color.dtype), n_out


def temporal_reproject(
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
    backend: str = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """Temporal accumulation: warp the previous frame's history into this frame and blend (paper §4.1).

    Args:
        current_color: (B, 3, H, W) this frame's 1-spp colour.
        depth, normal: (B, 1, H, W), (B, 3, H, W) this frame's G-buffer.
        K, cam_from_world: (B, 3, 3), (B, 4, 4) this frame's camera.
        history_color: (B, 3, Hp, Wp) accumulated colour of the previous frame.
        history_len: (B, 1, Hp, Wp) its sample count (float; 0 = no history).
        prev_depth, prev_normal, prev_K, prev_cam_from_world: the previous frame's G-buffer and camera.
        position_threshold, normal_threshold, sampling, soft, temperature: see :func:`backward_reproject`.
        alpha, warmup, max_history: see :func:`temporal_blend`.
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` (see :mod:`stereorepro.native`).

    Returns:
        color: (B, 3, H, W) accumulated colour.
        history_len: (B, 1, H, W) float sample count for the next frame.
        valid: (B, 1, H, W) bool, where the history was kept.
    """
    bind: dict = {}
    check_shape(current_color, ["B", "3", "H", "W"], "current_color", bind)
    check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    bind_p: dict = {"B": bind.get("B")} if bind else {}
    check_shape(history_color, ["B", "3", "H", "W"], "history_color", bind_p)
    check_shape(history_len, ["B", "1", "H", "W"], "history_len", bind_p)
    check_floating(current_color, "current_color")
    check_floating(history_len, "history_len")
    _check_inputs(history_color, prev_depth, prev_normal, prev_K, prev_cam_from_world, depth, normal, K,
                  cam_from_world, _TEMPORAL_NAMES)
    if _native.select_backend(backend, (current_color, depth, normal, history_color, history_len, prev_depth,
                                        prev_normal),
                              (K, cam_from_world, prev_K, prev_cam_from_world, position_threshold, normal_threshold,
                               alpha), soft) == "native":
        return _native.native_temporal_reproject(
            current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth, prev_normal,
            prev_K, prev_cam_from_world, position_threshold, normal_threshold, alpha, warmup, max_history, sampling)
    values = torch.cat([history_color.to(_compute_dtype(history_color, history_len)),
                        history_len.to(_compute_dtype(history_color, history_len))], 1)
    warped, valid, _reason, conf = backward_reproject(
        values, prev_depth, prev_normal, prev_K, prev_cam_from_world, depth, normal, K, cam_from_world,
        position_threshold, normal_threshold, sampling, soft, temperature, check=False)
    confidence = conf if soft else valid
    color, n = temporal_blend(current_color, warped[:, :3], warped[:, 3:4], confidence, alpha, warmup, max_history)
    return color, n, valid


def reason_to_rgb(reason: Tensor) -> Tensor:
    """Colour a reason map like the paper's Figure 1 (green position, cyan normal, red out of frame).

    Args:
        reason: (B, 1, H, W) uint8 :class:`Reason` codes.

    Returns:
        (B, 3, H, W) float32 RGB in [0, 1].
    """
    check_shape(reason, ["B", "1", "H", "W"], "reason")
    lut = torch.tensor([REASON_COLORS[Reason(i)] for i in range(len(Reason))], dtype=torch.float32,
                       device=reason.device)  # Rx3
    rgb = lut[reason[:, 0].long().clamp(0, len(Reason) - 1)]  # BxHxWx3
    return rgb.permute(0, 3, 1, 2).contiguous()


def _threshold_param(value, learnable: bool) -> Tensor:
    t = torch.as_tensor(float(value), dtype=torch.float32)
    return nn.Parameter(t) if learnable else t


class _ReprojectionBase(nn.Module):
    def __init__(self, position_threshold: float, normal_threshold: float, sampling: str, soft: bool,
                 temperature: float, backend: str = "auto"):
        super().__init__()
        self.backend = _native.check_backend(backend)
        if sampling not in _SAMPLINGS:
            raise ValueError(f"sampling must be one of {_SAMPLINGS}, got {sampling!r}")
        for name, val in (("position_threshold", position_threshold), ("normal_threshold", normal_threshold)):
            if not float(val) > 0:
                raise ValueError(f"{name} must be > 0, got {val}")
        if soft and not temperature > 0:
            raise ValueError(f"temperature must be > 0, got {temperature}")
        self.sampling = sampling
        self.soft = bool(soft)
        self.temperature = float(temperature)
        if soft:  # learnable
            self.position_threshold = _threshold_param(position_threshold, True)
            self.normal_threshold = _threshold_param(normal_threshold, True)
        else:
            self.register_buffer("position_threshold", _threshold_param(position_threshold, False))
            self.register_buffer("normal_threshold", _threshold_param(normal_threshold, False))

    def extra_repr(self) -> str:
        return (f"position_threshold={float(self.position_threshold):g}, "
                f"normal_threshold={float(self.normal_threshold):g}, sampling={self.sampling!r}, soft={self.soft}")


class StereoReprojection(_ReprojectionBase):
    """Stereo backward reprojection (one eye → the other) with discard masks. See :func:`stereo_reproject`.

    Args:
        position_threshold: max |P_src − P_dst| in scene units (the scene's limit; paper §4.1).
        normal_threshold: max |N_src − N_dst| between unit shading normals.
        sampling: ``"bilinear"`` or ``"nearest"``.
        soft: smooth accept tests; the thresholds become learnable ``nn.Parameter``s.
        temperature: softness relative to the thresholds.
        backend: ``"auto"`` (native kernel when built, on CPU, float32, hard, without autograd), ``"torch"`` or
            ``"native"``; ``STEREOREPRO_BACKEND`` overrides it. See :mod:`stereorepro.native`.

    Forward:
        ``forward(src_color, src_depth, src_normal, src_K, src_cam_from_world,
        dst_depth, dst_normal, dst_K, dst_cam_from_world) -> (color, valid, reason)`` with shapes
        (B,3,Hs,Ws), (B,1,Hs,Ws), (B,3,Hs,Ws), (B,3,3), (B,4,4), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4)
        → (B,3,H,W), (B,1,H,W) bool, (B,1,H,W) uint8.
    """

    input_names = ["src_color", "src_depth", "src_normal", "src_K", "src_cam_from_world",
                   "dst_depth", "dst_normal", "dst_K", "dst_cam_from_world"]
    output_names = ["color", "valid", "reason"]

    def __init__(self, position_threshold: float, normal_threshold: float, sampling: str = "bilinear",
                 soft: bool = False, temperature: float = 0.1, backend: str = "auto"):
        super().__init__(position_threshold, normal_threshold, sampling, soft, temperature, backend)

    def forward(self, src_color: Tensor, src_depth: Tensor, src_normal: Tensor, src_K: Tensor,
                src_cam_from_world: Tensor, dst_depth: Tensor, dst_normal: Tensor, dst_K: Tensor,
                dst_cam_from_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return stereo_reproject(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                                dst_K, dst_cam_from_world, self.position_threshold, self.normal_threshold,
                                self.sampling, self.soft, self.temperature, self.backend)


class TemporalReprojection(_ReprojectionBase):
    """Temporal reprojection + EMA accumulation. See :func:`temporal_reproject`.

    Args:
        position_threshold, normal_threshold, sampling, soft, temperature, backend: as :class:`StereoReprojection`.
        alpha: minimum weight of the current frame (paper: 0.2); learnable when ``soft``.
        warmup: running mean until the weight reaches ``alpha`` (BMFR); ``False`` = fixed EMA.
        max_history: cap of the accumulated sample count.

    Forward:
        ``forward(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
        prev_normal, prev_K, prev_cam_from_world) -> (color, history_len, valid)`` with shapes
        (B,3,H,W), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4), (B,3,H,W), (B,1,H,W), (B,1,H,W), (B,3,H,W),
        (B,3,3), (B,4,4) → (B,3,H,W), (B,1,H,W) float, (B,1,H,W) bool.
    """

    input_names = ["current_color", "depth", "normal", "K", "cam_from_world", "history_color", "history_len",
                   "prev_depth", "prev_normal", "prev_K", "prev_cam_from_world"]
    output_names = ["color", "history_len_out", "valid"]

    def __init__(self, position_threshold: float, normal_threshold: float, alpha: float = 0.2,
                 warmup: bool = True, max_history: float = 255.0, sampling: str = "bilinear", soft: bool = False,
                 temperature: float = 0.1, backend: str = "auto"):
        super().__init__(position_threshold, normal_threshold, sampling, soft, temperature, backend)
        if not (0.0 < float(alpha) <= 1.0):
            raise ValueError(f"alpha must be in (0, 1], got {alpha}")
        if not max_history >= 1:
            raise ValueError(f"max_history must be >= 1, got {max_history}")
        self.warmup = bool(warmup)
        self.max_history = float(max_history)
        if soft:
            self.alpha = nn.Parameter(torch.as_tensor(float(alpha), dtype=torch.float32))
        else:
            self.register_buffer("alpha", torch.as_tensor(float(alpha), dtype=torch.float32))

    def extra_repr(self) -> str:
        return super().extra_repr() + f", alpha={float(self.alpha):g}, warmup={self.warmup}, max_history={self.max_history:g}"

    def forward(self, current_color: Tensor, depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor,
                history_color: Tensor, history_len: Tensor, prev_depth: Tensor, prev_normal: Tensor,
                prev_K: Tensor, prev_cam_from_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return temporal_reproject(current_color, depth, normal, K, cam_from_world, history_color, history_len,
                                  prev_depth, prev_normal, prev_K, prev_cam_from_world, self.position_threshold,
                                  self.normal_threshold, self.alpha, self.warmup, self.max_history, self.sampling,
                                  self.soft, self.temperature, self.backend)
