"""The data model of the reprojection ops: a G-buffer :class:`View` with its camera, the accept
:class:`Thresholds`, the :class:`Blend` of temporal accumulation, the accumulated :class:`History`, and the named
results :class:`ReprojectionResult` and :class:`TemporalResult`.

Conventions (axes, pixel centres, depth, "no surface", motion) are those of :mod:`stereorepro.camera`.
:data:`VIEW_FIELDS` is the one description of a view's tensors: the checks, the modules' flat ``forward`` inputs,
their ONNX input names and symbolic dimensions all derive from it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .._checks import check_camera, check_device, check_floating, check_motion, check_shape, tracing
from ..errors import ParameterError, ParameterTypeError

__all__ = [
    "View",
    "Thresholds",
    "Blend",
    "FastClamp",
    "History",
    "ReprojectionResult",
    "TemporalResult",
    "Field",
    "VIEW_FIELDS",
    "MOTION_FIELDS",
    "view_fields",
]


class Field(NamedTuple):
    """One named tensor input: its name and symbolic shape (digits are fixed sizes, letters bind).

    Examples:
        >>> from stereorepro.reproject.view import Field
        >>> Field("depth", ("B", "1", "H", "W")).renamed("src_", "Hp", "Wp")
        Field(name='src_depth', shape=('B', '1', 'Hp', 'Wp'))
    """

    name: str
    shape: tuple[str, ...]

    def renamed(self, prefix: str = "", height: str = "H", width: str = "W") -> "Field":
        """This field with ``prefix`` before its name and the image dimensions called ``height`` / ``width``."""
        sizes = {"H": height, "W": width}
        return Field(prefix + self.name, tuple(sizes.get(s, s) for s in self.shape))


#: The tensors of every view, in this order: camera-z depth, unit world-space shading normals, intrinsics,
#: extrinsics.
VIEW_FIELDS = (
    Field("depth", ("B", "1", "H", "W")),
    Field("normal", ("B", "3", "H", "W")),
    Field("K", ("B", "3", "3")),
    Field("cam_from_world", ("B", "4", "4")),
)
#: The optional motion of a view to the other instant: screen-space (pixels) and world-space.
MOTION_FIELDS = (Field("motion", ("B", "2", "H", "W")), Field("motion_world", ("B", "3", "H", "W")))


def view_fields(prefix: str = "", height: str = "H", width: str = "W", motion: bool = False) -> tuple[Field, ...]:
    """The fields of a view as flat inputs named ``prefix + field`` (e.g. ``src_depth``), with the image
    dimensions called ``height`` / ``width``; the motion fields too with ``motion``.

    Examples:
        >>> from stereorepro.reproject.view import view_fields
        >>> [f.name for f in view_fields("dst_", motion=True)]
        ['dst_depth', 'dst_normal', 'dst_K', 'dst_cam_from_world', 'dst_motion', 'dst_motion_world']
        >>> view_fields("src_", "Hp", "Wp")[0].shape
        ('B', '1', 'Hp', 'Wp')
    """
    fields = VIEW_FIELDS + (MOTION_FIELDS if motion else ())
    return tuple(f.renamed(prefix, height, width) for f in fields)


@dataclass(frozen=True)
class View:
    """A G-buffer and its camera at one instant: what the reprojection ops read of a source or destination image.

    Attributes:
        depth: (B, 1, H, W) camera-space z; no surface where non-finite or <= 0.
        normal: (B, 3, H, W) unit world-space shading normals.
        K: (B, 3, 3) intrinsics (pixel centres at +0.5).
        cam_from_world: (B, 4, 4) rigid extrinsics (OpenCV axes).
        motion: optional (B, 2, H, W) screen-space motion to the other instant in pixels, ``other_pixel = pixel +
            motion`` (a renderer's motion vectors; read by the temporal ops, ignored by the stereo op).
        motion_world: optional (B, 3, H, W) world-space motion of the surface point to the other instant,
            ``P_other = P + motion_world`` (only with ``motion``; zeros when omitted: static geometry).

    Shapes, dtypes (floating), devices and camera values are checked once, here (skipped while tracing).

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 6, 8), 2.0); normal = torch.zeros(1, 3, 6, 8); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(60.0, 8, 6), torch.eye(4)[None])
        >>> view.batch_size, view.height, view.width
        (1, 6, 8)
    """

    depth: Tensor
    normal: Tensor
    K: Tensor
    cam_from_world: Tensor
    motion: Tensor | None = None
    motion_world: Tensor | None = None

    def __post_init__(self):
        self.check()

    def check(self, name: str = "View") -> None:
        """Raise ShapeError / TypeError / CameraError naming ``name`` and the field when the view is malformed."""
        if tracing():
            return
        bind = check_shape(self.depth, ["B", "1", "H", "W"], f"{name}.depth", None, False)
        check_shape(self.normal, ["B", "3", "H", "W"], f"{name}.normal", dict(bind), False)
        check_floating(self.depth, f"{name}.depth", False)
        check_floating(self.normal, f"{name}.normal", False)
        check_camera(self.K, self.cam_from_world, name, {"B": bind["B"]}, False)
        check_motion(self.motion, self.motion_world, self.depth, f"{name}.motion", f"{name}.motion_world", False)
        check_device(
            {
                f"{name}.depth": self.depth,
                f"{name}.normal": self.normal,
                f"{name}.K": self.K,
                f"{name}.cam_from_world": self.cam_from_world,
            },
            name,
            False,
        )

    @classmethod
    def unchecked(
        cls,
        depth: Tensor,
        normal: Tensor,
        K: Tensor,
        cam_from_world: Tensor,
        motion: Tensor | None = None,
        motion_world: Tensor | None = None,
    ) -> "View":
        """A view of tensors the caller has already checked (no checks run)."""
        view = object.__new__(cls)
        for f, v in zip(
            ("depth", "normal", "K", "cam_from_world", "motion", "motion_world"),
            (depth, normal, K, cam_from_world, motion, motion_world),
        ):
            object.__setattr__(view, f, v)
        return view

    @classmethod
    def from_camera(
        cls, camera, depth: Tensor, normal: Tensor, motion: Tensor | None = None, motion_world: Tensor | None = None
    ) -> "View":
        """A view from a :class:`~stereorepro.camera.PinholeCamera` (whose image size must match) and G-buffers."""
        if not tracing() and tuple(depth.shape[-2:]) != (camera.height, camera.width):
            from ..errors import ShapeError

            raise ShapeError(
                f"View.from_camera: depth is {tuple(depth.shape[-2:])} (H, W) but the camera is "
                f"{camera.height}x{camera.width} (HxW)"
            )
        return cls(depth, normal, camera.K, camera.cam_from_world, motion, motion_world)

    @classmethod
    def from_render(cls, result, camera, motion: bool = True) -> "View":
        """A view of a :class:`~stereorepro.render.RenderResult` rendered with G-buffers by ``camera``; its motion
        vectors are taken along when it has them and ``motion`` is true."""
        if result.depth is None or result.normal is None:
            from ..errors import UserError

            raise UserError("View.from_render: the render result has no G-buffers (render with gbuffers=True)")
        mv = result.motion if motion else None
        return cls.from_camera(camera, result.depth, result.normal, mv, result.motion_world if mv is not None else None)

    @property
    def batch_size(self) -> int:
        return self.depth.shape[0]

    @property
    def height(self) -> int:
        return self.depth.shape[-2]

    @property
    def width(self) -> int:
        return self.depth.shape[-1]

    @property
    def camera(self):
        """The view's :class:`~stereorepro.camera.PinholeCamera`."""
        from ..camera import PinholeCamera

        return PinholeCamera(self.K, self.cam_from_world, self.height, self.width)

    def without_motion(self) -> "View":
        """This view with its motion fields dropped (no checks rerun)."""
        if self.motion is None and self.motion_world is None:
            return self
        return View.unchecked(self.depth, self.normal, self.K, self.cam_from_world)

    def replace(self, **changes) -> "View":
        """A copy with some fields replaced (checked)."""
        return dataclasses.replace(self, **changes)

    def to(self, *args, **kwargs) -> "View":
        """Every tensor moved / cast like :meth:`torch.Tensor.to` (cameras too: pass float64 for far scenes)."""

        def move(x):
            return None if x is None else x.to(*args, **kwargs)

        return View(
            move(self.depth),
            move(self.normal),
            move(self.K),
            move(self.cam_from_world),
            move(self.motion),
            move(self.motion_world),
        )

    def flat(self, motion: bool = False) -> tuple[Tensor | None, ...]:
        """The tensors in :data:`VIEW_FIELDS` order (and the motion fields with ``motion``): a module's inputs."""
        out = (self.depth, self.normal, self.K, self.cam_from_world)
        return out + (self.motion, self.motion_world) if motion else out


