"""Path tracer benchmark: stage profile, ray throughput vs raw embreex, worker scaling, seconds per frame,
pixel-mask cost, for both tracer backends (``numpy`` reference and ``native`` C++ stages).

Writes bench/results/tracer.json and bench/results/tracer.md. Every timing is the median of ``--repeats``
runs after one warm-up run. Usage: ``python bench/tracer.py [--repeats 5] [--quick]``. The machine's load average
is recorded before and after (timings on a loaded machine are only comparable as ratios within one run).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _bench_common import time_interleaved, time_ms  # noqa: E402  (bench/ is the script's directory, first on sys.path)

from stereorepro.render import PathTracer  # noqa: E402
from stereorepro.render.tracer import native_available  # noqa: E402

BACKENDS = ["numpy"] + (["native"] if native_available() else [])
from stereorepro.scenes import list_scenes, load_scene  # noqa: E402

#: rounds of the round-robin timing behind the tracer / raw embreex ratios (at least)
RATIO_ROUNDS = 21


def median_time(fn, repeats):
    """Median seconds of ``fn()`` over ``repeats`` runs after one warm-up."""
    return time_ms(fn, repeats, warmup=1)["median_ms"] / 1e3


class _Recorder:
    """Wraps a TriangleBVH and keeps copies of every query (the identical rays for the raw comparison)."""

    def __init__(self, bvh):
        self.bvh, self.calls = bvh, []

    def intersect(self, o, d):
        self.calls.append(("intersect", np.ascontiguousarray(o, np.float32).copy(), d.copy(), None))
        return self.bvh.intersect(o, d)

    def occluded(self, o, d, tmax):
        self.calls.append(("occluded", o.copy(), d.copy(), tmax.copy()))
        return self.bvh.occluded(o, d, tmax)


def stage_profile(scene_name, repeats, W=320, H=180):
    """Seconds per 1-spp frame spent in each stage (one worker; ``PathTracer._stage_times``), per backend."""
    scene = load_scene(scene_name)
    cam = scene.stereo_cameras(0, W, H)[0]
    out = {}
    for be in BACKENDS:
        tr = PathTracer(scene, workers=1, backend=be)
        tr.render(cam, 0, 1, gbuffers=False)
        tr._stage_times = {}
        t0 = time.perf_counter()
        for _ in range(repeats):
            tr.render(cam, 0, 1, gbuffers=False)
        total = (time.perf_counter() - t0) / repeats
        st = {k: v / repeats for k, v in tr._stage_times.items()}
        st["other (setup, output tensors)"] = total - sum(st.values())
        out[be] = {
            "total_s": total,
            "stages_s": st,
            "intersect_fraction": sum(v for k, v in st.items() if k.startswith("intersect")) / total,
        }
    return {"scene": scene_name, "resolution": f"{W}x{H}", "backends": out}


def ray_throughput(scene_name, W, H, repeats):
    scene = load_scene(scene_name)
    tr = PathTracer(scene, workers=1, max_batch=W * H, backend="numpy")  # the rays are identical for both backends
    cam = scene.stereo_cameras(0, W, H)[0]
    rec = _Recorder(tr._bvh)
    tr._bvh = rec
    tr.render(cam, 0, 1, gbuffers=False)
    tr._bvh = rec.bvh
    kinds = {}
    names = ["primary", "bounce", "shadow"]
    for name, (q, o, d, tmax) in zip(names, rec.calls):
        raw = rec.bvh.raw_scene()
        if q == "intersect":
            t_raw = median_time(lambda: raw.run(o, d, output=1), repeats)
            t_wrap = median_time(lambda: rec.bvh.intersect(o, d), repeats)
        else:
            t_raw = median_time(lambda: raw.run(o, d, dists=tmax.copy(), query="OCCLUDED"), repeats)
            t_wrap = median_time(lambda: rec.bvh.occluded(o, d, tmax), repeats)
        kinds[name] = {
            "rays": len(o),
            "raw_embreex_mrays_s": len(o) / t_raw / 1e6,
            "wrapper_mrays_s": len(o) / t_wrap / 1e6,
        }

    # raw embreex on 2 threads over halves of the same rays (the best a 2-core tracer could do)
    def raw2():
        def part(args):
            q, o, d, tmax = args
            h = len(o) // 2
            raw = rec.bvh.raw_scene()
            for a, b in ((0, h), (h, len(o))):
                if q == "intersect":
                    raw.run(o[a:b], d[a:b], output=1)
                else:
                    raw.run(o[a:b], d[a:b], dists=tmax[a:b].copy(), query="OCCLUDED")

        with ThreadPoolExecutor(2) as ex:
            halves = []
            for q, o, d, tmax in rec.calls:
                h = len(o) // 2
                halves.append((q, o[:h], d[:h], None if tmax is None else tmax[:h]))
                halves.append((q, o[h:], d[h:], None if tmax is None else tmax[h:]))
            list(ex.map(lambda a: part(a), halves))

    def raw1():
        raw = rec.bvh.raw_scene()
        for q, o, d, tmax in rec.calls:
            if q == "intersect":
                raw.run(o, d, output=1)
            else:
                raw.run(o, d, dists=tmax.copy(), query="OCCLUDED")

    total = sum(len(c[1]) for c in rec.calls)
    # raw embreex and our tracer (each backend, 1 and 2 workers) timed round-robin, one call each per round, so
    # that all see the same machine state (the 2-thread numbers especially drift between separate timings)
    fns = {"raw1": raw1, "raw2": raw2}
    for be in BACKENDS:
        for workers in (1, 2):
            trw = PathTracer(scene, workers=workers, backend=be)
            fns[(be, workers)] = lambda trw=trw: trw.render(cam, 0, 1, gbuffers=False)
    times = {k: v["median_ms"] / 1e3 for k, v in time_interleaved(fns, repeats, warmup=1).items()}
    t_raw1, t_raw2 = times["raw1"], times["raw2"]
    out = {
        "scene": scene_name,
        "resolution": f"{W}x{H}",
        "kinds": kinds,
        "total_rays": total,
        "raw_embreex_1thread_mrays_s": total / t_raw1 / 1e6,
        "raw_embreex_2threads_mrays_s": total / t_raw2 / 1e6,
    }
    out["raw_speedup_2threads"] = t_raw1 / t_raw2
    out["backends"] = {}
    for be in BACKENDS:
        b = {}
        for workers in (1, 2):
            t = times[(be, workers)]
            b[f"tracer_{workers}w_mrays_s"] = total / t / 1e6
            b[f"tracer_{workers}w_s"] = t
        b["speedup_2w"] = b["tracer_1w_s"] / b["tracer_2w_s"]
        b["ratio_tracer1w_vs_raw1"] = b["tracer_1w_mrays_s"] / out["raw_embreex_1thread_mrays_s"]
        b["ratio_tracer2w_vs_raw2"] = b["tracer_2w_mrays_s"] / out["raw_embreex_2threads_mrays_s"]
        b["ratio_tracer2w_vs_raw1"] = b["tracer_2w_mrays_s"] / out["raw_embreex_1thread_mrays_s"]
        out["backends"][be] = b
    return out


def frame_times(resolutions, repeats):
    rows = []
    for name in list_scenes():
        scene = load_scene(name)
        trs = {be: PathTracer(scene, backend=be) for be in BACKENDS}
        for W, H in resolutions:
            cam = scene.stereo_cameras(0, W, H)[0]
            row = {"scene": name, "resolution": f"{W}x{H}", "triangles": int(len(trs["numpy"].faces))}
            for be, tr in trs.items():
                row[f"{be}_s_per_frame_with_gbuffers"] = median_time(lambda: tr.render(cam, 0, 1), repeats)
                row[f"{be}_s_radiance_only"] = median_time(lambda: tr.render(cam, 0, 1, gbuffers=False), repeats)
                row[f"{be}_s_gbuffer_only"] = median_time(lambda: tr.gbuffer(cam, 0), repeats)
            rows.append(row)
            print(
                f"  {name:26s} {W}x{H}: "
                + ", ".join(f"{be} {row[f'{be}_s_per_frame_with_gbuffers']:.3f} s" for be in trs),
                flush=True,
            )
    return rows


def mask_cost(repeats, W=320, H=180, frac=0.03):
    out = []
    for name in ("atrium", "living_room", "classroom"):
        scene = load_scene(name)
        cam = scene.stereo_cameras(0, W, H)[0]
        mask = torch.rand(H, W, generator=torch.Generator().manual_seed(0)) < frac
        for be in BACKENDS:
            tr = PathTracer(scene, backend=be)
            t_full = median_time(lambda: tr.render(cam, 0, 1, gbuffers=False), repeats)
            t_mask = median_time(lambda: tr.render(cam, 0, 1, gbuffers=False, pixel_mask=mask), repeats)
            out.append(
                {
                    "scene": name,
                    "backend": be,
                    "resolution": f"{W}x{H}",
                    "mask_fraction": float(mask.float().mean()),
                    "s_full": t_full,
                    "s_masked": t_mask,
                    "masked_over_full": t_mask / t_full,
                }
            )
    return out


def effect_costs(repeats, W=320, H=180):
    """What an undeclared effect does not cost: the same geometry with and without the effect."""
    out = []
    for base, variant in (
        ("atrium", "atrium_glossy"),
        ("living_room", "living_room_glossy"),
        ("atrium", "atrium_moving_light"),
        ("living_room", "living_room_moving_light"),
    ):
        res = {}
        for name in (base, variant):
            scene = load_scene(name)
            tr = PathTracer(scene, backend=BACKENDS[-1])
            cams = [scene.stereo_cameras(f, W, H)[0] for f in range(4)]

            def seq():
                for f, c in enumerate(cams):
                    tr.render(c, f, 1, gbuffers=False)

            res[name] = median_time(seq, repeats) / len(cams)
        out.append(
            {
                "backend": BACKENDS[-1],
                "base": base,
                "variant": variant,
                "s_per_frame_base": res[base],
                "s_per_frame_variant": res[variant],
                "extra_fraction": res[variant] / res[base] - 1,
            }
        )
    return out


def machine():
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        if subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip():
            commit += "+dirty"
    except OSError:
        commit = "unknown"
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import embreex  # noqa: F401 (version)

    return {
        "cpu": cpu,
        "cores": len(os.sched_getaffinity(0)),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "commit": commit,
        "backends": BACKENDS,
        "loadavg_start": list(os.getloadavg()),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="skip 1280x720")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    res = {"machine": machine(), "repeats": args.repeats}
    print("stage profile ...", flush=True)
    res["stages"] = [stage_profile(n, max(args.repeats, 5)) for n in ("living_room", "atrium")]
    print("ray throughput ...", flush=True)
    # the ratios are the targets and the machine is noisy: at least RATIO_ROUNDS rounds for their medians
    res["ratio_rounds"] = max(args.repeats, RATIO_ROUNDS)
    res["throughput"] = [
        ray_throughput(n, 320, 180, res["ratio_rounds"]) for n in ("atrium", "living_room", "classroom")
    ]
    print("pixel mask ...", flush=True)
    res["pixel_mask"] = mask_cost(args.repeats)
    print("effects ...", flush=True)
    res["effects"] = effect_costs(args.repeats)
    print("frame times ...", flush=True)
    resolutions = [(320, 180), (640, 360)] + ([] if args.quick else [(1280, 720)])
    res["frames"] = frame_times(resolutions, args.repeats)
    res["machine"]["loadavg_end"] = list(os.getloadavg())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tracer.json").write_text(json.dumps(res, indent=2))
    (out / "tracer.md").write_text(markdown(res))
    print(markdown(res))


def markdown(res) -> str:
    m = res["machine"]
    bes = m.get("backends", ["numpy"])
    la0, la1 = m.get("loadavg_start", [float("nan")] * 3), m.get("loadavg_end", [float("nan")] * 3)
    L = [
        "# Path tracer benchmark (`bench/tracer.py`)",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores; Python {m['python']}, numpy {m['numpy']}, torch {m['torch']}; "
        f"commit `{m['commit'][:18]}`; {m['date']}. Median of {res['repeats']} runs after a warm-up. "
        f"Backends: {', '.join(bes)} (bit-identical results). Load average (1/5/15 min) at start "
        f"{la0[0]:.2f}/{la0[1]:.2f}/{la0[2]:.2f}, at end {la1[0]:.2f}/{la1[1]:.2f}/{la1[2]:.2f}: other processes "
        "shared the cores, so compare numbers within this run, as ratios.",
        "",
        "## Stage profile (1 spp, 320x180, 1 worker; ms per frame)",
        "",
    ]
    names = []
    for r in res.get("stages", []):
        for be in bes:
            for k in r["backends"][be]["stages_s"]:
                if k not in names:
                    names.append(k)
    L += [
        "| scene | backend | total | " + " | ".join(names) + " | intersection share |",
        "|---|---|---|" + "---|" * len(names) + "---|",
    ]
    for r in res.get("stages", []):
        for be in bes:
            b = r["backends"][be]
            L.append(
                f"| {r['scene']} | {be} | {1e3 * b['total_s']:.1f} | "
                + " | ".join(f"{1e3 * b['stages_s'].get(k, 0.0):.1f}" for k in names)
                + f" | {100 * b['intersect_fraction']:.0f} % |"
            )
    L += [
        "",
        "## Ray throughput (320x180, 1 spp, identical rays)",
        "",
        "| scene | kind | rays | raw embreex Mrays/s | our wrapper Mrays/s |",
        "|---|---|---|---|---|",
    ]
    for t in res["throughput"]:
        for k, v in t["kinds"].items():
            L.append(
                f"| {t['scene']} | {k} | {v['rays']} | {v['raw_embreex_mrays_s']:.2f} | {v['wrapper_mrays_s']:.2f} |"
            )
    L += [
        "",
        "End to end (all rays of the frame / wall time of `render(gbuffers=False)`), against raw embreex on the "
        f"same rays (1 thread; 2 threads over halves of each batch); all of a scene's rows timed round-robin, median of "
        f"{res.get('ratio_rounds', res['repeats'])} rounds:",
        "",
        "| scene | backend | raw embreex 1 thr | tracer 1 worker | ratio | raw embreex 2 thr | tracer 2 workers | "
        "ratio | tracer 2-worker speed-up | raw 2-thread speed-up |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in res["throughput"]:
        for be in bes:
            b = t["backends"][be]
            L.append(
                f"| {t['scene']} | {be} | {t['raw_embreex_1thread_mrays_s']:.2f} | {b['tracer_1w_mrays_s']:.2f} | "
                f"{b['ratio_tracer1w_vs_raw1']:.2f} | {t['raw_embreex_2threads_mrays_s']:.2f} | "
                f"{b['tracer_2w_mrays_s']:.2f} | {b['ratio_tracer2w_vs_raw2']:.2f} | {b['speedup_2w']:.2f}x | "
                f"{t['raw_speedup_2threads']:.2f}x |"
            )
    L += [
        "",
        "## Seconds per 1-spp frame (one eye, default workers; G-buffers included / radiance only / G-buffer only)",
        "",
        "| scene | triangles | resolution | "
        + " | ".join(f"{be} s/frame | {be} radiance | {be} G-buffer" for be in bes)
        + " | "
        + ("native speed-up (s/frame) |" if "native" in bes else ""),
        "|---|---|---|" + "---|---|---|" * len(bes) + ("---|" if "native" in bes else ""),
    ]
    for r in res["frames"]:
        cells = " | ".join(
            f"{r[f'{be}_s_per_frame_with_gbuffers']:.3f} | {r[f'{be}_s_radiance_only']:.3f} | "
            f"{r.get(f'{be}_s_gbuffer_only', r.get('s_gbuffer_only', float('nan'))):.3f}"
            for be in bes
        )
        sp = (
            f" {r['numpy_s_per_frame_with_gbuffers'] / r['native_s_per_frame_with_gbuffers']:.2f}x |"
            if "native" in bes
            else ""
        )
        L.append(f"| {r['scene']} | {r['triangles']} | {r['resolution']} | {cells} |{sp}")
    L += [
        "",
        "## pixel_mask at 3 % of the pixels (320x180, 1 spp, radiance only)",
        "",
        "| scene | backend | full s | masked s | masked/full |",
        "|---|---|---|---|---|",
    ]
    for r in res["pixel_mask"]:
        L.append(
            f"| {r['scene']} | {r.get('backend', 'numpy')} | {r['s_full']:.4f} | {r['s_masked']:.4f} | "
            f"{r['masked_over_full']:.3f} |"
        )
    L += [
        "",
        "## What an undeclared effect does not cost (320x180, 1 spp, mean of 4 frames)",
        "",
        "| backend | base | variant | s/frame base | s/frame variant | extra |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["effects"]:
        L.append(
            f"| {r.get('backend', 'numpy')} | {r['base']} | {r['variant']} | {r['s_per_frame_base']:.4f} | "
            f"{r['s_per_frame_variant']:.4f} | {100 * r['extra_fraction']:+.1f} % |"
        )
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    main()
