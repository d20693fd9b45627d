"""The export formulation of the backward reprojection: what :func:`~stereorepro.export_onnx` writes for hard
tests, chosen for graph runtimes (onnxruntime, ``onnx.reference``) rather than for torch eager.

A runtime evaluates an exported graph node by node on whole-image tensors, so what costs there is the number of
whole-image elements each node reads and writes, and some node kinds far more than others per element (``Where``
with a tensor operand and ``Gather`` of rows far more than ``Add``, ``Mul`` or comparisons; ``GatherElements``
dominates the graph's time). The general path (:mod:`._general`) traced as it is builds a (B, C+5, 4·H·W)
``GatherElements`` index (an int64 tensor the size of the image × taps × channels) and some forty whole-image
``Where`` / ``Cast`` nodes for the per-tap tests. Here instead:

* the source is sanitised once into **planar tables**, one (B, Hp·Wp) table per channel of a padded image
  (``TABLE_PAD`` pixels of border, so that every tap of a clamped coordinate lands in it): values, normal (3), and
  ``z`` of the pixels a tap may accept (NaN where there is no surface, a value is not finite, or on the border),
  so that a single comparison rejects them; each tap reads them with ``GatherElements`` on int32 indices of
  (B, H·W) elements;
* the accept test of a tap is two comparisons and an ``And``; the accepted weights are summed tap by tap (taps
  unrolled: four, or one for nearest sampling), so the runtime reuses one tap's buffers for the next;
* **reasons** are computed for the pixels that need them only (a surface, in front of the source camera, and
  nothing accepted: ``Compress`` and ``ScatterElements``, usually a few per cent of the image): their taps' codes
  (``OUT_OF_FRAME`` off the image, ``NO_SURFACE_SRC``, ``NONFINITE``) from the tables and the padded depth, and
  the tests repeated with the real depth, on (taps, K) tensors (one node per step for all taps: a node on K
  elements costs mostly its launch); the rest follows from the depth and the projection in arithmetic (exact small
  integers);
* non-finite normals are zeroed by ``ThresholdedRelu(alpha=-inf)`` (a comparison ``x > -inf``, spec-defined
  for NaN and ±inf) of ``x − (x − x)`` (NaN where ``x`` is not finite) instead of ``Where``; values (which a
  rejected tap multiplies by 0) only need to be finite: one ``ThresholdedRelu`` and a ``Clip``;
* **rectified** (the caller declares a parallel rig at one instant, :func:`~stereorepro.camera.rectify_warp`):
  the vertical fraction of every tap is 0, so only the two taps of row y0 are read; the y0 + 1 taps have weight 0
  and contribute nothing to any output;
* **catmull_rom** sampling: the bilinear result above, then the 4×4 footprints of the general path
  (:func:`._general.catmull_rom_pixels`, 16 ``GatherElements`` rows per pixel) replace it where all 16 taps pass.

The per-element float arithmetic that decides a result (projection, tap coordinates, weights, squared distances,
comparisons) is that of :func:`._general.warp_pixels`, in the same order, so ``valid`` and ``reason`` are
identical and colours agree to rounding (the weighted sum is accumulated tap by tap).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ..camera import Warp, has_surface
from ._constants import COORD_MARGIN, OFF_FRAME, TABLE_PAD, TAP_OK_CODE
from ._general import (
    SourceTaps,
    TapTests,
    as_scalar,
    catmull_rom_pixels,
    compute_dtype,
    dst_rows,
    feature_reader,
    finite_or_zero,
    plane_terms,
    source_features,
)
from .reason import Reason


def _const(value, wdt: torch.dtype, dev) -> Tensor:
    return torch.full((), float(value), dtype=wdt, device=dev)


def _column(values, dtype: torch.dtype, dev) -> Tensor:
    """A (T, 1) constant (``torch.full`` pieces: ``torch.tensor`` of a list warns while tracing)."""
    return torch.cat([torch.full((1, 1), v, dtype=dtype, device=dev) for v in values])


def _finite(x: Tensor) -> Tensor:
    """``isfinite(x)`` as ``|x| < inf`` (NaN compares false): two cheap nodes, where the exporter writes
    ``isfinite`` as a cast to double, IsInf, IsNaN, Or and Not."""
    return x.abs() < math.inf


class _ZeroNonFinite(torch.autograd.Function):
    """``x`` with NaN and ±inf replaced by 0 (``finite_or_zero``). Exported as ``TR(x − (x − x))`` with
    ``TR = ThresholdedRelu(alpha=-inf)`` (``x if x > -inf else 0``): ``x − x`` is 0 where ``x`` is finite and NaN
    elsewhere, so ``x − (x − x)`` is ``x`` or NaN, which TR makes 0: three streaming nodes instead of a mask and a
    ``Where``. onnxruntime has ThresholdedRelu in float32 only, so float64 graphs keep ``Where``."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # noqa: D102 (what eager runs: the same values)
        return finite_or_zero(x)

    @staticmethod
    def symbolic(g, x):  # noqa: D102
        return g.op("ThresholdedRelu", g.op("Sub", x, g.op("Sub", x, x)), alpha_f=-math.inf)


