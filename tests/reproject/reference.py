"""A slow, obviously correct backward reprojection to test every backend against: numpy float64, one loop over the
destination pixels and one over their taps, written from the contract in the docstring of
``stereorepro.reproject.functional`` and nothing of the package (no compose_warp, no feature tables).

Per destination pixel: unproject its centre with the destination depth, move the point into the source camera,
project it, take the 2×2 bilinear taps (or the nearest one) and run the accept tests in order (inside the frame,
source surface, position, normal, finite values). The accepted weights are renormalised; an invalid pixel reports
the largest code among its taps of non-zero weight.

``sampling="catmull_rom"``: the bilinear result, replaced where all 16 pixels of the 4×4 footprint around the
bilinear taps pass every test by the sum of their values weighted with Keys' cubic convolution kernel (a = −0.5, the
Catmull-Rom spline) of the tap's distance to the sample point in x and in y, clamped at 0.

Each pixel also gets a ``margin``: the smallest distance of any decision it took to that decision's boundary
(point depth against 0, tap coordinate against a pixel edge, distance against a threshold; in scene units or
pixels). Backends compute in float32: where the margin is below their rounding, the two may decide differently and
both be right, so tests compare only pixels with a margin above it.
"""

from __future__ import annotations

import math

import numpy as np

KEPT, NO_SURFACE_DST, BEHIND_CAMERA, OUT_OF_FRAME, NO_SURFACE_SRC, POSITION, NORMAL, NONFINITE = range(8)


