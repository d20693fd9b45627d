"""Bring your own frames: a Mitsuba 3 stereo sequence through ``stereorepro reproject --from mitsuba``.

    python examples/mitsuba_stereo.py --out runs/mitsuba_stereo      # needs `pip install mitsuba`

Per eye and frame, Mitsuba renders one film with the ``aov`` integrator (``aovs = stereorepro.io.mitsuba.AOVS``,
an unjittered ``stratified`` sampler and a ``box`` filter put the AOVs at the pixel centres; ``float32``
components) and writes it with ``film.bitmap().write``. The noisy colour comes from a second render with an
``independent`` sampler. ``cameras.json`` holds our (OpenCV) cameras, from ``sensor_to_camera``. Nothing is
converted by hand: ``--from mitsuba`` turns ``pp`` into camera-z depth and the axes into ours.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch


def scene_dict(to_world, x_fov: float, width: int, height: int, aov: bool, spp: int):
    import mitsuba as mi

    from stereorepro.io.mitsuba import AOVS

    integ = {"type": "path", "max_depth": 3}
    return {
        "type": "scene",
        "integrator": {"type": "aov", "aovs": AOVS, "img": integ} if aov else integ,
        "sensor": {
            "type": "perspective",
            "fov_axis": "x",
            "fov": x_fov,
            "to_world": to_world,
            "sampler": (
                {"type": "stratified", "sample_count": 1, "jitter": False}
                if aov
                else {"type": "independent", "sample_count": spp}
            ),
            "film": {
                "type": "hdrfilm",
                "width": width,
                "height": height,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
                "component_format": "float32",
            },
        },
        "cube": {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate([0.0, 0.5, 0.0]).scale(0.5),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.3, 0.2]}},
        },
        "floor": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], -90.0).scale(4.0),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
        },
        "light": {"type": "point", "position": [1.0, 2.5, -1.0], "intensity": {"type": "rgb", "value": 6.0}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/mitsuba_stereo")
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--resolution", default="160x120")
    p.add_argument("--smoke", action="store_true", help="2 frames at 64x48")
    args = p.parse_args(argv)
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    from stereorepro import StereoRig, intrinsics_from_fov, look_at
    from stereorepro.camera import Eye
    from stereorepro.cli import main as cli
    from stereorepro.io.mitsuba import sensor_to_camera
    from stereorepro.io.exr import read_exr, write_exr

    W, H = (64, 48) if args.smoke else tuple(int(v) for v in args.resolution.split("x"))
    frames = 2 if args.smoke else args.frames
    out = Path(args.out)
    d = out / "frames"
    d.mkdir(parents=True, exist_ok=True)
    t = lambda a: torch.tensor([a], dtype=torch.float64)  # noqa: E731
    K = intrinsics_from_fov(45.0, W, H, dtype=torch.float64)
    x_fov = math.degrees(2 * math.atan(W / 2 / float(K[0, 0, 0])))
    records = []
    for i in range(frames):
        head = look_at(t([0.4 + 0.05 * i, 0.8, -3.2]), t([0.0, 0.3, 0.0]), t([0.0, 1.0, 0.0]))
        rec = {}
        for eye, cam in zip(Eye, StereoRig().cameras(head, K, H, W)):
            # our camera -> a Mitsuba sensor: to_world maps Mitsuba's x-left, y-up frame to the world
            to_world = mi.ScalarTransform4f(np.linalg.inv(cam.cam_from_world[0].numpy()) @ np.diag([-1.0, -1, 1, 1]))
            scene = mi.load_dict(scene_dict(to_world, x_fov, W, H, aov=True, spp=1))
            mi.render(scene, spp=1)
            path = d / f"{i:04d}_{eye}.exr"
            scene.sensors()[0].film().bitmap().write(str(path))  # Mitsuba's own film: R,G,B, dd.T, nn.*, pp.*
            noisy = np.array(
                mi.render(
                    mi.load_dict(scene_dict(to_world, x_fov, W, H, aov=False, spp=1)), spp=1, seed=2 * i + int(eye)
                ),
                np.float32,
            )
            ch = read_exr(path)
            ch.update(R=noisy[..., 0], G=noisy[..., 1], B=noisy[..., 2])
            write_exr(path, ch)
            ours = sensor_to_camera(scene.sensors()[0])  # the cameras.json entry, from the sensor itself
            rec[eye] = {"K": ours.K[0].tolist(), "cam_from_world": ours.cam_from_world[0].tolist()}
        records.append(rec)
    (d / "cameras.json").write_text(
        json.dumps(
            {
                "frames": records,
                "reprojection": {"position_threshold": 0.03 * max(1.0, 180 / H), "normal_threshold": 0.25},
            },
            indent=1,
        )
    )
    code = cli(
        ["reproject", "--from", "mitsuba", "--input", str(d), "--out", str(out / "reprojected"), "--mode", "both"]
    )
    summary = json.loads((out / "reprojected" / "summary.json").read_text())
    result = {
        "exit_code": code,
        "mean_surface_discard_pct": summary["mean_surface_discard_pct"],
        "mean_discard_pct": summary["mean_discard_pct"],
        "warnings": summary["warnings"],
        "frames": frames,
        "resolution": f"{W}x{H}",
    }
    (out / "mitsuba_stereo.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
