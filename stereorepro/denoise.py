"""A learned denoiser and its temporal reprojection in one graph (one nn.Module, one ONNX file).

Per frame, :func:`reproject_denoise`:

1. accumulates this frame's 1-spp colour with the previous frame's history
   (:func:`~stereorepro.reproject.temporal_reproject`, hard accept tests, EMA with warm-up);
2. optionally (``other``) reprojects the *other eye's* accumulated colour into this eye
   (:func:`~stereorepro.reproject.stereo_reproject`);
3. optionally (``previous_output``, a *recurrent* denoiser) warps the denoiser's own output of the previous frame
   into this frame, with the history's geometry and accept tests
   (:func:`~stereorepro.reproject.backward_reproject` from the previous view to this one);
4. stacks the denoiser's input features (:func:`denoise_features`, channels :func:`feature_names`), optionally
   with this frame's first-hit ``albedo``, and runs the denoiser, any module mapping (B, C_in, H, W) features to
   a (B, 3, H, W) frame.

It returns the denoised frame and the new state. The caller feeds the state back next frame, together with this
frame's G-buffer and camera::

    model = ReprojectionDenoiser(denoiser, position_threshold, normal_threshold)
    history = empty_history(depth, normal, K, cam_from_world)           # first frame: no history
    for frame in frames:
        denoised, color, n = model(frame.color, frame.depth, frame.normal, frame.K, frame.cam_from_world, *history)
        history = (color, n, frame.depth, frame.normal, frame.K, frame.cam_from_world)

The history is the plain accumulation, whatever the network does. A *recurrent* denoiser
(``ReprojectionDenoiser(..., recurrent=True)``) also gets its own previous output back, warped into this frame:
the caller feeds ``denoised`` back as ``prev_denoised``, so the outputs then depend on the network's past outputs
(a deployed graph and the torch module are compared over whole sequences)::

    model = ReprojectionDenoiser(denoiser, position_threshold, normal_threshold, recurrent=True, albedo=True)
    state = empty_history(depth, normal, K, cam_from_world, recurrent=True)  # zeros, no surface: nothing kept
    for frame in frames:
        g = (frame.depth, frame.normal, frame.K, frame.cam_from_world)
        denoised, color, n = model(frame.color, *g, *state, frame.albedo)
        state = (color, n, *g, denoised)                                      # prev_denoised = denoised

In the View form: ``state = empty_state(view, recurrent=True)``, then per frame
``out = reproject_denoise(color, view, history, prev_view, net, thresholds, previous_output=prev, albedo=albedo)``
with ``history, prev_view, prev = out.history, view, out.denoised`` for the next frame. Training unrolls this loop
(gradients flow through ``previous_output``; ``backend="auto"`` runs the differentiable torch path when an input
requires grad).

Features (:func:`feature_names`, in this order; C_in = :func:`feature_channels`: 9, + 4 with ``stereo``, + 3 with
``recurrent``, + 3 with ``albedo``):

============= ============================================================================================
channels      feature
============= ============================================================================================
0-2           ``log1p(max(color, 0))`` of the accumulated colour (first, so that a residual network such as
              ``examples/denoiser_preprocess.py``'s ``UNet`` starts from the accumulation)
3             ``history_len / max_history``: the accumulated sample count, in (0, 1]
4             ``valid``: 1 where the history passed the reprojection tests, else 0
5             ``1 / depth`` where the pixel has a surface, else 0 (inverse depth: finite, 0 at the background)
6-8           the shading normal (unit, world space), 0 where not finite
+4 stereo     (:data:`STEREO_FEATURES`) ``log1p(max(c, 0))`` of the other eye's accumulated colour reprojected
              into this eye, 0 where discarded; then 1 where the stereo reprojection kept the pixel, else 0
+3 recurrent  (:data:`RECURRENT_FEATURES`) ``log1p(max(p, 0))`` of the previous output warped into this frame,
              0 where the warp is not valid (the same pixels as ``valid``)
+3 albedo     (:data:`ALBEDO_FEATURES`) this frame's first-hit albedo, 0 where not finite
============= ============================================================================================

So 9, 13 (stereo), 12 (recurrent), 12 (albedo), 15 (recurrent and albedo), 19 (all three) channels; the
channels of an option sit after those of the options before it whatever else is on.

First frame: pass :func:`empty_history` / :func:`empty_state` (zero history, and a previous depth of 0, i.e. no
surface), so every history tap is rejected: ``valid`` is 0, the accumulation is this frame's colour and
``history_len`` 1 — what :func:`~stereorepro.temporal_step` gives without a state — and the warped previous
output is 0. (A history of length 0 on real depths also restarts the accumulation, but ``valid`` then reports the
tests' verdict on the empty history.)

Per frame: the same network run on :func:`empty_state` at every frame (``stereo=True`` adds an other eye with no
surface) sees every warped channel at 0 — only this frame's 1-spp colour, albedo, depth and normal: the per-frame
baseline of a network trained with the reprojected features.

Stereo: with ``stereo=True`` the forward takes five more inputs, the other eye's accumulated colour, G-buffer and
camera (``other_color`` (B, 3, H, W), ``other_depth``, ``other_normal``, ``other_K``, ``other_cam_from_world``),
typically the other eye's ``color`` output of this frame (run that eye first, e.g. the right eye temporal only,
then the left eye with stereo features). The other eye has this eye's size.
"""

