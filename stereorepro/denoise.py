"""A learned denoiser and its temporal reprojection in one graph (one nn.Module, one ONNX file).

Per frame, :func:`reproject_denoise`:

1. accumulates this frame's 1-spp colour with the previous frame's history
   (:func:`~stereorepro.reproject.temporal_reproject`, hard accept tests, EMA with warm-up);
2. optionally (``stereo``) reprojects the *other eye's* accumulated colour into this eye
   (:func:`~stereorepro.reproject.stereo_reproject`);
3. stacks the denoiser's input features (:func:`denoise_features`, channels in :data:`FEATURES`) and runs the
   denoiser, any module mapping (B, C_in, H, W) features to a (B, 3, H, W) frame.

It returns the denoised frame and the new state. The caller feeds the state back next frame, together with this
frame's G-buffer and camera::

    model = ReprojectionDenoiser(denoiser, position_threshold, normal_threshold)
    history = empty_history(depth, normal, K, cam_from_world)           # first frame: no history
    for frame in frames:
        denoised, color, n = model(frame.color, frame.depth, frame.normal, frame.K, frame.cam_from_world, *history)
        history = (color, n, frame.depth, frame.normal, frame.K, frame.cam_from_world)

The denoised frame is *not* fed back: the history is the plain accumulation, so the state does not depend on the
network and a deployed graph (onnxruntime) and the torch module cannot drift apart over a sequence.

Features (:data:`FEATURES`, in this order; (B, 9, H, W), (B, 13, H, W) with ``stereo``):

======== ============================================================================================
channels feature
======== ============================================================================================
0-2      ``log1p(max(color, 0))`` of the accumulated colour (first, so that a residual network such as
         ``examples/denoiser_preprocess.py``'s ``UNet`` starts from the accumulation)
3        ``history_len / max_history``: the accumulated sample count, in (0, 1]
4        ``valid``: 1 where the history passed the reprojection tests, else 0
5        ``1 / depth`` where the pixel has a surface, else 0 (inverse depth: finite, 0 at the background)
6-8      the shading normal (unit, world space), 0 where not finite
9-11     (``stereo``) ``log1p(max(c, 0))`` of the other eye's accumulated colour reprojected into this eye, 0
         where discarded
12       (``stereo``) 1 where the stereo reprojection kept the pixel, else 0
======== ============================================================================================

First frame: pass :func:`empty_history` (zero history, and a previous depth of 0, i.e. no surface), so every
history tap is rejected: ``valid`` is 0, the accumulation is this frame's colour and ``history_len`` 1 — what
:func:`~stereorepro.temporal_step` gives without a state. (A history of length 0 on real depths also restarts the
accumulation, but ``valid`` then reports the tests' verdict on the empty history.)

Stereo: with ``stereo=True`` the forward takes five more inputs, the other eye's accumulated colour, G-buffer and
camera (``other_color`` (B, 3, H, W), ``other_depth``, ``other_normal``, ``other_K``, ``other_cam_from_world``),
typically the other eye's ``color`` output of this frame (run that eye first, e.g. the right eye temporal only,
then the left eye with stereo features). The other eye has this eye's size.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from ._checks import check_floating, check_scalar, check_shape, tracing
from ._tensors import finite_or_zero
from .camera import has_surface
from .errors import ParameterError, ParameterTypeError, ShapeError
from .reproject import (
    Blend,
    History,
    StereoReprojection,
    TemporalReprojection,
    Thresholds,
    View,
    stereo_reproject,
    temporal_reproject,
)
from .reproject.functional import (
    as_thresholds,
    given_keywords,
    reject_extra_arguments,
    stereo_views,
    temporal_views,
    warn_flat_form,
)
from .reproject.view import Field, view_fields

__all__ = [
    "FEATURES",
    "STEREO_FEATURES",
    "OTHER_NAMES",
    "feature_channels",
    "denoise_features",
    "reprojection_features",
    "reproject_denoise",
    "DenoiserFeatures",
    "DenoiseResult",
    "empty_history",
    "ReprojectionDenoiser",
    "denoiser_example_inputs",
]

#: The denoiser's input channels, in order (see the module docstring).
FEATURES = (
    "log1p_color_r",
    "log1p_color_g",
    "log1p_color_b",
    "history_len_norm",
    "valid",
    "inverse_depth",
    "normal_x",
    "normal_y",
    "normal_z",
)
#: Channels appended with ``stereo=True``.
STEREO_FEATURES = ("log1p_stereo_r", "log1p_stereo_g", "log1p_stereo_b", "stereo_valid")

#: The five extra inputs of the stereo variant, in order: the other eye's colour and view (this eye's size).
OTHER_FIELDS = (Field("other_color", ("B", "3", "H", "W")), *view_fields("other_"))
OTHER_NAMES = tuple(f.name for f in OTHER_FIELDS)


def feature_channels(stereo: bool = False) -> int:
    """C_in of the denoiser: 9, or 13 with ``stereo``.

    Examples:
        >>> from stereorepro.denoise import feature_channels
        >>> feature_channels(), feature_channels(stereo=True)
        (9, 13)
    """
    return len(FEATURES) + (len(STEREO_FEATURES) if stereo else 0)


def _log1p_color(c: Tensor) -> Tensor:
    return torch.log1p(c.clamp_min(0.0))


def denoise_features(
    color: Tensor,
    history_len: Tensor,
    valid: Tensor,
    depth: Tensor,
    normal: Tensor,
    max_history: float = 255.0,
    stereo_color: Tensor | None = None,
    stereo_valid: Tensor | None = None,
) -> Tensor:
    """The denoiser's input: (B, 9, H, W), or (B, 13, H, W) with the stereo channels (:data:`FEATURES`,
    :data:`STEREO_FEATURES`), in ``color``'s dtype.

    Args:
        color: (B, 3, H, W) accumulated colour of this frame.
        history_len: (B, 1, H, W) its sample count (float).
        valid: (B, 1, H, W) bool (or 0/1 float), where the history was kept.
        depth: (B, 1, H, W) camera-space z; normal: (B, 3, H, W) unit world-space normals.
        max_history: the accumulation's cap of ``history_len``; the feature is ``history_len / max_history``.
        stereo_color: optional (B, 3, H, W) the other eye's colour reprojected into this eye.
        stereo_valid: (B, 1, H, W) bool, where it was kept (required with ``stereo_color``).

    Examples:
        >>> import torch
        >>> from stereorepro.denoise import denoise_features
        >>> depth = torch.full((1, 1, 4, 4), 2.0); normal = torch.zeros(1, 3, 4, 4); normal[:, 2] = -1
        >>> valid = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        >>> x = denoise_features(torch.ones(1, 3, 4, 4), torch.full((1, 1, 4, 4), 51.0), valid, depth, normal)
        >>> tuple(x.shape), [round(float(v), 4) for v in x[0, :, 0, 0]]  # log1p colour, n / 255, valid, 1 / z, N
        ((1, 9, 4, 4), [0.6931, 0.6931, 0.6931, 0.2, 1.0, 0.5, 0.0, 0.0, -1.0])
    """
    bind = check_shape(color, ["B", "3", "H", "W"], "color")
    check_shape(history_len, ["B", "1", "H", "W"], "history_len", bind)
    check_shape(valid, ["B", "1", "H", "W"], "valid", bind)
    check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    if (stereo_color is None) != (stereo_valid is None):
        raise ParameterError("stereo_color and stereo_valid go together: pass both or neither")
    if not tracing():
        check_scalar(max_history, "max_history", 1.0, allow_inf=True, tracing=False)
    dt = color.dtype
    surface = has_surface(depth)
    inv_depth = torch.where(
        surface,
        1.0 / torch.where(surface, depth, torch.ones((), dtype=depth.dtype, device=depth.device)),
        torch.zeros((), dtype=depth.dtype, device=depth.device),
    )
    feats = [
        _log1p_color(color),
        (history_len / float(max_history)).to(dt),
        valid.to(dt),
        inv_depth.to(dt),
        finite_or_zero(normal).to(dt),
    ]
    if stereo_color is not None:
        check_shape(stereo_color, ["B", "3", "H", "W"], "stereo_color", bind)
        check_shape(stereo_valid, ["B", "1", "H", "W"], "stereo_valid", bind)
        feats += [_log1p_color(stereo_color).to(dt), stereo_valid.to(dt)]
    return torch.cat(feats, 1)


class DenoiserFeatures(NamedTuple):
    """What :func:`reprojection_features` returns: the denoiser's input and the new state.

    Attributes:
        features: (B, 9, H, W), or (B, 13, H, W) with the other eye (:func:`denoise_features`).
        color: (B, 3, H, W) the accumulated colour — the next frame's history colour.
        history_len: (B, 1, H, W) its sample count — the next frame's history length.

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, intrinsics_from_fov, reprojection_features
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> out = reprojection_features(torch.ones(1, 3, 6, 8), view, History.empty(view), view, (0.01, 0.1))
        >>> features, color, history_len = out  # or out.features, out.color, out.history_len
        >>> tuple(features.shape), tuple(color.shape), float(history_len.max())
        ((1, 9, 6, 8), (1, 3, 6, 8), 1.0)
    """

    features: Tensor
    color: Tensor
    history_len: Tensor

    @property
    def history(self) -> History:
        """The next frame's :class:`~stereorepro.History`."""
        return History(self.color, self.history_len)


