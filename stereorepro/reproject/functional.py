"""The reprojection ops as pure tensor functions (paper §4.1), and the rule that picks their implementation.

For every destination pixel: unproject it with the destination depth, move it into the source camera, project
it, and read the 2×2 bilinear taps around that point in the source image (or the one nearest tap). A tap is
**accepted** only if

1. it lies inside the source frame,
2. the source pixel has a surface (see :func:`stereorepro.camera.has_surface`),
3. ``|P_src − P_dst| <= position_threshold`` (scene units; both points in the source camera's frame),
4. ``|N_src − N_dst| <= normal_threshold`` (unit world-space shading normals), and
5. its values are finite (policy: a NaN/Inf sample is rejected like an occluded one, so it never leaks).
   Non-finite *normals* (source or destination) are read as zero vectors, so they fail the normal test for any
   ``normal_threshold < 1`` and are reported as ``NORMAL``.

Accepted bilinear weights are renormalised by their sum; a pixel is ``valid`` when the accepted weight is > 0.
The same-instant stereo case and the temporal case are the same operation with different cameras
(paper §2.2: "stereo reprojection can be thought of as a special case of temporal reprojection").

Discard reasons (:class:`~stereorepro.reproject.reason.Reason`, uint8 map, 0 = kept) are ordered by the test that
failed; a tap's code is the first test it failed, and an invalid pixel reports the largest code among its taps of
non-zero bilinear weight (the test at which its most nearly accepted tap failed). That is what the paper's
Figure 1 colours.

Precision: positions are compared in the source camera frame after composing ``src_from_dst`` in float64
(:func:`stereorepro.camera.compose_warp`), so results do not degrade with distance from the world origin; they
degrade with distance from the camera as fp32 does (relative 6e-8). Pass float64 cameras for scenes far
(≥ 1e3 units) from the origin.

Dtypes: images may be float16/bfloat16/float32/float64; computation is float32 (float64 if any image input is
float64) and the colour output takes the dtype of the source colour.

Implementations (one backend rule, :func:`select_backend`): the torch reference (:mod:`._general`, with the
inference fast path :mod:`._fast`) and the native kernels (:mod:`._native`), which give the same results.
"""

from __future__ import annotations

from typing import Iterable

import torch
from torch import Tensor

from .. import _backend
from .._checks import (STEREO_NAMES, TEMPORAL_NAMES, check_floating, check_motion, check_reprojection_inputs,
                       check_sampling, check_scalar, check_shape, check_thresholds, tracing)
from ..camera import compose_warp, rectify_warp
from . import _fast, _general, _lean, _native
from ._general import as_scalar, compute_dtype, inference_only, squared_thresholds

__all__ = ["BACKENDS", "backward_reproject", "stereo_reproject", "temporal_blend", "temporal_reproject",
           "select_backend", "native_unsupported", "warp_values"]

#: Backend names the ops accept (``STEREOREPRO_BACKEND`` also accepts ``numpy`` and ``reference`` for torch).
BACKENDS = ("auto", "torch", "native")

#: Whether the torch backend may take the inference fast path (tests switch it off to exercise the general path).
FAST_PATH = True

#: Whether ONNX export writes the export formulation (:mod:`._lean`) for hard tests without motion vectors
#: (False: the general path, traced as it is; the benchmark compares both).
EXPORT_LEAN = True