from __future__ import annotations

import functools
import inspect
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
from .reproject.functional import as_thresholds, stereo_views, temporal_views, warn_flat_form, warp_values
from .reproject.view import Field, view_fields

__all__ = [
    "FEATURES",
    "STEREO_FEATURES",
    "RECURRENT_FEATURES",
    "ALBEDO_FEATURES",
    "OTHER_NAMES",
    "feature_names",
    "feature_channels",
    "denoise_features",
    "reprojection_features",
    "reproject_denoise",
    "DenoiserFeatures",
    "DenoiseResult",
    "empty_history",
    "DenoiserState",
    "empty_state",
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
#: Channels appended with ``recurrent=True``: the denoiser's previous output warped into this frame.
RECURRENT_FEATURES = ("log1p_previous_r", "log1p_previous_g", "log1p_previous_b")
#: Channels appended with ``albedo=True``: the first-hit albedo of this frame.
ALBEDO_FEATURES = ("albedo_r", "albedo_g", "albedo_b")

#: The five extra inputs of the stereo variant, in order: the other eye's colour and view (this eye's size).
OTHER_FIELDS = (Field("other_color", ("B", "3", "H", "W")), *view_fields("other_"))
OTHER_NAMES = tuple(f.name for f in OTHER_FIELDS)
#: The recurrent variant's extra input: the previous frame's ``denoised`` output (the previous frame's size).
PREVIOUS_FIELD = Field("prev_denoised", ("B", "3", "Hp", "Wp"))
#: The albedo variant's extra input: this frame's first-hit albedo.
ALBEDO_FIELD = Field("albedo", ("B", "3", "H", "W"))


def feature_names(stereo: bool = False, recurrent: bool = False, albedo: bool = False) -> tuple[str, ...]:
    """The denoiser's input channels, in order: :data:`FEATURES`, then :data:`STEREO_FEATURES` (``stereo``),
    :data:`RECURRENT_FEATURES` (``recurrent``) and :data:`ALBEDO_FEATURES` (``albedo``).

    Examples:
        >>> from stereorepro.denoise import feature_names
        >>> feature_names(recurrent=True, albedo=True)[9:]
        ('log1p_previous_r', 'log1p_previous_g', 'log1p_previous_b', 'albedo_r', 'albedo_g', 'albedo_b')
    """
    return (
        FEATURES
        + (STEREO_FEATURES if stereo else ())
        + (RECURRENT_FEATURES if recurrent else ())
        + (ALBEDO_FEATURES if albedo else ())
    )


def feature_channels(stereo: bool = False, recurrent: bool = False, albedo: bool = False) -> int:
    """C_in of the denoiser: 9, + 4 with ``stereo``, + 3 with ``recurrent``, + 3 with ``albedo``
    (:func:`feature_names`).

    Examples:
        >>> from stereorepro.denoise import feature_channels
        >>> feature_channels(), feature_channels(stereo=True), feature_channels(True, recurrent=True, albedo=True)
        (9, 13, 19)
    """
    return len(feature_names(stereo, recurrent, albedo))


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
    warped_previous: Tensor | None = None,
    albedo: Tensor | None = None,
) -> Tensor:
    """The denoiser's input: (B, C_in, H, W) in ``color``'s dtype, channels :func:`feature_names` (9, + 4 with the
    stereo channels, + 3 with ``warped_previous``, + 3 with ``albedo``).

    Args:
        color: (B, 3, H, W) accumulated colour of this frame.
        history_len: (B, 1, H, W) its sample count (float).
        valid: (B, 1, H, W) bool (or 0/1 float), where the history was kept.
        depth: (B, 1, H, W) camera-space z; normal: (B, 3, H, W) unit world-space normals.
        max_history: the accumulation's cap of ``history_len``; the feature is ``history_len / max_history``.
        stereo_color: optional (B, 3, H, W) the other eye's colour reprojected into this eye.
        stereo_valid: (B, 1, H, W) bool, where it was kept (required with ``stereo_color``).
        warped_previous: optional (B, 3, H, W) the denoiser's previous output warped into this frame, 0 where the
            warp was not valid (:func:`reprojection_features` makes it); the feature is ``log1p(max(x, 0))``.
        albedo: optional (B, 3, H, W) this frame's first-hit albedo; non-finite values become 0.

    Returns:
        (B, C_in, H, W) features.

    Raises:
        ShapeError: an input's shape does not match ``color``'s (B, H, W).
        ParameterError: ``stereo_color`` without ``stereo_valid`` (or the reverse), or ``max_history`` < 1.

    Examples:
        >>> import torch
        >>> from stereorepro.denoise import denoise_features
        >>> depth = torch.full((1, 1, 4, 4), 2.0); normal = torch.zeros(1, 3, 4, 4); normal[:, 2] = -1
        >>> valid = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        >>> x = denoise_features(torch.ones(1, 3, 4, 4), torch.full((1, 1, 4, 4), 51.0), valid, depth, normal)
        >>> tuple(x.shape), [round(float(v), 4) for v in x[0, :, 0, 0]]  # log1p colour, n / 255, valid, 1 / z, N
        ((1, 9, 4, 4), [0.6931, 0.6931, 0.6931, 0.2, 1.0, 0.5, 0.0, 0.0, -1.0])
        >>> x = denoise_features(torch.ones(1, 3, 4, 4), torch.ones(1, 1, 4, 4), valid, depth, normal,
        ...                      warped_previous=torch.zeros(1, 3, 4, 4), albedo=torch.full((1, 3, 4, 4), 0.5))
        >>> tuple(x.shape), [float(v) for v in x[0, 9:, 0, 0]]  # log1p of the warped previous output, albedo
        ((1, 15, 4, 4), [0.0, 0.0, 0.0, 0.5, 0.5, 0.5])
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
    if warped_previous is not None:
        check_shape(warped_previous, ["B", "3", "H", "W"], "warped_previous", bind)
        feats.append(_log1p_color(warped_previous).to(dt))
    if albedo is not None:
        check_shape(albedo, ["B", "3", "H", "W"], "albedo", bind)
        feats.append(finite_or_zero(albedo).to(dt))
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
    return tuple(
        reproject_denoise(
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
    )


def _view_form(flat, new_call: str):
    """Decorate the View form of a function whose deprecated flat form is ``flat``: a call whose second argument
    is not a :class:`~stereorepro.View` warns (DeprecationWarning naming ``new_call``) and runs ``flat``; a View
    call with arguments the View form does not take raises ParameterTypeError."""

    def decorate(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def dispatch(current_color, view, *args, **kwargs):
            if not isinstance(view, View):
                warn_flat_form(fn.__name__, new_call)
                return flat(current_color, view, *args, **kwargs)
            try:
                signature.bind(current_color, view, *args, **kwargs)
            except TypeError as e:
                raise ParameterTypeError(f"{fn.__name__}: unexpected arguments with View inputs: {e}") from None
            return fn(current_color, view, *args, **kwargs)

        return dispatch

    return decorate


@_view_form(
    _features_flat,
    "reprojection_features(current_color, view: View, history: History, prev_view: View, "
    "(position_threshold, normal_threshold), ...)",
)
def reprojection_features(
    current_color: Tensor,
    view: View,
    history,
    prev_view: View,
    thresholds,
    *,
    blend: Blend = Blend(),
    sampling: str = "bilinear",
    backend: str = "auto",
    other: tuple[Tensor, View] | None = None,
    previous_output: Tensor | None = None,
    albedo: Tensor | None = None,
) -> DenoiserFeatures:
    """The reprojection half of :func:`reproject_denoise`: the denoiser's input features and the new state.

    It has no trained parameters (hard tests), so a training loop can compute the features of a clip once and
    train the denoiser on them; with ``previous_output`` (a recurrent denoiser) the features depend on the
    network's previous output, and a training loop computes them frame by frame, unrolled (gradients flow into
    ``previous_output``). Arguments as :func:`reproject_denoise` (without the denoiser).

    Returns:
        :class:`DenoiserFeatures` ``(features (B, C_in, H, W), color (B, 3, H, W), history_len (B, 1, H, W))``,
        C_in = :func:`feature_channels` of the inputs given.

    Raises:
        ShapeError: an input's shape does not match its view (``previous_output``: ``prev_view``; ``albedo``:
            ``view``).
        ParameterTypeError: a non-floating ``previous_output`` or ``albedo``, a malformed ``other``, or arguments
            only the flat form takes.

    The flat form (``current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
    prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold, ...``, ``other`` as five
    tensors) still works for one release, with a DeprecationWarning, without ``previous_output`` and ``albedo``.

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, intrinsics_from_fov, reprojection_features
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> out = reprojection_features(torch.rand(1, 3, 6, 8), view, History.empty(view), view, (0.01, 0.1))
        >>> tuple(out.features.shape), float(out.history_len.max())
        ((1, 9, 6, 8), 1.0)
        >>> previous = torch.full((1, 3, 6, 8), 1.0)  # last frame's denoised output (same camera here: kept)
        >>> out = reprojection_features(torch.rand(1, 3, 6, 8), view, out.history, view, (0.01, 0.1),
        ...                             previous_output=previous, albedo=torch.full((1, 3, 6, 8), 0.5))
        >>> tuple(out.features.shape), round(float(out.features[0, 9, 0, 0]), 4)  # log1p(1)
        ((1, 15, 6, 8), 0.6931)
    """
    thr = as_thresholds(thresholds)
    if albedo is not None:
        _check_image(albedo, view, "albedo (this frame's first-hit albedo)", "albedo")
    if previous_output is not None:
        _check_image(
            previous_output, prev_view, "previous_output (the previous frame's denoised output)", "previous_output"
        )
    color, n, valid, _ = temporal_reproject(
        current_color, view, history, prev_view, thr, blend=blend, sampling=sampling, backend=backend
    )
    s_color = s_valid = warped = None
    if other is not None:
        o_color, o_view = _check_other(other, view)
        s_color, s_valid, _, _ = stereo_reproject(
            o_color,
            o_view,
            view,
            Thresholds(thr.position, thr.normal, position_test=thr.position_test),
            sampling=sampling,
            backend=backend,
        )
    if previous_output is not None:
        out = warp_values(previous_output, prev_view, view, thr, sampling, backend=backend, confidence=False)
        warped = torch.where(out.valid, out.values, torch.zeros((), dtype=out.values.dtype, device=out.values.device))
    max_history = Blend(*blend).max_history
    x = denoise_features(color, n, valid, view.depth, view.normal, max_history, s_color, s_valid, warped, albedo)
    return DenoiserFeatures(x, color, n)


def _check_image(x: Tensor, view: View, what: str, name: str) -> None:
    """``x`` (B, 3, H, W) at ``view``'s size, floating; errors name ``what``."""
    if tracing():
        return
    check_shape(x, ["B", "3", "H", "W"], what, {"B": view.batch_size, "H": view.height, "W": view.width}, False)
    check_floating(x, name, False)


