"""Where an image's error lives: shares of the squared error held by pixel regions, how concentrated it is, a
per-region effective spp from a two-rung ladder, the resampling bias of a scheme measured without the reference's
noise, and the regions of a reprojection's 4×4 footprint.

Pure functions of (1, C, H, W) images and (1, 1, H, W) bool masks (and, for the footprint, the two
:class:`~stereorepro.View` of a reprojection); ``bench/error_anatomy.py`` and the experiment apply them to a
scheme's frames (which pixels decide a scheme's effective spp).

**The resampling bias without the reference's noise.** Feeding a noisy reference ``R = r + e`` through a scheme that
is linear in its input (a warp with fixed accept masks and an EMA: ``S(x) = A x``) and scoring against ``R`` itself
gives ``E|S(R) − R|² = |(A − I) r|² + E|(A − I) e|²``: the bias plus a copy of the reference's noise that falls as
1/spp. Two independent halves ``R_a``, ``R_b`` of the reference (disjoint sample ranges) give errors ``u = S(R_a) −
R_a`` and ``v = S(R_b) − R_b`` whose noises are independent with mean zero, so ``E[u · v] = |(A − I) r|²`` exactly,
at any reference spp (:func:`split_bias`); :func:`block_standard_error` is its statistical error and
:func:`reference_noise_mse` the noise the full reference still carries.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..camera import compose_warp, has_surface
from ..errors import ParameterError
from ..reproject import Reason, View, backward_reproject

__all__ = [
    "squared_error",
    "error_concentration",
    "error_shares",
    "two_rung_spp",
    "edge_mask",
    "split_bias",
    "block_standard_error",
    "reference_noise_mse",
    "FOOTPRINT_FAILS",
    "footprint_failures",
    "footprint_regions",
]


def squared_error(image: Tensor, reference: Tensor) -> Tensor:
    """(1, 1, H, W) float64: the squared error of each pixel, averaged over channels (its mean is the MSE).

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import squared_error
        >>> se = squared_error(torch.ones(1, 3, 2, 2), torch.zeros(1, 3, 2, 2))
        >>> se.shape, se.dtype, float(se.mean())
        (torch.Size([1, 1, 2, 2]), torch.float64, 1.0)
    """
    d = image.double() - reference.double()
    return (d * d).mean(1, keepdim=True)


def error_concentration(se: Tensor, fractions=(0.01, 0.05)) -> dict[str, float]:
    """Share (%) of the total squared error held by the worst ``f`` of the pixels, for each ``f``.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import error_concentration
        >>> se = torch.zeros(1, 1, 10, 10, dtype=torch.float64); se[0, 0, 0, 0] = 3.0; se[0, 0, 5, 5] = 1.0
        >>> error_concentration(se)
        {'top_1pct': 75.0, 'top_5pct': 100.0}
    """
    flat = se.flatten().sort(descending=True).values
    total = float(flat.sum())
    out = {}
    for f in fractions:
        k = max(1, int(round(f * flat.numel())))
        out[f"top_{f * 100:g}pct"] = 100.0 * float(flat[:k].sum()) / total if total > 0 else 0.0
    return out


def error_shares(se: Tensor, regions: dict[str, Tensor], se_bias: Tensor | None = None) -> dict[str, dict]:
    """For each region (a (1, 1, H, W) bool mask): its pixel share (%), its share of the squared error (%), its
    mean squared error, and with ``se_bias`` (the same scheme's error on noise-free inputs) the share of its
    error that is bias (%).

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import error_shares
        >>> se = torch.tensor([[[[4.0, 0.0], [0.0, 0.0]]]], dtype=torch.float64)
        >>> left = torch.tensor([[[[True, False], [True, False]]]])
        >>> shares = error_shares(se, {"left": left, "right": ~left})
        >>> shares["left"]
        {'pixels_pct': 50.0, 'se_share_pct': 100.0, 'mse': 2.0}
        >>> shares["right"]["se_share_pct"]
        0.0
    """
    total = float(se.sum())
    out = {}
    for name, m in regions.items():
        n = int(m.sum())
        s = float(se[m].sum()) if n else 0.0
        row = {
            "pixels_pct": 100.0 * n / m.numel(),
            "se_share_pct": 100.0 * s / total if total > 0 else 0.0,
            "mse": s / n if n else None,
        }
        if se_bias is not None:
            b = float(se_bias[m].sum()) if n else 0.0
            row["bias_pct_of_region"] = 100.0 * b / s if s > 0 else None
        out[name] = row
    return out


def two_rung_spp(mse_scheme: float, mse_1: float, mse_n: float, n: int) -> float | None:
    """Effective spp of a region from its MSE at 1 and ``n`` spp, fitting ``mse(k) = b + v / k`` through both
    (``b``: what samples cannot remove there, e.g. the metric's clamp): ``v / (mse_scheme - b)``; None where the
    fit is degenerate (``v <= 0``), inf where the scheme is at or below the floor.

    Examples:
        >>> from stereorepro.measure.anatomy import two_rung_spp
        >>> two_rung_spp(0.125, 1.0, 0.25, 4)
        8.0
        >>> two_rung_spp(0.5, 1.0, 1.0, 4) is None
        True
    """
    v = (mse_1 - mse_n) * n / (n - 1)
    b = mse_1 - v
    if v <= 0:
        return None
    return float("inf") if mse_scheme <= b else v / (mse_scheme - b)


def edge_mask(reference: Tensor, fraction: float = 0.05) -> Tensor:
    """(1, 1, H, W) bool: the ``fraction`` of pixels with the largest local contrast of ``reference`` (max absolute
    difference to the 4 neighbours, channel mean) — the high-contrast edges.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import edge_mask
        >>> ref = torch.zeros(1, 3, 4, 4); ref[..., 2:] = 1.0
        >>> m = edge_mask(ref, fraction=0.5)
        >>> m.shape, m.dtype, int(m.sum()), m[0, 0, 0].tolist()
        (torch.Size([1, 1, 4, 4]), torch.bool, 8, [False, True, True, False])
    """
    x = reference.double().mean(1, keepdim=True)
    p = torch.nn.functional.pad(x, (1, 1, 1, 1), mode="replicate")
    c = p[..., 1:-1, 1:-1]
    g = torch.stack(
        [
            (c - p[..., 1:-1, :-2]).abs(),
            (c - p[..., 1:-1, 2:]).abs(),
            (c - p[..., :-2, 1:-1]).abs(),
            (c - p[..., 2:, 1:-1]).abs(),
        ]
    ).amax(0)
    k = max(1, int(round(fraction * g.numel())))
    thr = g.flatten().topk(k).values[-1]
    return g >= thr


def split_bias(error_a: Tensor, error_b: Tensor) -> Tensor:
    """(1, 1, H, W) float64: per pixel, the product of a scheme's errors on two independent halves of the reference,
    averaged over channels. Its mean over the pixels estimates the scheme's squared bias without the reference's
    noise (module docstring); a single pixel's value is noisy and may be negative, a region's sum is its share.

    Args:
        error_a: (1, C, H, W) the scheme fed the first half minus that half (in the metric's space).
        error_b: (1, C, H, W) the same for the second, independent half.

    Raises:
        ShapeError: the two errors differ in shape.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import split_bias
        >>> bias = torch.full((1, 3, 2, 2), 0.1)
        >>> noise = torch.tensor([1.0, -1.0]).repeat(6).view(1, 3, 2, 2) * 0.05
        >>> b = split_bias(bias + noise, bias - noise)  # the noise terms cancel in the mean of the products
        >>> b.shape, round(float(b.mean()), 6), round(0.1**2, 6)
        (torch.Size([1, 1, 2, 2]), 0.0075, 0.01)
    """
    from ..errors import ShapeError

    if error_a.shape != error_b.shape:
        raise ShapeError(f"split_bias: error_a {tuple(error_a.shape)} and error_b {tuple(error_b.shape)} differ")
    return (error_a.double() * error_b.double()).mean(1, keepdim=True)


def block_standard_error(values: Tensor, block: int = 8) -> float:
    """Standard error of ``values.mean()`` for a (1, 1, H, W) map whose pixels are correlated over a few pixels
    (a reprojection's bilinear taps, an EMA's history): the spread of the means of ``block`` × ``block`` tiles
    (rows and columns past the last whole tile left out), divided by the square root of their number. 0.0 with
    fewer than two tiles.

    Raises:
        ParameterError: ``block`` < 1.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import block_standard_error
        >>> x = torch.zeros(1, 1, 16, 16, dtype=torch.float64); x[..., :8, :] = 1.0  # tiles 1, 1, 0, 0
        >>> round(block_standard_error(x, block=8), 4)  # std 0.5774 of the four tile means, over sqrt(4)
        0.2887
    """
    if int(block) < 1:
        raise ParameterError(f"block_standard_error: block must be >= 1, got {block}")
    H, W = values.shape[-2:]
    h, w = H // block, W // block
    if h * w < 2:
        return 0.0
    tiles = values[..., : h * block, : w * block].double().reshape(h, block, w, block).mean((1, 3)).flatten()
    return float(tiles.std() / (tiles.numel() ** 0.5))


def reference_noise_mse(half_a: Tensor, half_b: Tensor, spp_a: int, spp_b: int) -> float:
    """The mean squared noise of the reference made of two independent halves (the mean of ``spp_a + spp_b``
    samples), from their spread: ``E|a − b|² = σ² (1/spp_a + 1/spp_b)`` and the whole reference's noise is ``σ² /
    (spp_a + spp_b)``, so it is ``mean|a − b|² · spp_a · spp_b / (spp_a + spp_b)²``.

    Args:
        half_a, half_b: (1, C, H, W) the two halves (in the metric's space).
        spp_a, spp_b: their sample counts.

    Raises:
        ParameterError: a sample count < 1.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import reference_noise_mse
        >>> a, b = torch.full((1, 3, 4, 4), 0.6), torch.full((1, 3, 4, 4), 0.4)
        >>> round(reference_noise_mse(a, b, 16, 16), 6)  # 0.2² · 16 · 16 / 32²
        0.01
    """
    if int(spp_a) < 1 or int(spp_b) < 1:
        raise ParameterError(f"reference_noise_mse: spp_a and spp_b must be >= 1, got {spp_a} and {spp_b}")
    d = half_a.double() - half_b.double()
    return float((d * d).mean()) * spp_a * spp_b / (spp_a + spp_b) ** 2


#: The reasons of a footprint tap that count as failing the reprojection's tests (:func:`footprint_failures`): the
#: tap has no surface, fails the position or the normal test, or holds non-finite values. A tap outside the source
#: image is neither accepted nor failing.
FOOTPRINT_FAILS = (Reason.NO_SURFACE_SRC, Reason.POSITION, Reason.NORMAL, Reason.NONFINITE)


def _source_position(src: View, dst: View) -> tuple[Tensor, Tensor]:
    """(u, v), each (B, 1, H, W) float64: where each destination pixel centre lies in the source image (its
    motion vector where ``dst`` has one, else the cameras); NaN behind the source camera or without a surface."""
    B, _, H, W = dst.depth.shape
    dev = dst.depth.device
    u_c = torch.arange(W, device=dev, dtype=torch.float64).view(1, 1, 1, W) + 0.5
    v_c = torch.arange(H, device=dev, dtype=torch.float64).view(1, 1, H, 1) + 0.5
    surface = has_surface(dst.depth)
    nan = torch.full((), float("nan"), dtype=torch.float64, device=dev)
    if dst.motion is not None:
        m = dst.motion.double()
        return torch.where(surface, u_c + m[:, 0:1], nan), torch.where(surface, v_c + m[:, 1:2], nan)
    warp = compose_warp(src.K, src.cam_from_world, dst.K, dst.cam_from_world, torch.float64)
    hom, kt = warp.pixel_src_from_pixel_dst, warp.K_src_t
    z = torch.where(surface, dst.depth.double(), torch.ones((), dtype=torch.float64, device=dev))
    x, y, w = (
        hom[:, i, 0].view(B, 1, 1, 1) * u_c
        + hom[:, i, 1].view(B, 1, 1, 1) * v_c
        + hom[:, i, 2].view(B, 1, 1, 1)
        + kt[:, i, 0].view(B, 1, 1, 1) / z
        for i in range(3)
    )
    ok = surface & (w > 0)
    return torch.where(ok, x / w, nan), torch.where(ok, y / w, nan)


def footprint_failures(src: View, dst: View, thresholds, size: int = 4) -> Tensor:
    """(B, 1, H, W) int64: for each destination pixel, how many taps of the ``size`` × ``size`` source footprint
    around its reprojected position fail the reprojection's tests (:data:`FOOTPRINT_FAILS`). ``size=2`` is the
    bilinear footprint (the taps a bilinear reprojection reads), ``size=4`` the bicubic one around it (one more
    pixel on each side). Each tap is tested by :func:`~stereorepro.reproject.backward_reproject` itself (one
    ``"nearest"`` reprojection per tap, placed by a motion vector), so the tests are exactly the reprojection's:
    where ``dst`` has motion vectors they place the footprint and ``dst.motion_world`` moves the point.

    Args:
        src: the source :class:`~stereorepro.View` (the history's or the other eye's).
        dst: the destination :class:`~stereorepro.View`, whose pixels are classified.
        thresholds: ``(position, normal)`` or :class:`~stereorepro.Thresholds`, as the reprojection's.
        size: 2 or 4.

    Raises:
        ParameterError: ``size`` is not 2 or 4.

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> from stereorepro.measure.anatomy import footprint_failures
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> dst = View(depth, normal, intrinsics_from_fov(10.0, 8, 6), torch.eye(4)[None])  # pixels 0.06 apart
        >>> near = depth.clone(); near[..., 4:] = 1.0  # a step: the right half of the source is nearer
        >>> fails = footprint_failures(View(near, normal, dst.K, dst.cam_from_world), dst, (0.3, 0.1))
        >>> fails[0, 0, 2].tolist()  # 4 taps per source column on the step's near side; none past the border
        [0, 0, 4, 8, 12, 16, 12, 8]
    """
    if size not in (2, 4):
        raise ParameterError(f"footprint_failures: size must be 2 or 4, got {size!r}")
    u, v = _source_position(src, dst)
    H, W = dst.depth.shape[-2:]
    u_c = torch.arange(W, device=u.device, dtype=torch.float64).view(1, 1, 1, W) + 0.5
    v_c = torch.arange(H, device=u.device, dtype=torch.float64).view(1, 1, H, 1) + 0.5
    values = torch.zeros_like(dst.depth)
    fails = torch.tensor([int(r) for r in FOOTPRINT_FAILS], device=dst.depth.device)
    count = torch.zeros(dst.depth.shape, dtype=torch.int64, device=dst.depth.device)
    offsets = range(-(size // 2) + 1, size // 2 + 1)  # 2: 0, 1; 4: -1 .. 2 around floor(u - 0.5)
    for ky in offsets:
        for kx in offsets:
            # nearest reads floor(u_c + motion) = floor(u - 0.5) + k: the footprint's tap (k, k')
            motion = torch.cat([u - u_c + (kx - 0.5), v - v_c + (ky - 0.5)], 1).to(dst.depth.dtype)
            at = View(dst.depth, dst.normal, dst.K, dst.cam_from_world, motion, dst.motion_world)
            reason = backward_reproject(values, src, at, thresholds, sampling="nearest").reason
            count += torch.isin(reason, fails.to(reason.dtype)).to(torch.int64)
    return count


def footprint_regions(failures: Tensor, valid: Tensor, surface: Tensor) -> dict[str, Tensor]:
    """A partition of the destination pixels by a reprojection's outcome and its footprint
    (:func:`footprint_failures`): ``interior`` (kept, every footprint tap passes), ``edge`` (kept, a footprint tap
    fails: near silhouettes and creases), ``discarded`` (a surface pixel the reprojection rejected) and ``no
    surface``; each a (B, 1, H, W) bool mask.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.anatomy import footprint_regions
        >>> fails = torch.tensor([[[[0, 3, 16, 0]]]])
        >>> valid = torch.tensor([[[[True, True, False, False]]]])
        >>> surface = torch.tensor([[[[True, True, True, False]]]])
        >>> {k: m[0, 0, 0].tolist() for k, m in footprint_regions(fails, valid, surface).items()}["edge"]
        [False, True, False, False]
    """
    return {
        "interior": valid & (failures == 0),
        "edge": valid & (failures > 0),
        "discarded": surface & ~valid,
        "no surface": ~surface & ~valid,
    }
