"""One frame's inputs to the experiment, per eye: G-buffer, the ladder of 1..L-spp prefix means and the reference,
each rendered once and cached (:class:`~.cache.RenderCache`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .cache import RenderCache
from .config import REFERENCE_OFFSET, ExperimentConfig

__all__ = ["EyeData", "render_eye"]


@dataclass
class EyeData:
    depth: torch.Tensor  # (1, 1, H, W)
    normal: torch.Tensor  # (1, 3, H, W)
    K: torch.Tensor  # (1, 3, 3)
    cam_from_world: torch.Tensor  # (1, 4, 4)
    ladder: list[torch.Tensor]  # prefix means at 1..L spp, each (1, 3, H, W)
    reference: torch.Tensor  # (1, 3, H, W)
    ms_gbuffer: float
    ms_per_spp: float  # mean wall time of one 1-spp full-frame render
    ms_reference: float
    camera: object = None
    motion: torch.Tensor | None = None  # (1, 2, H, W) to the previous frame (moving objects, frame > 0)
    motion_world: torch.Tensor | None = None  # (1, 3, H, W)
    object_id: torch.Tensor | None = None  # (1, 1, H, W) int32, -1 static (moving objects)


def render_eye(tracer, cache: RenderCache, base_key: dict, camera, frame: int, eye: int, cfg: ExperimentConfig,
               prev_camera=None) -> EyeData:
    """One eye's inputs; with ``prev_camera`` (scenes with moving objects, frame > 0) the G-buffer includes the
    motion to the previous frame and the moving objects' ids (cached under their own key)."""
    key = dict(base_key, frame=frame, eye=eye)
    motion = prev_camera is not None or getattr(tracer, "moving_objects", False)

    def gbuf():
        r = tracer.gbuffer(camera, frame, prev_camera=prev_camera)
        out = {"depth": r.depth.numpy(), "normal": r.normal.numpy()}
        for name in ("motion", "motion_world", "object_id"):
            if getattr(r, name) is not None:
                out[name] = getattr(r, name).numpy()
        return out, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    g, gmeta = cache.get_or_make(dict(key, kind="gbuffer_motion" if motion else "gbuffer",
                                      **({"prev": prev_camera is not None} if motion else {})), gbuf)
    rungs, times = [], []
    total = None
    for s in range(cfg.ladder_spp):
        def one(s=s):
            r = tracer.render(camera, frame, 1, sample_offset=s, eye=eye, gbuffers=False)
            return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

        d, meta = cache.get_or_make(dict(key, kind="spp", spp=1, offset=s), one)
        x = torch.from_numpy(d["radiance"]).double()
        total = x if total is None else total + x
        rungs.append((total / (s + 1)).float())
        times.append(meta["ms"])

    def ref():
        r = tracer.render(camera, frame, cfg.reference_spp, sample_offset=REFERENCE_OFFSET, eye=eye, gbuffers=False,
                          progress=False)
        return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    rd, rmeta = cache.get_or_make(dict(key, kind="spp", spp=cfg.reference_spp, offset=REFERENCE_OFFSET), ref)
    opt = {k: torch.from_numpy(g[k]) for k in ("motion", "motion_world", "object_id") if k in g}
    return EyeData(torch.from_numpy(g["depth"]), torch.from_numpy(g["normal"]), camera.K.float(),
                   camera.cam_from_world.double(), rungs, torch.from_numpy(rd["radiance"]), gmeta["ms"],
                   float(np.mean(times)), rmeta["ms"], camera, **opt)
