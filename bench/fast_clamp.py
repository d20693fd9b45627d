"""Fast-history clamping (NVIDIA NRD's RELAX, ``SpatiotemporalReprojection.fast_clamp``): what it does to lag on the
moving-light scenes and to the error on static ones, at the paper's EMA (alpha 0.2) and a slower one (0.1).

For each scene the first ``--frames`` frames of its camera path are rendered for both eyes: two independent 1-spp
streams with G-buffers, and a ``--reference-spp`` reference in two independent halves A and B. Each variant (slow
alpha × clamp settings) runs the stereo+temporal driver (the paper's fill) over each 1-spp stream; its right eye is
the temporal scheme (scored on the right eye), its left eye the stereo+temporal scheme (scored on the left eye).
Everything is scored in LDR (clamped to [0, 1]), over all pixels:

* **MSE** against the reference (A + B)/2 (includes the reference's own noise, the same for every variant);
* **bias²**, the squared error of the scheme's *expected* output: ``mean((o₁ − A)·(o₂ − B))`` with o₁, o₂ the
  outputs of the two independent 1-spp streams, A and B the independent reference halves: every cross term of
  independent noises has zero mean, so this estimates ``mean((E[o] − truth)²)`` without the noise of the 1-spp
  input or of the references. On the moving-light scenes it is mostly lag; on the static ones resampling bias
  (and whatever bias the clamp adds).
* **variance** ≈ MSE − bias² − the reference halves' noise (estimated as ``mean((A − B)²)/4``).

Means over frames 1..F−1 and over frames ``WARMUP``..F−1 (after the slow EMA's warm-up).

    nice -n 5 .venv/bin/python bench/fast_clamp.py --resolution 640x360 --frames 20 --reference-spp 16

Writes bench/results/fast_clamp.json|md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _bench_common import header, save

from stereorepro import FastClamp, SpatiotemporalReprojection
from stereorepro.reproject import functional
from stereorepro.render import PathTracer
from stereorepro.scenes import load_scene

SCENES = ("living_room_moving_light", "atrium_moving_light", "living_room", "classroom")
ALPHAS = (0.2, 0.1)
CLAMPS = (None, FastClamp(0.5, 2.0, 1), FastClamp(0.33, 2.0, 1), FastClamp(0.25, 2.0, 1), FastClamp(0.5, 1.0, 1))
WARMUP = 8
EYES = {"left": 0, "right": 1}


def render_scene(name: str, W: int, H: int, frames: int, ref_spp: int, seed: int) -> tuple[list[dict], tuple]:
    """Per frame and eye: G-buffer, two independent 1-spp streams and two independent reference halves."""
    scene = load_scene(name)
    tracer = PathTracer(scene, seed=seed)
    half = ref_spp // 2
    out = []
    for f in range(frames):
        cams = scene.stereo_cameras(f, W, H)
        per_eye = {}
        for eye, i in EYES.items():
            cam = cams[i]
            r0 = tracer.render(cam, f, 1, sample_offset=0, eye=i)
            r1 = tracer.render(cam, f, 1, sample_offset=1, eye=i, gbuffers=False)
            a = tracer.render(cam, f, half, sample_offset=2, eye=i, gbuffers=False).radiance.float()
            b = tracer.render(cam, f, half, sample_offset=2 + half, eye=i, gbuffers=False).radiance.float()
            per_eye[eye] = dict(
                gbuffer=(r0.depth.float(), r0.normal.float(), cam.K, cam.cam_from_world),
                noisy=(r0.radiance.float(), r1.radiance.float()),
                ref=(a.clamp(0, 1), b.clamp(0, 1)),
            )
        out.append(per_eye)
    return out, scene.thresholds(H)


def run_variant(frames: list[dict], thr: tuple, alpha: float, clamp, stream: int) -> list[dict]:
    """The stereo+temporal driver over one 1-spp stream: per frame the LDR outputs of both eyes."""
    st = SpatiotemporalReprojection(*thr, alpha=alpha)
    st.fast_clamp = clamp
    outs = []
    with torch.no_grad():
        for fr in frames:
            r, lf = fr["right"], fr["left"]
            right = st.right(r["noisy"][stream], *r["gbuffer"])
            st.left_trace_mask(*lf["gbuffer"])
            left = st.left(lf["noisy"][stream])
            outs.append({"right": right.clamp(0, 1), "left": left.clamp(0, 1)})
    return outs


def score(frames: list[dict], o1: list[dict], o2: list[dict]) -> dict:
    """Per frame (1..) and scheme: MSE of stream 1 against the reference, bias² by the cross product, the
    reference halves' noise."""
    per = {s: {"mse": [], "bias2": [], "ref_noise": []} for s in ("temporal", "stereo_temporal")}
    for fr, a1, a2 in list(zip(frames, o1, o2))[1:]:
        for scheme, eye in (("temporal", "right"), ("stereo_temporal", "left")):
            A, B = fr[eye]["ref"]
            ref = 0.5 * (A + B)
            per[scheme]["mse"].append(float((a1[eye] - ref).square().mean()))
            per[scheme]["bias2"].append(float(((a1[eye] - A) * (a2[eye] - B)).mean()))
            per[scheme]["ref_noise"].append(float((A - B).square().mean() / 4))
    return per


