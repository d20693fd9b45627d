"""The experiment's outputs: ``results.json``, ``tables.md``, ``report.md``, ``report.html`` and the figures (1, 3,
4 and the time-cost plot), each written atomically."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..._extras import require
from ...io.atomic import atomic_path, atomic_write, staged_outputs
from ...reproject import reason_to_rgb
from .config import LEFT, SCHEMES
from .report_html import write_report_html

__all__ = ["tables_markdown", "cost_markdown", "write_outputs", "write_frame_exr"]


def _fmt(x, nd=2):
    return "–" if x is None else f"{x:.{nd}f}"


def _spp(st: dict, key: str = "avg") -> str:
    """An effective-spp average; with frames beyond the ladder's top rung, its lower bound as ``≥ x``."""
    if st.get("beyond_ladder"):
        return "≥ " + _fmt(st.get(f"{key}_lower_bound"))
    return _fmt(st.get(key))


def _beyond_note(stats: dict, results: dict) -> list[str]:
    beyond = {k: v["beyond_ladder"] for k, v in stats.items() if v.get("beyond_ladder")}
    if not beyond:
        return []
    return [
        "",
        f"≥: frames whose error lies below the ladder's top rung ({results['ladder_spp']} spp), counted at the top "
        "rung (a lower bound; their extrapolated values, biased high, stay in results.json): "
        + ", ".join(f"{k} {n}" for k, n in beyond.items())
        + ". A longer ladder (--ladder-spp, with --reference-spp at least as long) measures them.",
    ]