def native_unsupported(images: Iterable[Tensor], others: Iterable = (), soft: bool = False,
                       motion: bool = False) -> str | None:
    """Why the native kernels cannot run these inputs, or None when they can.

    Args:
        images: image tensors (colours, depths, normals, history length): float32 or float16, each on its own
            (float16 is read as it is and computed in float32, as torch computes it).
        others: other inputs (cameras, thresholds, alpha): only device and autograd are checked.
        soft: soft accept tests (torch only).
        motion: motion vectors given (torch only).
    """
    images = list(images)
    tensors = images + [x for x in others if isinstance(x, Tensor)]
    if not _native.available():
        return "the native core stereorepro._core (with `reproject`) is not built or not importable"
    if tracing():
        return "tracing / ONNX export / torch.compile need the torch path"
    if soft:
        return "soft=True (differentiable thresholds) is implemented in torch only"
    if motion:
        return "motion vectors (motion=...) are implemented in torch only"
    devices = {str(t.device) for t in tensors if t.device.type != "cpu"}
    if devices:
        return f"the native kernels run on the CPU only, got tensors on {sorted(devices)}"
    dtypes = {t.dtype for t in images if t.dtype not in _native.DTYPES}
    if dtypes:
        return ("the native kernels read float32 or float16 images only (bfloat16 and float64 run on torch), got "
                f"images of dtype {sorted(map(str, dtypes))}")
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return "an input requires grad (autograd needs the torch path; use torch.no_grad() for native)"
    return None


def select_backend(backend: str, images: Iterable[Tensor], others: Iterable = (), soft: bool = False,
                   motion: bool = False) -> str:
    """Resolve ``backend`` (``"auto"`` | ``"torch"`` | ``"native"``) to ``"torch"`` or ``"native"``.

    * ``STEREOREPRO_BACKEND`` overrides ``backend`` when set (:mod:`stereorepro._backend`: the rule the tracer
      follows too);
    * ``"torch"`` always runs torch;
    * ``"auto"`` runs native when :func:`native_unsupported` finds nothing against it: ``_core`` built, every
      tensor on the CPU, image tensors float32, hard tests, no autograd, and not tracing / exporting / compiling;
    * ``"native"`` runs native and raises RuntimeError saying why when it is not possible;
    * tracing, ONNX export and ``torch.compile`` always use torch, whatever was asked.
    """
    chosen = _backend.resolve(backend, BACKENDS, lambda: native_unsupported(images, others, soft, motion),
                              reference_only=tracing())
    return "native" if chosen == "native" else "torch"