@_view_form(
    _denoise_flat,
    "reproject_denoise(current_color, view: View, history: History, prev_view: View, denoiser, "
    "(position_threshold, normal_threshold), ...)",
)
def reproject_denoise(
    current_color: Tensor,
    view: View,
    history,
    prev_view: View,
    denoiser,
    thresholds,
    *,
    blend: Blend = Blend(),
    sampling: str = "bilinear",
    backend: str = "auto",
    other: tuple[Tensor, View] | None = None,
    previous_output: Tensor | None = None,
    albedo: Tensor | None = None,
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
        previous_output=previous_output,
        albedo=albedo,
    )
    names = feature_names(other is not None, previous_output is not None, albedo is not None)
    return DenoiseResult(_run_denoiser(denoiser, x, current_color, names), color, n)


def _run_denoiser(denoiser, x: Tensor, current_color: Tensor, names: tuple[str, ...]) -> Tensor:
    """``denoiser(x)``, with errors that say what the features are and what the output must be."""
    if tracing():
        return denoiser(x)
    try:
        denoised = denoiser(x)
    except RuntimeError as e:  # typically a first layer built for another C_in: say what the features are
        if "channels" not in str(e):
            raise
        raise ShapeError(
            f"denoiser: failed on the features, shape {tuple(x.shape)} (C_in = {x.shape[1]}: {', '.join(names)}): {e}"
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


def empty_history(
    depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor, *, recurrent: bool = False
) -> tuple[Tensor, ...]:
    """The state to pass on a first frame (or after a camera cut): (history_color, history_len, prev_depth,
    prev_normal, prev_K, prev_cam_from_world) = zeros (B, 3, H, W), zeros (B, 1, H, W), zeros (B, 1, H, W) (no
    surface: every history tap is rejected), zeros (B, 3, H, W), ``K``, ``cam_from_world``; images in ``depth``'s
    dtype, on its device. With ``recurrent``, a seventh tensor follows: ``prev_denoised``, zeros (B, 3, H, W)
    (:class:`ReprojectionDenoiser` ``(recurrent=True)``'s input; every tap of it is rejected too).

    Examples:
        >>> import torch
        >>> from stereorepro.denoise import empty_history
        >>> depth, normal = torch.full((1, 1, 4, 4), 2.0), torch.zeros(1, 3, 4, 4)
        >>> color, length, prev_depth, *_ = empty_history(depth, normal, torch.eye(3)[None], torch.eye(4)[None])
        >>> tuple(color.shape), tuple(length.shape), float(prev_depth.abs().max())
        ((1, 3, 4, 4), (1, 1, 4, 4), 0.0)
        >>> *_, prev_denoised = empty_history(depth, normal, torch.eye(3)[None], torch.eye(4)[None], recurrent=True)
        >>> tuple(prev_denoised.shape), float(prev_denoised.abs().max())
        ((1, 3, 4, 4), 0.0)
    """
    bind = check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    z1 = torch.zeros_like(depth)
    state = (torch.zeros_like(normal), z1, z1.clone(), torch.zeros_like(normal), K, cam_from_world)
    if recurrent:
        state += (torch.zeros(normal.shape, dtype=depth.dtype, device=depth.device),)
    return state


class DenoiserState(NamedTuple):
    """What :func:`empty_state` returns: the inputs of :func:`reprojection_features` / :func:`reproject_denoise`
    that carry nothing over.

    Attributes:
        history: :meth:`History.empty <stereorepro.History.empty>` of the view.
        prev_view: the view with no surface (depth 0, normal 0; its camera): every history tap is rejected.
        previous_output: zeros (B, 3, H, W) (``recurrent``), else None.
        other: ``(zeros (B, 3, H, W), prev_view)`` (``stereo``): an other eye with no surface, every stereo tap
            rejected; else None.

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> from stereorepro.denoise import empty_state
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> state = empty_state(View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None]))
        >>> float(state.history.length.max()), float(state.prev_view.depth.max()), state.previous_output, state.other
        (0.0, 0.0, None, None)
    """

    history: History
    prev_view: View
    previous_output: Tensor | None
    other: tuple[Tensor, View] | None


def empty_state(view: View, *, recurrent: bool = False, stereo: bool = False) -> DenoiserState:
    """The state of a first frame (or after a camera cut), and the inputs of the *per-frame* use of a network
    trained with reprojected features: with it every warped channel of :func:`reprojection_features` (``valid``,
    the stereo channels, the warped previous output) is 0, and the accumulated colour is this frame's colour with
    ``history_len`` 1, so the network sees only this frame's colour, albedo, depth and normal.

    Args:
        view: this frame's :class:`~stereorepro.View` (B, H, W).
        recurrent: include ``previous_output`` (zeros (B, 3, H, W)).
        stereo: include ``other`` (zeros and a view with no surface).

    Returns:
        :class:`DenoiserState` ``(history, prev_view, previous_output, other)``, tensors in ``view.depth``'s dtype
        on its device.

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov, reprojection_features
        >>> from stereorepro.denoise import empty_state
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> state = empty_state(view, recurrent=True, stereo=True)
        >>> out = reprojection_features(torch.rand(1, 3, 6, 8), view, state.history, state.prev_view, (0.01, 0.1),
        ...                             other=state.other, previous_output=state.previous_output)
        >>> tuple(out.features.shape), float(out.features[:, 9:].abs().max()), float(out.history_len.max())
        ((1, 16, 6, 8), 0.0, 1.0)
    """
    if not isinstance(view, View):
        raise ParameterTypeError(f"view: expected a stereorepro.View, got {type(view).__name__}")
    zeros = torch.zeros_like(view.depth)
    none = View.unchecked(zeros, torch.zeros_like(view.normal), view.K, view.cam_from_world)
    color = torch.zeros(view.normal.shape, dtype=view.depth.dtype, device=view.depth.device)
    return DenoiserState(
        History.empty(view),
        none,
        color.clone() if recurrent else None,
        (color, none) if stereo else None,
    )


#: The inputs of :class:`ReprojectionDenoiser`'s forward after ``prev_cam_from_world``, with the option of each.
_OPTIONAL_INPUTS = {**{n: "stereo" for n in OTHER_NAMES}, PREVIOUS_FIELD.name: "recurrent", ALBEDO_FIELD.name: "albedo"}
_N_TEMPORAL = len(TemporalReprojection.input_fields)


class ReprojectionDenoiser(nn.Module):
    """Temporal reprojection + a learned denoiser (+ optional stereo, recurrent and albedo features) in one module.
    See :func:`reproject_denoise` and the module docstring (features, state, first frame).

    Args:
        denoiser: an nn.Module mapping (B, C_in, H, W) → (B, 3, H, W), C_in = :func:`feature_channels` of the
            options (9, + 4 ``stereo``, + 3 ``recurrent``, + 3 ``albedo``); its parameters are this module's
            (``self.denoiser``), trainable through it.
        position_threshold, normal_threshold: the accept tests (scene units; unit normals), hard.
        alpha, warmup, max_history, sampling, backend: as :class:`~stereorepro.TemporalReprojection`.
        stereo: also reproject the other eye's accumulated colour into this eye (five more inputs).
        recurrent: also warp the previous frame's denoised output into this frame (one more input,
            ``prev_denoised`` (B, 3, Hp, Wp): feed back the previous call's ``denoised``).
        albedo: also take this frame's first-hit albedo (one more input, ``albedo`` (B, 3, H, W)).

    Forward:
        ``forward(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
        prev_normal, prev_K, prev_cam_from_world[, other_color, other_depth, other_normal, other_K,
        other_cam_from_world][, prev_denoised][, albedo]) -> (denoised, color, history_len_out)`` with shapes
        (B,3,H,W), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4), (B,3,Hp,Wp), (B,1,Hp,Wp), (B,1,Hp,Wp), (B,3,Hp,Wp),
        (B,3,3), (B,4,4); with ``stereo`` (B,3,H,W), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4); with ``recurrent``
        (B,3,Hp,Wp); with ``albedo`` (B,3,H,W) → (B,3,H,W), (B,3,H,W), (B,1,H,W) float. The inputs after ``prev_cam_from_world`` are taken positionally in
        the order of :attr:`input_names` (what :func:`~stereorepro.export_onnx` feeds) or by name.
        Feed ``color`` and ``history_len_out`` back next frame as ``history_color`` / ``history_len``, with this
        frame's ``depth``, ``normal``, ``K``, ``cam_from_world`` as ``prev_*`` (and ``denoised`` as
        ``prev_denoised``).

    Export: ``stereorepro.export_onnx(model, path, inputs=denoiser_example_inputs(model))`` (symbolic B, H, W,
    and Hp, Wp for the history): one graph whose inputs are :attr:`input_names`.

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

        A recurrent denoiser with albedo: its own output goes back in as ``prev_denoised``.

        >>> model = ReprojectionDenoiser(torch.nn.Conv2d(15, 3, 1), 0.03, 0.2, recurrent=True, albedo=True)
        >>> model.input_names[11:]
        ['prev_denoised', 'albedo']
        >>> state = empty_history(*view, recurrent=True)  # history, previous view, prev_denoised: zeros
        >>> albedo = torch.full((1, 3, 6, 8), 0.5)
        >>> for frame in range(3):
        ...     denoised, color, n = model(torch.rand(1, 3, 6, 8), *view, *state, albedo)
        ...     state = (color, n, *view, denoised)
        >>> float(n.min())
        3.0
    """

    #: The forward's inputs without options (name, symbolic shape): the temporal op's; with ``stereo`` the other
    #: eye's colour and view follow (:data:`OTHER_FIELDS`), then ``prev_denoised`` (``recurrent``,
    #: :data:`PREVIOUS_FIELD`) and ``albedo`` (:data:`ALBEDO_FIELD`).
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
        recurrent: bool = False,
        albedo: bool = False,
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
        self.stereo, self.recurrent, self.albedo = bool(stereo), bool(recurrent), bool(albedo)
        self.input_fields = (
            type(self).input_fields
            + (OTHER_FIELDS if self.stereo else ())
            + ((PREVIOUS_FIELD,) if self.recurrent else ())
            + ((ALBEDO_FIELD,) if self.albedo else ())
        )
        self.input_names = [f.name for f in self.input_fields]
        self.denoiser = denoiser

    @property
    def in_channels(self) -> int:
        """C_in the denoiser must take: :func:`feature_channels` of the options."""
        return feature_channels(self.stereo, self.recurrent, self.albedo)

    @property
    def feature_names(self) -> tuple[str, ...]:
        """The denoiser's input channels, in order (:func:`feature_names` of the options)."""
        return feature_names(self.stereo, self.recurrent, self.albedo)

    def _options(self) -> str:
        return f"stereo={self.stereo}, recurrent={self.recurrent}, albedo={self.albedo}"

    def extra_repr(self) -> str:
        return f"{self._options()}, in_channels={self.in_channels}"

    def _optional_inputs(self, extra: tuple, named: dict, method: str) -> dict:
        """The inputs after ``prev_cam_from_world`` by name: ``extra`` positionally in :attr:`input_names` order,
        then ``named`` (those not None); errors say which option an input needs."""
        names = self.input_names[_N_TEMPORAL:]
        where = f"ReprojectionDenoiser({self._options()}).{method}"
        while extra and extra[-1] is None:  # None is "not given" (torch.onnx.export appends the keywords' defaults)
            extra = extra[:-1]
        if len(extra) > len(names):
            raise ParameterTypeError(
                f"{where} takes {len(self.input_names)} inputs ({', '.join(names) or 'none'} after "
                f"prev_cam_from_world), got {_N_TEMPORAL + len(extra)}: construct it with stereo=True, "
                "recurrent=True or albedo=True for more inputs"
            )
        given = {n: v for n, v in zip(names, extra) if v is not None}
        for name, value in named.items():
            if value is not None:
                if name in given:
                    raise ParameterTypeError(f"{where} got {name} twice (positionally and by name)")
                given[name] = value
        unexpected = [n for n in given if n not in names]
        if unexpected:
            options = sorted({_OPTIONAL_INPUTS[n] for n in unexpected})
            raise ParameterTypeError(
                f"{where} got {', '.join(unexpected)}: construct it with {' and '.join(o + '=True' for o in options)}"
            )
        missing = [n for n in names if n not in given]
        if missing:
            raise ParameterTypeError(f"{where} needs {', '.join(missing)}")
        return given

    def _call(self, fn, method: str, inputs: tuple, extra: tuple, named: dict, *denoiser) -> tuple:
        """``fn`` (:func:`reprojection_features` or :func:`reproject_denoise`) of the flat inputs, checked under
        their flat names."""
        given = self._optional_inputs(extra, named, method)
        current_color, current, history, previous = inputs[0], inputs[1:5], inputs[5:7], inputs[7:11]
        other = tuple(given[n] for n in OTHER_NAMES) if self.stereo else None
        view, history, prev_view, other = _flat_views(current_color, current, history, previous, other)
        prev_denoised = given.get(PREVIOUS_FIELD.name)
        if prev_denoised is not None:
            _check_image(
                prev_denoised, prev_view, "prev_denoised (the previous frame's denoised output)", "prev_denoised"
            )
        t = self.temporal
        return tuple(
            fn(
                current_color,
                view,
                history,
                prev_view,
                *denoiser,
                t.thresholds,
                blend=t.blend,
                sampling=t.sampling,
                backend=t.backend,
                other=other,
                previous_output=prev_denoised,
                albedo=given.get(ALBEDO_FIELD.name),
            )
        )

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
        *optional: Tensor,
        other_color: Tensor | None = None,
        other_depth: Tensor | None = None,
        other_normal: Tensor | None = None,
        other_K: Tensor | None = None,
        other_cam_from_world: Tensor | None = None,
        prev_denoised: Tensor | None = None,
        albedo: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The forward without the denoiser: (features, color, history_len) (:func:`reprojection_features`), the
        denoiser's training input."""
        inputs = (current_color, depth, normal, K, cam_from_world, history_color, history_len)
        inputs += (prev_depth, prev_normal, prev_K, prev_cam_from_world)
        named = dict(zip(OTHER_NAMES, (other_color, other_depth, other_normal, other_K, other_cam_from_world)))
        named.update(prev_denoised=prev_denoised, albedo=albedo)
        return self._call(reprojection_features, "features", inputs, optional, named)

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
        *optional: Tensor,
        other_color: Tensor | None = None,
        other_depth: Tensor | None = None,
        other_normal: Tensor | None = None,
        other_K: Tensor | None = None,
        other_cam_from_world: Tensor | None = None,
        prev_denoised: Tensor | None = None,
        albedo: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        inputs = (current_color, depth, normal, K, cam_from_world, history_color, history_len)
        inputs += (prev_depth, prev_normal, prev_K, prev_cam_from_world)
        named = dict(zip(OTHER_NAMES, (other_color, other_depth, other_normal, other_K, other_cam_from_world)))
        named.update(prev_denoised=prev_denoised, albedo=albedo)
        return self._call(reproject_denoise, "forward", inputs, optional, named, self.denoiser)


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
    previous frame), with ``stereo`` the other camera of that pair as the other eye, with ``recurrent`` a previous
    denoised frame (uniform in [0, 2), the history's size) and with ``albedo`` an albedo (uniform in [0, 1)).

    Examples:
        >>> import torch
        >>> from stereorepro import ReprojectionDenoiser
        >>> from stereorepro.denoise import denoiser_example_inputs
        >>> model = ReprojectionDenoiser(torch.nn.Identity(), 0.03, 0.2)
        >>> inputs = denoiser_example_inputs(model, height=4, width=6)
        >>> len(inputs) == len(model.input_names), tuple(inputs[0].shape)
        (True, (1, 3, 4, 6))
        >>> model = ReprojectionDenoiser(torch.nn.Identity(), 0.03, 0.2, recurrent=True, albedo=True)
        >>> [tuple(x.shape) for x in denoiser_example_inputs(model, height=4, width=6)[-2:]]
        [(1, 3, 4, 6), (1, 3, 4, 6)]
    """
    from ._testing import example_inputs

    kw = dict(batch=batch, height=height, width=width, dtype=dtype)
    inputs = example_inputs(TemporalReprojection(1.0, 1.0), seed=seed, **kw)
    if module.stereo:
        src = example_inputs(StereoReprojection(1.0, 1.0), seed=seed + 1, **kw)
        inputs += src[:5]  # src_color, src_depth, src_normal, src_K, src_cam_from_world: the other eye
    g = torch.Generator().manual_seed(seed + 2)
    if module.recurrent:
        inputs += ((2 * torch.rand(inputs[5].shape, generator=g, dtype=torch.float64)).to(dtype),)
    if module.albedo:
        inputs += (torch.rand(inputs[0].shape, generator=g, dtype=torch.float64).to(dtype),)
    return inputs