def tables_markdown(results: dict) -> str:
    """``tables.md``: Table 1 (discarded pixels, %) and Table 2 (effective spp) of a run's ``results``, then the
    after-warm-up averages, the paper's schemes' temporal error, the reference study and the moving-objects table when
    ``results`` has them.

    Examples:
        >>> from stereorepro.workflows.experiment.report import tables_markdown
        >>> row = {"avg": 4.0, "min": 2.0, "max": 6.0}
        >>> results = {"scene": "box", "frames": 2, "resolution": "8x6", "reference_spp": 64, "ladder_spp": 16,
        ...            "table1": {"stereo": row, "temporal": row},
        ...            "table2": {"stereo": row, "temporal": row, "stereo_temporal": row}}
        >>> md = tables_markdown(results)
        >>> md.splitlines()[4]
        '| stereo | 4.00 | 2.00 | 6.00 |'
        >>> md.splitlines()[-1]
        '| box | 4.00 | 2.00 | 6.00 | 4.00 | 2.00 | 6.00 | 4.00 | 2.00 | 6.00 |'
    """
    t1, t2 = results["table1"], results["table2"]
    lines = [
        f"**Table 1** — discarded pixels (%), {results['scene']}, {results['frames']} frames, {results['resolution']}",
        "",
        "| | Avg | Min | Max |",
        "|---|---:|---:|---:|",
    ]
    for k in ("stereo", "temporal"):
        lines.append(f"| {k} | {_fmt(t1[k]['avg'])} | {_fmt(t1[k]['min'])} | {_fmt(t1[k]['max'])} |")
    lines += [
        "",
        f"**Table 2** — effective spp ({results.get('metric', 'hdr').upper()} RMSE, reference "
        f"{results['reference_spp']} spp, ladder 1..."
        f"{results['ladder_spp']} spp)",
        "",
        "| | Stereo Avg | Min | Max | Temporal Avg | Min | Max | Stereo+temporal Avg | Min | Max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    cells = []
    for k in ("stereo", "temporal", "stereo_temporal"):
        cells += [_spp(t2[k]), _fmt(t2[k]["min"]), _fmt(t2[k]["max"])]
    lines.append(f"| {results['scene']} | " + " | ".join(cells) + " |")
    lines += _beyond_note(t2, results)
    warm = results.get("warmup_frames")
    if warm is not None and t2["stereo"].get("avg_after_warmup") is not None:
        lines += [
            "",
            f"After warm-up (frames {warm}..{results['frames'] - 1}): "
            + ", ".join(f"{k} {_spp(t2[k], 'avg_after_warmup')}" for k in ("stereo", "temporal", "stereo_temporal"))
            + "; discards "
            + ", ".join(f"{k} {_fmt(t1[k].get('avg_after_warmup'))} %" for k in ("stereo", "temporal")),
        ]
    lines += _temporal_table(results)
    study = results.get("reference_study")
    if study:
        keys = list(next(iter(study.values())))
        lines += [
            "",
            "**Reference spp** — the same images scored against references of fewer samples (prefixes of "
            "the run's reference) and ladders scored on each: effective spp (avg over frames)",
            "",
            "| reference spp | " + " | ".join(keys) + " |",
            "|---:|" + "---:|" * len(keys),
        ]
        for p, row in study.items():
            lines.append(f"| {p} | " + " | ".join(_fmt(row[k]["avg"]) for k in keys) + " |")
    if "moving_objects" in results:
        lines += ["", moving_markdown(results)]
    return "\n".join(lines) + "\n"


def _temporal_table(results: dict) -> list[str]:
    """The temporal error of the paper's schemes (lines of ``tables.md``); none when ``results`` has no such
    statistics."""
    te = results.get("temporal_error")
    rows = [k for k in ("stereo", "temporal", "stereo_temporal") if te and k in te]
    if not rows:
        return []
    lines = [
        "",
        f"**Temporal error** (lower = steadier) — the frame-to-frame change of the output minus the reference's, the "
        f"previous frame warped by the known motion ({results.get('metric', 'hdr').upper()} RMSE, frames 1.."
        f"{results['frames'] - 1})",
        "",
        "| | Avg | Min | Max |",
        "|---|---:|---:|---:|",
    ]
    for k in rows:
        lines.append(f"| {k} | {_fmt(te[k]['avg'], 4)} | {_fmt(te[k]['min'], 4)} | {_fmt(te[k]['max'], 4)} |")
    return lines


def moving_markdown(results: dict) -> str:
    """Moving objects: temporal discards on the moving objects' pixels and on the static rest, and effective spp,
    with camera-only warping (the paper's) and with motion vectors."""
    mo, t2, var = results["moving_objects"], results["table2"], results["table2_variants"]
    lines = [
        f"**Moving objects** — {_fmt(mo['moving_pixels_pct']['avg'], 1)} % of the right eye's pixels show "
        "moving objects (avg); temporal discards (%, avg over frames) and effective spp (avg)",
        "",
        "| warping | discards on moving objects | discards on static background | temporal spp | stereo+temporal spp |",
        "|---|---:|---:|---:|---:|",
    ]
    for label, k, st in (
        ("cameras only (paper)", "temporal", "stereo_temporal"),
        ("motion vectors", "temporal_mv", "stereo_temporal_mv"),
    ):
        spp_t = (t2 if k in t2 else var)[k]["avg"]
        spp_st = (t2 if st in t2 else var)[st]["avg"]
        lines.append(
            f"| {label} | {_fmt(mo[k]['moving']['avg'], 1)} | {_fmt(mo[k]['static']['avg'], 1)} | "
            f"{_fmt(spp_t)} | {_fmt(spp_st)} |"
        )
    return "\n".join(lines) + "\n"


def cost_markdown(results: dict) -> str:
    """The time-cost table of ``results["cost"]``: per scheme, ms per frame, effective spp and their ratio.

    Examples:
        >>> from stereorepro.workflows.experiment.report import cost_markdown
        >>> cost = [{"scheme": "stereo", "ms": 12.5, "effective_spp": 2.5, "ms_per_effective_spp": 5.0}]
        >>> print(cost_markdown({"cost": cost}).splitlines()[-1])
        | stereo | 12.5 | 2.50 | 5.0 |
    """
    lines = [
        "| scheme | ms / frame (evaluated eye) | effective spp (avg) | ms per effective spp |",
        "|---|---:|---:|---:|",
    ]
    for r in results["cost"]:
        ge, le = ("≥ ", "≤ ") if r.get("beyond_ladder") else ("", "")
        lines.append(
            f"| {r['scheme']} | {_fmt(r['ms'], 1)} | {ge}{_fmt(r['effective_spp'])} | "
            f"{le}{_fmt(r['ms_per_effective_spp'], 1)} |"
        )
    return "\n".join(lines) + "\n"


def _tonemap(x: torch.Tensor) -> np.ndarray:
    """(1, 3, H, W) linear → (H, W, 3) sRGB-ish in [0, 1] (clamp, gamma 2.2)."""
    return np.clip(x[0].permute(1, 2, 0).numpy(), 0, 1) ** (1 / 2.2)


def write_outputs(out: Path, results: dict, per_frame, keep, cfg) -> None:
    """Write the figures, ``tables.md``, ``report.md``, ``report.html`` and ``results.json`` into ``out`` as one set
    (:func:`~stereorepro.io.atomic.staged_outputs`): all of them or none, ``results.json`` last.

    Examples:
        >>> import os, tempfile
        >>> from pathlib import Path
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.run import run_experiment
        >>> from stereorepro.workflows.experiment.report import write_outputs
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, frames=2, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, flip=False, ssim=False, progress=False)
        >>> results = run_experiment(cfg, log=lambda message: None)  # a few seconds: renders, scores, figures
        >>> out = Path(tmp.name) / "again"
        >>> write_outputs(out, results, results["per_frame"], {}, cfg)  # no kept images: Figures 1 and 4 left out
        >>> sorted(os.listdir(out))
        ['fig3_rmse.png', 'fig_cost.png', 'report.html', 'report.md', 'results.json', 'tables.md']
        >>> tmp.cleanup()
    """
    with staged_outputs(out, last=["results.json"]) as stage:
        _write_outputs(stage, results, per_frame, keep, cfg)


def _write_outputs(out: Path, results: dict, per_frame, keep, cfg) -> None:
    matplotlib = require("matplotlib", "the experiment's figures")
    matplotlib.use("Agg")
    plt = require("matplotlib.pyplot", "the experiment's figures")

    def save(fig, name):
        try:
            with atomic_path(out / name) as tmp:
                fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
        finally:
            plt.close(fig)

    for figure in (_figure1, _figure3, _figure4, _figure_cost):
        made = figure(plt, results, per_frame, keep, cfg)
        if made is not None:
            save(*made)
    write_report_html(out, results, keep)  # embeds the figures written above
    atomic_write(out / "results.json", json.dumps(results, indent=1))
    tables = tables_markdown(results)
    atomic_write(out / "tables.md", tables)
    atomic_write(out / "report.md", _report_markdown(results, tables))


def _figure1(plt, results, per_frame, keep, cfg):
    """Figure 1: the discard reasons of the stereo and temporal steps (and temporal with motion vectors)."""
    if "fig1_stereo" not in keep:
        return None
    panels = [("fig1_stereo", "(a) Stereo"), ("fig1_temporal", "(b) Temporal")]
    if "fig1_temporal_mv" in keep:  # moving objects: the temporal discards with motion vectors beside
        panels = [
            ("fig1_stereo", "(a) Stereo"),
            ("fig1_temporal", "(b) Temporal, cameras only"),
            ("fig1_temporal_mv", "(c) Temporal, motion vectors"),
        ]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 3.2))
    for ax, (key, title) in zip(axes, panels):
        if key in keep:
            ax.imshow(reason_to_rgb(keep[key])[0].permute(1, 2, 0).numpy())
        ax.set_title(title)
        ax.axis("off")
    fig.suptitle("Discarded pixels: green position, cyan normal, red out of frame")
    return fig, "fig1_discards.png"