class DenoiseResult(NamedTuple):
    """What :func:`reproject_denoise` returns: ``denoised`` (B, 3, H, W), the denoiser's output, and the new state
    ``color`` (B, 3, H, W), ``history_len`` (B, 1, H, W) (the plain accumulation, not the denoised frame).

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, intrinsics_from_fov, reproject_denoise
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> keep_rgb = lambda features: features[:, :3]  # a stand-in denoiser: the accumulated colour as it is
        >>> denoised, color, history_len = reproject_denoise(torch.ones(1, 3, 6, 8), view, History.empty(view), view,
        ...                                                  keep_rgb, (0.01, 0.1))
        >>> tuple(denoised.shape), float(color.min()), float(history_len.max())
        ((1, 3, 6, 8), 1.0, 1.0)
    """

    denoised: Tensor
    color: Tensor
    history_len: Tensor

    @property
    def history(self) -> History:
        """The next frame's :class:`~stereorepro.History`."""
        return History(self.color, self.history_len)


def reprojection_features(
    current_color: Tensor,
    view: View,
    history,
    prev_view: View,
    thresholds,
    *legacy_args,
    blend: Blend = Blend(),
    sampling: str = "bilinear",
    backend: str = "auto",
    other: tuple[Tensor, View] | None = None,
    **legacy_kwargs,
) -> DenoiserFeatures:
    """The reprojection half of :func:`reproject_denoise`: the denoiser's input features and the new state.

    It has no trained parameters (hard tests), so a training loop can compute the features of a clip once and
    train the denoiser on them. Arguments as :func:`reproject_denoise` (without the denoiser).

    Returns:
        :class:`DenoiserFeatures` ``(features (B, 9 or 13, H, W), color (B, 3, H, W), history_len (B, 1, H, W))``.

    The flat form (``current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
    prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold, ...``, ``other`` as five
    tensors) still works for one release, with a DeprecationWarning.

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, intrinsics_from_fov, reprojection_features
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> out = reprojection_features(torch.rand(1, 3, 6, 8), view, History.empty(view), view, (0.01, 0.1))
        >>> tuple(out.features.shape), float(out.history_len.max())
        ((1, 9, 6, 8), 1.0)
    """
    if not isinstance(view, View):
        warn_flat_form(
            "reprojection_features",
            "reprojection_features(current_color, view: View, history: History, "
            "prev_view: View, (position_threshold, normal_threshold), ...)",
        )
        args = (current_color, view, history, prev_view, thresholds) + legacy_args
        kw = dict(legacy_kwargs, **given_keywords(sampling=(sampling, "bilinear"), backend=(backend, "auto")))
        if other is not None:
            kw["other"] = other
        return _features_flat(*args, **kw)
    reject_extra_arguments("reprojection_features", legacy_args, legacy_kwargs)
    thr = as_thresholds(thresholds)
    color, n, valid, _ = temporal_reproject(
        current_color, view, history, prev_view, thr, blend=blend, sampling=sampling, backend=backend
    )
    s_color = s_valid = None
    if other is not None:
        o_color, o_view = _check_other(other, view)
        s_color, s_valid, _, _ = stereo_reproject(
            o_color, o_view, view, Thresholds(thr.position, thr.normal), sampling=sampling, backend=backend
        )
    max_history = Blend(*blend).max_history
    return DenoiserFeatures(
        denoise_features(color, n, valid, view.depth, view.normal, max_history, s_color, s_valid), color, n
    )


