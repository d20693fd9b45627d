"""Why a scene's temporal discards are what they are (e.g. Sponza's, above the paper's): the right eye's temporal
discards split by reason, against how fast the camera moves.

For each scene and each ``--slowdowns`` factor k, the scene's camera path is sampled k times more densely (the
same path, k·(N−1)+1 frames: the camera moves 1/k as far per frame) and, at the experiment's frames
f = 1 .. ``--frames``−1 of the original path, the G-buffer of frame k·f is reprojected from frame k·f − 1 exactly as
the experiment's temporal scheme does (bilinear taps, the scene's thresholds at this resolution). Reported per
scene and k: the temporal discard percentage of the surface pixels (what Table 1 counts), its split by
:class:`~stereorepro.reproject.Reason`, and the camera's motion per frame (translation, rotation, and the mean and
95th-percentile screen motion of the surface pixels, in pixels of a 720-row image). Only G-buffers are rendered
(no path tracing), so it runs in minutes.

    .venv/bin/python bench/temporal_discards.py --scenes shared_sponza shared_living_room shared_classroom \\
        --resolution 640x360 --frames 30 --slowdowns 1 2 4

Writes bench/results/temporal_discards_<W>x<H>.json|md.
"""

from __future__ import annotations

import argparse
import copy
import math

import numpy as np
import torch
from _bench_common import header, save

from stereorepro.camera import camera_motion, has_surface
from stereorepro.workflows.experiment.config import RIGHT
from stereorepro.render import PathTracer
from stereorepro.reproject import Reason, View, backward_reproject
from stereorepro.scenes import load_scene

#: The paper's Table 1 temporal discards (average %), for the comparison column.
PAPER_TEMPORAL = {"shared_sponza": 3.96, "shared_living_room": 1.48, "shared_classroom": 2.19}


def slowed(scene, k: int):
    """``scene`` with its camera path sampled ``k`` times more densely: frame k·f is the original frame f."""
    out = copy.copy(scene)  # a shallow copy keeps what loading attached (geometry, materials, mesh offsets)
    out.num_frames = (scene.num_frames - 1) * k + 1
    return out


def pose_change(a, b) -> tuple[float, float]:
    """(distance between the camera centres, rotation angle in degrees) from PinholeCamera ``a`` to ``b``."""
    r = a.cam_from_world[0, :3, :3].double() @ b.cam_from_world[0, :3, :3].double().T
    cos = float(((torch.trace(r) - 1) / 2).clamp(-1, 1))
    return float(torch.linalg.norm(a.center_world.double() - b.center_world.double())), math.degrees(math.acos(cos))