def _figure3(plt, results, per_frame, keep, cfg):
    """Figure 3: framewise RMSE of each paper scheme on its evaluated eye, against that eye's ladder rungs: (a) the
    left eye (stereo, stereo + temporal), (b) the right eye (temporal). The legend sits below the panels."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    fr = [r["frame"] for r in per_frame]
    rungs = [n for n in (1, 2, 8, 16) if n <= cfg.ladder_spp]
    greys = dict(zip(rungs, ("0.15", "0.35", "0.55", "0.75")))
    panels = [
        (axes[0], "left", ("stereo", "stereo_temporal"), "(a) left eye"),
        (axes[1], "right", ("temporal",), "(b) right eye"),
    ]
    colours = {"stereo": "tab:blue", "stereo_temporal": "tab:red", "temporal": "tab:green"}
    for ax, eye, names, title in panels:
        for n in rungs:
            ax.plot(
                fr,
                [r["ladder_rmse"][eye][n - 1] for r in per_frame],
                "--",
                lw=1,
                color=greys[n],
                label=f"path tracing, {n} spp",
            )
        for k in names:
            ax.plot(fr, [r["rmse"][k] for r in per_frame], lw=2, color=colours[k], label=k.replace("_", " + "))
        ax.set_xlabel("frame")
        ax.set_title(title, fontsize=10)
        ax.set_yscale("log")
    axes[0].set_ylabel(f"RMSE ({results.get('metric', 'ldr').upper()})")
    handles = {}
    for ax in axes:  # one entry per label: the rungs appear in both panels
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(
        handles.values(),
        handles.keys(),
        loc="upper center",
        bbox_to_anchor=(0.5, 0.0),
        ncol=4,
        fontsize=8,
        frameon=False,
    )
    fig.suptitle(f"{results['scene']}: framewise RMSE of the paper's schemes")
    fig.tight_layout()
    return fig, "fig3_rmse.png"


def _figure4(plt, results, per_frame, keep, cfg):
    """Figure 4: 1 spp, reference, top ladder rung and the Figure-4 scheme's output, on that scheme's evaluated eye at
    the last frame (:attr:`~stereorepro.workflows.experiment.config.Scheme.figure4`)."""
    if "fig4" not in keep:
        return None
    k = keep["fig4"]
    scheme = next(s for s in SCHEMES if s.figure4)
    fig, axes = plt.subplots(1, 4, figsize=(14, 2.9))
    panels = [
        ("1 spp", k["one"]),
        (f"{cfg.reference_spp} spp reference", k["ref"]),
        (f"{cfg.ladder_spp} spp", k["top"]),
        (f"{scheme.name.replace('_', ' + ')}: {k['spp']:.2f} effective spp", k["method"]),
    ]
    for ax, (t, img) in zip(axes, panels):
        ax.imshow(_tonemap(img))
        ax.set_title(t, fontsize=9)
        ax.axis("off")
    eye = "left" if scheme.eye == LEFT else "right"
    fig.suptitle(
        f"{results['scene']}, frame {per_frame[-1]['frame']} (the last of {len(per_frame)}), {eye} eye", fontsize=10
    )
    fig.tight_layout()
    return fig, "fig4_comparison.png"


#: The cost plot's marker per scheme family (longest matching name prefix first); a scheme of no family gets "*".
_COST_FAMILY_MARKERS = (("stereo_temporal", "^"), ("alternate", "D"), ("temporal", "s"), ("stereo", "o"))


def _cost_styles(names: list[str], colours) -> dict[str, tuple[str, tuple]]:
    """Marker and colour of each scheme in the cost plot: the marker says the family (stereo, temporal,
    stereo + temporal, alternate), the colour the variant (the rest of the name: plain, nearest, blend, alpha0.1,
    an option...), so the same option reads alike in every family and no two schemes share a symbol (for up to
    ``len(colours)`` variants)."""
    styles, variants = {}, {}
    for name in names:
        marker, variant = "*", name
        for prefix, m in _COST_FAMILY_MARKERS:
            if name == prefix or name.startswith(prefix + "_"):
                marker, variant = m, name[len(prefix) + 1 :]
                break
        colour = colours[variants.setdefault(variant, len(variants)) % len(colours)]
        styles[name] = (marker, colour)
    return styles


def _figure_cost(plt, results, per_frame, keep, cfg):
    """What accuracy costs in time: effective spp against ms per frame. Plain path tracing at n spp is the black line
    (each point labelled with its n); every scheme is one marker with its own legend entry beside the axes, its shape
    the scheme's family and its colour the variant (:func:`_cost_styles`)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig, ax = plt.subplots(figsize=(8.5, 4.5))
    pt = [r for r in results["cost"] if r["scheme"].startswith("path tracing")]
    spp = [r["scheme"].split()[-2] for r in pt]  # "path tracing 16 spp" -> "16"
    ax.plot(
        [r["ms"] for r in pt],
        [r["effective_spp"] for r in pt],
        "k.-",
        label=f"path tracing, {spp[0]}–{spp[-1]} spp" if pt else "path tracing",
    )
    for r, n in zip(pt, spp):
        ax.annotate(n, (r["ms"], r["effective_spp"]), fontsize=7, xytext=(4, -9), textcoords="offset points")
    rest = [r for r in results["cost"] if not r["scheme"].startswith("path tracing") and r["effective_spp"]]
    styles = _cost_styles([r["scheme"] for r in rest], plt.get_cmap("tab20").colors)
    for r in rest:
        marker, colour = styles[r["scheme"]]
        ax.plot(r["ms"], r["effective_spp"], marker, color=colour, ms=6, label=r["scheme"])
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis, values in (
        (ax.xaxis, [r["ms"] for r in results["cost"]]),
        (ax.yaxis, [r["effective_spp"] for r in results["cost"] if r["effective_spp"]]),
    ):
        decades = np.log10(max(values) / min(values)) if values and min(values) > 0 else 0.0
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2.5 else (1.0,)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("ms per frame (evaluated eye)")
    ax.set_ylabel("effective spp")
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, frameon=False)
    ax.set_title(f"{results['scene']}: what accuracy costs in time")
    return fig, "fig_cost.png"


