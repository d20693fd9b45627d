"""Image error metrics and the paper's *effective spp* (samples per pixel) estimator.

Effective spp (paper §3, §4.1)
------------------------------
The effective spp of an image is the number of samples per pixel a plain path tracer would need to reach the
same error against the reference. It is read off a **ladder**: plain path-traced images at increasing sample
counts ``ladder_spp`` (e.g. 1, 2, ..., 16) whose errors ``ladder_rmse`` against the reference are measured
like the method's. The ladder's images are nested prefixes of one sample stream (rung n uses samples 1..n)
and that stream is disjoint from the reference's samples.

Noise model. Path-traced noise is unbiased with variance proportional to ``1/n``, so against a reference

    MSE(n) = a / n + b,        a > 0, b >= 0,

where ``a`` is the per-sample variance (averaged over pixels) and ``b`` a floor: the reference's own noise
(see *Reference noise*) plus any bias. Equivalently ``RMSE ~ c / sqrt(n)`` while ``b`` is negligible.

Interpolation. Between the two rungs ``n_lo < n_hi`` whose RMSEs bracket the value, the default
``interpolation="inverse_mse"`` is linear in ``1 / RMSE**2`` against spp. With ``b = 0`` the inverse MSE,
``n / a``, is exactly linear in ``n``, so this interpolation is exact for an ideal ladder at any spacing of
the rungs. ``interpolation="linear"`` is the paper's literal reading (linear in RMSE between n and n + 1);
it over-estimates between rungs because RMSE is convex in n: on an ideal ladder by up to 0.13 spp between
rungs 1 and 2, 0.04 between 4 and 5, 0.012 between 15 and 16.

Flags. Every estimate comes with one flag from :data:`EFFECTIVE_SPP_FLAGS`:

* ``"exact"``: the RMSE equals a rung's RMSE exactly; the rung's spp is returned.
* ``"interpolated"``: bracketed by two rungs of a strictly decreasing ladder.
* ``"extrapolated_low"``: the error is above the first rung's. The ``1/n`` law is anchored at the first
  rung: ``spp = n_0 * (MSE_0 - b) / (MSE - b)`` (< n_0), with the floor ``b`` of the ladder's least-squares
  fit (:func:`fit_ladder`); with ``b = 0`` this is ``n_0 * MSE_0 / MSE``. (Should a fit put ``b`` at or
  above ``MSE_0``, a pathological ladder, ``b = 0`` is used here.)
* ``"extrapolated_high"``: the error is below the last rung's. Same curve, ``a' / n + b`` with the fitted
  floor ``b``, re-anchored through the last rung (``a' = n_last * (MSE_last - b)``) so the estimate is
  continuous there: ``spp = n_last * (MSE_last - b) / (MSE - b)``.
* ``"beyond_floor"``: the error is at or below the fitted floor ``b`` (or below the last rung while the
  last rung itself is at or below ``b``): no finite spp reaches it. The estimate is ``+inf``, never a
  clamped number. An RMSE of exactly 0 against an ideal ladder (``b = 0``) also lands here.
* ``"fitted_nonmonotonic"``: the ladder's RMSE is not strictly decreasing (noise made neighbouring rungs
  cross), so bracketing is ambiguous. The whole-ladder fit is used instead: ``spp = a / (MSE - b)``
  (``"beyond_floor"`` and ``+inf`` if ``MSE <= b``).

Every branch is non-increasing in the RMSE, so a lower error never gives a lower effective spp on a given
ladder.

Reference noise
---------------
A reference rendered with ``N_ref`` spp is ``ref = t + e_ref`` (``t`` the converged image, ``e_ref`` zero-mean
noise with per-pixel variance ``s2 / N_ref``). For any image ``x = t + e_x`` whose noise is independent of
``e_ref`` (a ladder rung, or the method's output, as long as neither uses the reference's samples)::

    MSE(x, ref) = mean((e_x - e_ref)^2)
                = MSE(x, t) + mean(e_ref^2) - 2 mean(e_x * e_ref)
                ~ MSE(x, t) + s2 / N_ref   +  (zero-mean cross term).

The middle term is not only equal in expectation for every image compared against the same reference: it is
the *same realised number* for the method and for every rung, because it depends on the reference alone.
Matching the method's MSE against the ladder's therefore compares ``MSE_method(x, t) + c`` with
``MSE_ladder(n, t) + c``; the constant cancels and the spp at which they are equal is unchanged. What is left
is the cross terms, zero-mean fluctuations of relative size ``~ 1/sqrt(pixels)``, and a second-order effect
of interpolation: with the offset, ``1 / MSE`` is no longer exactly linear in ``n`` between two rungs (the
error is ``O((c / MSE)^2)`` of the rung spacing). Comparing the method's MSE against a *truth*-based ladder,
or against the formula ``a / MSE``, would not cancel it and would under-estimate spp.

Choosing ``N_ref``. In the ladder fit ``c`` is the floor ``b``. Above the last rung (``"extrapolated_high"``)
and in the fit, the estimate depends on ``MSE - b``, so ``b`` must stay small compared with the last rung's
variance ``a / n_last`` or the flat region swallows the resolvable range: with
``N_ref = k * n_last`` the last rung carries ``b / MSE_last = 1 / (k + 1)`` of its error as floor. For
``"extrapolated_high"`` estimates the model asks ``k >= 8``; the paper's 4096 spp reference leaves ``b`` at < 0.4 %
of the 16-spp rung's error. On the real scenes' ladders (LDR, references of 2–8 ladder lengths) the extrapolation runs
high, often far (``bench/results/ladder_extrapolation.md``: a measured ladder cut short, extrapolated, and compared
with its full length), so the experiment reports frames beyond its ladder as a lower bound. Inside the ladder the
cancellation holds in practice down to ``k = 1/2`` (the reference-spp
study of ``experiment --reference-chunk-spp``, which scores every ladder against the reference's prefixes; results in
``bench/results/paper720.md``). Hence :func:`suggest_reference_spp`'s default ``k = 1``.

Shapes: B batch, C channels, H height, W width, N ladder rungs, F frames (one effective spp per frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from .._checks import ShapeError, all_finite, check_floating, check_shape
from ..errors import ParameterError, ParameterTypeError
from .._extras import available, require

__all__ = [
    "EFFECTIVE_SPP_FLAGS",
    "mse",
    "rmse",
    "ssim",
    "flip",
    "flip_available",
    "ladder_rmse",
    "fit_ladder",
    "effective_spp",
    "effective_spp_many",
    "suggest_reference_spp",
    "EffectiveSppLadder",
]

#: Flags returned by :func:`effective_spp` / :func:`effective_spp_many` (see the module docstring).
EFFECTIVE_SPP_FLAGS: tuple[str, ...] = (
    "exact",
    "interpolated",
    "extrapolated_low",
    "extrapolated_high",
    "beyond_floor",
    "fitted_nonmonotonic",
)
_EXACT, _INTERP, _LOW, _HIGH, _FLOOR, _NONMONO = range(len(EFFECTIVE_SPP_FLAGS))

_INTERPOLATIONS = ("inverse_mse", "linear")
_NONFINITE_POLICIES = ("raise", "ignore")


# ----------------------------------------------------------------------------------------------------------
# Pixel errors
# ----------------------------------------------------------------------------------------------------------


def _check_pair(image: Tensor, reference: Tensor, mask: Tensor | None, name: str) -> None:
    bind = check_shape(image, ["B", "C", "H", "W"], f"{name} image")
    check_shape(reference, ["R", "C", "H", "W"], f"{name} reference", bind)
    check_floating(image, f"{name} image")
    check_floating(reference, f"{name} reference")
    if reference.shape[0] not in (1, bind["B"]):
        raise ShapeError(f"{name}: reference batch must be 1 or B={bind['B']}, got shape {tuple(reference.shape)}")
    if mask is not None:
        check_shape(mask, ["B", "1", "H", "W"], f"{name} mask", bind)
        if mask.dtype != torch.bool:
            raise ParameterTypeError(f"{name} mask: expected a bool tensor, got dtype {mask.dtype}")


def _pixel_valid(image: Tensor, reference: Tensor, mask: Tensor | None, nonfinite: str, name: str) -> Tensor:
    """(B, 1, H, W) bool: pixels entering the mean, after the non-finite policy. Raises per the policy."""
    if nonfinite not in _NONFINITE_POLICIES:
        raise ParameterError(f"{name}: nonfinite must be one of {_NONFINITE_POLICIES}, got {nonfinite!r}")
    B = image.shape[0]
    valid = torch.ones_like(image[:, :1], dtype=torch.bool) if mask is None else mask.clone()
    ref_bad = ~torch.isfinite(reference).all(1, keepdim=True).expand(B, -1, -1, -1) & valid
    if bool(ref_bad.any()):
        raise ParameterError(
            f"{name}: reference has {int(ref_bad.sum())} non-finite pixel(s) inside the mask; "
            "a reference must be finite (mask those pixels out)"
        )
    img_bad = ~torch.isfinite(image).all(1, keepdim=True) & valid
    n_bad = int(img_bad.sum())
    if n_bad:
        if nonfinite == "raise":
            items = torch.nonzero(img_bad.flatten(1).any(1)).flatten().tolist()
            raise ParameterError(
                f"{name}: image has {n_bad} non-finite pixel(s) (NaN/inf) in batch item(s) "
                f"{items}; pass nonfinite='ignore' to exclude them from the mean"
            )
        valid = valid & ~img_bad
    empty = valid.flatten(1).sum(1) == 0
    if bool(empty.any()):
        raise ParameterError(f"{name}: no valid pixels in batch item(s) {torch.nonzero(empty).flatten().tolist()}")
    return valid


def _check_finite(name: str, **tensors: Tensor) -> None:
    """ParameterError naming the first of ``tensors`` (B, C, H, W) with pixels holding a NaN/inf channel."""
    for nm, t in tensors.items():
        if all_finite(t):
            continue
        n_bad = int((~torch.isfinite(t)).any(1).sum())
        if n_bad:
            raise ParameterError(f"{name}: {nm} has {n_bad} non-finite pixel(s) (NaN/inf)")


def mse(image: Tensor, reference: Tensor, mask: Tensor | None = None, nonfinite: str = "raise") -> Tensor:
    """Mean squared error per batch item, over channels and (masked) pixels, computed in float64.

    Args:
        image: (B, C, H, W) floating point, e.g. linear HDR radiance.
        reference: (B, C, H, W) or (1, C, H, W) (broadcast over the batch); must be finite inside the mask.
        mask: optional (B, 1, H, W) bool; only True pixels count (all channels of a pixel together).
        nonfinite: policy for pixels of ``image`` with any NaN/inf channel inside the mask: ``"raise"``
            (default) raises ValueError naming their count; ``"ignore"`` excludes those pixels from the mean,
            like a mask. A batch item left without pixels raises ValueError either way.

    Returns:
        (B,) float64.

    Examples:
        >>> x = torch.zeros(2, 3, 4, 4); ref = torch.full((1, 3, 4, 4), 0.5)
        >>> mse(x, ref)
        tensor([0.2500, 0.2500], dtype=torch.float64)
    """
    _check_pair(image, reference, mask, "mse")
    valid = _pixel_valid(image, reference, mask, nonfinite, "mse")
    C = image.shape[1]
    diff = image.to(torch.float64) - reference.to(torch.float64)  # BxCxHxW
    sq = torch.where(valid, diff * diff, torch.zeros((), dtype=torch.float64, device=diff.device))
    return sq.flatten(1).sum(1) / (valid.flatten(1).sum(1).to(torch.float64) * C)


def rmse(image: Tensor, reference: Tensor, mask: Tensor | None = None, nonfinite: str = "raise") -> Tensor:
    """Root mean squared error per batch item: ``sqrt(mse(...))``. Same arguments as :func:`mse`.

    Returns:
        (B,) float64.

    Examples:
        >>> import torch
        >>> from stereorepro.measure import rmse
        >>> ref = torch.zeros(2, 3, 4, 4); img = ref.clone(); img[1] += 0.5
        >>> rmse(img, ref).tolist()
        [0.0, 0.5]
    """
    return mse(image, reference, mask, nonfinite).sqrt()


def flip_available() -> bool:
    """True when NVIDIA's FLIP (``pip install flip-evaluator``; extras ``[flip]`` and ``[experiment]``) is
    installed.

    Examples:
        >>> from stereorepro.measure.metrics import flip_available
        >>> isinstance(flip_available(), bool)
        True
    """
    return available("flip_evaluator")


def flip(image: Tensor, reference: Tensor) -> Tensor:
    """Mean LDR FLIP error per batch item (NVIDIA's perceptual difference, 0 = identical; ``flip-evaluator``), of
    linear radiance clamped to [0, 1] (the display at exposure 1, as the experiment's LDR RMSE; passed as linear,
    ``inputsRGB=False``), at FLIP's default 67 pixels per degree.

    Effective spp stays MSE-based: it rests on the 1/n decay of an unbiased estimator's MSE, which FLIP (a
    perceptual, non-additive error) does not have; FLIP is reported beside it.

    Args:
        image, reference: (B, 3, H, W) (reference may be (1, 3, H, W)), finite (non-finite values raise, as in
            :func:`mse` and :func:`ssim`: clamping would read NaN as 0).

    Returns:
        (B,) float64.

    Examples:
        >>> import torch
        >>> from stereorepro.measure.metrics import flip, flip_available
        >>> image = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0))
        >>> # flip needs flip-evaluator; without it, use the value FLIP gives identical images (0)
        >>> err = flip(image, image) if flip_available() else torch.zeros(2, dtype=torch.float64)
        >>> err.shape, err.dtype, err.tolist()
        (torch.Size([2]), torch.float64, [0.0, 0.0])
    """
    _check_pair(image, reference, None, "flip")
    if image.shape[1] != 3:
        raise ShapeError(f"flip: expected 3 colour channels, got shape {tuple(image.shape)}")
    _check_finite("flip", image=image, reference=reference)
    flip_evaluator = require("flip_evaluator", "flip (NVIDIA's FLIP)")
    ref = reference.expand_as(image)
    out = []
    for b in range(image.shape[0]):

        def hwc(t):
            return t[b].detach().to("cpu", torch.float32).clamp(0, 1).permute(1, 2, 0).contiguous().numpy()

        _, mean, _ = flip_evaluator.evaluate(hwc(ref), hwc(image), "LDR", inputsRGB=False, applyMagma=False)
        out.append(float(mean))
    return torch.tensor(out, dtype=torch.float64)


def ssim(
    image: Tensor,
    reference: Tensor,
    mask: Tensor | None = None,
    window_size: int = 11,
    tonemap: str = "clamp",
    max_val: float = 1.0,
) -> Tensor:
    """Mean SSIM per batch item (kornia's Gaussian-window SSIM, sigma 1.5), computed in float64.

    SSIM's constants assume a known data range ``max_val``; HDR radiance has none, so values are first mapped
    to a display range:

    * ``tonemap="clamp"`` (default): negatives to 0, values above 1 to 1 (the displayed image at exposure 1;
      differences among highlights above 1 are not seen);
    * ``tonemap="reinhard"``: negatives to 0, then ``x / (1 + x)`` per channel, order-preserving onto [0, 1);
    * ``tonemap="none"``: values used as they are, with the caller's ``max_val``.

    Args:
        image: (B, C, H, W) floating point, finite (non-finite values raise: they spread through the window).
        reference: (B, C, H, W) or (1, C, H, W), finite.
        mask: optional (B, 1, H, W) bool; the SSIM map is averaged over True pixels (the window still reads
            the neighbours).
        window_size: odd number of Gaussian taps; H and W must exceed ``window_size // 2``.
        tonemap: "clamp", "reinhard" or "none", see above.
        max_val: data range L after tonemapping (1.0 unless ``tonemap="none"``).

    Returns:
        (B,) float64, exactly 1 for identical images (black ones too: the SSIM ratio without an epsilon, its
        constants keep the denominator > 0).

    Examples:
        >>> import torch
        >>> from stereorepro.measure import ssim
        >>> ref = torch.linspace(0, 1, 768).reshape(1, 3, 16, 16)
        >>> checker = ((torch.arange(16)[:, None] + torch.arange(16)) % 2).float()
        >>> round(float(ssim(ref, ref)[0]), 6), round(float(ssim(ref + 0.1 * checker, ref)[0]), 3)
        (1.0, 0.502)
    """
    _check_pair(image, reference, mask, "ssim")
    if tonemap not in ("clamp", "reinhard", "none"):
        raise ParameterError(f"ssim: tonemap must be 'clamp', 'reinhard' or 'none', got {tonemap!r}")
    if window_size < 1 or window_size % 2 == 0:
        raise ParameterError(f"ssim: window_size must be a positive odd integer, got {window_size}")
    if not (isinstance(max_val, (int, float)) and math.isfinite(max_val) and max_val > 0):
        raise ParameterError(f"ssim: max_val must be a finite number > 0, got {max_val!r}")
    H, W = image.shape[-2:]
    if min(H, W) <= window_size // 2:
        raise ShapeError(f"ssim: image {H}x{W} too small for window_size={window_size}")
    _check_finite("ssim", image=image, reference=reference)
    kornia = require("kornia", "ssim")  # lazy: importing kornia costs ~2 s; only SSIM needs it

    def _map(t: Tensor) -> Tensor:
        t = t.to(torch.float64)
        if tonemap == "clamp":
            return t.clamp(0.0, 1.0)
        if tonemap == "reinhard":
            t = t.clamp_min(0.0)
            return t / (1.0 + t)
        return t

    x, y = _map(image), _map(reference).expand_as(image)
    smap = kornia.metrics.ssim(x, y, window_size, max_val=float(max_val), eps=0.0).mean(1, keepdim=True)  # Bx1xHxW
    if mask is None:
        return smap.flatten(1).mean(1)
    count = mask.flatten(1).sum(1)
    if bool((count == 0).any()):
        raise ParameterError(f"ssim: empty mask in batch item(s) {torch.nonzero(count == 0).flatten().tolist()}")
    return torch.where(mask, smap, torch.zeros_like(smap)).flatten(1).sum(1) / count.to(torch.float64)


def ladder_rmse(
    ladder_images: Tensor | Sequence[Tensor], reference: Tensor, mask: Tensor | None = None, nonfinite: str = "raise"
) -> Tensor:
    """RMSE of every rung of a ladder against the reference.

    Args:
        ladder_images: (N, B, C, H, W) tensor, or a sequence of N (B, C, H, W) tensors; rung i is the plain
            path-traced image at ``ladder_spp[i]`` spp (nested prefixes of one sample stream, disjoint from the
            reference's).
        reference: (B, C, H, W) or (1, C, H, W).
        mask, nonfinite: as in :func:`mse`, applied to every rung.

    Returns:
        (B, N) float64: row b is the ladder of batch item (frame) b, ready for :func:`effective_spp_many`.

    Examples:
        >>> import torch
        >>> from stereorepro.measure import ladder_rmse
        >>> ref = torch.zeros(1, 3, 4, 4)
        >>> rungs = [ref + 0.4, ref + 0.2, ref + 0.1]  # 1, 4 and 16 spp: the error halves per 4x samples
        >>> [[round(v, 6) for v in row] for row in ladder_rmse(rungs, ref).tolist()]
        [[0.4, 0.2, 0.1]]
    """
    if isinstance(ladder_images, Tensor):
        check_shape(ladder_images, ["N", "B", "C", "H", "W"], "ladder_rmse ladder_images")
        rungs = list(ladder_images.unbind(0))
    else:
        rungs = list(ladder_images)
    if len(rungs) == 0:
        raise ParameterError("ladder_rmse: the ladder has no images")
    shapes = {tuple(r.shape) if isinstance(r, Tensor) else None for r in rungs}
    if len(shapes) != 1:
        raise ShapeError(f"ladder_rmse: all rungs must share one (B, C, H, W) shape, got {sorted(map(str, shapes))}")
    return torch.stack([rmse(r, reference, mask, nonfinite) for r in rungs], dim=1)


# ----------------------------------------------------------------------------------------------------------
# Effective spp
# ----------------------------------------------------------------------------------------------------------


def _as_f64(x, name: str) -> Tensor:
    t = x if isinstance(x, Tensor) else torch.as_tensor(x, dtype=torch.float64)  # not float32 by default
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64, torch.int16, torch.int8, torch.uint8)):
        raise ParameterTypeError(f"{name}: expected real numbers, got dtype {t.dtype}")
    return t.detach().to(torch.float64)


def _check_ladder(ladder_spp, ladder_rmse_, name: str) -> tuple[Tensor, Tensor]:
    """Validated (N,) spp and (F, N) RMSE (F = 1 for a shared ladder), float64."""
    s = _as_f64(ladder_spp, f"{name} ladder_spp")
    R = _as_f64(ladder_rmse_, f"{name} ladder_rmse").to(s.device)
    if s.dim() != 1 or s.numel() == 0:
        raise ShapeError(f"{name}: ladder_spp must be a non-empty 1-D sequence (N,), got shape {tuple(s.shape)}")
    if not bool(torch.isfinite(s).all()) or not bool((s > 0).all()):
        raise ParameterError(f"{name}: ladder_spp must be finite and > 0, got {s.tolist()}")
    if s.numel() > 1 and not bool((s[1:] > s[:-1]).all()):
        raise ParameterError(f"{name}: ladder_spp must be strictly increasing, got {s.tolist()}")
    if R.dim() == 1:
        R = R.unsqueeze(0)
    if R.dim() != 2 or R.shape[1] != s.numel():
        raise ShapeError(f"{name}: ladder_rmse must be (N,) or (F, N) with N={s.numel()}, got shape {tuple(R.shape)}")
    bad = ~torch.isfinite(R) | (R <= 0)
    if bool(bad.any()):
        raise ParameterError(f"{name}: ladder_rmse must be finite and > 0; {int(bad.sum())} value(s) are not")
    return s, R


def _unit_scale(R: Tensor) -> Tensor:
    """(F, 1) int64 ``k`` per row with ``R[:, 0]·2^k`` in [0.5, 1): RMSEs scaled by ``2^k`` (:func:`_scaled`) square
    without overflow or underflow wherever float64 holds them, and the scaling is exact (a power of two), so every
    ratio of MSEs — the fit's shape, the effective spp — is the same bit for bit as unscaled."""
    return -torch.frexp(R[:, :1])[1].to(torch.int64)


def _scaled(x: Tensor, k: Tensor) -> Tensor:
    """``x·2^k``, in two exact steps (one power of two alone could leave float64's range)."""
    half = torch.div(k, 2, rounding_mode="floor")
    return x * torch.pow(2.0, half.to(x.dtype)) * torch.pow(2.0, (k - half).to(x.dtype))


def _squares(R: Tensor, name: str) -> Tensor:
    """``R²`` of scaled RMSEs, or ParameterError when a ladder spans more than float64 can square."""
    M = R * R
    if not bool((torch.isfinite(M) & (M >= torch.finfo(M.dtype).tiny)).all()):
        raise ParameterError(
            f"{name}: ladder_rmse spans too wide a range within a ladder (its MSEs leave "
            f"float64's range), got {R.tolist()} after scaling each row by a power of two"
        )
    return M


def _fit(s: Tensor, M: Tensor, name: str) -> tuple[Tensor, Tensor]:
    """Relative least squares fit of ``M ~ a / s + b``, a > 0, b >= 0, per row. s (N,), M (F, N) → a, b (F,)."""
    F, N = M.shape
    M0 = M[:, :1]
    Mn = M / M0  # normalised: fit is scale-free, result rescaled by M0
    if N == 1:
        return (s[0] * M[:, 0]).clone(), torch.zeros(F, dtype=M.dtype, device=M.device)
    # Residual i: (a x_i + b) / M_i - 1, x = 1/s  →  features u = x/M, v = 1/M, target 1.
    u = (1.0 / s) / Mn  # FxN
    v = 1.0 / Mn
    A = torch.stack([u, v], dim=-1)  # FxNx2
    sol = torch.linalg.lstsq(A, torch.ones_like(u)[..., None], driver="gelsd").solution[..., 0]  # Fx2 (SVD)
    a_free, b_free = sol[:, 0], sol[:, 1]
    interior = torch.isfinite(sol).all(1) & (a_free > 0) & (b_free >= 0)
    Suu, Svv = (u * u).sum(1), (v * v).sum(1)
    Su, Sv = u.sum(1), v.sum(1)
    # Boundary candidates of the convex problem: b = 0 (a > 0 always) or a = 0 (flat ladder).
    a_b0 = Su / Suu
    b_a0 = Sv / Svv

    def _obj(a, b):
        return ((a[:, None] * u + b[:, None] * v - 1.0) ** 2).sum(1)

    zero = torch.zeros_like(a_b0)
    flat = ~interior & (_obj(zero, b_a0) < _obj(a_b0, zero))
    if bool(flat.any()):
        raise ParameterError(
            f"{name}: ladder error does not decrease with spp (best fit MSE = a/n + b has a = 0) "
            f"in frame(s) {torch.nonzero(flat).flatten().tolist()}"
        )
    a = torch.where(interior, a_free, a_b0)
    b = torch.where(interior, b_free, zero)
    return a * M0[:, 0], b * M0[:, 0]


def fit_ladder(ladder_spp, ladder_rmse) -> tuple[Tensor, Tensor]:
    """Fit ``MSE(n) = a / n + b`` (a > 0, b >= 0) to a ladder by relative least squares.

    The residuals are relative, ``(a / n_i + b - MSE_i) / MSE_i``: MSE estimates from P pixels have a
    roughly constant relative spread (``~ sqrt(2 / P)``), and plain least squares would let the 1-spp rung
    dominate. If the unconstrained optimum has ``b < 0`` the fit is redone with ``b = 0`` (bias cannot be
    negative); a ladder whose best fit is flat (``a = 0``) raises ValueError. A one-rung ladder gives
    ``b = 0``, ``a = n_0 MSE_0``.

    Args:
        ladder_spp: (N,) strictly increasing, > 0.
        ladder_rmse: (N,) or (F, N), > 0.

    Returns:
        (a, b): float64 tensors of shape () for a (N,) ladder, (F,) for (F, N); in MSE units.

    Examples:
        >>> from stereorepro.measure import fit_ladder
        >>> a, b = fit_ladder([1.0, 4.0, 16.0], [0.4, 0.2, 0.1])  # MSE(n) = 0.16 / n
        >>> round(float(a), 6), round(float(b), 6)
        (0.16, 0.0)
    """
    s, R = _check_ladder(ladder_spp, ladder_rmse, "fit_ladder")
    k = _unit_scale(R)
    a, b = _fit(s, _squares(_scaled(R, k), "fit_ladder"), "fit_ladder")
    a, b = _scaled(a, -2 * k[:, 0]), _scaled(b, -2 * k[:, 0])  # back to the ladder's MSE units
    if not bool(torch.isfinite(a).all() and torch.isfinite(b).all() and (a > 0).all()):
        raise ParameterError(
            f"fit_ladder: the fit's MSE (a = {a.tolist()}, b = {b.tolist()}) is beyond float64's "
            "range; effective_spp_many works on such ladders (it uses only ratios)"
        )
    shared = _as_f64(ladder_rmse, "fit_ladder ladder_rmse").dim() == 1
    return (a[0], b[0]) if shared else (a, b)


def effective_spp_many(
    rmse_values, ladder_spp, ladder_rmse, interpolation: str = "inverse_mse"
) -> tuple[Tensor, list[str]]:
    """Effective spp of F frames (paper §4.1), vectorised. See the module docstring for the model and flags.

    Args:
        rmse_values: (F,) RMSE of the method's frames against the reference; finite and >= 0.
        ladder_spp: (N,) strictly increasing spp of the ladder's rungs, e.g. ``1..16``.
        ladder_rmse: (N,) one ladder for all frames, or (F, N) a ladder per frame (same reference as the
            frame's ``rmse_values``), e.g. from :func:`ladder_rmse`. Finite and > 0.
        interpolation: ``"inverse_mse"`` (default, linear in 1/RMSE² vs spp: exact for MSE ∝ 1/spp) or
            ``"linear"`` (linear in RMSE vs spp, the paper's literal reading). Only affects ``"interpolated"``.

    Returns:
        spp: (F,) float64, ``+inf`` where flagged ``"beyond_floor"``.
        flags: list of F strings from :data:`EFFECTIVE_SPP_FLAGS`.

    Raises:
        ParameterError: NaN/inf/negative RMSE, an invalid ladder, or a ladder whose error does not decrease
            (a ValueError).

    Examples:
        >>> spp, flags = effective_spp_many([0.5, 0.3], [1, 2, 4], [1.0, 2 ** -0.5, 0.5])
        >>> [round(x, 6) for x in spp.tolist()], flags
        ([4.0, 11.111111], ['exact', 'extrapolated_high'])
    """
    if interpolation not in _INTERPOLATIONS:
        raise ParameterError(f"effective_spp: interpolation must be one of {_INTERPOLATIONS}, got {interpolation!r}")
    r = _as_f64(rmse_values, "effective_spp rmse_values")
    if r.dim() != 1:
        raise ShapeError(f"effective_spp: rmse_values must be 1-D (F,), got shape {tuple(r.shape)}")
    bad = ~torch.isfinite(r) | (r < 0)
    if bool(bad.any()):
        raise ParameterError(
            f"effective_spp: rmse values must be finite and >= 0; got {r[bad].tolist()} "
            f"at frame(s) {torch.nonzero(bad).flatten().tolist()}"
        )
    s, R = _check_ladder(ladder_spp, ladder_rmse, "effective_spp")
    F, N = r.numel(), s.numel()
    if R.shape[0] not in (1, F):
        raise ShapeError(
            f"effective_spp: ladder_rmse (F, N) must have F={F} rows (one per value), got shape {tuple(R.shape)}"
        )
    r = r.to(s.device)
    R = R.expand(F, N)
    k = _unit_scale(R)  # every quantity below is a ratio of MSEs: scaled exactly, squared safely
    r, R = _scaled(r, k[:, 0]), _scaled(R, k)
    m, M = r * r, _squares(R, "effective_spp")  # F, FxN
    a, b = _fit(s, M, "effective_spp")
    inf = torch.full_like(m, math.inf)

    # Monotonic ladders: bracket. k = number of rungs with larger error (rungs 0..k-1, since M decreases).
    mono = (M[:, 1:] < M[:, :-1]).all(1) if N > 1 else torch.ones(F, dtype=torch.bool, device=m.device)
    k = (M > m[:, None]).sum(1)
    eq = M == m[:, None]
    exact = eq.any(1)
    exact_spp = s[eq.to(torch.int8).argmax(1)]
    lo = (k - 1).clamp(0, N - 1)
    hi = k.clamp(0, N - 1)
    s_lo, s_hi = s[lo], s[hi]
    M_lo, M_hi = M.gather(1, lo[:, None])[:, 0], M.gather(1, hi[:, None])[:, 0]
    if interpolation == "inverse_mse":
        t = (1.0 / m - 1.0 / M_lo) / (1.0 / M_hi - 1.0 / M_lo)
    else:
        R_lo, R_hi = R.gather(1, lo[:, None])[:, 0], R.gather(1, hi[:, None])[:, 0]
        t = (R_lo - r) / (R_lo - R_hi)
    interp_spp = torch.minimum(torch.maximum(s_lo + t * (s_hi - s_lo), s_lo), s_hi)  # clamp: rounding only
    b_low = torch.where(M[:, 0] > b, b, torch.zeros_like(b))
    low_spp = s[0] * (M[:, 0] - b_low) / (m - b_low)
    M_last = M[:, -1]
    high_ok = (m > b) & (M_last > b)
    high_spp = torch.where(high_ok, s[-1] * (M_last - b) / (m - b), inf)
    fit_ok = m > b
    fit_spp = torch.where(fit_ok, a / (m - b), inf)

    is_low = mono & ~exact & (k == 0)
    is_high = mono & ~exact & (k == N)
    spp = torch.where(
        ~mono,
        fit_spp,
        torch.where(exact, exact_spp, torch.where(is_low, low_spp, torch.where(is_high, high_spp, interp_spp))),
    )
    code = torch.full((F,), _INTERP, dtype=torch.int64, device=m.device)
    code = torch.where(mono & exact, torch.full_like(code, _EXACT), code)
    code = torch.where(is_low, torch.full_like(code, _LOW), code)
    code = torch.where(is_high, torch.where(high_ok, torch.full_like(code, _HIGH), torch.full_like(code, _FLOOR)), code)
    code = torch.where(~mono, torch.where(fit_ok, torch.full_like(code, _NONMONO), torch.full_like(code, _FLOOR)), code)
    return spp, [EFFECTIVE_SPP_FLAGS[c] for c in code.tolist()]


def effective_spp(rmse_value, ladder_spp, ladder_rmse, interpolation: str = "inverse_mse") -> tuple[float, str]:
    """Effective spp of one frame (paper §4.1): :func:`effective_spp_many` for a single value.

    Args:
        rmse_value: float or 0-d tensor, the method's RMSE against the reference; finite and >= 0.
        ladder_spp: (N,) strictly increasing spp of the ladder's rungs.
        ladder_rmse: (N,) RMSE of the rungs against the same reference.
        interpolation: ``"inverse_mse"`` (default) or ``"linear"``.

    Returns:
        (spp, flag): spp a Python float (``inf`` for ``"beyond_floor"``), flag from :data:`EFFECTIVE_SPP_FLAGS`.

    Examples:
        >>> effective_spp(0.8, [1, 2, 3], [1.0, 0.7, 0.55])  # doctest: +ELLIPSIS
        (1.540441176..., 'interpolated')
    """
    r = _as_f64(rmse_value, "effective_spp rmse_value")
    if r.numel() != 1:
        raise ShapeError(f"effective_spp: rmse_value must be a scalar, got shape {tuple(r.shape)}")
    R = _as_f64(ladder_rmse, "effective_spp ladder_rmse")
    if R.dim() != 1:
        raise ShapeError(
            f"effective_spp: ladder_rmse must be 1-D (N,), got shape {tuple(R.shape)}; "
            "use effective_spp_many for a ladder per frame"
        )
    spp, flags = effective_spp_many(r.reshape(1), ladder_spp, R, interpolation)
    return float(spp[0]), flags[0]


def suggest_reference_spp(max_ladder_spp: float, ratio: float = 1.0) -> int:
    """Reference spp for a ladder up to ``max_ladder_spp``: the next power of two at or above
    ``ratio * max_ladder_spp``.

    Effective spp matched inside the ladder does not depend on the reference's noise to first order (module
    docstring, *Reference noise*), so ``ratio = 1`` (the default) is enough there (the reference-spp study in
    ``bench/results/paper720.md``). Estimates above the ladder's top rung
    (``"extrapolated_high"``) depend on the floor ``b = s2 / N_ref``, ``1 / (ratio + 1)`` of the last rung's MSE:
    use ``ratio >= 8`` when those matter.

    Args:
        max_ladder_spp: the ladder's highest spp, > 0.
        ratio: >= 1; 1 by default (8 or more for estimates beyond the ladder).

    Examples:
        >>> suggest_reference_spp(32)
        32
        >>> suggest_reference_spp(16, ratio=16)
        256
    """
    if not (max_ladder_spp > 0 and math.isfinite(max_ladder_spp)):
        raise ParameterError(f"suggest_reference_spp: max_ladder_spp must be finite and > 0, got {max_ladder_spp}")
    if not (ratio >= 1 and math.isfinite(ratio)):
        raise ParameterError(f"suggest_reference_spp: ratio must be finite and >= 1, got {ratio}")
    return 1 << max(0, math.ceil(math.log2(ratio * max_ladder_spp) - 1e-12))


@dataclass(frozen=True)
class EffectiveSppLadder:
    """A validated ladder shared by many frames: stores settings and calls :func:`effective_spp_many`.

    Attributes:
        ladder_spp: (N,) float64, strictly increasing.
        ladder_rmse: (N,) float64, > 0.
        interpolation: ``"inverse_mse"`` or ``"linear"``.

    Examples:
        >>> from stereorepro.measure import EffectiveSppLadder
        >>> ladder = EffectiveSppLadder([1.0, 4.0, 16.0], [0.4, 0.2, 0.1])  # RMSE of 1, 4 and 16 spp
        >>> ladder((0.16 / 8) ** 0.5)  # an image with the RMSE of 8 spp
        (8.0, 'interpolated')
        >>> [round(v, 6) for v in ladder.fit]
        [0.16, 0.0]
    """

    ladder_spp: Tensor
    ladder_rmse: Tensor
    interpolation: str = "inverse_mse"

    def __post_init__(self):
        s, R = _check_ladder(self.ladder_spp, self.ladder_rmse, "EffectiveSppLadder")
        if R.shape[0] != 1 or _as_f64(self.ladder_rmse, "EffectiveSppLadder").dim() != 1:
            raise ShapeError(
                f"EffectiveSppLadder: ladder_rmse must be 1-D (N,), got shape "
                f"{tuple(torch.as_tensor(self.ladder_rmse).shape)}"
            )
        if self.interpolation not in _INTERPOLATIONS:
            raise ParameterError(
                f"EffectiveSppLadder: interpolation must be one of {_INTERPOLATIONS}, got {self.interpolation!r}"
            )
        _fit(s, _squares(_scaled(R, _unit_scale(R)), "EffectiveSppLadder"), "EffectiveSppLadder")  # a flat ladder
        object.__setattr__(self, "ladder_spp", s)
        object.__setattr__(self, "ladder_rmse", R[0])

    @classmethod
    def from_images(
        cls,
        ladder_spp,
        ladder_images: Tensor | Sequence[Tensor],
        reference: Tensor,
        mask: Tensor | None = None,
        interpolation: str = "inverse_mse",
    ) -> "EffectiveSppLadder":
        """Ladder from N images of one frame: ladder_images (N, 1, C, H, W) or N × (1, C, H, W)."""
        R = ladder_rmse(ladder_images, reference, mask)
        if R.shape[0] != 1:
            raise ShapeError(
                f"EffectiveSppLadder.from_images: one frame (B = 1) expected, got B = {R.shape[0]}; "
                "use ladder_rmse + effective_spp_many for several frames"
            )
        return cls(_as_f64(ladder_spp, "ladder_spp"), R[0], interpolation)

    @property
    def fit(self) -> tuple[float, float]:
        """(a, b) of ``MSE(n) = a / n + b`` (see :func:`fit_ladder`)."""
        a, b = fit_ladder(self.ladder_spp, self.ladder_rmse)
        return float(a), float(b)

    def __call__(self, rmse_value) -> tuple[float, str]:
        """Effective spp of one RMSE: ``(spp, flag)``."""
        return effective_spp(rmse_value, self.ladder_spp, self.ladder_rmse, self.interpolation)

    def many(self, rmse_values) -> tuple[Tensor, list[str]]:
        """Effective spp of (F,) RMSEs: ``(spp (F,), flags)``."""
        return effective_spp_many(rmse_values, self.ladder_spp, self.ladder_rmse, self.interpolation)
