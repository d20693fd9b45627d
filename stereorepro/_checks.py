"""Boundary checks with errors that name the argument, the expected and the actual shape.

Checks run only at public entry points. They are skipped while tracing for ONNX export (the graph must not
carry Python-side asserts) but shapes are already fixed by then.
"""

from __future__ import annotations

import math
import os
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .errors import CameraError, ParameterError, ParameterTypeError, ShapeError

__all__ = [
    "check_shape",
    "check_floating",
    "check_device",
    "check_camera",
    "check_named_camera",
    "check_same_hw",
    "check_sampling",
    "check_reprojection_inputs",
    "check_camera_values",
    "check_motion",
    "check_scalar",
    "check_thresholds",
    "check_blend",
    "check_blend_inputs",
    "intrinsics_problem",
    "rigid_problem",
    "tracing",
    "all_finite",
    "ShapeError",
    "CameraError",
    "ParameterError",
    "ParameterTypeError",
    "SAMPLINGS",
    "STEREO_NAMES",
    "TEMPORAL_NAMES",
    "FLOAT32_MAX",
    "check_backend_env",
    "check_resolution",
    "physical_memory",
]

#: The largest finite float32: finite scalar parameters beyond it are refused (the ops compute in float32 unless an
#: input is float64, the native kernels always; ``inf`` is the way to say "no limit").
FLOAT32_MAX = float(torch.finfo(torch.float32).max)

#: Tap sampling of the reprojection: 2×2 bilinear taps (the paper's), the one nearest tap, or 4×4 Catmull-Rom taps
#: where the whole footprint passes the tests (bilinear elsewhere; NVIDIA NRD's rule).
SAMPLINGS = ("bilinear", "nearest", "catmull_rom")

#: Argument names of the reprojection roles, as the stereo and the temporal functions call them.
STEREO_NAMES = dict(
    src_values="src_color",
    src_depth="src_depth",
    src_normal="src_normal",
    src="src",
    dst_depth="dst_depth",
    dst_normal="dst_normal",
    dst="dst",
)
TEMPORAL_NAMES = dict(
    src_values="history_color",
    src_depth="prev_depth",
    src_normal="prev_normal",
    src="prev",
    dst_depth="depth",
    dst_normal="normal",
    dst="current",
)


def tracing() -> bool:
    """True while torch.jit traces, torch.compile compiles or ONNX exports: the graph must be plain torch ops (no
    data-dependent Python checks, no native kernels). The one definition the package uses."""
    return torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


_tracing = tracing  # the name the package used before


def all_finite(t: Tensor) -> bool:
    """Whether every element of ``t`` is finite (eager mode): one sum first, which is finite only when every element
    is (a NaN or an infinity makes it NaN or infinite), and the elementwise test only when the sum is not finite
    (a non-finite element, or finite values whose sum overflows). At 1280×720×3 float32 the sum takes a few ms,
    ``isfinite(t).all()`` several times that.

    Examples:
        >>> import torch
        >>> from stereorepro._checks import all_finite
        >>> all_finite(torch.ones(2, 3)), all_finite(torch.tensor([1.0, float("nan")]))
        (True, False)
        >>> all_finite(torch.tensor([3e38, 3e38]))  # the sum overflows; every element is finite
        True
    """
    if not (t.is_floating_point() or t.is_complex()) or t.numel() == 0:
        return True
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


def _skip(is_tracing: bool | None) -> bool:
    """Whether a check is skipped: ``is_tracing`` as the caller found it (callers running many checks ask once:
    the question costs microseconds), or asked now."""
    return tracing() if is_tracing is None else is_tracing


def check_sampling(sampling: str) -> str:
    """``sampling`` if it is one of :data:`SAMPLINGS`, else ParameterError naming the choices."""
    if sampling not in SAMPLINGS:
        raise ParameterError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    return sampling