def _check_other(other, view: View) -> tuple[Tensor, View]:
    """``other`` as ``(other_color, other_view)``, checked against this eye's ``view``: errors name
    ``other_color`` / ``other_view`` (the stereo op would call them its ``color`` and ``src``)."""
    if not (isinstance(other, (tuple, list)) and len(other) == 2 and isinstance(other[1], View)):
        raise ParameterTypeError(f"other: expected (other_color, other_view: View), got {type(other).__name__}")
    o_color, o_view = other
    if not tracing():
        check_shape(
            o_color,
            ["B", "3", "H", "W"],
            "other_color (the other eye's colour)",
            {"B": o_view.batch_size, "H": o_view.height, "W": o_view.width},
            False,
        )
        check_floating(o_color, "other_color", False)
        if o_view.batch_size != view.batch_size:
            raise ShapeError(f"other_view: batch size {o_view.batch_size}, this eye's view has {view.batch_size}")
    return o_color, o_view


#: Flat names of the other eye's inputs, for the checks of the flat forms.
_OTHER_NAMES = dict(
    src_values="other_color",
    src_depth="other_depth",
    src_normal="other_normal",
    src="other",
    dst_depth="depth",
    dst_normal="normal",
    dst="current",
)


def _flat_views(current_color: Tensor, current: tuple, history: tuple, previous: tuple, other: tuple | None):
    """(view, History, prev_view, other as (colour, View) or None) of flat inputs, checked under their flat names."""
    history = History(*history)
    view, prev_view = temporal_views(current_color, current, history, previous)
    if other is None:
        return view, history, prev_view, None
    if len(other) != len(OTHER_NAMES):
        raise ParameterError(f"other: expected ({', '.join(OTHER_NAMES)}), got {len(other)} tensors")
    depth = current[0]
    check_shape(
        other[0], ["B", "3", "H", "W"], "other_color", {"B": depth.shape[0], "H": depth.shape[-2], "W": depth.shape[-1]}
    )
    o_view, _ = stereo_views(other[0], tuple(other[1:]), current, _OTHER_NAMES)
    return view, history, prev_view, (other[0], o_view)


