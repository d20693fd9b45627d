"""The experiment's ``report.html``: one self-contained page (:mod:`stereorepro.workflows.html_report`) with the
run's settings, its tables, each scheme's image against the reference (a slider wipes between them, on the full
frame and on the regions of highest error), the error maps, the discarded pixels and the figures' plots.

It is built from what the figures are drawn from: ``results`` (``results.json``), the images the run kept
(``keep``, filled by :func:`~stereorepro.workflows.experiment.run.run_experiment`) and the figure files already in
the output folder (``fig_cost.png``, ``fig3_rmse.png``). ``keep`` keys it reads, each optional:

* ``"last_frame"``: the last frame's images, ``{"images": {scheme: (1, 3, H, W)}, "eyes": {scheme: "left" |
  "right"}, "references": {eye: (1, 3, H, W)}, "one_spp": {eye: (1, 3, H, W)}}``: a comparison per eye of all
  its schemes and its 1-spp input;
* ``"fig4"``: Figure 4's images (the ``stereo_temporal`` scheme, 1 spp, the reference and the top ladder rung of
  the left eye at the last frame): the left eye's comparison when ``"last_frame"`` is absent, and the top rung
  beside the schemes when it is there;
* ``"fig1_stereo"``, ``"fig1_temporal"``, ``"fig1_temporal_mv"``: Figure 1's discard reasons ``(1, 1, H, W)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...reproject import reason_to_rgb
from ..html_report import Page, abs_error, colorbar, colorize, downscale, full_frame, tonemap, worst_crop
from .config import metric_image

__all__ = ["report_page", "write_report_html"]

#: The widest image the page shows (pixels): larger frames are box-averaged down; smaller ones, and the zoomed
#: regions, are shown enlarged by an integer factor up to this width.
MAX_WIDTH = 480
#: The width the error maps and discard maps are enlarged towards (pixels; an integer factor, pixelated).
_GALLERY_WIDTH = 320

#: The metric tables the page shows when the run measured them: results key, title, what it measures.
_METRICS = (
    ("flip", "FLIP", "mean LDR FLIP against the reference (0 = identical), averaged over frames"),
    ("ssim", "SSIM", "mean LDR SSIM against the reference (1 = identical), averaged over frames"),
    (
        "temporal_error",
        "Temporal error",
        "flicker: the change from the previous frame (warped by the known motion) beyond the reference's own "
        "change, RMSE, averaged over frames 1.. (0 = as stable as the reference)",
    ),
)


#: What the error maps and the zoomed regions measure, per metric (:func:`~.config.metric_image`).
_METRIC_IMAGE = {"ldr": "radiance clamped to [0, 1]", "hdr": "linear radiance"}


def _metric(results: dict) -> str:
    return results.get("metric", "ldr")


def _error(image, reference, results: dict) -> np.ndarray:
    """Per-pixel error ``(H, W)`` of the images the run's metric scores (clamped to [0, 1] for ``"ldr"``): where
    the error that effective spp counts lies."""
    m = _metric(results)
    return abs_error(metric_image(image, m), metric_image(reference, m))


def _f(x, nd: int = 2) -> str:
    return "–" if x is None else f"{x:.{nd}f}"


def _stats_rows(stats: dict, nd: int = 2) -> list[list[str]]:
    def avg(v: dict) -> str:  # effective spp with frames beyond the ladder: its lower bound
        return "≥ " + _f(v.get("avg_lower_bound"), nd) if v.get("beyond_ladder") else _f(v.get("avg"), nd)

    return [[k, avg(v), _f(v.get("min"), nd), _f(v.get("max"), nd)] for k, v in stats.items()]


def _settings(page: Page, results: dict) -> None:
    """The run's settings, as ``report.md``'s first paragraph gives them."""
    th, cache = results["thresholds"], results["cache"]
    page.section("Settings")
    page.table(
        [
            ["scene", results["scene"]],
            ["frames, resolution", f"{results['frames']} frames at {results['resolution']}"],
            ["reference, ladder", f"{results['reference_spp']} spp, 1..{results['ladder_spp']} spp"],
            ["metric", f"{_metric(results).upper()} RMSE (effective spp)"],
            [
                "thresholds",
                f"position {th['position']:.4g} (scene {th['position_scene']:.4g} × {th['scale']:.3g} for the "
                f"resolution), normal {th['normal']:.3g}",
            ],
            ["seed", str(results["seed"])],
            ["code", f"stereorepro {results['version']} (renderer {results['code']})"],
            ["wall time", f"{results['wall_s']:.0f} s (cache hits / misses {cache['hits']} / {cache['misses']})"],
        ]
    )


def _tables(page: Page, results: dict) -> None:
    """Tables 1 and 2, the variants, the image metrics and the resampling bias."""
    page.section("Tables")
    t1, t2 = results["table1"], results["table2"]
    head = ["scheme", "Avg", "Min", "Max"]
    page.table(
        _stats_rows({k: t1[k] for k in ("stereo", "temporal") if k in t1}), head, "**Table 1**: discarded pixels (%)"
    )
    metric = _metric(results).upper()
    page.table(
        _stats_rows(t2) + _stats_rows(results.get("table2_variants") or {}),
        head,
        f"**Table 2**: effective spp ({metric} RMSE against the {results['reference_spp']}-spp reference, ladder "
        f"1..{results['ladder_spp']} spp); below the paper's three schemes, the variants on the same renders",
    )
    for key, title, about in _METRICS:
        if results.get(key):
            page.table(_stats_rows(results[key], 4), head, f"**{title}**: {about}")
    bias = results.get("bias") or {}

    def avg(scheme: str, key: str):
        return ((bias[scheme].get(key) or {}).get("avg")) if scheme in bias else None

    rows = [
        [
            k,
            "–" if avg(k, "bias_mse") is None else f"{avg(k, 'bias_mse'):.2e}",
            "–" if avg(k, "bias_share") is None else _f(100 * avg(k, "bias_share"), 1) + " %",
        ]
        for k in ("stereo", "temporal", "stereo_temporal")
        if k in bias
    ]
    if rows:
        page.table(
            rows,
            ["scheme", "bias MSE (avg)", "share of the scheme's MSE"],
            "**Resampling bias** without the reference's noise: the mean product of the scheme's errors on the "
            "reference's two independent halves (needs at least 2 reference chunks)",
        )


def _eye_images(keep: dict, results: dict) -> dict:
    """eye -> (methods {label: (1, 3, H, W)}, reference, the scheme whose error picks the zoomed regions)."""
    last, eyes = keep.get("last_frame"), {}
    if last:
        for name, img in last["images"].items():
            eyes.setdefault(last["eyes"][name], {})[name] = img
    elif "fig4" in keep:
        eyes["left"] = {"stereo_temporal": keep["fig4"]["method"]}
        last = {"references": {"left": keep["fig4"]["ref"]}, "one_spp": {"left": keep["fig4"]["one"]}}
    out = {}
    for eye, methods in eyes.items():
        lead = next((k for k in ("stereo_temporal", "temporal", "stereo") if k in methods), next(iter(methods)))
        extra = {"1 spp": last["one_spp"][eye]} if eye in last.get("one_spp", {}) else {}
        if eye == "left" and "fig4" in keep:
            extra[f"path tracing, {results['ladder_spp']} spp"] = keep["fig4"]["top"]
        out[eye] = (dict(methods, **extra), last["references"][eye], lead)
    return out


def _comparisons(page: Page, keep: dict, results: dict) -> dict:
    """Per eye, every scheme against the reference on the full frame and the two regions where the lead scheme
    (``stereo_temporal`` on the left eye, ``temporal`` on the right) errs most; returns what :func:`_error_maps`
    shows."""
    eyes = _eye_images(keep, results)
    if not eyes:
        return eyes
    page.section("Images")
    page.text(
        f"Frame {results['frames'] - 1} (the last). Each panel: the chosen method left of the line, the "
        f"{results['reference_spp']}-spp reference right of it; drag on an image or move the slider, pick the "
        "method in the menu. Zoomed regions: where the lead scheme's error is highest."
    )
    for eye, (methods, ref, lead) in sorted(eyes.items()):
        err = _error(methods[lead], ref, results)
        h, w = err.shape
        size = max(8, min(h, w) // 6)  # shown enlarged: 2x at 1280x720
        first = worst_crop(err, size, f"{lead}'s highest error")
        rest = err.copy()
        rest[max(0, first.y - size) : first.y + 2 * size, max(0, first.x - size) : first.x + 2 * size] = 0
        crops = [full_frame(ref), first]
        if rest.any():
            crops.append(worst_crop(rest, size, f"{lead}'s next-highest error"))
        page.section(f"{eye.capitalize()} eye", level=3)
        label = f"reference ({results['reference_spp']} spp)"
        page.compare(methods, ref, crops, reference_label=label, max_width=MAX_WIDTH, min_width=MAX_WIDTH)
    return eyes


def _error_maps(page: Page, eyes: dict, results: dict) -> None:
    """Per eye, each method's error map on one scale (the 99th percentile of that eye's errors)."""
    if not eyes:
        return
    page.section("Error maps")
    for eye, (methods, ref, _) in sorted(eyes.items()):
        errs = {k: downscale(_error(v, ref, results), MAX_WIDTH)[..., 0] for k, v in methods.items()}
        vmax = float(np.percentile(np.concatenate([e.ravel() for e in errs.values()]), 99)) or 1.0
        page.section(f"{eye.capitalize()} eye", level=3)
        page.text(
            f"Mean absolute error over R, G, B of the images the metric scores ({_METRIC_IMAGE[_metric(results)]}): "
            f"black 0, light yellow {vmax:.3g} and above."
        )
        page.image(colorbar(256, 10), caption=f"0 … {vmax:.3g}")
        scale = max(1, _GALLERY_WIDTH // next(iter(errs.values())).shape[1])
        page.gallery({k: colorize(e, vmax) for k, e in errs.items()}, scale=scale)


def _discards(page: Page, keep: dict, results: dict) -> None:
    """Figure 1: the discard reasons of the stereo and temporal steps at Figure 1's frame."""
    panels = {
        "stereo (left eye)": keep.get("fig1_stereo"),
        "temporal, cameras only (right eye)" if "fig1_temporal_mv" in keep else "temporal (right eye)": keep.get(
            "fig1_temporal"
        ),
        "temporal, motion vectors (right eye)": keep.get("fig1_temporal_mv"),
    }
    images = {k: downscale(reason_to_rgb(v)[0], MAX_WIDTH) for k, v in panels.items() if v is not None}
    if not images:
        return
    page.section("Discarded pixels")
    page.text(
        "The pixels each step discards (Figure 1): green the position test, cyan the normal test, red out of "
        "frame, black kept or no surface."
    )
    scale = max(1, _GALLERY_WIDTH // next(iter(images.values())).shape[1])
    page.gallery({k: tonemap(v, gamma=1.0) for k, v in images.items()}, scale=scale)


def _plots(page: Page, results: dict, figures: Path | None) -> None:
    """The time-cost table and plot, and Figure 3 (framewise RMSE), from the figure files in ``figures``."""
    page.section("What accuracy costs in time")
    page.table(
        [
            [
                r["scheme"],
                _f(r["ms"], 1),
                ("≥ " if r.get("beyond_ladder") else "") + _f(r["effective_spp"]),
                ("≤ " if r.get("beyond_ladder") else "") + _f(r["ms_per_effective_spp"], 1),
            ]
            for r in results["cost"]
        ],
        ["scheme", "ms / frame (evaluated eye)", "effective spp (avg)", "ms per effective spp"],
    )
    for name, caption in (("fig_cost.png", "effective spp against ms per frame"), ("fig3_rmse.png", "framewise RMSE")):
        if figures is not None and (figures / name).is_file():
            page.image(figures / name, caption=f"{caption} ({name})")


def report_page(results: dict, keep: dict, figures: str | Path | None = None) -> Page:
    """The experiment's report page, built from ``results`` (``results.json``), the images the run kept (``keep``,
    keys in the module's docstring) and the figure files in the folder ``figures`` (``fig_cost.png``,
    ``fig3_rmse.png``; None: no plots).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.run import run_experiment
        >>> from stereorepro.workflows.experiment.report_html import report_page
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, frames=2, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, flip=False, ssim=False, progress=False)
        >>> results = run_experiment(cfg, log=lambda message: None)
        >>> html = report_page(results, {}, figures=tmp.name).render()  # no kept images: tables and plots
        >>> "<b>Table 2</b>" in html or "<strong>Table 2</strong>" in html, "fig_cost.png" in html
        (True, True)
        >>> tmp.cleanup()
    """
    page = Page(f"Experiment report: {results['scene']}")
    _settings(page, results)
    _tables(page, results)
    eyes = _comparisons(page, keep, results)
    _error_maps(page, eyes, results)
    _discards(page, keep, results)
    _plots(page, results, None if figures is None else Path(figures))
    return page


def write_report_html(out: str | Path, results: dict, keep: dict) -> Path:
    """Write ``out/report.html`` (:func:`report_page`, with the figure files already in ``out``) atomically;
    returns its path.

    Examples:
        >>> import tempfile
        >>> from stereorepro.workflows.experiment.report_html import write_report_html
        >>> row = {"avg": 2.0, "min": 1.0, "max": 3.0}
        >>> results = {"scene": "box", "frames": 2, "resolution": "8x6", "reference_spp": 64, "ladder_spp": 16,
        ...            "seed": 0, "thresholds": {"position": 0.1, "position_scene": 0.1, "scale": 1.0, "normal": 0.2},
        ...            "version": "0", "code": "0", "wall_s": 1.0, "cache": {"hits": 0, "misses": 2},
        ...            "table1": {"stereo": row, "temporal": row}, "table2": {"stereo": row}, "cost": []}
        >>> with tempfile.TemporaryDirectory() as d:
        ...     print(write_report_html(d, results, {}).name)
        report.html
    """
    path = Path(out) / "report.html"
    return report_page(results, keep, figures=Path(out)).write(path)
