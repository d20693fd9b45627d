"""The fast path of the backward reprojection: hard tests when no autograd graph is needed and nothing traces
the call (and the squared thresholds are finite). Wherever a result depends on it, it performs the per-element float
arithmetic of warp_pixels, so values, valid, reason and confidence are identical to the general path
(``TestFastPath`` in ``tests/reproject/test_reproject.py``); what changes is the memory traffic, which bounds this
op on a CPU:

* the source is sanitised once into a padded gather table (fast_source_table) holding, per pixel, the values,
  the source-camera point (px, py, z) (the per-tap formula of warp_pixels evaluated once per pixel: the same
  bits) and the normal. A pixel no tap may accept (no surface, non-finite values, the TABLE_PAD border) has a NaN
  or infinite point, which fails the position test: no per-tap frame, surface or finiteness tests, no index
  clamping. Invalid destination pixels are sent to the border the same way;
* accept tests are float arithmetic (a comparison into a float tensor is vectorised, into a bool one it is not);
* one gather of all taps' table rows per row block; one pass of float ops over (channel, tap, pixel) arrays;
* reasons only for invalid pixels (fast_reasons): no surface / behind the camera / every tap out of frame
  directly, the rest (occlusions, ...) through warp_pixels on those pixels alone;
* destination rows in blocks of FAST_BLOCK_PIXELS, with scratch buffers reused across blocks (out= / in-place);
* motion vectors (fast_motion_source) replace the projection of a pixel by ``pixel + motion`` and move its point by
  the world motion, as warp_pixels' motion source; a pixel that reads no tap is sent to the border as above.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ..camera import Warp, has_surface
from ._constants import COORD_MARGIN, F32_EXACT_INT, OFF_FRAME, TABLE_PAD
from ._general import (
    DstPixels,
    SourceTaps,
    TapTests,
    catmull_rom_pixels,
    pixel_centres,
    plane_terms,
    raw_reader,
    warp_pixels,
)
from .reason import Reason

#: Destination pixels per block in the fast path (its per-block working set is larger than the general path's).
FAST_BLOCK_PIXELS = 1 << 15

#: Table sizes from which the table-index arithmetic runs in float64 (module-level so that a test can lower it).
_F32_EXACT = F32_EXACT_INT


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


def fast_source_table(
    src_values: Tensor, src_depth: Tensor, src_normal: Tensor, K_src_inv: Tensor, wdt: torch.dtype
) -> Tensor:
    """The fast path's gather table: (B, C+6, Hp·Wp) with Hp, Wp = Hs + 2·TABLE_PAD, Ws + 2·TABLE_PAD.

    Channels: values (all 0 for a pixel with any non-finite value), the pixel's point in the source camera frame
    px, py, z (NaN or ±inf where no tap may be accepted: no surface, non-finite values, the border), normal
    (non-finite components 0, as finite_or_zero).
    """
    B, C, Hs, Ws = src_values.shape
    dev = src_values.device
    p = TABLE_PAD
    tab = torch.empty(B, C + 6, Hs + 2 * p, Ws + 2 * p, dtype=wdt, device=dev)
    for border in (tab[:, :, :p], tab[:, :, p + Hs :], tab[:, :, p : p + Hs, :p], tab[:, :, p : p + Hs, p + Ws :]):
        border.fill_(0.0)
        border[:, C : C + 3].fill_(math.nan)
    inner = tab[:, :, p : p + Hs, p : p + Ws]
    sv = src_values.to(wdt)
    s0 = sv.sum(1, keepdim=True)
    s0 = torch.sub(s0, s0, out=s0)  # 0 where all values of the pixel are finite, NaN elsewhere
    torch.sub(sv, s0, out=inner[:, :C]).nan_to_num_(0.0, 0.0, 0.0)  # x - 0 = x, bit for bit (-0 included)
    sz = src_depth.to(wdt)
    surface = torch.gt(sz, 0.0, out=torch.empty_like(sz))  # 1.0 / 0.0
    zm = torch.sub(sz, s0).div_(surface)  # z where z > 0 and the values are finite; NaN or ±inf elsewhere
    ki = K_src_inv.reshape(B, 9, 1, 1)
    ut = torch.arange(Ws, dtype=wdt, device=dev).view(1, 1, 1, Ws) + 0.5
    vt = torch.arange(Hs, dtype=wdt, device=dev).view(1, 1, Hs, 1) + 0.5
    torch.mul(zm, ki[:, 0:1] * ut + ki[:, 1:2] * vt + ki[:, 2:3], out=inner[:, C : C + 1])  # px, as in warp_pixels
    torch.mul(zm, ki[:, 4:5] * vt + ki[:, 5:6], out=inner[:, C + 1 : C + 2])  # py
    inner[:, C + 2 : C + 3] = zm
    torch.nan_to_num(src_normal.to(wdt), 0.0, 0.0, 0.0, out=inner[:, C + 3 :])
    return tab.view(B, C + 6, -1)


class _RowGeometry(NamedTuple):
    """What :func:`fast_geometry` needs of the whole frame (computed once per call of :func:`fast_reproject`)."""

    proj_point: Tensor  #: (B, 6, 3) [pixel_src_from_pixel_dst; ray_src_from_pixel_dst]: rows 0-2 give the
    #: homogeneous source pixel, rows 3-5 the point
    proj_point_u: Tensor  #: (B, 6, 1, W) column 0 of proj_point times the destination pixel centres u
    v_c: Tensor  #: (1, 1, H, 1) destination pixel centres v
    K_src_t: Tensor  #: (B, 3, 1)
    t_src_from_dst: Tensor  #: (B, 3, 1)
    lo: Tensor  #: (1, 2, 1) lower clamp of the taps' (x, y)
    hi: Tensor  #: (1, 2, 1) upper clamp
    one: Tensor  #: 1 in the work dtype
    sampling: str
    padded_width: int  #: Wp, the width of the padded source table
    idx_dtype: torch.dtype  #: float dtype of the table-index arithmetic
    u_c: Tensor | None = None  #: (1, 1, 1, W) destination pixel centres u (with motion vectors)
    rotation: Tensor | None = None  #: (B, 3, 3, 1) the source camera's rotation (with world motion)
    plane_rotation: Tensor | None = None  #: (B, 9, 1) the source camera's rotation, row-major (plane test)
    thr_p2: Tensor | None = None  #: the squared position threshold (plane test)


class _Motion(NamedTuple):
    """Motion vectors of the destination (see :func:`warp_pixels`), with the source camera's rotation."""

    motion: Tensor  #: (B, 2, H, W) screen motion to the source instant
    world: Tensor | None  #: (B, 3, H, W) world motion of the destination points
    rotation: Tensor | None  #: (B, 3, 3) rotation of the source ``cam_from_world`` (with ``world``)

    def rows(self, r0: int, r1: int) -> tuple[Tensor, Tensor | None]:
        """Motion and world motion of rows r0 .. r1 - 1, flattened to (B, 2 | 3, N)."""

        def flat(x):
            return None if x is None else x[:, :, r0:r1].reshape(x.shape[0], x.shape[1], -1)

        return flat(self.motion), flat(self.world)

    def pixels(self, b: int, p: Tensor, yy: Tensor, xx: Tensor) -> tuple[Tensor, Tensor | None]:
        """Motion and world motion of pixels ``p`` of batch item ``b`` as (1, 2 | 3, 1, K)."""

        def take(x):
            return None if x is None else _gather_pixels(x, b, p, yy, xx).view(1, x.shape[1], 1, -1)

        return take(self.motion), take(self.world)


