"""Cameras and the project's geometric conventions (written once, here; referred to everywhere; the docs page
``docs/conventions.md`` presents them on the docs site).

Conventions
-----------
* **Camera axes** follow OpenCV: x right, y down, z forward. A camera looks along its +z axis.
* **Transforms** are named ``<to>_from_<from>`` and read in matrix-product order:
  ``points_cam = cam_from_world @ points_world``. ``cam_from_world`` is a rigid (B, 4, 4) matrix
  (rotation + translation, no scale).
* **Pixels**: pixel (x, y) (column, row) covers [x, x+1) × [y, y+1); its **centre is at (x + 0.5, y + 0.5)**.
  Continuous image coordinates ``uv`` are in pixels with that origin; ``K`` maps camera space to them:
  ``uv = (K @ p_cam)[:2] / p_cam.z``.
* **Depth** is the camera-space z of the visible surface (not the ray length).
* **No surface**: a pixel whose depth is non-finite (NaN, ±inf) or ``<= 0`` has no surface (a ray that
  missed the scene). :func:`has_surface` is the single test used everywhere.
* **Normals** are unit shading normals in **world** space, (B, 3, H, W); values at pixels without a surface
  are ignored.
* **Motion vectors** point to the previous frame: ``prev_pixel = pixel + motion`` (pixels, these axes and pixel
  centres), ``P_prev = P + motion_world`` (world units); NaN where there is no surface (:func:`camera_motion`
  gives the motion of static geometry).
* **Eyes** are :class:`Eye` values: ``Eye.LEFT == "left"`` (index 0) sits at -x of the head (cyclopean) camera,
  ``Eye.RIGHT == "right"`` (index 1) at +x, :data:`DEFAULT_BASELINE` apart unless a rig says otherwise.
* **Sub-pixel jitter** (TAA-style, off unless asked for): frame ``f`` of a sequence uses the offset
  :func:`jitter_offset` ``(dx, dy) = (halton(i, 2) - 0.5, halton(i, 3) - 0.5)`` with ``i = f % length + 1`` (index 0,
  the offset (-0.5, -0.5), is skipped), the same for both eyes. The jittered camera (:func:`jitter_intrinsics`,
  :meth:`PinholeCamera.jittered`) has its principal point moved by ``-(dx, dy)`` (``cx' = cx - dx``,
  ``cy' = cy - dy``): its pixel centre ``(x + 0.5, y + 0.5)`` looks along the unjittered camera's ray through the
  image point ``(x + 0.5 + dx, y + 0.5 + dy)``, i.e. a world point at ``uv`` in the unjittered image is at
  ``uv - (dx, dy)`` in the jittered one. Everything downstream (G-buffers, reprojection, motion) simply uses the
  jittered camera's ``K``; pixel centres stay at +0.5.
* **World positions** derived from depth are never formed in world space inside the reprojection: points are
  compared in the source camera's frame, so precision depends on distance from the camera, not from the
  world origin. Pass camera matrices as float64 when the scene lies far (≥ 1e3 units) from the origin: a
  float32 translation of 1e4 carries ~1e-3 units of rounding.

Shapes: B batch, H height, W width. Every function here is a pure tensor function; :class:`PinholeCamera` and
:class:`StereoRig` are light containers around them.
"""

from __future__ import annotations

import math
import operator
import warnings
from dataclasses import dataclass
from enum import Enum
from typing import NamedTuple

import torch
from torch import Tensor

from ._checks import check_camera, check_floating, check_named_camera, check_scalar, check_shape, tracing

__all__ = [
    "DEFAULT_BASELINE",
    "DEFAULT_RESOLUTION",
    "Eye",
    "rectify_warp",
    "has_surface",
    "pixel_centers",
    "intrinsics_from_fov",
    "look_at",
    "invert_rigid",
    "unproject",
    "project",
    "inverse_intrinsics",
    "Warp",
    "compose_warp",
    "camera_motion",
    "world_motion_from_view_z",
    "halton",
    "jitter_offset",
    "jitter_intrinsics",
    "PinholeCamera",
    "StereoRig",
]

#: Default eye separation of a :class:`StereoRig`, in scene units: 0.065 = 6.5 cm when the units are metres (an
#: adult's typical interpupillary distance).
DEFAULT_BASELINE = 0.065

#: Default image size ``(width, height)`` in pixels of the command line, the experiment and the benchmarks; the
#: scene files' thresholds are tuned for images of about this many rows.
DEFAULT_RESOLUTION = (320, 180)


def has_surface(depth: Tensor) -> Tensor:
    """True where a pixel has a surface: depth finite and > 0.

    Args:
        depth: camera-space z, any shape, e.g. (B, 1, H, W).

    Returns:
        bool tensor of the same shape.

    Examples:
        >>> import torch
        >>> from stereorepro.camera import has_surface
        >>> has_surface(torch.tensor([[2.0, 0.0, float("inf"), float("nan")]])).tolist()
        [[True, False, False, False]]
    """
    return (depth > 0) & (depth < math.inf)  # NaN compares false; one comparison less than isfinite, and an
    # exported graph gets two nodes where torch.isfinite exports as a cast to double, IsInf, IsNaN, Or and Not


def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """Continuous coordinates of pixel centres.

    Returns:
        (2, H, W): ``[0]`` = u = x + 0.5 (column), ``[1]`` = v = y + 0.5 (row).

    Examples:
        >>> from stereorepro.camera import pixel_centers
        >>> uv = pixel_centers(2, 3)
        >>> tuple(uv.shape), uv[:, 1].tolist()
        ((2, 2, 3), [[0.5, 1.5, 2.5], [1.5, 1.5, 1.5]])
    """
    v = torch.arange(height, device=device, dtype=dtype) + 0.5
    u = torch.arange(width, device=device, dtype=dtype) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=0)