def _report_markdown(results: dict, tables: str | None = None) -> str:
    """``report.md``: the run's settings, the tables (``tables``: :func:`tables_markdown` of ``results``), the
    variants, the resampling bias, FLIP, SSIM and the temporal error, the time cost, the figures."""
    tables = tables_markdown(results) if tables is None else tables
    report = _report_header(results) + [
        "",
        tables,
        "",
        "Variants (same renders):",
        "",
        "| scheme | Avg | Min | Max |",
        "|---|---:|---:|---:|",
    ]
    for kk, v in results["table2_variants"].items():
        report.append(f"| {kk} | {_spp(v)} | {_fmt(v['min'])} | {_fmt(v['max'])} |")
    report += _beyond_note(results["table2_variants"], results)
    report += _bias_section(results) + _metric_sections(results) + _cost_section(results)
    return "\n".join(report)


def _report_header(results: dict) -> list[str]:
    th, cache = results["thresholds"], results["cache"]
    return [
        f"# Experiment report: {results['scene']}",
        "",
        f"{results['frames']} frames at {results['resolution']}, reference {results['reference_spp']} spp, "
        f"ladder 1..{results['ladder_spp']} spp, seed {results['seed']}; thresholds: position "
        f"{th['position']:.4g} (scene {th['position_scene']:.4g} × "
        f"{th['scale']:.3g} for the resolution), normal {th['normal']:.3g}. "
        f"stereorepro {results['version']} (renderer {results['code']}); wall time {results['wall_s']:.0f} s "
        f"(cache hits/misses {cache['hits']}/{cache['misses']}).",
    ]