def fast_motion_source(
    geo: _RowGeometry, zc: Tensor, motion: tuple[Tensor, Tensor | None], point: Tensor, r0: int, r1: int, uv_raw: Tensor
) -> None:
    """The source pixel of N destination pixels from their motion vectors (warp_pixels' motion source).

    Writes ``uv_raw`` (B, 2, N): pixel centre + motion; the lower clamp (OFF_FRAME) where the motion or world motion
    is not finite; NaN where the pixel has no surface (``zc`` <= 0) or its moved point is not in front of the source
    camera. Moves ``point`` (B, 3, N), the destination point in the source camera frame, by R_src · world motion
    (zero where not finite), in place.
    """
    mo, mw = motion
    B, wdt = zc.shape[0], zc.dtype
    h = r1 - r0
    mo = mo.to(wdt)
    ok = torch.isfinite(mo).all(1, keepdim=True)
    if mw is not None:
        mw = mw.to(wdt)
        ok &= torch.isfinite(mw).all(1, keepdim=True)
        mw = torch.where(ok, mw, 0.0)
        R = geo.rotation  # (B, 3, 3, 1): R[:, :, j] is column j as (B, 3, 1)
        point += R[:, :, 0] * mw[:, 0:1] + R[:, :, 1] * mw[:, 1:2] + R[:, :, 2] * mw[:, 2:3]
    uv = uv_raw.view(B, 2, h, -1)
    torch.add(mo[:, 0:1].view(B, 1, h, -1), geo.u_c, out=uv[:, 0:1])
    torch.add(mo[:, 1:2].view(B, 1, h, -1), geo.v_c[:, :, r0:r1], out=uv[:, 1:2])
    uv_raw.masked_fill_(~ok, OFF_FRAME)
    uv_raw.masked_fill_(~((zc > 0) & (point[:, 2:3] > 0)), math.nan)