def intrinsics_from_fov(
    vfov_deg: float, width: int, height: int, batch: int = 1, dtype=torch.float32, device=None
) -> Tensor:
    """Pinhole intrinsics with square pixels and the principal point at the image centre.

    Args:
        vfov_deg: vertical field of view in degrees.

    Returns:
        K: (B, 3, 3).

    Examples:
        >>> from stereorepro import intrinsics_from_fov
        >>> K = intrinsics_from_fov(90.0, 4, 2)  # focal length = half the height at 90 degrees
        >>> tuple(K.shape), K[0].tolist()
        ((1, 3, 3), [[1.0, 0.0, 2.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    """
    if not (0.0 < vfov_deg < 180.0):
        raise ValueError(f"vfov_deg must be in (0, 180), got {vfov_deg}")
    f = 0.5 * height / math.tan(math.radians(vfov_deg) * 0.5)
    K = torch.tensor([[f, 0.0, width * 0.5], [0.0, f, height * 0.5], [0.0, 0.0, 1.0]], dtype=dtype, device=device)
    return K.expand(batch, 3, 3).clone()


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """``cam_from_world`` of a camera at ``eye`` looking at ``target`` (OpenCV axes: image up is -y).

    Args:
        eye, target, up: (B, 3) world coordinates / world up direction.

    Returns:
        cam_from_world: (B, 4, 4), rigid.

    Raises:
        ValueError: a non-finite input, ``target == eye``, a zero ``up`` or one parallel to the view direction.

    Examples:
        >>> import torch
        >>> from stereorepro.camera import look_at
        >>> T = look_at(torch.tensor([[0.0, 0.0, -2.0]]), torch.zeros(1, 3), torch.tensor([[0.0, -1.0, 0.0]]))
        >>> (T[0, :3, :3] + 0.0).tolist(), (T[0, :3, 3] + 0.0).tolist()  # axes aligned, origin 2 ahead
        ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, 2.0])
    """
    check_shape(eye, ["B", "3"], "eye")
    check_shape(target, ["B", "3"], "target")
    check_shape(up, ["B", "3"], "up")
    forward = target - eye
    length = forward.pow(2).sum(-1, keepdim=True).sqrt()
    if not bool(torch.isfinite(eye).all() and torch.isfinite(target).all() and torch.isfinite(up).all()):
        raise ValueError("look_at: eye, target and up must be finite")
    if bool((length <= 0).any()):
        raise ValueError("look_at: target equals eye (no viewing direction)")
    if bool((up.pow(2).sum(-1) <= 0).any()):
        raise ValueError("look_at: `up` is the zero vector")
    forward = forward / length
    right = torch.cross(forward, up.to(forward), dim=-1)
    norm = right.pow(2).sum(-1, keepdim=True).sqrt()
    if bool((norm < 1e-12).any()):
        raise ValueError("look_at: `up` is parallel to the viewing direction")
    right = right / norm
    down = torch.cross(forward, right, dim=-1)
    R = torch.stack([right, down, forward], dim=-2)  # (B, 3, 3), rows = camera axes in world
    t = -(R @ eye.unsqueeze(-1))  # (B, 3, 1)
    T = torch.zeros(eye.shape[0], 4, 4, dtype=eye.dtype, device=eye.device)
    T[:, :3, :3] = R
    T[:, :3, 3:] = t
    T[:, 3, 3] = 1.0
    return T


def invert_rigid(T: Tensor) -> Tensor:
    """Inverse of rigid (B, 4, 4) transforms: ``[R | t]^-1 = [R^T | -R^T t]`` (ONNX-friendly, no linalg.inv).

    Examples:
        >>> import torch
        >>> from stereorepro.camera import invert_rigid
        >>> T = torch.eye(4)[None]; T[0, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
        >>> invert_rigid(T)[0, :3, 3].tolist(), bool(torch.equal(invert_rigid(T) @ T, torch.eye(4)[None]))
        ([-1.0, -2.0, -3.0], True)
    """
    return _invert_rigid(T, torch)


def inverse_intrinsics(K: Tensor) -> Tensor:
    """Closed-form inverse of upper-triangular pinhole intrinsics (B, 3, 3) (skew allowed, K[2] = [0, 0, 1]).

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import inverse_intrinsics
        >>> K = intrinsics_from_fov(90.0, 4, 2)
        >>> (inverse_intrinsics(K)[0] + 0.0).tolist(), bool(torch.allclose(inverse_intrinsics(K) @ K, torch.eye(3)))
        ([[1.0, 0.0, -2.0], [0.0, 1.0, -1.0], [0.0, 0.0, 1.0]], True)
    """
    return _inverse_intrinsics(K, torch)


# The formulas of invert_rigid, inverse_intrinsics and compose_warp, written once for both array libraries: ``xp`` is
# the module ``torch`` (tensors: autograd, tracing, any device) or ``numpy`` (float64 arrays: compose_warp's CPU
# path); the bodies use only names the two share.


def _invert_rigid(T, xp):
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.swapaxes(-1, -2)
    top = xp.concatenate([Rt, -(Rt @ t)], -1)
    bottom = T[..., 3:, :]  # [0, 0, 0, 1]
    return xp.concatenate([top, bottom], -2)


def _inverse_intrinsics(K, xp):
    fx, s, cx = K[:, 0, 0], K[:, 0, 1], K[:, 0, 2]
    fy, cy = K[:, 1, 1], K[:, 1, 2]
    return _upper_triangular(1.0 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy), 1.0 / fy, -cy / fy, xp)


