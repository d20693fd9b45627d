"""A production denoiser downstream: Intel Open Image Denoise (``pip install pyoidn``) with and without our
reprojection, on held-out frames of the built-in scenes.

    python examples/oidn_denoise.py --out runs/oidn          # full: 3 scenes, 160x90, 1024-spp references
    python examples/oidn_denoise.py --smoke --out /tmp/oidn  # what CI runs

Per scene, frames 0..F-1 are traced at 1 spp per eye (the G-buffer's albedo and normal are OIDN's auxiliary
images), and both eyes of the last ``--eval`` frames are scored against references (LDR RMSE, effective spp on a
1..8-spp ladder of the same pixels, as the experiment does):

* both eyes: ``1 spp`` and ``OIDN(1 spp)``, the raw samples and OIDN on them;
* left eye: ``stereo+temporal`` (the paper's scheme), ``OIDN(stereo+temporal)`` (OIDN on its output) and
  ``OIDN, then stereo+temporal`` (OIDN on every 1-spp frame of both eyes, those fed through the same scheme);
* right eye: the same with temporal accumulation alone: ``temporal``, ``OIDN(temporal)``, ``OIDN, then temporal``.

The reference's own noise is estimated from its two independent halves and reported as a share of the best
method's MSE (it must stay below 10 % for the ranking to mean anything). ms/frame are medians of the OIDN calls
and of the reprojection steps on this machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

METHODS = ("1 spp", "OIDN(1 spp)", "stereo+temporal", "OIDN(stereo+temporal)", "OIDN, then stereo+temporal")
#: The right eye's methods: temporal accumulation alone (the stereo step feeds the left eye).
RIGHT_METHODS = ("1 spp", "OIDN(1 spp)", "temporal", "OIDN(temporal)", "OIDN, then temporal")


def oidn(color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, times: list) -> torch.Tensor:
    """OIDN (RT filter, HDR, auxiliary images from the G-buffer) on a (1, 3, H, W) image."""
    import pyoidn

    c = np.ascontiguousarray(color[0].permute(1, 2, 0).numpy().astype(np.float32).clip(0, None))
    a = np.ascontiguousarray(albedo[0].permute(1, 2, 0).numpy().astype(np.float32).clip(0, 1))
    n = np.ascontiguousarray(normal[0].permute(1, 2, 0).numpy().astype(np.float32))
    t0 = time.perf_counter()
    out = pyoidn.denoise(c, albedo=a, normal=n, hdr=True)
    times.append((time.perf_counter() - t0) * 1e3)
    return torch.from_numpy(np.asarray(out)).permute(2, 0, 1)[None].contiguous()


def ldr(x: torch.Tensor) -> torch.Tensor:
    return x.clamp(0.0, 1.0)


def rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.sqrt(torch.mean((ldr(a) - ldr(b)).double() ** 2)))


def run_scene(name: str, W: int, H: int, frames: int, n_eval: int, ref_spp: int, seed: int) -> dict:
    from stereorepro import SpatiotemporalReprojection, load_scene
    from stereorepro.camera import Eye
    from stereorepro.render import PathTracer

    scene = load_scene(name)
    tracer = PathTracer(scene, seed=seed)
    pos, nrm = scene.thresholds(H)
    plain = SpatiotemporalReprojection(pos, nrm)
    after_oidn = SpatiotemporalReprojection(pos, nrm)
    first = scene.num_frames // 2 - frames // 2
    t_oidn, t_rep = [], []
    rows = []
    for k in range(frames):
        f = first + k
        left_cam, right_cam = scene.stereo_cameras(f, W, H)
        R = tracer.render(right_cam, f, 1, eye=Eye.RIGHT)
        L = tracer.render(left_cam, f, 1, eye=Eye.LEFT)
        t0 = time.perf_counter()
        tr_right = plain.right(R.radiance, R.depth, R.normal, right_cam.K, right_cam.cam_from_world)
        plain.left_trace_mask(L.depth, L.normal, left_cam.K, left_cam.cam_from_world)
        st = plain.left(L.radiance)
        t_rep.append((time.perf_counter() - t0) * 1e3)
        dR, dL = (oidn(x.radiance, x.albedo, x.normal, t_oidn) for x in (R, L))
        then_right = after_oidn.right(dR, R.depth, R.normal, right_cam.K, right_cam.cam_from_world)
        after_oidn.left_trace_mask(L.depth, L.normal, left_cam.K, left_cam.cam_from_world)
        then = after_oidn.left(dL)
        if k < frames - n_eval:
            continue
        per_eye = {
            "left": (
                left_cam,
                Eye.LEFT,
                L.radiance,
                {
                    "1 spp": L.radiance,
                    "OIDN(1 spp)": dL,
                    "stereo+temporal": st,
                    "OIDN(stereo+temporal)": oidn(st, L.albedo, L.normal, t_oidn),
                    "OIDN, then stereo+temporal": then,
                },
            ),
            "right": (
                right_cam,
                Eye.RIGHT,
                R.radiance,
                {
                    "1 spp": R.radiance,
                    "OIDN(1 spp)": dR,
                    "temporal": tr_right,
                    "OIDN(temporal)": oidn(tr_right, R.albedo, R.normal, t_oidn),
                    "OIDN, then temporal": then_right,
                },
            ),
        }
        rows.append(
            {
                "frame": f,
                **{
                    eye: score(tracer, cam, f, key, one, images, ref_spp)
                    for eye, (cam, key, one, images) in per_eye.items()
                },
            }
        )

    def summary(eye: str, methods) -> dict:
        return {
            m: {
                "rmse": statistics.mean(r[eye]["methods"][m]["rmse"] for r in rows),
                "effective_spp": statistics.mean(r[eye]["methods"][m]["effective_spp"] for r in rows),
                "flags": sorted({r[eye]["methods"][m]["flag"] for r in rows}),
            }
            for m in methods
        }

    return {
        "scene": name,
        "resolution": f"{W}x{H}",
        "frames": frames,
        "evaluated_frames": [r["frame"] for r in rows],
        "reference_spp": ref_spp,
        "methods": summary("left", METHODS),
        "methods_right": summary("right", RIGHT_METHODS),
        "per_frame": rows,
        "reference_noise_share_of_best_mse": max(
            r[e]["reference_noise_share_of_best_mse"] for r in rows for e in ("left", "right")
        ),
        "ms_oidn_median": statistics.median(t_oidn),
        "ms_reprojection_median": statistics.median(t_rep),
    }


def score(tracer, cam, f: int, eye, one_spp: torch.Tensor, images: dict, ref_spp: int) -> dict:
    """RMSE and effective spp of ``images`` against a ``ref_spp`` reference of one eye, and the reference's own
    noise (from its two independent halves) as a share of the best method's MSE."""
    from stereorepro import effective_spp

    half = ref_spp // 2
    ra = tracer.render(cam, f, half, sample_offset=1 << 24, eye=eye, gbuffers=False).radiance
    rb = tracer.render(cam, f, half, sample_offset=(1 << 24) + half, eye=eye, gbuffers=False).radiance
    ref = 0.5 * (ra + rb)
    ref_noise_mse = rmse(ra, rb) ** 2 / 4  # the halves differ by twice the full mean's noise variance
    ladder, total = [], None
    for s in range(8):  # 1..8-spp prefix means (sample 0 is the 1-spp frame itself)
        x = one_spp if s == 0 else tracer.render(cam, f, 1, sample_offset=s, eye=eye, gbuffers=False).radiance
        total = x.double() if total is None else total + x.double()
        ladder.append(rmse((total / (s + 1)).float(), ref))
    out = {"reference_noise_mse": ref_noise_mse, "methods": {}}
    for m, img in images.items():
        e = rmse(img, ref)
        spp, flag = effective_spp(e, list(range(1, 9)), ladder)
        out["methods"][m] = {"rmse": e, "effective_spp": spp, "flag": flag}
    best = min(v["rmse"] for v in out["methods"].values()) ** 2
    out["reference_noise_share_of_best_mse"] = ref_noise_mse / best if best > 0 else None
    return out