def fast_geometry(
    geo: _RowGeometry,
    z: Tensor,
    n: Tensor,
    r0: int,
    r1: int,
    uv_raw: Tensor,
    sc: _Scratch,
    motion: tuple[Tensor, Tensor | None] | None = None,
):
    """Destination rows r0 .. r1 - 1 -> taps: the fast path's share of the projection and tap weights of
    :func:`warp_pixels` (same arithmetic for every pixel that can have an accepted tap).

    Args:
        geo: see :func:`fast_reproject`.
        z: (B, 1, N) depth, n: (B, 3, N) normal of the N = (r1 - r0)·W pixels (any float dtype and strides).
        uv_raw: (B, 2, N), written: the source pixel (u, v) before clamping; non-finite where the pixel has a
            surface but is behind the source camera or projects to infinity (``front`` False in warp_pixels).
        motion: the pixels' motion (B, 2, N) and world motion (B, 3, N) or None (see :func:`fast_motion_source`).

    Returns:
        point_normal: (B, 6, N) the destination point in the source camera frame and the sanitised destination normal.
        wts: (B, 2, 2, N) bilinear weights of the taps (y0 | y0 + 1, x0 | x0 + 1), None for nearest sampling.
        corner: (B, 1, N) y0·Wp + x0 for tap (x0, y0) (nearest: the tap), exact in its float dtype; the table
            index of a tap is this plus TABLE_PAD·Wp + TABLE_PAD plus its offset from (x0, y0).
        plane: (B, 4, N) the plane test's normal in the source camera's axes and squared threshold (-1 where the
            normal is unusable: :func:`._general.plane_terms`), or None for the distance test.

    Invalid pixels need no flag: no surface (z <= 0 -> 1/z = inf, NaN z) or behind the camera (wz <= 0 ->
    w / 0) make u, v non-finite, sanitised to the border, so every tap is rejected; z = +inf gives an infinite q.
    """
    pp, kt, t, one, Wp, idx_dtype = (
        geo.proj_point,
        geo.K_src_t,
        geo.t_src_from_dst,
        geo.one,
        geo.padded_width,
        geo.idx_dtype,
    )
    B, h, W = z.shape[0], r1 - r0, geo.proj_point_u.shape[-1]
    N, wdt = h * W, pp.dtype
    v = sc.views(
        ("geometry", N),
        [
            ("zc", (B, 1, N), wdt),
            ("inv", (B, 1, N), wdt),
            ("base", (B, 6, h, W), wdt),
            ("w", (B, 3, N), wdt),
            ("point_normal", (B, 6, N), wdt),
            ("uv", (B, 2, N), wdt),
            ("xy0", (B, 2, N), wdt),
            ("wa", (B, 2, 2, N), wdt),
            ("wts", (B, 2, 2, N), wdt),
            ("corner", (B, 1, N), idx_dtype),
        ],
    )
    zc = torch.clamp_min(z.to(wdt), 0.0, out=v["zc"])
    inv = torch.reciprocal(zc, out=v["inv"])
    # proj_point @ [u, v, 1] as in warp_pixels: (c0·u + c1·v) + c2 over the columns c of proj_point, c0·u
    # precomputed
    base = torch.add(geo.proj_point_u, pp[:, :, 1, None, None] * geo.v_c[:, :, r0:r1], out=v["base"])
    base = base.add_(pp[:, :, 2, None, None]).view(B, 6, N)
    w = torch.mul(kt, inv, out=v["w"]).add_(base[:, :3])  # pixel_src_from_pixel_dst @ [u, v, 1] + K_src_t / z
    point_normal = v["point_normal"]
    torch.mul(base[:, 3:], zc, out=point_normal[:, :3]).add_(t)  # (ray_src_from_pixel_dst @ [u, v, 1]) z + t
    torch.nan_to_num(n.to(wdt), 0.0, 0.0, 0.0, out=point_normal[:, 3:])
    plane = None if geo.plane_rotation is None else fast_plane(geo, base[:, 3:], zc, n.to(wdt))
    if motion is None:
        torch.div(w[:, :2], torch.clamp_min(w[:, 2:3], 0.0, out=inv), out=uv_raw)  # wz <= 0: ±inf or NaN
    else:
        fast_motion_source(geo, zc, motion, point_normal[:, :3], r0, r1, uv_raw)
    # the taps' x = clamp(u, -COORD_MARGIN, Ws + COORD_MARGIN) - 0.5 in warp_pixels; here u - 0.5 clamped to
    # [-COORD_MARGIN - 1, Ws + COORD_MARGIN - 1] (integer bounds, so that pixels off the frame have f = 0): the same
    # bits wherever a tap can be in the frame. Non-finite coordinates go below the lower bound, then to it.
    bilinear = geo.sampling == "bilinear"
    uv = torch.sub(uv_raw, 0.5 if bilinear else 0.0, out=v["uv"])
    uv.nan_to_num_(-float(TABLE_PAD), -float(TABLE_PAD), -float(TABLE_PAD)).clamp_(geo.lo, geo.hi)
    xy0 = torch.floor(uv, out=v["xy0"])
    wts = None
    if bilinear:
        wa = v["wa"]  # (B, axis x|y, 1 - f | f, N)
        f = torch.sub(uv, xy0, out=wa[:, :, 1])
        torch.sub(one, f, out=wa[:, :, 0])
        wts = torch.mul(wa[:, 1, :, None], wa[:, 0, None, :], out=v["wts"])
    xy0 = xy0.to(idx_dtype)  # (float64 for tables of 2^24 pixels or more)
    corner = torch.mul(xy0[:, 1:2], Wp, out=v["corner"]).add_(xy0[:, 0:1])
    return point_normal, wts, corner, plane


