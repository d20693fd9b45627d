"""The paper's claim made concrete: what a reprojected stereo frame costs against tracing both eyes.

In one run, on a built-in scene: trace the right eye at 1 spp; the left eye's G-buffer (primary rays only);
reproject right → left (native kernel when built, else torch); trace only the left eye's discarded pixels
(pixel_mask). Compared with tracing both eyes at 1 spp. Writes bench/results/stereo_cost.{json,md}.

    python bench/stereo_cost.py [--scene living_room --resolution 1280x720 --repeats 3]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import header, save, time_ms  # noqa: E402

from stereorepro import PathTracer, StereoReprojection, load_scene  # noqa: E402
from stereorepro.reproject import _native as native  # noqa: E402
from stereorepro.camera import Eye  # noqa: E402
from stereorepro.cli import parse_resolution  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="living_room")
    ap.add_argument("--resolution", type=parse_resolution, default=(1280, 720))
    ap.add_argument("--frame", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    W, H = args.resolution
    scene = load_scene(args.scene)
    tracer = PathTracer(scene)
    left, right = scene.stereo_cameras(args.frame, W, H)
    R = args.repeats
    r = tracer.render(right, args.frame, 1, eye=Eye.RIGHT)
    gl = tracer.gbuffer(left, args.frame)
    backend = "native" if native.available() else "torch"
    m = StereoReprojection(*scene.thresholds(H), backend=backend)
    inputs = (
        r.radiance,
        r.depth,
        r.normal,
        right.K.float(),
        right.cam_from_world,
        gl.depth,
        gl.normal,
        left.K.float(),
        left.cam_from_world,
    )
    with torch.inference_mode():
        _, valid, _ = m(*inputs)
    mask = ~valid[0, 0]
    t = {
        "trace 1 spp, one eye (with G-buffers)": time_ms(
            lambda: tracer.render(right, args.frame, 1, eye=Eye.RIGHT), R, 1
        ),
        "G-buffer only, one eye": time_ms(lambda: tracer.gbuffer(left, args.frame), R, 1),
        f"reprojection R→L ({backend})": time_ms(lambda: m(*inputs), max(R, 7), 2),
        "trace left discarded pixels only": time_ms(
            lambda: tracer.render(left, args.frame, 1, eye=Eye.LEFT, pixel_mask=mask, gbuffers=False), R, 1
        ),
    }
    ms = {k: v["median_ms"] for k, v in t.items()}
    trace = ms["trace 1 spp, one eye (with G-buffers)"]
    rep = ms[f"reprojection R→L ({backend})"]
    stereo = trace + rep + ms["trace left discarded pixels only"]
    stereo_gb = stereo + ms["G-buffer only, one eye"]
    derived = {
        "discarded_pct": 100.0 * float(mask.float().mean()),
        "tracing_1spp_over_reprojection": trace / rep,
        "stereo_frame_over_two_traced_eyes": stereo / (2 * trace),
        "stereo_frame_with_left_gbuffer_over_two_traced_eyes": stereo_gb / (2 * trace),
    }
    lines = [
        f"`{args.scene}` frame {args.frame} at {W}×{H}, 1 spp, median of {R} after warm-up.",
        "",
        "| step | ms |",
        "|---|---:|",
    ]
    lines += [f"| {k} | {v:.1f} |" for k, v in ms.items()]
    lines += [
        "",
        "| derived | value |",
        "|---|---:|",
        f"| left pixels discarded (traced) | {derived['discarded_pct']:.2f} % |",
        f"| tracing one eye at 1 spp ÷ reprojecting it | {derived['tracing_1spp_over_reprojection']:.0f}× |",
        f"| stereo frame (right traced + reprojection + left discards) ÷ two traced eyes | "
        f"{derived['stereo_frame_over_two_traced_eyes']:.3f} |",
        f"| same, counting the left G-buffer's primary rays too | "
        f"{derived['stereo_frame_with_left_gbuffer_over_two_traced_eyes']:.3f} |",
    ]
    table = "\n".join(lines) + "\n"
    save(
        "stereo_cost",
        {**header(), "scene": args.scene, "resolution": f"{W}x{H}", "timings": t, "derived": derived},
        table,
    )
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
