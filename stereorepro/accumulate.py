"""Accumulation over a frame sequence: the one temporal step of an eye, and the paper's combined scheme (§4.1) as a
small stateful driver, with two schemes beyond the paper (a blended left eye, alternating eyes).

:func:`temporal_step` is how every sequence in the package (this driver, the ``reproject`` command, the
examples) advances one eye's history by a frame: :func:`~stereorepro.reproject.temporal_reproject` with the
reasons, or a fresh start where there is no history yet.

Per frame, for a stereo pair, :class:`SpatiotemporalReprojection`:

1. **right eye**: the caller traces it at 1 spp; :meth:`~SpatiotemporalReprojection.right` accumulates it
   temporally (history warped from the previous right frame, EMA with warm-up);
2. **stereo R → L**: :meth:`~SpatiotemporalReprojection.left_trace_mask` backward-reprojects the accumulated right
   eye into the left eye and returns the left pixels whose taps were all discarded — the **trace-me mask**;
3. **left fill**: the caller traces only those pixels at 1 spp and passes them to
   :meth:`~SpatiotemporalReprojection.left`; with temporal accumulation on, the traced samples are blended with
   the left eye's own warped history ("we also need to temporally accumulate left-eye data in order to fill the
   discarded pixels with accumulated data").

Switching ``temporal`` or ``stereo`` off gives the paper's other two schemes: stereo only (right eye at 1 spp,
left = reprojection + traced discards) and temporal only (the right eye's accumulation).

Beyond the paper (the authors' follow-up, IEEE Access 8:133514, 2020, reports +47 % effective spp from blending
traced and stereo-reprojected data), two schemes at the same ray budget (one eye in full at
1 spp plus the other eye's stereo discards, every frame):

* **Blended left eye** (``left_mode="blend"``, :func:`blend_histories`). The paper's left eye is a *fill*: where
  the stereo reprojection keeps a pixel, the left eye shows the reprojected right history and drops its own.
  The blend keeps both at every pixel: the reprojected right history S (count n_S, the right eye's history
  length reprojected with the same taps) and the left eye's own history L warped from its previous frame
  (count n_L), as a weighted mean with weights ``w_S = ρ·h(n_S)`` and ``w_L = h(n_L)``, where ``h(n) =
  min(n, 1/α − 1)`` is the weight :func:`~stereorepro.reproject.temporal_blend`'s warm-up EMA gives a history of
  n samples against one new sample (with warm-up off the EMA gives every history the same weight, so
  ``h = 1`` for n > 0), and ``ρ = stereo_weight`` discounts the reprojected history for its resampling in the
  other eye's view (bilinear blur, view-dependent shading). The combined count is ``min(ρ·n_S + n_L,
  max_history)``. Where the stereo reprojection discards, the traced 1-spp sample is blended into L by the
  usual EMA (exactly the fill rule there). With one history empty the blend is that history alone, so with
  nothing reprojected it *is* the fill; and when S is a single fresh sample (n_S = 1, ρ = 1) the rule is
  exactly the EMA's ``a = max(1/(n_L + 1), α)``. The left eye's new state is this blend, which the next
  frame's left step warps.
* **Alternating eyes** (``alternate=True``): the right eye is traced in full on even frames and the left eye on
  odd frames (:meth:`~SpatiotemporalReprojection.fully_traced_eye`); the traced eye takes the one temporal step
  (:func:`temporal_step`) on its own history and is reprojected into the other eye, which traces only its
  discards and fills (or blends) them with its own history. Call :meth:`~SpatiotemporalReprojection.full`,
  :meth:`~SpatiotemporalReprojection.other_trace_mask` and :meth:`~SpatiotemporalReprojection.other` (the
  eye-neutral names of ``right``, ``left_trace_mask`` and ``left``) with the eyes it names.

Why the driver is a plain class and not an nn.Module: it holds tensors *between* calls (each eye's history and
G-buffer), and its three calls per frame interleave with the caller's renderer; an nn.Module forward here takes
plain tensors and keeps no state, so that it exports to ONNX. The driver's settings live in a
:class:`~stereorepro.StereoReprojection` and a :class:`~stereorepro.TemporalReprojection` (its
``stereo_module`` and ``temporal_module``), whose pure functions it calls.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import (
    STEREO_NAMES,
    TEMPORAL_NAMES,
    check_camera,
    check_floating,
    check_motion,
    check_reprojection_inputs,
    check_scalar,
    check_shape,
    tracing,
)
from ._tensors import as_scalar, compute_dtype
from .camera import Eye
from .errors import ParameterError, ParameterTypeError
from .reproject import History, Reason, StereoReprojection, TemporalReprojection, Thresholds, View, temporal_reproject
from .reproject.view import _check_footprint_weighting, _check_history_rounding
from .reproject.view import _check_position_test
from .reproject.functional import _footprint_weighted, temporal_blend, temporal_views, warp_values
from .reproject.clamp import _clamp_checked
from .reproject.functional import _blend_checked
from .reproject.view import FastClamp, _check_fast_clamp

__all__ = [
    "EyeState",
    "temporal_step",
    "warp_history",
    "blend_histories",
    "SpatiotemporalReprojection",
    "LEFT_MODES",
    "STEREO_WEIGHT",
]

#: The reprojected eye's modes: ``"fill"`` (the paper: reprojection where kept, traced samples elsewhere) and
#: ``"blend"`` (:func:`blend_histories` at every pixel).
LEFT_MODES = ("fill", "blend")

#: Default ``stereo_weight`` ρ of :func:`blend_histories`: a reprojected right history counts as ρ times its length.
#: Once both histories are saturated the reprojection's share is ρ/(1 + ρ), so the blend adds a memory pole
#: 1/(1 + ρ) to the EMA's 1 − alpha: ρ trades variance for lag; 0.5 keeps the pole (2/3) below the EMA's (0.8).
STEREO_WEIGHT = 0.5


@dataclass(frozen=True)
class EyeState:
    """One eye's accumulated frame and the G-buffer/camera it lives in.

    Attributes:
        color: (B, 3, H, W) accumulated colour.
        history_len: (B, 1, H, W) float sample count.
        depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).
        fast_color: optional (B, 3, H, W) fast history (:class:`~stereorepro.reproject.FastClamp`; its length is
            ``history_len``); None without one (a step with the clamp on then starts it from ``color``).

    Examples:
        >>> import torch
        >>> from stereorepro.accumulate import EyeState
        >>> z = torch.zeros(1, 1, 2, 2)
        >>> state = EyeState(torch.ones(1, 3, 2, 2), z + 4, z + 2, torch.zeros(1, 3, 2, 2), torch.eye(3)[None],
        ...                  torch.eye(4)[None])
        >>> float(state.history.length.max()), tuple(state.view.depth.shape)
        (4.0, (1, 1, 2, 2))
    """

    color: Tensor
    history_len: Tensor
    depth: Tensor
    normal: Tensor
    K: Tensor
    cam_from_world: Tensor
    fast_color: Tensor | None = None

    @property
    def view(self) -> View:
        """The G-buffer and camera the accumulated frame lives in."""
        return View.unchecked(self.depth, self.normal, self.K, self.cam_from_world)

    @property
    def history(self) -> History:
        """The accumulated colour and sample count."""
        return History(self.color, self.history_len)


def temporal_step(
    module: TemporalReprojection,
    state: EyeState | None,
    color: Tensor,
    depth: Tensor,
    normal: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
) -> tuple[EyeState, Tensor, Tensor]:
    """Advance one eye's accumulation by a frame.

    Args:
        module: the settings (thresholds, alpha, warm-up, cap, sampling, soft, backend); its parameters carry
            gradients when it is soft. With its ``fast_clamp`` (a :class:`~stereorepro.reproject.FastClamp`) the
            state also carries a fast history (``EyeState.fast_color``, warped with the slow one) and the new
            colour is clamped to the fast history's box where the history was kept.
        state: the eye's previous frame, or None for the first frame of an accumulation.
        color: (B, 3, H, W) this frame's samples; depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3);
            cam_from_world: (B, 4, 4).
        motion, motion_world: optional (B, 2, H, W) / (B, 3, H, W) motion to the previous frame (see
            :func:`~stereorepro.reproject.temporal_reproject`); ignored on the first frame.

    Returns:
        state: the new :class:`EyeState` (accumulated colour and sample count with this frame's G-buffer).
        valid: (B, 1, H, W) bool, where the history was kept (all False on the first frame).
        reason: (B, 1, H, W) uint8 :class:`~stereorepro.Reason` (``NO_HISTORY`` everywhere on the first frame).

    Examples:
        >>> import torch
        >>> from stereorepro import TemporalReprojection, intrinsics_from_fov
        >>> from stereorepro.accumulate import temporal_step
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> camera = (depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> module = TemporalReprojection(0.03, 0.2)
        >>> state, valid, _ = temporal_step(module, None, torch.ones(1, 3, 6, 8), *camera)  # first frame
        >>> bool(valid.any()), float(state.history_len.max())
        (False, 1.0)
        >>> state, valid, _ = temporal_step(module, state, torch.zeros(1, 3, 6, 8), *camera)  # same camera
        >>> bool(valid.all()), float(state.history_len.max()), round(float(state.color.mean()), 4)
        (True, 2.0, 0.5)
    """
    return _temporal_step(module, state, color, depth, normal, K, cam_from_world, motion, motion_world, True)


def _temporal_step(
    module, state, color, depth, normal, K, cam_from_world, motion, motion_world, clamp: bool
) -> tuple[EyeState, Tensor, Tensor]:
    """:func:`temporal_step`; with the module's ``fast_clamp`` and ``clamp`` False the slow colour is returned
    unclamped (the driver's fill clamps it to the fast history it assembles with the stereo reprojection)."""
    if state is None:
        n = torch.ones_like(depth, dtype=torch.float32)
        valid = torch.zeros_like(depth, dtype=torch.bool)
        reason = torch.full_like(depth, int(Reason.NO_HISTORY), dtype=torch.uint8)
        fast = color if module.fast_clamp is not None else None
        return EyeState(color, n, depth, normal, K, cam_from_world, fast), valid, reason
    m = module
    view, prev_view = temporal_views(
        color,
        (depth, normal, K, cam_from_world),
        state.history,
        (state.depth, state.normal, state.K, state.cam_from_world),
        (motion, motion_world),
    )
    if m.fast_clamp is not None:
        out, n, fast, valid, reason = _fast_clamped_step(m, state, color, view, prev_view, clamp)
        return EyeState(out, n, depth, normal, K, cam_from_world, fast), valid, reason
    out, n, valid, reason = temporal_reproject(
        color,
        view,
        state.history,
        prev_view,
        m.thresholds,
        blend=m.blend,
        sampling=m.sampling,
        soft=m.soft,
        backend=m.backend,
        return_reason=True,
    )
    return EyeState(out, n, depth, normal, K, cam_from_world), valid, reason


def _warp_state(m: TemporalReprojection, state: EyeState, view: View, fast: bool):
    """One warp of ``state``'s colour and length (and with ``fast`` its fast colour, or its colour where it has
    none) into ``view``: (color, length (footprint-weighted when the module says so), fast color or None, valid,
    reason, den)."""
    C = state.color.shape[1]
    parts = [state.color, state.history_len]
    if fast and state.fast_color is not None and not tracing():
        check_shape(state.fast_color, ["B", "C", "H", "W"], "EyeState.fast_color", dict(zip("BCHW", state.color.shape)))
        check_floating(state.fast_color, "EyeState.fast_color")
    if fast:
        parts.append(state.color if state.fast_color is None else state.fast_color)
    work = compute_dtype(*parts)
    values = torch.cat([t.to(work) for t in parts], 1)  # the sample count (and the fast colour) ride along
    warped, valid, reason, den = warp_values(values, state.view, view, m.thresholds, m.sampling, m.soft, m.backend)
    length = _footprint_weighted(warped[:, C : C + 1], den) if m.footprint_weighting else warped[:, C : C + 1]
    return warped[:, :C], length, warped[:, C + 1 :] if fast else None, valid, reason, den


def _fast_clamped_step(m: TemporalReprojection, state: EyeState, color: Tensor, view: View, prev_view: View, clamp):
    """The temporal step with a fast history (``m.fast_clamp``): both histories in one warp, each blended with its
    own alpha on the shared length (restarted together), the slow one clamped where kept when ``clamp``.
    (color, length, fast color, valid, reason)."""
    slow_w, n_w, fast_w, valid, reason, den = _warp_state(m, state, view, True)
    confidence = den if m.soft else valid
    blend, fc = m.blend, m.fast_clamp
    slow, n = _blend_checked(color, slow_w, n_w, confidence, *blend[:4])
    fast, _ = _blend_checked(color, fast_w, n_w, confidence, fc.alpha, blend.warmup, blend.max_history)
    if clamp:
        slow = torch.where(valid, _clamp_checked(slow, fast, fc.sigma, fc.radius, m.backend), slow)
    return slow, n, fast, valid, reason


def warp_history(
    module: TemporalReprojection,
    state: EyeState,
    depth: Tensor,
    normal: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    *,
    return_fast: bool = False,
) -> tuple[Tensor, ...]:
    """The warp of :func:`temporal_step` without its blend: an eye's history moved into this frame.

    The same warp (taps, tests, backend rule) as :func:`~stereorepro.reproject.temporal_reproject`, so blending
    its outputs with :func:`~stereorepro.reproject.temporal_blend` gives :func:`temporal_step`'s result bit for bit.

    Args:
        module: the temporal settings (thresholds, sampling, soft, temperature, backend, footprint_weighting).
        state: the eye's previous frame.
        depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4) — this frame.
        motion, motion_world: optional (B, 2, H, W) / (B, 3, H, W) motion to the previous frame.
        return_fast: also warp the fast history (``state.fast_color``, or ``state.color`` where the state has
            none) in the same warp, and return it fifth.

    Returns:
        color: (B, 3, H, W) warped history colour (0 where discarded).
        history_len: (B, 1, H, W) its warped sample count (0 where discarded), scaled by the footprint quality
            when the module's ``footprint_weighting`` is on.
        valid: (B, 1, H, W) bool, where the history was kept.
        reason: (B, 1, H, W) uint8 :class:`~stereorepro.Reason`.
        fast_color: (B, 3, H, W) the warped fast history, only with ``return_fast``.

    Examples:
        >>> import torch
        >>> from stereorepro import TemporalReprojection, intrinsics_from_fov
        >>> from stereorepro.accumulate import EyeState, warp_history
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> camera = (depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> state = EyeState(torch.full((1, 3, 6, 8), 0.5), torch.full((1, 1, 6, 8), 3.0), *camera)
        >>> color, length, valid, reason = warp_history(TemporalReprojection(0.03, 0.2), state, *camera)  # camera still
        >>> float(color.max()), float(length.max()), bool(valid.all()), int(reason.max())
        (0.5, 3.0, True, 0)
    """
    check_reprojection_inputs(
        state.color,
        state.depth,
        state.normal,
        state.K,
        state.cam_from_world,
        depth,
        normal,
        K,
        cam_from_world,
        TEMPORAL_NAMES,
    )
    if not tracing():
        check_shape(
            state.history_len,
            ["B", "1", "H", "W"],
            "history_len",
            {"B": state.color.shape[0], "H": state.color.shape[-2], "W": state.color.shape[-1]},
        )
        check_floating(state.history_len, "history_len")
        check_motion(motion, motion_world, depth, "motion", "motion_world")
    view = View.unchecked(depth, normal, K, cam_from_world, motion, motion_world)
    color, length, fast, valid, reason, _ = _warp_state(module, state, view, return_fast)
    return (color, length, valid, reason, fast) if return_fast else (color, length, valid, reason)


def _ema_weight(n: Tensor, a: Tensor, warmup: bool) -> Tensor:
    """The weight :func:`~stereorepro.reproject.temporal_blend` gives a history of ``n`` samples against one new
    sample: ``(1 − a)/a`` with ``a = max(1/(n + 1), alpha)``, i.e. ``min(n, 1/alpha − 1)`` with warm-up; without
    warm-up every non-empty history gets the same ``1/alpha − 1``, written 1 here (only ratios of weights are
    used)."""
    if warmup:
        return torch.minimum(n, (1.0 - a) / a)  # alpha = 0: 1/0 = inf, the running mean
    one, zero = torch.ones((), dtype=n.dtype, device=n.device), torch.zeros((), dtype=n.dtype, device=n.device)
    return torch.where((n > 0) & (a < 1.0), one, zero)


def blend_histories(
    traced_color: Tensor,
    stereo_color: Tensor,
    stereo_len: Tensor,
    stereo_valid: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    history_valid: Tensor,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
    stereo_weight=STEREO_WEIGHT,
    history_rounding: str = "none",
) -> tuple[Tensor, Tensor]:
    """The blended left eye: the stereo-reprojected history, the eye's own warped history and the traced samples.

    At every pixel the two histories are combined by a weighted mean of their sample counts, as the warm-up EMA
    (:func:`~stereorepro.reproject.temporal_blend`) weighs a history against a new sample:

    * ``h(n) = min(n, 1/alpha − 1)`` (``warmup``; the EMA gives a history of n samples the weight ``(1 − a)/a``
      with ``a = max(1/(n + 1), alpha)``: its sample count until the alpha floor takes over). Without warm-up
      the EMA weighs every non-empty history alike: ``h(n) = 1`` for n > 0. The cap keeps two histories that
      share samples (the left history was largely built from the right one) from out-voting each other by
      long counts, and bounds the blend's memory: saturated, S's share is ρ/(1 + ρ) every frame.
    * ``w_S = stereo_weight · h(n_S)`` where ``stereo_valid``, ``w_L = h(n_L)`` where ``history_valid`` (0
      elsewhere; a negative or NaN count is 0). ``stereo_weight`` (ρ) discounts the reprojected history: it was
      resampled from the other eye's view (bilinear blur, view-dependent shading).
    * Both weights > 0: ``H = L + w_S/(w_S + w_L)·(S − L)``, count ``min(ρ·n_S + n_L, max_history)``. Only S
      (or both weights 0 where S is kept, e.g. ``alpha = 1``: no history is trusted, the fill): ``H = S``, count
      ``min(ρ·n_S, max_history)``. Only L: ``H = L``, count ``n_L``. Neither: 0, count 0.
    * Where the stereo reprojection discards (``~stereo_valid``: the pixels the caller traced) the 1-spp sample
      is blended into H by :func:`~stereorepro.reproject.temporal_blend` (S is absent there, so this is the
      fill rule exactly). Elsewhere the output is H.

    Limits: nothing reprojected (``stereo_valid`` all False) gives the fill (``temporal_blend`` of the traced
    samples into L) bit for bit; no own history gives the fill's colours (counts ρ·n_S); and when S is one fresh
    sample (n_S = 1, ρ = 1) the weight of S is ``1/(1 + min(n_L, 1/alpha − 1)) = max(1/(n_L + 1), alpha)``, the
    EMA's.

    Args:
        traced_color: (B, C, H, W) 1-spp samples; read only where ``stereo_valid`` is False.
        stereo_color: (B, C, H, W) the other eye's accumulated colour reprojected into this eye (S).
        stereo_len: (B, 1, H, W) its history length reprojected with the same taps (n_S).
        stereo_valid: (B, 1, H, W) bool, where the stereo reprojection kept the pixel.
        history_color: (B, C, H, W) this eye's own history warped into this frame (L).
        history_len: (B, 1, H, W) its sample count (n_L).
        history_valid: (B, 1, H, W) bool, where the own history was kept.
        alpha, warmup, max_history: the EMA's settings (see :func:`~stereorepro.reproject.temporal_blend`).
        stereo_weight: ρ >= 0, a finite number or one-element tensor (learnable).
        history_rounding: ``"none"`` or ``"bmfr"``: integer counts, as BMFR stores them: the traced pixels'
            through :func:`~stereorepro.reproject.temporal_blend`'s ``"bmfr"`` rule, the kept pixels' count
            rounded half to even (the weights use the unrounded counts).

    Returns:
        color: (B, C, H, W), dtype of ``traced_color``; finite wherever the inputs it selects are.
        history_len: (B, 1, H, W) float, the new sample count.

    Differentiable in the colours, counts, ``alpha`` and ``stereo_weight`` (``min`` has a kink at
    ``n = 1/alpha − 1``).

    Examples:
        >>> import torch
        >>> from stereorepro.accumulate import blend_histories
        >>> ones = torch.ones(1, 1, 1, 2); yes, no = ones > 0, ones < 0
        >>> traced, stereo, own = torch.zeros(1, 3, 1, 2), torch.ones(1, 3, 1, 2), torch.zeros(1, 3, 1, 2)
        >>> color, length = blend_histories(traced, stereo, 2 * ones, yes, own, 2 * ones, no, stereo_weight=1.0)
        >>> color[0, 0].tolist(), length[0, 0].tolist()  # only the stereo history is valid: taken as it is
        ([[1.0, 1.0]], [[2.0, 2.0]])
        >>> color, length = blend_histories(traced, stereo, 2 * ones, yes, own, 2 * ones, yes, stereo_weight=1.0)
        >>> color[0, 0].tolist(), length[0, 0].tolist()  # both valid, equal counts: their mean, counts added
        ([[0.5, 0.5]], [[4.0, 4.0]])
    """
    if not tracing():
        bind = check_shape(traced_color, ["B", "C", "H", "W"], "traced_color")
        check_shape(stereo_color, ["B", "C", "H", "W"], "stereo_color", bind)
        check_shape(history_color, ["B", "C", "H", "W"], "history_color", bind)
        for name, t in (
            ("stereo_len", stereo_len),
            ("history_len", history_len),
            ("stereo_valid", stereo_valid),
            ("history_valid", history_valid),
        ):
            check_shape(t, ["B", "1", "H", "W"], name, bind)
        for name, t in (
            ("traced_color", traced_color),
            ("stereo_color", stereo_color),
            ("history_color", history_color),
            ("stereo_len", stereo_len),
            ("history_len", history_len),
        ):
            check_floating(t, name)
        for name, t in (("stereo_valid", stereo_valid), ("history_valid", history_valid)):
            if t.dtype != torch.bool:
                raise ParameterTypeError(f"{name}: expected a bool mask, got dtype {t.dtype}")
        check_scalar(alpha, "alpha")
        check_scalar(max_history, "max_history", 1.0, allow_inf=True)
        check_scalar(stereo_weight, "stereo_weight", 0.0)
    _check_history_rounding(history_rounding, "blend_histories")
    wdt = compute_dtype(traced_color, stereo_color, history_color, stereo_len, history_len)
    dev = traced_color.device
    zero = torch.zeros((), dtype=wdt, device=dev)
    S, L = stereo_color.to(wdt), history_color.to(wdt)
    n_s, n_l = stereo_len.to(wdt), history_len.to(wdt)
    n_s = torch.where(n_s > 0, n_s, zero)  # negative and NaN: no samples (as temporal_blend reads a count)
    n_l = torch.where(n_l > 0, n_l, zero)
    a = as_scalar(alpha, n_s).clamp(0.0, 1.0)
    rho = as_scalar(stereo_weight, n_s)
    cap = as_scalar(max_history, n_s)
    w_s = torch.where(stereo_valid, rho * _ema_weight(n_s, a, warmup), zero)
    w_l = torch.where(history_valid, _ema_weight(n_l, a, warmup), zero)
    both = (w_s > 0) & (w_l > 0)
    use_s = stereo_valid & ~(w_l > 0)  # S alone, or no weight on either where S is kept: the fill's choice
    use_l = ~both & ~use_s & history_valid
    # the mix only where both are used, on masked values so that nothing non-finite elsewhere reaches a gradient
    f = w_s / torch.where(both, w_s + w_l, torch.ones((), dtype=wdt, device=dev))
    s_m, l_m = torch.where(both, S, zero), torch.where(both, L, zero)
    mixed = l_m + f * (s_m - l_m)
    hist = torch.where(both, mixed, torch.where(use_s, S, torch.where(use_l, L, zero)))
    n_hist = torch.where(
        both,
        torch.minimum(rho * n_s + n_l, cap),
        torch.where(use_s, torch.minimum(rho * n_s, cap), torch.where(use_l, n_l, zero)),
    )
    # the traced samples where the stereo reprojection discarded: the EMA into the own history (the fill rule)
    trace = ~stereo_valid
    cur = torch.where(trace, traced_color, torch.zeros((), dtype=traced_color.dtype, device=dev))
    filled, n_filled = temporal_blend(cur, hist, n_hist, history_valid, alpha, warmup, max_history, history_rounding)
    out = torch.where(stereo_valid, hist.to(filled.dtype), filled)
    n = torch.where(stereo_valid, _stored_count(n_hist, history_rounding).to(n_filled.dtype), n_filled)
    return out, n


def _stored_count(n: Tensor, history_rounding: str) -> Tensor:
    """A count an eye keeps without adding a sample (a reprojected or blended one): ``n``, or with ``"bmfr"``
    ``n`` rounded half to even (BMFR's integer storage)."""
    return torch.round(n) if history_rounding == "bmfr" else n


class SpatiotemporalReprojection:
    """Stateful driver of stereo + temporal reprojection (paper §4.1), and of the blended and alternating schemes.

    Args:
        position_threshold: scene-scale limit of |P_src − P_dst| (scene units).
        normal_threshold: limit of |N_src − N_dst| (unit normals).
        alpha: minimum EMA weight of a new frame (paper: 0.2).
        warmup: running mean until the weight reaches ``alpha`` (BMFR).
        max_history: cap of the sample count.
        sampling: ``"bilinear"`` (paper), ``"nearest"`` or ``"catmull_rom"`` (history and stereo reads; see
            :func:`~stereorepro.reproject.backward_reproject`).
        stereo: reproject the right eye into the left (else the left eye is traced in full).
        temporal: accumulate over time (else every frame starts afresh).
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` for the warps (see
            :func:`~stereorepro.reproject.select_backend`).
        left_mode: the reprojected eye's rule: ``"fill"`` (the paper: the reprojection where kept, its own
            accumulated traced samples elsewhere) or ``"blend"`` (:func:`blend_histories` at every pixel: the
            reprojection and its own warped history, weighted by sample counts; the hard keep masks, also when the
            temporal module is soft). With ``alternate`` it applies to whichever eye is reprojected.
        stereo_weight: ρ of :func:`blend_histories` (``"blend"`` only).
        alternate: trace the right eye in full on even frames and the left eye on odd frames (see
            :meth:`fully_traced_eye`); needs ``stereo``.

    The stored history lengths are floats; set :attr:`history_rounding` to ``"bmfr"`` after construction for
    BMFR's integer counts (every temporal step, the reprojected eye's kept stereo counts and the blend's).

    Example (one frame; ``trace`` is your renderer)::

        st = SpatiotemporalReprojection(0.03, 0.2)
        right = st.right(trace_right(), depth_r, normal_r, K_r, T_r)
        mask = st.left_trace_mask(depth_l, normal_l, K_l, T_l)      # (B, 1, H, W) bool: trace these
        left = st.left(trace_left(pixel_mask=mask))

    With ``alternate=True`` ask which eye to trace in full, and use the eye-neutral calls::

        full_eye = st.fully_traced_eye()                             # Eye.RIGHT on even frames, Eye.LEFT on odd
        other_eye = full_eye.other
        out[full_eye] = st.full(trace(full_eye), *gbuffer[full_eye])
        mask = st.other_trace_mask(*gbuffer[other_eye])
        out[other_eye] = st.other(trace(other_eye, pixel_mask=mask))

    Examples:
        >>> import torch
        >>> from stereorepro import SpatiotemporalReprojection, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 6, 8), 3.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> K, right_pose = intrinsics_from_fov(90.0, 8, 6), torch.eye(4)[None]
        >>> left_pose = right_pose.clone(); left_pose[0, 0, 3] = 1.0  # 1 pixel of disparity at depth 3
        >>> st = SpatiotemporalReprojection(0.03, 0.2)
        >>> right = st.right(torch.ones(1, 3, 6, 8), depth, normal, K, right_pose)  # traced in full
        >>> mask = st.left_trace_mask(depth, normal, K, left_pose)  # what the right eye cannot give
        >>> left = st.left(torch.zeros(1, 3, 6, 8))  # traced where mask (zeros here), reprojected elsewhere
        >>> tuple(left.shape), int(mask.sum()), float(left.sum())
        ((1, 3, 6, 8), 6, 126.0)
    """

    def __init__(
        self,
        position_threshold: float,
        normal_threshold: float,
        alpha: float = 0.2,
        warmup: bool = True,
        max_history: float = 255.0,
        sampling: str = "bilinear",
        stereo: bool = True,
        temporal: bool = True,
        backend: str = "auto",
        left_mode: str = "fill",
        stereo_weight: float = STEREO_WEIGHT,
        alternate: bool = False,
    ):
        if left_mode not in LEFT_MODES:
            raise ParameterError(f"left_mode must be one of {LEFT_MODES}, got {left_mode!r}")
        check_scalar(stereo_weight, "stereo_weight", 0.0)
        if alternate and not stereo:
            raise ParameterError("alternate=True reprojects the fully traced eye into the other: it needs stereo=True")
        self.stereo_module = StereoReprojection(position_threshold, normal_threshold, sampling, backend=backend)
        self.temporal_module = TemporalReprojection(
            position_threshold, normal_threshold, alpha, warmup, max_history, sampling, backend=backend
        )
        self.backend = backend
        self.stereo = bool(stereo)
        self.temporal = bool(temporal)
        self.left_mode = left_mode
        self.stereo_weight = stereo_weight
        self.alternate = bool(alternate)
        self.reset()

    @property
    def history_rounding(self) -> str:
        """How the eyes store their history lengths: ``"none"`` (floats, the default) or ``"bmfr"`` (BMFR's
        integer counts: :func:`~stereorepro.reproject.temporal_blend`'s rule in every temporal step, counts kept
        without a new sample rounded half to even). The temporal module's setting; set it before the first frame.

        Examples:
            >>> from stereorepro import SpatiotemporalReprojection
            >>> st = SpatiotemporalReprojection(0.03, 0.2)
            >>> st.history_rounding = "bmfr"
            >>> st.history_rounding, st.temporal_module.history_rounding
            ('bmfr', 'bmfr')
        """
        return self.temporal_module.history_rounding

    @history_rounding.setter
    def history_rounding(self, value: str) -> None:
        _check_history_rounding(value, "SpatiotemporalReprojection")
        self.temporal_module.history_rounding = value

    @property
    def footprint_weighting(self) -> bool:
        """Whether every temporal step scales the warped history length by the footprint quality (NVIDIA NRD's
        rule, see :func:`~stereorepro.reproject.temporal_reproject`; the blended scheme's own history too). The
        temporal module's setting; set it before the first frame.

        Examples:
            >>> from stereorepro import SpatiotemporalReprojection
            >>> st = SpatiotemporalReprojection(0.03, 0.2)
            >>> st.footprint_weighting = True
            >>> st.footprint_weighting, st.temporal_module.footprint_weighting
            (True, True)
        """
        return self.temporal_module.footprint_weighting

    @footprint_weighting.setter
    def footprint_weighting(self, value: bool) -> None:
        _check_footprint_weighting(value, "SpatiotemporalReprojection")
        self.temporal_module.footprint_weighting = value

    @property
    def position_test(self) -> str:
        """What the position threshold bounds in every warp (the stereo step and the temporal steps):
        ``"distance"`` (default; scene units) or ``"plane"`` (the distance to the destination's tangent plane
        relative to view depth, slope-scaled; see :class:`~stereorepro.reproject.Thresholds`), the threshold then
        a fraction of view depth. The stereo and temporal modules' setting; set it before the first frame.

        Examples:
            >>> from stereorepro import SpatiotemporalReprojection
            >>> st = SpatiotemporalReprojection(0.01, 0.2)
            >>> st.position_test = "plane"
            >>> st.position_test, st.stereo_module.position_test, st.temporal_module.position_test
            ('plane', 'plane', 'plane')
        """
        return self.temporal_module.position_test

    @position_test.setter
    def position_test(self, value: str) -> None:
        _check_position_test(value, "SpatiotemporalReprojection")
        self.stereo_module.position_test = value
        self.temporal_module.position_test = value

    @property
    def fast_clamp(self) -> FastClamp | None:
        """``None`` (default) or a :class:`~stereorepro.reproject.FastClamp`: every eye keeps a fast history
        beside its slow one, and the slow one is clamped to the fast one's colour box (NRD RELAX) where it was
        kept. Where: the fully traced eye's temporal step (whole frame); the reprojected eye in ``"fill"`` at its
        traced pixels that kept their own history, against the box of its whole fast frame (the stereo
        reprojection of the fully traced eye's fast history where the stereo step keeps, its own fast step
        elsewhere); the reprojected pixels show the fully traced eye's history, clamped in that eye. In
        ``"blend"`` the fast histories are blended like the slow ones (:func:`blend_histories` with the fast
        ``alpha``) and the blended slow history is clamped to the blended fast one's box wherever a history (the
        stereo one or its own) was kept. Without ``temporal`` nothing is accumulated and nothing clamped. The
        temporal module's setting; set it before the first frame.

        Examples:
            >>> from stereorepro import FastClamp, SpatiotemporalReprojection
            >>> st = SpatiotemporalReprojection(0.03, 0.2)
            >>> st.fast_clamp = FastClamp(alpha=0.5)
            >>> st.fast_clamp == st.temporal_module.fast_clamp
            True
        """
        return self.temporal_module.fast_clamp

    @fast_clamp.setter
    def fast_clamp(self, value: FastClamp | None) -> None:
        _check_fast_clamp(value, "SpatiotemporalReprojection")
        self.temporal_module.fast_clamp = value

    def _fast_on(self) -> bool:
        """Whether the eyes keep fast histories (a fast clamp set and temporal accumulation on)."""
        return self.temporal and self.temporal_module.fast_clamp is not None

    def reset(self) -> None:
        """Forget all history (e.g. at a camera cut); the next frame is frame 0 (right eye in full)."""
        self.right_state: EyeState | None = None
        self.left_state: EyeState | None = None
        #: Frames completed (:meth:`other` / :meth:`left` calls) since the last reset.
        self.frame_index = 0
        self._frame_eye: Eye | None = None  # the eye full() accumulated last
        self._left_gbuffer: tuple | None = None
        self._stereo_out: tuple[Tensor, Tensor] | None = None
        self._stereo_fast: Tensor | None = None
        #: (B, 1, H, W) bool: where the fully traced eye kept its history this frame (None on its first frame).
        self.full_valid: Tensor | None = None
        #: (B, 1, H, W) uint8 :class:`~stereorepro.Reason` of the fully traced eye's temporal discards.
        self.full_reason: Tensor | None = None
        #: ``full_valid`` / ``full_reason`` when the right eye is the fully traced one (always, unless alternate).
        self.right_valid: Tensor | None = None
        self.right_reason: Tensor | None = None
        #: (B, 1, H, W) bool / uint8: the stereo reprojection's kept mask and discard reasons, this frame.
        self.stereo_valid: Tensor | None = None
        self.stereo_reason: Tensor | None = None
        #: (B, 1, H, W) bool: where the reprojected eye kept its own history (fill: at its traced pixels; blend:
        #: at every pixel); None without one.
        self.other_valid: Tensor | None = None
        #: ``other_valid`` when the left eye is the reprojected one (always, unless alternate).
        self.left_valid: Tensor | None = None

    def fully_traced_eye(self) -> Eye:
        """:attr:`Eye.RIGHT <stereorepro.camera.Eye>` or ``Eye.LEFT`` (equal to ``"right"`` / ``"left"``): the eye
        to trace in full at 1 spp for the frame in progress (always the right eye unless ``alternate``, then the
        left on odd frames). The other eye (``.other``) traces only the pixels of :meth:`other_trace_mask`."""
        return Eye.LEFT if self.alternate and self.frame_index % 2 == 1 else Eye.RIGHT

    def _accumulate(
        self,
        state: EyeState | None,
        color,
        depth,
        normal,
        K,
        cam_from_world,
        motion=None,
        motion_world=None,
        clamp: bool = True,
    ):
        """Temporal step of one eye: (color, history_len, valid, reason, fast color); valid/reason None without
        history, the fast colour None without a fast clamp (the slow colour unclamped unless ``clamp``)."""
        if not self.temporal or state is None:
            fast = color if self._fast_on() else None
            return color, torch.ones_like(depth, dtype=torch.float32), None, None, fast
        new, valid, reason = _temporal_step(
            self.temporal_module, state, color, depth, normal, K, cam_from_world, motion, motion_world, clamp
        )
        return new.color, new.history_len, valid, reason, new.fast_color

    def _expect(self, call: str, full_eye: str) -> None:
        if self.fully_traced_eye() != full_eye:
            raise RuntimeError(
                f"{call}(): frame {self.frame_index} traces the {self.fully_traced_eye()} eye in full "
                "(alternate=True); call full(), other_trace_mask() and other() with the eyes "
                "fully_traced_eye() names"
            )

    def full(
        self,
        color: Tensor,
        depth: Tensor,
        normal: Tensor,
        K: Tensor,
        cam_from_world: Tensor,
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> Tensor:
        """Accumulate this frame's fully traced eye (:meth:`fully_traced_eye`; :meth:`right` outside alternate
        mode).

        Args:
            color: (B, 3, H, W) 1-spp radiance of that eye.
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).
            motion, motion_world: optional motion to the previous frame for the temporal step (moving objects;
                :func:`~stereorepro.reproject.temporal_reproject`). The stereo step uses the cameras.

        Returns:
            (B, 3, H, W) that eye's output for this frame.
        """
        bind = check_shape(color, ["B", "3", "H", "W"], "color")
        check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
        check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
        eye = self.fully_traced_eye()
        check_camera(K, cam_from_world, eye, {"B": bind.get("B")} if "B" in bind else None)
        check_motion(motion, motion_world, depth)  # on every frame: the first one does not read it
        out, n, valid, reason, fast = self._accumulate(
            getattr(self, f"{eye}_state"), color, depth, normal, K, cam_from_world, motion, motion_world
        )
        self.full_valid, self.full_reason = valid, reason
        self.right_valid, self.right_reason = (valid, reason) if eye == "right" else (None, None)
        setattr(self, f"{eye}_state", EyeState(out, n, depth, normal, K, cam_from_world, fast))
        self._frame_eye = eye
        # a new frame: the other eye must run other_trace_mask() again before other()
        self._stereo_out = None
        self._stereo_fast = None
        self._left_gbuffer = None
        self.stereo_valid = self.stereo_reason = None
        return out

    def right(
        self,
        color: Tensor,
        depth: Tensor,
        normal: Tensor,
        K: Tensor,
        cam_from_world: Tensor,
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> Tensor:
        """Accumulate this frame's right eye: :meth:`full` when the right eye is the fully traced one (always,
        unless ``alternate``; RuntimeError on the frames that trace the left eye in full).

        Args:
            color: (B, 3, H, W) 1-spp radiance of the right eye.
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).
            motion, motion_world: optional motion to the previous frame for the temporal step (moving objects;
                :func:`~stereorepro.reproject.temporal_reproject`). The stereo step uses the cameras.

        Returns:
            (B, 3, H, W) the right eye's output for this frame.
        """
        self._expect("right", "right")
        return self.full(color, depth, normal, K, cam_from_world, motion, motion_world)

    def other_trace_mask(
        self,
        depth: Tensor,
        normal: Tensor,
        K: Tensor,
        cam_from_world: Tensor,
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> Tensor:
        """Reproject the fully traced eye into the other and return the other eye's pixels that must be traced.

        Args:
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4) — the other eye's
                G-buffer.
            motion, motion_world: optional motion of the other eye to its previous frame, for its temporal step
                in :meth:`other`.

        Returns:
            (B, 1, H, W) bool trace-me mask (all True when ``stereo`` is off).
        """
        src_eye = self.fully_traced_eye()
        if self._frame_eye != src_eye or getattr(self, f"{src_eye}_state") is None:
            raise RuntimeError(
                f"the trace mask of the reprojected eye (left_trace_mask() / other_trace_mask()) "
                f"needs the fully traced eye ({'right()' if src_eye == 'right' else 'full()'}) "
                "to be called first for this frame"
            )
        if not tracing():
            check_shape(depth, ["B", "1", "H", "W"], "depth")
            check_motion(motion, motion_world, depth)  # before other() reads it (it does not on the first frame)
        self._left_gbuffer = (depth, normal, K, cam_from_world, motion, motion_world)
        if not self.stereo:
            self.stereo_valid = torch.zeros_like(depth, dtype=torch.bool)
            self.stereo_reason = None
            return ~self.stereo_valid
        r, m = getattr(self, f"{src_eye}_state"), self.stereo_module
        work = compute_dtype(r.color, r.history_len)
        values = torch.cat([r.color.to(work), r.history_len.to(work)], 1)  # the sample count rides along
        fast = r.fast_color if self._fast_on() and r.fast_color is not None else None
        if fast is not None:  # the fast history rides along too
            values = torch.cat([values, fast.to(work)], 1)
        check_reprojection_inputs(
            values,
            r.depth,
            r.normal,
            r.K,
            r.cam_from_world,
            depth,
            normal,
            K,
            cam_from_world,
            dict(STEREO_NAMES, src_values=f"{src_eye} history"),
        )
        dst = View.unchecked(depth, normal, K, cam_from_world)
        hard = Thresholds(m.position_threshold, m.normal_threshold, position_test=m.position_test)  # hard tests
        warped, valid, reason, _ = warp_values(
            values, r.view, dst, hard, m.sampling, backend=m.backend, confidence=False
        )
        self._stereo_out = (warped[:, :3], warped[:, 3:4])
        self._stereo_fast = warped[:, 4:] if fast is not None else None  # the fast history reprojected with it
        self.stereo_valid, self.stereo_reason = valid, reason
        return ~valid

    def left_trace_mask(
        self,
        depth: Tensor,
        normal: Tensor,
        K: Tensor,
        cam_from_world: Tensor,
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> Tensor:
        """Reproject the right eye into the left and return the pixels that must be traced (:meth:`other_trace_mask`
        when the left eye is the reprojected one: always, unless ``alternate``).

        Args:
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4) — the left G-buffer.
            motion, motion_world: optional motion of the left eye to its previous frame, for its temporal step
                in :meth:`left`.

        Returns:
            (B, 1, H, W) bool trace-me mask (all True when ``stereo`` is off).
        """
        self._expect("left_trace_mask", "right")
        return self.other_trace_mask(depth, normal, K, cam_from_world, motion, motion_world)

    def other(self, traced_color: Tensor) -> Tensor:
        """Complete the reprojected eye from its traced discarded pixels (``left_mode``: fill or blend) and end
        the frame.

        Args:
            traced_color: (B, 3, H, W) 1-spp radiance; only pixels of the trace-me mask are read.

        Returns:
            (B, 3, H, W) the reprojected eye's output for this frame.
        """
        if self._left_gbuffer is None:
            raise RuntimeError(
                "left() / other() needs left_trace_mask() / other_trace_mask() to be called first for this frame"
            )
        depth, normal, K, cam_from_world, motion, motion_world = self._left_gbuffer
        check_shape(
            traced_color,
            ["B", "3", "H", "W"],
            "traced_color",
            {"B": depth.shape[0], "H": depth.shape[-2], "W": depth.shape[-1]},
        )
        eye = self._frame_eye.other
        state = getattr(self, f"{eye}_state")
        fast = None
        if self.left_mode == "blend" and self._stereo_out is not None:
            (s_color, s_len), s_fast = self._stereo_out, self._stereo_fast
            hist_fast = torch.zeros_like(s_color)
            if self.temporal and state is not None:
                hist, hist_len, valid, _, *own_fast = warp_history(
                    self.temporal_module,
                    state,
                    depth,
                    normal,
                    K,
                    cam_from_world,
                    motion,
                    motion_world,
                    return_fast=self._fast_on(),
                )
                hist_fast = own_fast[0] if own_fast else hist_fast
            else:
                hist, hist_len = torch.zeros_like(s_color), torch.zeros_like(s_len)
                valid = None
            m = self.temporal_module
            out, n = blend_histories(
                traced_color,
                s_color,
                s_len,
                self.stereo_valid,
                hist,
                hist_len,
                torch.zeros_like(self.stereo_valid) if valid is None else valid,
                m.alpha,
                m.warmup,
                m.max_history,
                self.stereo_weight,
                m.history_rounding,
            )
            self.other_valid = valid
            if self._fast_on():
                own_valid = torch.zeros_like(self.stereo_valid) if valid is None else valid
                out, fast = self._blend_fast(
                    out, traced_color, (s_color, s_len, s_fast), hist_fast, hist_len, own_valid
                )
        else:
            trace = ~self.stereo_valid
            traced = torch.where(trace, traced_color, torch.zeros((), dtype=traced_color.dtype))
            filled, n, valid, _, fast = self._accumulate(
                state, traced, depth, normal, K, cam_from_world, motion, motion_world, clamp=False
            )
            self.other_valid = None if valid is None else valid & trace
            if self._stereo_out is not None:
                (s_color, s_len), s_fast = self._stereo_out, self._stereo_fast
                out = torch.where(self.stereo_valid, s_color.to(filled.dtype), filled)
                n = torch.where(self.stereo_valid, _stored_count(s_len, self.history_rounding), n)
                if fast is not None:  # the whole fast frame: the stereo one where kept, its own step elsewhere
                    s_fast = s_color if s_fast is None else s_fast
                    fast = torch.where(self.stereo_valid, s_fast.to(fast.dtype), fast)
            else:
                out = filled
            if fast is not None and valid is not None:  # the clamp at the traced pixels that kept a history
                fc = self.temporal_module.fast_clamp
                out = torch.where(
                    valid & trace, _clamp_checked(out, fast, fc.sigma, fc.radius, self.temporal_module.backend), out
                )
        self.left_valid = self.other_valid if eye == "left" else None
        setattr(self, f"{eye}_state", EyeState(out, n, depth, normal, K, cam_from_world, fast))
        self._left_gbuffer = None
        self.frame_index += 1
        return out

    def _blend_fast(self, out, traced_color, stereo, hist_fast, hist_len, own_valid):
        """The blended scheme's fast history (:func:`blend_histories` of the fast colours with the fast alpha, on
        the slow histories' counts and masks) and the blended slow colour ``out`` clamped to its box wherever a
        history was kept: (clamped colour, fast colour)."""
        s_color, s_len, s_fast = stereo
        m, fc = self.temporal_module, self.temporal_module.fast_clamp
        fast, _ = blend_histories(
            traced_color,
            s_color if s_fast is None else s_fast,
            s_len,
            self.stereo_valid,
            hist_fast,
            hist_len,
            own_valid,
            fc.alpha,
            m.warmup,
            m.max_history,
            self.stereo_weight,
        )
        kept = self.stereo_valid | own_valid
        return torch.where(kept, _clamp_checked(out, fast, fc.sigma, fc.radius, m.backend), out), fast

    def left(self, traced_color: Tensor) -> Tensor:
        """Complete the left eye from the traced discarded pixels (:meth:`other` when the left eye is the
        reprojected one: always, unless ``alternate``).

        Args:
            traced_color: (B, 3, H, W) 1-spp radiance; only pixels of the trace-me mask are read.

        Returns:
            (B, 3, H, W) the left eye's output for this frame.
        """
        self._expect("left", "right")
        return self.other(traced_color)
