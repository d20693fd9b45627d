"""Test inputs, not part of the public API: analytic G-buffers (planes and spheres ray-cast in torch, with a smooth
procedural texture) and the example inputs of the reprojection modules built from them (:func:`example_inputs`).

These give reprojection tests, examples and benchmarks inputs with known answers and no renderer: depth, world
normal and colour are exact functions of the camera, and the same world point has the same colour from every
viewpoint (a diffuse, view-independent texture).

World convention for the built-in analytic scene: y up, floor at y = 0, the camera looks along −z.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor, nn

from .camera import DEFAULT_BASELINE, PinholeCamera, StereoRig, camera_motion, intrinsics_from_fov, look_at

__all__ = [
    "Plane",
    "Sphere",
    "AnalyticScene",
    "default_scene",
    "Gbuffer",
    "raycast",
    "texture",
    "camera_pair",
    "example_inputs",
]


@dataclass(frozen=True)
class Plane:
    """Points P with ``normal · P = offset``."""

    normal: tuple[float, float, float]
    offset: float
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class AnalyticScene:
    planes: tuple[Plane, ...] = ()
    spheres: tuple[Sphere, ...] = ()
    frequency: float = 3.0  #: texture frequency in radians per scene unit
    origin_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: whole scene translated by this (precision tests)
    extra: dict = field(default_factory=dict)


def default_scene(origin_offset=(0.0, 0.0, 0.0)) -> AnalyticScene:
    """A floor, a back wall, a side wall and three spheres (occlusions and disocclusions in both eyes)."""
    ox, oy, oz = origin_offset
    return AnalyticScene(
        planes=(
            Plane((0.0, 1.0, 0.0), 0.0 + oy, (0.9, 0.8, 0.7)),
            Plane((0.0, 0.0, 1.0), -6.0 + oz, (0.7, 0.8, 0.9)),
            Plane((1.0, 0.0, 0.0), -3.0 + ox, (0.8, 0.9, 0.7)),
        ),
        spheres=(
            Sphere((0.0 + ox, 0.8 + oy, -3.0 + oz), 0.8, (1.0, 0.5, 0.4)),
            Sphere((1.3 + ox, 0.4 + oy, -2.0 + oz), 0.4, (0.4, 1.0, 0.5)),
            Sphere((-1.2 + ox, 1.5 + oy, -4.0 + oz), 0.6, (0.5, 0.6, 1.0)),
        ),
        origin_offset=tuple(origin_offset),
    )


def texture(points_world: Tensor, tint: Tensor, scene: AnalyticScene) -> Tensor:
    """Smooth procedural albedo-like colour of world points (B, 3, H, W) → (B, 3, H, W) in (0, 1)."""
    off = torch.tensor(scene.origin_offset, dtype=points_world.dtype, device=points_world.device).view(1, 3, 1, 1)
    p = (points_world - off) * scene.frequency
    phase = torch.tensor([0.0, 2.1, 4.2], dtype=p.dtype, device=p.device).view(1, 3, 1, 1)
    pattern = (
        0.5
        + 0.2 * torch.sin(p[:, 0:1] + phase)
        + 0.2 * torch.sin(p[:, 1:2] * 1.3 + 2 * phase)
        + 0.08 * torch.sin(p[:, 2:3] * 0.7 + phase)
    )
    return pattern * tint


class Gbuffer(NamedTuple):
    """What :func:`raycast` sees at a camera's pixel centres.

    Attributes:
        depth: (B, 1, H, W) camera z, +inf where there is no surface.
        normal: (B, 3, H, W) world unit normals facing the camera, 0 where there is no surface.
        position: (B, 3, H, W) world positions, 0 where there is no surface.
        color: (B, 3, H, W) the surface's :func:`texture`, 0 where there is no surface.
    """

    depth: Tensor
    normal: Tensor
    position: Tensor
    color: Tensor


def raycast(camera: PinholeCamera, scene: AnalyticScene, dtype=torch.float64) -> Gbuffer:
    """Ray-cast pixel centres of ``camera`` against ``scene`` (see :class:`Gbuffer`)."""
    cam = camera.to(dtype)
    d = cam.ray_directions()  # Bx3xHxW, camera z = 1 → t = depth
    B, _, H, W = d.shape
    o = cam.center_world.view(B, 3, 1, 1)
    best_t = torch.full((B, 1, H, W), float("inf"), dtype=dtype)
    best_n = torch.zeros(B, 3, H, W, dtype=dtype)
    best_tint = torch.zeros(B, 3, H, W, dtype=dtype)
    for pl in scene.planes:
        n = torch.tensor(pl.normal, dtype=dtype).view(1, 3, 1, 1)
        denom = (n * d).sum(1, keepdim=True)
        t = (pl.offset - (n * o).sum(1, keepdim=True)) / torch.where(denom.abs() > 1e-12, denom, torch.ones_like(denom))
        ok = (denom.abs() > 1e-12) & (t > 1e-9) & (t < best_t)
        best_t = torch.where(ok, t, best_t)
        best_n = torch.where(ok, n.expand_as(best_n), best_n)
        best_tint = torch.where(ok, torch.tensor(pl.tint, dtype=dtype).view(1, 3, 1, 1).expand_as(best_tint), best_tint)
    for sp in scene.spheres:
        c = torch.tensor(sp.center, dtype=dtype).view(1, 3, 1, 1)
        oc = o - c
        a = (d * d).sum(1, keepdim=True)
        b = 2.0 * (d * oc).sum(1, keepdim=True)
        cc = (oc * oc).sum(1, keepdim=True) - sp.radius**2
        disc = b * b - 4 * a * cc
        sq = disc.clamp_min(0).sqrt()
        t = (-b - sq) / (2 * a)
        ok = (disc >= 0) & (t > 1e-9) & (t < best_t)
        best_t = torch.where(ok, t, best_t)
        n = (o + t * d - c) / sp.radius
        best_n = torch.where(ok, n, best_n)
        best_tint = torch.where(ok, torch.tensor(sp.tint, dtype=dtype).view(1, 3, 1, 1).expand_as(best_tint), best_tint)
    hit = torch.isfinite(best_t)
    # Two-sided: flip normals towards the camera.
    flip = (best_n * d).sum(1, keepdim=True) > 0
    best_n = torch.where(flip, -best_n, best_n)
    position = torch.where(hit, o + best_t.where(hit, torch.zeros_like(best_t)) * d, torch.zeros_like(d))
    color = torch.where(hit, texture(position, best_tint, scene), torch.zeros_like(position))
    return Gbuffer(best_t, torch.where(hit, best_n, torch.zeros_like(best_n)), position, color)


def camera_pair(
    height: int,
    width: int,
    batch: int = 1,
    baseline: float = DEFAULT_BASELINE,
    forward: float = 0.0,
    yaw_deg: float = 0.0,
    vfov_deg: float = 60.0,
    origin_offset=(0.0, 0.0, 0.0),
    dtype=torch.float64,
) -> tuple[PinholeCamera, PinholeCamera]:
    """(dst, src) cameras looking into :func:`default_scene`: a stereo pair (``baseline``) plus optional motion.

    The source camera is the right eye of a rig at the head pose moved ``forward`` along its viewing axis and rotated by
    ``yaw_deg``; the destination is the left eye of the unmoved head.
    """
    ox, oy, oz = origin_offset
    K = intrinsics_from_fov(vfov_deg, width, height, batch, dtype=dtype)
    eye = torch.tensor([[0.3 + ox, 1.4 + oy, 1.5 + oz]], dtype=dtype).expand(batch, 3)
    target = torch.tensor([[0.0 + ox, 0.8 + oy, -3.0 + oz]], dtype=dtype).expand(batch, 3)
    up = torch.tensor([[0.0, 1.0, 0.0]], dtype=dtype).expand(batch, 3)
    head = look_at(eye, target, up)
    rig = StereoRig(eye_separation=baseline)
    left, _ = rig.cameras(head, K, height, width)
    import math

    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    motion = torch.tensor(
        [[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, -forward], [0.0, 0.0, 0.0, 1.0]], dtype=dtype
    )  # head_new_from_head_old in camera axes
    _, right = rig.cameras(motion @ head, K, height, width)
    return left, right


def example_inputs(
    module: nn.Module,
    batch: int = 1,
    height: int = 24,
    width: int = 32,
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
    head_motion: bool = True,
) -> tuple[Tensor, ...]:
    """Realistic inputs for a module's forward: :func:`default_scene` seen by a stereo pair with a little head
    motion (occlusions, disocclusions, out-of-frame taps, background without surface).

    ``head_motion=False`` gives the paper's same-instant case instead: a parallel rig (6.5 cm baseline), whose
    epipolar lines are image rows.

    Returns a tuple in the order of ``module.input_names``.
    """
    motion = dict(forward=0.05, yaw_deg=0.5) if head_motion else {}
    dst, src = camera_pair(height, width, batch, **motion)
    scene = default_scene()
    gd, gs = raycast(dst, scene), raycast(src, scene)
    g = torch.Generator().manual_seed(seed)
    noisy = gs.color * (0.5 + torch.rand(gs.color.shape, generator=g, dtype=gs.color.dtype))  # 1-spp-like
    f = Gbuffer(*(v.to(dtype) for v in gd))
    s = Gbuffer(*(v.to(dtype) for v in gs))
    by_name = {
        "src_color": noisy.to(dtype),
        "src_depth": s.depth,
        "src_normal": s.normal,
        "src_K": src.K.to(dtype),
        "src_cam_from_world": src.cam_from_world.to(dtype),
        "dst_depth": f.depth,
        "dst_normal": f.normal,
        "dst_K": dst.K.to(dtype),
        "dst_cam_from_world": dst.cam_from_world.to(dtype),
        "current_color": (f.color * (0.5 + torch.rand(f.color.shape, generator=g, dtype=f.color.dtype))),
        "depth": f.depth,
        "normal": f.normal,
        "K": dst.K.to(dtype),
        "cam_from_world": dst.cam_from_world.to(dtype),
        "history_color": s.color,
        "history_len": torch.full_like(s.depth, 3.0),
        "prev_depth": s.depth,
        "prev_normal": s.normal,
        "prev_K": src.K.to(dtype),
        "prev_cam_from_world": src.cam_from_world.to(dtype),
    }
    if "motion" in module.input_names:  # static geometry: the motion of the cameras, no world motion
        by_name["motion"] = camera_motion(gd.depth, dst.K, dst.cam_from_world, src.K, src.cam_from_world).to(dtype)
        by_name["motion_world"] = torch.zeros_like(f.normal)
    return tuple(by_name[n] for n in module.input_names)
