"""Former home of the native dispatch (kept importable): the kernels are :mod:`stereorepro.reproject._native`, the
backend rule :func:`stereorepro.reproject.select_backend` (:mod:`stereorepro._backend`)."""

from __future__ import annotations

from ._backend import ENV_VAR
from ._checks import STEREO_NAMES, check_reprojection_inputs, check_sampling
from .reproject._native import _core, available
from .reproject.functional import (BACKENDS, _native_backward, _native_temporal, native_unsupported,
                                   select_backend)

__all__ = ["BACKENDS", "ENV_VAR", "available", "native_unsupported", "select_backend", "native_backward_reproject",
           "native_temporal_reproject", "check_backend"]


def check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend


def _check_native(sampling: str, soft: bool) -> None:
    check_sampling(sampling)
    if soft:
        raise ValueError("native: soft=True is implemented in torch only (use backend='torch')")
    if not available():
        raise RuntimeError("native: stereorepro._core with the reprojection kernels is not available")


def native_backward_reproject(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                              dst_K, dst_cam_from_world, position_threshold, normal_threshold,
                              sampling: str = "bilinear", soft: bool = False, temperature: float = 0.1,
                              check: bool = True, want_confidence: bool = True):
    """:func:`stereorepro.backward_reproject` with ``backend="native"`` (same arguments and returns; confidence
    None with ``want_confidence=False``)."""
    _check_native(sampling, soft)
    if check:
        check_reprojection_inputs(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth,
                                  dst_normal, dst_K, dst_cam_from_world, dict(STEREO_NAMES, src_values="src_values"))
    return _native_backward(src_values, src_depth, src_normal, src_K, src_cam_from_world, dst_depth, dst_normal,
                            dst_K, dst_cam_from_world, position_threshold, normal_threshold, sampling,
                            want_confidence)


def native_temporal_reproject(current_color, depth, normal, K, cam_from_world, history_color, history_len,
                              prev_depth, prev_normal, prev_K, prev_cam_from_world, position_threshold,
                              normal_threshold, alpha=0.2, warmup: bool = True, max_history: float = 255.0,
                              sampling: str = "bilinear", soft: bool = False, temperature: float = 0.1):
    """:func:`stereorepro.temporal_reproject` with ``backend="native"`` (arguments assumed checked)."""
    _check_native(sampling, soft)
    return _native_temporal(current_color, depth, normal, K, cam_from_world, history_color, history_len,
                            prev_depth, prev_normal, prev_K, prev_cam_from_world, position_threshold,
                            normal_threshold, alpha, warmup, max_history, sampling)
