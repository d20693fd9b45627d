"""Tables 1-2 next to the paper's from finished experiment runs (their results.json; nothing is rendered): each cell
as the average over all frames, the average after the warm-up and [min, max], beside the paper's average and
maximum; the variants (alpha, blending, alternating eyes, nearest) and the reference-spp study of each run.
Rows are named by the runs' scenes (by their folders where two runs share a scene); a run given to --fill fills
only what its scene's row lacks (e.g. FLIP and SSIM from a run made for them), and the record says which fields
came from where.

    python bench/paper_tables.py --runs /work/runs720/final/shared_living_room /work/runs720/final/shared_classroom \\
        --name paper720

Writes bench/results/<name>.json|md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import header, save  # noqa: E402
from paper import PAPER_NAME, PAPER_T1, PAPER_T2  # noqa: E402

from stereorepro.workflows.experiment.run import _spp_stats  # noqa: E402


def _t(x, nd=2):
    return "–" if x is None else f"{x:.{nd}f}"


def _avg(o: dict, key: str = "avg") -> str:
    """An effective-spp average; with frames beyond the ladder's top rung, its lower bound as ``≥ x``."""
    return "≥ " + _t(o.get(f"{key}_lower_bound")) if o.get("beyond_ladder") else _t(o.get(key))


def _pair(o: dict) -> str:
    return f"{_avg(o)} / {_avg(o, 'avg_after_warmup')}"


def _cell(o: dict) -> str:
    return f"{_pair(o)} [{_t(o['min'])}, {_t(o['max'])}]"


def _sources(scene: str, r: dict) -> str:
    filled: dict[str, list[str]] = {}
    for k, d in (r.get("filled_from") or {}).items():
        filled.setdefault(d, []).append(k)
    return f"{scene} `{r['path']}`" + "".join(f" ({', '.join(ks)} from `{d}`)" for d, ks in filled.items())