class Thresholds(NamedTuple):
    """The accept tests of a tap: a position test and ``|N_src − N_dst| <= normal`` (unit normals), each threshold a
    number or a one-element tensor >= 0 (``inf`` accepts everything); ``temperature`` is the softness of
    ``soft=True`` tests, relative to the thresholds. A plain ``(position, normal)`` pair works too.

    ``position_test`` (one of :data:`POSITION_TESTS`) says what ``position`` bounds:

    * ``"distance"`` (default): ``|P_src − P_dst| <= position``, an absolute distance in scene units;
    * ``"plane"``: the distance of the source tap to the destination pixel's tangent plane, relative to its view
      depth and widened at grazing angles (NVIDIA NRD's disocclusion test, without its parallax term):
      ``|n_dst · (P_src − P_dst)| <= position · z_dst / (0.05 + 0.95·|n_dst · v_dst|)``. ``position`` is then a
      fraction of view depth (dimensionless); ``n_dst`` is the destination pixel's world normal, ``z_dst`` its
      depth, ``v_dst`` the unit direction of its view ray (from the destination camera through the pixel) and
      ``P_dst`` the point the distance test compares with (moved by the world motion, when given). A destination
      normal that is not finite or shorter than 0.5 (``|n|² < 0.25``) defines no plane: its taps fail the
      position test. The soft test uses the plane distance² against the threshold² as ``"distance"`` does. Either
      test reports ``Reason.POSITION``.

    Examples:
        >>> from stereorepro import Thresholds
        >>> t = Thresholds(0.01, 0.1)  # 1 cm of position, 0.1 of normal
        >>> t, t.position, t._replace(normal=float("inf")).normal
        (Thresholds(position=0.01, normal=0.1, temperature=0.1, position_test='distance'), 0.01, inf)
        >>> Thresholds(0.01, 0.1, position_test="plane").position_test  # 1 % of view depth off the plane
        'plane'
    """

    position: float | Tensor
    normal: float | Tensor
    temperature: float = 0.1
    position_test: str = "distance"