def check_shape(x, shape: Sequence[str], name: str, bind: dict | None = None, tracing: bool | None = None) -> dict:
    """Check ``x`` against a symbolic shape such as ``["B", "3", "H", "W"]``.

    Digits must match exactly; letters bind to the first size seen (in ``bind``, shared across calls so that
    e.g. all ``H`` agree). Returns the binding. ``tracing``: see :func:`_skip` (all checks take it).
    """
    bind = {} if bind is None else bind
    if _skip(tracing):
        return bind
    if not isinstance(x, Tensor):
        raise ParameterTypeError(
            f"{name}: expected a torch.Tensor of shape ({', '.join(shape)}), got {type(x).__name__}"
        )
    if x.dim() != len(shape):
        raise ShapeError(
            f"{name}: expected {len(shape)}-D tensor of shape ({', '.join(shape)}), "
            f"got {x.dim()}-D with shape {tuple(x.shape)}"
        )
    for i, (want, got) in enumerate(zip(shape, x.shape)):
        if want.isdigit():
            if int(want) != got:
                raise ShapeError(
                    f"{name}: expected shape ({', '.join(shape)}), got {tuple(x.shape)} (dim {i} must be {want})"
                )
        else:
            if want in bind and bind[want] != got:
                raise ShapeError(
                    f"{name}: expected shape ({', '.join(shape)}) with {want}={bind[want]}, got {tuple(x.shape)}"
                )
            bind.setdefault(want, got)
    return bind


