"""Helpers shared by the render tests (imported explicitly; not a pytest conftest)."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import torch

from stereorepro.camera import PinholeCamera, intrinsics_from_fov, look_at


def write_scene(tmp_path: Path, body: str, name: str = "test_scene") -> Path:
    """Write a scene TOML (with default camera / reprojection tables unless given) and return its path."""
    body = textwrap.dedent(body)
    if "[camera]" not in body:
        body += "\n[camera]\nvfov_deg = 60.0\npositions = [[0.0, 0.0, -3.0]]\ntargets = [[0.0, 0.0, 0.0]]\n"
    if "[reprojection]" not in body:
        body += "\n[reprojection]\nposition_threshold = 0.05\nnormal_threshold = 0.25\n"
    p = tmp_path / f"{name}.toml"
    p.write_text(body)
    return p


def box_scene(tmp_path: Path, albedo: float, emission: float, half: float = 1.0, center=(0.0, 0.0, 0.0)) -> Path:
    """A closed box (enclosure) whose every surface has the same albedo and emission."""
    lo = [c - half for c in center]
    hi = [c + half for c in center]
    return write_scene(
        tmp_path,
        f"""
        effects = []
        num_frames = 1
        [geometry]
        boxes = [{{min = {lo}, max = {hi}, material = "wall"}}]
        [materials.wall]
        albedo = [{albedo}, {albedo}, {albedo}]
        emission = [{emission}, {emission}, {emission}]
        [camera]
        vfov_deg = 60.0
        positions = [[{center[0]}, {center[1]}, {center[2] - 0.5 * half}]]
        targets = [[{center[0]}, {center[1]}, {center[2] + half}]]
        """,
        "furnace",
    )


def camera_looking(eye, target, up=(0.0, 1.0, 0.0), width=32, height=32, vfov=60.0) -> PinholeCamera:
    t = lambda a: torch.tensor([a], dtype=torch.float64)  # noqa: E731
    return PinholeCamera(
        intrinsics_from_fov(vfov, width, height, dtype=torch.float64), look_at(t(eye), t(target), t(up)), height, width
    )


def plane_point_light_scene(
    tmp_path: Path, albedo=0.5, intensity=2.0, height=1.0, scale=1.0, offset=(0.0, 0.0, 0.0), extra=""
) -> Path:
    """A square plane y = offset_y (side 20*scale) under a point light at height*scale above (offset)."""
    s = 10.0 * scale
    ox, oy, oz = offset
    return write_scene(
        tmp_path,
        f"""
        effects = []
        num_frames = 1
        [geometry]
        quads = [{{corner = [{ox - s}, {oy}, {oz - s}], edge_u = [{2 * s}, 0.0, 0.0], edge_v = [0.0, 0.0, {2 * s}], material = "floor"}}]
        {extra}
        [materials.floor]
        albedo = [{albedo}, {albedo}, {albedo}]
        [materials.block]
        albedo = [0.5, 0.5, 0.5]
        [[lights]]
        type = "point"
        intensity = [{intensity}, {intensity}, {intensity}]
        position = [{ox}, {oy + height * scale}, {oz}]
        """,
        "plane",
    )


def plane_radiance(points_world: torch.Tensor, light, albedo, intensity) -> torch.Tensor:
    """Analytic radiance (N,) of a Lambertian plane y = const at points (N, 3) under a point light (3,)."""
    d = torch.as_tensor(light, dtype=torch.float64) - points_world.double()
    d2 = (d * d).sum(-1)
    cos = d[:, 1] / d2.sqrt()
    return albedo / math.pi * intensity * cos / d2
