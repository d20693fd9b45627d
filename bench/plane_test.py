"""The slope-scaled plane test (``Thresholds(position_test="plane")``) against the scenes' absolute position
thresholds, through the experiment's drivers on real scenes.

For each scene both eyes are rendered over the first ``--frames`` frames of the scene's camera path: 1 spp with
G-buffers, and a ``--reference-spp`` reference from an independent sample stream. Each position test then drives

* the **temporal** scheme (``SpatiotemporalReprojection(stereo=False)``: both eyes traced in full, each accumulated
  over time) and
* the **stereo+temporal** scheme (the paper's: the right eye traced in full and accumulated, the left eye
  reprojected from it where the tests pass, traced and accumulated elsewhere),

alpha 0.2 with warm-up, bilinear reads, the scene's normal threshold, over

* the 1-spp frames, scored against the references (LDR, clamped to [0, 1]; RMSE over all pixels of both eyes,
  frames 1..F−1; the references' own noise is in every configuration's number alike);
* the G-buffer albedo, noise-free and exactly known at every frame, scored against the current frame's albedo:
  the error of what the tests let through (resampling and wrongly kept taps) alone.

Reported: the temporal discards (the right eye's surface pixels whose history was discarded, frames 1..), the
stereo discards (the left eye's surface pixels the right eye could not give), both RMSEs, and the share of the right
eye's surface pixels whose whole 4×4 footprint passes the temporal tests (what lets ``sampling="catmull_rom"``
act). Configurations: ``distance`` at the scene's own threshold (``Scene.thresholds(H)``: its position threshold
times ``threshold_scale(H)``, what the experiment uses) and ``plane`` at each ``--relative`` threshold.

    nice -n 5 .venv/bin/python bench/plane_test.py --scenes living_room classroom living_room_textured \\
        --resolution 640x360 --frames 16 --reference-spp 16 --relative 0.005 0.01 0.02

Writes bench/results/plane_test.json|md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from _bench_common import header, save

from stereorepro import SpatiotemporalReprojection, Thresholds, View, backward_reproject
from stereorepro.camera import has_surface
from stereorepro.render import PathTracer
from stereorepro.scenes import load_scene

SCHEMES = {"temporal": False, "stereo+temporal": True}  # name: stereo


def render_frames(name: str, W: int, H: int, frames: int, ref_spp: int, seed: int) -> list[dict]:
    """Per frame and eye (0 left, 1 right): the View, 1-spp radiance, reference radiance and albedo (float32)."""
    scene = load_scene(name)
    tracer = PathTracer(scene, seed=seed)
    out = []
    for f in range(frames):
        eyes = []
        for eye, cam in enumerate(scene.stereo_cameras(f, W, H)):
            r = tracer.render(cam, f, 1, sample_offset=0, eye=eye)
            ref = tracer.render(cam, f, ref_spp, sample_offset=1, eye=eye, gbuffers=False).radiance
            view = View(r.depth.float(), r.normal.float(), cam.K, cam.cam_from_world)
            eyes.append(dict(view=view, noisy=r.radiance.float(), ref=ref.float(), albedo=r.albedo.float()))
        out.append(eyes)
    return out


def drive(frames: list[list[dict]], thr: Thresholds, stereo: bool, key: str):
    """The scheme over ``key`` ("noisy" or "albedo") frames: per frame (left, right) outputs, the right eye's
    temporal keep mask and the stereo keep mask."""
    st = SpatiotemporalReprojection(thr.position, thr.normal, alpha=0.2, stereo=stereo)
    st.position_test = thr.position_test
    outs = []
    for left, right in frames:
        r, lv = right["view"], left["view"]
        color_r = st.right(right[key], r.depth, r.normal, r.K, r.cam_from_world)
        st.left_trace_mask(lv.depth, lv.normal, lv.K, lv.cam_from_world)
        color_l = st.left(left[key])
        outs.append((color_l, color_r, st.full_valid, st.stereo_valid if stereo else None))
    return outs


def footprint_share(frames: list[list[dict]], thr: Thresholds) -> list[float]:
    """Per frame 1..: the share of the right eye's surface pixels whose 4×4 temporal footprint passes every test
    (a random image's Catmull-Rom and bilinear warps differ exactly there, almost surely)."""
    g = torch.Generator().manual_seed(0)
    shares = []
    for i in range(1, len(frames)):
        prev, view = frames[i - 1][1]["view"], frames[i][1]["view"]
        probe = torch.rand(1, 3, *view.depth.shape[-2:], generator=g)
        cub = backward_reproject(probe, prev, view, thr, sampling="catmull_rom").values
        bil = backward_reproject(probe, prev, view, thr).values
        surface = has_surface(view.depth)[0, 0]
        shares.append(float((cub != bil).any(1)[0][surface].float().mean()))
    return shares


def measure(frames: list[list[dict]], thr: Thresholds) -> dict:
    """Discards, RMSEs and footprint share of both schemes for one configuration."""
    res = {}
    for scheme, stereo in SCHEMES.items():
        noisy, albedo = drive(frames, thr, stereo, "noisy"), drive(frames, thr, stereo, "albedo")
        mse, amse, tdisc, sdisc = [], [], [], []
        for i in range(1, len(frames)):
            (cl, cr, full_valid, stereo_valid), (al, ar, _, _) = noisy[i], albedo[i]
            left, right = frames[i]
            for c, eye in ((cl, left), (cr, right)):
                mse.append(float((c.clamp(0, 1) - eye["ref"].clamp(0, 1)).square().mean()))
            amse.append(float(((al - left["albedo"]).square().mean() + (ar - right["albedo"]).square().mean()) / 2))
            surf_r, surf_l = has_surface(right["view"].depth), has_surface(left["view"].depth)
            tdisc.append(float((~full_valid & surf_r).sum() / surf_r.sum()))
            if stereo:
                sdisc.append(float((~stereo_valid & surf_l).sum() / surf_l.sum()))
        res[scheme] = {
            "rmse_ldr": float(np.sqrt(np.mean(mse))),
            "albedo_rmse": float(np.sqrt(np.mean(amse))),
            "temporal_discard_pct": 100 * float(np.mean(tdisc)),
            "stereo_discard_pct": 100 * float(np.mean(sdisc)) if sdisc else None,
        }
    res["footprint_pass_pct"] = 100 * float(np.mean(footprint_share(frames, thr)))
    return res


def configurations(name: str, H: int, relative: list[float]) -> list[tuple[str, Thresholds]]:
    pos, nrm = load_scene(name).thresholds(H)
    out = [(f"distance {pos:g}", Thresholds(pos, nrm))]
    return out + [(f"plane {r:g}", Thresholds(r, nrm, position_test="plane")) for r in relative]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["living_room", "classroom", "living_room_textured"])
    ap.add_argument("--resolution", default="640x360")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--reference-spp", type=int, default=16)
    ap.add_argument("--relative", type=float, nargs="+", default=[0.005, 0.01, 0.02])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    W, H = (int(x) for x in args.resolution.split("x"))
    record = header() | {
        "command": "nice -n 5 .venv/bin/python bench/plane_test.py --scenes "
        + " ".join(args.scenes)
        + f" --resolution {W}x{H} --frames {args.frames} --reference-spp {args.reference_spp} --relative "
        + " ".join(f"{r:g}" for r in args.relative),
        "resolution": [W, H],
        "frames": args.frames,
        "reference_spp": args.reference_spp,
        "alpha": 0.2,
        "scenes": {},
    }
    rows = []
    for name in args.scenes:
        t0 = time.perf_counter()
        frames = render_frames(name, W, H, args.frames, args.reference_spp, args.seed)
        scene_rec = {"render_s": time.perf_counter() - t0, "configs": {}}
        for label, thr in configurations(name, H, args.relative):
            t1 = time.perf_counter()
            res = measure(frames, thr)
            res["thresholds"] = [thr.position, thr.normal, thr.position_test]
            res["seconds"] = time.perf_counter() - t1
            scene_rec["configs"][label] = res
            t, s = res["temporal"], res["stereo+temporal"]
            rows.append(
                f"| {name} | {label} | {t['temporal_discard_pct']:.2f} | {t['rmse_ldr']:.4f} | "
                f"{t['albedo_rmse']:.4f} | {s['stereo_discard_pct']:.2f} | {s['temporal_discard_pct']:.2f} | "
                f"{s['rmse_ldr']:.4f} | {s['albedo_rmse']:.4f} | {res['footprint_pass_pct']:.1f} |"
            )
            print(rows[-1], flush=True)
        record["scenes"][name] = scene_rec
    md = (
        f"Position tests through the drivers, {W}x{H}, frames 0..{args.frames - 1} of each scene's path, alpha 0.2 "
        f"with warm-up, bilinear reads, the scene's normal threshold. `distance t`: the absolute test at the "
        f"scene's own threshold t (scene units, `Scene.thresholds(H)`); `plane r`: the slope-scaled plane test at "
        f"r of view depth. Discards: % of surface pixels (temporal: the right eye's history, frames 1..; stereo: "
        f"the left eye's pixels the right eye could not give). RMSE: LDR, both eyes, all pixels, frames 1.., 1 spp "
        f"against {args.reference_spp}-spp references (their noise included alike); albedo RMSE: the noise-free "
        f"albedo through the scheme against the current albedo. Footprint pass: % of the right eye's surface "
        f"pixels whose 4x4 temporal footprint passes every test (where Catmull-Rom acts).\n\n"
        f"Commit {record['commit']}, {record['machine']['cpu']} ({record['machine']['cores']} cores), "
        f"{record['date']}. Command: `{record['command']}`\n\n"
        "| scene | test | temporal: discards % | RMSE | albedo RMSE | stereo+temporal: stereo discards % | "
        "temporal discards % | RMSE | albedo RMSE | footprint pass % |\n"
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n" + "\n".join(rows) + "\n"
    )
    save("plane_test", record, md)


if __name__ == "__main__":
    main()