def _features_flat(
    current_color,
    depth,
    normal,
    K,
    cam_from_world,
    history_color,
    history_len,
    prev_depth,
    prev_normal,
    prev_K,
    prev_cam_from_world,
    position_threshold,
    normal_threshold,
    alpha=0.2,
    warmup=True,
    max_history=255.0,
    sampling="bilinear",
    backend="auto",
    other=None,
):
    """The flat form of :func:`reprojection_features` (deprecated): a plain 3-tuple."""
    view, history, prev_view, other = _flat_views(
        current_color,
        (depth, normal, K, cam_from_world),
        (history_color, history_len),
        (prev_depth, prev_normal, prev_K, prev_cam_from_world),
        other,
    )
    return tuple(
        reprojection_features(
            current_color,
            view,
            history,
            prev_view,
            (position_threshold, normal_threshold),
            blend=Blend(alpha, warmup, max_history),
            sampling=sampling,
            backend=backend,
            other=other,
        )
    )


def reproject_denoise(
    current_color: Tensor,
    view: View,
    history,
    prev_view: View,
    denoiser,
    thresholds,
    *legacy_args,
    blend: Blend = Blend(),
    sampling: str = "bilinear",
    backend: str = "auto",
    other: tuple[Tensor, View] | None = None,
    **legacy_kwargs,
) -> DenoiseResult:
    """Temporal reprojection, (optional) stereo reprojection and a denoiser, for one eye and one frame.

    Args:
        current_color: (B, 3, H, W) this frame's 1-spp colour.
        view: this frame's :class:`~stereorepro.View` (H, W).
        history: :class:`~stereorepro.History` ``(color (B, 3, Hp, Wp), length (B, 1, Hp, Wp))``, the state
            returned for the previous frame (first frame: :meth:`History.empty <stereorepro.History.empty>`).
        prev_view: the previous frame's :class:`~stereorepro.View` (Hp, Wp).
        denoiser: a callable (an nn.Module) mapping (B, C_in, H, W) features (:func:`denoise_features`;
            C_in = :func:`feature_channels`) to a (B, 3, H, W) frame.
        thresholds, blend, sampling, backend: the temporal reprojection's settings
            (:func:`~stereorepro.reproject.temporal_reproject`; hard tests); the stereo step uses the same
            thresholds, sampling and backend.
        other: optional ``(other_color (B, 3, H, W), other_view)``: the other eye's accumulated colour and its
            :class:`~stereorepro.View`, reprojected into this eye as four more feature channels.

    Returns:
        :class:`DenoiseResult` ``(denoised (B, 3, H, W), color (B, 3, H, W), history_len (B, 1, H, W))``.

    The flat form (``current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
    prev_normal, prev_K, prev_cam_from_world, denoiser, position_threshold, normal_threshold, ...``) still works
    for one release, with a DeprecationWarning.

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, intrinsics_from_fov, reproject_denoise
        >>> from stereorepro.denoise import feature_channels
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> net = torch.nn.Conv2d(feature_channels(), 3, 3, padding=1)
        >>> out = reproject_denoise(torch.rand(1, 3, 6, 8), view, History.empty(view), view, net, (0.01, 0.1))
        >>> tuple(out.denoised.shape)
        (1, 3, 6, 8)
    """
    if not isinstance(view, View):
        warn_flat_form(
            "reproject_denoise",
            "reproject_denoise(current_color, view: View, history: History, "
            "prev_view: View, denoiser, (position_threshold, normal_threshold), ...)",
        )
        args = (current_color, view, history, prev_view, denoiser, thresholds) + legacy_args
        kw = dict(legacy_kwargs, **given_keywords(sampling=(sampling, "bilinear"), backend=(backend, "auto")))
        if other is not None:
            kw["other"] = other
        return tuple(_denoise_flat(*args, **kw))
    reject_extra_arguments("reproject_denoise", legacy_args, legacy_kwargs)
    if not callable(denoiser):
        raise ParameterTypeError(
            f"denoiser: expected a module mapping (B, C_in, H, W) to (B, 3, H, W), got {type(denoiser).__name__}"
        )
    x, color, n = reprojection_features(
        current_color,
        view,
        history,
        prev_view,
        thresholds,
        blend=blend,
        sampling=sampling,
        backend=backend,
        other=other,
    )
    return DenoiseResult(_run_denoiser(denoiser, x, current_color, other is not None), color, n)