def _upper_triangular(m00, m01, m02, m11, m12, xp):
    """(B, 3, 3) matrices ``[[m00, m01, m02], [0, m11, m12], [0, 0, 1]]`` from (B,) entries: stacked in torch
    (differentiable and traceable), written into a zero array in numpy (cheaper than stacking; compose_warp runs
    once per frame)."""
    if xp is torch:
        zero = torch.zeros_like(m00)
        one = torch.ones_like(m00)
        rows = [torch.stack(r, -1) for r in ([m00, m01, m02], [zero, m11, m12], [zero, zero, one])]
        return torch.stack(rows, -2)
    out = xp.zeros(m00.shape + (3, 3), m00.dtype)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2], out[:, 1, 1], out[:, 1, 2], out[:, 2, 2] = m00, m01, m02, m11, m12, 1.0
    return out


def _snap(A, xp, tol: float = 1e-12):
    """Round entries within ``tol`` (relative) of an integer to it (float64 camera compositions); round half to
    even in both libraries."""
    r = xp.round(A)
    return xp.where(abs(A - r) <= tol * (1.0 + abs(A)), r, A)


def _compose_warp(src_K, src_cam_from_world, dst_K, dst_cam_from_world, xp) -> tuple:
    """The five matrices of :class:`Warp`, in the inputs' (float64) dtype."""
    src_from_dst = _snap(src_cam_from_world @ _invert_rigid(dst_cam_from_world, xp), xp)
    M = src_from_dst[:, :3, :3] @ _inverse_intrinsics(dst_K, xp)
    t = src_from_dst[:, :3, 3:]
    return M, t, _snap(src_K @ M, xp), src_K @ t, _inverse_intrinsics(src_K, xp)


class Warp(NamedTuple):
    """Per-batch matrices of a backward warp from a destination camera into a source camera.

    ``q = z · ray_src_from_pixel_dst @ [u, v, 1] + t_src_from_dst`` is the destination pixel (u, v) at depth z as a
    point in the source camera's frame, and ``uvw = pixel_src_from_pixel_dst @ [u, v, 1] + K_src_t / z`` its
    homogeneous source pixel, with ``ray_src_from_pixel_dst = R K_dst^-1``, ``pixel_src_from_pixel_dst = K_src R
    K_dst^-1`` (the homography at infinity) and ``K_src_t = K_src t`` (R, t: ``src_cam_from_dst``).

    Attributes:
        ray_src_from_pixel_dst: (B, 3, 3). t_src_from_dst: (B, 3, 1). pixel_src_from_pixel_dst: (B, 3, 3).
        K_src_t: (B, 3, 1). K_src_inv: (B, 3, 3) = ``K_src^-1``.

    The former one-letter names (``M``, ``t``, ``P``, ``kt``, ``Ks_inv``) still read the same fields, with a
    DeprecationWarning, for one release; positional unpacking is unchanged.

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import compose_warp
        >>> K = intrinsics_from_fov(90.0, 4, 2); src = torch.eye(4)[None]; dst = src.clone(); dst[0, 0, 3] = -0.5
        >>> warp = compose_warp(K, src, K, dst, torch.float32)  # dst camera 0.5 to the right of src
        >>> warp.K_src_t.flatten().tolist(), bool(torch.equal(warp.pixel_src_from_pixel_dst, torch.eye(3)[None]))
        ([0.5, 0.0, 0.0], True)
    """

    ray_src_from_pixel_dst: Tensor
    t_src_from_dst: Tensor
    pixel_src_from_pixel_dst: Tensor
    K_src_t: Tensor
    K_src_inv: Tensor

    def _legacy(self, old: str, new: str) -> Tensor:
        warnings.warn(f"Warp.{old} is deprecated: use Warp.{new}", DeprecationWarning, stacklevel=3)
        return getattr(self, new)

    M = property(lambda self: self._legacy("M", "ray_src_from_pixel_dst"))
    t = property(lambda self: self._legacy("t", "t_src_from_dst"))
    P = property(lambda self: self._legacy("P", "pixel_src_from_pixel_dst"))
    kt = property(lambda self: self._legacy("kt", "K_src_t"))
    Ks_inv = property(lambda self: self._legacy("Ks_inv", "K_src_inv"))


def compose_warp(
    src_K: Tensor, src_cam_from_world: Tensor, dst_K: Tensor, dst_cam_from_world: Tensor, dtype: torch.dtype
) -> Warp:
    """The :class:`Warp` from a destination camera into a source camera, composed in float64, cast to ``dtype``.

    Entries within 1e-12 (relative) of an integer are snapped to it, so identical cameras give ``P = I`` and
    ``t = 0`` exactly: identity warps and integer-pixel shifts are bit-exact. CPU cameras that need no gradient
    and are not being traced are composed in numpy (the same formulas, a fraction of the per-call overhead of
    some 40 tiny torch ops); otherwise in torch ops (autograd, ONNX export, other devices).

    Args:
        src_K, dst_K: (B, 3, 3) intrinsics. src_cam_from_world, dst_cam_from_world: (B, 4, 4) rigid extrinsics.
        dtype: dtype of the returned matrices.

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import compose_warp
        >>> K, pose = intrinsics_from_fov(60.0, 6, 4), torch.eye(4)[None]
        >>> warp = compose_warp(K, pose, K, pose, torch.float32)  # identical cameras: an exact identity
        >>> bool(torch.equal(warp.pixel_src_from_pixel_dst, torch.eye(3)[None])), float(warp.t_src_from_dst.abs().max())
        (True, 0.0)
    """
    cams = (src_K, src_cam_from_world, dst_K, dst_cam_from_world)
    if not tracing() and all(
        c.device.type == "cpu" and not (c.requires_grad and torch.is_grad_enabled()) for c in cams
    ):
        return _compose_warp_numpy(cams, dtype)
    return Warp(*(m.to(dtype) for m in _compose_warp(*(c.double() for c in cams), torch)))