def _bias_section(results: dict) -> list[str]:
    """The resampling bias without the reference's noise, each scheme's share of it, and where the error lives."""
    b = results["bias"]
    schemes = [k for k in ("stereo", "temporal", "stereo_temporal") if k in b]
    lines = [
        "",
        "## Resampling bias",
        "",
        "The part of each scheme's error that more samples cannot remove (bilinear blur compounded over frames, "
        "edges): the scheme fed each of the reference's two independent halves (the mean of its first half of "
        "chunks, and of the rest) and "
        "scored against that half; the mean product of the two errors is the squared bias, without the "
        "reference's noise (`stereorepro.measure.anatomy.split_bias`; ± its standard error over 8×8 tiles, an upper "
        "bound). Shares: of the scheme's MSE as the tables score it, and of that MSE less the noise the "
        f"{results['reference_spp']}-spp reference still carries (estimated from its halves' spread).",
        "",
    ]
    if not schemes or not b[schemes[0]].get("bias_mse", {}).get("n"):
        lines += [
            "Not measured: it needs the reference in two chunks or more (`--reference-chunk-spp` at most half of "
            "`--reference-spp`).",
        ]
    else:
        lines += [
            "| scheme | bias MSE (avg ± se) | share of the scheme's MSE | reference noise MSE | "
            "share without the reference's noise |",
            "|---|---:|---:|---:|---:|",
        ]
        for kk in schemes:
            v = b[kk]
            lines.append(
                f"| {kk} | {_fmt(v['bias_mse']['avg'], 6)} ± {_fmt(v['bias_mse_se']['avg'], 6)} | "
                f"{_pct(v['bias_share']['avg'])} | {_fmt(v['reference_noise_mse']['avg'], 6)} | "
                f"{_pct(v['bias_share_without_reference_noise']['avg'])} |"
            )
    lines += [
        "",
        f"For scale: the left eye's {results['ladder_spp']}-spp RMSE averages {_fmt(b['ladder_top_rmse']['avg'], 4)}.",
    ]
    return lines + _anatomy_section(b, schemes) + [""]


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def _anatomy_section(b: dict, schemes: list[str]) -> list[str]:
    """Each scheme's pixels, squared error and bias by its reprojection's footprint in the evaluated eye."""
    rows = [(k, g, v) for k in schemes for g, v in (b[k].get("anatomy") or {}).items() if v["pixels_pct"]["n"]]
    if not rows:
        return []
    lines = [
        "",
        "### Where the error lives",
        "",
        "The evaluated eye's pixels by the scheme's reprojection into it (stereo: right → left; temporal: the "
        "previous right frame → this one) and the 4×4 footprint around each reprojected position: *interior* "
        "(kept, all 16 taps pass the position and normal tests), *edge* (kept, a footprint tap fails: near "
        "silhouettes and creases, and at grazing angles where the outer taps lie beyond the position threshold), "
        "*discarded* (rejected: fresh samples), *no surface*. Averages over frames of each region's share (%).",
        "",
        "| scheme | region | pixels | squared error | bias |",
        "|---|---|---:|---:|---:|",
    ]
    for k, g, v in rows:
        lines.append(
            f"| {k} | {g} | {_fmt(v['pixels_pct']['avg'], 1)} | {_fmt(v['mse_share_pct']['avg'], 1)} | "
            f"{_fmt(v['bias_share_pct']['avg'], 1)} |"
        )
    return lines


