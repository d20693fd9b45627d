"""Tables 1-2 next to the paper's from finished experiment runs (their results.json; nothing is rendered): each cell
as the average over all frames, the average after the warm-up and [min, max], beside the paper's average and
maximum; the variants (alpha, blending, alternating eyes, nearest) and the reference-spp study of each run.

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


def _t(x, nd=2):
    return "–" if x is None else f"{x:.{nd}f}"


def _cell(o: dict) -> str:
    return f"{_t(o['avg'])} / {_t(o.get('avg_after_warmup'))} [{_t(o['min'])}, {_t(o['max'])}]"


def tables(runs: dict[str, dict]) -> str:
    any_run = next(iter(runs.values()))
    lines = [
        f"Ours: {any_run['frames']} frames at {any_run['resolution']}, reference {any_run['reference_spp']} spp "
        f"(chunks of {any_run.get('reference_chunk_spp')}), ladder 1..{any_run['ladder_spp']} spp, "
        f"{any_run['metric'].upper()} RMSE. Cells: average over all frames / average from frame "
        f"{any_run.get('warmup_frames')} on [min, max]. Paper: 60 frames at 1280×720, 4096-spp references, "
        "average (max).",
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
            + " | ".join(
                f"{_t(r['table2_variants'][k]['avg'])} / {_t(r['table2_variants'][k].get('avg_after_warmup'))}"
                if k in r["table2_variants"]
                else "–"
                for r in runs.values()
            )
            + " |"
        )
    lines += _option_lines(runs)
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
            "resampling bias as a share of the MSE (avg, without reference noise), ms per frame of the evaluated "
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
                f"| {k} | {_t(t2[k]['avg'])} / {_t(t2[k].get('avg_after_warmup'))} | "
                f"{_pct(t2[k]['avg'], t2[base]['avg']) if k != base else ''} | "
                f"{_t((te.get(k) or {}).get('avg'), 4)} | {share} | {_t(ms.get(f'reproject_{k}_ms'), 0)} |"
            )
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, help="experiment output folders (with results.json)")
    ap.add_argument("--name", required=True, help="results file name under bench/results/")
    ap.add_argument("--note", default="", help="a paragraph above the tables (how the runs were made)")
    args = ap.parse_args(argv)
    runs = {}
    for d in args.runs:
        r = json.loads((Path(d) / "results.json").read_text())
        runs[Path(d).name] = {
            k: r.get(k)
            for k in (
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
            )
        }
        runs[Path(d).name].update(path=str(d), scene=r["scene"])
    md = tables(runs)
    if args.note:
        md = args.note + "\n\n" + md
    record = {**header(), "runs": runs, "paper_table1": PAPER_T1, "paper_table2": PAPER_T2, "note": args.note}
    save(args.name, record, md, script="paper_tables.py")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