def backward_reproject(
    src_values: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    src_K: Tensor,
    src_cam_from_world: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    dst_K: Tensor,
    dst_cam_from_world: Tensor,
    position_threshold,
    normal_threshold,
    sampling: str = "bilinear",
    soft: bool = False,
    temperature: float = 0.1,
    check: bool = True,
    backend: str = "auto",
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
    rectified: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Backward-warp ``src_values`` into the destination view with per-tap discard tests.

    Args:
        src_values: (B, C, Hs, Ws) values to carry (colour; extra channels such as history length ride along).
        src_depth: (B, 1, Hs, Ws) camera-z depth of the source view.
        src_normal: (B, 3, Hs, Ws) unit world-space shading normals of the source view.
        src_K: (B, 3, 3) source intrinsics.
        src_cam_from_world: (B, 4, 4) source extrinsics (rigid).
        dst_depth: (B, 1, H, W) camera-z depth of the destination view.
        dst_normal: (B, 3, H, W) unit world-space shading normals of the destination view.
        dst_K: (B, 3, 3) destination intrinsics.
        dst_cam_from_world: (B, 4, 4) destination extrinsics (rigid).
        position_threshold: max |P_src − P_dst| in scene units (float or 0-d tensor).
        normal_threshold: max |N_src − N_dst| between unit normals (float or 0-d tensor).
        sampling: ``"bilinear"`` (2×2 taps, the paper's choice) or ``"nearest"`` (one tap).
        soft: replace the position and normal step functions by sigmoids
            ``sigmoid((thr² − d²) / (2·temperature·thr²))`` (≈ a sigmoid in (thr − d) / (temperature·thr)), so
            that the output is differentiable in the thresholds. ``valid`` and ``reason`` still report the hard
            decision at the current thresholds.
        temperature: softness relative to the threshold (dimensionless), used when ``soft``. Soft colours are
            renormalised by ``max(accepted weight, SOFT_DEN_FLOOR)`` so that gradients stay bounded.
        check: validate shapes/dtypes (public boundary).
        backend: ``"auto"`` | ``"torch"`` | ``"native"``: see :func:`select_backend`.
        motion: optional (B, 2, H, W) motion vectors in pixels, ``src_pixel = dst_pixel + motion`` (a renderer's
            screen-space motion to the source frame): the taps are read there instead of where the cameras put
            the destination point. Non-finite motion sends the pixel out of the frame (``OUT_OF_FRAME``). Torch
            only: ``backend="auto"`` then runs torch's general path.
        motion_world: optional (B, 3, H, W) world-space motion of the destination point to the source instant
            (``P_src = P_dst + motion_world``; with ``motion``): the position test compares the source tap with
            the moved point, so a moving object is kept and a disocclusion is still rejected. Default zeros
            (static geometry).
        rectified: the caller declares a rectified pair (a parallel rig at one instant with equal intrinsics,
            the paper's stereo case): every destination pixel reads its own source row, with the rounding of
            real cameras removed (:func:`stereorepro.camera.rectify_warp`, which raises CameraError for cameras
            that are not such a pair). Every backend then reads two taps per pixel instead of four, and so does
            the exported ONNX graph. Not with ``motion``.

    Returns:
        values: (B, C, H, W) warped values (0 where nothing was accepted), dtype of ``src_values``.
        valid: (B, 1, H, W) bool, accepted bilinear weight > 0.
        reason: (B, 1, H, W) uint8 :class:`Reason` codes (0 where valid).
        confidence: (B, 1, H, W) accepted bilinear weight in [0, 1] before renormalisation (soft weights when
            ``soft``), in the compute dtype.

    On the torch backend, hard tests without autograd or tracing (and with finite squared thresholds) take a
    faster path with identical outputs (:mod:`stereorepro.reproject._fast`); gradients, tracing, ONNX export and
    soft tests take the general one (:mod:`stereorepro.reproject._general`).
    """
    check_sampling(sampling)
    if check:
        check_reprojection_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                                  dst_K, dst_cam_from_world, dict(STEREO_NAMES, src_values="src_values"))
        check_thresholds(position_threshold, normal_threshold)
        check_motion(motion, motion_world, dst_depth, "motion", "motion_world")
    if rectified and motion is not None:
        raise ValueError("backward_reproject: rectified=True declares a same-instant stereo pair; it cannot be "
                         "combined with motion vectors")
    if _is_empty(dst_depth):
        return _empty_outputs(src_values, dst_depth, confidence=True)
    if select_backend(backend, (src_values, src_depth, src_normal, dst_depth, dst_normal),
                      (src_K, src_cam_from_world, dst_K, dst_cam_from_world, position_threshold, normal_threshold),
                      soft, motion is not None) == "native":
        return _native_backward(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                                dst_K, dst_cam_from_world, position_threshold, normal_threshold, sampling,
                                rectified=rectified)
    return _torch_backward(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                           dst_cam_from_world, position_threshold, normal_threshold, sampling, soft, temperature,
                           motion, motion_world, rectified)


def _exporting_lean(soft: bool, motion) -> bool:
    """Whether this call is being exported in the export formulation (:mod:`._lean`): hard tests, no motion
    vectors, :data:`EXPORT_LEAN`."""
    return EXPORT_LEAN and not soft and motion is None and torch.onnx.is_in_onnx_export()


def _warp(src_K, src_cam_from_world, dst_K, dst_cam_from_world, dtype, dst_depth, rectified: bool):
    """The composed warp (:func:`compose_warp`), rectified when the caller declares a rectified pair."""
    warp = compose_warp(src_K, src_cam_from_world, dst_K, dst_cam_from_world, dtype)
    return rectify_warp(warp, *dst_depth.shape[-2:]) if rectified else warp


def _torch_backward(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                    dst_cam_from_world, position_threshold, normal_threshold, sampling, soft, temperature,
                    motion=None, motion_world=None, rectified=False):
    """The torch backend of :func:`backward_reproject` (arguments checked): the fast path where it applies, and
    the export formulation (:mod:`._lean`) while exporting to ONNX with hard tests."""
    wdt = compute_dtype(src_values, src_depth, src_normal, dst_depth, dst_normal)
    warp = _warp(src_K, src_cam_from_world, dst_K, dst_cam_from_world, wdt, dst_depth, rectified)
    if _exporting_lean(soft, motion):
        return _lean.lean_reproject(src_values, src_depth, src_normal, dst_depth, dst_normal, warp,
                                    position_threshold, normal_threshold, sampling, rectified)
    inference = inference_only((src_values, src_depth, src_normal, dst_depth, dst_normal, src_K, dst_K,
                                src_cam_from_world, dst_cam_from_world, position_threshold, normal_threshold,
                                motion, motion_world))
    if motion is not None:  # motion vectors: the general path (the fast path and native warp with cameras only)
        return _general.general_reproject(src_values, src_depth, src_normal, dst_depth, dst_normal, warp,
                                          position_threshold, normal_threshold, sampling, soft, temperature,
                                          inference, motion, motion_world, src_cam_from_world[:, :3, :3])
    if inference and not soft and FAST_PATH:  # the usual inference case: same results, less memory traffic
        thr2 = squared_thresholds(position_threshold, normal_threshold, wdt, dst_depth.device)
        if bool(torch.isfinite(thr2).all()):
            return _fast.fast_reproject(src_values, src_depth, src_normal, dst_depth, dst_normal, warp, thr2,
                                        position_threshold, normal_threshold, sampling)
    return _general.general_reproject(src_values, src_depth, src_normal, dst_depth, dst_normal, warp,
                                      position_threshold, normal_threshold, sampling, soft, temperature, inference)


def _native_thresholds(position_threshold, normal_threshold) -> tuple[float, float]:
    """float32 thr·thr of both thresholds, squared as the torch path squares them."""
    thr2 = squared_thresholds(position_threshold, normal_threshold, torch.float32, "cpu").detach().view(2)
    return float(thr2[0]), float(thr2[1])


def _native_backward(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                     dst_cam_from_world, position_threshold, normal_threshold, sampling, want_confidence=True,
                     rectified=False):
    """The native backend of :func:`backward_reproject` (arguments checked, hard tests, float32 compute on the CPU;
    float32 or float16 images)."""
    warp = _warp(src_K, src_cam_from_world, dst_K, dst_cam_from_world, torch.float32, dst_depth, rectified)
    return _native.reproject(src_values, src_depth, src_normal, warp, dst_depth, dst_normal,
                             _native_thresholds(position_threshold, normal_threshold), sampling == "bilinear",
                             want_confidence)


def _native_temporal(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
                     prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold, alpha, warmup,
                     max_history, sampling):
    """The native backend of :func:`temporal_reproject` (arguments checked): one fused warp-and-blend pass."""
    like = torch.empty((), dtype=torch.float32)
    a = as_scalar(alpha.detach() if isinstance(alpha, Tensor) else alpha, like).clamp(0.0, 1.0)
    warp = compose_warp(prev_K, prev_cam_from_world, K, cam_from_world, torch.float32)
    return _native.temporal_reproject(current_color, history_color, history_len, prev_depth, prev_normal, warp, depth,
                                      normal, _native_thresholds(position_threshold, normal_threshold),
                                      sampling == "bilinear", float(a), bool(warmup),
                                      float(as_scalar(max_history, like)))


def stereo_reproject(
    src_color: Tensor,
    src_depth: Tensor,
    src_normal: Tensor,
    src_K: Tensor,
    src_cam_from_world: Tensor,
    dst_depth: Tensor,
    dst_normal: Tensor,
    dst_K: Tensor,
    dst_cam_from_world: Tensor,
    position_threshold,
    normal_threshold,
    sampling: str = "bilinear",
    soft: bool = False,
    temperature: float = 0.1,
    backend: str = "auto",
    rectified: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Reproject one eye into the other at the same instant (paper §4.1: right → left).

    Args: as :func:`backward_reproject`, with ``src_color`` (B, 3, Hs, Ws), ``backend``: ``"auto"`` |
        ``"torch"`` | ``"native"`` (see :func:`select_backend`; ``STEREOREPRO_BACKEND`` overrides it), and
        ``rectified``: the pair is a parallel rig with equal intrinsics (two taps per pixel; see
        :func:`backward_reproject`).

    Returns:
        color: (B, 3, H, W) reprojected colour, 0 where discarded.
        valid: (B, 1, H, W) bool.
        reason: (B, 1, H, W) uint8 :class:`Reason`.

    Example:
        >>> import torch
        >>> from stereorepro import stereo_reproject, intrinsics_from_fov
        >>> K = intrinsics_from_fov(60.0, 8, 6); T = torch.eye(4)[None]
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> color = torch.rand(1, 3, 6, 8)
        >>> out, valid, reason = stereo_reproject(color, depth, normal, K, T, depth, normal, K, T, 0.01, 0.1)
        >>> bool(torch.equal(out, color)), bool(valid.all()), int(reason.max())
        (True, True, 0)
    """
    check_shape(src_color, ["B", "3", "H", "W"], "src_color")
    check_sampling(sampling)
    check_reprojection_inputs(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                              dst_K, dst_cam_from_world, STEREO_NAMES)
    check_thresholds(position_threshold, normal_threshold)
    return warp_values(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                       dst_cam_from_world, position_threshold, normal_threshold, sampling, soft, temperature, backend,
                       rectified)


def warp_values(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                dst_cam_from_world, position_threshold, normal_threshold, sampling="bilinear", soft=False,
                temperature=0.1, backend="auto", rectified=False) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`backward_reproject` without the confidence map (the native kernel then does not write it), arguments
    assumed checked: (values (B, C, H, W), valid, reason (B, 1, H, W)). Used by :func:`stereo_reproject` and the
    stereo step of :class:`~stereorepro.accumulate.SpatiotemporalReprojection`."""
    if _is_empty(dst_depth):
        return _empty_outputs(src_values, dst_depth)
    args = (src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
            dst_cam_from_world, position_threshold, normal_threshold, sampling)
    if select_backend(backend, (src_values, src_depth, src_normal, dst_depth, dst_normal),
                      (src_K, src_cam_from_world, dst_K, dst_cam_from_world, position_threshold, normal_threshold),
                      soft) == "native":
        values, valid, reason, _ = _native_backward(*args, want_confidence=False, rectified=rectified)
    else:
        values, valid, reason, _ = _torch_backward(*args, soft, temperature, rectified=rectified)
    return values, valid, reason


def _is_empty(dst_depth: Tensor) -> bool:
    """True for a destination without pixels (B = 0, H = 0 or W = 0): the ops return empty outputs."""
    return not tracing() and dst_depth.numel() == 0


def _empty_outputs(values_like: Tensor, dst_depth: Tensor, confidence: bool = False) -> tuple[Tensor, ...]:
    """(values (B, C, H, W), valid, reason[, confidence] (B, 1, H, W)) for an empty destination."""
    B, _, H, W = dst_depth.shape
    dev = dst_depth.device
    out = (values_like.new_zeros(B, values_like.shape[1], H, W), torch.zeros(B, 1, H, W, dtype=torch.bool, device=dev),
           torch.zeros(B, 1, H, W, dtype=torch.uint8, device=dev))
    if confidence:
        out += (torch.zeros(B, 1, H, W, dtype=compute_dtype(values_like, dst_depth), device=dev),)
    return out


def _check_blend_scalars(alpha, max_history) -> None:
    check_scalar(alpha, "alpha")
    check_scalar(max_history, "max_history", 1.0, allow_inf=True)


def temporal_blend(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    confidence: Tensor,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
) -> tuple[Tensor, Tensor]:
    """Blend a (reprojected) history into the current frame: the paper's 20 % exponential moving average.

    ``a = max(1 / (n + 1), alpha)`` with ``warmup`` (a running mean until the EMA weight is reached, as in BMFR,
    the paper's group's code), else ``a = alpha``; ``out = (1 − a)·history + a·current``. Where the history is
    discarded the output restarts from the current sample with ``n = 1``. With hard tests ``confidence`` is the
    valid mask (0/1); with soft tests it is the accepted weight and the output mixes
    ``confidence·blend + (1 − confidence)·current``.

    Args:
        current_color: (B, C, H, W) this frame's samples.
        history_color: (B, C, H, W) history already warped into this frame.
        history_len: (B, 1, H, W) accumulated sample count n of the warped history (float).
        confidence: (B, 1, H, W) bool valid mask, or float in [0, 1].
        alpha: minimum weight of the current frame, in (0, 1] (float or 0-d tensor; learnable): a finite number,
            clamped to [0, 1] (a learnable alpha may step outside); NaN or ±inf raise ValueError.
        warmup: use ``max(1/(n+1), alpha)`` instead of a fixed ``alpha``.
        max_history: cap of n, a number >= 1 (``inf``: no cap).

    A negative or NaN ``history_len`` counts as no history (n = 0). The output colour is finite wherever
    ``current_color`` is (a non-finite history never leaks; a non-finite current sample passes through where the
    history is discarded, as the renderer produced it).

    Returns:
        color: (B, C, H, W), dtype of ``current_color``.
        history_len: (B, 1, H, W) float, the new n (1 where restarted, capped at ``max_history``).
    """
    if not tracing():
        _check_blend_scalars(alpha, max_history)
    wdt = compute_dtype(current_color, history_color)
    cur = current_color.to(wdt)
    hist = history_color.to(wdt)
    n = history_len.to(wdt)
    n = torch.where(n > 0, n, torch.zeros((), dtype=wdt, device=n.device))  # negative and NaN: no history
    one = torch.ones((), dtype=wdt, device=cur.device)
    a_min = as_scalar(alpha, n).clamp(0.0, 1.0)
    a = torch.maximum(1.0 / (n + 1.0), a_min) if warmup else a_min.expand_as(n)
    # a == 1 gives exactly the current sample, even where the history is not finite
    blended = torch.where(a >= 1.0, cur, (1.0 - a) * hist + a * cur)
    n_next = torch.minimum(n + 1.0, as_scalar(max_history, n))
    if confidence.dtype == torch.bool:
        out = torch.where(confidence, blended, cur)
        n_out = torch.where(confidence, n_next, one)
    else:
        s = confidence.to(wdt)
        keep = s > 0
        out = torch.where(keep, s * torch.where(keep, blended, cur) + (1.0 - s) * cur, cur)
        n_out = torch.where(keep, s * n_next + (1.0 - s), one)
    return out.to(current_color.dtype), n_out


def temporal_reproject(
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
    position_threshold,
    normal_threshold,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
    sampling: str = "bilinear",
    soft: bool = False,
    temperature: float = 0.1,
    backend: str = "auto",
    return_reason: bool = False,
    motion: Tensor | None = None,
    motion_world: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Temporal accumulation: warp the previous frame's history into this frame and blend (paper §4.1).

    Args:
        current_color: (B, 3, H, W) this frame's 1-spp colour.
        depth, normal: (B, 1, H, W), (B, 3, H, W) this frame's G-buffer.
        K, cam_from_world: (B, 3, 3), (B, 4, 4) this frame's camera.
        history_color: (B, 3, Hp, Wp) accumulated colour of the previous frame.
        history_len: (B, 1, Hp, Wp) its sample count (float; 0 = no history).
        prev_depth, prev_normal, prev_K, prev_cam_from_world: the previous frame's G-buffer and camera.
        position_threshold, normal_threshold, sampling, soft, temperature: see :func:`backward_reproject`.
        alpha, warmup, max_history: see :func:`temporal_blend`.
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` (see :func:`select_backend`).
        return_reason: also return the discard reasons of the history.
        motion: optional (B, 2, H, W) screen-space motion to the previous frame in pixels (``prev_pixel = pixel +
            motion``, e.g. :attr:`~stereorepro.render.RenderResult.motion`): the history is read there instead of
            where the cameras alone put it, so objects that move independently of the camera keep their history.
        motion_world: optional (B, 3, H, W) world-space motion of the surface to the previous frame (``P_prev = P
            + motion_world``): the position test compares the history with the moved point (zeros if omitted:
            static geometry). See :func:`backward_reproject`; with motion the op runs on torch's general path.

    Returns:
        color: (B, 3, H, W) accumulated colour.
        history_len: (B, 1, H, W) float sample count for the next frame.
        valid: (B, 1, H, W) bool, where the history was kept.
        reason: (B, 1, H, W) uint8 :class:`Reason` of the history's discards (only with ``return_reason``; the
            native backend then warps and blends in two passes, with the same results).
    """
    bind: dict = {}
    check_shape(current_color, ["B", "3", "H", "W"], "current_color", bind)
    check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    bind_p: dict = {"B": bind.get("B")} if bind else {}
    check_shape(history_color, ["B", "3", "H", "W"], "history_color", bind_p)
    check_shape(history_len, ["B", "1", "H", "W"], "history_len", bind_p)
    check_floating(current_color, "current_color")
    check_floating(history_len, "history_len")
    check_reprojection_inputs(history_color, prev_depth, prev_normal, prev_K, prev_cam_from_world, depth, normal, K,
                  cam_from_world, TEMPORAL_NAMES)
    check_sampling(sampling)
    if not tracing():
        check_thresholds(position_threshold, normal_threshold)
        _check_blend_scalars(alpha, max_history)
        check_motion(motion, motion_world, depth, "motion", "motion_world")
    if _is_empty(depth):
        color, valid, reason = _empty_outputs(current_color, depth)
        n = torch.zeros(depth.shape, dtype=compute_dtype(history_color, history_len), device=depth.device)
        return (color, n, valid, reason) if return_reason else (color, n, valid)
    images = (current_color, depth, normal, history_color, history_len, prev_depth, prev_normal)
    others = (K, cam_from_world, prev_K, prev_cam_from_world, position_threshold, normal_threshold, alpha)
    native = select_backend(backend, images, others, soft, motion is not None) == "native"
    if native and not return_reason:
        return _native_temporal(current_color, depth, normal, K, cam_from_world, history_color, history_len,
                                prev_depth, prev_normal, prev_K, prev_cam_from_world, position_threshold,
                                normal_threshold, alpha, warmup, max_history, sampling)
    work = compute_dtype(history_color, history_len)
    values = torch.cat([history_color.to(work), history_len.to(work)], 1)  # colour and n ride together
    args = (values, prev_depth, prev_normal, prev_K, prev_cam_from_world, depth, normal, K, cam_from_world,
            position_threshold, normal_threshold, sampling)
    if native:
        warped, valid, reason, _ = _native_backward(*args, want_confidence=False)
        confidence = valid
    else:
        warped, valid, reason, den = _torch_backward(*args, soft, temperature, motion, motion_world)
        confidence = den if soft else valid
    # exporting the reprojection's export formulation: its blend too (the history it warps is finite)
    blend = _lean.lean_blend if not native and _exporting_lean(soft, motion) else temporal_blend
    color, n = blend(current_color, warped[:, :3], warped[:, 3:4], confidence, alpha, warmup, max_history)
    return (color, n, valid, reason) if return_reason else (color, n, valid)
