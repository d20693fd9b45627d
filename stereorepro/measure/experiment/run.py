"""The experiment's run loop: per frame, render (or read from the cache) both eyes' inputs, run every scheme on
the same 1-spp inputs, and measure it against the reference as effective spp."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from ... import __version__
from ...accumulate import SpatiotemporalReprojection
from ...camera import has_surface
from ..metrics import effective_spp_many, flip, flip_available, ladder_rmse, rmse
from .cache import RenderCache, code_version, scene_fingerprint
from .config import LEFT, RIGHT, ExperimentConfig, validate_config
from .config import schemes as all_schemes
from .inputs import render_eye
from .report import write_frame_exr, write_outputs

__all__ = ["run_experiment"]


def _stats(xs) -> dict:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    if not xs:
        return {"avg": None, "min": None, "max": None, "n": 0}
    return {"avg": float(np.mean(xs)), "min": float(np.min(xs)), "max": float(np.max(xs)), "n": len(xs)}


def _metric_image(x: torch.Tensor, metric: str) -> torch.Tensor:
    return x.clamp(0.0, 1.0) if metric == "ldr" else x


def run_experiment(cfg: ExperimentConfig, log=print) -> dict:
    """Run the experiment and write its outputs into ``cfg.out``. Returns the ``results.json`` content."""
    from tqdm.auto import tqdm

    from ...render import PathTracer
    from ...scenes import load_scene, threshold_scale

    validate_config(cfg)
    scene = load_scene(cfg.scene)
    frames = scene.num_frames if cfg.frames is None else int(cfg.frames)
    if not 1 <= frames <= scene.num_frames:
        raise ValueError(f"frames must be in 1..{scene.num_frames} for scene {scene.name!r}, got {frames}")
    out = Path(cfg.out)  # everything is checked: only now is anything created
    out.mkdir(parents=True, exist_ok=True)
    W, H = cfg.width, cfg.height
    scale = cfg.threshold_scale if cfg.threshold_scale is not None else threshold_scale(H)
    pos_thr, nrm_thr = scene.thresholds(H, scale)
    tracer = PathTracer(scene, seed=cfg.seed, workers=cfg.workers)
    cache = RenderCache(Path(cfg.cache_dir) if cfg.cache_dir else out / "cache", force=cfg.force, log=log)
    code = cfg.renderer_version or code_version()
    base_key = {"scene": scene_fingerprint(scene), "code": code, "seed": cfg.seed, "w": W, "h": H}
    moving = "moving_objects" in scene.effects
    use_flip = bool(cfg.flip) and flip_available()
    schemes = all_schemes(cfg, moving)
    drivers = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                  stereo=s.stereo, temporal=s.temporal) for s in schemes}
    # The same schemes fed with the noise-free references: their error is the resampling bias alone (bilinear blur
    # compounded over frames, edges), the part of the error that more samples cannot remove.
    clean = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                stereo=s.stereo, temporal=s.temporal) for s in schemes if s.paper}
    per_frame = []
    timing = {k: [] for k in ("trace_1spp_ms", "gbuffer_ms", "trace_left_discards_ms", "reference_ms")}
    timing.update({f"reproject_{s.name}_ms": [] for s in schemes})
    keep = {}  # frames kept for figures
    fig1_frame = frames // 2
    t_start = time.perf_counter()
    bar = tqdm(range(frames), desc=f"{scene.name} {W}x{H}", unit="frame", disable=not cfg.progress)
    for f in bar:
        left_cam, right_cam = scene.stereo_cameras(f, W, H)
        prev = scene.stereo_cameras(f - 1, W, H) if moving and f > 0 else (None, None)
        eyes = {LEFT: render_eye(tracer, cache, base_key, left_cam, f, LEFT, cfg, prev[LEFT]),
                RIGHT: render_eye(tracer, cache, base_key, right_cam, f, RIGHT, cfg, prev[RIGHT])}
        L, R = eyes[LEFT], eyes[RIGHT]
        timing["trace_1spp_ms"] += [L.ms_per_spp, R.ms_per_spp]
        timing["gbuffer_ms"] += [L.ms_gbuffer, R.ms_gbuffer]
        timing["reference_ms"] += [L.ms_reference, R.ms_reference]
        surface = {e: has_surface(d.depth) for e, d in eyes.items()}
        row = {"frame": f, "discard_pct": {}, "rmse": {}, "effective_spp": {}, "flags": {},
               "ladder_rmse": {}, "no_surface_pct": {}, "rmse_noise_free": {}, "flip": {}}
        if moving:
            row.update(discard_pct_moving={}, discard_pct_static={}, moving_pct=100.0 * float(
                ((R.object_id >= 0) & surface[RIGHT]).float().mean()))
        ladder_spp = list(range(1, cfg.ladder_spp + 1))
        ladder_err = {}
        for e, d in eyes.items():
            errs = ladder_rmse([_metric_image(x, cfg.metric) for x in d.ladder],
                               _metric_image(d.reference, cfg.metric))[0].tolist()
            ladder_err[e] = errs
            row["ladder_rmse"]["left" if e == LEFT else "right"] = errs
            row["no_surface_pct"]["left" if e == LEFT else "right"] = 100.0 * float((~surface[e]).float().mean())
        for s in schemes:
            drv = drivers[s.name]
            mv_r = (R.motion, R.motion_world) if s.motion else (None, None)
            mv_l = (L.motion, L.motion_world) if s.motion else (None, None)
            t0 = time.perf_counter()
            right_out = drv.right(R.ladder[0], R.depth, R.normal, R.K, R.cam_from_world, *mv_r)
            t1 = time.perf_counter()
            mask = drv.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world, *mv_l)
            left_out = drv.left(L.ladder[0])  # the left 1-spp samples; only masked pixels are read
            t2 = time.perf_counter()
            # per-eye accounting: a stereo scheme's left eye pays for its own steps, the right eye for its own
            timing[f"reproject_{s.name}_ms"].append((t2 - t1) * 1e3 if s.stereo else (t1 - t0) * 1e3)
            img = left_out if s.eye == LEFT else right_out
            d = eyes[s.eye]
            err = float(rmse(_metric_image(img, cfg.metric), _metric_image(d.reference, cfg.metric))[0])
            spp, flags = effective_spp_many(torch.tensor([err]), torch.tensor(ladder_spp, dtype=torch.float64),
                                            torch.tensor(ladder_err[s.eye], dtype=torch.float64))
            row["rmse"][s.name] = err
            if use_flip:
                row["flip"][s.name] = float(flip(img, d.reference)[0])
            if s.name in clean:
                c = clean[s.name]
                c_right = c.right(R.reference, R.depth, R.normal, R.K, R.cam_from_world, *mv_r)
                c.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world, *mv_l)
                c_left = c.left(L.reference)
                row["rmse_noise_free"][s.name] = float(rmse(_metric_image(c_left if s.eye == LEFT else c_right,
                                                                          cfg.metric),
                                                            _metric_image(d.reference, cfg.metric))[0])
            row["effective_spp"][s.name] = float(spp[0])
            row["flags"][s.name] = flags[0]
            if s.name == "stereo":
                surf = surface[LEFT]
                row["discard_pct"]["stereo"] = 100.0 * float((mask & surf).sum() / surf.sum().clamp_min(1))
                if f == fig1_frame:
                    keep["fig1_stereo"] = drv.stereo_reason.clone()
                    # the masked trace the paper counts, timed for real (same samples as the full 1-spp render)
                    r = tracer.render(L.camera, f, 1, sample_offset=0, eye=LEFT, gbuffers=False,
                                      pixel_mask=mask[0, 0])
                    timing["trace_left_discards_ms"].append(r.time_s * 1e3)
                    row["masked_trace_matches"] = bool(torch.equal(torch.where(mask, r.radiance, 0.0),
                                                                   torch.where(mask, L.ladder[0], 0.0)))
            if s.name in ("temporal", "temporal_mv") and drv.right_valid is not None:
                surf = surface[RIGHT]
                row["discard_pct"][s.name] = 100.0 * float((~drv.right_valid & surf).sum()
                                                           / surf.sum().clamp_min(1))
                if moving:  # discards on the moving objects' pixels and on the static rest
                    mov = (R.object_id >= 0) & surf
                    for part, sel in (("discard_pct_moving", mov), ("discard_pct_static", surf & ~mov)):
                        row[part][s.name] = (100.0 * float((~drv.right_valid & sel).sum() / sel.sum())
                                             if bool(sel.any()) else None)
                if f == fig1_frame:
                    keep["fig1_" + s.name] = drv.right_reason.clone()
            if s.name == "stereo_temporal" and f == frames - 1:
                keep["fig4"] = {"method": left_out.clone(), "one": L.ladder[0].clone(), "ref": L.reference.clone(),
                                "top": L.ladder[-1].clone(), "spp": row["effective_spp"][s.name]}
        if cfg.exr:
            write_frame_exr(out / "exr", f, eyes, drivers)
        per_frame.append(row)
        bar.set_postfix(st=f"{row['effective_spp']['stereo_temporal']:.1f}spp", cache=f"{cache.hits}/{cache.misses}")
    wall = time.perf_counter() - t_start

    table1 = {"stereo": _stats([r["discard_pct"].get("stereo") for r in per_frame]),
              "temporal": _stats([r["discard_pct"].get("temporal") for r in per_frame])}
    moving_table = None
    if moving:  # temporal discards on moving-object pixels vs the static background, camera-only vs motion vectors
        moving_table = {"moving_pixels_pct": _stats([r["moving_pct"] for r in per_frame]),
                        **{k: {part: _stats([r[f"discard_pct_{part}"].get(k) for r in per_frame])
                               for part in ("moving", "static")} for k in ("temporal", "temporal_mv")}}
    table2 = {s.name: _stats([r["effective_spp"][s.name] for r in per_frame]) for s in schemes}
    timing_ms = {k: float(np.median(v)) if v else None for k, v in timing.items()}
    cost = _cost_table(schemes, table2, timing_ms, cfg)
    bias = {k: {"rmse_noise_free": _stats([r["rmse_noise_free"][k] for r in per_frame]),
                "bias_share_of_mse": _stats([(r["rmse_noise_free"][k] / r["rmse"][k]) ** 2 for r in per_frame
                                             if r["rmse"][k] > 0])} for k in clean}
    bias["ladder_top_rmse"] = _stats([r["ladder_rmse"]["left"][-1] for r in per_frame])
    results = {
        "scene": scene.name, "effects": sorted(scene.effects), "frames": frames, "resolution": f"{W}x{H}",
        "reference_spp": cfg.reference_spp, "ladder_spp": cfg.ladder_spp, "seed": cfg.seed, "metric": cfg.metric,
        "thresholds": {"position": pos_thr, "normal": nrm_thr, "position_scene": float(scene.position_threshold),
                       "scale": scale},
        "table1": table1,
        "flip": ({s.name: _stats([r["flip"][s.name] for r in per_frame]) for s in schemes} if use_flip else None),
        **({"moving_objects": moving_table} if moving else {}),
        "table2": {k: table2[k] for k in ("stereo", "temporal", "stereo_temporal")},
        "table2_variants": {k: v for k, v in table2.items() if k not in ("stereo", "temporal", "stereo_temporal")},
        "timing_ms": timing_ms, "cost": cost, "bias": bias, "per_frame": per_frame,
        "flags": _flag_counts(per_frame), "cache": {"hits": cache.hits, "misses": cache.misses,
                                                     "recomputed_corrupt": cache.corrupt},
        "wall_s": wall, "version": __version__, "code": code,
    }
    write_outputs(out, results, per_frame, keep, cfg)
    return results


def _flag_counts(per_frame) -> dict:
    counts: dict = {}
    for r in per_frame:
        for k, fl in r["flags"].items():
            counts.setdefault(k, {}).setdefault(fl, 0)
            counts[k][fl] += 1
    return counts


def _cost_table(schemes, table2, t, cfg) -> list[dict]:
    """ms per frame of the evaluated eye for each scheme and for plain path tracing at n spp.

    Per-eye cost accounting: the stereo schemes' left eye costs its G-buffer, the reprojection and the traced
    discards (the right eye is paid for once, by itself); temporal's right eye costs its 1-spp trace, its G-buffer
    and the reprojection. G-buffers are counted although a real renderer gets them with the primary ray.
    """
    spp_ms = t["trace_1spp_ms"]
    gb = t["gbuffer_ms"]
    masked = t["trace_left_discards_ms"] or 0.0
    rows = [{"scheme": f"path tracing {n} spp", "ms": n * spp_ms, "effective_spp": float(n),
             "ms_per_effective_spp": spp_ms} for n in (1, 2, 4, 8, 16) if n <= cfg.ladder_spp]
    for s in schemes:
        rep = t[f"reproject_{s.name}_ms"]
        if s.stereo:
            ms = gb + rep + masked
        else:
            ms = spp_ms + gb + rep
        e = table2[s.name]["avg"]
        rows.append({"scheme": s.name, "ms": ms, "effective_spp": e,
                     "ms_per_effective_spp": (ms / e) if e else None, "reprojection_ms": rep})
    return rows
