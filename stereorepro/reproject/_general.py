"""The general path of the backward reprojection: differentiable, traceable, exportable; soft or hard tests.

Every other implementation (the fast inference path, the native kernels) is defined by this one: they compute the
same per-element float arithmetic and are parity-tested against it. The discard tests are those of
:func:`stereorepro.reproject.backward_reproject`.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from .._checks import tracing
from .._tensors import as_scalar, compute_dtype, finite_or_zero  # noqa: F401 (the torch paths' names)
from ..camera import Warp, has_surface
from ._constants import COORD_MARGIN, OFF_FRAME, PLANE_BASE, PLANE_MIN_NORMAL2, PLANE_SLOPE
from .reason import Reason


#: Smallest accepted weight the soft path divides by (see :func:`backward_reproject`).
SOFT_DEN_FLOOR = 1e-3

#: Destination pixels per block in blocked inference (see :func:`backward_reproject`).
BLOCK_PIXELS = 1 << 16


def inference_only(inputs) -> bool:
    """True when no autograd graph is needed and nothing traces/exports/compiles the call: the row-blocked and
    fast paths apply (tracing and ONNX export always take the single-block general path)."""
    if tracing():
        return False
    return not (torch.is_grad_enabled() and any(isinstance(x, Tensor) and x.requires_grad for x in inputs))


def squared_thresholds(position_threshold, normal_threshold, wdt: torch.dtype, dev) -> Tensor:
    """(1, 2, 1, 1, 1) = (thr_p², thr_n²) in the compute dtype, squared exactly as the general path does."""
    like = torch.empty((), dtype=wdt, device=dev)
    thr_p, thr_n = as_scalar(position_threshold, like), as_scalar(normal_threshold, like)
    return torch.stack([thr_p * thr_p, thr_n * thr_n]).view(1, 2, 1, 1, 1)


#: Logit below which a soft accept weight is treated as saturated: ``sigmoid(-SOFT_LOGIT_FLOOR)`` ≈ 8.8e-27.
SOFT_LOGIT_FLOOR = 60.0


def _reciprocal(z: Tensor) -> Tensor:
    """``1 / z``; when ``z`` needs a gradient, the gradient is that of ``1 / max(z, tiny**0.4)`` (≈ 6e-16 in
    fp32): ``-1/z²`` would overflow for depths below ~5e-20 and turn a zero upstream gradient into NaN. The
    forward value is exactly ``1 / z``."""
    inv = 1.0 / z
    if not (z.requires_grad and torch.is_grad_enabled()):
        return inv
    safe = 1.0 / z.clamp_min(torch.finfo(z.dtype).tiny ** 0.4)
    return inv.detach() + (safe - safe.detach())


def _soft_distance2(diff: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """|P_src − P_dst|² for the soft test from its components, each clamped to ±1e18 (fp32; ±1e150 in fp64) and
    non-finite ones (inf − inf) read as the bound: the sum stays finite and so do its gradients, for huge depths
    (a renderer's FLT_MAX sky) too. The hard decisions use the unclamped distance."""
    lim = 1e18 if diff[0].dtype != torch.float64 else 1e150
    total = 0.0
    for d in diff:
        d = torch.where(torch.isfinite(d), d, torch.full((), lim, dtype=d.dtype, device=d.device))
        total = total + d.clamp(-lim, lim).square()
    return total


def _soft_accept(d2: Tensor, thr2: Tensor, tau: float) -> Tensor:
    """``sigmoid((thr² − d²) / (2·tau·thr²))``, with d² capped where the logit passes ``-SOFT_LOGIT_FLOOR`` (the
    weight is ~1e-26 there either way), thr² floored at 1e-30 and an infinite thr² giving 1, so that neither the
    value nor its gradients in ``d2`` and ``thr2`` overflow (for a huge but finite depth too)."""
    unbounded = torch.isinf(thr2)  # an infinite threshold accepts everything: weight 1
    one = torch.ones((), dtype=d2.dtype, device=d2.device)
    t2 = torch.where(unbounded, one, thr2).clamp_min(max(torch.finfo(d2.dtype).tiny, 1e-30))
    d2 = torch.minimum(d2, t2 * (1.0 + 2.0 * tau * SOFT_LOGIT_FLOOR))
    return torch.where(unbounded, one, torch.sigmoid((t2 - d2) / (2 * tau * t2)))


def source_features(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, wdt: torch.dtype) -> Tensor:
    """The source, sanitised once, as gatherable rows: (B, C+5, Hs·Ws) = values, depth, normal, flags.

    Non-finite values and missing surfaces become finite placeholders that the flags reject, so a rejected tap
    can never leak NaN/Inf (0 · NaN = NaN). Flags: bit 0 = has a surface, bit 1 = finite values. Purely per
    pixel, so it may equally be applied to already gathered pixels (B, ·, 1, M).
    """
    B, C = src_values.shape[:2]
    zero = torch.zeros((), dtype=wdt, device=src_values.device)
    one = torch.ones((), dtype=wdt, device=src_values.device)
    sv = src_values.to(wdt)
    sv_finite = torch.isfinite(sv.sum(1, keepdim=True))  # any NaN/Inf in a pixel makes its sum non-finite
    sz = src_depth.to(wdt)
    s_ok = has_surface(sz)
    flags = s_ok.to(wdt) + 2.0 * sv_finite.to(wdt)
    return torch.cat(
        [torch.where(sv_finite, sv, zero), torch.where(s_ok, sz, one), finite_or_zero(src_normal.to(wdt)), flags], 1
    ).reshape(B, C + 5, -1)


def feature_reader(feats: Tensor):
    """``read_taps`` for :func:`warp_pixels` over the whole source: index (B, T, ...) -> (B, C+5, T·...)."""

    def read_taps(index: Tensor) -> Tensor:
        B, Fg = feats.shape[:2]
        return torch.gather(feats, 2, index.reshape(B, 1, -1).expand(B, Fg, index[0].numel()))

    return read_taps


def raw_reader(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, b: int, wdt: torch.dtype):
    """``read_taps`` for :func:`warp_pixels` that sanitises only the gathered pixels of batch item ``b`` (the
    fast path's reason pass touches few pixels; building the whole feature table would cost more)."""
    Ws = src_values.shape[-1]

    def read_taps(index: Tensor) -> Tensor:
        flat = index.reshape(-1)
        yy, xx = flat // Ws, flat % Ws  # (C, Hs, Ws) inputs of any strides, indexed without a copy
        take = [x[b][:, yy, xx][None, :, None] for x in (src_values, src_depth, src_normal)]  # (1, ·, 1, M)
        return source_features(*take, wdt)

    return read_taps


def pixel_centres(r0: int, r1: int, W: int, wdt: torch.dtype, dev) -> tuple[Tensor, Tensor]:
    """Pixel centres of destination rows r0 .. r1 - 1: u_c (1, 1, 1, W), v_c (1, 1, h, 1)."""
    return (
        torch.arange(W, device=dev, dtype=wdt).view(1, 1, 1, W) + 0.5,
        torch.arange(r1 - r0, device=dev, dtype=wdt).view(1, 1, r1 - r0, 1) + (r0 + 0.5),
    )


class SourceTaps(NamedTuple):
    """How :func:`warp_pixels` reads the source view."""

    read: Callable[[Tensor], Tensor]  #: index (B, T, *S) into the source pixels -> (B, C+5, T·prod(S)) rows
    channels: int  #: C, the number of carried values
    height: int  #: Hs
    width: int  #: Ws
    rotation: Tensor | None = None  #: (B, 3, 3) the source ``cam_from_world``'s rotation (world motion, plane test)


class DstPixels(NamedTuple):
    """The destination pixels :func:`warp_pixels` reprojects: S = (h, W) rows, or (1, K) a list of pixels."""

    depth: Tensor  #: (B, 1, *S)
    normal: Tensor  #: (B, 3, *S)
    u_c: Tensor  #: pixel centres, broadcastable to (1, 1, *S)
    v_c: Tensor
    motion: Tensor | None = None  #: (B, 2, *S): source position = pixel centre + motion instead of the warp's
    motion_world: Tensor | None = None  #: (B, 3, *S): the destination point moved to the source instant


class TapTests(NamedTuple):
    """The accept tests and the sampling (see :func:`~stereorepro.reproject.backward_reproject`)."""

    position_threshold: object  #: float or 0-d tensor
    normal_threshold: object
    sampling: str  #: ``"bilinear"`` | ``"nearest"`` | ``"catmull_rom"``
    soft: bool = False
    temperature: float = 0.1
    position_test: str = "distance"  #: ``"distance"`` | ``"plane"`` (see :class:`~stereorepro.Thresholds`)


def dst_rows(
    dst_depth: Tensor,
    dst_normal: Tensor,
    motion: Tensor | None,
    motion_world: Tensor | None,
    r0: int,
    r1: int,
    wdt: torch.dtype,
) -> DstPixels:
    """Rows r0 .. r1 - 1 of the destination view as :class:`DstPixels`."""

    def rows(x):
        return None if x is None else x[:, :, r0:r1]

    u_c, v_c = pixel_centres(r0, r1, dst_depth.shape[-1], wdt, dst_depth.device)
    return DstPixels(rows(dst_depth), rows(dst_normal), u_c, v_c, rows(motion), rows(motion_world))


class _Projection(NamedTuple):
    u: Tensor  #: (B, 1, *S) source pixel x, clamped; OFF_FRAME where ``front`` is False
    v: Tensor
    q: Tensor  #: (B, 3, *S) the destination point in the source camera frame
    front: Tensor  #: (B, 1, *S) in front of the source camera with finite (u, v)
    dst_ok: Tensor  #: (B, 1, *S) the destination pixel has a surface
    ray: Tensor  #: (B, 3, *S) ray_src_from_pixel_dst @ [u, v, 1]: the view ray, in the source camera's axes
    z: Tensor  #: (B, 1, *S) the destination depth (1 where there is no surface)


def _project(warp: Warp, pixels: DstPixels, source: SourceTaps) -> _Projection:
    """Destination pixels -> source pixels (u, v) and source-camera points q."""
    wdt = warp.K_src_inv.dtype
    dev = pixels.depth.device
    B = warp.K_src_inv.shape[0]
    u_c, v_c = pixels.u_c, pixels.v_c
    ray = warp.ray_src_from_pixel_dst.reshape(B, 3, 3, 1, 1)  # ray[:, :, j] is column j as (B, 3, 1, 1)
    t = warp.t_src_from_dst.reshape(B, 3, 1, 1)
    hom = warp.pixel_src_from_pixel_dst.reshape(B, 9, 1, 1)  # hom[:, 3*i+j : 3*i+j+1] is entry (i, j)
    kt = warp.K_src_t.reshape(B, 3, 1, 1)
    z_dst = pixels.depth.to(wdt)
    dst_ok = has_surface(z_dst)  # Bx1xHxW
    one = torch.ones((), dtype=wdt, device=dev)
    z_dst = torch.where(dst_ok, z_dst, one)
    inv_z = _reciprocal(z_dst)
    wx = hom[:, 0:1] * u_c + hom[:, 1:2] * v_c + hom[:, 2:3] + kt[:, 0:1] * inv_z  # Bx1xHxW
    wy = hom[:, 3:4] * u_c + hom[:, 4:5] * v_c + hom[:, 5:6] + kt[:, 1:2] * inv_z
    wz = hom[:, 6:7] * u_c + hom[:, 7:8] * v_c + hom[:, 8:9] + kt[:, 2:3] * inv_z  # = q_z / z
    front = wz > 0
    wz = torch.where(front, wz, one)
    u = wx / wz
    v = wy / wz
    view_ray = ray[:, :, 0] * u_c + ray[:, :, 1] * v_c + ray[:, :, 2]
    q = view_ray * z_dst + t  # Bx3xHxW
    if pixels.motion is not None:  # the source position from the motion vectors, the source point moved with it
        u, v, q, front = _motion_source(pixels.motion, pixels.motion_world, source.rotation, u_c, v_c, q)
    front = front & torch.isfinite(u) & torch.isfinite(v)
    # Keep coordinates finite and in a small range: anything clamped is out of frame anyway.
    off = torch.full((), OFF_FRAME, dtype=wdt, device=dev)
    u = torch.where(front, u, off).clamp(-COORD_MARGIN, source.width + COORD_MARGIN)
    v = torch.where(front, v, off).clamp(-COORD_MARGIN, source.height + COORD_MARGIN)
    return _Projection(u, v, q, front, dst_ok, view_ray, z_dst)


def _taps(u: Tensor, v: Tensor, sampling: str, Hs: int, Ws: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The taps (T = 4 or 1) of source pixel (u, v): xi, yi, bilinear weights, in_frame and the flat source index
    (clamped into the frame), each BxTxHxW. ``"catmull_rom"`` starts from the bilinear taps (its fallback)."""
    if sampling != "nearest":
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
    in_frame = (xi >= 0) & (xi <= Ws - 1) & (yi >= 0) & (yi <= Hs - 1)
    # integer arithmetic: float32 would be exact only below 2^24 source pixels
    index = yi.clamp(0, Hs - 1).to(torch.int64) * Ws + xi.clamp(0, Ws - 1).to(torch.int64)  # BxTxHxW
    return xi, yi, wts, in_frame, index


def plane_terms(
    ray: list[Tensor], z: Tensor, normal: list[Tensor], rotation: Tensor
) -> tuple[list[Tensor], Tensor, Tensor]:
    """The per-pixel terms of the plane test (``Thresholds(position_test="plane")``), in the operation order
    every implementation uses.

    Args:
        ray: the 3 components of the destination pixel's view ray in the source camera's axes
            (``ray_src_from_pixel_dst @ [u, v, 1]``); z: its depth; normal: the 3 components of its world normal
            as given (cast to the compute dtype); rotation: (B, 9, ...) the source ``cam_from_world`` rotation,
            row-major, broadcastable against the components.

    Returns:
        nc: the normal in the source camera's axes, ``(R[i,0]·n0 + R[i,1]·n1) + R[i,2]·n2`` (0 where unusable);
        scale: ``z / (PLANE_BASE + PLANE_SLOPE·|nc·ray| / sqrt(ray·ray))``; usable: ``|n|² >= PLANE_MIN_NORMAL2``
        and finite. A tap passes iff ``plane² <= thr² · (scale·scale)``, ``plane = (nc0·d0 + nc1·d1) + nc2·d2``,
        d = P_dst − P_src in the source camera frame.
    """
    nn = (normal[0] * normal[0] + normal[1] * normal[1]) + normal[2] * normal[2]
    usable = (nn >= PLANE_MIN_NORMAL2) & (nn < math.inf)
    zero = torch.zeros((), dtype=z.dtype, device=z.device)
    n = [torch.where(usable, c, zero) for c in normal]
    nc = [
        (rotation[:, 3 * i : 3 * i + 1] * n[0] + rotation[:, 3 * i + 1 : 3 * i + 2] * n[1])
        + rotation[:, 3 * i + 2 : 3 * i + 3] * n[2]
        for i in range(3)
    ]
    nv = (nc[0] * ray[0] + nc[1] * ray[1]) + nc[2] * ray[2]
    rr = (ray[0] * ray[0] + ray[1] * ray[1]) + ray[2] * ray[2]
    cosine = nv.abs() / torch.sqrt(rr)
    base = torch.full((), PLANE_BASE, dtype=z.dtype, device=z.device)
    slope = torch.full((), PLANE_SLOPE, dtype=z.dtype, device=z.device)
    return nc, z / (base + slope * cosine), usable


class _PlaneTerms(NamedTuple):
    nc: list[Tensor]  #: 3 × (B, 1, *S) the destination normal in the source camera's axes
    thr2: Tensor  #: (B, 1, *S) the hard test's squared threshold (-1 where the normal is unusable)
    soft_thr2: Tensor  #: (B, 1, *S) the soft test's (the scale clamped, so that gradients stay finite)
    usable: Tensor  #: (B, 1, *S) bool


def _plane_of(proj: _Projection, dst_normal: Tensor, rotation: Tensor | None, tests: TapTests) -> _PlaneTerms | None:
    """The plane test's per-pixel terms (None for the distance test)."""
    if tests.position_test != "plane":
        return None
    wdt = proj.q.dtype
    B = proj.q.shape[0]
    rot = rotation.to(wdt).reshape(B, 9, *([1] * (proj.q.dim() - 2)))
    normal = dst_normal.to(wdt)
    nc, scale, usable = plane_terms(
        [proj.ray[:, i : i + 1] for i in range(3)], proj.z, [normal[:, i : i + 1] for i in range(3)], rot
    )
    thr_p = as_scalar(tests.position_threshold, scale)
    thr_p2 = thr_p * thr_p
    thr2 = torch.where(usable, thr_p2 * (scale * scale), torch.full((), -1.0, dtype=wdt, device=scale.device))
    soft = scale.clamp_max(1e18 if wdt != torch.float64 else 1e150)
    return _PlaneTerms(nc, thr2, thr_p2 * (soft * soft), usable)


def _soft_plane2(diff: tuple[Tensor, Tensor, Tensor], nc: list[Tensor]) -> Tensor:
    """The squared plane distance for the soft test: the components clamped as in :func:`_soft_distance2`, the
    distance clamped to the same bound, so that it and its gradients stay finite."""
    lim = 1e18 if diff[0].dtype != torch.float64 else 1e150
    d = [torch.where(torch.isfinite(x), x, torch.full((), lim, dtype=x.dtype, device=x.device)) for x in diff]
    d = [x.clamp(-lim, lim) for x in d]
    return ((nc[0] * d[0] + nc[1] * d[1]) + nc[2] * d[2]).clamp(-lim, lim).square()


class _TapTerms(NamedTuple):
    src_ok: Tensor  #: BxTxHxW the source tap has a surface
    finite: Tensor  #: BxTxHxW its values are finite
    diff: tuple[Tensor, Tensor, Tensor]  #: components of P_dst − P_src in the source camera frame
    d_n2: Tensor  #: BxTxHxW |N_src − N_dst|²
    pos_ok: Tensor
    nrm_ok: Tensor
    thr_p: Tensor  #: the thresholds as 0-d tensors of the compute dtype
    thr_n: Tensor
    plane: _PlaneTerms | None = None  #: the plane test's terms (None: the distance test)


def _tap_terms(
    g: Tensor,
    C: int,
    xi: Tensor,
    yi: Tensor,
    K_src_inv: Tensor,
    q: Tensor,
    dst_normal: Tensor,
    tests: TapTests,
    plane: _PlaneTerms | None = None,
) -> _TapTerms:
    """The per-tap position and normal tests on the gathered source rows ``g`` (B, C+5, T, *S); ``plane``: the
    plane test's terms (:func:`_plane_of`) instead of the distance test."""
    B = K_src_inv.shape[0]
    z_src = g[:, C]  # BxTxHxW, 1 where no surface
    n_src = g[:, C + 1 : C + 4]  # Bx3xTxHxW
    g_flags = g[:, C + 4]
    src_ok = (g_flags == 1.0) | (g_flags == 3.0)
    finite = g_flags >= 2.0
    ki = K_src_inv.reshape(B, 9, 1, 1)
    ut = xi + 0.5
    vt = yi + 0.5
    px = z_src * (ki[:, 0:1] * ut + ki[:, 1:2] * vt + ki[:, 2:3])
    py = z_src * (ki[:, 4:5] * vt + ki[:, 5:6])
    diff = (q[:, 0:1] - px, q[:, 1:2] - py, q[:, 2:3] - z_src)
    d_pos2 = diff[0].square() + diff[1].square() + diff[2].square()
    n_dst = finite_or_zero(dst_normal.to(K_src_inv.dtype)).unsqueeze(2)  # Bx3x1xHxW
    d_n2 = (n_src - n_dst).square().sum(1)  # BxTxHxW
    thr_p = as_scalar(tests.position_threshold, d_pos2)
    thr_n = as_scalar(tests.normal_threshold, d_n2)
    if plane is None:
        pos_ok = d_pos2 <= thr_p * thr_p
    else:
        nc = plane.nc
        distance = (nc[0] * diff[0] + nc[1] * diff[1]) + nc[2] * diff[2]
        pos_ok = distance * distance <= plane.thr2
    return _TapTerms(src_ok, finite, diff, d_n2, pos_ok, d_n2 <= thr_n * thr_n, thr_p, thr_n, plane)


def _reasons(terms: _TapTerms, in_frame: Tensor, wts: Tensor, proj: _Projection, valid: Tensor) -> Tensor:
    """Reason codes (uint8): first failing test per tap; an invalid pixel reports the max over its taps of
    weight > 0."""
    dev = valid.device

    def u8(r: Reason) -> Tensor:
        return torch.full((), int(r), dtype=torch.uint8, device=dev)

    code = torch.where(terms.finite, u8(Reason.KEPT), u8(Reason.NONFINITE))
    code = torch.where(terms.nrm_ok, code, u8(Reason.NORMAL))
    code = torch.where(terms.pos_ok, code, u8(Reason.POSITION))
    code = torch.where(terms.src_ok, code, u8(Reason.NO_SURFACE_SRC))
    code = torch.where(in_frame & (wts > 0), code, torch.where(wts > 0, u8(Reason.OUT_OF_FRAME), u8(Reason.KEPT)))
    reason = code.amax(1, keepdim=True)
    reason = torch.where(proj.front, reason, u8(Reason.BEHIND_CAMERA))
    reason = torch.where(proj.dst_ok, reason, u8(Reason.NO_SURFACE_DST))
    return torch.where(valid, u8(Reason.KEPT), reason)


def warp_pixels(
    source: SourceTaps, warp: Warp, pixels: DstPixels, tests: TapTests, out_dtype: torch.dtype
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The general path (differentiable, traceable): reproject destination pixels; see :func:`backward_reproject`.

    ``source.read`` returns :func:`source_features` rows; with ``pixels.motion_world``, ``source.rotation`` is
    needed (the position test compares the source tap with the moved point).

    Returns:
        values (B, C, *S), valid, reason, confidence (B, 1, *S).
    """
    wdt = warp.K_src_inv.dtype
    dev = pixels.depth.device
    B = warp.K_src_inv.shape[0]
    H, W = pixels.depth.shape[-2:]
    C = source.channels
    proj = _project(warp, pixels, source)
    xi, yi, wts, in_frame, index = _taps(proj.u, proj.v, tests.sampling, source.height, source.width)
    T = xi.shape[1]
    zero = torch.zeros((), dtype=wdt, device=dev)
    one = torch.ones((), dtype=wdt, device=dev)
    g = source.read(index).reshape(B, C + 5, T, H, W)
    plane = _plane_of(proj, pixels.normal, source.rotation, tests)
    terms = _tap_terms(g, C, xi, yi, warp.K_src_inv, proj.q, pixels.normal, tests, plane)

    pixel_ok = proj.dst_ok & proj.front  # Bx1xHxW
    base_ok = pixel_ok & in_frame & terms.src_ok & terms.finite  # BxTxHxW: the tests that stay hard
    hard = base_ok & terms.pos_ok & terms.nrm_ok
    if tests.soft:
        tau = float(tests.temperature)
        if plane is None:
            a_pos = _soft_accept(_soft_distance2(terms.diff), terms.thr_p * terms.thr_p, tau)
        else:
            a_pos = _soft_accept(_soft_plane2(terms.diff, plane.nc), plane.soft_thr2, tau)
            a_pos = torch.where(plane.usable, a_pos, zero)
        a_soft = a_pos * _soft_accept(terms.d_n2, terms.thr_n * terms.thr_n, tau)
        accept_w = torch.where(base_ok, a_soft, zero)
    else:
        accept_w = hard.to(wdt)

    ws = wts * accept_w  # BxTxHxW
    den = ws.sum(1, keepdim=True)  # Bx1xHxW
    num = (ws.unsqueeze(1) * g[:, :C]).sum(2)  # BxCxHxW (the gathered values are finite: sanitised above)
    has_w = den > 0
    # Soft weights can be tiny but positive; dividing by them gives gradients of ~num/den² that overflow. The soft
    # path renormalises by max(den, SOFT_DEN_FLOOR): a pixel that is all but rejected fades to 0 instead.
    den_safe = den.clamp_min(SOFT_DEN_FLOOR) if tests.soft else torch.where(has_w, den, one)
    values = torch.where(has_w, num / den_safe, zero)
    if tests.sampling == "catmull_rom":
        values = catmull_rom_pixels(source, warp, pixels, tests, values)
    valid = (wts * hard.to(wdt)).sum(1, keepdim=True) > 0
    reason = _reasons(terms, in_frame, wts, proj, valid)
    return values.to(out_dtype), valid, reason, den


#: Offsets of the Catmull-Rom footprint's columns (rows) from the bilinear tap (0, 0), x0 = floor(u − 0.5).
CUBIC_OFFSETS = (-1.0, 0.0, 1.0, 2.0)


def catmull_rom_weights(f: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Catmull-Rom weights (Keys' cubic convolution with a = −0.5) of the taps at offsets −1, 0, 1, 2 from
    ``floor(x)``, for the fraction ``f = x − floor(x)`` in [0, 1), evaluated in this operation order by every
    implementation: ``((−0.5·f + 1)·f − 0.5)·f``, ``(1.5·f − 2.5)·f·f + 1``, ``((−1.5·f + 2)·f + 0.5)·f``,
    ``(0.5·f − 0.5)·f·f``. They sum to 1 (to rounding); f = 0 gives (0, 1, 0, 0).

    Examples:
        >>> import torch
        >>> from stereorepro.reproject._general import catmull_rom_weights
        >>> [round(float(w), 4) for w in catmull_rom_weights(torch.tensor(0.5))]
        [-0.0625, 0.5625, 0.5625, -0.0625]
    """
    return (
        ((-0.5 * f + 1.0) * f - 0.5) * f,
        (1.5 * f - 2.5) * f * f + 1.0,
        ((-1.5 * f + 2.0) * f + 0.5) * f,
        (0.5 * f - 0.5) * f * f,
    )


def catmull_rom_pixels(source: SourceTaps, warp: Warp, pixels: DstPixels, tests: TapTests, values: Tensor) -> Tensor:
    """The ``"catmull_rom"`` values of destination pixels whose bilinear result is ``values`` (B, C, *S).

    The footprint is the 4×4 source pixels around the bilinear taps (columns x0 − 1 .. x0 + 2, rows likewise).
    Where every one of the 16 lies in the frame with a surface, finite values and passes the position and normal
    tests (hard decisions, also under soft tests), the result is the separable 16-tap Catmull-Rom sum (row sums
    first, each over its four columns in order, then the rows in order) clamped at 0 per channel; elsewhere the
    pixel keeps ``values``. Differentiable in the values and the source position.
    """
    B, C = warp.K_src_inv.shape[0], source.channels
    S = pixels.depth.shape[2:]
    proj = _project(warp, pixels, source)
    x, y = proj.u - 0.5, proj.v - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    wx, wy = catmull_rom_weights(x - x0), catmull_rom_weights(y - y0)
    xi = torch.cat([x0 + dx for dy in CUBIC_OFFSETS for dx in CUBIC_OFFSETS], 1)  # (B, 16, *S), row-major
    yi = torch.cat([y0 + dy for dy in CUBIC_OFFSETS for dx in CUBIC_OFFSETS], 1)
    Hs, Ws = source.height, source.width
    in_frame = (xi >= 0) & (xi <= Ws - 1) & (yi >= 0) & (yi <= Hs - 1)
    index = yi.clamp(0, Hs - 1).to(torch.int64) * Ws + xi.clamp(0, Ws - 1).to(torch.int64)
    g = source.read(index).reshape(B, C + 5, 16, *S)
    plane = _plane_of(proj, pixels.normal, source.rotation, tests)
    terms = _tap_terms(g, C, xi, yi, warp.K_src_inv, proj.q, pixels.normal, tests, plane)
    tap_ok = in_frame & terms.src_ok & terms.finite & terms.pos_ok & terms.nrm_ok
    ok = tap_ok.all(1, keepdim=True) & proj.dst_ok & proj.front
    total = None
    for j in range(4):
        row = wx[0] * g[:, :C, 4 * j] + wx[1] * g[:, :C, 4 * j + 1] + wx[2] * g[:, :C, 4 * j + 2]
        row = row + wx[3] * g[:, :C, 4 * j + 3]
        total = wy[j] * row if total is None else total + wy[j] * row
    return torch.where(ok, total.clamp_min(0.0), values.to(total.dtype))


def _motion_source(
    motion: Tensor, motion_world: Tensor | None, src_rotation: Tensor, u_c: Tensor, v_c: Tensor, q: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Source coordinates (u, v) = pixel centre + motion, and the expected source-camera point
    ``q + R_src · motion_world``. Non-finite motion (or world motion) sends the pixel out of the frame
    (``OUT_OF_FRAME``); ``front`` is the moved point's ``z > 0``."""
    wdt = q.dtype
    mo = motion.to(wdt)
    ok = torch.isfinite(mo).all(1, keepdim=True)
    zero = torch.zeros((), dtype=wdt, device=q.device)
    if motion_world is not None:
        mw = motion_world.to(wdt)
        ok = ok & torch.isfinite(mw).all(1, keepdim=True)
        mw = torch.where(ok, mw, zero)
        R = src_rotation.to(wdt).reshape(q.shape[0], 3, 3, *([1] * (q.dim() - 2)))
        q = q + (R[:, :, 0] * mw[:, 0:1] + R[:, :, 1] * mw[:, 1:2] + R[:, :, 2] * mw[:, 2:3])
    far = torch.full((), OFF_FRAME, dtype=wdt, device=q.device)
    u = torch.where(ok, u_c + torch.where(ok, mo[:, 0:1], zero), far)
    v = torch.where(ok, v_c + torch.where(ok, mo[:, 1:2], zero), far)
    return u, v, q, q[:, 2:3] > 0


def general_reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    warp: Warp,
    position_threshold,
    normal_threshold,
    sampling: str,
    soft: bool,
    temperature: float,
    inference: bool,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    src_rotation: Tensor | None = None,
    position_test: str = "distance",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`~stereorepro.reproject.backward_reproject` on the general path, with the cameras composed;
    ``src_rotation`` (B, 3, 3) is needed with ``motion_world`` and with ``position_test="plane"``.

    In inference (``inference``: no autograd graph, nothing traces) on large images, destination rows are
    processed in blocks of :data:`BLOCK_PIXELS`, so that the per-tap intermediates stay in cache (the op is
    memory-bound); results are bit-identical to one block. Gradients and tracing need one graph.
    """
    wdt = warp.K_src_inv.dtype
    dev = dst_depth.device
    B, C, Hs, Ws = src_values.shape
    H, W = dst_depth.shape[-2:]
    feats = source_features(src_values, src_depth, src_normal, wdt)
    source = SourceTaps(feature_reader(feats), C, Hs, Ws, src_rotation)
    tests = TapTests(position_threshold, normal_threshold, sampling, soft, temperature, position_test)
    rows = max(1, BLOCK_PIXELS // max(1, B * W)) if inference else None
    if rows is None or rows >= H:
        return warp_pixels(
            source, warp, dst_rows(dst_depth, dst_normal, motion, motion_world, 0, H, wdt), tests, src_values.dtype
        )
    values = torch.empty(B, C, H, W, dtype=src_values.dtype, device=dev)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=dev)
    reason = torch.empty(B, 1, H, W, dtype=torch.uint8, device=dev)
    den = torch.empty(B, 1, H, W, dtype=wdt, device=dev)
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        out = warp_pixels(
            source, warp, dst_rows(dst_depth, dst_normal, motion, motion_world, r0, r1, wdt), tests, src_values.dtype
        )
        for buf, o in zip((values, valid, reason, den), out):
            buf[:, :, r0:r1] = o
    return values, valid, reason, den