def _compose_warp_numpy(cams: tuple[Tensor, ...], dtype: torch.dtype) -> Warp:
    """:func:`compose_warp` of CPU cameras in float64 numpy, cast to ``dtype``."""
    import numpy as np

    out = _compose_warp(*(c.detach().to(torch.float64).numpy() for c in cams), np)
    if dtype in (torch.float32, torch.float64):  # numpy's cast rounds to nearest, as torch's
        npd = np.float32 if dtype == torch.float32 else np.float64
        return Warp(*(torch.from_numpy(np.ascontiguousarray(a, dtype=npd)) for a in out))
    return Warp(*(torch.from_numpy(np.ascontiguousarray(a)).to(dtype) for a in out))


#: How far from a rectified pair :func:`rectify_warp` accepts cameras: the vertical disparity it removes is at
#: most this many pixels anywhere in the frame (rows), and at most this fraction of the horizontal one (baseline).
RECTIFIED_TOLERANCE_PX = 1e-3
RECTIFIED_TOLERANCE_REL = 1e-4


def rectify_warp(warp: Warp, height: int, width: int, check: bool = True) -> Warp:
    """The :class:`Warp` of a rectified stereo pair: every destination pixel reads its own row of the source.

    A parallel rig at one instant with equal intrinsics (the paper's stereo case) warps rows to rows: ``P``'s last
    two rows are ``(0, 1, 0)`` and ``(0, 0, 1)`` and ``kt = (k, 0, 0)``. Real cameras (look-at rotations, float32
    extrinsics) miss that by rounding (~1e-9), which gives every bilinear footprint a second row of weight ~1e-6;
    this sets those entries exactly, so the vertical fraction of every tap is 0 and two taps per pixel suffice
    (the fast path, the native kernels and the exported graph then read only row y0). ``M`` and ``t`` (the
    position test) are kept as they are.

    Args:
        warp: composed for the pair (:func:`compose_warp`).
        height, width: the destination image's size (for the tolerance check).
        check: raise :class:`~stereorepro.errors.CameraError` when the cameras are not a rectified pair within
            :data:`RECTIFIED_TOLERANCE_PX` pixels of vertical disparity anywhere in the frame (rows) and
            :data:`RECTIFIED_TOLERANCE_REL` of the horizontal disparity (baseline); skipped while tracing.

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import compose_warp, rectify_warp
        >>> K = intrinsics_from_fov(90.0, 4, 2); src = torch.eye(4)[None]; dst = src.clone(); dst[0, 0, 3] = -0.5
        >>> warp = compose_warp(K, src, K, dst, torch.float32)
        >>> P = warp.pixel_src_from_pixel_dst.clone(); P[0, 1, 0] = 1e-7  # rounding of real cameras
        >>> rect = rectify_warp(warp._replace(pixel_src_from_pixel_dst=P), 2, 4)
        >>> rect.pixel_src_from_pixel_dst[0, 1:].tolist(), rect.K_src_t.flatten().tolist()
        ([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.5, 0.0, 0.0])
    """
    M, t, P, kt, Ks_inv = warp
    if check and not tracing():
        Pd, ktd = P.detach().double(), kt.detach().double()
        size = float(max(height, width, 1))
        rows = (Pd[:, 1, 0].abs() * width + (Pd[:, 1, 1] - 1).abs() * height + Pd[:, 1, 2].abs()) + (
            Pd[:, 2, 0].abs() * width + Pd[:, 2, 1].abs() * height + (Pd[:, 2, 2] - 1).abs()
        ) * size
        base = ktd[:, 1, 0].abs() + ktd[:, 2, 0].abs() * size
        limit = RECTIFIED_TOLERANCE_REL * ktd[:, 0, 0].abs() + 1e-12
        if bool((rows > RECTIFIED_TOLERANCE_PX).any()) or bool((base > limit).any()):
            from .errors import CameraError

            raise CameraError(
                f"rectified=True: the cameras are not a rectified pair (rows deviate by up to {float(rows.max()):.3g} "
                f"px, vertical/forward baseline {float(base.max()):.3g} against {float(limit.max()):.3g}); pass "
                "rectified=False for a general pair"
            )
    rows = torch.eye(3, dtype=P.dtype, device=P.device)[1:].expand(P.shape[0], 2, 3)  # (0, 1, 0), (0, 0, 1)
    return Warp(M, t, torch.cat([P[:, :1], rows], 1), torch.cat([kt[:, :1], torch.zeros_like(kt[:, 1:])], 1), Ks_inv)


def unproject(depth: Tensor, K: Tensor) -> Tensor:
    """Camera-space points of every pixel centre at the given depth (camera z).

    Args:
        depth: (B, 1, H, W); pixels without a surface give non-finite or meaningless points.
        K: (B, 3, 3).

    Returns:
        points_cam: (B, 3, H, W).

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import unproject
        >>> points = unproject(torch.full((1, 1, 2, 4), 2.0), intrinsics_from_fov(90.0, 4, 2))
        >>> tuple(points.shape), points[0, :, 0, 0].tolist()  # the top-left pixel centre (0.5, 0.5) at z = 2
        ((1, 3, 2, 4), [-3.0, -1.0, 2.0])
    """
    check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_shape(K, ["B", "3", "3"], "K")
    B, _, H, W = depth.shape
    uv1 = torch.cat(
        [pixel_centers(H, W, depth.device, depth.dtype), torch.ones(1, H, W, device=depth.device, dtype=depth.dtype)], 0
    )  # 3xHxW
    rays = inverse_intrinsics(K.to(depth.dtype)) @ uv1.reshape(1, 3, H * W)  # Bx3xHW, z = 1
    return rays.reshape(B, 3, H, W) * depth


