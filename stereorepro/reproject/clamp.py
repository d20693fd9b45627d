"""Fast-history clamping (NVIDIA NRD's RELAX): a slow, low-noise history clamped to the colour box of a fast,
responsive one, so that it cannot lag far behind a change of lighting or an edge the slow EMA smears.

:func:`fast_history_clamp` is the pure tensor op; :class:`~stereorepro.reproject.FastHistoryClamp` its module
(exportable); the settings a temporal step takes are :class:`~stereorepro.reproject.FastClamp`
(:attr:`TemporalReprojection.fast_clamp <stereorepro.TemporalReprojection.fast_clamp>`), applied by
:func:`stereorepro.accumulate.temporal_step` and the stereo driver.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .._checks import all_finite, check_floating, check_scalar, check_shape, tracing
from .._tensors import as_scalar, compute_dtype
from . import _native
from .functional import select_backend
from .view import _check_radius

__all__ = ["fast_history_clamp"]


def fast_history_clamp(color: Tensor, fast_color: Tensor, sigma=2.0, radius: int = 1, backend: str = "auto") -> Tensor:
    """Clamp a (slow) history to the colour box of a fast history's neighbourhood, per channel (NRD RELAX).

    At each pixel and channel the box is ``[μ − sigma·σ, μ + sigma·σ]``, μ and σ the mean and standard deviation
    of ``fast_color`` over the ``(2·radius + 1)²`` window around the pixel: ``σ = sqrt(max(E[x²] − μ², 0))``
    (the population deviation). At the image borders only the in-frame pixels of the window count (a 3×3
    window has 4 pixels at a corner, 6 on an edge). Non-finite ``fast_color`` values are left out of the moments
    like pixels outside the frame; where a window holds no finite value ``color`` is returned as it is. A NaN in
    ``color`` stays NaN, ``±inf`` is clamped to the box.

    With a slow history of EMA weight α (e.g. 0.1) and a fast one of a larger weight (e.g. 0.5) that share the
    same warp and restarts, the clamp bounds how far the slow one lags behind a change (a light switched on, a
    moving light's shadow) by the spread of the fast history's neighbourhood, while leaving it alone where the
    two agree within their noise. The temporal step does this itself when its module's
    :attr:`~stereorepro.TemporalReprojection.fast_clamp` is set (:func:`stereorepro.accumulate.temporal_step`,
    one warp of both histories); with your own loop, compose two :func:`~stereorepro.reproject.temporal_reproject`
    calls that share the history length and clamp where the history was kept (the example below).

    Args:
        color: (B, C, H, W) the colour to clamp (the slow history after its blend).
        fast_color: (B, C, H, W) the fast history (after its blend) whose neighbourhood gives the box.
        sigma: the box's half width in standard deviations, a finite number >= 0 or a one-element tensor
            (RELAX's default 2).
        radius: the window's radius in pixels, an int >= 0 (1: 3×3; 2: 5×5).
        backend: ``"auto"`` | ``"torch"`` | ``"native"``, the ops' one rule
            (:func:`~stereorepro.reproject.select_backend`): the native core (the same bytes) for float32 /
            float16 CPU tensors without autograd, else torch.

    Returns:
        (B, C, H, W) the clamped colour, dtype of ``color`` (float16 / bfloat16 computed in float32).
        Differentiable in ``color``, ``fast_color`` and a tensor ``sigma`` (σ = 0, a constant window, has a
        zero gradient in the variance).

    Raises:
        ShapeError: ``color`` is not 4-d or ``fast_color`` has another shape.
        ParameterTypeError: ``radius`` is not an int, or a tensor is not floating point.
        ParameterError: ``sigma`` is negative or not finite, ``radius`` is negative, or ``backend`` is unknown.
        RuntimeError: ``backend="native"`` where it cannot run (the message says why).

    Examples:
        >>> import torch
        >>> from stereorepro import fast_history_clamp
        >>> fast = torch.tensor([[[[0.9, 1.0, 1.1], [1.0, 1.0, 1.0], [1.1, 1.0, 0.9]]]])  # mean 1, std ~0.067
        >>> slow = torch.full((1, 1, 3, 3), 0.2)  # lagging behind a light switched on
        >>> round(float(fast_history_clamp(slow, fast)[0, 0, 1, 1]), 4)  # clamped to 1 - 2 * 0.0667
        0.8667
        >>> bool(torch.equal(fast_history_clamp(fast, fast, radius=1), fast))  # inside its own box: unchanged
        True

        With your own loop (one history length, two colours; ``clamp`` only where the history was kept):

        >>> from stereorepro import Blend, History, View, intrinsics_from_fov, temporal_reproject
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> plain = slow = fast = History.empty(view)
        >>> for frame in range(12):
        ...     current = torch.full((1, 3, 6, 8), 0.0 if frame < 8 else 1.0)  # the light goes on at frame 8
        ...     plain = temporal_reproject(current, view, plain, view, (0.01, 0.1), blend=Blend(alpha=0.1)).history
        ...     s = temporal_reproject(current, view, slow, view, (0.01, 0.1), blend=Blend(alpha=0.1))
        ...     f = temporal_reproject(current, view, History(fast.color, slow.length), view, (0.01, 0.1),
        ...                            blend=Blend(alpha=0.5))
        ...     slow = History(torch.where(s.valid, fast_history_clamp(s.color, f.color), s.color), s.history_len)
        ...     fast = f.history
        >>> round(float(plain.color.mean()), 4), round(float(slow.color.mean()), 4)  # lagging; clamped to the fast
        (0.352, 0.9375)
    """
    if not tracing():
        bind = check_shape(color, ["B", "C", "H", "W"], "fast_history_clamp: color")
        check_shape(fast_color, ["B", "C", "H", "W"], "fast_history_clamp: fast_color", bind)
        check_floating(color, "fast_history_clamp: color")
        check_floating(fast_color, "fast_history_clamp: fast_color")
        check_scalar(sigma, "fast_history_clamp: sigma", 0.0)
    _check_radius(radius, "fast_history_clamp")
    return _clamp_checked(color, fast_color, sigma, radius, backend)


def _box_sum(t: Tensor, radius: int) -> Tensor:
    """Sum of ``t`` (..., H, W) over the (2·radius + 1)² window around each pixel, zero outside the frame: separable,
    by shifted slices of a zero-padded copy (several times faster than ``avg_pool2d`` on CPU; exports as Pad, Slice
    and Add)."""
    H, W = t.shape[-2:]
    rows = F.pad(t, (radius, radius, 0, 0))
    s = rows[..., :, 0:W]
    for i in range(1, 2 * radius + 1):
        s = s + rows[..., :, i : i + W]
    cols = F.pad(s, (0, 0, radius, radius))
    out = cols[..., 0:H, :]
    for i in range(1, 2 * radius + 1):
        out = out + cols[..., i : i + H, :]
    return out


def _clamp_checked(color: Tensor, fast_color: Tensor, sigma, radius: int, backend: str = "auto") -> Tensor:
    """:func:`fast_history_clamp` of arguments the caller has checked, on the backend the one rule picks. In torch,
    when every fast value is finite (eager mode) the finite masks are skipped: the window counts depend on the
    border alone and every window has a value; the result is the same, byte for byte (and the native core's)."""
    if select_backend(backend, [color, fast_color], [sigma]) == "native":
        return _native.fast_history_clamp(color, fast_color, float(sigma), radius)
    wdt = compute_dtype(color, fast_color)
    x = fast_color.to(wdt)
    C, H, W = x.shape[-3:]
    zero = torch.zeros((), dtype=wdt, device=x.device)
    one = torch.ones((), dtype=wdt, device=x.device)
    traced = tracing()
    masked = traced or not all_finite(x)
    if masked:
        finite = torch.isfinite(x)
        x = torch.where(finite, x, zero)
        count = _box_sum(finite.to(wdt), radius)  # the in-frame, finite pixels of each window
    else:
        count = _box_sum(torch.ones((1, 1, H, W), dtype=wdt, device=x.device), radius)
    has = count > 0
    safe = torch.where(has, count, one)
    sums = _box_sum(torch.cat([x, x * x], 1), radius)  # both moments in one pass
    mean = sums[:, :C] / safe
    var = sums[:, C:] / safe - mean * mean
    pos = var > 0
    # no infinite gradient at var = 0. Eager on the CPU the root is taken in float64, so that a float32 one is
    # correctly rounded (torch's vectorised float32 sqrt is not) and the native core's std::sqrt gives the same bytes;
    # elsewhere (GPUs, some without float64; traced graphs) torch's own
    v = torch.where(pos, var, one)
    exact = not traced and v.device.type == "cpu" and v.dtype == torch.float32
    std = torch.where(pos, torch.sqrt(v.double()).to(wdt) if exact else torch.sqrt(v), zero)
    half = as_scalar(sigma, mean) * std
    c = color.to(wdt)
    clamped = torch.minimum(torch.maximum(c, mean - half), mean + half)
    return (torch.where(has, clamped, c) if masked else clamped).to(color.dtype)
