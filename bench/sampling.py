"""Catmull-Rom against bilinear history reads (``sampling="catmull_rom"``): the temporal scheme on real scenes.

For each scene the right eye is rendered over the first ``--frames`` frames of the scene's camera path: 1 spp with
G-buffers, and a ``--reference-spp`` reference from an independent sample stream. Each sampling then runs the
experiment's temporal scheme (``temporal_reproject``, the scene's thresholds at this resolution, alpha 0.2 with
warm-up) over

* the 1-spp frames, scored against the references (LDR: clamped to [0, 1]; MSE over all pixels): what a user sees,
  resampling blur and noise averaging together;
* the G-buffer albedo, noise-free and exactly known at every frame, scored against the current frame's albedo: the
  resampling error alone, on the scene's own content (textures included), with no reference noise in it; once
  point-sampled at the pixel centres (as the G-buffer is: hard texture edges alias) and once box-filtered over
  3×3 sub-pixel centres (``albedo_aa``: rendered at 3× the resolution and averaged, the pixel filter the radiance
  references converge to).

Also reported: the share of the surface pixels whose whole 4×4 footprint passes the tests (where Catmull-Rom
replaces the bilinear value). Means over frames 1..F−1 and over frames 4..F−1 (after the warm-up). Each
``--position-scales`` factor multiplies the scene's position threshold (1: the experiment's; the absolute position
test rejects footprint taps 1.5–2 pixels away on slanted surfaces, larger factors show what the cubic does where
more footprints pass).

    .venv/bin/python bench/sampling.py --scenes living_room living_room_textured --resolution 320x180 \\
        --frames 12 --reference-spp 64 --position-scales 1 3

Writes bench/results/sampling.json|md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _bench_common import header, save

from stereorepro import History, Thresholds, View, backward_reproject, temporal_reproject
from stereorepro.camera import has_surface
from stereorepro.render import PathTracer
from stereorepro.scenes import load_scene

SAMPLINGS = ("bilinear", "catmull_rom")
WARMUP = 4


def render_frames(name: str, W: int, H: int, frames: int, ref_spp: int, seed: int) -> list[dict]:
    """Per frame: the right eye's View, 1-spp radiance, reference radiance and albedo (float32)."""
    scene = load_scene(name)
    tracer = PathTracer(scene, seed=seed)
    out = []
    for f in range(frames):
        cam = scene.stereo_cameras(f, W, H)[1]
        r = tracer.render(cam, f, 1, sample_offset=0, eye=1)
        ref = tracer.render(cam, f, ref_spp, sample_offset=1, eye=1, gbuffers=False).radiance
        view = View(r.depth.float(), r.normal.float(), cam.K, cam.cam_from_world)
        fine = tracer.render(scene.stereo_cameras(f, 3 * W, 3 * H)[1], f, 1, eye=1).albedo.float()
        albedo_aa = torch.nn.functional.avg_pool2d(fine, 3)
        out.append(
            dict(view=view, noisy=r.radiance.float(), ref=ref.float(), albedo=r.albedo.float(), albedo_aa=albedo_aa)
        )
    return out


def run_scheme(frames: list[dict], thr: Thresholds, sampling: str) -> dict:
    """The temporal scheme over the noisy frames and over the albedo: per-frame errors (frames 1..)."""
    hist = {k: History.empty(frames[0]["view"]) for k in ("noisy", "albedo", "albedo_aa")}
    prev = frames[0]["view"]
    err = {"mse_ldr": [], "albedo_mse": [], "albedo_aa_mse": [], "cubic_share": []}
    g = torch.Generator().manual_seed(0)
    for i, fr in enumerate(frames):
        view = fr["view"]
        for k in hist:
            out = temporal_reproject(fr[k], view, hist[k], prev, thr, sampling=sampling)
            hist[k] = out.history
            if i == 0:
                continue
            if k == "noisy":
                err["mse_ldr"].append(float((out.color.clamp(0, 1) - fr["ref"].clamp(0, 1)).square().mean()))
            else:
                err[f"{k}_mse"].append(float((out.color - fr[k]).square().mean()))
        if i and sampling == "catmull_rom":  # where the cubic applies: a random image's warps differ there
            probe = torch.rand(1, 3, *view.depth.shape[-2:], generator=g)
            cub = backward_reproject(probe, prev, view.without_motion(), thr, sampling="catmull_rom").values
            bil = backward_reproject(probe, prev, view.without_motion(), thr).values
            surface = has_surface(view.depth)[0, 0]
            err["cubic_share"].append(float((cub != bil).any(1)[0][surface].float().mean()))
        prev = view
    return err