def project(points_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Project camera-space points to continuous pixel coordinates.

    Args:
        points_cam: (B, 3, H, W).
        K: (B, 3, 3).

    Returns:
        uv: (B, 2, H, W) pixel coordinates (centres at +0.5); undefined where z <= 0.
        z: (B, 1, H, W) camera-space depth of the points.

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import pixel_centers, project, unproject
        >>> K = intrinsics_from_fov(90.0, 4, 2)
        >>> uv, z = project(unproject(torch.full((1, 1, 2, 4), 2.0), K), K)  # back to the pixel centres
        >>> bool(torch.allclose(uv, pixel_centers(2, 4))), z.unique().tolist()
        (True, [2.0])
    """
    check_shape(points_cam, ["B", "3", "H", "W"], "points_cam")
    B, _, H, W = points_cam.shape
    p = (K.to(points_cam.dtype) @ points_cam.reshape(B, 3, H * W)).reshape(B, 3, H, W)
    z = points_cam[:, 2:3]
    return p[:, :2] / z, z


def camera_motion(
    depth: Tensor, K: Tensor, cam_from_world: Tensor, prev_K: Tensor, prev_cam_from_world: Tensor
) -> Tensor:
    """Screen-space motion vectors of static geometry from the cameras alone: where each pixel's surface point
    was in the previous camera's image, ``prev_pixel = pixel + motion`` (the convention of
    :attr:`stereorepro.render.RenderResult.motion`), computed in float64.

    Args:
        depth: (B, 1, H, W) camera-z depth of this frame.
        K, cam_from_world: (B, 3, 3), (B, 4, 4) this frame's camera; prev_K, prev_cam_from_world: the previous.

    Returns:
        motion: (B, 2, H, W) in the dtype of ``depth``; NaN where there is no surface or where the point is not in
        front of the previous camera.

    Raises:
        ShapeError: shapes or batch sizes that do not fit, naming the argument.
        ParameterTypeError: a tensor that is not floating point.
        CameraError: camera values the ops refuse (``K`` must be finite pinhole, ``cam_from_world`` rigid), e.g.
            ``K * 0`` or a scaled ``cam_from_world``.

    Examples:
        >>> import torch
        >>> from stereorepro import camera_motion, intrinsics_from_fov
        >>> K, pose = intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None]
        >>> prev = pose.clone(); prev[0, 0, 3] = -0.5  # the previous camera sat 0.5 to the right
        >>> motion = camera_motion(torch.full((1, 1, 2, 4), 2.0), K, pose, K, prev)
        >>> tuple(motion.shape), motion[0, :, 0, 0].tolist()  # a point 2 away moved 0.25 px
        ((1, 2, 2, 4), [-0.25, 0.0])
    """
    if not tracing():
        bind = check_shape(depth, ["B", "1", "H", "W"], "camera_motion: depth", None, False)
        check_floating(depth, "camera_motion: depth", False)
        check_named_camera(K, cam_from_world, "camera_motion", "", {"B": bind["B"]}, False)
        check_named_camera(prev_K, prev_cam_from_world, "camera_motion", "prev_", {"B": bind["B"]}, False)
    d = depth.double()
    ok = has_surface(d)
    p_cam = unproject(torch.where(ok, d, torch.ones((), dtype=d.dtype, device=d.device)), K.double())
    prev_from_cam = prev_cam_from_world.double() @ invert_rigid(cam_from_world.double())
    B, _, H, W = d.shape
    q = (prev_from_cam[:, :3, :3] @ p_cam.reshape(B, 3, H * W) + prev_from_cam[:, :3, 3:]).reshape(B, 3, H, W)
    uv, z = project(q, prev_K.double())
    motion = uv - pixel_centers(H, W, d.device, d.dtype)
    keep = ok & (z > 0)
    return torch.where(keep, motion, torch.full((), float("nan"), dtype=d.dtype, device=d.device)).to(depth.dtype)


def world_motion_from_view_z(
    depth: Tensor,
    motion: Tensor,
    view_z_delta: Tensor,
    K: Tensor,
    cam_from_world: Tensor,
    prev_K: Tensor,
    prev_cam_from_world: Tensor,
) -> Tensor:
    """World-space motion from 2.5D motion (screen motion + view-z delta, the input NVIDIA's NRD recommends): the
    ``motion_world`` the reprojection ops read (:class:`~stereorepro.View`), converted once, at the boundary.

    A pixel's surface point ``P`` (this frame's depth and camera) was, at the previous instant, at the previous
    camera's pixel ``pixel + motion`` with camera z ``depth + view_z_delta``; unprojected there by the previous
    camera it gives ``P_prev``, and ``motion_world = P_prev − P``. That is the point's own motion, rigid or not, as
    exact as its inputs (computed in float64): a renderer may store the 2.5D form in float16 (screen offsets and a
    z difference keep their precision where world-space deltas far from the origin do not).

    Args:
        depth: (B, 1, H, W) camera-z depth of this frame.
        motion: (B, 2, H, W) screen motion to the previous frame in pixels (``prev_pixel = pixel + motion``).
        view_z_delta: (B, 1, H, W) the point's camera z in the previous camera minus its camera z in this one
            (NRD's ``viewZ_prev − viewZ``).
        K, cam_from_world: (B, 3, 3), (B, 4, 4) this frame's camera; prev_K, prev_cam_from_world: the previous.

    Returns:
        motion_world: (B, 3, H, W) in the dtype of ``motion``; NaN where there is no surface, where ``motion`` or
        ``view_z_delta`` is not finite, or where the previous camera z is not > 0 (the ops read no history there).

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> K, T = intrinsics_from_fov(60.0, 7, 5), torch.eye(4)[None]
        >>> depth = torch.full((1, 1, 5, 7), 2.0)
        >>> mw = world_motion_from_view_z(depth, torch.zeros(1, 2, 5, 7), torch.full((1, 1, 5, 7), 0.5), K, T, K, T)
        >>> [round(float(x), 6) + 0.0 for x in mw[0, :, 2, 3]]  # the centre pixel's point moved 0.5 along its ray
        [0.0, 0.0, 0.5]
    """
    bind = check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_shape(motion, ["B", "2", "H", "W"], "motion", bind)
    check_shape(view_z_delta, ["B", "1", "H", "W"], "view_z_delta", bind)
    check_camera(K, cam_from_world, "world_motion_from_view_z: camera", {"B": bind["B"]})
    check_camera(prev_K, prev_cam_from_world, "world_motion_from_view_z: previous camera", {"B": bind["B"]})
    d, mo, dz = depth.double(), motion.double(), view_z_delta.double()
    B, _, H, W = d.shape
    one = torch.ones((), dtype=d.dtype, device=d.device)
    ok = has_surface(d)
    z_prev = d + dz
    keep = ok & torch.isfinite(mo).all(1, keepdim=True) & torch.isfinite(dz) & (z_prev > 0)
    pixel = pixel_centers(H, W, d.device, d.dtype).unsqueeze(0)  # 1x2xHxW
    uv1_prev = torch.cat([pixel + torch.where(keep, mo, 0.0), one.expand(B, 1, H, W)], 1)
    p_prev = (inverse_intrinsics(prev_K.double()) @ uv1_prev.reshape(B, 3, H * W)) * torch.where(
        keep, z_prev, one
    ).reshape(B, 1, H * W)  # Bx3xHW, the previous camera's frame
    p_cam = unproject(torch.where(ok, d, one), K.double()).reshape(B, 3, H * W)
    world_from_cam, world_from_prev = invert_rigid(cam_from_world.double()), invert_rigid(prev_cam_from_world.double())
    # P_prev − P, rotation parts first: the translations cancel exactly when both cameras coincide
    delta = (
        world_from_prev[:, :3, :3] @ p_prev
        - world_from_cam[:, :3, :3] @ p_cam
        + (world_from_prev[:, :3, 3:] - world_from_cam[:, :3, 3:])
    )
    nan = torch.full((), math.nan, dtype=d.dtype, device=d.device)
    return torch.where(keep, delta.reshape(B, 3, H, W), nan).to(motion.dtype)


def _integer(value, name: str) -> int:
    """``value`` as a Python int (ints and numpy / torch integer scalars; not bools, not floats), else TypeError."""
    if isinstance(value, bool):
        raise TypeError(f"{name}: expected an integer, got a bool ({value!r})")
    try:
        return operator.index(value)
    except TypeError:
        raise TypeError(f"{name}: expected an integer, got {type(value).__name__} ({value!r})") from None


def halton(index: int, base: int) -> float:
    """The radical inverse of ``index`` in ``base`` (the ``index``-th point of the Halton sequence of that base).

    The base-``b`` digits of ``index`` are mirrored about the radix point: ``index = sum d_k b^k`` gives
    ``sum d_k b^-(k+1)``. Base 2: 0, 0.5, 0.25, 0.75, 0.125, ... for ``index`` = 0, 1, 2, 3, 4; base 3: 0, 1/3, 2/3,
    1/9, 4/9, ... Computed exactly in integers and rounded once (to nearest), so the value is the float nearest
    the exact fraction (base 2: exact for index < 2**53), never 1.0.

    Args:
        index: integer >= 0.
        base: integer >= 2.

    Returns:
        float in [0, 1); 0 only for ``index = 0``.

    Raises:
        TypeError: a non-integer index or base (bools and floats included).
        ValueError: index < 0 or base < 2.

    Examples:
        >>> [halton(i, 2) for i in range(1, 5)]
        [0.5, 0.25, 0.75, 0.125]
    """
    i, b = _integer(index, "halton: index"), _integer(base, "halton: base")
    if i < 0:
        raise ValueError(f"halton: index must be >= 0, got {i}")
    if b < 2:
        raise ValueError(f"halton: base must be >= 2, got {b}")
    num, den = 0, 1
    while i > 0:
        i, digit = divmod(i, b)
        num = num * b + digit
        den *= b
    return min(num / den, math.nextafter(1.0, 0.0))  # < 1 exactly; rounding could reach 1.0 only for den > 2^53


def jitter_offset(frame: int, length: int = 16) -> tuple[float, float]:
    """The TAA sub-pixel offset (dx, dy) of ``frame``, in pixels, from the Halton (2, 3) sequence.

    ``i = frame % length + 1`` (Python's modulo: non-negative for any integer ``frame``), ``dx = halton(i, 2) -
    0.5``, ``dy = halton(i, 3) - 0.5``: the sequence starts at index 1 (index 0 would be the pixel's corner,
    (-0.5, -0.5)) and repeats every ``length`` frames. Frame 0: (0.0, -1/6); frame 1: (-0.25, 1/6); frame 2:
    (0.25, -7/18). Both eyes of a stereo frame use the same offset. Pass it to :func:`jitter_intrinsics` /
    :meth:`PinholeCamera.jittered` (its sign convention is there).

    Args:
        frame: integer frame index.
        length: period of the sequence, integer >= 1 (16 = a common TAA choice; 8 is another).

    Returns:
        (dx, dy), floats in [-0.5, 0.5) (in fact in (-0.5, 0.5)): the offset from the pixel centre, x right, y down.

    Raises:
        TypeError: a non-integer frame or length. ValueError: length < 1.

    >>> jitter_offset(0), jitter_offset(1)
    ((0.0, -0.16666666666666669), (-0.25, 0.16666666666666663))
    """
    f, n = _integer(frame, "jitter_offset: frame"), _integer(length, "jitter_offset: length")
    if n < 1:
        raise ValueError(f"jitter_offset: length must be >= 1, got {n}")
    i = f % n + 1
    return halton(i, 2) - 0.5, halton(i, 3) - 0.5


def jitter_intrinsics(K: Tensor, dx, dy) -> Tensor:
    """Intrinsics of a camera jittered by (dx, dy) pixels: the principal point moved to ``(cx - dx, cy - dy)``.

    Sign convention: the jittered camera's pixel centre ``(x + 0.5, y + 0.5)`` looks along the ray of the
    unjittered camera's image point ``(x + 0.5 + dx, y + 0.5 + dy)``; equivalently a camera-space point that
    projects to ``uv`` with ``K`` projects to ``uv - (dx, dy)`` with the result (skew included). So tracing the
    jittered camera's pixel centres samples the unjittered image at the centres + (dx, dy), which is what
    :meth:`PinholeCamera.ray_directions` with ``jitter = (dx, dy)`` does for the unjittered camera.

    The subtraction is done in ``K``'s dtype (float32 K: ``cx - dx`` rounds to ~1e-5 px at cx ~ 1000; pass float64
    intrinsics for an exact shift). Differentiable with respect to ``K``.

    Args:
        K: (B, 3, 3) intrinsics.
        dx, dy: the offset in pixels (x right, y down): finite numbers or one-element tensors, e.g. from
            :func:`jitter_offset`; any finite value is accepted (whole pixels shift the image).

    Returns:
        (B, 3, 3), a new tensor (``K`` is not modified).

    Raises:
        ValueError: non-finite dx or dy. TypeError: dx or dy not a number.

    Examples:
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.camera import jitter_intrinsics
        >>> K = intrinsics_from_fov(90.0, 4, 2)
        >>> K[0, :2, 2].tolist(), jitter_intrinsics(K, 0.25, -0.5)[0, :2, 2].tolist()  # (cx, cy) -> (cx - dx, cy - dy)
        ([2.0, 1.0], [1.75, 1.5])
    """
    check_shape(K, ["B", "3", "3"], "K")
    check_scalar(dx, "jitter: dx (pixels)", tracing=False)
    check_scalar(dy, "jitter: dy (pixels)", tracing=False)
    shift = torch.zeros(3, 3, dtype=K.dtype, device=K.device)
    shift[0, 2] = float(dx)
    shift[1, 2] = float(dy)
    return K - shift  # x - 0 is x: every other entry is kept bit for bit


@dataclass(frozen=True)
class PinholeCamera:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        K: (B, 3, 3) intrinsics, pixel centres at +0.5.
        cam_from_world: (B, 4, 4) rigid extrinsics (OpenCV axes).
        height, width: image size in pixels.

    Examples:
        >>> import torch
        >>> from stereorepro import PinholeCamera, intrinsics_from_fov
        >>> cam = PinholeCamera(intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None], height=2, width=4)
        >>> points = cam.unproject(torch.full((1, 1, 2, 4), 2.0))  # world points, (1, 3, 2, 4)
        >>> uv, z = cam.project(points)
        >>> cam.batch_size, points[0, :, 0, 0].tolist(), uv[0, :, 0, 0].tolist(), float(z.max())
        (1, [-3.0, -1.0, 2.0], [0.5, 0.5], 2.0)
    """

    K: Tensor
    cam_from_world: Tensor
    height: int
    width: int

    def __post_init__(self):
        check_camera(self.K, self.cam_from_world, "camera")
        if self.height < 1 or self.width < 1:
            raise ValueError(f"camera: image size must be positive, got {self.height}x{self.width}")

    @property
    def batch_size(self) -> int:
        return self.K.shape[0]

    @property
    def world_from_cam(self) -> Tensor:
        """(B, 4, 4)."""
        return invert_rigid(self.cam_from_world)

    @property
    def center_world(self) -> Tensor:
        """(B, 3) camera centre in world coordinates."""
        return self.world_from_cam[:, :3, 3]

    def to(self, *args, **kwargs) -> "PinholeCamera":
        return PinholeCamera(
            self.K.to(*args, **kwargs), self.cam_from_world.to(*args, **kwargs), self.height, self.width
        )

    def __getitem__(self, i) -> "PinholeCamera":
        sl = slice(i, i + 1) if isinstance(i, int) else i
        return PinholeCamera(self.K[sl], self.cam_from_world[sl], self.height, self.width)

    def jittered(self, dx, dy) -> "PinholeCamera":
        """This camera moved by a sub-pixel offset (dx, dy) in pixels (TAA jitter; see :func:`jitter_intrinsics`).

        The result's pixel centre ``(x + 0.5, y + 0.5)`` looks along this camera's ray through
        ``(x + 0.5 + dx, y + 0.5 + dy)``: a world point at ``uv`` in this camera's image is at ``uv - (dx, dy)`` in
        the jittered one. Only the principal point changes (``cx - dx``, ``cy - dy``); the pose is the same. Use the
        same (dx, dy) for both eyes (:func:`jitter_offset`).

        Raises:
            ValueError: non-finite dx or dy.
        """
        return PinholeCamera(jitter_intrinsics(self.K, dx, dy), self.cam_from_world, self.height, self.width)

    def unproject(self, depth: Tensor) -> Tensor:
        """World points of every pixel at ``depth`` (B, 1, H, W) → (B, 3, H, W)."""
        p_cam = unproject(depth, self.K)
        B, _, H, W = p_cam.shape
        T = self.world_from_cam.to(p_cam.dtype)
        return (T[:, :3, :3] @ p_cam.reshape(B, 3, -1) + T[:, :3, 3:]).reshape(B, 3, H, W)

    def project(self, points_world: Tensor) -> tuple[Tensor, Tensor]:
        """World points (B, 3, H, W) → (uv (B, 2, H, W), z (B, 1, H, W))."""
        check_shape(points_world, ["B", "3", "H", "W"], "points_world")
        B, _, H, W = points_world.shape
        T = self.cam_from_world.to(points_world.dtype)
        p_cam = (T[:, :3, :3] @ points_world.reshape(B, 3, -1) + T[:, :3, 3:]).reshape(B, 3, H, W)
        return project(p_cam, self.K)

    def ray_directions(self, jitter: Tensor | None = None) -> Tensor:
        """World-space directions through pixel centres (or jittered positions), scaled so that camera z = 1.

        A hit at ray parameter t along these directions has depth t (camera z), so depth needs no extra work.

        Args:
            jitter: optional (B, 2, H, W) offsets in pixels added to the centres (e.g. in [-0.5, 0.5)).

        Returns:
            (B, 3, H, W) world-space directions (not normalised).
        """
        B = self.batch_size
        H, W = self.height, self.width
        dtype = self.K.dtype
        uv = pixel_centers(H, W, self.K.device, dtype).expand(B, 2, H, W)
        if jitter is not None:
            uv = uv + jitter.to(dtype)
        uv1 = torch.cat([uv, torch.ones(B, 1, H, W, device=uv.device, dtype=dtype)], 1)
        d_cam = inverse_intrinsics(self.K) @ uv1.reshape(B, 3, -1)
        R_wc = self.world_from_cam[:, :3, :3].to(dtype)
        return (R_wc @ d_cam).reshape(B, 3, H, W)


class Eye(str, Enum):
    """One eye of a stereo pair: the package's one representation of "which eye".

    A string enum, so an eye compares and hashes equal to its name (``Eye.LEFT == "left"``), formats as it
    (``f"{frame:04d}_{eye}.exr"``) and is written as it to JSON: the names of file names, ``cameras.json`` keys
    and the command line. ``int(eye)`` is its index, 0 left and 1 right: the order of
    :meth:`StereoRig.cameras` and the eye field of the path tracer's random-number key. ``Eye(x)`` takes an
    :class:`Eye`, a name or an index.

    >>> Eye("right") is Eye(1) is Eye.RIGHT
    True
    >>> Eye.LEFT == "left", int(Eye.RIGHT), f"0007_{Eye.LEFT}.exr", Eye.LEFT.other
    (True, 1, '0007_left.exr', <Eye.RIGHT: 'right'>)
    """

    LEFT = "left"
    RIGHT = "right"

    def __str__(self) -> str:  # also what format() and f-strings give
        return self.value

    def __int__(self) -> int:
        return 0 if self is Eye.LEFT else 1

    @property
    def other(self) -> "Eye":
        """The other eye of the pair."""
        return Eye.RIGHT if self is Eye.LEFT else Eye.LEFT

    @classmethod
    def _missing_(cls, value):  # by index: Eye(0), Eye(1) (a bool is not an index here)
        try:
            i = operator.index(value)
        except TypeError:
            return None
        return (cls.LEFT, cls.RIGHT)[i] if i in (0, 1) and not isinstance(value, bool) else None


@dataclass(frozen=True)
class StereoRig:
    """A parallel (sensor-shift) stereo rig: two cameras translated along the head's x axis only.

    Attributes:
        eye_separation: distance between the eyes in scene units (:data:`DEFAULT_BASELINE` = 0.065 = 6.5 cm when
            units are metres).
        convergence_distance: distance (scene units) at which the views converge through a sensor shift
            (principal points shifted, optical axes stay parallel: no keystoning). ``None`` = parallel
            views converging at infinity.

    Examples:
        >>> import torch
        >>> from stereorepro import StereoRig, intrinsics_from_fov
        >>> K, head = intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None]
        >>> left, right = StereoRig(eye_separation=0.1).cameras(head, K, 2, 4)
        >>> [round(x, 6) + 0.0 for x in left.center_world[0].tolist()], round(float(right.center_world[0, 0]), 6)
        ([-0.05, 0.0, 0.0], 0.05)
    """

    eye_separation: float = DEFAULT_BASELINE
    convergence_distance: float | None = None

    def __post_init__(self):
        if not (self.eye_separation > 0 and math.isfinite(self.eye_separation)):
            raise ValueError(f"StereoRig: eye_separation must be positive and finite, got {self.eye_separation}")
        if self.convergence_distance is not None and not (self.convergence_distance > 0):
            raise ValueError(f"StereoRig: convergence_distance must be positive, got {self.convergence_distance}")

    def cameras(
        self, cam_from_world_head: Tensor, K: Tensor, height: int, width: int
    ) -> tuple[PinholeCamera, PinholeCamera]:
        """Left and right cameras of a head pose.

        Args:
            cam_from_world_head: (B, 4, 4) pose of the head (cyclopean eye), OpenCV axes.
            K: (B, 3, 3) intrinsics of the head camera; each eye gets its own sensor shift.

        Returns:
            (left, right) :class:`PinholeCamera` (indexed by ``int(eye)``, :class:`Eye`); the left eye sits at
            x = -s/2, the right at +s/2 in head space.
        """
        check_camera(K, cam_from_world_head, "head")
        half = 0.5 * self.eye_separation
        out = []
        for sign in (-1.0, +1.0):  # left, right
            # eye_from_head: translate by -eye_position (eye at sign*half along head x).
            eye_from_head = torch.eye(4, dtype=cam_from_world_head.dtype, device=cam_from_world_head.device)
            eye_from_head = eye_from_head.expand_as(cam_from_world_head).clone()
            eye_from_head[:, 0, 3] = -sign * half
            K_eye = K.clone()
            if self.convergence_distance is not None:
                # A head-axis point at distance d lies at x = -sign*half in this eye: shift cx to centre it.
                K_eye[:, 0, 2] = K[:, 0, 2] + sign * K[:, 0, 0] * half / self.convergence_distance
            out.append(PinholeCamera(K_eye, eye_from_head @ cam_from_world_head, height, width))
        return out[0], out[1]