def _cell(v: dict) -> str:
    """RMSE, then effective spp: ``~`` marks a value extrapolated beyond the 8-spp ladder, ``>8`` one below the
    ladder's fitted floor (the ladder cannot say how many spp it is worth)."""
    spp = v["effective_spp"]
    if not np.isfinite(spp):
        return f"{v['rmse']:.4f} (>8 spp)"
    mark = "~" if any(f.startswith("extrapolated") for f in v["flags"]) else ""
    return f"{v['rmse']:.4f} ({mark}{spp:.1f} spp)"


def table(results: list[dict]) -> str:
    lines = [
        "| scene, eye | 1 spp | OIDN(1 spp) | reprojected | OIDN(reprojected) | OIDN, then reprojected | "
        "ref. noise / best MSE | OIDN ms | reprojection ms |",
        "|---|" + "---:|" * 8,
    ]
    for r in results:
        for eye, key, methods in (
            ("left: stereo+temporal", "methods", METHODS),
            ("right: temporal", "methods_right", RIGHT_METHODS),
        ):
            cells = [_cell(r[key][m]) for m in methods]
            lines.append(
                f"| {r['scene']}, {eye} | "
                + " | ".join(cells)
                + " | "
                + (
                    f"{100 * r['reference_noise_share_of_best_mse']:.1f} % | {r['ms_oidn_median']:.0f} | "
                    f"{r['ms_reprojection_median']:.0f} |"
                    if key == "methods"
                    else " | | |"
                )
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/oidn")
    p.add_argument("--smoke", action="store_true", help="one scene, 48x27, 4 frames, 64-spp reference")
    p.add_argument("--scenes", default="living_room,classroom,atrium")
    p.add_argument("--resolution", default="160x90")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--eval", type=int, default=3, help="held-out frames scored at the end of the sequence")
    p.add_argument("--reference-spp", type=int, default=1024)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.smoke:
        scenes, (W, H), frames, n_eval, ref = ["living_room"], (48, 27), 4, 1, 64
    else:
        scenes = a.scenes.split(",")
        W, H = (int(v) for v in a.resolution.split("x"))
        frames, n_eval, ref = a.frames, a.eval, a.reference_spp
    results = [run_scene(s, W, H, frames, n_eval, ref, a.seed) for s in scenes]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from stereorepro.io.atomic import atomic_write

    doc = {"results": results, "table": table(results), "smoke": a.smoke}
    atomic_write(out / "oidn_denoise.json", json.dumps(doc, indent=1))
    atomic_write(out / "oidn_denoise.md", "LDR RMSE (effective spp) on held-out frames\n\n" + doc["table"])
    print(doc["table"])
    return doc


if __name__ == "__main__":
    main()