def summary(per_frame: dict) -> dict:
    return {
        k: {"all": float(np.mean(v)), "after_warmup": float(np.mean(v[WARMUP - 1 :]))}
        for k, v in per_frame.items()
        if v
    }


def table_rows(name: str, thr: Thresholds, res: dict) -> list[str]:
    """The Markdown rows of one scene and threshold (all frames, after the warm-up)."""
    b, c = res["bilinear"]["mean"], res["catmull_rom"]["mean"]
    rows = []
    for part in ("all", "after_warmup"):
        rows.append(
            f"| {name} | {thr.position:g} | {part} | {b['mse_ldr'][part]:.4e} | {c['mse_ldr'][part]:.4e} | "
            f"{100 * (c['mse_ldr'][part] / b['mse_ldr'][part] - 1):+.1f} % | {b['albedo_mse'][part]:.4e} | "
            f"{c['albedo_mse'][part]:.4e} | {b['albedo_mse'][part] / c['albedo_mse'][part]:.2f}x | "
            f"{b['albedo_aa_mse'][part]:.4e} | {c['albedo_aa_mse'][part]:.4e} | "
            f"{b['albedo_aa_mse'][part] / c['albedo_aa_mse'][part]:.2f}x | {100 * c['cubic_share'][part]:.1f} % |"
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["living_room", "living_room_textured"])
    ap.add_argument("--resolution", default="320x180")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--reference-spp", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--position-scales", type=float, nargs="+", default=[1.0])
    args = ap.parse_args()
    W, H = (int(x) for x in args.resolution.split("x"))
    record = header() | {
        "resolution": [W, H],
        "frames": args.frames,
        "reference_spp": args.reference_spp,
        "alpha": 0.2,
        "warmup_frames_skipped": WARMUP - 1,
        "scenes": {},
    }
    rows = []
    for name in args.scenes:
        t0 = time.perf_counter()
        frames = render_frames(name, W, H, args.frames, args.reference_spp, args.seed)
        render_s = time.perf_counter() - t0
        for scale in args.position_scales:
            pos, nrm = load_scene(name).thresholds(H)
            thr = Thresholds(pos * scale, nrm)
            res = {"thresholds": [thr.position, thr.normal], "position_scale": scale, "render_s": render_s}
            for s in SAMPLINGS:
                per_frame = run_scheme(frames, thr, s)
                res[s] = {"per_frame": per_frame, "mean": summary(per_frame)}
            record["scenes"][f"{name} x{scale:g}"] = res
            rows += table_rows(name, thr, res)
            print(*rows[-2:], sep="\n", flush=True)
    md = (
        f"Temporal scheme (right eye), {W}x{H}, frames 0..{args.frames - 1} of each scene's path, alpha 0.2 with "
        f"warm-up, the scene's normal threshold and its position threshold times each scale; noisy: 1 spp against {args.reference_spp}-spp references (LDR, "
        "clamped to [0, 1]); albedo: the noise-free G-buffer albedo through the same scheme against the current "
        "frame's albedo (resampling error alone). 'after warm-up': frames "
        f"{WARMUP}..{args.frames - 1}.\n\n"
        "| scene | position threshold | frames | noisy MSE bilinear | noisy MSE catmull_rom | change | albedo MSE bilinear | "
        "albedo MSE catmull_rom | ratio | box-filtered albedo MSE bilinear | catmull_rom | ratio | "
        "surface pixels with the cubic |\n"
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n" + "\n".join(rows) + "\n"
    )
    save("sampling", record, md)


if __name__ == "__main__":
    main()