def summary(per: dict) -> dict:
    out = {}
    for scheme, d in per.items():
        out[scheme] = {}
        for part, sl in (("all", slice(0, None)), ("after_warmup", slice(WARMUP - 1, None))):
            mse, bias2, noise = (float(np.mean(d[k][sl])) for k in ("mse", "bias2", "ref_noise"))
            out[scheme][part] = {
                "mse": mse,
                "rmse": mse**0.5,
                "bias2": bias2,
                "variance": mse - bias2 - noise,
                "ref_noise": noise,
            }
    return out


def label(clamp) -> str:
    return "off" if clamp is None else f"a={clamp.alpha:g} s={clamp.sigma:g} r={clamp.radius}"


def table(results: dict, part: str) -> str:
    rows = [
        "| scene | scheme | slow alpha | clamp | RMSE | change | bias² | change | variance | change |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, res in results.items():
        for scheme in ("temporal", "stereo_temporal"):
            for alpha in ALPHAS:
                base = res[f"{alpha:g}"]["off"][scheme][part]
                for clamp in CLAMPS:
                    m = res[f"{alpha:g}"][label(clamp)][scheme][part]

                    def pct(k):
                        return "" if clamp is None else f"{100 * (m[k] / base[k] - 1):+.1f} %"

                    rows.append(
                        f"| {name} | {scheme} | {alpha:g} | {label(clamp)} | {m['rmse']:.4f} | {pct('rmse')} | "
                        f"{m['bias2']:.3e} | {pct('bias2')} | {m['variance']:.3e} | {pct('variance')} |"
                    )
    return "\n".join(rows) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--resolution", default="640x360")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--reference-spp", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    W, H = (int(x) for x in args.resolution.split("x"))
    record = header() | {
        "command": "bench/fast_clamp.py "
        + " ".join(
            f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
            for k, v in vars(args).items()
        ),
        "resolution": [W, H],
        "frames": args.frames,
        "reference_spp": args.reference_spp,
        "warmup_frames_skipped": WARMUP - 1,
        "clamps": [label(c) for c in CLAMPS],
        "scenes": {},
    }
    results = {}
    for name in args.scenes:
        t0 = time.perf_counter()
        frames, thr = render_scene(name, W, H, args.frames, args.reference_spp, args.seed)
        t1 = time.perf_counter()
        res = {"thresholds": list(thr), "render_s": t1 - t0}
        for alpha in ALPHAS:
            res[f"{alpha:g}"] = {}
            for clamp in CLAMPS:
                o1 = run_variant(frames, thr, alpha, clamp, 0)
                o2 = run_variant(frames, thr, alpha, clamp, 1)
                per = score(frames, o1, o2)
                res[f"{alpha:g}"][label(clamp)] = summary(per) | {"per_frame": per}
                s = res[f"{alpha:g}"][label(clamp)]
                print(
                    f"{name} alpha {alpha:g} {label(clamp)}: temporal rmse {s['temporal']['all']['rmse']:.4f} "
                    f"bias2 {s['temporal']['all']['bias2']:.3e}; stereo+temporal rmse "
                    f"{s['stereo_temporal']['all']['rmse']:.4f} bias2 {s['stereo_temporal']['all']['bias2']:.3e}",
                    flush=True,
                )
        res["schemes_s"] = time.perf_counter() - t1
        res["backend"] = functional.select_backend("auto", [frames[0]["right"]["noisy"][0]])
        record["scenes"][name] = res
        results[name] = res
        del frames
    md = (
        f"Fast-history clamping, {W}x{H}, frames 0..{args.frames - 1} of each scene's path, the stereo+temporal "
        f"driver (fill; warm-up EMA at the slow alpha, the scene's thresholds): temporal = its right eye, "
        f"stereo_temporal = its left eye. LDR (clamped to [0, 1]), all pixels. RMSE against {args.reference_spp}-spp "
        "references (their noise included); bias² = mean((o₁ − A)(o₂ − B)) over two independent 1-spp runs and "
        "two independent reference halves (the error of the expected output: lag on the moving-light scenes, "
        "resampling bias on the static ones); variance = MSE − bias² − reference noise. Changes against the same "
        f"slow alpha without the clamp. Command: `nice -n 5 .venv/bin/python {record['command']}`.\n\n"
        f"## All frames (1..{args.frames - 1})\n\n" + table(results, "all") + "\n"
        f"## After the warm-up (frames {WARMUP}..{args.frames - 1})\n\n" + table(results, "after_warmup")
    )
    save("fast_clamp", record, md)


if __name__ == "__main__":
    main()