def fast_plane(geo: _RowGeometry, ray: Tensor, z: Tensor, normal: Tensor) -> Tensor:
    """(B, 4, N): the plane test's normal in the source camera's axes (3) and squared threshold of N pixels (view
    ray (B, 3, N), depth (B, 1, N), raw normal (B, 3, N)), -1 where the normal is unusable; the general path's
    operations (:func:`._general.plane_terms`)."""
    nc, scale, usable = plane_terms(
        [ray[:, i : i + 1] for i in range(3)], z, [normal[:, i : i + 1] for i in range(3)], geo.plane_rotation
    )
    thr2 = torch.where(usable, geo.thr_p2 * (scale * scale), -1.0)
    return torch.cat([*nc, thr2], 1)


def fast_accept(
    taps: Tensor,
    point_normal: Tensor,
    wts: Tensor | None,
    thr2: Tensor,
    sc: _Scratch,
    key,
    values: Tensor,
    valid: Tensor,
    den: Tensor,
    plane: Tensor | None = None,
) -> None:
    """Accept tests and the renormalised sum over the taps of N destination pixels (the tail of warp_pixels).

    Args:
        taps: (B, C+6, Ty, Tx, N) gathered table rows (any strides); Ty = Tx = 2 (bilinear) or 1 (nearest).
        point_normal: (B, 6, N), wts: (B, Ty, Tx, N) or None (a single tap of weight 1), thr2: (1, 2, 1, 1, 1).
        values: (B, C, N), valid, den: (B, 1, N), written. Where nothing is accepted ``values`` is ±0 (the
            sign of a sum of zeros); the caller writes +0 there.
        plane: the plane test's (B, 4, N) terms from :func:`fast_geometry` (None: the distance test).
    """
    B, F, Ty, Tx, N = taps.shape
    C, T, wdt = F - 6, Ty * Tx, taps.dtype
    v = sc.views(
        ("accept", key),
        [
            ("d", (B, 6, Ty, Tx, N), wdt),
            ("s", (B, 2, Ty, Tx, N), wdt),
            ("a", (B, 2, Ty, Tx, N), wdt),
            ("ws", (B, Ty, Tx, N), wdt),
            ("prod", (B, C, Ty, Tx, N), wdt),
            ("num", (B, C, N), wdt),
            ("den_safe", (B, 1, N), wdt),
        ],
    )
    # (p_src - q)², (n_src - n_dst)² in one pass (mse_loss without reduction: exactly the square of the difference)
    d = torch.ops.aten.mse_loss.out(taps[:, C:], point_normal[:, :, None, None], 0, out=v["d"]).view(B, 2, 3, Ty, Tx, N)
    s = torch.add(d[:, :, 0], d[:, :, 1], out=v["s"]).add_(d[:, :, 2])  # d_pos2, d_n2 summed as warp_pixels
    a = torch.le(s, thr2, out=v["a"])  # 1.0 / 0.0, NaN -> 0.0
    if plane is not None:  # the position test replaced: (P_src − q)·nc = −(the general path's distance), bit for bit
        diff = taps[:, C : C + 3] - point_normal[:, :3, None, None]
        nc = plane[:, :3, None, None]
        dist = (diff[:, 0] * nc[:, 0] + diff[:, 1] * nc[:, 1]) + diff[:, 2] * nc[:, 2]
        torch.le(dist * dist, plane[:, 3, None, None], out=a[:, 0])
    ws = torch.mul(a[:, 0], a[:, 1], out=v["ws"])
    if wts is not None:
        ws.mul_(wts)  # = wts · hard
    torch.sum(ws.view(B, T, N), 1, keepdim=True, out=den)
    prod = torch.mul(taps[:, :C], ws[:, None], out=v["prod"])
    num = torch.sum(prod.view(B, C, T, N), 2, out=v["num"])
    torch.gt(den, 0.0, out=valid)
    # den > 0 is a sum of products of two weights >= 2^-24 (fractions of coordinates < 2^23), so it is above
    # `tiny`: clamping divides by den itself where valid
    torch.div(num, torch.clamp_min(den, torch.finfo(wdt).tiny, out=v["den_safe"]), out=values)