#: Values of :attr:`Thresholds.position_test`: ``"distance"`` (absolute distance in scene units) or ``"plane"``
#: (distance to the destination's tangent plane relative to view depth, slope-scaled).
POSITION_TESTS = ("distance", "plane")


def _check_position_test(position_test, where: str) -> None:
    """ParameterError naming ``where`` and the choices unless ``position_test`` is one of :data:`POSITION_TESTS`."""
    if not (isinstance(position_test, str) and position_test in POSITION_TESTS):
        raise ParameterError(f"{where}: position_test must be one of {POSITION_TESTS}, got {position_test!r}")


#: Values of ``history_rounding`` (:class:`Blend`, :func:`~stereorepro.reproject.temporal_blend`): ``"none"``
#: stores the float history length, ``"bmfr"`` BMFR's integer one.
HISTORY_ROUNDINGS = ("none", "bmfr")


def _check_history_rounding(history_rounding, where: str) -> None:
    """ParameterError naming ``where`` and the choices unless ``history_rounding`` is one of
    :data:`HISTORY_ROUNDINGS`."""
    if not (isinstance(history_rounding, str) and history_rounding in HISTORY_ROUNDINGS):
        raise ParameterError(f"{where}: history_rounding must be one of {HISTORY_ROUNDINGS}, got {history_rounding!r}")