def measure(scene_name: str, W: int, H: int, frames: int, k: int) -> dict:
    scene = load_scene(scene_name)
    if "moving_objects" in scene.effects:
        raise SystemExit(f"{scene_name}: scenes with moving objects are not supported (their animation keeps its pace)")
    scene = slowed(scene, k)
    tracer = PathTracer(scene)
    thr_p, thr_n = scene.thresholds(H)
    counts = {r.name.lower(): 0 for r in Reason if r != Reason.KEPT}
    surf_total = disc_total = 0
    per_frame, trans, rot, flow_mean, flow_p95 = [], [], [], [], []
    views = {}  # frame -> (camera, G-buffer); at k = 1 a pair's current frame is the next pair's previous one

    def view(fr: int):
        if fr not in views:
            cam = scene.stereo_cameras(fr, W, H)[int(RIGHT)]
            views[fr] = (cam, tracer.gbuffer(cam, fr))
        return views[fr]

    for f in range(1, frames):
        cur_f, prev_f = k * f, k * f - 1
        for old in [x for x in views if x < prev_f]:
            del views[old]
        prev, gp = view(prev_f)
        cam, g = view(cur_f)
        _, valid, reason, _ = backward_reproject(
            torch.zeros(1, 3, H, W),
            View(gp.depth, gp.normal, prev.K.float(), prev.cam_from_world.double()),
            View(g.depth, g.normal, cam.K.float(), cam.cam_from_world.double()),
            (thr_p, thr_n),
        )
        surf = has_surface(g.depth)
        disc = ~valid & surf
        surf_total += int(surf.sum())
        disc_total += int(disc.sum())
        for r in counts:
            counts[r] += int(((reason == int(Reason[r.upper()])) & surf).sum())
        per_frame.append(100.0 * float(disc.sum()) / max(int(surf.sum()), 1))
        t, a = pose_change(prev, cam)
        trans.append(t)
        rot.append(a)
        motion = camera_motion(g.depth, cam.K, cam.cam_from_world, prev.K, prev.cam_from_world)  # static scenes
        m = motion[0].double().norm(dim=0)[surf[0, 0]]
        m = m[torch.isfinite(m)] * (720.0 / H)  # pixels of a 720-row image (NaN: behind the previous camera)
        flow_mean.append(float(m.mean()))
        flow_p95.append(float(torch.quantile(m[:: max(1, m.numel() // 200_000)], 0.95)))
    pct = lambda n: 100.0 * n / max(surf_total, 1)  # noqa: E731
    return {
        "scene": scene_name,
        "slowdown": k,
        "pairs": frames - 1,
        "thresholds": [thr_p, thr_n],
        "discard_pct": pct(disc_total),
        "discard_pct_per_frame": per_frame,
        "by_reason_pct": {r: pct(n) for r, n in counts.items() if n},
        "translation_per_frame": float(np.mean(trans)),
        "rotation_deg_per_frame": float(np.mean(rot)),
        "flow_px720_mean": float(np.mean(flow_mean)),
        "flow_px720_p95": float(np.mean(flow_p95)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["shared_sponza", "shared_living_room", "shared_classroom"])
    ap.add_argument("--resolution", default="640x360")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--slowdowns", type=int, nargs="+", default=[1, 2, 4])
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.resolution.lower().split("x"))
    rows = []
    for name in args.scenes:
        for k in args.slowdowns:
            rows.append(measure(name, W, H, args.frames, k))
            r = rows[-1]
            print(
                f"{name} 1/{k}: {r['discard_pct']:.2f} % {r['by_reason_pct']} flow {r['flow_px720_mean']:.2f} px",
                flush=True,
            )
    reasons = sorted({x for r in rows for x in r["by_reason_pct"]}, key=lambda x: int(Reason[x.upper()]))
    lines = [
        "| scene | speed | camera per frame | screen motion, 720p px (mean / p95) | temporal discards % "
        "| paper % | " + " | ".join(reasons) + " |",
        "|---|---:|---|---|---:|---:|" + "---:|" * len(reasons),
    ]
    for r in rows:
        paper = PAPER_TEMPORAL.get(r["scene"])
        lines.append(
            f"| {r['scene']} | 1/{r['slowdown']} | {100 * r['translation_per_frame']:.1f} cm, "
            f"{r['rotation_deg_per_frame']:.2f}° | {r['flow_px720_mean']:.2f} / {r['flow_px720_p95']:.2f} "
            f"| {r['discard_pct']:.2f} | {'' if paper is None else paper} | "
            + " | ".join(f"{r['by_reason_pct'].get(x, 0.0):.2f}" for x in reasons)
            + " |"
        )
    table = (
        f"Temporal discards of the right eye at {W}×{H}, frames 1..{args.frames - 1} of each scene's path "
        f"(speed 1/k: the path sampled k times more densely), split by reason (% of surface pixels).\n\n"
        + "\n".join(lines)
        + "\n"
    )
    record = {**header(), "resolution": f"{W}x{H}", "frames": args.frames, "rows": rows}
    j, md = save(f"temporal_discards_{W}x{H}", record, table, script="temporal_discards.py")
    print(table)
    print(f"wrote {j} and {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
