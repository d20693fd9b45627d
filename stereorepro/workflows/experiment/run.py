"""The experiment's run loop: per frame, render (or read from the cache) both eyes' inputs, run every scheme on
the same 1-spp inputs, and measure it against the reference as effective spp."""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from ..._version import __version__
from ...accumulate import SpatiotemporalReprojection
from ...camera import has_surface
from ...measure.metrics import effective_spp_many, flip, flip_available, rmse, ssim
from .cache import RenderCache
from .config import LEFT, RIGHT, ExperimentConfig, metric_image, validate_config
from .config import schemes as all_schemes
from .inputs import RenderContext, cache_footprint, estimate_cache_bytes, reference, render_eye, spec_for
from .report import write_frame_exr, write_outputs

__all__ = ["run_experiment"]


#: Frames before this one are the warm-up: every statistic is also reported over the frames from it on
#: (``avg_after_warmup``), where the histories have filled (an EMA at 20 % holds ~90 % of its weight in 10 frames).
WARMUP_FRAMES = 10


def _stats(xs) -> dict:
    warm = [x for x in xs[WARMUP_FRAMES:] if x is not None and math.isfinite(x)]
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    if not xs:
        return {"avg": None, "min": None, "max": None, "n": 0, "avg_after_warmup": None}
    return {"avg": float(np.mean(xs)), "min": float(np.min(xs)), "max": float(np.max(xs)), "n": len(xs),
            "avg_after_warmup": float(np.mean(warm)) if warm else None}



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
    cache_dir = Path(cfg.cache_dir) if cfg.cache_dir else out / "cache"
    cache = RenderCache(cache_dir, force=cfg.force, log=log)
    spec = spec_for(cfg, scene, cache_dir)
    code, moving = json.loads(spec.base_key)["code"], spec.moving
    need, free = estimate_cache_bytes(spec, frames), shutil.disk_usage(cache_dir).free
    if need > free:  # a warning, not an error: the cache may already hold most of it
        log(f"warning: the render cache needs up to {need / 2**30:.1f} GiB for {frames} frames "
            f"({need / (2 * frames) / 2**20:.0f} MiB per eye and frame) and {cache_dir} has "
            f"{free / 2**30:.1f} GiB free")
    t_start = time.perf_counter()  # the wall time includes a cluster's renders
    distributed = None
    if cfg.scheduler:  # every render runs on the cluster first; the loop below then reads the cache
        from .distributed import render_all

        distributed = render_all(spec, range(frames), cfg.scheduler, force=cfg.force, progress=cfg.progress,
                                 log=log)
        cache = RenderCache(cache_dir, log=log, sweep_on_start=False)  # the entries are made: no recomputing
    ctx = RenderContext(spec, cache=cache, scene=scene, tracer=PathTracer(scene, seed=cfg.seed, workers=cfg.workers))
    use_flip = bool(cfg.flip) and flip_available()
    schemes = all_schemes(cfg, moving)
    drivers = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                  stereo=s.stereo, temporal=s.temporal, left_mode=s.left_mode,
                                                  alternate=s.alternate) for s in schemes}
    # The same schemes fed with the noise-free references: their error is the resampling bias alone (bilinear blur
    # compounded over frames, edges), the part of the error that more samples cannot remove.
    clean = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                stereo=s.stereo, temporal=s.temporal) for s in schemes if s.paper}
    per_frame = []
    timing = {k: [] for k in ("trace_1spp_ms", "gbuffer_ms", "trace_left_discards_ms", "reference_ms")}
    timing.update({f"reproject_{s.name}_ms": [] for s in schemes})
    keep = {}  # frames kept for figures
    fig1_frame = frames // 2
    bar = tqdm(range(frames), desc=f"{scene.name} {W}x{H}", unit="frame", disable=not cfg.progress)
    for f in bar:
        eyes = {LEFT: render_eye(ctx, f, LEFT), RIGHT: render_eye(ctx, f, RIGHT)}
        L, R = eyes[LEFT], eyes[RIGHT]
        timing["trace_1spp_ms"] += [L.ms_per_spp, R.ms_per_spp]
        timing["gbuffer_ms"] += [L.ms_gbuffer, R.ms_gbuffer]
        timing["reference_ms"] += [L.ms_reference, R.ms_reference]
        surface = {e: has_surface(d.depth) for e, d in eyes.items()}
        row = {"frame": f, "discard_pct": {}, "rmse": {}, "effective_spp": {}, "flags": {},
               "ladder_rmse": {}, "no_surface_pct": {}, "rmse_noise_free": {}, "flip": {}, "ssim": {},
               "reference_study": {}}
        if moving:
            row.update(discard_pct_moving={}, discard_pct_static={}, moving_pct=100.0 * float(
                ((R.object_id >= 0) & surface[RIGHT]).float().mean()))
        ladder_spp = list(range(1, cfg.ladder_spp + 1))
        ladder_err = {}
        prefixes = eyes[LEFT].prefix_spp[:-1]  # smaller references for the reference-spp study (chunked runs)
        prefix_refs = {e: {p: metric_image(reference(ctx, f, e, p)[0], cfg.metric) for p in prefixes} for e in eyes}
        for e, d in eyes.items():
            errs = d.ladder_rmse[cfg.metric]
            ladder_err[e] = errs
            row["ladder_rmse"]["left" if e == LEFT else "right"] = errs
            row["no_surface_pct"]["left" if e == LEFT else "right"] = 100.0 * float((~surface[e]).float().mean())
        for s in schemes:
            drv = drivers[s.name]
            mv_r = (R.motion, R.motion_world) if s.motion else (None, None)
            mv_l = (L.motion, L.motion_world) if s.motion else (None, None)
            # the fully traced eye (the right one, or every other frame the left one with ``alternate``) and the
            # reprojected one, whose 1-spp samples are read only where the mask says "trace"
            (F, mv_f), (O, mv_o) = ((R, mv_r), (L, mv_l)) if drv.fully_traced_eye() == "right" else ((L, mv_l),
                                                                                                    (R, mv_r))
            t0 = time.perf_counter()
            full_out = drv.full(F.sample, F.depth, F.normal, F.K, F.cam_from_world, *mv_f)
            t1 = time.perf_counter()
            mask = drv.other_trace_mask(O.depth, O.normal, O.K, O.cam_from_world, *mv_o)
            other_out = drv.other(O.sample)
            t2 = time.perf_counter()
            right_out, left_out = (full_out, other_out) if F is R else (other_out, full_out)
            # per-eye accounting: a stereo scheme's left eye pays for its own steps, the right eye for its own
            timing[f"reproject_{s.name}_ms"].append((t2 - t1) * 1e3 if s.stereo else (t1 - t0) * 1e3)
            img = left_out if s.eye == LEFT else right_out
            d = eyes[s.eye]
            err = float(rmse(metric_image(img, cfg.metric), metric_image(d.reference, cfg.metric))[0])
            spp, flags = effective_spp_many(torch.tensor([err]), torch.tensor(ladder_spp, dtype=torch.float64),
                                            torch.tensor(ladder_err[s.eye], dtype=torch.float64))
            row["rmse"][s.name] = err
            if use_flip:
                row["flip"][s.name] = float(flip(img, d.reference)[0])
            if cfg.ssim and s.paper:  # LDR SSIM (clamp), the paper's three schemes: ~8 s per image at 720p here
                row["ssim"][s.name] = float(ssim(img, d.reference, tonemap="clamp")[0])
            if s.name in clean:
                c = clean[s.name]
                c_right = c.right(R.reference, R.depth, R.normal, R.K, R.cam_from_world, *mv_r)
                c.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world, *mv_l)
                c_left = c.left(L.reference)
                row["rmse_noise_free"][s.name] = float(rmse(metric_image(c_left if s.eye == LEFT else c_right,
                                                                          cfg.metric),
                                                            metric_image(d.reference, cfg.metric))[0])
            row["effective_spp"][s.name] = float(spp[0])
            if s.paper and prefixes:  # the same image scored against each smaller reference and its own ladder
                lad = torch.as_tensor(d.prefix_ladder_rmse[cfg.metric], dtype=torch.float64)
                for i, p in enumerate(prefixes):
                    e_p = rmse(metric_image(img, cfg.metric), prefix_refs[s.eye][p])
                    spp_p, _ = effective_spp_many(e_p, torch.tensor(ladder_spp, dtype=torch.float64), lad[i:i + 1])
                    row["reference_study"].setdefault(str(p), {})[s.name] = float(spp_p[0])
            row["flags"][s.name] = flags[0]
            if s.name == "stereo":
                surf = surface[LEFT]
                row["discard_pct"]["stereo"] = 100.0 * float((mask & surf).sum() / surf.sum().clamp_min(1))
                if f == fig1_frame:
                    keep["fig1_stereo"] = drv.stereo_reason.clone()
                    # the masked trace the paper counts, timed for real (same samples as the full 1-spp render)
                    r = ctx.tracer.render(L.camera, f, 1, sample_offset=0, eye=LEFT, gbuffers=False,
                                          pixel_mask=mask[0, 0], pixel_sampling=L.pixel_sampling)
                    timing["trace_left_discards_ms"].append(r.time_s * 1e3)
                    row["masked_trace_matches"] = bool(torch.equal(torch.where(mask, r.radiance, 0.0),
                                                                   torch.where(mask, L.sample, 0.0)))
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
                keep["fig4"] = {"method": left_out.clone(), "one": L.sample.clone(), "ref": L.reference.clone(),
                                "top": L.top.clone(), "spp": row["effective_spp"][s.name]}
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
    study = {p: {k: _stats([r["reference_study"][p][k] for r in per_frame]) for k in _study_schemes(per_frame, p)}
             for p in per_frame[0]["reference_study"]}
    if study:  # the run's own reference last, for comparison
        study[str(cfg.reference_spp)] = {k: table2[k] for k in next(iter(study.values()))}
    results = {
        "scene": scene.name, "effects": sorted(scene.effects), "frames": frames, "resolution": f"{W}x{H}",
        "reference_spp": cfg.reference_spp, "reference_chunk_spp": spec.reference_chunk_spp,
        "ladder_spp": cfg.ladder_spp, "warmup_frames": WARMUP_FRAMES, "reference_study": study or None,
        "seed": cfg.seed, "metric": cfg.metric, "jitter": bool(cfg.jitter),
        "thresholds": {"position": pos_thr, "normal": nrm_thr, "position_scene": float(scene.position_threshold),
                       "scale": scale},
        "table1": table1,
        "flip": ({s.name: _stats([r["flip"][s.name] for r in per_frame]) for s in schemes} if use_flip else None),
        "ssim": ({s.name: _stats([r["ssim"][s.name] for r in per_frame]) for s in schemes if s.paper}
                 if cfg.ssim else None),
        **({"moving_objects": moving_table} if moving else {}),
        "table2": {k: table2[k] for k in ("stereo", "temporal", "stereo_temporal")},
        "table2_variants": {k: v for k, v in table2.items() if k not in ("stereo", "temporal", "stereo_temporal")},
        "timing_ms": timing_ms, "cost": cost, "bias": bias, "per_frame": per_frame,
        "flags": _flag_counts(per_frame), "cache": {"hits": cache.hits, "misses": cache.misses,
                                                     "recomputed_corrupt": cache.corrupt,
                                                     "dir": str(cache_dir), **cache_footprint(ctx, frames)},
        "distributed": distributed,
        "wall_s": wall, "version": __version__, "code": code,
    }
    write_outputs(out, results, per_frame, keep, cfg)
    return results


def _study_schemes(per_frame, p: str) -> list[str]:
    return list(per_frame[0]["reference_study"][p])


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