#: The image metrics the report has a section for, if the run measured them: the section's title, the key of
#: ``results`` holding the statistics, the table's column, and what the section says.
_METRIC_SECTIONS = (
    (
        "FLIP",
        "flip",
        "FLIP (avg)",
        "Mean LDR FLIP (NVIDIA's perceptual error, 0 = identical; radiance clamped to [0, 1]) against the "
        "reference, averaged over frames. Effective spp above stays MSE-based: it rests on the 1/n decay "
        "of an unbiased estimator's MSE, which FLIP does not have.",
    ),
    (
        "SSIM",
        "ssim",
        "SSIM (avg)",
        "Mean LDR SSIM (Gaussian window 11, sigma 1.5, radiance clamped to [0, 1]; 1 = identical) of the "
        "paper's schemes against the reference, averaged over frames.",
    ),
    (
        "Temporal stability",
        "temporal_error",
        "temporal error (avg, lower = steadier)",
        "The temporal error (stereorepro.measure.temporal_error, a reference-relative warping error) of each "
        "frame from the second on: the previous frame of the output and of the reference is warped into the "
        "current one by the known geometry (bilinear, the run's thresholds, motion vectors where objects move), "
        "and the RMSE of the output's frame-to-frame change minus the reference's change is taken over the "
        "pixels the warp accepts (disocclusions and pixels without a surface left out), tonemapped as the run's "
        "metric (ldr: clamped to [0, 1]). 0 = as steady as the reference: camera motion and true lighting "
        "changes cancel; independent noise of standard deviation s in every frame gives about s·√2. It sees the "
        "flicker that the per-frame RMSE, FLIP and SSIM cannot.",
    ),
)


