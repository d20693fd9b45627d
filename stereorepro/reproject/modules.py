"""The reprojection ops as nn.Modules: each stores its configuration (thresholds, sampling, backend; learnable
with ``soft=True``) and calls its pure function. Forwards take and return plain tensors (ONNX export needs that).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .. import _backend
from .._checks import check_blend, check_sampling, check_scalar, check_thresholds
from ..errors import ParameterTypeError
from . import _flat
from .functional import BACKENDS, stereo_reproject, temporal_reproject
from .view import Blend, Field, History, Thresholds, _check_footprint_weighting, _check_history_rounding, view_fields
from .view import _check_position_test
from ..errors import ParameterError
from .clamp import fast_history_clamp
from .view import FastClamp, _check_fast_clamp, _check_radius

__all__ = ["StereoReprojection", "TemporalReprojection", "FastHistoryClamp"]


def _threshold_param(value, learnable: bool) -> Tensor:
    t = torch.as_tensor(float(value), dtype=torch.float32)
    return nn.Parameter(t) if learnable else t


def _image(name: str, channels: str, height: str = "H", width: str = "W") -> Field:
    return Field(name, ("B", channels, height, width))


class _ReprojectionBase(nn.Module):
    def __init__(
        self,
        position_threshold: float,
        normal_threshold: float,
        sampling: str,
        soft: bool,
        temperature: float,
        backend: str = "auto",
    ):
        super().__init__()
        self.backend = _backend.check(backend, BACKENDS)
        check_sampling(sampling)
        check_thresholds(position_threshold, normal_threshold, tracing=False)
        if soft:
            check_scalar(temperature, "temperature", 0.0, lo_open=True, tracing=False)
        self.sampling = sampling
        self.soft = bool(soft)
        self.temperature = float(temperature)
        if soft:  # learnable
            self.position_threshold = _threshold_param(position_threshold, True)
            self.normal_threshold = _threshold_param(normal_threshold, True)
        else:
            self.register_buffer("position_threshold", _threshold_param(position_threshold, False))
            self.register_buffer("normal_threshold", _threshold_param(normal_threshold, False))
        self.position_test = "distance"

    @property
    def position_test(self) -> str:
        """What ``position_threshold`` bounds: ``"distance"`` (default; scene units) or ``"plane"`` (the distance to
        the destination's tangent plane relative to view depth, slope-scaled: see
        :class:`~stereorepro.reproject.Thresholds`); set after construction (checked when set), honoured by the
        exported graph.

        Examples:
            >>> from stereorepro import StereoReprojection
            >>> m = StereoReprojection(0.01, 0.3)
            >>> m.position_test = "plane"  # position_threshold 0.01: 1 % of view depth off the plane
            >>> m.thresholds.position_test
            'plane'
        """
        return self._position_test

    @position_test.setter
    def position_test(self, value: str) -> None:
        _check_position_test(value, type(self).__name__)
        self._position_test = value

    @property
    def thresholds(self) -> Thresholds:
        """The accept tests as the functions take them."""
        return Thresholds(self.position_threshold, self.normal_threshold, self.temperature, self.position_test)

    def extra_repr(self) -> str:
        return (
            f"position_threshold={float(self.position_threshold):g}, "
            f"normal_threshold={float(self.normal_threshold):g}, sampling={self.sampling!r}, soft={self.soft}"
            + (f", position_test={self.position_test!r}" if self.position_test != "distance" else "")
        )


class StereoReprojection(_ReprojectionBase):
    """Stereo backward reprojection (one eye → the other) with discard masks. See :func:`stereo_reproject`.

    Args:
        position_threshold: max |P_src − P_dst| in scene units (the scene's limit; paper §4.1).
        normal_threshold: max |N_src − N_dst| between unit shading normals.
        sampling: ``"bilinear"``, ``"nearest"`` or ``"catmull_rom"`` (see :func:`~stereorepro.reproject.backward_reproject`).
        soft: smooth accept tests; the thresholds become learnable ``nn.Parameter``s.
        temperature: softness relative to the thresholds.
        backend: ``"auto"`` (native kernel when built, on CPU, float32, hard, without autograd), ``"torch"`` or
            ``"native"``; ``STEREOREPRO_BACKEND`` overrides it. See :func:`~stereorepro.reproject.select_backend`.
        rectified: declare a rectified pair (parallel rig, one instant, equal intrinsics: the paper's stereo case):
            every pixel reads its own source row with two taps instead of four, in eager and in the exported graph
            (:func:`~stereorepro.camera.rectify_warp`; eager calls raise CameraError for other cameras, an
            exported graph trusts the declaration).

    Forward:
        ``forward(src_color, src_depth, src_normal, src_K, src_cam_from_world,
        dst_depth, dst_normal, dst_K, dst_cam_from_world) -> (color, valid, reason)`` with shapes
        (B,3,Hs,Ws), (B,1,Hs,Ws), (B,3,Hs,Ws), (B,3,3), (B,4,4), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4)
        → (B,3,H,W), (B,1,H,W) bool, (B,1,H,W) uint8.

    Examples:
        >>> import torch
        >>> from stereorepro import StereoReprojection, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> K, pose = intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None]
        >>> color = torch.arange(24.0).reshape(1, 3, 2, 4)
        >>> out, valid, reason = StereoReprojection(0.01, 0.1)(color, depth, normal, K, pose, depth, normal, K, pose)
        >>> bool(torch.equal(out, color)), bool(valid.all()), int(reason.max())  # same view: every pixel kept
        (True, True, 0)
    """

    #: The forward's inputs: name and symbolic shape (the one description ONNX export reads).
    input_fields = (_image("src_color", "3", "Hp", "Wp"), *view_fields("src_", "Hp", "Wp"), *view_fields("dst_"))
    input_names = [f.name for f in input_fields]
    output_names = ["color", "valid", "reason"]

    def __init__(
        self,
        position_threshold: float,
        normal_threshold: float,
        sampling: str = "bilinear",
        soft: bool = False,
        temperature: float = 0.1,
        backend: str = "auto",
        rectified: bool = False,
    ):
        super().__init__(position_threshold, normal_threshold, sampling, soft, temperature, backend)
        self.rectified = bool(rectified)

    def extra_repr(self) -> str:
        return super().extra_repr() + (", rectified=True" if self.rectified else "")

    def forward(
        self,
        src_color: Tensor,
        src_depth: Tensor,
        src_normal: Tensor,
        src_K: Tensor,
        src_cam_from_world: Tensor,
        dst_depth: Tensor,
        dst_normal: Tensor,
        dst_K: Tensor,
        dst_cam_from_world: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        src, dst = _flat.stereo_views(
            src_color,
            (src_depth, src_normal, src_K, src_cam_from_world),
            (dst_depth, dst_normal, dst_K, dst_cam_from_world),
        )
        out = stereo_reproject(
            src_color,
            src,
            dst,
            self.thresholds,
            sampling=self.sampling,
            soft=self.soft,
            backend=self.backend,
            rectified=self.rectified,
        )
        return out.values, out.valid, out.reason


class TemporalReprojection(_ReprojectionBase):
    """Temporal reprojection + EMA accumulation. See :func:`temporal_reproject`.

    Args:
        position_threshold, normal_threshold, sampling, soft, temperature, backend: as :class:`StereoReprojection`.
        alpha: minimum weight of the current frame (paper: 0.2); learnable when ``soft``.
        warmup: running mean until the weight reaches ``alpha`` (BMFR); ``False`` = fixed EMA.
        max_history: cap of the accumulated sample count.
        history_rounding: ``"none"`` (the float count) or ``"bmfr"`` (BMFR's integer count, see
            :func:`~stereorepro.reproject.temporal_blend`); also an attribute that may be set after construction
            (checked when set).
        motion_vectors: the forward takes two more inputs, ``motion`` (B,2,H,W) and ``motion_world`` (B,3,H,W),
            the renderer's motion to the previous frame (moving objects; see :func:`temporal_reproject`); they are
            then part of ``input_names`` and of the exported ONNX graph. Without it they may still be passed by
            keyword.

    Attributes:
        footprint_weighting: ``False`` (default) or ``True``: scale the warped history length by the footprint
            quality before the blend (:class:`~stereorepro.reproject.Blend`, :func:`temporal_reproject`); set
            after construction (checked when set).

    Forward:
        ``forward(current_color, depth, normal, K, cam_from_world, history_color, history_len, prev_depth,
        prev_normal, prev_K, prev_cam_from_world[, motion, motion_world]) -> (color, history_len, valid)`` with
        shapes (B,3,H,W), (B,1,H,W), (B,3,H,W), (B,3,3), (B,4,4), (B,3,H,W), (B,1,H,W), (B,1,H,W), (B,3,H,W),
        (B,3,3), (B,4,4)[, (B,2,H,W), (B,3,H,W)] → (B,3,H,W), (B,1,H,W) float, (B,1,H,W) bool.

    Examples:
        >>> import torch
        >>> from stereorepro import TemporalReprojection, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> K, pose = intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None]
        >>> step = TemporalReprojection(0.01, 0.1, alpha=0.2)
        >>> history, n = torch.zeros(1, 3, 2, 4), torch.full((1, 1, 2, 4), 9.0)  # 9 samples of black
        >>> color, n, valid = step(torch.ones(1, 3, 2, 4), depth, normal, K, pose, history, n, depth, normal, K, pose)
        >>> round(float(color.max()), 6), float(n.max()), bool(valid.all())  # weight max(1/10, 0.2) on the new frame
        (0.2, 10.0, True)
    """

    #: The forward's inputs without motion vectors: name and symbolic shape (what ONNX export reads); with
    #: ``motion_vectors`` the motion fields follow.
    input_fields = (
        _image("current_color", "3"),
        *view_fields(""),
        _image("history_color", "3", "Hp", "Wp"),
        _image("history_len", "1", "Hp", "Wp"),
        *view_fields("prev_", "Hp", "Wp"),
    )
    input_names = [f.name for f in input_fields]
    output_names = ["color", "history_len_out", "valid"]

    def __init__(
        self,
        position_threshold: float,
        normal_threshold: float,
        alpha: float = 0.2,
        warmup: bool = True,
        max_history: float = 255.0,
        sampling: str = "bilinear",
        soft: bool = False,
        temperature: float = 0.1,
        backend: str = "auto",
        motion_vectors: bool = False,
        history_rounding: str = "none",
    ):
        super().__init__(position_threshold, normal_threshold, sampling, soft, temperature, backend)
        self.history_rounding = history_rounding
        self.footprint_weighting = False
        self.fast_clamp = None
        self.motion_vectors = bool(motion_vectors)
        if self.motion_vectors:
            self.input_fields = type(self).input_fields + view_fields(motion=True)[-2:]
            self.input_names = [f.name for f in self.input_fields]
        check_scalar(alpha, "alpha", 0.0, 1.0, lo_open=True, tracing=False)
        check_blend(alpha, max_history, tracing=False)
        self.warmup = bool(warmup)
        self.max_history = float(max_history)
        if soft:
            self.alpha = nn.Parameter(torch.as_tensor(float(alpha), dtype=torch.float32))
        else:
            self.register_buffer("alpha", torch.as_tensor(float(alpha), dtype=torch.float32))

    def extra_repr(self) -> str:
        return (
            super().extra_repr() + f", alpha={float(self.alpha):g}, warmup={self.warmup}, "
            f"max_history={self.max_history:g}"
            + (f", history_rounding={self.history_rounding!r}" if self.history_rounding != "none" else "")
            + (", footprint_weighting=True" if self.footprint_weighting else "")
            + (f", fast_clamp={self.fast_clamp!r}" if self.fast_clamp is not None else "")
            + (", motion_vectors=True" if self.motion_vectors else "")
        )

    @property
    def footprint_weighting(self) -> bool:
        """Whether the warped history length is scaled by the footprint quality (see :func:`temporal_reproject`)."""
        return self._footprint_weighting

    @footprint_weighting.setter
    def footprint_weighting(self, value: bool) -> None:
        _check_footprint_weighting(value, "TemporalReprojection")
        self._footprint_weighting = value

    @property
    def fast_clamp(self) -> FastClamp | None:
        """``None`` (default) or a :class:`~stereorepro.reproject.FastClamp`: the temporal step of
        :func:`stereorepro.accumulate.temporal_step` (and the stereo driver) then keeps a fast history beside the
        slow one and clamps the slow one to the fast one's colour box (NRD RELAX). The forward, one history in
        and out, cannot: it raises ParameterError while this is set. Checked when set."""
        return self._fast_clamp

    @fast_clamp.setter
    def fast_clamp(self, value: FastClamp | None) -> None:
        _check_fast_clamp(value, "TemporalReprojection")
        self._fast_clamp = value

    @property
    def history_rounding(self) -> str:
        """How the new history length is stored: ``"none"`` or ``"bmfr"`` (see
        :func:`~stereorepro.reproject.temporal_blend`)."""
        return self._history_rounding

    @history_rounding.setter
    def history_rounding(self, value: str) -> None:
        _check_history_rounding(value, "TemporalReprojection")
        self._history_rounding = value

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
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        if self.fast_clamp is not None:
            raise ParameterError(
                "TemporalReprojection.forward: fast_clamp needs a fast history the forward does not carry; "
                "use stereorepro.accumulate.temporal_step (or set fast_clamp = None)"
            )
        if self.motion_vectors and motion is None and not torch.jit.is_tracing():
            raise ParameterTypeError(
                "TemporalReprojection(motion_vectors=True).forward needs `motion` (and motion_world)"
            )
        history = History(history_color, history_len)
        view, prev_view = _flat.temporal_views(
            current_color,
            (depth, normal, K, cam_from_world),
            history,
            (prev_depth, prev_normal, prev_K, prev_cam_from_world),
            (motion, motion_world),
        )
        out = temporal_reproject(
            current_color,
            view,
            history,
            prev_view,
            self.thresholds,
            blend=self.blend,
            sampling=self.sampling,
            soft=self.soft,
            backend=self.backend,
        )
        return out.color, out.history_len, out.valid

    @property
    def blend(self) -> Blend:
        """The accumulation settings as the functions take them."""
        return Blend(self.alpha, self.warmup, self.max_history, self.history_rounding, self.footprint_weighting)


class FastHistoryClamp(nn.Module):
    """Fast-history clamping as a module: :func:`~stereorepro.reproject.fast_history_clamp` with its settings
    stored (exports to ONNX: Pad, Slice, Add, Sqrt, Min/Max).

    Args:
        sigma: the box's half width in standard deviations (finite, >= 0; RELAX: 2).
        radius: the window's radius in pixels (an int >= 0; 1: 3×3).
        backend: ``"auto"`` | ``"torch"`` | ``"native"`` (:func:`~stereorepro.reproject.select_backend`; ONNX
            export always traces the torch path).

    Forward:
        ``forward(color, fast_color) -> color`` with shapes (B,C,H,W), (B,C,H,W) → (B,C,H,W).

    Raises:
        ParameterError: ``sigma`` negative or not finite, ``radius`` negative.
        ParameterTypeError: ``radius`` not an int.

    Examples:
        >>> import torch
        >>> from stereorepro import FastHistoryClamp
        >>> fast = torch.tensor([[[[0.0, 1.0], [0.0, 1.0]]]])  # mean 0.5, std 0.5 over the whole 2x2 frame
        >>> FastHistoryClamp(sigma=1.0)(torch.full((1, 1, 2, 2), 3.0), fast)[0, 0].tolist()
        [[1.0, 1.0], [1.0, 1.0]]
    """

    input_fields = (Field("color", ("B", "C", "H", "W")), Field("fast_color", ("B", "C", "H", "W")))
    input_names = [f.name for f in input_fields]
    output_names = ["clamped"]

    def __init__(self, sigma: float = 2.0, radius: int = 1, backend: str = "auto"):
        super().__init__()
        check_scalar(sigma, "FastHistoryClamp: sigma", 0.0, tracing=False)
        _check_radius(radius, "FastHistoryClamp")
        self.sigma = float(sigma)
        self.radius = radius
        self.backend = _backend.check(backend, BACKENDS, "FastHistoryClamp: ")

    def extra_repr(self) -> str:
        return f"sigma={self.sigma:g}, radius={self.radius}, backend={self.backend!r}"

    def forward(self, color: Tensor, fast_color: Tensor) -> Tensor:
        return fast_history_clamp(color, fast_color, self.sigma, self.radius, self.backend)
