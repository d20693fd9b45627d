"""Our Tables 1-2 next to the paper's: runs `stereorepro experiment` per scene and writes
bench/results/paper.{json,md}. Renders are cached under --out, so an interrupted run resumes.

    python bench/paper.py --scenes shared_living_room shared_classroom shared_sponza \
        --frames 30 --resolution 320x180 --reference-spp 128 --ladder-spp 16 --out runs/paper
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import header, save  # noqa: E402

from stereorepro.camera import DEFAULT_RESOLUTION  # noqa: E402
from stereorepro.cli import parse_resolution  # noqa: E402
from stereorepro.workflows.experiment import ExperimentConfig, run_experiment  # noqa: E402

# Mäkitalo et al., Table 1 (discard %, avg/min/max) and Table 2 (effective spp, avg/min/max); 720p, 60 frames.
PAPER_T1 = {
    "Sponza": {"stereo": (2.01, 1.24, 2.96), "temporal": (3.96, 3.57, 4.46)},
    "Living Room": {"stereo": (2.50, 2.31, 2.72), "temporal": (1.48, 0.70, 2.27)},
    "Classroom": {"stereo": (4.36, 3.58, 5.91), "temporal": (2.19, 1.52, 2.97)},
}
PAPER_T2 = {
    "Sponza": ((1.63, 1.55, 1.71), (7.69, 1.00, 10.44), (10.07, 1.66, 13.48)),
    "Living Room": ((1.61, 1.55, 1.64), (12.76, 1.00, 14.36), (18.22, 1.62, 20.94)),
    "Sponza (Glossy)": ((1.58, 1.33, 1.82), (7.97, 1.00, 11.25), (10.09, 1.68, 15.24)),
    "Living Room (Glossy)": ((1.63, 1.48, 1.69), (11.27, 1.00, 12.93), (16.63, 1.61, 19.80)),
    "Sponza (Moving Light)": ((1.59, 1.48, 1.65), (6.92, 1.00, 8.82), (8.65, 1.57, 11.59)),
    "Living Room (Moving Light)": ((1.61, 1.55, 1.65), (11.40, 1.00, 12.83), (15.45, 1.62, 17.98)),
    "Classroom": ((1.60, 1.54, 1.64), (10.83, 1.00, 14.30), (16.50, 1.58, 19.55)),
}
PAPER_NAME = {
    "shared_sponza": "Sponza",
    "shared_living_room": "Living Room",
    "shared_classroom": "Classroom",
    "atrium": "Sponza",
    "atrium_glossy": "Sponza (Glossy)",
    "atrium_moving_light": "Sponza (Moving Light)",
    "living_room": "Living Room",
    "living_room_glossy": "Living Room (Glossy)",
    "living_room_moving_light": "Living Room (Moving Light)",
    "classroom": "Classroom",
}


def _t(x):
    return "–" if x is None else f"{x:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--resolution", type=parse_resolution, default=DEFAULT_RESOLUTION)
    ap.add_argument("--reference-spp", type=int, default=128)
    ap.add_argument("--ladder-spp", type=int, default=16)
    ap.add_argument("--out", default="runs/paper")
    ap.add_argument("--name", default="paper", help="results file name under bench/results/")
    ap.add_argument("--metric", choices=("hdr", "ldr"), default="ldr")
    ap.add_argument(
        "--reanalyse",
        action="store_true",
        help="reuse each scene's cached renders (renderer version from its results.json), no rendering",
    )
    ap.add_argument("--analysis-out", default=None, help="write experiment outputs here instead of --out (cache stays)")
    args = ap.parse_args(argv)
    w, h = args.resolution
    runs = {}
    for scene in args.scenes:
        run_dir = Path(args.out) / scene
        version = None
        if args.reanalyse:
            import json

            version = json.loads((run_dir / "results.json").read_text())["code"]
        out_dir = Path(args.analysis_out) / scene if args.analysis_out else run_dir
        cfg = ExperimentConfig(
            scene=scene,
            out=str(out_dir),
            frames=args.frames,
            width=w,
            height=h,
            reference_spp=args.reference_spp,
            ladder_spp=args.ladder_spp,
            metric=args.metric,
            renderer_version=version,
            cache_dir=str(run_dir / "cache"),
        )
        r = run_experiment(cfg)
        runs[scene] = {
            k: r[k]
            for k in (
                "table1",
                "table2",
                "table2_variants",
                "thresholds",
                "frames",
                "resolution",
                "reference_spp",
                "ladder_spp",
                "timing_ms",
                "cost",
                "flags",
                "wall_s",
                "bias",
                "metric",
                "code",
            )
        }
    lines = [
        f"Ours: {args.frames} frames at {w}×{h}, reference {args.reference_spp} spp, ladder 1..{args.ladder_spp} "
        f"spp, {args.metric.upper()} RMSE. Paper: 60 frames at 1280×720, 4096-spp references. "
        f"Cells: avg [min, max].",
        "",
        "| scene (paper row) | stereo discard % ours | paper | temporal discard % ours | paper | "
        "stereo spp ours | paper | temporal spp ours | paper | stereo+temporal spp ours | paper |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, r in runs.items():
        p = PAPER_NAME.get(scene, "")
        t1 = PAPER_T1.get(p.split(" (")[0], {})
        t2 = PAPER_T2.get(p)
        cells = [f"{scene} ({p})"]
        for k in ("stereo", "temporal"):
            o = r["table1"][k]
            cells += [f"{_t(o['avg'])} [{_t(o['min'])}, {_t(o['max'])}]", f"{t1[k][0]:.2f}" if k in t1 else "–"]
        for i, k in enumerate(("stereo", "temporal", "stereo_temporal")):
            o = r["table2"][k]
            cells += [f"{_t(o['avg'])} [{_t(o['min'])}, {_t(o['max'])}]", f"{t2[i][0]:.2f}" if t2 else "–"]
        lines.append("| " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n"
    record = {
        **header(),
        "args": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()},
        "runs": runs,
        "paper_table1": PAPER_T1,
        "paper_table2": PAPER_T2,
    }
    save(args.name, record, table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
