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


def render_eye(tracer, cache: RenderCache, base_key: dict, camera, frame: int, eye: int, cfg: ExperimentConfig
                ) -> EyeData:
    key = dict(base_key, frame=frame, eye=eye)

    def gbuf():
        r = tracer.gbuffer(camera, frame)
        return ({"depth": r.depth.numpy(), "normal": r.normal.numpy()},
                {"ms": r.time_s * 1e3, "rays": r.ray_counts})

    g, gmeta = cache.get_or_make(dict(key, kind="gbuffer"), gbuf)
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
    return EyeData(torch.from_numpy(g["depth"]), torch.from_numpy(g["normal"]), camera.K.float(),
                   camera.cam_from_world.double(), rungs, torch.from_numpy(rd["radiance"]), gmeta["ms"],
                   float(np.mean(times)), rmeta["ms"], camera)
