"""The reprojection ops as pure tensor functions (paper §4.1), and the rule that picks their implementation.

For every destination pixel: unproject it with the destination depth, move it into the source camera, project
it, and read the 2×2 bilinear taps around that point in the source image (or the one nearest tap). A tap is
**accepted** only if

1. it lies inside the source frame,
2. the source pixel has a surface (see :func:`stereorepro.camera.has_surface`),
3. ``|P_src − P_dst| <= position_threshold`` (scene units; both points in the source camera's frame),
4. ``|N_src − N_dst| <= normal_threshold`` (unit world-space shading normals), and
5. its values are finite (policy: a NaN/Inf sample is rejected like an occluded one, so it never leaks).
   Non-finite *normal components* (source or destination) are read as zero, so a normal with one is no longer a
   unit vector: it fails the normal test at ordinary thresholds and is reported as ``NORMAL``.

Accepted bilinear weights are renormalised by their sum; a pixel is ``valid`` when the accepted weight is > 0.

``sampling="catmull_rom"`` (NVIDIA NRD's rule for history reads): the same bilinear pass, then, where all 16
source pixels of the 4×4 footprint around the bilinear taps pass tests 1–5, the separable 16-tap Catmull-Rom sum
(Keys' cubic with a = −0.5; torch's ``grid_sample(mode="bicubic")`` is a = −0.75) replaces the bilinear value,
clamped at 0 per channel of the result (for non-negative quantities: radiance, sample counts). Elsewhere the pixel
keeps its bilinear value with renormalised accepted weights, so ``valid``, ``reason`` and ``confidence`` are the
bilinear ones. All 16 taps rather than NRD's 12 (corners dropped, weights renormalised): NRD drops the corners to
save texture fetches on a GPU (five bilinear fetches), a cost our gathers do not have, and the full tensor product
is the exact separable filter that reproduces linear and quadratic signals (the 12-tap form does not); every
implementation uses the same 16 taps and the same order of operations. Carried extra channels (the temporal op's
history length) are sampled the same way as colour, so that a pixel's colour and its count come from one footprint.
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
from .._checks import (
    STEREO_NAMES,
    check_blend,
    check_blend_inputs,
    check_device,
    check_floating,
    check_motion,
    check_sampling,
    check_shape,
    check_thresholds,
    tracing,
)
from ..camera import compose_warp, rectify_warp
from ..errors import ShapeError
from . import _fast, _general, _lean, _native
from ._flat import given_keywords, reject_extra_arguments, stereo_views, temporal_views, warn_flat_form
from ._constants import NATIVE_MAX_CHANNELS
from ._general import as_scalar, compute_dtype, inference_only, squared_thresholds
from .view import (
    Blend,
    History,
    ReprojectionResult,
    TemporalResult,
    Thresholds,
    View,
    _check_footprint_weighting,
    _check_history_rounding,
    _check_position_test,
)

__all__ = [
    "BACKENDS",
    "backward_reproject",
    "stereo_reproject",
    "temporal_blend",
    "temporal_reproject",
    "select_backend",
    "native_unsupported",
    "warp_values",
    "reproject_history",
    "as_thresholds",
    "stereo_views",
    "temporal_views",
]

#: Backend names the ops accept (:data:`stereorepro._backend.OP_NAMES`; ``STEREOREPRO_BACKEND`` also accepts
#: ``numpy`` and ``reference`` for torch).
BACKENDS = _backend.OP_NAMES

#: Whether the torch backend may take the inference fast path (tests switch it off to exercise the general path).
FAST_PATH = True

#: Whether ONNX export writes the export formulation (:mod:`._lean`) for hard tests, motion vectors or not
#: (False: the general path, traced as it is; the benchmark compares both).
EXPORT_LEAN = True


def native_unsupported(
    images: Iterable[Tensor], others: Iterable = (), soft: bool = False, motion: bool = False, channels: int = 0
) -> str | None:
    """Why the native kernels cannot run these inputs, or None when they can.

    Args:
        images: image tensors (colours, depths, normals, history length, motion vectors): float32 or float16, each
            on its own (float16 is read as it is and computed in float32, as torch computes it).
        others: other inputs (cameras, thresholds, alpha): only device and autograd are checked.
        soft: soft accept tests (torch only).
        motion: motion vectors given (read by the native kernels too; their tensors belong in ``images``).
        channels: value channels carried per pixel (at most :data:`~._constants.NATIVE_MAX_CHANNELS` natively).

    Examples:
        >>> import torch
        >>> from stereorepro.reproject.functional import native_unsupported
        >>> reason = native_unsupported([torch.ones(1, 1, 2, 2, dtype=torch.float64)])
        >>> "float64 run on torch" in reason
        True
    """
    images = list(images)
    tensors = images + [x for x in others if isinstance(x, Tensor)]
    if not _native.available():
        return "the native core stereorepro._core (with `reproject`) is not built or not importable"
    if tracing():
        return "tracing / ONNX export / torch.compile need the torch path"
    if soft:
        return "soft=True (differentiable thresholds) is implemented in torch only"
    if channels > NATIVE_MAX_CHANNELS:
        return f"the native kernels carry at most {NATIVE_MAX_CHANNELS} value channels, got {channels}"
    devices = {str(t.device) for t in tensors if t.device.type != "cpu"}
    if devices:
        return f"the native kernels run on the CPU only, got tensors on {sorted(devices)}"
    dtypes = {t.dtype for t in images if t.dtype not in _native.DTYPES}
    if dtypes:
        return (
            "the native kernels read float32 or float16 images only (bfloat16 and float64 run on torch), got "
            f"images of dtype {sorted(map(str, dtypes))}"
        )
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return "an input requires grad (autograd needs the torch path; use torch.no_grad() for native)"
    return None


def select_backend(
    backend: str,
    images: Iterable[Tensor],
    others: Iterable = (),
    soft: bool = False,
    motion: bool = False,
    channels: int = 0,
) -> str:
    """Resolve ``backend`` (``"auto"`` | ``"torch"`` | ``"native"``) to ``"torch"`` or ``"native"``.

    * ``STEREOREPRO_BACKEND`` overrides ``backend`` when set (:mod:`stereorepro._backend`: the rule the tracer
      follows too);
    * ``"torch"`` always runs torch;
    * ``"auto"`` runs native when :func:`native_unsupported` finds nothing against it: ``_core`` built, every
      tensor on the CPU, image tensors float32, hard tests, no autograd, and not tracing / exporting / compiling;
    * ``"native"`` runs native and raises RuntimeError saying why when it is not possible;
    * tracing, ONNX export and ``torch.compile`` always use torch, whatever was asked.

    Examples:
        >>> import torch
        >>> from stereorepro.reproject.functional import select_backend
        >>> select_backend("torch", [torch.ones(1, 1, 2, 2)])
        'torch'
        >>> select_backend("auto", [torch.ones(1, 1, 2, 2, dtype=torch.float64)])  # float64 images run on torch
        'torch'
    """
    chosen = _backend.resolve(
        backend, BACKENDS, lambda: native_unsupported(images, others, soft, motion, channels), reference_only=tracing()
    )
    return "native" if chosen == "native" else "torch"


def as_thresholds(thresholds) -> Thresholds:
    """``thresholds`` as :class:`Thresholds`: a Thresholds, or a ``(position, normal)`` pair (TypeError otherwise).

    Examples:
        >>> from stereorepro.reproject.functional import as_thresholds
        >>> as_thresholds((0.01, 0.1))
        Thresholds(position=0.01, normal=0.1, temperature=0.1, position_test='distance')
    """
    if isinstance(thresholds, Thresholds):
        return thresholds
    if isinstance(thresholds, (tuple, list)) and len(thresholds) in (2, 3, 4):
        return Thresholds(*thresholds)
    raise TypeError(
        f"thresholds: expected Thresholds(position, normal) or a (position, normal) pair, got "
        f"{type(thresholds).__name__}"
    )


def _as_pair(x, cls, what: str):
    if isinstance(x, cls):
        return x
    required = len(cls._fields) - len(cls._field_defaults) if cls is not Blend else 3  # (alpha, warmup, max_history)
    if isinstance(x, (tuple, list)) and required <= len(x) <= len(cls._fields):
        return cls(*x)
    raise TypeError(f"{what}: expected {cls.__name__}({', '.join(cls._fields)}), got {type(x).__name__}")


def _check_op_inputs(
    op: str, values: Tensor, values_name: str, channels: str, src: View, dst: View, thr: Thresholds, sampling: str
) -> None:
    """Checks of an op's arguments beyond what each :class:`View` checked at construction: the values against the
    source view, the two views against each other, the sampling and the thresholds."""
    if not isinstance(src, View) or not isinstance(dst, View):
        bad = "src" if not isinstance(src, View) else "dst"
        raise TypeError(f"{op}: {bad} must be a stereorepro.View, got {type(src if bad == 'src' else dst).__name__}")
    check_sampling(sampling)
    if tracing():
        return
    check_shape(
        values, ["B", channels, "H", "W"], values_name, {"B": src.batch_size, "H": src.height, "W": src.width}, False
    )
    if values.shape[-2] == 0 or values.shape[-1] == 0:
        raise ShapeError(f"{values_name}: the source image needs at least one pixel, got shape {tuple(values.shape)}")
    check_floating(values, values_name, False)
    if dst.batch_size != src.batch_size:
        raise ShapeError(
            f"{op}: the views' batch sizes differ: {src.batch_size} (source) and {dst.batch_size} (destination)"
        )
    check_device({values_name: values, "source view": src.depth, "destination view": dst.depth}, op, False)
    check_thresholds(thr.position, thr.normal, False)
    _check_position_test(thr.position_test, f"{op}: thresholds")


def backward_reproject(
    values: Tensor,
    src: View,
    dst: View,
    thresholds,
    *legacy_args,
    sampling: str = "bilinear",
    soft: bool = False,
    backend: str = "auto",
    rectified: bool = False,
    **legacy_kwargs,
) -> ReprojectionResult:
    """Backward-warp ``values`` of the source view into the destination view with per-tap discard tests.

    Args:
        values: (B, C, Hs, Ws) values to carry (colour; extra channels such as history length ride along).
        src: the source :class:`View` (Hs, Ws), whose pixels ``values`` are.
        dst: the destination :class:`View` (H, W). Its ``motion`` (B, 2, H, W), when given, places the taps:
            ``src_pixel = dst_pixel + motion`` instead of where the cameras put the destination point (non-finite
            motion: ``OUT_OF_FRAME``), and the position test compares the source tap with ``P + motion_world``
            (a moving object is kept, a disocclusion still rejected). Every implementation reads them (native:
            float32 or float16 motion); 2.5D motion (screen motion + view-z delta) converts to ``motion_world``
            with :func:`stereorepro.camera.world_motion_from_view_z`.
        thresholds: :class:`Thresholds` or ``(position, normal)``: max |P_src − P_dst| in scene units and max
            |N_src − N_dst| between unit normals, each a number or one-element tensor >= 0.
        sampling: ``"bilinear"`` (2×2 taps, the paper's choice), ``"nearest"`` (one tap) or ``"catmull_rom"``
            (4×4 Catmull-Rom where all 16 footprint taps pass the tests, else bilinear; results clamped at 0: see
            the module notes). Every backend and the exported graph.
        soft: replace the position and normal step functions by sigmoids
            ``sigmoid((thr² − d²) / (2·temperature·thr²))`` (``temperature`` of ``thresholds``), so that the output
            is differentiable in the thresholds. ``valid`` and ``reason`` still report the hard decision; soft
            colours are renormalised by ``max(accepted weight, SOFT_DEN_FLOOR)`` so that gradients stay bounded.
        backend: ``"auto"`` | ``"torch"`` | ``"native"``: see :func:`select_backend`.
        rectified: the caller declares a rectified pair (a parallel rig at one instant with equal intrinsics,
            the paper's stereo case): every destination pixel reads its own source row, with the rounding of
            real cameras removed (:func:`stereorepro.camera.rectify_warp`, which raises CameraError for cameras
            that are not such a pair); two taps per pixel instead of four, also in the exported ONNX graph. Not
            with motion vectors.

    Returns:
        :class:`ReprojectionResult` ``(values (B, C, H, W), valid, reason, confidence (B, 1, H, W))``.

    On the torch backend, hard tests without autograd or tracing take a faster path with identical outputs
    (:mod:`stereorepro.reproject._fast`), motion vectors or not; gradients, tracing, soft tests and infinite
    thresholds take the general one (:mod:`stereorepro.reproject._general`), and ONNX export with hard tests writes
    the export formulation (:mod:`stereorepro.reproject._lean`).

    The flat form ``backward_reproject(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth,
    dst_normal, dst_K, dst_cam_from_world, position_threshold, normal_threshold, ...)`` still works for one
    release, with a DeprecationWarning, and returns a plain 4-tuple.

    Examples:
        >>> import torch
        >>> from stereorepro import View, backward_reproject, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> values = torch.rand(1, 5, 6, 8)
        >>> out = backward_reproject(values, view, view, (0.01, 0.1))
        >>> bool(torch.equal(out.values, values)), bool(out.valid.all()), float(out.confidence.min())
        (True, True, 1.0)
    """
    if not isinstance(src, View):
        warn_flat_form(
            "backward_reproject",
            "backward_reproject(values, src: View, dst: View, (position_threshold, normal_threshold), ...)",
        )
        return _flat_backward(
            values,
            src,
            dst,
            thresholds,
            *legacy_args,
            **given_keywords(
                sampling=(sampling, "bilinear"),
                soft=(soft, False),
                backend=(backend, "auto"),
                rectified=(rectified, False),
            ),
            **legacy_kwargs,
        )
    reject_extra_arguments("backward_reproject", legacy_args, legacy_kwargs)
    thr = as_thresholds(thresholds)
    _check_op_inputs("backward_reproject", values, "values", "C", src, dst, thr, sampling)
    if rectified and dst.motion is not None:
        raise ValueError(
            "backward_reproject: rectified=True declares a same-instant stereo pair; it cannot be "
            "combined with motion vectors (dst.motion)"
        )
    return warp_values(values, src, dst, thr, sampling, soft, backend, rectified)


def warp_values(
    values: Tensor,
    src: View,
    dst: View,
    thresholds: Thresholds,
    sampling: str = "bilinear",
    soft: bool = False,
    backend: str = "auto",
    rectified: bool = False,
    confidence: bool = True,
) -> ReprojectionResult:
    """:func:`backward_reproject` of arguments the caller has checked; without ``confidence`` the result's
    confidence is None (the native kernel then does not write it). The stereo op, the temporal op and the
    combined scheme's stereo step call it.

    Examples:
        >>> import torch
        >>> from stereorepro import Thresholds, View, intrinsics_from_fov
        >>> from stereorepro.reproject.functional import warp_values
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> values = torch.rand(1, 2, 6, 8, generator=torch.Generator().manual_seed(0))
        >>> out = warp_values(values, view, view, Thresholds(0.01, 0.1), confidence=False)
        >>> bool(torch.equal(out.values, values)), bool(out.valid.all()), out.confidence is None
        (True, True, True)
    """
    if _is_empty(dst.depth):
        return ReprojectionResult(*_empty_outputs(values, dst.depth, confidence))
    images = (values, src.depth, src.normal, dst.depth, dst.normal) + _motion_of(dst)
    others = (src.K, src.cam_from_world, dst.K, dst.cam_from_world, thresholds.position, thresholds.normal)
    if select_backend(backend, images, others, soft, dst.motion is not None, values.shape[1]) == "native":
        out = _native_backward(values, src, dst, thresholds, sampling, confidence, rectified)
    else:
        out = _torch_backward(values, src, dst, thresholds, sampling, soft, rectified)
    return ReprojectionResult(out[0], out[1], out[2], out[3] if confidence else None)


def _motion_of(view: View) -> tuple[Tensor, ...]:
    """The motion tensors ``view`` carries (none, motion, or motion and motion_world)."""
    return tuple(x for x in (view.motion, view.motion_world) if x is not None)


def _exporting_lean(soft: bool) -> bool:
    """Whether this call is being exported in the export formulation (:mod:`._lean`): hard tests,
    :data:`EXPORT_LEAN`."""
    return EXPORT_LEAN and not soft and torch.onnx.is_in_onnx_export()


def _warp(src: View, dst: View, dtype: torch.dtype, rectified: bool):
    """The composed warp (:func:`compose_warp`), rectified when the caller declares a rectified pair."""
    warp = compose_warp(src.K, src.cam_from_world, dst.K, dst.cam_from_world, dtype)
    return rectify_warp(warp, *dst.depth.shape[-2:]) if rectified else warp


def _torch_backward(
    values: Tensor, src: View, dst: View, thr: Thresholds, sampling: str, soft: bool, rectified: bool = False
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The torch backend of :func:`backward_reproject` (arguments checked): the fast path where it applies, and
    the export formulation (:mod:`._lean`) while exporting to ONNX with hard tests."""
    wdt = compute_dtype(values, src.depth, src.normal, dst.depth, dst.normal)
    warp = _warp(src, dst, wdt, rectified)
    motion, motion_world = dst.motion, dst.motion_world
    plane = thr.position_test == "plane"
    src_rotation = src.cam_from_world[:, :3, :3] if motion is not None or plane else None
    if _exporting_lean(soft):
        return _lean.lean_reproject(
            values,
            src.depth,
            src.normal,
            dst.depth,
            dst.normal,
            warp,
            thr.position,
            thr.normal,
            sampling,
            rectified,
            motion,
            motion_world,
            src_rotation,
            thr.position_test,
        )
    inference = inference_only(
        (
            values,
            src.depth,
            src.normal,
            dst.depth,
            dst.normal,
            src.K,
            dst.K,
            src.cam_from_world,
            dst.cam_from_world,
            thr.position,
            thr.normal,
            motion,
            motion_world,
        )
    )
    if inference and not soft and FAST_PATH:  # the usual inference case: same results, less memory traffic
        thr2 = squared_thresholds(thr.position, thr.normal, wdt, dst.depth.device)
        if bool(torch.isfinite(thr2).all()):
            return _fast.fast_reproject(
                values,
                src.depth,
                src.normal,
                dst.depth,
                dst.normal,
                warp,
                thr2,
                thr.position,
                thr.normal,
                sampling,
                motion,
                motion_world,
                src_rotation,
                thr.position_test,
            )
    return _general.general_reproject(
        values,
        src.depth,
        src.normal,
        dst.depth,
        dst.normal,
        warp,
        thr.position,
        thr.normal,
        sampling,
        soft,
        thr.temperature,
        inference,
        motion,
        motion_world,
        src_rotation,
        thr.position_test,
    )


def _native_thresholds(thr: Thresholds) -> tuple[float, float]:
    """float32 thr·thr of both thresholds, squared as the torch path squares them."""
    thr2 = squared_thresholds(thr.position, thr.normal, torch.float32, "cpu").detach().view(2)
    return float(thr2[0]), float(thr2[1])


def _native_backward(
    values: Tensor,
    src: View,
    dst: View,
    thr: Thresholds,
    sampling: str,
    want_confidence: bool = True,
    rectified: bool = False,
):
    """The native backend of :func:`backward_reproject` (arguments checked, hard tests, float32 compute on the CPU;
    float32 or float16 images)."""
    warp = _warp(src, dst, torch.float32, rectified)
    return _native.reproject(
        values,
        src.depth,
        src.normal,
        warp,
        dst.depth,
        dst.normal,
        _native_thresholds(thr),
        sampling != "nearest",
        want_confidence,
        dst.motion,
        dst.motion_world,
        src.cam_from_world[:, :3, :3],
        sampling == "catmull_rom",
        plane=thr.position_test == "plane",
    )


def _native_temporal(
    current_color: Tensor, view: View, history: History, prev_view: View, thr: Thresholds, blend: Blend, sampling: str
):
    """The native backend of :func:`temporal_reproject` (arguments checked): one fused warp-and-blend pass."""
    like = torch.empty((), dtype=torch.float32)
    alpha = blend.alpha
    a = as_scalar(alpha.detach() if isinstance(alpha, Tensor) else alpha, like).clamp(0.0, 1.0)
    rounding = blend.history_rounding
    warp = compose_warp(prev_view.K, prev_view.cam_from_world, view.K, view.cam_from_world, torch.float32)
    return _native.temporal_reproject(
        current_color,
        history.color,
        history.length,
        prev_view.depth,
        prev_view.normal,
        warp,
        view.depth,
        view.normal,
        _native_thresholds(thr),
        sampling != "nearest",
        float(a),
        bool(blend.warmup),
        float(_length_cap(blend.max_history, a, rounding)),
        view.motion,
        view.motion_world,
        prev_view.cam_from_world[:, :3, :3],
        rounding == "bmfr",
        sampling == "catmull_rom",
        bool(blend.footprint_weighting),
        plane=thr.position_test == "plane",
    )


def stereo_reproject(
    color: Tensor,
    src: View,
    dst: View,
    thresholds,
    *legacy_args,
    sampling: str = "bilinear",
    soft: bool = False,
    backend: str = "auto",
    rectified: bool = False,
    **legacy_kwargs,
) -> ReprojectionResult:
    """Reproject one eye into the other at the same instant (paper §4.1: right → left).

    Args:
        color: (B, 3, Hs, Ws) the source eye's colour.
        src, dst: the source and destination :class:`View` (their ``motion`` is not used: same instant).
        thresholds, sampling, soft, backend, rectified: see :func:`backward_reproject` (``rectified``: two taps
            per pixel for a parallel rig with equal intrinsics).

    Returns:
        :class:`ReprojectionResult` ``(values (B, 3, H, W) colour, 0 where discarded; valid (B, 1, H, W) bool;
        reason (B, 1, H, W) uint8 Reason; confidence None)``.

    The flat form ``stereo_reproject(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth,
    dst_normal, dst_K, dst_cam_from_world, position_threshold, normal_threshold, ...)`` still works for one
    release, with a DeprecationWarning, and returns a plain 3-tuple.

    Examples:
        >>> import torch
        >>> from stereorepro import View, stereo_reproject, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> color = torch.rand(1, 3, 6, 8)
        >>> out, valid, reason, _ = stereo_reproject(color, view, view, (0.01, 0.1))
        >>> bool(torch.equal(out, color)), bool(valid.all()), int(reason.max())
        (True, True, 0)
    """
    if not isinstance(src, View):
        warn_flat_form(
            "stereo_reproject",
            "stereo_reproject(src_color, src: View, dst: View, (position_threshold, normal_threshold), ...)",
        )
        return _flat_stereo(
            color,
            src,
            dst,
            thresholds,
            *legacy_args,
            **given_keywords(
                sampling=(sampling, "bilinear"),
                soft=(soft, False),
                backend=(backend, "auto"),
                rectified=(rectified, False),
            ),
            **legacy_kwargs,
        )
    reject_extra_arguments("stereo_reproject", legacy_args, legacy_kwargs)
    thr = as_thresholds(thresholds)
    _check_op_inputs("stereo_reproject", color, "color", "3", src, dst, thr, sampling)
    return warp_values(color, src, dst.without_motion(), thr, sampling, soft, backend, rectified, confidence=False)


def _is_empty(dst_depth: Tensor) -> bool:
    """True for a destination without pixels (B = 0, H = 0 or W = 0): the ops return empty outputs."""
    return not tracing() and dst_depth.numel() == 0


def _empty_outputs(values_like: Tensor, dst_depth: Tensor, confidence: bool = False) -> tuple[Tensor, ...]:
    """(values (B, C, H, W), valid, reason[, confidence] (B, 1, H, W)) for an empty destination."""
    B, _, H, W = dst_depth.shape
    dev = dst_depth.device
    out = (
        values_like.new_zeros(B, values_like.shape[1], H, W),
        torch.zeros(B, 1, H, W, dtype=torch.bool, device=dev),
        torch.zeros(B, 1, H, W, dtype=torch.uint8, device=dev),
    )
    if confidence:
        out += (torch.zeros(B, 1, H, W, dtype=compute_dtype(values_like, dst_depth), device=dev),)
    return out


def temporal_blend(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    confidence: Tensor,
    alpha=0.2,
    warmup: bool = True,
    max_history: float = 255.0,
    history_rounding: str = "none",
) -> History:
    """Blend a (reprojected) history into the current frame: the paper's 20 % exponential moving average.

    ``a = max(1 / (n + 1), alpha)`` with ``warmup`` (a running mean until the EMA weight is reached, as in BMFR,
    the paper's group's code), else ``a = alpha``; ``out = (1 − a)·history + a·current``. Where the history is
    discarded the output restarts from the current sample with ``n = 1``. With hard tests ``confidence`` is the
    valid mask (0/1); with soft tests it is the accepted weight and the output mixes
    ``confidence·blend + (1 − confidence)·current``.

    ``history_rounding`` says how the new length is stored where the history is kept:

    * ``"none"`` (default): the float ``min(n + 1, max_history)``;
    * ``"bmfr"``: BMFR's integer count (Koskela et al. 2019, kernel ``accumulate_noisy_data``, which keeps it in
      an 8-bit buffer): ``min(round_half_even(n) + 1, max_history)``, and 1 where ``a = 1`` (``alpha >= 1``: the
      history is not used). ``n`` is the warped length, i.e. the bilinear interpolation over the accepted taps
      (weights renormalised) of the stored integer lengths, which BMFR also interpolates; the rounding is of
      that interpolated count, *before* the new sample's ``+ 1``. The colour weight ``a`` is computed from the
      unrounded ``n``, as BMFR computes it (``max(1/(n + 1), alpha)``): rounding changes only what the next frame
      reads. BMFR's cap is the default ``max_history = 255`` (an integer cap keeps the lengths integers; an
      ``inf`` one lets them grow). With soft tests the rounded length is mixed like the float one
      (``confidence·n_next + 1 − confidence``). ``round`` has a zero gradient: the colour's gradient is that of
      ``"none"`` on the same inputs, the length's is zero. Where histories start from :meth:`History.empty` and
      every step rounds, the lengths stay integers and this op stores what BMFR would store.

    Args:
        current_color: (B, C, H, W) this frame's samples.
        history_color: (B, C, H, W) history already warped into this frame.
        history_len: (B, 1, H, W) accumulated sample count n of the warped history (float).
        confidence: (B, 1, H, W) bool valid mask, or float in [0, 1].
        alpha: minimum weight of the current frame, in (0, 1] (float or 0-d tensor; learnable): a finite number,
            clamped to [0, 1] (a learnable alpha may step outside); NaN or ±inf raise ValueError.
        warmup: use ``max(1/(n+1), alpha)`` instead of a fixed ``alpha``.
        max_history: cap of n, a number >= 1 (``inf``: no cap).
        history_rounding: ``"none"`` or ``"bmfr"`` (see above); anything else raises ParameterError.

    A negative or NaN ``history_len`` counts as no history (n = 0). The output colour is finite wherever
    ``current_color`` is (a non-finite history never leaks; a non-finite current sample passes through where the
    history is discarded, as the renderer produced it).

    Returns:
        :class:`History` ``(color (B, C, H, W) in the dtype of current_color, length (B, 1, H, W) float)``: the
        new n is 1 where restarted, capped at ``max_history``.

    Examples:
        >>> import torch
        >>> from stereorepro import temporal_blend
        >>> cur, hist = torch.ones(1, 3, 2, 2), torch.zeros(1, 3, 2, 2)
        >>> out = temporal_blend(cur, hist, torch.full((1, 1, 2, 2), 9.0), torch.ones(1, 1, 2, 2, dtype=torch.bool))
        >>> round(float(out.color[0, 0, 0, 0]), 6), float(out.length[0, 0, 0, 0])
        (0.2, 10.0)
        >>> n = torch.full((1, 1, 2, 2), 2.5)  # an interpolated length between taps of 2 and 3 samples
        >>> valid = torch.ones(1, 1, 2, 2, dtype=torch.bool)
        >>> float(temporal_blend(cur, hist, n, valid).length[0, 0, 0, 0])  # the float count
        3.5
        >>> float(temporal_blend(cur, hist, n, valid, history_rounding="bmfr").length[0, 0, 0, 0])  # 2.5 -> 2, + 1
        3.0
    """
    _check_history_rounding(history_rounding, "temporal_blend")
    if not tracing():
        check_blend(alpha, max_history)
        check_blend_inputs(current_color, history_color, history_len, confidence)
    return _blend_checked(
        current_color, history_color, history_len, confidence, alpha, warmup, max_history, history_rounding
    )


def _blend_checked(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    confidence: Tensor,
    alpha,
    warmup: bool,
    max_history,
    history_rounding: str = "none",
) -> History:
    """:func:`temporal_blend` of arguments the caller has checked (the temporal step's own warped history)."""
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
    n_next = torch.minimum(_stored_length(n, history_rounding), _length_cap(max_history, a_min, history_rounding))
    if confidence.dtype == torch.bool:
        out = torch.where(confidence, blended, cur)
        n_out = torch.where(confidence, n_next, one)
    else:
        s = confidence.to(wdt)
        keep = s > 0
        out = torch.where(keep, s * torch.where(keep, blended, cur) + (1.0 - s) * cur, cur)
        n_out = torch.where(keep, s * n_next + (1.0 - s), one)
    return History(out.to(current_color.dtype), n_out)


def _stored_length(n: Tensor, history_rounding: str) -> Tensor:
    """The length a kept history stores before the cap: ``n + 1``, or ``round_half_even(n) + 1`` (``"bmfr"``)."""
    return (torch.round(n) if history_rounding == "bmfr" else n) + 1.0


def _length_cap(max_history, a_min: Tensor, history_rounding: str) -> Tensor:
    """The cap of the stored length: ``max_history``; with ``"bmfr"`` 1 where ``alpha >= 1`` (BMFR stores one
    sample when its blend weight is 1; with warm-up the weight also reaches 1 at ``n = 0``, where the rounded
    length is 1 already)."""
    cap = as_scalar(max_history, a_min)
    if history_rounding != "bmfr":
        return cap
    return torch.where(a_min >= 1.0, torch.ones((), dtype=cap.dtype, device=cap.device), cap)


def _footprint_weighted(n: Tensor, den: Tensor) -> Tensor:
    """The warped length ``n`` scaled by the footprint quality: ``n·(0.5 + 0.5·q)``, ``q = clamp(den, 0, 1)`` the
    accepted bilinear weight before renormalisation (the native kernel computes the same float operations)."""
    q = den.to(n.dtype).clamp(0.0, 1.0)
    return n * (0.5 + 0.5 * q)


def temporal_reproject(
    current_color: Tensor,
    view: View,
    history,
    prev_view: View,
    thresholds,
    *legacy_args,
    blend: Blend = Blend(),
    sampling: str = "bilinear",
    soft: bool = False,
    backend: str = "auto",
    return_reason: bool = False,
    **legacy_kwargs,
) -> TemporalResult:
    """Temporal accumulation: warp the previous frame's history into this frame and blend (paper §4.1).

    Args:
        current_color: (B, 3, H, W) this frame's 1-spp colour.
        view: this frame's :class:`View` (H, W). Its ``motion`` (B, 2, H, W), when given, is the screen-space
            motion to the previous frame (``prev_pixel = pixel + motion``, e.g. a renderer's motion vectors) and
            ``motion_world`` the surface's world motion (``P_prev = P + motion_world``): the history is read
            there, so objects that move independently of the camera keep their history (see
            :func:`backward_reproject`; every backend).
        history: :class:`History` ``(color (B, 3, Hp, Wp), length (B, 1, Hp, Wp))`` of the previous frame (the
            previous call's :attr:`TemporalResult.history`; first frame: :meth:`History.empty`).
        prev_view: the previous frame's :class:`View` (Hp, Wp).
        thresholds, sampling, soft, backend: see :func:`backward_reproject`.
        blend: :class:`Blend` ``(alpha, warmup, max_history, history_rounding)``: see :func:`temporal_blend`
            (``history_rounding="bmfr"``: the stored length is BMFR's integer count, on every backend and in the
            exported graph). ``footprint_weighting=True`` (NVIDIA NRD's footprint quality, every backend and the
            exported graph): the warped length ``n`` is multiplied by ``(1 + q)/2`` before the blend, ``q`` being
            the bilinear weight of the accepted taps of the history's 2×2 footprint *before* renormalisation
            (clamped to [0, 1]; with ``sampling="catmull_rom"`` the same bilinear weight, with ``"nearest"`` 1
            where kept, with ``soft`` the soft weight sum). A pixel whose four taps pass keeps ``n``; one whose
            only accepted tap carries weight ``w`` gets ``n·(1 + w)/2``, at least half. Everything of
            :func:`temporal_blend` then uses the scaled ``n``: the warm-up weight ``max(1/(n + 1), alpha)``, the
            stored ``min(n + 1, max_history)`` (the cap after the scaling) and with ``"bmfr"`` the rounding
            (of the scaled ``n``). Differentiable in the colour as the default (``q`` is a tap weight).
        return_reason: also return the discard reasons of the history (the native backend then warps and blends
            in two passes, with the same results).

    Returns:
        :class:`TemporalResult` ``(color (B, 3, H, W), history_len (B, 1, H, W) float, valid (B, 1, H, W) bool,
        reason (B, 1, H, W) uint8 or None)``.

    The flat form ``temporal_reproject(current_color, depth, normal, K, cam_from_world, history_color,
    history_len, prev_depth, prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold,
    ...)`` still works for one release, with a DeprecationWarning, and returns a plain 3- or 4-tuple.

    Examples:
        >>> import torch
        >>> from stereorepro import History, View, temporal_reproject, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> current = torch.ones(1, 3, 6, 8)
        >>> first = temporal_reproject(current, view, History.empty(view), view, (0.01, 0.1))
        >>> bool(torch.equal(first.color, current)), float(first.history_len.max())
        (True, 1.0)
        >>> second = temporal_reproject(torch.zeros(1, 3, 6, 8), view, first.history, view, (0.01, 0.1))
        >>> float(second.color.max()), float(second.history_len.max())
        (0.5, 2.0)
    """
    if not isinstance(view, View):
        warn_flat_form(
            "temporal_reproject",
            "temporal_reproject(current_color, view: View, history: History, "
            "prev_view: View, (position_threshold, normal_threshold), ...)",
        )
        return _flat_temporal(
            current_color,
            view,
            history,
            prev_view,
            thresholds,
            *legacy_args,
            **given_keywords(
                sampling=(sampling, "bilinear"),
                soft=(soft, False),
                backend=(backend, "auto"),
                return_reason=(return_reason, False),
            ),
            **legacy_kwargs,
        )
    reject_extra_arguments("temporal_reproject", legacy_args, legacy_kwargs)
    thr = as_thresholds(thresholds)
    history = _as_pair(history, History, "temporal_reproject: history")
    blend = _as_pair(blend, Blend, "temporal_reproject: blend")
    check_shape(
        current_color, ["B", "3", "H", "W"], "current_color", {"B": view.batch_size, "H": view.height, "W": view.width}
    )
    check_floating(current_color, "current_color")
    _check_op_inputs("temporal_reproject", history.color, "history.color", "3", prev_view, view, thr, sampling)
    check_shape(
        history.length,
        ["B", "1", "H", "W"],
        "history.length",
        {"B": prev_view.batch_size, "H": prev_view.height, "W": prev_view.width},
    )
    check_floating(history.length, "history.length")
    _check_history_rounding(blend.history_rounding, "temporal_reproject: blend")
    _check_footprint_weighting(blend.footprint_weighting, "temporal_reproject: blend")
    if not tracing():
        check_blend(blend.alpha, blend.max_history)
    return reproject_history(
        current_color, view, history, prev_view, thr, blend, sampling, soft, backend, return_reason
    )


def reproject_history(
    current_color: Tensor,
    view: View,
    history: History,
    prev_view: View,
    thr: Thresholds,
    blend: Blend,
    sampling: str = "bilinear",
    soft: bool = False,
    backend: str = "auto",
    return_reason: bool = False,
) -> TemporalResult:
    """:func:`temporal_reproject` of arguments the caller has checked.

    Examples:
        >>> import torch
        >>> from stereorepro import Blend, History, Thresholds, View, intrinsics_from_fov
        >>> from stereorepro.reproject.functional import reproject_history
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> first = reproject_history(torch.ones(1, 3, 6, 8), view, History.empty(view), view, Thresholds(0.01, 0.1),
        ...                           Blend())
        >>> out = reproject_history(torch.zeros(1, 3, 6, 8), view, first.history, view, Thresholds(0.01, 0.1), Blend())
        >>> float(out.color.max()), float(out.history_len.max())
        (0.5, 2.0)
    """
    if _is_empty(view.depth):
        color, valid, reason = _empty_outputs(current_color, view.depth)
        n = torch.zeros(view.depth.shape, dtype=compute_dtype(*history), device=view.depth.device)
        return TemporalResult(color, n, valid, reason if return_reason else None)
    images = (
        current_color,
        view.depth,
        view.normal,
        history.color,
        history.length,
        prev_view.depth,
        prev_view.normal,
    ) + _motion_of(view)
    others = (view.K, view.cam_from_world, prev_view.K, prev_view.cam_from_world, thr.position, thr.normal, blend.alpha)
    channels = history.color.shape[1] + 1  # the history length rides along
    native = select_backend(backend, images, others, soft, view.motion is not None, channels) == "native"
    if native and not return_reason:
        return TemporalResult(*_native_temporal(current_color, view, history, prev_view, thr, blend, sampling))
    work = compute_dtype(*history)
    values = torch.cat([history.color.to(work), history.length.to(work)], 1)  # colour and n ride together
    footprint = bool(blend.footprint_weighting)
    if native:
        warped, valid, reason, den = _native_backward(values, prev_view, view, thr, sampling, footprint)
        confidence = valid
    else:
        warped, valid, reason, den = _torch_backward(values, prev_view, view, thr, sampling, soft)
        confidence = den if soft else valid
    n_warped = _footprint_weighted(warped[:, 3:4], den) if footprint else warped[:, 3:4]
    # exporting the reprojection's export formulation: its blend too (the history it warps is finite)
    blend_fn = _lean.lean_blend if not native and _exporting_lean(soft) else _blend_checked
    color, n = blend_fn(current_color, warped[:, :3], n_warped, confidence, *blend[:4])
    return TemporalResult(color, n, valid, reason if return_reason else None)


# The flat forms of the ops (deprecated): checks under the flat argument names, then the View forms' code.


def _flat_backward(
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
    soft=False,
    temperature=0.1,
    check=True,
    backend="auto",
    motion=None,
    motion_world=None,
    rectified=False,
) -> ReprojectionResult:
    """The flat form of :func:`~stereorepro.reproject.backward_reproject` (deprecated)."""
    check_sampling(sampling)
    src, dst = stereo_views(
        src_values,
        (src_depth, src_normal, src_K, src_cam_from_world),
        (dst_depth, dst_normal, dst_K, dst_cam_from_world),
        dict(STEREO_NAMES, src_values="src_values"),
        check,
    )
    if check:
        check_thresholds(position_threshold, normal_threshold)
        check_motion(motion, motion_world, dst_depth, "motion", "motion_world")
    if rectified and motion is not None:
        raise ValueError(
            "backward_reproject: rectified=True declares a same-instant stereo pair; it cannot be "
            "combined with motion vectors"
        )
    dst = View.unchecked(dst_depth, dst_normal, dst_K, dst_cam_from_world, motion, motion_world)
    thr = Thresholds(position_threshold, normal_threshold, temperature)
    return warp_values(src_values, src, dst, thr, sampling, soft, backend, rectified)


def _flat_stereo(
    src_color,
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
    soft=False,
    temperature=0.1,
    backend="auto",
    rectified=False,
) -> tuple[Tensor, Tensor, Tensor]:
    """The flat form of :func:`~stereorepro.reproject.stereo_reproject` (deprecated)."""
    check_shape(src_color, ["B", "3", "H", "W"], "src_color")
    check_sampling(sampling)
    src, dst = stereo_views(
        src_color,
        (src_depth, src_normal, src_K, src_cam_from_world),
        (dst_depth, dst_normal, dst_K, dst_cam_from_world),
    )
    check_thresholds(position_threshold, normal_threshold)
    thr = Thresholds(position_threshold, normal_threshold, temperature)
    out = warp_values(src_color, src, dst, thr, sampling, soft, backend, rectified, confidence=False)
    return out[0], out[1], out[2]


def _flat_temporal(
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
    soft=False,
    temperature=0.1,
    backend="auto",
    return_reason=False,
    motion=None,
    motion_world=None,
    history_rounding="none",
    footprint_weighting=False,
) -> tuple[Tensor, ...]:
    """The flat form of :func:`~stereorepro.reproject.temporal_reproject` (deprecated)."""
    history = History(history_color, history_len)
    view, prev_view = temporal_views(
        current_color,
        (depth, normal, K, cam_from_world),
        history,
        (prev_depth, prev_normal, prev_K, prev_cam_from_world),
        (motion, motion_world),
    )
    check_sampling(sampling)
    _check_history_rounding(history_rounding, "temporal_reproject")
    _check_footprint_weighting(footprint_weighting, "temporal_reproject")
    if not tracing():
        check_thresholds(position_threshold, normal_threshold)
        check_blend(alpha, max_history)
    out = reproject_history(
        current_color,
        view,
        history,
        prev_view,
        Thresholds(position_threshold, normal_threshold, temperature),
        Blend(alpha, warmup, max_history, history_rounding, footprint_weighting),
        sampling,
        soft,
        backend,
        return_reason,
    )
    return tuple(out) if return_reason else tuple(out[:3])