def _check_footprint_weighting(footprint_weighting, where: str) -> None:
    """ParameterError naming ``where`` unless ``footprint_weighting`` is a bool."""
    if not isinstance(footprint_weighting, bool):
        raise ParameterError(f"{where}: footprint_weighting must be True or False, got {footprint_weighting!r}")


class Blend(NamedTuple):
    """Temporal accumulation: ``a = max(1/(n+1), alpha)`` with ``warmup`` (BMFR's running mean until the weight
    reaches ``alpha``), else ``a = alpha``; ``out = (1 − a)·history + a·current``; n capped at ``max_history``.
    ``alpha`` may be a learnable one-element tensor. ``history_rounding``: how the new length is stored,
    ``"none"`` (the float ``min(n + 1, max_history)``) or ``"bmfr"`` (BMFR's integer
    ``min(round_half_even(n) + 1, max_history)``; see :func:`~stereorepro.reproject.temporal_blend`). A
    ``(alpha, warmup, max_history)`` triple still works where a Blend is taken. ``footprint_weighting``: scale
    the warped history length by the footprint quality before the blend, ``n ← n·(1 + q)/2`` with ``q`` the
    accepted bilinear weight of the history's taps (NVIDIA NRD's rule; see
    :func:`~stereorepro.reproject.temporal_reproject`); ``False`` (default) leaves ``n`` as warped.

    Examples:
        >>> from stereorepro import Blend
        >>> Blend(), Blend(alpha=0.1, warmup=False).alpha
        (Blend(alpha=0.2, warmup=True, max_history=255.0, history_rounding='none', footprint_weighting=False), 0.1)
        >>> Blend(history_rounding="bmfr").history_rounding
        'bmfr'
        >>> Blend(footprint_weighting=True).footprint_weighting
        True
    """

    alpha: float | Tensor = 0.2
    warmup: bool = True
    max_history: float = 255.0
    history_rounding: str = "none"
    footprint_weighting: bool = False


class FastClamp(NamedTuple):
    """Fast-history clamping of a temporal step (NVIDIA NRD's RELAX): beside the slow history the step keeps a
    fast one, blended with ``a_fast = max(1/(n + 1), alpha)`` (``alpha`` alone without warm-up) on the same warp
    and history length n as the slow one (restarted where the slow one is), and clamps the slow result where the
    history was kept to ``[μ − sigma·σ, μ + sigma·σ]``, the per-channel mean and standard deviation of the fast
    history over the ``(2·radius + 1)²`` window (:func:`~stereorepro.reproject.fast_history_clamp`). Set as
    :attr:`TemporalReprojection.fast_clamp <stereorepro.TemporalReprojection.fast_clamp>`.

    Attributes:
        alpha: the fast history's minimum EMA weight, in (0, 1]; larger than the slow ``alpha`` (0.5 by
            default: a history of about two frames).
        sigma: the box's half width in standard deviations, finite, >= 0 (RELAX: 2).
        radius: the window's radius in pixels, an int >= 0 (1: 3×3).

    Examples:
        >>> from stereorepro import FastClamp
        >>> FastClamp(), FastClamp(alpha=0.25, radius=2).radius
        (FastClamp(alpha=0.5, sigma=2.0, radius=1), 2)
    """

    alpha: float = 0.5
    sigma: float = 2.0
    radius: int = 1


def _check_radius(radius, where: str) -> None:
    """ParameterTypeError unless ``radius`` is an int (not a bool), ParameterError unless it is >= 0."""
    if isinstance(radius, bool) or not isinstance(radius, int):
        raise ParameterTypeError(f"{where}: radius must be an int >= 0 (1: a 3x3 window), got {radius!r}")
    if radius < 0:
        raise ParameterError(f"{where}: radius must be >= 0 (1: a 3x3 window), got {radius}")