def _run_denoiser(denoiser, x: Tensor, current_color: Tensor, stereo: bool) -> Tensor:
    """``denoiser(x)``, with errors that say what the features are and what the output must be."""
    if tracing():
        return denoiser(x)
    try:
        denoised = denoiser(x)
    except RuntimeError as e:  # typically a first layer built for another C_in: say what the features are
        if "channels" not in str(e):
            raise
        raise ShapeError(
            f"denoiser: failed on the features, shape {tuple(x.shape)} (C_in = {x.shape[1]}: "
            f"{', '.join(FEATURES + (STEREO_FEATURES if stereo else ()))}): {e}"
        ) from e
    if not isinstance(denoised, Tensor):
        raise ParameterTypeError(
            f"denoiser: expected it to return a tensor of shape (B, 3, H, W), got {type(denoised).__name__}"
        )
    B, _, H, W = current_color.shape
    if tuple(denoised.shape) != (B, 3, H, W):
        raise ShapeError(
            f"denoiser: expected an output of shape (B, 3, H, W) = {(B, 3, H, W)} for input "
            f"features {tuple(x.shape)}, got {tuple(denoised.shape)}"
        )
    return denoised


def _denoise_flat(
    current_color,
    depth,
    normal,
    K,
    cam_from_world,
    history_color,
    history_len,
    prev_depth,
    prev_normal,
    prev_K,
    prev_cam_from_world,
    denoiser,
    position_threshold,
    normal_threshold,
    alpha=0.2,
    warmup=True,
    max_history=255.0,
    sampling="bilinear",
    backend="auto",
    other=None,
):
    """The flat form of :func:`reproject_denoise` (deprecated)."""
    view, history, prev_view, other = _flat_views(
        current_color,
        (depth, normal, K, cam_from_world),
        (history_color, history_len),
        (prev_depth, prev_normal, prev_K, prev_cam_from_world),
        other,
    )
    return reproject_denoise(
        current_color,
        view,
        history,
        prev_view,
        denoiser,
        (position_threshold, normal_threshold),
        blend=Blend(alpha, warmup, max_history),
        sampling=sampling,
        backend=backend,
        other=other,
    )


