"""Which pixels decide a scene's temporal effective spp (e.g. why Classroom's is low).

Runs the temporal scheme (right eye, EMA at each ``--alphas`` weight) over an experiment's cached renders (or renders
them), and after the warm-up frames splits the LDR squared error by region:

* by the reference: saturated (a channel >= 1), bright, mid, dark; high-contrast edges (top 5 %) and the rest;
* by the history length of each pixel this frame (1 = history lost, 2-4, 5-9, >= 10);
* by this frame's temporal discard reason;

and reports per region its pixel share, its share of the squared error, how much of its error is bias (the same
scheme fed the noise-free references), and its effective spp from a two-rung ladder (1 spp and the top rung) —
plus the same with the saturated pixels or the edges left out of the metric, and maps of one frame.

    .venv/bin/python bench/error_anatomy.py --scene shared_classroom --resolution 1280x720 --frames 30 \\
        --reference-spp 32 --reference-chunk-spp 16 --ladder-spp 32 --cache-dir /work/runs720/cache \\
        --renderer-version 9e51c24cf7b5e039

Writes bench/results/error_anatomy_<scene>_<W>x<H>.json|md and a figure beside them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _bench_common import RESULTS, header, save

from stereorepro.accumulate import SpatiotemporalReprojection
from stereorepro.camera import DEFAULT_RESOLUTION, has_surface
from stereorepro.measure.anatomy import edge_mask, error_concentration, error_shares, squared_error, two_rung_spp
from stereorepro.workflows.experiment import ExperimentConfig
from stereorepro.workflows.experiment.config import RIGHT, metric_image
from stereorepro.workflows.experiment.inputs import RenderContext, render_eye, spec_for
from stereorepro.workflows.experiment.run import WARMUP_FRAMES
from stereorepro.reproject import Reason
from stereorepro.scenes import load_scene, threshold_scale

HIST_BINS = (("hist 1 (lost)", 1, 1), ("hist 2-4", 2, 4), ("hist 5-9", 5, 9), ("hist >= 10", 10, 1e9))


def regions(ref: torch.Tensor, surface: torch.Tensor, hist: torch.Tensor, reason: torch.Tensor | None) -> dict:
    lum = ref.mean(1, keepdim=True)
    sat = (ref >= 1.0).any(1, keepdim=True)
    out = {
        "saturated (ref >= 1)": sat,
        "bright (0.3-1)": ~sat & (lum >= 0.3),
        "mid (0.05-0.3)": (lum >= 0.05) & (lum < 0.3) & ~sat,
        "dark (< 0.05)": lum < 0.05,
    }
    edges = edge_mask(ref.clamp(0, 1))
    out["edges (top 5 % contrast)"] = edges
    out["not edges"] = ~edges
    for name, lo, hi in HIST_BINS:
        out[name] = surface & (hist >= lo) & (hist <= hi)
    out["no surface"] = ~surface
    if reason is not None:
        for r in Reason:
            m = reason == int(r)
            if bool(m.any()):
                out[f"reason {r.name.lower()}"] = m
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="classroom")
    ap.add_argument("--resolution", default="{}x{}".format(*DEFAULT_RESOLUTION))
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--reference-spp", type=int, default=64)
    ap.add_argument("--reference-chunk-spp", type=int, default=None)
    ap.add_argument("--ladder-spp", type=int, default=16)
    ap.add_argument("--alphas", default="0.2,0.1")
    ap.add_argument("--cache-dir", default=str(RESULTS.parent / ".cache"))
    ap.add_argument("--renderer-version", default=None)
    ap.add_argument("--figure-frame", type=int, default=None, help="default: the last frame")
    ap.add_argument(
        "--normal-scale",
        type=float,
        default=1.0,
        help="multiply the scene's normal threshold (what looser tests would keep)",
    )
    ap.add_argument("--position-scale", type=float, default=1.0, help="multiply the scene's position threshold")
    args = ap.parse_args()
    W, H = (int(v) for v in args.resolution.split("x"))
    cfg = ExperimentConfig(
        scene=args.scene,
        out=".",
        frames=args.frames,
        width=W,
        height=H,
        reference_spp=args.reference_spp,
        ladder_spp=args.ladder_spp,
        reference_chunk_spp=args.reference_chunk_spp,
        renderer_version=args.renderer_version,
    )
    scene = load_scene(args.scene)
    ctx = RenderContext(spec_for(cfg, scene, Path(args.cache_dir)), scene=scene)
    pos_thr, nrm_thr = scene.thresholds(H, threshold_scale(H))
    pos_thr, nrm_thr = pos_thr * args.position_scale, nrm_thr * args.normal_scale
    alphas = [float(a) for a in args.alphas.split(",")]
    drv = {a: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=a, stereo=False) for a in alphas}
    clean = {a: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=a, stereo=False) for a in alphas}
    fig_frame = args.frames - 1 if args.figure_frame is None else args.figure_frame
    acc = {a: {} for a in alphas}  # region -> sums over the frames after warm-up
    conc, fig = {a: [] for a in alphas}, None
    L = args.ladder_spp

    def add(a, name, m, se, se_b, se1, seL):
        d = acc[a].setdefault(name, {"n": 0, "se": 0.0, "bias": 0.0, "se1": 0.0, "seL": 0.0, "total": 0.0})
        d["n"] += int(m.sum())
        d["se"] += float(se[m].sum())
        d["bias"] += float(se_b[m].sum())
        d["se1"] += float(se1[m].sum())
        d["seL"] += float(seL[m].sum())
        d["total"] += float(se.sum())

    for f in range(args.frames):
        R = render_eye(ctx, f, RIGHT)
        ref = metric_image(R.reference, "ldr")
        se1 = squared_error(metric_image(R.sample, "ldr"), ref)
        seL = squared_error(metric_image(R.top, "ldr"), ref)
        surface = has_surface(R.depth)
        for a in alphas:
            out = drv[a].right(R.sample, R.depth, R.normal, R.K, R.cam_from_world)
            out_c = clean[a].right(R.reference, R.depth, R.normal, R.K, R.cam_from_world)
            if f < WARMUP_FRAMES and f != fig_frame:
                continue
            se = squared_error(metric_image(out, "ldr"), ref)
            se_b = squared_error(metric_image(out_c, "ldr"), ref)
            hist = drv[a].right_state.history_len
            reg = regions(R.reference, surface, hist, drv[a].right_reason)
            if f == fig_frame and a == alphas[0]:
                fig = {
                    "se": se[0, 0].numpy(),
                    "hist": hist[0, 0].numpy(),
                    "ref": ref[0].permute(1, 2, 0).numpy(),
                    "sat": reg["saturated (ref >= 1)"][0, 0].numpy(),
                    "edges": reg["edges (top 5 % contrast)"][0, 0].numpy(),
                    "out": metric_image(out, "ldr")[0].permute(1, 2, 0).numpy(),
                }
                fig_shares = error_shares(se, reg, se_b)
                fig_conc = error_concentration(se)
            if f < WARMUP_FRAMES:
                continue
            conc[a].append(error_concentration(se))
            every = torch.ones_like(surface)
            for name, m in {
                "all pixels": every,
                **reg,
                "all but saturated": ~reg["saturated (ref >= 1)"],
                "all but edges": ~reg["edges (top 5 % contrast)"],
                "all but saturated and edges": ~reg["saturated (ref >= 1)"] & ~reg["edges (top 5 % contrast)"],
            }.items():
                add(a, name, m, se, se_b, se1, seL)
        print(f"frame {f}", flush=True)

    report = {}
    for a in alphas:
        rows = {}
        total = acc[a]["all pixels"]["se"]
        for name, d in acc[a].items():
            n = max(d["n"], 1)
            rows[name] = {
                "pixels_pct": 100.0 * d["n"] / acc[a]["all pixels"]["n"],
                "se_share_pct": 100.0 * d["se"] / total if total else None,
                "bias_pct_of_region": 100.0 * d["bias"] / d["se"] if d["se"] else None,
                "effective_spp_two_rung": two_rung_spp(d["se"] / n, d["se1"] / n, d["seL"] / n, L),
            }
        report[str(a)] = {
            "regions": rows,
            "concentration": {k: float(np.mean([c[k] for c in conc[a]])) for k in conc[a][0]},
        }
    rec = {
        **header(),
        "scene": args.scene,
        "resolution": f"{W}x{H}",
        "frames": args.frames,
        "thresholds": {"position": pos_thr, "normal": nrm_thr},
        "after_warmup_from": WARMUP_FRAMES,
        "reference_spp": args.reference_spp,
        "ladder_spp": L,
        "alphas": report,
        "figure_frame": {"frame": fig_frame, "regions": fig_shares, "concentration": fig_conc},
    }
    lines = [
        f"Error anatomy of the temporal scheme, {args.scene} {W}×{H}, frames {WARMUP_FRAMES}..{args.frames - 1} "
        f"(LDR squared error; reference {args.reference_spp} spp; two-rung ladder 1 and {L} spp; thresholds: "
        f"position {pos_thr:g}, normal {nrm_thr:g})",
        "",
    ]
    for a in alphas:
        r = report[str(a)]
        lines += [
            f"**alpha = {a}**: the worst 1 % of pixels hold {r['concentration']['top_1pct']:.0f} % of the "
            f"squared error, the worst 5 % {r['concentration']['top_5pct']:.0f} %",
            "",
            "| region | pixels % | share of squared error % | bias % of its error | effective spp |",
            "|---|---:|---:|---:|---:|",
        ]
        for name, v in r["regions"].items():
            e, b = v["effective_spp_two_rung"], v["bias_pct_of_region"]
            lines.append(
                f"| {name} | {v['pixels_pct']:.1f} | {v['se_share_pct']:.1f} | "
                f"{'–' if b is None else f'{b:.0f}'} | {'–' if e is None else f'{e:.1f}'} |"
            )
        lines.append("")
    name = f"error_anatomy_{args.scene}_{W}x{H}"
    if args.normal_scale != 1.0 or args.position_scale != 1.0:
        name += f"_pos{args.position_scale:g}_nrm{args.normal_scale:g}"
    save(name, rec, "\n".join(lines) + "\n", script="error_anatomy.py")
    if fig is not None:
        _figure(fig, RESULTS / f"{name}.png", f"{args.scene} {W}x{H}, frame {fig_frame}, alpha {alphas[0]}")
    print("\n".join(lines))


def _figure(fig: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f, ax = plt.subplots(2, 2, figsize=(12, 7))
    ax[0, 0].imshow(fig["ref"] ** (1 / 2.2))
    ax[0, 0].set_title("reference (LDR)")
    ax[0, 1].imshow(fig["out"] ** (1 / 2.2))
    ax[0, 1].set_title("temporal")
    im = ax[1, 0].imshow(np.log10(fig["se"] + 1e-6), cmap="magma")
    ax[1, 0].set_title("log10 squared error")
    plt.colorbar(im, ax=ax[1, 0])
    im = ax[1, 1].imshow(fig["hist"], cmap="viridis", vmax=12)
    ax[1, 1].set_title("history length")
    plt.colorbar(im, ax=ax[1, 1])
    for a in ax.flat:
        a.axis("off")
    f.suptitle(title)
    f.tight_layout()
    from stereorepro.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        f.savefig(tmp, format="png", dpi=80)
    plt.close(f)


if __name__ == "__main__":
    main()