def _check_fast_clamp(fast_clamp, where: str) -> None:
    """ParameterError naming ``where`` and the field unless ``fast_clamp`` is None or a valid :class:`FastClamp`
    (ParameterTypeError for a field of the wrong kind: a string for a number, a float radius)."""
    if fast_clamp is None:
        return
    if not isinstance(fast_clamp, FastClamp):
        raise ParameterError(f"{where}: fast_clamp must be None or a FastClamp, got {fast_clamp!r}")
    from .._checks import check_scalar

    check_scalar(fast_clamp.alpha, f"{where}: fast_clamp.alpha", 0.0, 1.0, lo_open=True, tracing=False)
    check_scalar(fast_clamp.sigma, f"{where}: fast_clamp.sigma", 0.0, tracing=False)
    _check_radius(fast_clamp.radius, f"{where}: fast_clamp")


class History(NamedTuple):
    """The accumulated state of one eye: ``color`` (B, C, H, W) and ``length`` (B, 1, H, W), the float sample
    count n (0 = no history).

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None])
        >>> from stereorepro import History
        >>> history = History.empty(view)  # the first frame: no samples yet
        >>> tuple(history.color.shape), tuple(history.length.shape), float(history.length.max())
        ((1, 3, 2, 4), (1, 1, 2, 4), 0.0)
    """

    color: Tensor
    length: Tensor

    @classmethod
    def empty(cls, view: View, channels: int = 3, dtype: torch.dtype | None = None) -> "History":
        """No history yet (the first frame): zeros of ``view``'s size. A temporal step with it returns the current
        frame with ``history_len`` 1 (``valid`` still reports the accept tests against the previous view given)."""
        dtype = view.depth.dtype if dtype is None else dtype
        B, _, H, W = view.depth.shape
        zeros = torch.zeros(B, channels, H, W, dtype=dtype, device=view.depth.device)
        return cls(zeros, torch.zeros(B, 1, H, W, dtype=dtype, device=view.depth.device))


class ReprojectionResult(NamedTuple):
    """What a backward reprojection returns.

    Attributes:
        values: (B, C, H, W) warped values, 0 where nothing was accepted; dtype of the source values.
        valid: (B, 1, H, W) bool, accepted bilinear weight > 0.
        reason: (B, 1, H, W) uint8 :class:`~stereorepro.reproject.Reason` codes (0 where valid).
        confidence: (B, 1, H, W) accepted bilinear weight in [0, 1] before renormalisation (soft weights with
            soft tests), in the compute dtype; ``None`` where the op was not asked for it.

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None])
        >>> from stereorepro import backward_reproject
        >>> out = backward_reproject(torch.arange(8.0).reshape(1, 1, 2, 4), view, view, (0.01, 0.1))
        >>> out.values[0, 0].tolist(), bool(out.valid.all()), out.reason.dtype, float(out.confidence.min())
        ([[0.0, 1.0, 2.0, 3.0], [4.0, 5.0, 6.0, 7.0]], True, torch.uint8, 1.0)
        >>> values, valid, reason, confidence = out  # a NamedTuple: unpacks too
    """

    values: Tensor
    valid: Tensor
    reason: Tensor
    confidence: Tensor | None = None


class TemporalResult(NamedTuple):
    """What a temporal accumulation step returns.

    Attributes:
        color: (B, C, H, W) accumulated colour, dtype of the current colour.
        history_len: (B, 1, H, W) float sample count n for the next frame.
        valid: (B, 1, H, W) bool, where the history was kept.
        reason: (B, 1, H, W) uint8 :class:`~stereorepro.reproject.Reason` of the history's discards; ``None``
            unless asked for (``return_reason=True``).

    Examples:
        >>> import torch
        >>> from stereorepro import View, intrinsics_from_fov
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> view = View(depth, normal, intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None])
        >>> from stereorepro import History, temporal_reproject
        >>> first = temporal_reproject(torch.ones(1, 3, 2, 4), view, History.empty(view), view, (0.01, 0.1))
        >>> second = temporal_reproject(torch.zeros(1, 3, 2, 4), view, first.history, view, (0.01, 0.1))
        >>> float(second.color.max()), float(second.history_len.max()), bool(second.valid.all()), second.reason
        (0.5, 2.0, True, None)
    """

    color: Tensor
    history_len: Tensor
    valid: Tensor
    reason: Tensor | None = None

    @property
    def history(self) -> History:
        """The state to pass as the next frame's history."""
        return History(self.color, self.history_len)