def tables(runs: dict[str, dict]) -> str:
    any_run = next(iter(runs.values()))
    lines = [
        f"Ours: {any_run['frames']} frames at {any_run['resolution']}, reference {any_run['reference_spp']} spp "
        f"(chunks of {any_run.get('reference_chunk_spp')}), ladder 1..{any_run['ladder_spp']} spp, "
        f"{any_run['metric'].upper()} RMSE. Cells: average over all frames / average from frame "
        f"{any_run.get('warmup_frames')} on [min, max]. Paper: 60 frames at 1280×720, 4096-spp references, "
        "average (max).",
        "",
        "Runs: " + "; ".join(_sources(scene, r) for scene, r in runs.items()) + ".",
        "",
        "**Table 1** — discarded pixels (%)",
        "",
        "| scene | stereo, ours | paper | temporal, ours | paper |",
        "|---|---|---:|---|---:|",
    ]
    for scene, r in runs.items():
        t1 = PAPER_T1.get(PAPER_NAME.get(r["scene"], "").split(" (")[0], {})
        cells = [scene]
        for k in ("stereo", "temporal"):
            p = t1.get(k)
            cells += [_cell(r["table1"][k]), f"{p[0]:.2f} ({p[2]:.2f})" if p else "–"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "**Table 2** — effective spp",
        "",
        "| scene | stereo, ours | paper | temporal, ours | paper | stereo+temporal, ours | paper |",
        "|---|---|---:|---|---:|---|---:|",
    ]
    for scene, r in runs.items():
        t2 = PAPER_T2.get(PAPER_NAME.get(r["scene"], ""))
        cells = [scene]
        for i, k in enumerate(("stereo", "temporal", "stereo_temporal")):
            cells += [_cell(r["table2"][k]), f"{t2[i][0]:.2f} ({t2[i][2]:.2f})" if t2 else "–"]
        lines.append("| " + " | ".join(cells) + " |")
    names = [k for k in any_run["table2_variants"]]
    lines += [
        "",
        "**Variants** — effective spp, average over all frames / from the warm-up on",
        "",
        "| variant | " + " | ".join(runs) + " |",
        "|---|" + "---|" * len(runs),
    ]
    for k in names:
        lines.append(
            f"| {k} | "
            + " | ".join(_pair(r["table2_variants"][k]) if k in r["table2_variants"] else "–" for r in runs.values())
            + " |"
        )
    lines += _bias_lines(runs)
    lines += _option_lines(runs)
    lines += _perceptual_lines(runs)
    for scene, r in runs.items():
        study = r.get("reference_study")
        if not study:
            continue
        keys = list(next(iter(study.values())))
        lines += [
            "",
            f"**Reference spp, {scene}** ({r['frames']} frames) — effective spp (avg) with the references "
            "of fewer samples",
            "",
            "| reference spp | " + " | ".join(keys) + " |",
            "|---:|" + "---:|" * len(keys),
        ]
        for p, row in study.items():
            lines.append(f"| {p} | " + " | ".join(_t(row[k]["avg"]) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def _pct(x, base) -> str:
    return "–" if x is None or not base else f"{100.0 * (x / base - 1.0):+.1f} %"


def _bias_lines(runs: dict[str, dict]) -> list[str]:
    """The paper's schemes' resampling bias (from the reference's halves: no reference noise in it) as a share of
    the MSE the tables score and of that MSE less the reference's own noise, and where it lives (the edge pixels'
    share of the pixels and of the bias: a tap of the 4x4 footprint fails a test)."""

    def pct(b: dict, key: str) -> str:
        v = (b.get(key) or {}).get("avg")
        return "–" if v is None else f"{100.0 * v:.1f} %"

    rows = []
    for scene, r in runs.items():
        for k in ("stereo", "temporal", "stereo_temporal"):
            b = (r.get("bias") or {}).get(k) or {}
            edge = (b.get("anatomy") or {}).get("edge") or {}
            if (b.get("bias_share") or {}).get("avg") is not None:
                rows.append(
                    f"| {scene} | {k} | {pct(b, 'bias_share')} | {pct(b, 'bias_share_without_reference_noise')} | "
                    f"{_t(edge.get('pixels_pct', {}).get('avg'), 1)} % | "
                    f"{_t(edge.get('bias_share_pct', {}).get('avg'), 1)} % |"
                )
    if not rows:
        return []
    return [
        "",
        "**Resampling bias** (from the reference's two independent halves, so without the reference's noise), "
        "average over frames: its share of the MSE the tables score and of that MSE less the reference's own noise; "
        "the edge pixels (a tap of the 4×4 footprint fails the position or normal test): their share of the pixels "
        "and of the bias",
        "",
        "| scene | scheme | share of the scored MSE | share of the MSE less reference noise | edge pixels "
        "| edge share of the bias |",
        "|---|---|---:|---:|---:|---:|",
        *rows,
    ]


def _perceptual_lines(runs: dict[str, dict]) -> list[str]:
    """Mean LDR FLIP of every scheme and mean LDR SSIM of the paper's schemes, per run (average over the frames
    scored: every ``perceptual_every``-th)."""
    scored = {scene: r for scene, r in runs.items() if r.get("flip") or r.get("ssim")}
    if not scored:
        return []
    every = ", ".join(f"{scene}: {r.get('perceptual_every') or 1}" for scene, r in scored.items())
    lines = [
        "",
        "**FLIP and SSIM** — mean LDR FLIP (0 = identical) of every scheme and mean LDR SSIM (1 = identical) of the "
        f"paper's schemes against the reference, average over the frames scored (one frame in K, K = {every}; "
        "counted back from the last)",
        "",
        "| scheme | " + " | ".join(f"{scene} FLIP | SSIM" for scene in scored) + " |",
        "|---|" + "---:|---:|" * len(scored),
    ]
    names = list(dict.fromkeys(k for r in scored.values() for k in (r.get("flip") or r.get("ssim") or {})))
    for k in names:
        cells = []
        for r in scored.values():
            f, s = (r.get("flip") or {}).get(k) or {}, (r.get("ssim") or {}).get(k) or {}
            cells += [_t(f.get("avg"), 4), _t(s.get("avg"), 4)]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return lines


def _option_lines(runs: dict[str, dict]) -> list[str]:
    """Per run with option variants: each option against its plain scheme (effective spp, temporal error, the
    resampling bias's share of the MSE without reference noise, ms per frame of the evaluated eye)."""
    lines = []
    for scene, r in runs.items():
        if not r.get("option_variants"):
            continue
        t2 = {**r["table2"], **r["table2_variants"]}
        te, bias, ms = r.get("temporal_error") or {}, r.get("bias") or {}, r.get("timing_ms") or {}
        lines += [
            "",
            f"**Option variants, {scene}** ({r['frames']} frames at {r['resolution']}) — effective spp average "
            "over all frames / from the warm-up on (change against the plain scheme), temporal error (avg), "
            "resampling bias (without reference noise) as a share of the scored MSE (avg), ms per frame of the evaluated "
            "eye's steps (median)",
            "",
            "| scheme | effective spp | change | temporal error | bias share | ms |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for k in [k for k in t2 if k in ("temporal", "stereo_temporal") or k in bias and k not in r["table2"]]:
            base = "temporal" if k.startswith("temporal") else "stereo_temporal"
            b = (bias.get(k) or {}).get("bias_share") or {}
            share = "–" if b.get("avg") is None else f"{100.0 * b['avg']:.1f} %"
            lines.append(
                f"| {k} | {_pair(t2[k])} | "
                f"{_pct(t2[k]['avg'], t2[base]['avg']) if k != base else ''} | "
                f"{_t((te.get(k) or {}).get('avg'), 4)} | {share} | {_t(ms.get(f'reproject_{k}_ms'), 0)} |"
            )
    return lines


FIELDS = (
    "table1",
    "table2",
    "table2_variants",
    "reference_study",
    "frames",
    "resolution",
    "reference_spp",
    "reference_chunk_spp",
    "ladder_spp",
    "warmup_frames",
    "metric",
    "code",
    "jitter",
    "cost",
    "timing_ms",
    "bias",
    "cache",
    "wall_s",
    "thresholds",
    "flags",
    "option_variants",
    "temporal_error",
    "flip",
    "ssim",
    "perceptual_every",
)


def _bound_old_results(got: dict, r: dict) -> None:
    """Effective-spp statistics written before the experiment bounded the frames beyond the ladder's top rung
    (no ``beyond_ladder``): recomputed from the run's per-frame values and flags, as the experiment does now."""
    for table in ("table2", "table2_variants"):
        for k, st in (got.get(table) or {}).items():
            if "beyond_ladder" not in st and r.get("per_frame"):
                bound = _spp_stats(r["per_frame"], k, r["ladder_spp"])
                st.update({x: v for x, v in bound.items() if x not in st})


def _load(d: str) -> dict:
    r = json.loads((Path(d) / "results.json").read_text())
    got = {k: r.get(k) for k in FIELDS}
    _bound_old_results(got, r)
    return {**got, "path": str(d), "scene": r["scene"]}


def collect(paths: list[str], fill: list[str] = ()) -> dict[str, dict]:
    """The runs' results, one row each, named by the run's scene where only one run has it, else by its folder.
    Each run in ``fill`` fills, in the row of its scene, only the fields that row lacks (``None`` or empty);
    ``filled_from`` records which fields came from which folder."""
    loaded = [_load(d) for d in paths]
    scenes = [r["scene"] for r in loaded]
    runs = {(r["scene"] if scenes.count(r["scene"]) == 1 else Path(r["path"]).name): r for r in loaded}
    for d in fill:
        got = _load(d)
        rows = [r for r in runs.values() if r["scene"] == got["scene"]]
        if len(rows) != 1:
            raise SystemExit(f"paper_tables.py: --fill {d}: {len(rows)} runs of scene {got['scene']} to fill, not 1")
        filled = [k for k in FIELDS if not rows[0].get(k) and got[k]]
        rows[0].update({k: got[k] for k in filled})
        rows[0].setdefault("filled_from", {}).update(dict.fromkeys(filled, str(d)))
    return runs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, help="experiment output folders (with results.json)")
    ap.add_argument("--fill", nargs="*", default=[], help="runs that fill only what their scene's row lacks")
    ap.add_argument("--name", required=True, help="results file name under bench/results/")
    ap.add_argument("--note", default="", help="a paragraph above the tables (how the runs were made)")
    args = ap.parse_args(argv)
    runs = collect(args.runs, args.fill)
    md = tables(runs)
    if args.note:
        md = args.note + "\n\n" + md
    record = {**header(), "runs": runs, "paper_table1": PAPER_T1, "paper_table2": PAPER_T2, "note": args.note}
    save(args.name, record, md, script="paper_tables.py")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
