"""What moving objects cost: the per-frame BVH against the alternatives embreex allows, and the reprojection
with motion vectors against camera-only warping, on each implementation (native, torch fast path, torch general
path) and on ``backend="auto"``.

    .venv/bin/python bench/moving_objects.py        # writes bench/results/moving_objects.{json,md}

embreex (4.4) has no instancing and no vertex updates: a moving object means a new BVH. The options are (a) one
BVH of the whole scene rebuilt per frame (what the tracer does) or (b) the static geometry's BVH built once plus a
small BVH of the moving faces rebuilt per frame, every query run on both and the nearer hit kept. (b) is estimated
from its parts: the small build plus one more query per ray set on the small BVH.
"""

from __future__ import annotations

import numpy as np
import torch

from _bench_common import header, save, time_interleaved, time_ms
from stereorepro import History, TemporalReprojection, View, camera_motion, load_scene
from stereorepro.camera import Eye
from stereorepro._testing import example_inputs
from stereorepro.render import PathTracer
from stereorepro.render._embree import TriangleBVH
from stereorepro.reproject import _native, functional
from stereorepro.reproject.functional import temporal_reproject


def bvh_costs(W=320, H=180) -> dict:
    scene = load_scene("living_room_moving_objects")
    tr = PathTracer(scene)
    v = tr.object_vertices(17)
    moving = tr.face_object >= 0
    static_faces, moving_faces = tr.faces[~moving], tr.faces[moving]
    cam = scene.stereo_cameras(17, W, H)[1]
    tr.gbuffer(cam, 17)  # warm the frame's geometry
    K = cam.K[0].double().numpy()
    wfc = cam.world_from_cam[0].double().numpy()
    ys, xs = np.mgrid[0:H, 0:W]
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5, np.ones(W * H)], 0)
    d = (wfc[:3, :3] @ np.linalg.inv(K) @ pix).T.astype(np.float32)
    o = np.broadcast_to(wfc[:3, 3].astype(np.float32), d.shape).copy()
    full_bvh, small_bvh = TriangleBVH(v, tr.faces), TriangleBVH(v, moving_faces)
    t = time_interleaved(
        {
            "place objects (object_vertices)": lambda: tr.object_vertices(17),
            "build: whole scene": lambda: TriangleBVH(v, tr.faces),
            "build: moving faces only": lambda: TriangleBVH(v, moving_faces),
            "query: primary rays, whole scene": lambda: full_bvh.intersect(o, d),
            "query: primary rays, moving faces only": lambda: small_bvh.intersect(o, d),
        },
        repeats=9,
        warmup=2,
    )
    render = time_ms(lambda: tr.render(cam, 17, 1, eye=Eye.RIGHT, gbuffers=False), repeats=5, warmup=1)
    out = {
        "scene": scene.name,
        "triangles": int(len(tr.faces)),
        "moving_triangles": int(moving.sum()),
        "static_triangles": int(len(static_faces)),
        "resolution": f"{W}x{H}",
        "timings": t,
        "render_1spp_one_eye": render,
    }
    try:  # a real scene's geometry, for scale
        big = load_scene("shared_living_room").geometry()
        out["shared_living_room_triangles"] = int(len(big.faces))
        out["shared_living_room_build"] = time_ms(lambda: TriangleBVH(big.vertices, big.faces), repeats=3, warmup=1)
    except Exception as e:  # noqa: BLE001 - the shared meshes are optional
        out["shared_living_room_build"] = f"not measured: {e}"
    return out


def _general_path(fn):
    """``fn`` with the torch fast path switched off (the general path: the reference)."""

    def call():
        functional.FAST_PATH = False
        try:
            return fn()
        finally:
            functional.FAST_PATH = True

    return call


def reprojection_costs() -> dict:
    """Temporal reprojection (the cameras' own motion vectors, zero world motion) on every implementation."""
    rows = {}
    thr = (0.05, 0.25)
    for W, H in ((320, 180), (1280, 720)):
        m = TemporalReprojection(*thr)
        cur, depth, normal, K, T, hc, hl, pd, pn, pK, pT = example_inputs(m, height=H, width=W)
        motion = camera_motion(depth, K, T, pK, pT)
        view, moving = View(depth, normal, K, T), View(depth, normal, K, T, motion, torch.zeros_like(normal))
        prev, hist = View(pd, pn, pK, pT), History(hc, hl)

        def step(v, backend):
            return lambda: temporal_reproject(cur, v, hist, prev, thr, backend=backend)

        fns = {
            "torch fast path, cameras": step(view, "torch"),
            "torch fast path, motion vectors": step(moving, "torch"),
            "torch general path, motion vectors": _general_path(step(moving, "torch")),
            "auto, motion vectors": step(moving, "auto"),
        }
        if _native.available():
            fns["native, cameras"] = step(view, "native")
            fns["native, motion vectors"] = step(moving, "native")
        with torch.no_grad():
            rows[f"{W}x{H}"] = time_interleaved(fns, repeats=7, warmup=2)
    return rows


def main() -> None:
    rec = header()
    rec["bvh"] = bvh_costs()
    rec["reprojection"] = reprojection_costs()
    b = rec["bvh"]
    t = b["timings"]
    md = [
        f"Scene `{b['scene']}`: {b['triangles']} triangles, {b['moving_triangles']} of them moving; "
        f"{b['resolution']}. Medians of {t['build: whole scene']['repeats']} after warm-up.",
        "",
        "| step | ms |",
        "|---|---:|",
    ]
    for k, v in t.items():
        md.append(f"| {k} | {v['median_ms']:.2f} |")
    md.append(f"| one 1-spp render of one eye (for scale) | {b['render_1spp_one_eye']['median_ms']:.1f} |")
    sl = b.get("shared_living_room_build")
    if isinstance(sl, dict):
        md.append(
            f"| build: shared_living_room ({b['shared_living_room_triangles']} triangles) | {sl['median_ms']:.1f} |"
        )
    md += [
        "",
        "Temporal reprojection, `temporal_reproject` (synthetic scene of `example_inputs`), ms:",
        "",
        "| resolution | " + " | ".join(next(iter(rec["reprojection"].values()))) + " |",
        "|---|" + "---:|" * len(next(iter(rec["reprojection"].values()))),
    ]
    for res, row in rec["reprojection"].items():
        md.append(f"| {res} | " + " | ".join(f"{v['median_ms']:.1f}" for v in row.values()) + " |")
    j, m = save("moving_objects", rec, "\n".join(md) + "\n")
    print(m.read_text())


if __name__ == "__main__":
    main()
