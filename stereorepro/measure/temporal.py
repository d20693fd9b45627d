"""Temporal stability of an image sequence against its reference sequence: the reference-relative warping error.

Shapes: B batch, C channels, H × W the current frame, Hp × Wp the previous one.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import ShapeError, check_floating, check_shape
from ..errors import ParameterError, ParameterTypeError
from ..reproject import View, backward_reproject
from .metrics import _check_finite

__all__ = ["TEMPORAL_TONEMAPS", "temporal_error"]

#: The display mappings :func:`temporal_error` applies before differencing: ``"clamp"`` to [0, 1] (the LDR
#: convention of :func:`~stereorepro.measure.metrics.flip`, :func:`~stereorepro.measure.metrics.ssim` and the
#: experiment's ``ldr`` metric) or ``"none"`` (linear radiance).
TEMPORAL_TONEMAPS = ("clamp", "none")


def temporal_error(
    image: Tensor,
    reference: Tensor,
    prev_image: Tensor,
    prev_reference: Tensor,
    view: View,
    prev_view: View,
    thresholds,
    *,
    tonemap: str = "clamp",
) -> Tensor:
    """Temporal error per batch item: how much more (or less) an image sequence changes from frame to frame than
    its reference sequence does, after following the scene's known motion. 0 = as steady as the reference;
    flicker of a per-frame denoiser or of 1-spp noise shows as a positive value.

    Definition (the *reference-relative warping error*). The previous frame is warped into the current one by the
    known geometry, ``W(x) = backward_reproject(x, src=prev_view, dst=view, thresholds).values`` (hard tests,
    bilinear; ``view.motion``, when given, places the taps on moving objects). With ``T`` the tonemap, per pixel
    and channel::

        d = (T(image) − W(T(prev_image))) − (T(reference) − W(T(prev_reference)))

    and the result is ``sqrt(mean(d²))`` over the C channels of the pixels where the warp is ``valid``. This is the
    occlusion-masked warping error of Lai et al. 2018 ("Learning Blind Video Temporal Consistency", ECCV: the
    consecutive-frame difference after warping by the known flow, masked where the flow is occluded), which is also
    the temporal derivative that Chaitanya et al. 2017 (recurrent denoising autoencoder, SIGGRAPH) penalise in their
    temporal loss, here made **reference-relative**: the reference's own change is subtracted, so that a true change
    of the lighting (a moving light, a specular highlight sliding over a surface) is not counted as flicker, and
    neither is the warp's own residual. Without clamping, ``W`` being linear and the same for both sequences,
    ``d = e − W(e_prev)`` with ``e = image − reference``: the metric is the warping error of the *error image*.
    Camera motion alone therefore gives ~0: an image that equals the reference, or differs from it by a constant,
    gives exactly 0 (accepted bilinear weights sum to 1), and an error that stays on the same surface points from
    frame to frame cancels up to the warp's bilinear blur of it. Independent noise of standard deviation ``s`` per
    frame over a static camera gives ``s·√2`` (the difference of two independent samples); under motion, bilinear
    resampling averages the previous frame's noise, and the value lies between ``s·√(5/4)`` and ``s·√2``.

    Which pixels count: those the warp accepts (``valid``), i.e. current pixels that have a surface whose point
    the previous frame also saw (within ``thresholds``). Disoccluded pixels, pixels coming from outside the
    previous frame, and pixels without a surface (no point to follow: the environment seen through them moves by
    the camera's rotation alone, which a depth-based warp cannot place) are left out. A batch item with no valid
    pixel gives NaN (nothing was comparable), never a number made up.

    Computed as ``d = e − W(e_prev)`` with ``e = T(image) − T(reference)`` (``W`` is linear: one warp instead of
    two), the differences in the images' dtype, their squares and the mean in float64.

    Args:
        image: (B, C, H, W) the current frame, e.g. a denoiser's output (linear radiance), finite.
        reference: (B, C, H, W) or (1, C, H, W) the current frame's reference, finite.
        prev_image: (B, C, Hp, Wp) the previous frame of the sequence, finite.
        prev_reference: (B, C, Hp, Wp) or (1, C, Hp, Wp) the previous frame's reference, finite.
        view: the current frame's :class:`~stereorepro.View` (B, H, W): depth, normal, K, cam_from_world and
            optionally motion to the previous frame.
        prev_view: the previous frame's :class:`~stereorepro.View` (B, Hp, Wp).
        thresholds: :class:`~stereorepro.Thresholds` or ``(position, normal)``: the warp's accept tests, as in
            :func:`~stereorepro.backward_reproject`.
        tonemap: ``"clamp"`` (default: every image clamped to [0, 1] first, the LDR convention of the other
            metrics) or ``"none"`` (linear values), see :data:`TEMPORAL_TONEMAPS`.

    Returns:
        (B,) float64; NaN for a batch item without valid pixels. Differentiable in the four images (a training
        loss): the gradient of the square root is infinite at an error of exactly 0, as for
        :func:`~stereorepro.measure.metrics.rmse`.

    Raises:
        ParameterError: a tonemap other than ``"clamp"`` or ``"none"``, or an image with a NaN/inf value (as
            :func:`~stereorepro.measure.metrics.rmse` by default: a non-finite value is not an error measure).
        ParameterTypeError: a view that is not a :class:`~stereorepro.View`, or an image that is not a
            floating-point tensor.
        ShapeError: images whose shapes do not match each other or their views.

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> from stereorepro.measure import temporal_error
        >>> depth = torch.full((1, 1, 32, 32), 2.0); normal = torch.zeros(1, 3, 32, 32); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 32, 32), torch.eye(4)[None])  # a static camera
        >>> g = torch.Generator().manual_seed(0)
        >>> ref = torch.full((1, 3, 32, 32), 0.5)
        >>> noisy = [ref + 0.05 * torch.randn(1, 3, 32, 32, generator=g) for _ in range(2)]  # new noise per frame
        >>> round(float(temporal_error(noisy[1], ref, noisy[0], ref, view, view, (0.01, 0.1))), 3)  # ~0.05·√2 = 0.071
        0.07
        >>> float(temporal_error(noisy[0], ref, noisy[0], ref, view, view, (0.01, 0.1)))  # the same noise: steady
        0.0
    """
    sq, valid = _squared_residual(image, reference, prev_image, prev_reference, view, prev_view, thresholds, tonemap)
    count = valid.flatten(1).sum(1)
    total = torch.where(valid, sq, torch.zeros((), dtype=sq.dtype, device=sq.device)).flatten(1).sum(1)
    mean = total / count.clamp_min(1).to(torch.float64)
    return torch.where(count > 0, mean, torch.full_like(mean, math.nan)).sqrt()


def _squared_residual(
    image: Tensor,
    reference: Tensor,
    prev_image: Tensor,
    prev_reference: Tensor,
    view: View,
    prev_view: View,
    thresholds,
    tonemap: str,
) -> tuple[Tensor, Tensor]:
    """Per pixel: ``mean(d²)`` over the channels (B, 1, H, W) float64, and the warp's ``valid`` (B, 1, H, W)."""
    name = "temporal_error"
    if tonemap not in TEMPORAL_TONEMAPS:
        raise ParameterError(f"{name}: tonemap must be one of {TEMPORAL_TONEMAPS}, got {tonemap!r}")
    for arg, v in (("view", view), ("prev_view", prev_view)):
        if not isinstance(v, View):
            raise ParameterTypeError(f"{name}: {arg} must be a stereorepro.View, got {type(v).__name__}")
    # the views' sizes first: an image that does not fit its view is named as the image
    bind = {"B": view.batch_size, "H": view.height, "W": view.width}
    prev = {"B": prev_view.batch_size, "Hp": prev_view.height, "Wp": prev_view.width}
    check_shape(image, ["B", "C", "H", "W"], f"{name} image (sizes of view)", bind)
    check_shape(prev_image, ["B", "C", "Hp", "Wp"], f"{name} prev_image (sizes of prev_view)", prev | {"C": bind["C"]})
    check_shape(reference, ["R", "C", "H", "W"], f"{name} reference", dict(bind))
    check_shape(prev_reference, ["R", "C", "Hp", "Wp"], f"{name} prev_reference", dict(prev))
    for arg, t in (
        ("image", image),
        ("reference", reference),
        ("prev_image", prev_image),
        ("prev_reference", prev_reference),
    ):
        check_floating(t, f"{name} {arg}")
        if arg.endswith("reference") and t.shape[0] not in (1, bind["B"]):
            raise ShapeError(f"{name}: {arg} batch must be 1 or B={bind['B']}, got shape {tuple(t.shape)}")
    _check_finite(name, image=image, reference=reference, prev_image=prev_image, prev_reference=prev_reference)

    def T(t: Tensor) -> Tensor:
        return t.clamp(0.0, 1.0) if tonemap == "clamp" else t

    # W is linear (accepted bilinear weights renormalised, the same for every channel): warping the previous error
    # image once equals W(T(prev_image)) − W(T(prev_reference)), at half the cost
    dtype = torch.promote_types(prev_image.dtype, prev_reference.dtype)
    prev_error = T(prev_image).to(dtype) - T(prev_reference).to(dtype)  # BxCxHpxWp
    warped = backward_reproject(prev_error, prev_view, view, thresholds)
    error = T(image) - T(reference)  # BxCxHxW
    d = error.to(torch.float64) - warped.values.to(torch.float64)
    return (d * d).mean(1, keepdim=True), warped.valid
