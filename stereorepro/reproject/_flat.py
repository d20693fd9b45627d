"""Flat tensor arguments → :class:`~stereorepro.reproject.view.View`: what the modules' ``forward`` (plain tensors,
for ONNX) and the deprecated flat forms of the ops share. The checks run with the flat argument names, so errors
name what the caller passed (``src_depth``, ``prev_K[0]``), then the views are built without checking again.
"""

from __future__ import annotations

from torch import Tensor

from .._checks import (STEREO_NAMES, TEMPORAL_NAMES, check_blend, check_floating, check_motion, check_reprojection_inputs,
                       check_sampling, check_shape, check_thresholds, tracing)
from . import functional
from .view import Blend, History, ReprojectionResult, Thresholds, View

__all__ = ["stereo_views", "temporal_views", "backward_reproject", "stereo_reproject", "temporal_reproject"]


def stereo_views(src_values: Tensor, src: tuple[Tensor, ...], dst: tuple[Tensor, ...], names: dict = STEREO_NAMES,
                 check: bool = True) -> tuple[View, View]:
    """Check a source image ``src_values`` (B, C, Hs, Ws) with the source and destination G-buffers and cameras
    ``(depth, normal, K, cam_from_world)`` under the flat names ``names``; return the two views."""
    if check:
        check_reprojection_inputs(src_values, *src, *dst, names)
    return View.unchecked(*src), View.unchecked(*dst)


def temporal_views(current_color: Tensor, current: tuple[Tensor, ...], history: History,
                   previous: tuple[Tensor, ...], motion: tuple[Tensor | None, Tensor | None] = (None, None)
                   ) -> tuple[View, View]:
    """Check a temporal step's flat inputs under the flat names (``current_color``, ``depth``, ..., ``history_color``,
    ``prev_depth``, ..., ``motion``); return (this frame's view with its motion, the previous frame's view)."""
    depth, normal = current[:2]
    bind: dict = {}
    check_shape(current_color, ["B", "3", "H", "W"], "current_color", bind)
    check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
    check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
    bind_p: dict = {"B": bind.get("B")} if bind else {}
    check_shape(history.color, ["B", "3", "H", "W"], "history_color", bind_p)
    check_shape(history.length, ["B", "1", "H", "W"], "history_len", bind_p)
    check_floating(current_color, "current_color")
    check_floating(history.length, "history_len")
    check_reprojection_inputs(history.color, *previous, *current, TEMPORAL_NAMES)
    if not tracing():
        check_motion(*motion, depth, "motion", "motion_world")
    return View.unchecked(*current, *motion), View.unchecked(*previous)


def backward_reproject(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                       dst_cam_from_world, position_threshold, normal_threshold, sampling="bilinear", soft=False,
                       temperature=0.1, check=True, backend="auto", motion=None, motion_world=None,
                       rectified=False) -> ReprojectionResult:
    """The flat form of :func:`~stereorepro.reproject.backward_reproject` (deprecated)."""
    check_sampling(sampling)
    src, dst = stereo_views(src_values, (src_depth, src_normal, src_K, src_cam_from_world),
                            (dst_depth, dst_normal, dst_K, dst_cam_from_world), dict(STEREO_NAMES,
                                                                                    src_values="src_values"), check)
    if check:
        check_thresholds(position_threshold, normal_threshold)
        check_motion(motion, motion_world, dst_depth, "motion", "motion_world")
    if rectified and motion is not None:
        raise ValueError("backward_reproject: rectified=True declares a same-instant stereo pair; it cannot be "
                         "combined with motion vectors")
    dst = View.unchecked(dst_depth, dst_normal, dst_K, dst_cam_from_world, motion, motion_world)
    thr = Thresholds(position_threshold, normal_threshold, temperature)
    return functional.warp_values(src_values, src, dst, thr, sampling, soft, backend, rectified)


def stereo_reproject(src_color, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal, dst_K,
                     dst_cam_from_world, position_threshold, normal_threshold, sampling="bilinear", soft=False,
                     temperature=0.1, backend="auto", rectified=False) -> tuple[Tensor, Tensor, Tensor]:
    """The flat form of :func:`~stereorepro.reproject.stereo_reproject` (deprecated)."""
    check_shape(src_color, ["B", "3", "H", "W"], "src_color")
    check_sampling(sampling)
    src, dst = stereo_views(src_color, (src_depth, src_normal, src_K, src_cam_from_world),
                            (dst_depth, dst_normal, dst_K, dst_cam_from_world))
    check_thresholds(position_threshold, normal_threshold)
    thr = Thresholds(position_threshold, normal_threshold, temperature)
    out = functional.warp_values(src_color, src, dst, thr, sampling, soft, backend, rectified, confidence=False)
    return out[0], out[1], out[2]


def temporal_reproject(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
                       prev_normal, prev_K, prev_cam_from_world, position_threshold, normal_threshold, alpha=0.2,
                       warmup=True, max_history=255.0, sampling="bilinear", soft=False, temperature=0.1,
                       backend="auto", return_reason=False, motion=None, motion_world=None) -> tuple[Tensor, ...]:
    """The flat form of :func:`~stereorepro.reproject.temporal_reproject` (deprecated)."""
    history = History(history_color, history_len)
    view, prev_view = temporal_views(current_color, (depth, normal, K, cam_from_world), history,
                                     (prev_depth, prev_normal, prev_K, prev_cam_from_world), (motion, motion_world))
    check_sampling(sampling)
    if not tracing():
        check_thresholds(position_threshold, normal_threshold)
        check_blend(alpha, max_history)
    out = functional.reproject_history(current_color, view, history, prev_view,
                                       Thresholds(position_threshold, normal_threshold, temperature),
                                       Blend(alpha, warmup, max_history), sampling, soft, backend, return_reason)
    return tuple(out) if return_reason else tuple(out[:3])
