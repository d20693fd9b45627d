"""How far the ladder's extrapolation above its top rung can be trusted, measured on finished experiment runs (their
results.json; nothing is rendered). Each run's per-frame ladder is cut to its first L/f rungs; every frame whose
scheme the full ladder places between L/f and L (interpolated, on the eye it evaluates) is estimated again on the cut
ladder, where it lies above the top rung (``extrapolated_high``: the fit ``a / n + b`` re-anchored at the top rung,
or ``beyond_floor``: +inf), and compared with the full ladder's value. The cut ladder's reference is the run's, so
it has ``k = reference spp / top rung = f`` times the top rung's samples (the experiment's own runs have k = 1).

    python bench/ladder_extrapolation.py --runs bench/results/paper720_60/options_shared_living_room \\
        bench/results/paper720_60/shared_classroom bench/results/paper720_60/shared_sponza --name ladder_extrapolation

Writes bench/results/<name>.json|md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import header, save  # noqa: E402

from stereorepro.measure.metrics import effective_spp  # noqa: E402


def _eye(scheme: str) -> str:
    return "right" if scheme.startswith("temporal") else "left"


def cut_ladder_errors(results: dict, factor: int) -> tuple[list[float], int, int]:
    """Relative errors ``cut / full - 1`` (``inf`` where the cut ladder puts the frame beyond its floor) over the
    frames and schemes the full ladder of ``results`` places in (L / factor, L]; and the counts of such frames that
    land ``beyond_floor`` and that were skipped (their value is not reproduced from the eye's ladder)."""
    top = int(results["ladder_spp"])
    cut = top // factor
    errs, floor, skipped = [], 0, 0
    for row in results["per_frame"]:
        for k, value in row["rmse"].items():
            full = row["effective_spp"].get(k)
            if row["flags"].get(k) != "interpolated" or not (cut < full <= top):
                continue
            ladder = row["ladder_rmse"][_eye(k)]
            again, _ = effective_spp(value, list(range(1, top + 1)), ladder)
            if abs(again - full) > 1e-6 * full:
                skipped += 1
                continue
            est, flag = effective_spp(value, list(range(1, cut + 1)), ladder[:cut])
            floor += flag == "beyond_floor"
            errs.append(est / full - 1.0)
    return errs, floor, skipped


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, help="experiment output folders (with results.json)")
    ap.add_argument("--factors", type=int, nargs="+", default=[2, 4], help="cut the ladder to L / f rungs")
    ap.add_argument("--name", default="ladder_extrapolation", help="results file name under bench/results/")
    args = ap.parse_args(argv)
    rows = []
    for d in args.runs:
        r = json.loads((Path(d) / "results.json").read_text())
        for f in args.factors:
            errs, floor, skipped = cut_ladder_errors(r, f)
            fin = [e for e in errs if math.isfinite(e)]
            q = np.percentile(fin, [25, 50, 75]).tolist() if fin else [None] * 3
            rows.append(
                {
                    "run": d,
                    "scene": r["scene"],
                    "resolution": r["resolution"],
                    "reference_spp": r["reference_spp"],
                    "ladder_spp": r["ladder_spp"],
                    "cut_to": r["ladder_spp"] // f,
                    "k": r["reference_spp"] / (r["ladder_spp"] // f),
                    "frames": len(errs),
                    "beyond_floor": floor,
                    "skipped": skipped,
                    "median_all": float(np.median(errs)) if errs else None,
                    "q25": q[0],
                    "median_finite": q[1],
                    "q75": q[2],
                }
            )
    pct = lambda x: "–" if x is None else ("+inf" if math.isinf(x) else f"{100 * x:+.0f} %")  # noqa: E731
    md = [
        __doc__.split("\n\n")[0].replace("\n", " "),
        "",
        "| scene | resolution | ladder cut to | k | frames | median error (all) | quartiles (finite) | +inf |",
        "|---|---|---:|---:|---:|---:|---|---:|",
    ]
    for x in rows:
        md.append(
            f"| {x['scene']} | {x['resolution']} | {x['cut_to']} of {x['ladder_spp']} | {x['k']:g} | {x['frames']} | "
            f"{pct(x['median_all'])} | {pct(x['q25'])} / {pct(x['median_finite'])} / {pct(x['q75'])} | "
            f"{x['beyond_floor']} |"
        )
    text = "\n".join(md) + "\n"
    save(args.name, {**header(), "rows": rows}, text, script="ladder_extrapolation.py")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
