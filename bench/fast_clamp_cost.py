"""What fast-history clamping (``TemporalReprojection.fast_clamp``) costs per frame: the temporal step with and without
it, and the box clamp alone on the torch reference and the native core, at one resolution.

The G-buffers are ray-cast analytic frames (:mod:`stereorepro._testing`: a floor, walls and spheres; the previous
frame's camera is :func:`~stereorepro._testing.camera_pair`'s source, 6.5 cm aside and 5 cm forward, so that some
history is discarded), the colours uniform noise; the step is
:func:`stereorepro.accumulate.temporal_step` from a state that carries a history length and (with the clamp) a fast
history. All timings round-robin in one process (each callable once per round, medians after warm-up), so their
ratios compare like with like on a loaded machine.

    nice -n 5 .venv/bin/python bench/fast_clamp_cost.py --resolution 1280x720

Writes bench/results/fast_clamp_cost.json|md.
"""

from __future__ import annotations

import argparse

import torch
from _bench_common import header, save, time_interleaved

from stereorepro import FastClamp, TemporalReprojection, fast_history_clamp
from stereorepro._testing import camera_pair, default_scene, raycast
from stereorepro.accumulate import EyeState, temporal_step
from stereorepro.reproject import _native


def frames(W: int, H: int):
    """Two ray-cast G-buffers (previous, current), float32."""
    cur, prev = camera_pair(H, W, forward=0.05, dtype=torch.float32)
    scene = default_scene()
    out = []
    for cam in (prev, cur):
        g = raycast(cam, scene, dtype=torch.float32)
        out.append((g.depth, g.normal, cam.K, cam.cam_from_world))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="1280x720")
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    W, H = (int(x) for x in args.resolution.split("x"))
    (pd, pn, pK, pc), (d, n, K, c) = frames(W, H)
    gen = torch.Generator().manual_seed(0)
    color, hist, fast = (torch.rand(1, 3, H, W, generator=gen) for _ in range(3))
    length = torch.full((1, 1, H, W), 5.0)
    thr = (0.05, 0.2)
    fns = {}
    for backend in ("native", "torch") if _native.available() else ("torch",):
        plain = TemporalReprojection(*thr, backend=backend)
        clamped = TemporalReprojection(*thr, backend=backend)
        clamped.fast_clamp = FastClamp()
        s_plain = EyeState(hist, length, pd, pn, pK, pc)
        s_fast = EyeState(hist, length, pd, pn, pK, pc, fast)
        fns[f"temporal step, {backend}"] = lambda m=plain, s=s_plain: temporal_step(m, s, color, d, n, K, c)
        fns[f"temporal step + fast clamp, {backend}"] = lambda m=clamped, s=s_fast: temporal_step(
            m, s, color, d, n, K, c
        )
        fns[f"box clamp alone, {backend}"] = lambda b=backend: fast_history_clamp(hist, fast, 2.0, 1, backend=b)
    with torch.no_grad():
        times = time_interleaved(fns, repeats=args.repeats)
    record = header() | {
        "command": f"bench/fast_clamp_cost.py --resolution {args.resolution} --repeats {args.repeats}",
        "resolution": [W, H],
        "torch_threads": torch.get_num_threads(),
        "times": times,
    }
    rows = ["| what | median ms | min ms | × its backend's plain step |", "|---|---:|---:|---:|"]
    for name, t in times.items():
        base = times[f"temporal step, {name.rsplit(', ', 1)[1]}"]["median_ms"]
        rows.append(f"| {name} | {t['median_ms']:.1f} | {t['min_ms']:.1f} | {t['median_ms'] / base:.2f} |")
    md = (
        f"Fast-history clamping's cost at {W}x{H}, B=1, float32, `FastClamp()` (fast alpha 0.5, 2σ, 3×3): the temporal "
        "step (`stereorepro.accumulate.temporal_step`; the module's backend runs the warp, the blends and the box "
        f"clamp) with and without the clamp, and the box clamp alone; medians of {args.repeats} round-robin rounds "
        "after warm-up (the ratios compare within this run). Command: "
        f"`nice -n 5 .venv/bin/python {record['command']}`.\n\n" + "\n".join(rows) + "\n"
    )
    save("fast_clamp_cost", record, md)
    print(md)


if __name__ == "__main__":
    main()
