"""Distribution overhead on one machine: the demo's experiment in process against the same on a 2-worker Dask
LocalCluster (``--scheduler local:2``), each from an empty cache, in A B B A order (ratios in one run).

    .venv/bin/python bench/dask_overhead.py [--repeats 2] [--frames 24]

Writes bench/results/dask_overhead.json|md. Also checks that both give the same tables.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from _bench_common import header, save

from stereorepro.cli.demo import DEFAULTS
from stereorepro.workflows.experiment import ExperimentConfig, run_experiment


def one(scheduler: str | None, frames: int, root: Path) -> tuple[float, dict]:
    out = Path(tempfile.mkdtemp(dir=root))
    w, h = DEFAULTS["resolution"]
    cfg = ExperimentConfig(
        scene=DEFAULTS["scene"],
        out=str(out),
        frames=frames,
        width=w,
        height=h,
        reference_spp=DEFAULTS["reference_spp"],
        ladder_spp=DEFAULTS["ladder_spp"],
        progress=False,
        scheduler=scheduler,
    )
    t0 = time.perf_counter()
    res = run_experiment(cfg, log=lambda *a: None)
    wall = time.perf_counter() - t0
    shutil.rmtree(out)
    return wall, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=DEFAULTS["frames"])
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench-dist-"))
    walls: dict[str, list[float]] = {"in_process": [], "local_2": []}
    tables = {}
    order = (["in_process", "local_2", "local_2", "in_process"] * args.repeats)[: 2 * args.repeats]
    for name in order:
        wall, res = one(None if name == "in_process" else "local:2", args.frames, root)
        walls[name].append(wall)
        tables[name] = (res["table1"], res["table2"], res["table2_variants"])
        print(f"{name}: {wall:.1f} s", flush=True)
    shutil.rmtree(root, ignore_errors=True)
    med = {k: statistics.median(v) for k, v in walls.items()}
    ratio = med["local_2"] / med["in_process"]
    same = tables["in_process"] == tables["local_2"]
    w, h = DEFAULTS["resolution"]
    rec = {
        **header(),
        "config": {
            "scene": DEFAULTS["scene"],
            "frames": args.frames,
            "resolution": f"{w}x{h}",
            "reference_spp": DEFAULTS["reference_spp"],
            "ladder_spp": DEFAULTS["ladder_spp"],
        },
        "order": order,
        "wall_s": walls,
        "median_s": med,
        "ratio_local2_over_in_process": ratio,
        "identical_tables": same,
    }
    md = (
        "| run | wall s (each) | median s |\n|---|---|---:|\n"
        + "".join(f"| {k} | {', '.join(f'{x:.1f}' for x in v)} | {med[k]:.1f} |\n" for k, v in walls.items())
        + f"\nLocalCluster(2) / in process: **{ratio:.2f}×**; identical tables: {same}. "
        f"Demo config ({DEFAULTS['scene']}, {args.frames} frames, {w}×{h}, reference {DEFAULTS['reference_spp']} "
        f"spp, ladder {DEFAULTS['ladder_spp']}), each run from an empty cache, order {' '.join(order)}.\n"
    )
    save("dask_overhead", rec, md)
    print(md)


if __name__ == "__main__":
    main()