def _np(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if hasattr(x, "detach") else np.asarray(x, np.float64)


def _has_surface(z: float) -> bool:
    return z > 0 and z < math.inf  # NaN: False


def _finite_or_zero(n: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(n), n, 0.0)  # non-finite normal components read as 0


def _taps(u: float, v: float, sampling: str):
    """[(x, y, weight)], and the distance of the sample point to the nearest pixel edge that decides the taps."""
    if sampling == "nearest":
        x, y = math.floor(u), math.floor(v)
        return [(x, y, 1.0)], min(u - x, x + 1 - u, v - y, y + 1 - v)
    x, y = u - 0.5, v - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    taps = [
        (x0, y0, (1 - fx) * (1 - fy)),
        (x0 + 1, y0, fx * (1 - fy)),
        (x0, y0 + 1, (1 - fx) * fy),
        (x0 + 1, y0 + 1, fx * fy),
    ]
    return taps, min(fx, 1 - fx, fy, 1 - fy)


def _tap_code(src, b, x, y, q, n_dst, thr_p, thr_n, Ks_inv):
    """The first test tap (x, y) fails (KEPT: none), and the margin of the tests it ran."""
    values, depth, normal = src
    Hs, Ws = depth.shape[-2:]
    if not (0 <= x < Ws and 0 <= y < Hs):
        return OUT_OF_FRAME, math.inf  # the edge margin is the caller's
    z = depth[b, 0, y, x]
    if not _has_surface(z):
        return NO_SURFACE_SRC, math.inf
    p_src = z * (Ks_inv @ np.array([x + 0.5, y + 0.5, 1.0]))  # the tap's point in the source camera
    d_pos = float(np.linalg.norm(p_src - q))
    margin = abs(d_pos - thr_p)
    if not d_pos <= thr_p:
        return POSITION, margin
    d_nrm = float(np.linalg.norm(_finite_or_zero(normal[b, :, y, x]) - n_dst))
    margin = min(margin, abs(d_nrm - thr_n))
    if not d_nrm <= thr_n:
        return NORMAL, margin
    if not np.isfinite(values[b, :, y, x]).all():
        return NONFINITE, margin
    return KEPT, margin


def _keys(t: float, a: float = -0.5) -> float:
    """Keys' cubic convolution kernel at distance t (a = −0.5: Catmull-Rom)."""
    t = abs(t)
    if t <= 1:
        return (a + 2) * t**3 - (a + 3) * t**2 + 1
    if t < 2:
        return a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a
    return 0.0


def _cubic(src, b, u, v, q, n_dst, thr_p, thr_n, Ks_inv):
    """The Catmull-Rom value at source point (u, v) (None unless all 16 footprint taps pass), and the margin of the
    footprint's tests."""
    x0, y0 = math.floor(u - 0.5), math.floor(v - 0.5)
    total, margin, all_ok = 0.0, math.inf, True
    for y in range(y0 - 1, y0 + 3):
        for x in range(x0 - 1, x0 + 3):
            code, m = _tap_code(src, b, x, y, q, n_dst, thr_p, thr_n, Ks_inv)
            margin = min(margin, m)
            all_ok = all_ok and code == KEPT
            if all_ok:
                total = total + _keys(x + 0.5 - u) * _keys(y + 0.5 - v) * src[0][b, :, y, x]
    return (np.maximum(total, 0.0) if all_ok else None), margin


def _pixel(src, b, xd, yd, dst, cams, thr_p, thr_n, sampling):
    """(values (C,), reason, accepted weight, margin) of destination pixel (xd, yd) of batch item b."""
    dst_depth, dst_normal = dst
    Kd_inv, src_from_dst, Ks, Ks_inv = cams
    C = src[0].shape[1]
    z = dst_depth[b, 0, yd, xd]
    if not _has_surface(z):
        return np.zeros(C), NO_SURFACE_DST, 0.0, math.inf
    p_dst = z * (Kd_inv[b] @ np.array([xd + 0.5, yd + 0.5, 1.0]))  # in the destination camera
    q = src_from_dst[b, :3, :3] @ p_dst + src_from_dst[b, :3, 3]  # the same point in the source camera
    margin = abs(q[2])
    uvw = Ks[b] @ q
    if not q[2] > 0:
        return np.zeros(C), BEHIND_CAMERA, 0.0, margin
    u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
    taps, edge = _taps(u, v, sampling)
    margin = min(margin, edge)
    n_dst = _finite_or_zero(dst_normal[b, :, yd, xd])
    num, den, worst = np.zeros(C), 0.0, KEPT
    for x, y, w in taps:
        code, m = _tap_code(src, b, x, y, q, n_dst, thr_p, thr_n, Ks_inv[b])
        margin = min(margin, m)
        if w > 0:
            worst = max(worst, code)
            if code == KEPT:
                num, den = num + w * src[0][b, :, y, x], den + w
    if den > 0 and sampling == "catmull_rom":
        cubic, m = _cubic(src, b, u, v, q, n_dst, thr_p, thr_n, Ks_inv[b])
        margin = min(margin, m)
        if cubic is not None:
            return cubic, KEPT, den, margin
    if den > 0:
        return num / den, KEPT, den, margin
    return np.zeros(C), worst, 0.0, margin


def reference_backward_reproject(
    src_values,
    src_depth,
    src_normal,
    src_K,
    src_cam_from_world,
    dst_depth,
    dst_normal,
    dst_K,
    dst_cam_from_world,
    position_threshold,
    normal_threshold,
    sampling="bilinear",
):
    """The arguments of ``backward_reproject`` (tensors or arrays). Returns numpy arrays: values (B, C, H, W)
    float64, valid (B, 1, H, W) bool, reason (B, 1, H, W) uint8, confidence (B, 1, H, W) float64 (the accepted
    bilinear weight) and margin (B, 1, H, W) float64 (see the module docstring)."""
    src = (_np(src_values), _np(src_depth), _np(src_normal))
    dst = (_np(dst_depth), _np(dst_normal))
    Kd, Ks = _np(dst_K), _np(src_K)
    src_from_dst = _np(src_cam_from_world) @ np.linalg.inv(_np(dst_cam_from_world))
    cams = (np.linalg.inv(Kd), src_from_dst, Ks, np.linalg.inv(Ks))
    thr_p, thr_n = float(position_threshold), float(normal_threshold)
    B, C = src[0].shape[:2]
    H, W = dst[0].shape[-2:]
    values = np.zeros((B, C, H, W))
    reason = np.zeros((B, 1, H, W), np.uint8)
    conf = np.zeros((B, 1, H, W))
    margin = np.zeros((B, 1, H, W))
    for b in range(B):
        for yd in range(H):
            for xd in range(W):
                values[b, :, yd, xd], reason[b, 0, yd, xd], conf[b, 0, yd, xd], margin[b, 0, yd, xd] = _pixel(
                    src, b, xd, yd, dst, cams, thr_p, thr_n, sampling
                )
    return values, conf > 0, reason, conf, margin


def reference_temporal_blend(current, warped_history, warped_len, valid, alpha=0.2, warmup=True, max_history=255.0):
    """The blend of ``temporal_blend`` (hard tests) per pixel: ``a = max(1/(n+1), alpha)`` (or ``alpha``),
    ``(1 − a)·history + a·current`` where the history was kept (n + 1, capped), the current sample and n = 1
    elsewhere; a negative or NaN n counts as 0. Numpy arrays in, (colour, history length) out."""
    cur, hist, n0 = _np(current), np.asarray(warped_history, np.float64), np.asarray(warped_len, np.float64)
    out, n_out = cur.copy(), np.ones(n0.shape)
    B, _, H, W = cur.shape
    for b in range(B):
        for y in range(H):
            for x in range(W):
                if not valid[b, 0, y, x]:
                    continue
                n = n0[b, 0, y, x] if n0[b, 0, y, x] > 0 else 0.0
                a = max(1.0 / (n + 1.0), alpha) if warmup else alpha
                out[b, :, y, x] = cur[b, :, y, x] if a >= 1 else (1 - a) * hist[b, :, y, x] + a * cur[b, :, y, x]
                n_out[b, 0, y, x] = min(n + 1.0, max_history)
    return out, n_out