def check_floating(x: Tensor, name: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    if not x.is_floating_point():
        raise ParameterTypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def check_device(tensors: dict, name: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    devices = {k: v.device for k, v in tensors.items() if isinstance(v, Tensor)}
    if len(set(devices.values())) > 1:
        raise ShapeError(
            f"{name}: all tensors must be on one device, got " + ", ".join(f"{k}={d}" for k, d in devices.items())
        )


def intrinsics_problem(K: np.ndarray) -> str | None:
    """What is wrong with pinhole intrinsics ``K`` (3, 3) (float64 numpy), or None. The one rule: finite,
    ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with ``fx, fy > 0`` (a zero focal length is singular; a negative one
    is an axis flip)."""
    if not np.isfinite(K).all():
        return f"values must be finite, got {K.tolist()}"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return (
            f"focal lengths must be > 0 (zero is singular, negative is an axis flip), got fx={K[0, 0]:g}, "
            f"fy={K[1, 1]:g}"
        )
    if not (K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0 and K[2, 2] == 1):
        return f"expected pinhole intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
    return None


def rigid_problem(T: np.ndarray, tol: float = 1e-4) -> str | None:
    """What is wrong with a rigid transform ``T`` (4, 4) (float64 numpy), or None: finite, last row
    ``[0, 0, 0, 1]``, rotation part orthonormal within ``tol`` (no scale, no shear) with determinant +1 (a
    determinant of −1 is a mirror / axis flip, typically another renderer's camera axes left unconverted)."""
    if not np.isfinite(T).all():
        return f"values must be finite, got {T.tolist()}"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol, rtol=0.0):
        return f"expected a rigid transform with last row [0, 0, 0, 1], got last row {T[3].tolist()}"
    R = T[:3, :3]
    if np.linalg.det(R) < 0:
        return (
            "det(R) = -1: a mirror / axis flip, not a rotation (convert the camera axes to OpenCV's: x right, "
            "y down, z forward)"
        )
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if not err <= tol:
        return (
            f"expected a rigid transform (rotation + translation): the rotation part is scaled or sheared "
            f"(|R^T R - I| = {err:.3g})"
        )
    return None


def _rigid_tol(dtype: torch.dtype) -> float:
    return max(1e-4, 16.0 * torch.finfo(dtype).eps)


def check_camera_values(K: Tensor, cam_from_world: Tensor, name: str, tracing: bool | None = None) -> None:
    """CameraError naming ``name``, the batch item and the problem when a camera breaks
    :func:`intrinsics_problem` or :func:`rigid_problem` (values are read, so this synchronises a GPU)."""
    if _skip(tracing):
        return
    Ks = K.detach().to("cpu", torch.float64).numpy()
    Ts = cam_from_world.detach().to("cpu", torch.float64).numpy()
    tol = _rigid_tol(cam_from_world.dtype)
    name = "" if name in ("", "current", "camera") else f"{name}_"
    for b in range(Ks.shape[0]):
        problem = intrinsics_problem(Ks[b])
        if problem:
            raise CameraError(f"{name}K[{b}]: {problem}")
        problem = rigid_problem(Ts[b], tol)
        if problem:
            raise CameraError(f"{name}cam_from_world[{b}]: {problem}")


def check_camera(
    K: Tensor, cam_from_world: Tensor, name: str, bind: dict | None = None, tracing: bool | None = None
) -> dict:
    """Shapes (B, 3, 3) and (B, 4, 4), floating dtypes, and the values (:func:`check_camera_values`)."""
    tracing = _skip(tracing)
    bind = check_shape(K, ["B", "3", "3"], f"{name} K", bind, tracing)
    bind = check_shape(cam_from_world, ["B", "4", "4"], f"{name} cam_from_world", bind, tracing)
    check_floating(K, f"{name} K", tracing)
    check_floating(cam_from_world, f"{name} cam_from_world", tracing)
    check_camera_values(K, cam_from_world, name, tracing)
    return bind


def check_named_camera(
    K: Tensor, cam_from_world: Tensor, op: str, prefix: str = "", bind: dict | None = None, tracing: bool | None = None
) -> dict:
    """:func:`check_camera` for a function whose arguments are called ``{prefix}K`` and ``{prefix}cam_from_world``
    (e.g. ``prev_``): every error reads ``op: prev_K[0]: ...`` / ``op: prev_cam_from_world: expected shape ...``."""
    if _skip(tracing):
        return {} if bind is None else bind
    bind = check_shape(K, ["B", "3", "3"], f"{op}: {prefix}K", bind, False)
    bind = check_shape(cam_from_world, ["B", "4", "4"], f"{op}: {prefix}cam_from_world", bind, False)
    check_floating(K, f"{op}: {prefix}K", False)
    check_floating(cam_from_world, f"{op}: {prefix}cam_from_world", False)
    try:
        check_camera_values(K, cam_from_world, prefix.rstrip("_"), False)
    except CameraError as e:
        raise CameraError(f"{op}: {e}") from None
    return bind


def check_scalar(
    value,
    name: str,
    lo: float = -math.inf,
    hi: float = math.inf,
    lo_open: bool = False,
    allow_inf: bool = False,
    tracing: bool | None = None,
) -> None:
    """ParameterError unless ``value`` (a number or a one-element tensor) is a number in [lo, hi] ((lo, hi] with
    ``lo_open``); NaN is never accepted, ±inf only with ``allow_inf``, finite values only within float32's range
    (:data:`FLOAT32_MAX`: the value becomes a float32 scalar in the ops). ParameterTypeError for what is not a
    real number. Tensor values are read (a GPU syncs)."""
    if _skip(tracing):
        return
    if isinstance(value, Tensor):
        if value.numel() != 1:
            raise ShapeError(f"{name}: expected a number or a one-element tensor, got shape {tuple(value.shape)}")
        if not (
            value.is_floating_point() or value.dtype in (torch.int32, torch.int64, torch.int16, torch.int8, torch.uint8)
        ):
            raise ParameterTypeError(f"{name}: expected a real number, got a tensor of dtype {value.dtype}")
        v = float(value.detach().reshape(()))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        v = float(value)
    else:
        raise ParameterTypeError(f"{name}: expected a number or a one-element tensor, got {type(value).__name__}")
    ok = (v > lo if lo_open else v >= lo) and v <= hi and not math.isnan(v) and (allow_inf or math.isfinite(v))
    if not ok:
        kind = "a number" if allow_inf else "a finite number"
        span = "" if (lo, hi) == (-math.inf, math.inf) else f" in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise ParameterError(f"{name}: expected {kind}{span}, got {v!r}")
    if math.isfinite(v) and abs(v) > FLOAT32_MAX:
        raise ParameterError(
            f"{name}: {v!r} is beyond float32's range (|x| <= {FLOAT32_MAX:.7g})"
            + ("; pass inf for no limit" if allow_inf else "")
        )


def check_motion(
    motion,
    motion_world,
    dst_depth: Tensor,
    name: str = "motion",
    name_world: str = "motion_world",
    tracing: bool | None = None,
) -> None:
    """Motion vectors (B, 2, H, W) and world motion (B, 3, H, W) of the destination ``dst_depth`` (B, 1, H, W):
    floating tensors on its device; ``motion_world`` only with ``motion``."""
    if _skip(tracing):
        return
    if motion is None:
        if motion_world is not None:
            raise ParameterError(f"{name_world} needs {name} (the screen-space motion) as well")
        return
    B, _, H, W = dst_depth.shape
    check_shape(motion, ["B", "2", "H", "W"], name, {"B": B, "H": H, "W": W}, False)
    check_floating(motion, name, False)
    check_device({name: motion, "depth": dst_depth}, name, False)
    if motion_world is not None:
        check_shape(motion_world, ["B", "3", "H", "W"], name_world, {"B": B, "H": H, "W": W}, False)
        check_floating(motion_world, name_world, False)
        check_device({name_world: motion_world, "depth": dst_depth}, name_world, False)


def check_thresholds(position_threshold, normal_threshold, tracing: bool | None = None) -> None:
    """The accept thresholds: each a number or one-element tensor, >= 0 (+inf accepts everything; a finite value
    beyond float32's range is refused, see :func:`check_scalar`)."""
    if _skip(tracing):
        return
    check_scalar(position_threshold, "position_threshold", 0.0, allow_inf=True, tracing=False)
    check_scalar(normal_threshold, "normal_threshold", 0.0, allow_inf=True, tracing=False)


def check_blend(alpha, max_history, tracing: bool | None = None) -> None:
    """The temporal blend's scalars: ``alpha`` a finite number (clamped to [0, 1] where used), ``max_history`` a
    number >= 1 (``inf``: no cap); finite values within float32's range (:func:`check_scalar`)."""
    if _skip(tracing):
        return
    check_scalar(alpha, "alpha", tracing=False)
    check_scalar(max_history, "max_history", 1.0, allow_inf=True, tracing=False)


def check_blend_inputs(
    current_color: Tensor,
    history_color: Tensor,
    history_len: Tensor,
    confidence: Tensor,
    op: str = "temporal_blend",
    tracing: bool | None = None,
) -> None:
    """The tensors of a temporal blend: ``current_color`` and ``history_color`` (B, C, H, W) floating,
    ``history_len`` (B, 1, H, W) floating, ``confidence`` (B, 1, H, W) bool or floating, all on one device;
    errors name ``op`` and the argument."""
    if _skip(tracing):
        return
    bind = check_shape(current_color, ["B", "C", "H", "W"], f"{op}: current_color", None, False)
    check_shape(history_color, ["B", "C", "H", "W"], f"{op}: history_color", bind, False)
    check_shape(history_len, ["B", "1", "H", "W"], f"{op}: history_len", bind, False)
    check_shape(confidence, ["B", "1", "H", "W"], f"{op}: confidence", bind, False)
    for name, t in (("current_color", current_color), ("history_color", history_color), ("history_len", history_len)):
        check_floating(t, f"{op}: {name}", False)
    if not (confidence.dtype == torch.bool or confidence.is_floating_point()):
        raise ParameterTypeError(
            f"{op}: confidence: expected a bool mask or floating weights, got dtype {confidence.dtype}"
        )
    check_device(
        {
            "current_color": current_color,
            "history_color": history_color,
            "history_len": history_len,
            "confidence": confidence,
        },
        op,
        False,
    )


def check_same_hw(a: Tensor, b: Tensor, name_a: str, name_b: str, tracing: bool | None = None) -> None:
    if _skip(tracing):
        return
    if a.shape[-2:] != b.shape[-2:]:
        raise ShapeError(f"{name_a} and {name_b} must have the same H, W: got {tuple(a.shape)} and {tuple(b.shape)}")


def check_reprojection_inputs(
    src_values,
    src_depth,
    src_normal,
    src_K,
    src_cam_from_world,
    dst_depth,
    dst_normal,
    dst_K,
    dst_cam_from_world,
    names: dict,
) -> None:
    """Boundary checks of a backward reprojection; ``names`` maps roles to the caller's argument names
    (:data:`STEREO_NAMES`, :data:`TEMPORAL_NAMES`) so errors name what the user passed."""
    if tracing():
        return
    tr = False  # asked once for all the checks below
    bind_src: dict = {}
    check_shape(src_values, ["B", "C", "H", "W"], names["src_values"], bind_src, tr)
    if src_values.shape[-2] == 0 or src_values.shape[-1] == 0:
        raise ShapeError(
            f"{names['src_values']}: the source image needs at least one pixel, got shape {tuple(src_values.shape)}"
        )
    check_shape(src_depth, ["B", "1", "H", "W"], names["src_depth"], bind_src, tr)
    check_shape(src_normal, ["B", "3", "H", "W"], names["src_normal"], bind_src, tr)
    bind_b = {"B": bind_src["B"]} if "B" in bind_src else {}
    check_shape(dst_depth, ["B", "1", "H", "W"], names["dst_depth"], dict(bind_b), tr)
    check_shape(
        dst_normal,
        ["B", "3", "H", "W"],
        names["dst_normal"],
        {**bind_b, "H": dst_depth.shape[-2], "W": dst_depth.shape[-1]},
        tr,
    )
    check_camera(src_K, src_cam_from_world, names["src"], dict(bind_b), tr)
    check_camera(dst_K, dst_cam_from_world, names["dst"], dict(bind_b), tr)
    for role, t in (
        ("src_values", src_values),
        ("src_depth", src_depth),
        ("src_normal", src_normal),
        ("dst_depth", dst_depth),
        ("dst_normal", dst_normal),
    ):
        check_floating(t, names[role], tr)
    check_device(
        {
            names["src_values"]: src_values,
            names["src_depth"]: src_depth,
            names["src_normal"]: src_normal,
            names["src"] + "_K": src_K,
            names["src"] + "_cam_from_world": src_cam_from_world,
            names["dst_depth"]: dst_depth,
            names["dst_normal"]: dst_normal,
            names["dst"] + "_K": dst_K,
            names["dst"] + "_cam_from_world": dst_cam_from_world,
        },
        "reprojection",
        tr,
    )


def check_backend_env() -> str | None:
    """The ``STEREOREPRO_BACKEND`` override, lower-cased, or None when unset; ParameterError naming the variable
    and the names it takes (:data:`stereorepro._backend.NAMES`) otherwise. Commands check it before they create
    anything (the ops and the tracer check it again when they resolve their backend)."""
    from . import _backend

    env = os.environ.get(_backend.ENV_VAR, "").strip().lower()
    if env and env not in _backend.NAMES:
        raise ParameterError(f"{_backend.ENV_VAR} must be one of {_backend.NAMES}, got {env!r}")
    return env or None


def physical_memory() -> int | None:
    """Bytes of memory this process can have: the machine's physical memory, or its container's limit (cgroup v2
    ``memory.max`` or v1 ``memory.limit_in_bytes``) when lower; None when neither can be read."""
    sizes = []
    try:
        sizes.append(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit():
            sizes.append(int(text))
    sizes = [s for s in sizes if s > 0]
    return min(sizes) if sizes else None


def _bytes(n: float) -> str:
    """``n`` bytes in binary units (``1.5 TiB``)."""
    units = ("B", "KiB", "MiB", "GiB", "TiB", "PiB")
    i = 0
    while n >= 1024 and i < len(units) - 1:
        n, i = n / 1024, i + 1
    return f"{n:.1f} {units[i]}"


def check_resolution(width: int, height: int, bytes_per_pixel: int, what: str, limit: int | None = None) -> int:
    """The one resolution / memory guard: the memory a ``width`` × ``height`` run of ``what`` needs, estimated as
    ``width·height·bytes_per_pixel`` (each workflow states its measured peak per pixel), returned when it fits in
    ``limit`` (default: :func:`physical_memory`; no limit when that is unknown), else ParameterError naming the
    estimate and the limit. Called before anything is allocated or created."""
    need = int(width) * int(height) * int(bytes_per_pixel)
    limit = physical_memory() if limit is None else limit
    if limit is not None and need > limit:
        raise ParameterError(
            f"{what} at {width}x{height} needs about {_bytes(need)} of memory ({bytes_per_pixel} "
            f"bytes per pixel), more than this machine's {_bytes(limit)}: use a smaller resolution"
        )
    return need
