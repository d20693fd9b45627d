"""The paper's combined scheme over a frame sequence (§4.1), as a small stateful driver.

Per frame, for a stereo pair:

1. **right eye**: the caller traces it at 1 spp; :meth:`SpatiotemporalReprojection.right` accumulates it
   temporally (history warped from the previous right frame, EMA with warm-up);
2. **stereo R → L**: :meth:`~SpatiotemporalReprojection.left_trace_mask` backward-reprojects the accumulated right
   eye into the left eye and returns the left pixels whose taps were all discarded — the **trace-me mask**;
3. **left fill**: the caller traces only those pixels at 1 spp and passes them to
   :meth:`~SpatiotemporalReprojection.left`; with temporal accumulation on, the traced samples are blended with
   the left eye's own warped history ("we also need to temporally accumulate left-eye data in order to fill the
   discarded pixels with accumulated data").

Switching ``temporal`` or ``stereo`` off gives the paper's other two schemes: stereo only (right eye at 1 spp,
left = reprojection + traced discards) and temporal only (the right eye's accumulation).

The driver holds tensors between frames; it is not an nn.Module and is not exported. Its settings live in a
:class:`~stereorepro.StereoReprojection` and a :class:`~stereorepro.TemporalReprojection`; it calls the same pure
functions they do (:func:`~stereorepro.backward_reproject`, through the native kernel when the backend rules allow,
and :func:`~stereorepro.temporal_blend`), because it also needs the warped history length and the reasons.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import native as _native
from ._checks import check_camera, check_shape
from .reproject import StereoReprojection, TemporalReprojection, _compute_dtype, backward_reproject, temporal_blend

__all__ = ["SpatiotemporalReprojection", "EyeState"]


@dataclass(frozen=True)
class EyeState:
    """One eye's accumulated frame and the G-buffer/camera it lives in.

    Attributes:
        color: (B, 3, H, W) accumulated colour.
        history_len: (B, 1, H, W) float sample count.
        depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).
    """

    color: Tensor
    history_len: Tensor
    depth: Tensor
    normal: Tensor
    K: Tensor
    cam_from_world: Tensor


def _warp(values, depth_src, normal_src, K_src, T_src, depth_dst, normal_dst, K_dst, T_dst, module, backend):
    """:func:`~stereorepro.backward_reproject` through the native kernel when the backend rules allow it."""
    args = (values, depth_src, normal_src, K_src, T_src, depth_dst, normal_dst, K_dst, T_dst,
            module.position_threshold, module.normal_threshold, module.sampling)
    if _native.select_backend(backend, (values, depth_src, normal_src, depth_dst, normal_dst),
                              (K_src, T_src, K_dst, T_dst, module.position_threshold, module.normal_threshold)
                              ) == "native":
        return _native.native_backward_reproject(*args, want_confidence=False)
    return backward_reproject(*args)


class SpatiotemporalReprojection:
    """Stateful driver of stereo + temporal reprojection (paper §4.1).

    Args:
        position_threshold: scene-scale limit of |P_src − P_dst| (scene units).
        normal_threshold: limit of |N_src − N_dst| (unit normals).
        alpha: minimum EMA weight of a new frame (paper: 0.2).
        warmup: running mean until the weight reaches ``alpha`` (BMFR).
        max_history: cap of the sample count.
        sampling: ``"bilinear"`` (paper) or ``"nearest"``.
        stereo: reproject the right eye into the left (else the left eye is traced in full).
        temporal: accumulate over time (else every frame starts afresh).
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` for the warps (see :mod:`stereorepro.native`).

    Example (one frame; ``trace`` is your renderer)::

        st = SpatiotemporalReprojection(0.03, 0.2)
        right = st.right(trace_right(), depth_r, normal_r, K_r, T_r)
        mask = st.left_trace_mask(depth_l, normal_l, K_l, T_l)      # (B, 1, H, W) bool: trace these
        left = st.left(trace_left(pixel_mask=mask))
    """

    def __init__(self, position_threshold: float, normal_threshold: float, alpha: float = 0.2,
                 warmup: bool = True, max_history: float = 255.0, sampling: str = "bilinear",
                 stereo: bool = True, temporal: bool = True, backend: str = "auto"):
        self.backend = _native.check_backend(backend)
        self.stereo_module = StereoReprojection(position_threshold, normal_threshold, sampling)
        self.temporal_module = TemporalReprojection(position_threshold, normal_threshold, alpha, warmup,
                                                    max_history, sampling)
        self.stereo = bool(stereo)
        self.temporal = bool(temporal)
        self.reset()

    def reset(self) -> None:
        """Forget all history (e.g. at a camera cut)."""
        self.right_state: EyeState | None = None
        self.left_state: EyeState | None = None
        self._left_gbuffer: tuple | None = None
        self._stereo_out: tuple[Tensor, Tensor] | None = None
        #: (B, 1, H, W) bool: where the right eye kept its history this frame (None on the first frame).
        self.right_valid: Tensor | None = None
        #: (B, 1, H, W) uint8 :class:`~stereorepro.Reason` of the right eye's temporal discards.
        self.right_reason: Tensor | None = None
        #: (B, 1, H, W) bool / uint8: the stereo reprojection's kept mask and discard reasons, this frame.
        self.stereo_valid: Tensor | None = None
        self.stereo_reason: Tensor | None = None
        #: (B, 1, H, W) bool: where the left eye's traced pixels kept their own history.
        self.left_valid: Tensor | None = None

    def _accumulate(self, state: EyeState | None, color, depth, normal, K, cam_from_world):
        """Temporal step of one eye: returns (color, history_len, valid, reason)."""
        ones = torch.ones_like(depth, dtype=torch.float32)
        if not self.temporal or state is None:
            return color, ones, None, None
        m = self.temporal_module
        dt = _compute_dtype(state.color, state.history_len)
        values = torch.cat([state.color.to(dt), state.history_len.to(dt)], 1)
        warped, valid, reason, _ = _warp(values, state.depth, state.normal, state.K, state.cam_from_world, depth,
                                         normal, K, cam_from_world, m, self.backend)
        out, n = temporal_blend(color, warped[:, :3], warped[:, 3:4], valid, m.alpha, m.warmup, m.max_history)
        return out, n, valid, reason

    def right(self, color: Tensor, depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor) -> Tensor:
        """Accumulate this frame's right eye.

        Args:
            color: (B, 3, H, W) 1-spp radiance of the right eye.
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).

        Returns:
            (B, 3, H, W) the right eye's output for this frame.
        """
        bind = check_shape(color, ["B", "3", "H", "W"], "color")
        check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
        check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
        check_camera(K, cam_from_world, "right", {"B": bind.get("B")} if "B" in bind else None)
        out, n, valid, reason = self._accumulate(self.right_state, color, depth, normal, K, cam_from_world)
        self.right_valid, self.right_reason = valid, reason
        self.right_state = EyeState(out, n, depth, normal, K, cam_from_world)
        # a new frame: the left eye must run left_trace_mask() again before left()
        self._stereo_out = None
        self._left_gbuffer = None
        self.stereo_valid = self.stereo_reason = None
        return out

    def left_trace_mask(self, depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor) -> Tensor:
        """Reproject the right eye into the left and return the pixels that must be traced.

        Args:
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4) — the left G-buffer.

        Returns:
            (B, 1, H, W) bool trace-me mask (all True when ``stereo`` is off).
        """
        if self.right_state is None:
            raise RuntimeError("left_trace_mask() needs right() to be called first for this frame")
        self._left_gbuffer = (depth, normal, K, cam_from_world)
        if not self.stereo:
            self.stereo_valid = torch.zeros_like(depth, dtype=torch.bool)
            self.stereo_reason = None
            return ~self.stereo_valid
        r = self.right_state
        m = self.stereo_module
        dt = _compute_dtype(r.color, r.history_len)
        values = torch.cat([r.color.to(dt), r.history_len.to(dt)], 1)
        warped, valid, reason, _ = _warp(values, r.depth, r.normal, r.K, r.cam_from_world, depth, normal, K,
                                         cam_from_world, m, self.backend)
        self._stereo_out = (warped[:, :3], warped[:, 3:4])
        self.stereo_valid, self.stereo_reason = valid, reason
        return ~valid

    def left(self, traced_color: Tensor) -> Tensor:
        """Complete the left eye from the traced discarded pixels.

        Args:
            traced_color: (B, 3, H, W) 1-spp radiance; only pixels of the trace-me mask are read.

        Returns:
            (B, 3, H, W) the left eye's output for this frame.
        """
        if self._left_gbuffer is None:
            raise RuntimeError("left() needs left_trace_mask() to be called first for this frame")
        depth, normal, K, T = self._left_gbuffer
        check_shape(traced_color, ["B", "3", "H", "W"], "traced_color",
                    {"B": depth.shape[0], "H": depth.shape[-2], "W": depth.shape[-1]})
        trace = ~self.stereo_valid
        traced = torch.where(trace, traced_color, torch.zeros((), dtype=traced_color.dtype))
        filled, n, valid, _ = self._accumulate(self.left_state, traced, depth, normal, K, T)
        self.left_valid = None if valid is None else valid & trace
        if self._stereo_out is not None:
            s_color, s_len = self._stereo_out
            out = torch.where(self.stereo_valid, s_color.to(filled.dtype), filled)
            n = torch.where(self.stereo_valid, s_len, n)
        else:
            out = filled
        self.left_state = EyeState(out, n, depth, normal, K, T)
        self._left_gbuffer = None
        return out