def _gather_pixels(x: Tensor, b: int, p: Tensor, yy: Tensor, xx: Tensor) -> Tensor:
    """(1, C, K): pixels ``p`` (flat; rows yy, columns xx) of batch item ``b`` of a (B, C, H, W) tensor."""
    xb = x[b]
    if xb.is_contiguous():  # (index_select along the last dim is much slower than this gather)
        return torch.gather(xb.view(1, xb.shape[0], -1), 2, p.view(1, 1, -1).expand(1, xb.shape[0], -1))
    return xb[:, yy, xx][None]


def fast_reasons(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    warp: Warp,
    tests: TapTests,
    b: int,
    p: Tensor,
    uv: Tensor,
    motion: _Motion | None = None,
    src_rotation: Tensor | None = None,
) -> Tensor:
    """Reason codes (K,) uint8 of the invalid destination pixels ``p`` (flat indices) of batch item ``b``
    (``src_rotation`` (B, 3, 3): with world motion and for the plane test).

    ``uv`` (2, K) is their unclamped source pixel from :func:`fast_geometry`. No surface, behind the camera and
    "every tap out of frame" (the image border: most invalid pixels) follow from it and the depth as in
    :func:`warp_pixels`; the others (occlusions, ...) go through :func:`warp_pixels` on those pixels only (with
    their ``motion``, when given).
    """
    C, Hs, Ws = src_values.shape[1:]
    wdt, dev = warp.K_src_inv.dtype, dst_depth.device
    W, K = dst_depth.shape[-1], p.numel()
    yy, xx = p // W, p % W
    z = _gather_pixels(dst_depth, b, p, yy, xx).to(wdt).view(K)
    dst_ok = has_surface(z)
    front = torch.isfinite(uv).all(0)  # with a surface: as `front` in warp_pixels
    u, v = uv[0].clamp(-COORD_MARGIN, Ws + COORD_MARGIN), uv[1].clamp(-COORD_MARGIN, Hs + COORD_MARGIN)
    if tests.sampling == "bilinear":  # taps x0, x0 + 1 (y0, y0 + 1) all outside [0, Ws - 1] ([0, Hs - 1])
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
        rotation = None if src_rotation is None else src_rotation[b : b + 1]
        source = SourceTaps(raw_reader(src_values, src_depth, src_normal, b, wdt), C, Hs, Ws, rotation)
        pixels = DstPixels(
            z[rest].view(1, 1, 1, k),
            _gather_pixels(dst_normal, b, p, yy, xx).view(1, 3, 1, k),
            (xx.to(wdt) + 0.5).view(1, 1, 1, k),
            (yy.to(wdt) + 0.5).view(1, 1, 1, k),
            *(motion.pixels(b, p, yy, xx) if motion is not None else ()),
        )
        _, _, reason, _ = warp_pixels(source, Warp(*(c[b : b + 1] for c in warp)), pixels, tests, wdt)
        code[rest] = reason.view(k)
    return code