def empty_history(
    depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The state to pass on a first frame (or after a camera cut): (history_color, history_len, prev_depth,
    prev_normal, prev_K, prev_cam_from_world) = zeros (B, 3, H, W), zeros (B, 1, H, W), zeros (B, 1, H, W) (no
    surface: every history tap is rejected), zeros (B, 3, H, W), ``K``, ``cam_from_world``; images in ``depth``'s
    dtype, on its device.

    Examples:
        >>> import torch
        >>> from stereorepro.denoise import empty_history
        >>> depth, normal = torch.full((1, 1, 4, 4), 2.0), torch.zeros(1, 3, 4, 4)
        >>> color, length, prev_depth, *_ = empty_history(depth, normal, torch.eye(3)[None], torch.eye(4)[None])
        >>> tuple(color.shape), tuple(length.shape), float(prev_depth.abs().max())
        ((1, 3, 4, 4), (1, 1, 4, 4), 0.0)
    """
    bind = check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    z1 = torch.zeros_like(depth)
    return (torch.zeros_like(normal), z1, z1.clone(), torch.zeros_like(normal), K, cam_from_world)


class ReprojectionDenoiser(nn.Module):
    """Temporal reprojection + a learned denoiser (+ optional stereo features) in one module. See
    :func:`reproject_denoise` and the module docstring (features, state, first frame).

    Args:
        denoiser: an nn.Module mapping (B, C_in, H, W) → (B, 3, H, W), C_in = :func:`feature_channels` (9, or 13
            with ``stereo``); its parameters are this module's (``self.denoiser``), trainable through it.
        position_threshold, normal_threshold: the accept tests (scene units; unit normals), hard.
        alpha, warmup, max_history, sampling, backend: as :class:`~stereorepro.TemporalReprojection`.
        stereo: also reproject the other eye's accumulated colour into this eye (five more inputs).

    Forward:
        ``forward(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
        prev_normal, prev_K, prev_cam_from_world[, other_color, other_depth, other_normal, other_K,
        other_cam_from_world]) -> (denoised, color, history_len_out)`` with shapes (B,3,H,W), (B,1,H,W), (B,3,H,W),
        (B,3,3), (B,4,4), (B,3,Hp,Wp), (B,1,Hp,Wp), (B,1,Hp,Wp), (B,3,Hp,Wp), (B,3,3), (B,4,4)[, (B,3,H,W),
        (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4)] → (B,3,H,W), (B,3,H,W), (B,1,H,W) float.
        Feed ``color`` and ``history_len_out`` back next frame as ``history_color`` / ``history_len``, with this
        frame's ``depth``, ``normal``, ``K``, ``cam_from_world`` as ``prev_*``.

    Export: ``stereorepro.export_onnx(model, path, inputs=denoiser_example_inputs(model))`` (symbolic B, H, W,
    and Hp, Wp for the history).

    Examples:
        >>> import torch
        >>> from stereorepro import ReprojectionDenoiser, intrinsics_from_fov
        >>> from stereorepro.denoise import empty_history
        >>> _ = torch.manual_seed(0)  # the convolution's initial weights and the colours below
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = (depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> model = ReprojectionDenoiser(torch.nn.Conv2d(9, 3, 3, padding=1), 0.03, 0.2)
        >>> history = empty_history(*view)  # first frame: nothing to reproject
        >>> denoised, color, n = model(torch.rand(1, 3, 6, 8), *view, *history)
        >>> model.in_channels, tuple(denoised.shape), float(n.max())
        (9, (1, 3, 6, 8), 1.0)
        >>> denoised, color, n = model(torch.rand(1, 3, 6, 8), *view, color, n, *view)  # next frame, same camera
        >>> float(n.min())
        2.0
    """

    #: The forward's inputs without the other eye (name, symbolic shape): the temporal op's; with ``stereo`` the
    #: other eye's colour and view follow (:data:`OTHER_FIELDS`).
    input_fields = TemporalReprojection.input_fields
    input_names = [f.name for f in input_fields]
    output_names = ["denoised", "color", "history_len_out"]

    def __init__(
        self,
        denoiser: nn.Module,
        position_threshold: float,
        normal_threshold: float,
        alpha: float = 0.2,
        warmup: bool = True,
        max_history: float = 255.0,
        sampling: str = "bilinear",
        backend: str = "auto",
        stereo: bool = False,
    ):
        super().__init__()
        if not isinstance(denoiser, nn.Module):
            raise ParameterTypeError(
                f"denoiser: expected an nn.Module mapping (B, C_in, H, W) to "
                f"(B, 3, H, W), got {type(denoiser).__name__}"
            )
        # the settings (validated there): hard tests, no learnable thresholds
        self.temporal = TemporalReprojection(
            position_threshold, normal_threshold, alpha, warmup, max_history, sampling, backend=backend
        )
        self.stereo = bool(stereo)
        if self.stereo:
            self.input_fields = type(self).input_fields + OTHER_FIELDS
            self.input_names = [f.name for f in self.input_fields]
        self.denoiser = denoiser

    @property
    def in_channels(self) -> int:
        """C_in the denoiser must take: :func:`feature_channels` (``stereo``)."""
        return feature_channels(self.stereo)

    def extra_repr(self) -> str:
        return f"stereo={self.stereo}, in_channels={self.in_channels}"

    def _other(self, others: tuple, method: str) -> tuple | None:
        given = [n for n, o in zip(OTHER_NAMES, others) if o is not None]
        if self.stereo and len(given) != len(OTHER_NAMES):
            missing = [n for n in OTHER_NAMES if n not in given]
            raise ParameterTypeError(f"ReprojectionDenoiser(stereo=True).{method} needs {', '.join(missing)}")
        if not self.stereo and given:
            raise ParameterTypeError(
                f"ReprojectionDenoiser(stereo=False).{method} got {', '.join(given)}: "
                "construct it with stereo=True for stereo features"
            )
        return others if self.stereo else None

    def _views(
        self, current_color: Tensor, current: tuple, history: tuple, previous: tuple, others: tuple, method: str
    ) -> tuple:
        """(view, History, prev_view, other) of the flat inputs, checked under their flat names."""
        other = self._other(others, method)
        return _flat_views(current_color, current, history, previous, other)

    def features(
        self,
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
        other_color: Tensor | None = None,
        other_depth: Tensor | None = None,
        other_normal: Tensor | None = None,
        other_K: Tensor | None = None,
        other_cam_from_world: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The forward without the denoiser: (features, color, history_len) (:func:`reprojection_features`), the
        denoiser's training input."""
        view, history, prev_view, other = self._views(
            current_color,
            (depth, normal, K, cam_from_world),
            (history_color, history_len),
            (prev_depth, prev_normal, prev_K, prev_cam_from_world),
            (other_color, other_depth, other_normal, other_K, other_cam_from_world),
            "features",
        )
        t = self.temporal
        return tuple(
            reprojection_features(
                current_color,
                view,
                history,
                prev_view,
                t.thresholds,
                blend=t.blend,
                sampling=t.sampling,
                backend=t.backend,
                other=other,
            )
        )

    def forward(
        self,
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
        other_color: Tensor | None = None,
        other_depth: Tensor | None = None,
        other_normal: Tensor | None = None,
        other_K: Tensor | None = None,
        other_cam_from_world: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        view, history, prev_view, other = self._views(
            current_color,
            (depth, normal, K, cam_from_world),
            (history_color, history_len),
            (prev_depth, prev_normal, prev_K, prev_cam_from_world),
            (other_color, other_depth, other_normal, other_K, other_cam_from_world),
            "forward",
        )
        t = self.temporal
        return tuple(
            reproject_denoise(
                current_color,
                view,
                history,
                prev_view,
                self.denoiser,
                t.thresholds,
                blend=t.blend,
                sampling=t.sampling,
                backend=t.backend,
                other=other,
            )
        )


def denoiser_example_inputs(
    module: ReprojectionDenoiser,
    batch: int = 1,
    height: int = 24,
    width: int = 32,
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
) -> tuple[Tensor, ...]:
    """Synthetic inputs for ``module``'s forward, in the order of its ``input_names`` (for export and tests):
    :func:`stereorepro._testing.example_inputs`' temporal inputs (a stereo pair with head motion, one eye as the
    previous frame), and with ``stereo`` the other camera of that pair as the other eye.

    Examples:
        >>> import torch
        >>> from stereorepro import ReprojectionDenoiser
        >>> from stereorepro.denoise import denoiser_example_inputs
        >>> model = ReprojectionDenoiser(torch.nn.Identity(), 0.03, 0.2)
        >>> inputs = denoiser_example_inputs(model, height=4, width=6)
        >>> len(inputs) == len(model.input_names), tuple(inputs[0].shape)
        (True, (1, 3, 4, 6))
    """
    from ._testing import example_inputs

    kw = dict(batch=batch, height=height, width=width, dtype=dtype)
    temporal = example_inputs(TemporalReprojection(1.0, 1.0), seed=seed, **kw)
    if not module.stereo:
        return temporal
    src = example_inputs(StereoReprojection(1.0, 1.0), seed=seed + 1, **kw)
    return temporal + src[:5]  # src_color, src_depth, src_normal, src_K, src_cam_from_world: the other eye
