"""Accumulation over a frame sequence: the one temporal step of an eye, and the paper's combined scheme (§4.1) as a
small stateful driver.

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

from ._checks import STEREO_NAMES, check_camera, check_reprojection_inputs, check_shape
from .reproject import Reason, StereoReprojection, TemporalReprojection, temporal_reproject
from .reproject.functional import warp_values
from .reproject._general import compute_dtype

__all__ = ["EyeState", "temporal_step", "SpatiotemporalReprojection"]


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


def temporal_step(module: TemporalReprojection, state: EyeState | None, color: Tensor, depth: Tensor,
                  normal: Tensor, K: Tensor, cam_from_world: Tensor, motion: Tensor | None = None,
                  motion_world: Tensor | None = None) -> tuple[EyeState, Tensor, Tensor]:
    """Advance one eye's accumulation by a frame.

    Args:
        module: the settings (thresholds, alpha, warm-up, cap, sampling, soft, backend); its parameters carry
            gradients when it is soft.
        state: the eye's previous frame, or None for the first frame of an accumulation.
        color: (B, 3, H, W) this frame's samples; depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3);
            cam_from_world: (B, 4, 4).
        motion, motion_world: optional (B, 2, H, W) / (B, 3, H, W) motion to the previous frame (see
            :func:`~stereorepro.reproject.temporal_reproject`); ignored on the first frame.

    Returns:
        state: the new :class:`EyeState` (accumulated colour and sample count with this frame's G-buffer).
        valid: (B, 1, H, W) bool, where the history was kept (all False on the first frame).
        reason: (B, 1, H, W) uint8 :class:`~stereorepro.Reason` (``NO_HISTORY`` everywhere on the first frame).
    """
    if state is None:
        n = torch.ones_like(depth, dtype=torch.float32)
        valid = torch.zeros_like(depth, dtype=torch.bool)
        reason = torch.full_like(depth, int(Reason.NO_HISTORY), dtype=torch.uint8)
        return EyeState(color, n, depth, normal, K, cam_from_world), valid, reason
    m = module
    out, n, valid, reason = temporal_reproject(
        color, depth, normal, K, cam_from_world, state.color, state.history_len, state.depth, state.normal, state.K,
        state.cam_from_world, m.position_threshold, m.normal_threshold, m.alpha, m.warmup, m.max_history, m.sampling,
        m.soft, m.temperature, m.backend, return_reason=True, motion=motion, motion_world=motion_world)
    return EyeState(out, n, depth, normal, K, cam_from_world), valid, reason


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
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` for the warps (see
            :func:`~stereorepro.reproject.select_backend`).

    Example (one frame; ``trace`` is your renderer)::

        st = SpatiotemporalReprojection(0.03, 0.2)
        right = st.right(trace_right(), depth_r, normal_r, K_r, T_r)
        mask = st.left_trace_mask(depth_l, normal_l, K_l, T_l)      # (B, 1, H, W) bool: trace these
        left = st.left(trace_left(pixel_mask=mask))
    """

    def __init__(self, position_threshold: float, normal_threshold: float, alpha: float = 0.2,
                 warmup: bool = True, max_history: float = 255.0, sampling: str = "bilinear",
                 stereo: bool = True, temporal: bool = True, backend: str = "auto"):
        self.stereo_module = StereoReprojection(position_threshold, normal_threshold, sampling, backend=backend)
        self.temporal_module = TemporalReprojection(position_threshold, normal_threshold, alpha, warmup,
                                                    max_history, sampling, backend=backend)
        self.backend = backend
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

    def _accumulate(self, state: EyeState | None, color, depth, normal, K, cam_from_world, motion=None,
                    motion_world=None):
        """Temporal step of one eye: (color, history_len, valid, reason); valid/reason None without history."""
        if not self.temporal or state is None:
            return color, torch.ones_like(depth, dtype=torch.float32), None, None
        new, valid, reason = temporal_step(self.temporal_module, state, color, depth, normal, K, cam_from_world,
                                           motion, motion_world)
        return new.color, new.history_len, valid, reason

    def right(self, color: Tensor, depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor,
              motion: Tensor | None = None, motion_world: Tensor | None = None) -> Tensor:
        """Accumulate this frame's right eye.

        Args:
            color: (B, 3, H, W) 1-spp radiance of the right eye.
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4).
            motion, motion_world: optional motion to the previous frame for the temporal step (moving objects;
                :func:`~stereorepro.reproject.temporal_reproject`). The stereo step uses the cameras.

        Returns:
            (B, 3, H, W) the right eye's output for this frame.
        """
        bind = check_shape(color, ["B", "3", "H", "W"], "color")
        check_shape(depth, ["B", "1", "H", "W"], "depth", bind)
        check_shape(normal, ["B", "3", "H", "W"], "normal", bind)
        check_camera(K, cam_from_world, "right", {"B": bind.get("B")} if "B" in bind else None)
        out, n, valid, reason = self._accumulate(self.right_state, color, depth, normal, K, cam_from_world, motion,
                                                 motion_world)
        self.right_valid, self.right_reason = valid, reason
        self.right_state = EyeState(out, n, depth, normal, K, cam_from_world)
        # a new frame: the left eye must run left_trace_mask() again before left()
        self._stereo_out = None
        self._left_gbuffer = None
        self.stereo_valid = self.stereo_reason = None
        return out

    def left_trace_mask(self, depth: Tensor, normal: Tensor, K: Tensor, cam_from_world: Tensor,
                        motion: Tensor | None = None, motion_world: Tensor | None = None) -> Tensor:
        """Reproject the right eye into the left and return the pixels that must be traced.

        Args:
            depth: (B, 1, H, W); normal: (B, 3, H, W); K: (B, 3, 3); cam_from_world: (B, 4, 4) — the left G-buffer.
            motion, motion_world: optional motion of the left eye to its previous frame, for its temporal step
                in :meth:`left`.

        Returns:
            (B, 1, H, W) bool trace-me mask (all True when ``stereo`` is off).
        """
        if self.right_state is None:
            raise RuntimeError("left_trace_mask() needs right() to be called first for this frame")
        self._left_gbuffer = (depth, normal, K, cam_from_world, motion, motion_world)
        if not self.stereo:
            self.stereo_valid = torch.zeros_like(depth, dtype=torch.bool)
            self.stereo_reason = None
            return ~self.stereo_valid
        r, m = self.right_state, self.stereo_module
        work = compute_dtype(r.color, r.history_len)
        values = torch.cat([r.color.to(work), r.history_len.to(work)], 1)  # the sample count rides along
        args = (values, r.depth, r.normal, r.K, r.cam_from_world, depth, normal, K, cam_from_world)
        check_reprojection_inputs(*args, dict(STEREO_NAMES, src_values="right history"))
        warped, valid, reason = warp_values(*args, m.position_threshold, m.normal_threshold, m.sampling,
                                            backend=m.backend)
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
        depth, normal, K, cam_from_world, motion, motion_world = self._left_gbuffer
        check_shape(traced_color, ["B", "3", "H", "W"], "traced_color",
                    {"B": depth.shape[0], "H": depth.shape[-2], "W": depth.shape[-1]})
        trace = ~self.stereo_valid
        traced = torch.where(trace, traced_color, torch.zeros((), dtype=traced_color.dtype))
        filled, n, valid, _ = self._accumulate(self.left_state, traced, depth, normal, K, cam_from_world, motion,
                                               motion_world)
        self.left_valid = None if valid is None else valid & trace
        if self._stereo_out is not None:
            s_color, s_len = self._stereo_out
            out = torch.where(self.stereo_valid, s_color.to(filled.dtype), filled)
            n = torch.where(self.stereo_valid, s_len, n)
        else:
            out = filled
        self.left_state = EyeState(out, n, depth, normal, K, cam_from_world)
        self._left_gbuffer = None
        return out