def fast_reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    warp: Warp,
    thr2: Tensor,
    position_threshold,
    normal_threshold,
    sampling: str,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    src_rotation: Tensor | None = None,
    position_test: str = "distance",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`backward_reproject` for hard tests without autograd or tracing (see the module notes); ``motion``
    (B, 2, H, W), ``motion_world`` (B, 3, H, W), ``src_rotation`` (B, 3, 3) and ``position_test`` as in
    :func:`general_reproject`."""
    hom = warp.pixel_src_from_pixel_dst
    wdt, dev = hom.dtype, dst_depth.device
    B, C, Hs, Ws = src_values.shape
    H, W = dst_depth.shape[-2:]
    F, Wp = C + 6, Ws + 2 * TABLE_PAD
    cubic = sampling == "catmull_rom"  # the bilinear pass, then the Catmull-Rom footprints of its valid pixels
    sampling = "bilinear" if cubic else sampling
    bilinear = sampling == "bilinear"
    tab = fast_source_table(src_values, src_depth, src_normal, warp.K_src_inv, wdt)
    Np = tab.shape[-1]
    # table indices are computed in floating point: exact below 2^24 in float32
    idx_dtype = wdt if wdt == torch.float64 or Np + Wp < _F32_EXACT else torch.float64
    off = -1.0 if bilinear else 0.0  # see fast_geometry
    lo = torch.full((1, 2, 1), -COORD_MARGIN + off, dtype=wdt, device=dev)
    hi = torch.tensor([Ws + COORD_MARGIN + off, Hs + COORD_MARGIN + off], dtype=wdt, device=dev).view(1, 2, 1)
    pp = torch.cat([hom, warp.ray_src_from_pixel_dst], 1)  # (B, 6, 3)
    u_c, v_c = pixel_centres(0, H, W, wdt, dev)
    mv = None if motion is None else _Motion(motion, motion_world, src_rotation)
    rotation = None if motion_world is None else src_rotation.to(wdt).reshape(B, 3, 3, 1)
    plane = position_test == "plane"
    geo = _RowGeometry(
        pp,
        pp[:, :, 0, None, None] * u_c,
        v_c,
        warp.K_src_t,
        warp.t_src_from_dst,
        lo,
        hi,
        torch.ones((), dtype=wdt, device=dev),
        sampling,
        Wp,
        idx_dtype,
        u_c,
        rotation,
        src_rotation.to(wdt).reshape(B, 9, 1) if plane else None,
        thr2[0, 0, 0, 0, 0] if plane else None,
    )
    sc = _Scratch(dev)

    values = torch.empty(B, C, H, W, dtype=wdt, device=dev)
    valid = torch.empty(B, 1, H, W, dtype=torch.bool, device=dev)
    den = torch.empty(B, 1, H, W, dtype=wdt, device=dev)
    uv_raw = torch.empty(B, 2, H * W, dtype=wdt, device=dev)  # for the reasons of invalid pixels
    offsets = torch.tensor([[0.0, 1.0], [Wp, Wp + 1.0]] if bilinear else [[0.0]], dtype=idx_dtype, device=dev)
    offsets += TABLE_PAD * Wp + TABLE_PAD  # (0, 0) of the source image in the padded table
    # v_s = v + hom[1, 2] for every pixel (hom[1] = (0, 1, ·), hom[2] = (0, 0, 1), K_src_t y = z = 0): bilinear taps
    # may all have fy = 0 (rectified stereo), checked per block; otherwise the check would only cost time
    rectified = bilinear and bool(
        (hom[:, 1, :2] == torch.tensor([0.0, 1.0], dtype=wdt, device=dev)).all()
        & (hom[:, 2] == torch.tensor([0.0, 0.0, 1.0], dtype=wdt, device=dev)).all()
        & (warp.K_src_t[:, 1:] == 0).all()
    )
    rows = max(1, FAST_BLOCK_PIXELS // max(1, B * W))
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        N = (r1 - r0) * W
        point_normal, wts, corner, plane_rows = fast_geometry(
            geo,
            dst_depth[:, :, r0:r1].reshape(B, 1, N),
            dst_normal[:, :, r0:r1].reshape(B, 3, N),
            r0,
            r1,
            uv_raw[:, :, r0 * W : r1 * W],
            sc,
            None if mv is None else mv.rows(r0, r1),
        )
        offs = offsets
        if rectified and not torch.count_nonzero(wts[:, 1, 0]):  # (1 - fx)·fy, 1 - fx > 0
            # fy = 0 for every pixel (rectified stereo): the y0 + 1 taps weigh 0, the y0 taps give the same sums
            offs, wts = offsets[:1], wts[:, :1]
        T = offs.numel()
        v = sc.views(
            ("taps", N, T),
            [("fidx", (B, T, N), idx_dtype), ("idx", (B, T, N), torch.int64), ("taps", (B, F, T * N), wdt)],
        )
        idx = v["idx"].copy_(torch.add(corner, offs.view(1, T, 1), out=v["fidx"]))
        taps = torch.gather(tab, 2, idx.view(B, 1, T * N).expand(B, F, T * N), out=v["taps"])
        fast_accept(
            taps.view(B, F, *offs.shape, N),
            point_normal,
            wts,
            thr2,
            sc,
            (N, T),
            values[:, :, r0:r1].view(B, C, N),
            valid[:, :, r0:r1].view(B, 1, N),
            den[:, :, r0:r1].view(B, 1, N),
            plane_rows,
        )

    reason = torch.zeros(B, 1, H, W, dtype=torch.uint8, device=dev)
    for b in range(B):
        p = torch.nonzero(~valid[b].view(H * W)).squeeze(1)
        if p.numel():
            values[b].view(C, H * W).index_fill_(1, p, 0.0)  # +0 where nothing is accepted, as the general path
            reason[b].view(H * W).index_copy_(
                0,
                p,
                fast_reasons(
                    src_values,
                    src_depth,
                    src_normal,
                    dst_depth,
                    dst_normal,
                    warp,
                    TapTests(position_threshold, normal_threshold, sampling, position_test=position_test),
                    b,
                    p,
                    uv_raw[b].index_select(1, p),
                    mv,
                    src_rotation,
                ),
            )
    if cubic:
        tests = TapTests(position_threshold, normal_threshold, "catmull_rom", position_test=position_test)
        for b in range(B):
            fast_catmull_rom(
                src_values,
                src_depth,
                src_normal,
                dst_depth,
                dst_normal,
                warp,
                tests,
                b,
                values,
                valid,
                mv,
                src_rotation,
            )
    return values.to(src_values.dtype), valid, reason, den


def fast_catmull_rom(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    warp: Warp,
    tests: TapTests,
    b: int,
    values: Tensor,
    valid: Tensor,
    motion: _Motion | None = None,
    src_rotation: Tensor | None = None,
) -> None:
    """``"catmull_rom"`` on the fast path: batch item ``b``'s bilinear ``values`` (B, C, H, W) (compute dtype,
    overwritten) are replaced by :func:`catmull_rom_pixels` on its valid pixels only (a pixel whose bilinear
    result is invalid has a failing tap in its footprint and keeps its values)."""
    C, Hs, Ws = src_values.shape[1:]
    wdt = warp.K_src_inv.dtype
    H, W = dst_depth.shape[-2:]
    p = torch.nonzero(valid[b].view(H * W)).squeeze(1)
    k = p.numel()
    if not k:
        return
    yy, xx = p // W, p % W
    rotation = None if src_rotation is None else src_rotation[b : b + 1]
    source = SourceTaps(raw_reader(src_values, src_depth, src_normal, b, wdt), C, Hs, Ws, rotation)
    pixels = DstPixels(
        _gather_pixels(dst_depth, b, p, yy, xx).to(wdt).view(1, 1, 1, k),
        _gather_pixels(dst_normal, b, p, yy, xx).view(1, 3, 1, k),
        (xx.to(wdt) + 0.5).view(1, 1, 1, k),
        (yy.to(wdt) + 0.5).view(1, 1, 1, k),
        *(motion.pixels(b, p, yy, xx) if motion is not None else ()),
    )
    flat = values[b].view(C, H * W)
    bilinear = flat.index_select(1, p).view(1, C, 1, k)
    cubic = catmull_rom_pixels(source, Warp(*(c[b : b + 1] for c in warp)), pixels, tests, bilinear)
    flat.index_copy_(1, p, cubic.view(C, k))