class _Pick(torch.autograd.Function):
    """Indices (K,) int64 of the True elements of a 1-D bool mask. Exported as ``Compress(Range(0, n), mask)``:
    onnxruntime's ``NonZero`` (what ``torch.nonzero`` exports to) is slower."""

    @staticmethod
    def forward(ctx, mask: Tensor) -> Tensor:  # noqa: D102
        return torch.nonzero(mask).reshape(-1)

    @staticmethod
    def symbolic(g, mask):  # noqa: D102
        def const(v):
            return g.op("Constant", value_t=torch.tensor(v, dtype=torch.int64))

        n = g.op("Squeeze", g.op("Shape", mask), const([0]))
        return g.op("Compress", g.op("Range", const(0), n, const(1)), mask, axis_i=0)


def _pick(mask: Tensor) -> Tensor:
    return _Pick.apply(mask) if torch.onnx.is_in_onnx_export() else _Pick.forward(None, mask)


class _SomeFinite(torch.autograd.Function):
    """``x`` with NaN and -inf replaced by 0 and +inf by the largest finite value: finite, and ``x`` wherever
    ``x`` is finite. Enough for values that a rejected tap multiplies by 0; exported as two nodes,
    ``Clip(ThresholdedRelu(x, alpha=-inf), -max, max)`` (float32)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # noqa: D102
        return torch.nan_to_num(x, 0.0, torch.finfo(x.dtype).max, 0.0)

    @staticmethod
    def symbolic(g, x):  # noqa: D102
        big = torch.finfo(torch.float32).max
        lo, hi = (g.op("Constant", value_t=torch.tensor(v, dtype=torch.float32)) for v in (-big, big))
        return g.op("Clip", g.op("ThresholdedRelu", x, alpha_f=-math.inf), lo, hi)


def _export_or_eager(fn, x: Tensor) -> Tensor:
    """``fn``'s exported form while exporting float32 (onnxruntime has ThresholdedRelu in float32 only), else
    its eager form."""
    if x.dtype == torch.float32 and torch.onnx.is_in_onnx_export():
        return fn.apply(x)
    return fn.forward(None, x)


def _finite_or_zero(x: Tensor) -> Tensor:
    return _export_or_eager(_ZeroNonFinite, x)


def source_tables(src_values: Tensor, src_depth: Tensor, src_normal: Tensor, wdt: torch.dtype) -> list[Tensor]:
    """The source as planar tables of (B, Np) elements, Np = (Hs + 2·TABLE_PAD)·(Ws + 2·TABLE_PAD).

    Returns:
        C + 4 tables: values (C; finite, and exact where all the pixel's values are finite), z where a tap
            may be accepted (NaN where there is no surface, a value of the pixel is not finite, and on the border),
            normal (3; non-finite components 0, as in :func:`._general.source_features`).
    """
    B, C = src_values.shape[:2]
    sv = src_values.to(wdt)
    total = sv[:, 0:1]
    for c in range(1, C):  # left to right, as the sum over channels of the general path and the native kernels
        total = total + sv[:, c : c + 1]
    finite = _finite(total)
    sz = src_depth.to(wdt)
    nan = (has_surface(sz) & finite).to(wdt).reciprocal() - 1.0  # 0 where a tap may be accepted, inf elsewhere ...
    z_acc = sz + (nan - nan)  # ... inf - inf = NaN: z where a tap may be accepted, NaN elsewhere
    vals = _export_or_eager(_SomeFinite, sv)  # finite; exact where the pixel may be accepted
    normal = _finite_or_zero(src_normal.to(wdt))
    pad = (TABLE_PAD,) * 4

    def table(x: Tensor, border: float) -> Tensor:
        return F.pad(x, pad, value=border).reshape(B, -1)

    taps = (
        [table(vals[:, c : c + 1], 0.0) for c in range(C)]
        + [table(z_acc, math.nan)]
        + [table(normal[:, c : c + 1], 0.0) for c in range(3)]
    )
    return taps


class _TapGeometry:
    """Per destination pixel (all of them, or the K whose reasons are needed): the tap coordinates and the
    terms of :func:`._general.warp_pixels`' per-tap arithmetic, each computed once, when a tap first needs it.

    Args:
        x0, y0: the tap (0, 0) coordinates; fx, fy: bilinear fractions (None for nearest sampling).
        ki: the 9 entries of K_src^-1 (per batch (B, 1), or per pixel); q: the destination point in the source
            camera (3); nd: the sanitised destination normal (3); thr_p2, thr_n2: squared thresholds; plane: the
            plane test's normal in the source camera's axes (3) and squared threshold per pixel, or None (the
            distance test).
    """

    def __init__(self, x0, y0, fx, fy, ki, q, nd, thr_p2, thr_n2, plane=None):
        self.x0, self.y0, self.fx, self.fy, self.ki, self.q, self.nd = x0, y0, fx, fy, ki, q, nd
        self.thr_p2, self.thr_n2, self.plane = thr_p2, thr_n2, plane
        self._kx, self._ky, self._g = {}, {}, {}

    def position_ok(self, z: Tensor, dx, dy) -> Tensor:
        """|P_src − q|² <= thr² of tap (x0 + dx, y0 + dy) of depth z: px = z·((ki0·ut + ki1·vt) + ki2),
        py = z·(ki4·vt + ki5) with ut = x + 0.5, vt = y + 0.5 of the tap (warp_pixels' order). ``dx``, ``dy``:
        ints (the terms of each are cached), or (T, 1) float tensors of stacked taps."""
        ki = self.ki
        cached = not isinstance(dx, Tensor)  # stacked taps are computed once
        kx = self._kx.get(dx) if cached else None
        if kx is None:
            kx = ki[0] * (self.x0 + (dx + 0.5))
            if cached:
                self._kx[dx] = kx
        kys = self._ky.get(dy) if cached else None
        if kys is None:
            vt = self.y0 + (dy + 0.5)
            kys = ki[1] * vt, ki[4] * vt + ki[5]
            if cached:
                self._ky[dy] = kys
        ky, ky_p = kys
        px = z * (kx + ky + ki[2])
        py = z * ky_p
        q = self.q
        if self.plane is not None:  # the plane test: (nc0·d0 + nc1·d1) + nc2·d2, squared, against thr²·scale²
            nc, thr2 = self.plane
            dist = (nc[0] * (q[0] - px) + nc[1] * (q[1] - py)) + nc[2] * (q[2] - z)
            return dist * dist <= thr2
        return (q[0] - px).square() + (q[1] - py).square() + (q[2] - z).square() <= self.thr_p2

    def normal_ok(self, n: list[Tensor]) -> Tensor:
        """|N_src − N_dst|² <= thr_n² (components summed in order)."""
        nd = self.nd
        return (n[0] - nd[0]).square() + (n[1] - nd[1]).square() + (n[2] - nd[2]).square() <= self.thr_n2

    def weight(self, dx: int, dy: int) -> Tensor | None:
        """The bilinear weight of tap (x0 + dx, y0 + dy): (1 − fx | fx)·(1 − fy | fy); None for nearest."""
        if self.fx is None:
            return None
        for axis, f in (("x", self.fx), ("y", self.fy)):
            if axis not in self._g:
                self._g[axis] = 1 - f
        return (self.fx if dx else self._g["x"]) * (self.fy if dy else self._g["y"])


class _Sizes(NamedTuple):
    """Image sizes (ints in eager; traced sizes while exporting, so the graph keeps symbolic dims)."""

    B: object  #: batch, from the source values
    H: object  #: destination height
    W: object  #: destination width
    Hs: object  #: source height
    Ws: object  #: source width
    Wp: object  #: source width with the border of the tables, Ws + 2·TABLE_PAD


def _project(
    warp: Warp, dst_depth: Tensor, size: _Sizes, motion: tuple | None = None
) -> tuple[Tensor, Tensor, list[Tensor], Tensor, Tensor, list[Tensor]]:
    """Destination pixels -> source coordinates and source-camera points (warp_pixels' arithmetic), on (B, H, W)
    with the pixel centres broadcast ((1, 1, W) and (1, H, 1)). With ``motion`` = (motion (B, 2, H, W),
    motion_world (B, 3, H, W) or None, source rotation (B, 3, 3)): the coordinates and moved points of
    :func:`_motion_source`.

    Returns:
        u, v: (B, H·W) source coordinates, clamped; OFF_FRAME where the pixel has no surface or is not in front of
            the source camera (such pixels read border taps only; their reason follows from depth and projection).
        q: 3 × (B, H·W) the destination point in the source camera frame. front, dst_ok: (B, H, W) bool.
        ray: 3 × (B, H·W) the view ray ``ray_src_from_pixel_dst @ [u, v, 1]`` (for the plane test).
    """
    hom, kt, ray, t = warp.pixel_src_from_pixel_dst, warp.K_src_t, warp.ray_src_from_pixel_dst, warp.t_src_from_dst
    wdt = warp.K_src_inv.dtype
    dev = dst_depth.device
    B, H, W, Hs, Ws = size.B, size.H, size.W, size.Hs, size.Ws

    def coef(A: Tensor, i: int, j: int) -> Tensor:  # (B, 1, 1) entry of a (B, 3, k) matrix
        return A[:, i, j].reshape(B, 1, 1)

    u_c = (torch.arange(W, dtype=wdt, device=dev) + 0.5).view(1, 1, -1)
    v_c = (torch.arange(H, dtype=wdt, device=dev) + 0.5).view(1, -1, 1)
    z_dst = dst_depth.to(wdt).reshape(B, H, W)
    dst_ok = has_surface(z_dst)
    inv_z = 1.0 / z_dst  # without a surface: anything (the pixel is sent to the border below)
    wx = coef(hom, 0, 0) * u_c + coef(hom, 0, 1) * v_c + coef(hom, 0, 2) + coef(kt, 0, 0) * inv_z
    wy = coef(hom, 1, 0) * u_c + coef(hom, 1, 1) * v_c + coef(hom, 1, 2) + coef(kt, 1, 0) * inv_z
    wz = coef(hom, 2, 0) * u_c + coef(hom, 2, 1) * v_c + coef(hom, 2, 2) + coef(kt, 2, 0) * inv_z
    view_ray = [coef(ray, i, 0) * u_c + coef(ray, i, 1) * v_c + coef(ray, i, 2) for i in range(3)]
    q = [view_ray[i] * z_dst + coef(t, i, 0) for i in range(3)]
    if motion is None:
        u = wx / wz  # wz <= 0: sent to the border below
        v = wy / wz
        front = (wz > 0) & _finite(u) & _finite(v)
        sent = front & dst_ok
    else:
        u, v, front, moved = _motion_source(motion, q, u_c, v_c, size)
        sent = front & dst_ok & moved
    q = [x.reshape(B, -1) for x in q]
    # arithmetic instead of Where (far dearer per element in onnxruntime): made finite and clamped, the coordinate
    # times 1 plus -0 where kept, times 0 plus OFF_FRAME elsewhere: exactly u, or OFF_FRAME
    sent = sent.to(wdt)
    far = (1.0 - sent) * OFF_FRAME
    u = (_export_or_eager(_SomeFinite, u).clamp(-COORD_MARGIN, Ws + COORD_MARGIN) * sent + far).reshape(B, -1)
    v = (_export_or_eager(_SomeFinite, v).clamp(-COORD_MARGIN, Hs + COORD_MARGIN) * sent + far).reshape(B, -1)
    return u, v, q, front, dst_ok, [x.reshape(B, -1) for x in view_ray]


def _motion_source(motion: tuple, q: list[Tensor], u_c: Tensor, v_c: Tensor, size: _Sizes):
    """:func:`._general._motion_source` on (B, H, W): u, v = pixel centre + motion; ``q`` (3 × (B, H, W)) moved in
    place by R_src · world motion (zero where not finite: finite values times 0, no ``Where``). Returns u, v,
    ``front`` (the moved point's z > 0, with finite u, v where the motion is finite) and ``moved`` (the motion and
    world motion are finite: elsewhere the pixel is sent to OFF_FRAME, where every tap is off the frame)."""
    mo, mw, rotation = motion
    B, H, W = size.B, size.H, size.W
    wdt = q[0].dtype
    mo = mo.to(wdt).reshape(B, 2, H, W)
    u, v = u_c + mo[:, 0], v_c + mo[:, 1]
    ok = _finite(mo[:, 0]) & _finite(mo[:, 1])
    if mw is not None:
        mw = mw.to(wdt).reshape(B, 3, H, W)
        comps = [mw[:, i] for i in range(3)]
        for x in comps:
            ok = ok & _finite(x)
        keep = ok.to(wdt)
        comps = [_export_or_eager(_SomeFinite, x) * keep for x in comps]
        R = rotation.to(wdt)
        for i in range(3):
            r = [R[:, i, j].reshape(B, 1, 1) for j in range(3)]
            q[i] = q[i] + (r[0] * comps[0] + r[1] * comps[1] + r[2] * comps[2])
    front = (q[2] > 0) & ((_finite(u) & _finite(v)) | ~ok)
    return u, v, front, ok


def _tap_corners(u: Tensor, v: Tensor, sampling: str, rectified: bool, Wp):
    """Tap (0, 0) of each pixel: x0, y0, the bilinear fractions fx, fy (None for nearest), the tap offsets read
    and ``corner``, the table index of tap (0, 0) (B, H·W) int32."""
    if sampling == "bilinear":
        x, y = u - 0.5, v - 0.5
        x0, y0 = torch.floor(x), torch.floor(y)
        fx, fy = x - x0, y - y0
        taps = [(0, 0), (1, 0)] + ([] if rectified else [(0, 1), (1, 1)])
    else:
        x0, y0 = torch.floor(u), torch.floor(v)
        fx = fy = None
        taps = [(0, 0)]
    corner = (y0.to(torch.int32) + TABLE_PAD) * Wp + (x0.to(torch.int32) + TABLE_PAD)  # (B, H·W)
    return x0, y0, fx, fy, taps, corner


def _accumulate(tap_tables: list[Tensor], C: int, corner: Tensor, taps, geo: _TapGeometry, Wp, wdt: torch.dtype):
    """The accepted, weighted sums over the taps: num C × (B, H·W), den (B, H·W). Taps one after the other: z
    first (the position test), then normals, then values, so that few gathered planes are alive at once."""
    num = den = None
    for dx, dy in taps:
        index = corner + (dy * Wp + dx) if (dx or dy) else corner
        z = torch.gather(tap_tables[C], 1, index)
        pos_ok = geo.position_ok(z, dx, dy)
        n = [torch.gather(tab, 1, index) for tab in tap_tables[C + 1 :]]
        accept = (pos_ok & geo.normal_ok(n)).to(wdt)
        w = geo.weight(dx, dy)
        ws = accept if w is None else w * accept
        vals = [torch.gather(tab, 1, index) for tab in tap_tables[:C]]
        num = [ws * x for x in vals] if num is None else [a + ws * x for a, x in zip(num, vals)]
        den = ws if den is None else den + ws
    return num, den


def _tap_codes(
    geo_k: _TapGeometry,
    taps,
    steps: tuple[Tensor, ...],
    index: Tensor,
    depth_table: Tensor,
    z_table: Tensor,
    normal_tables: list[Tensor],
    Hs,
    Ws,
) -> Tensor:
    """The reason code (K,) of K picked pixels: the max over their taps (stacked as (T, K): one node per step for
    all taps; each element's arithmetic is that of the tap it stands for) of each tap's first failed test.

    ``steps`` = (dx, dy) of the taps as (T, 1) int64, then as float; ``index`` (T, K) indexes the flattened tables
    (``depth_table``: the padded raw source depth).
    """
    dxi, dyi, dxs, dys = steps
    T = len(taps)
    wdt, dev = depth_table.dtype, depth_table.device

    def tap_gather(table: Tensor) -> Tensor:  # (T, -1): an exported 0 (K = 0) would mean "keep that dimension"
        return torch.gather(table, 0, index.reshape(-1)).reshape(T, -1)

    xt, yt = geo_k.x0 + dxs, geo_k.y0 + dys
    in_frame = (xt >= 0) & (xt <= Ws - 1) & (yt >= 0) & (yt <= Hs - 1)
    z_raw = tap_gather(depth_table)
    # each tap's destination-independent code, in exact small-integer arithmetic: OUT_OF_FRAME (3) off the source
    # image, else TAP_OK_CODE (8) where z is acceptable, NONFINITE (7) where the pixel has a surface (its values
    # are not finite), NO_SURFACE_SRC (4)
    code = has_surface(z_raw).to(wdt) * 3.0 + float(Reason.NO_SURFACE_SRC)
    code = code + _finite(tap_gather(z_table)).to(wdt) * (TAP_OK_CODE - code)
    code = (code - float(Reason.OUT_OF_FRAME)) * in_frame.to(wdt) + float(Reason.OUT_OF_FRAME)
    pos_ok = geo_k.position_ok(z_raw, dxs, dys)
    nrm_ok = geo_k.normal_ok([tap_gather(tab) for tab in normal_tables])
    c_ok = _const(TAP_OK_CODE, wdt, dev)
    code = torch.minimum(
        torch.minimum(code, torch.where(pos_ok, c_ok, float(Reason.POSITION))),
        torch.where(nrm_ok, c_ok, float(Reason.NORMAL)),
    )
    if T > 1:  # taps of weight 0 do not report a reason (tap (0, 0) always does)
        w = torch.cat([geo_k.weight(dx, dy) for dx, dy in taps])  # (T, K)
        code = code * ((w > 0) | ((dxi + dyi) == 0)).to(wdt)
    return code.amax(0)


def _reasons(
    geo: _TapGeometry,
    taps,
    corner: Tensor,
    tap_tables: list[Tensor],
    src_depth: Tensor,
    dst_ok: Tensor,
    front: Tensor,
    inval: Tensor,
    size: _Sizes,
) -> Tensor:
    """Reason codes (B, 1, H, W) uint8: NO_SURFACE_DST (1) / BEHIND_CAMERA (2) from the projection, 0 where valid
    (``inval`` = 0), and the taps' codes (:func:`_tap_codes`) for the K pixels that have a surface in front of the
    source camera but accepted nothing (``Compress`` and ``ScatterElements``: usually a few per cent of the
    image)."""
    B, H, W, Hs, Ws, Wp = size
    wdt, dev = inval.dtype, inval.device
    C = len(tap_tables) - 4
    ok_f, front_f = dst_ok.to(wdt).reshape(B, -1), front.to(wdt).reshape(B, -1)
    reason = inval * (ok_f * (1.0 - front_f) * 2.0 + (1.0 - ok_f))
    N = reason.shape[1]
    pick = _pick((ok_f * front_f * inval).reshape(-1) > 0)  # (K,) flat pixel indices
    batch = torch.div(pick, N, rounding_mode="floor")

    def sel(x: Tensor | None, per_batch: bool = False) -> Tensor | None:
        """(B, N) -> (K,) at the picked pixels; ``per_batch``: (B, 1) -> (K,) of their batch items."""
        if x is None:
            return None
        return torch.gather(x.reshape(-1), 0, batch if per_batch else pick)

    def row(x: Tensor | None) -> Tensor | None:
        return None if x is None else x.unsqueeze(0)

    dxi = _column([dx for dx, _ in taps], torch.int64, dev)  # (T, 1): constants ...
    dyi = _column([dy for _, dy in taps], torch.int64, dev)
    offsets = dyi * Wp + dxi  # ... and Wp a traced size (a Python int here would be baked into the graph)
    dxs, dys = dxi.to(wdt), dyi.to(wdt)
    x0_k, y0_k = sel(geo.x0).unsqueeze(0), sel(geo.y0).unsqueeze(0)  # (1, K)
    geo_k = _TapGeometry(
        x0_k,
        y0_k,
        row(sel(geo.fx)),
        row(sel(geo.fy)),
        [row(sel(k, True)) for k in geo.ki],
        [row(sel(x)) for x in geo.q],
        [row(sel(x)) for x in geo.nd],
        geo.thr_p2,
        geo.thr_n2,
        None if geo.plane is None else ([row(sel(x)) for x in geo.plane[0]], row(sel(geo.plane[1]))),
    )
    depth_table = F.pad(src_depth.to(wdt), (TABLE_PAD,) * 4, value=math.nan).reshape(-1)
    z_table = tap_tables[C].reshape(-1)
    normal_tables = [tab.reshape(-1) for tab in tap_tables[C + 1 :]]
    index = (sel(corner).to(torch.int64) + batch * tap_tables[0].shape[1]).unsqueeze(0) + offsets  # (T, K)
    code_max = _tap_codes(geo_k, taps, (dxi, dyi, dxs, dys), index, depth_table, z_table, normal_tables, Hs, Ws)
    return reason.reshape(-1).scatter(0, pick, code_max).reshape(B, 1, H, W).to(torch.uint8)


def lean_reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    warp: Warp,
    position_threshold,
    normal_threshold,
    sampling: str,
    rectified: bool = False,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    src_rotation: Tensor | None = None,
    position_test: str = "distance",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`~stereorepro.reproject.backward_reproject` with hard tests, in the export formulation.

    Args: as :func:`._general.general_reproject` (``src_values`` (B, C, Hs, Ws), ``dst_depth`` (B, 1, H, W),
        ``dst_normal`` (B, 3, H, W), ``warp`` composed), plus ``rectified``: read only the taps of row y0 (the
        warp must have been rectified: :func:`~stereorepro.camera.rectify_warp`), and the destination's motion
        vectors ``motion`` (B, 2, H, W), ``motion_world`` (B, 3, H, W) with the source rotation ``src_rotation``
        (B, 3, 3) (see :func:`._general.general_reproject`; needed for ``position_test="plane"`` too).

    Returns:
        values (B, C, H, W) in the dtype of ``src_values``, valid (B, 1, H, W) bool, reason (B, 1, H, W) uint8,
        confidence (B, 1, H, W) accepted bilinear weight in the compute dtype.

    The projection runs on (B, H, W) with the pixel centres broadcast; the taps on (B, H·W), so that they gather
    the (B, Np) tables along axis 1.
    """
    wdt = warp.K_src_inv.dtype
    dev = dst_depth.device
    B, C = src_values.shape[:2]
    Hs, Ws = src_values.shape[-2:]
    H, W = dst_depth.shape[-2:]
    size = _Sizes(B, H, W, Hs, Ws, Ws + 2 * TABLE_PAD)
    tap_tables = source_tables(src_values, src_depth, src_normal, wdt)
    moving = None if motion is None else (motion, motion_world, src_rotation)
    u, v, q, front, dst_ok, view_ray = _project(warp, dst_depth, size, moving)
    n_dst = _finite_or_zero(dst_normal.to(wdt)).reshape(B, 3, -1)
    nd = [n_dst[:, c] for c in range(3)]
    like = torch.empty((), dtype=wdt, device=dev)
    thr_p, thr_n = as_scalar(position_threshold, like), as_scalar(normal_threshold, like)
    thr_p2, thr_n2 = thr_p * thr_p, thr_n * thr_n
    cubic = sampling == "catmull_rom"
    cubic_tests = TapTests(position_threshold, normal_threshold, sampling, position_test=position_test)
    x0, y0, fx, fy, taps, corner = _tap_corners(u, v, "bilinear" if cubic else sampling, rectified, size.Wp)
    ki = [warp.K_src_inv[:, i, j : j + 1] for i in range(3) for j in range(3)]  # (B, 1) each
    plane = None
    if position_test == "plane":  # per pixel: the normal in the source camera's axes, the squared threshold
        n_raw = dst_normal.to(wdt).reshape(B, 3, -1)
        z_dst = dst_depth.to(wdt).reshape(B, -1)
        rot = src_rotation.to(wdt).reshape(B, 9)
        nc, scale, usable = plane_terms(view_ray, z_dst, [n_raw[:, c] for c in range(3)], rot)
        plane = (nc, torch.where(usable, thr_p2 * (scale * scale), _const(-1.0, wdt, dev)))
    geo = _TapGeometry(x0, y0, fx, fy, ki, q, nd, thr_p2, thr_n2, plane)
    num, den = _accumulate(tap_tables, C, corner, taps, geo, size.Wp, wdt)
    valid = den > 0
    inval = 1.0 - valid.to(wdt)
    den_safe = den + inval  # den where valid, 1 elsewhere (where num = 0)
    reason = _reasons(geo, taps, corner, tap_tables, src_depth, dst_ok, front, inval, size)
    shape = (B, 1, H, W)
    valid, den = valid.reshape(shape), den.reshape(shape)
    # The values' nodes are made last. onnxruntime's default order is a depth-first walk from the last-made output
    # node, visiting a node's last-made input first: so the colour's chain (taps, weights, value gathers) runs
    # before the reasons, and the taps' weights and indices are freed before the reasons' tensors are made (a
    # lower peak memory than with the values made first). Each channel is reshaped before the Concat that makes
    # the output (onnxruntime copies a Reshape whose result is a graph output).
    values = torch.cat([(x / den_safe).reshape(B, 1, H, W) for x in num], 1)
    if cubic:  # the general path's Catmull-Rom footprints over the bilinear result (16 gathers per pixel)
        source = SourceTaps(feature_reader(source_features(src_values, src_depth, src_normal, wdt)), C, Hs, Ws)
        pixels = dst_rows(dst_depth, dst_normal, motion, motion_world, 0, H, wdt)
        values = catmull_rom_pixels(source._replace(rotation=src_rotation), warp, pixels, cubic_tests, values)
    if values.dtype != src_values.dtype:  # (a same-dtype .to() is exported as a Cast: a copy of the image)
        values = values.to(src_values.dtype)
    return values, valid, reason, den


def lean_blend(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    valid: Tensor,
    alpha,
    warmup: bool,
    max_history,
    history_rounding: str = "none",
) -> tuple[Tensor, Tensor]:
    """:func:`~stereorepro.reproject.temporal_blend` with hard tests in the export formulation, for the history
    :func:`lean_reproject` warps (finite everywhere: its values are sums of finite table entries), with arithmetic
    where the general blend has ``Where`` (dear per element in onnxruntime).

    The current frame's weight ``a`` is raised to 1 where the history is discarded, so one expression,
    ``(1 − a)·history + a·current``, gives the blend where the history is kept (the same operations as
    :func:`temporal_blend`) and ``0·history + current`` elsewhere and where ``a`` reaches 1: the current sample
    (a zero's sign aside), non-finite ones included. The new count is ``n_next·v + (1 − v)``: ``n_next`` or 1;
    with ``history_rounding="bmfr"`` ``n_next`` rounds ``n`` half to even first (ONNX ``Round``) and its cap is 1
    where ``alpha >= 1`` (a scalar ``Where``), as ``temporal_blend``.

    Args:
        current_color: (B, 3, H, W); history_color: (B, 3, H, W) and history_len: (B, 1, H, W) as warped by
            :func:`lean_reproject`; valid: (B, 1, H, W) bool; alpha, warmup, max_history, history_rounding: as
            ``temporal_blend``.

    Returns:
        color (B, 3, H, W) in the dtype of ``current_color``, history_len (B, 1, H, W) in the compute dtype.
    """
    wdt = compute_dtype(current_color, history_color)
    cur, hist = current_color.to(wdt), history_color.to(wdt)
    n = torch.relu(history_len.to(wdt))  # finite here: max(n, 0) is temporal_blend's "negative: no history"
    v = valid.to(wdt)
    a_min = as_scalar(alpha, n).clamp(0.0, 1.0)
    a = torch.maximum(1.0 / (n + 1.0), a_min) if warmup else a_min
    a = torch.maximum(a, 1.0 - v)  # 1 where the history is discarded
    out = (1.0 - a) * hist + a * cur
    cap = as_scalar(max_history, n)
    if history_rounding == "bmfr":
        n = torch.round(n)
        cap = torch.where(a_min >= 1.0, torch.ones((), dtype=wdt, device=n.device), cap)
    n_out = torch.minimum(n + 1.0, cap) * v + (1.0 - v)
    if out.dtype != current_color.dtype:
        out = out.to(current_color.dtype)
    return out, n_out
