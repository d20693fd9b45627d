"""Where an image's error lives: shares of the squared error held by pixel regions, how concentrated it is, and a
per-region effective spp from a two-rung ladder.

Pure functions of (1, C, H, W) images and (1, 1, H, W) bool masks; ``bench/error_anatomy.py`` applies them to a
scheme's frames (which pixels decide a scheme's effective spp).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["squared_error", "error_concentration", "error_shares", "two_rung_spp", "edge_mask"]


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