def _metric_sections(results: dict) -> list[str]:
    lines = []
    for title, key, column, about in _METRIC_SECTIONS:
        stats = results.get(key)
        every = results.get("perceptual_every", 1)
        if stats and key in ("flip", "ssim") and every > 1:
            n = max(v["n"] for v in stats.values())
            about += f" Scored on one frame in {every}, counted back from the last ({n} frames)."
        if stats:
            lines += [
                "",
                f"## {title}",
                "",
                about,
                "",
                f"| scheme | {column} | Min | Max |",
                "|---|---:|---:|---:|",
            ]
            lines += [
                f"| {kk} | {_fmt(v['avg'], 4)} | {_fmt(v['min'], 4)} | {_fmt(v['max'], 4)} |" for kk, v in stats.items()
            ]
    return lines


def _cost_section(results: dict) -> list[str]:
    t = results["timing_ms"]
    flags = ", ".join(f"{k}: {v}" for k, v in results["flags"].get("stereo_temporal", {}).items())
    return [
        "",
        "## What accuracy costs in time",
        "",
        f"Median per frame: 1-spp trace of one eye {_fmt(t['trace_1spp_ms'], 1)} ms, G-buffer "
        f"{_fmt(t['gbuffer_ms'], 1)} ms, tracing only the left eye's discarded pixels "
        f"{_fmt(t['trace_left_discards_ms'], 1)} ms.",
        "",
        cost_markdown(results),
        "",
        "![cost](fig_cost.png)",
        "",
        "## Figures",
        "",
        "![fig1](fig1_discards.png)",
        "",
        "![fig3](fig3_rmse.png)",
        "",
        "![fig4](fig4_comparison.png)",
        "",
        f"Effective-spp flags (stereo+temporal): {flags}. `extrapolated_high` means the value lies beyond "
        f"the ladder's top rung and was extrapolated on a fit of the ladder (see stereorepro.measure.metrics).",
        "",
    ]


def write_frame_exr(root: Path, f: int, eyes: dict, drivers: dict) -> None:
    """Write frame ``f`` of each eye as ``root/<frame>_<eye>.exr``: the ``stereo_temporal`` driver's colour of that
    eye (R, G, B), the eye's depth (Z) and normal (N.X, N.Y, N.Z).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from types import SimpleNamespace
        >>> import torch
        >>> from stereorepro.camera import Eye
        >>> from stereorepro.workflows.experiment.report import write_frame_exr
        >>> eye = SimpleNamespace(depth=torch.ones(1, 1, 2, 3), normal=torch.zeros(1, 3, 2, 3))
        >>> state = SimpleNamespace(color=torch.zeros(1, 3, 2, 3))
        >>> drivers = {"stereo_temporal": SimpleNamespace(left_state=state, right_state=state)}
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_frame_exr(Path(d), 3, {Eye.LEFT: eye, Eye.RIGHT: eye}, drivers)
        ...     print(sorted(p.name for p in Path(d).iterdir()))
        ['0003_left.exr', '0003_right.exr']
    """
    from ...io.exr import write_exr

    root.mkdir(parents=True, exist_ok=True)
    for e, d in eyes.items():
        name = str(e)
        drv = drivers["stereo_temporal"]
        state = drv.left_state if e == LEFT else drv.right_state
        chans = {c: state.color[0, i].numpy() for i, c in enumerate("RGB")}
        chans["Z"] = d.depth[0, 0].numpy()
        chans.update({f"N.{c}": d.normal[0, i].numpy() for i, c in enumerate("XYZ")})
        write_exr(root / f"{f:04d}_{name}.exr", chans)
