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

import torch
from torch import Tensor, nn

from . import native as _native
from ._checks import check_camera, check_device, check_floating, check_shape
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
    bind_src: dict = {}
    check_shape(src_values, ["B", "C", "H", "W"], names["src_values"], bind_src)
    check_shape(src_depth, ["B", "1", "H", "W"], names["src_depth"], bind_src)
    check_shape(src_normal, ["B", "3", "H", "W"], names["src_normal"], bind_src)
    bind_b = {"B": bind_src["B"]} if "B" in bind_src else {}
    check_shape(dst_depth, ["B", "1", "H", "W"], names["dst_depth"], dict(bind_b))
    check_shape(dst_normal, ["B", "3", "H", "W"], names["dst_normal"], {**bind_b, "H": dst_depth.shape[-2],
                                                                         "W": dst_depth.shape[-1]})
    check_camera(src_K, src_cam_from_world, names["src"], dict(bind_b))
    check_camera(dst_K, dst_cam_from_world, names["dst"], dict(bind_b))
    for role, t in (("src_values", src_values), ("src_depth", src_depth), ("src_normal", src_normal),
                    ("dst_depth", dst_depth), ("dst_normal", dst_normal)):
        check_floating(t, names[role])
    check_device({names["src_values"]: src_values, names["src_depth"]: src_depth,
                  names["src_normal"]: src_normal, names["src"] + "_K": src_K,
                  names["src"] + "_cam_from_world": src_cam_from_world, names["dst_depth"]: dst_depth,
                  names["dst_normal"]: dst_normal, names["dst"] + "_K": dst_K,
                  names["dst"] + "_cam_from_world": dst_cam_from_world}, "reprojection")


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

    Returns:
        M: (B, 3, 3), t: (B, 3, 1), P: (B, 3, 3), kt: (B, 3, 1), Ks_inv: (B, 3, 3) = K_src^-1.
    """
    src_from_dst = _snap(src_cam_from_world.double() @ invert_rigid(dst_cam_from_world.double()))
    M64 = src_from_dst[:, :3, :3] @ _inverse_intrinsics(dst_K.double())
    t64 = src_from_dst[:, :3, 3:]
    P = _snap(src_K.double() @ M64).to(dtype)
    kt = (src_K.double() @ t64).to(dtype)
    Ks_inv = _inverse_intrinsics(src_K.double()).to(dtype)
    return M64.to(dtype), t64.to(dtype), P, kt, Ks_inv


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
    feats = _source_features(src_values, src_depth, src_normal, cd)
    warp = dict(feats=feats, C=C, Hs=Hs, Ws=Ws, cams=(M, t, P, kt, Ks_inv), position_threshold=position_threshold,
                normal_threshold=normal_threshold, sampling=sampling, soft=soft, temperature=temperature,
                out_dtype=src_values.dtype)
    rows = _row_block(B, H, W, (src_values, src_depth, src_normal, dst_depth, dst_normal, src_K, dst_K,
                                src_cam_from_world, dst_cam_from_world, position_threshold, normal_threshold))
    if rows is None:
        return _warp_rows(dst_depth=dst_depth, dst_normal=dst_normal, row0=0, **warp)
    # Inference on large images: destination rows in blocks, so that the per-tap intermediates stay in cache
    # (the op is memory-bound). Results are bit-identical to one block (same arithmetic per pixel).
    values = torch.empty(B, C, H, W, dtype=src_values.dtype, device=dev)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=dev)
    reason = torch.empty(B, 1, H, W, dtype=torch.uint8, device=dev)
    den = torch.empty(B, 1, H, W, dtype=cd, device=dev)
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        out = _warp_rows(dst_depth=dst_depth[:, :, r0:r1], dst_normal=dst_normal[:, :, r0:r1], row0=r0, **warp)
        for buf, o in zip((values, valid, reason, den), out):
            buf[:, :, r0:r1] = o
    return values, valid, reason, den


#: Smallest accepted weight the soft path divides by (see :func:`backward_reproject`).
SOFT_DEN_FLOOR = 1e-3

#: Destination pixels per block in blocked inference (see :func:`backward_reproject`).
BLOCK_PIXELS = 1 << 16


def _row_block(B: int, H: int, W: int, inputs) -> int | None:
    """Rows per block; None = one block (gradients or tracing need one graph, or the image is small)."""
    if _tracing_or_exporting():
        return None
    if torch.is_grad_enabled() and any(isinstance(x, Tensor) and x.requires_grad for x in inputs):
        return None
    rows = max(1, BLOCK_PIXELS // max(1, B * W))
    return None if rows >= H else rows


def _tracing_or_exporting() -> bool:
    return torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or torch.compiler.is_compiling()


def _source_features(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, cd: torch.dtype) -> Tensor:
    """The source, sanitised once, as gatherable rows: (B, C+5, Hs·Ws) = values, depth, normal, flags.

    Non-finite values and missing surfaces become finite placeholders that the flags reject, so a rejected tap
    can never leak NaN/Inf (0 · NaN = NaN). Flags: bit 0 = has a surface, bit 1 = finite values.
    """
    B, C, Hs, Ws = src_values.shape
    zero = torch.zeros((), dtype=cd, device=src_values.device)
    one = torch.ones((), dtype=cd, device=src_values.device)
    sv = src_values.to(cd)
    sv_finite = torch.isfinite(sv.sum(1, keepdim=True))  # any NaN/Inf in a pixel makes its sum non-finite
    sz = src_depth.to(cd)
    s_ok = has_surface(sz)
    flags = s_ok.to(cd) + 2.0 * sv_finite.to(cd)
    return torch.cat([torch.where(sv_finite, sv, zero), torch.where(s_ok, sz, one),
                      _finite_or_zero(src_normal.to(cd)), flags], 1).reshape(B, C + 5, Hs * Ws)


def _warp_rows(feats: Tensor, C: int, Hs: int, Ws: int, cams, dst_depth: Tensor, dst_normal: Tensor, row0: int,
               position_threshold, normal_threshold, sampling: str, soft: bool, temperature: float,
               out_dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Reproject destination rows ``row0 .. row0 + h`` (dst_depth (B, 1, h, W)); see :func:`backward_reproject`."""
    M, t, P, kt, Ks_inv = cams
    cd = feats.dtype
    dev = dst_depth.device
    B = feats.shape[0]
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
    v_c = torch.arange(H, device=dev, dtype=cd).view(1, 1, H, 1) + (row0 + 0.5)
    u_c = torch.arange(W, device=dev, dtype=cd).view(1, 1, 1, W) + 0.5
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
    g = torch.gather(feats, 2, index.reshape(B, 1, T * H * W).expand(B, C + 5, T * H * W))
    g = g.reshape(B, C + 5, T, H, W)
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
            dst_cam_from_world, position_threshold, normal_threshold, sampling, check=False)
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
