"""Mitsuba 3 frames in: ``render_gbuffer`` and ``stereorepro reproject --from mitsuba`` against a real Mitsuba
render (``scalar_rgb``; skipped where mitsuba is not installed)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from stereorepro import StereoRig, intrinsics_from_fov, look_at
from stereorepro.cli import main
from stereorepro.io.mitsuba import AOVS, FLIP, render_gbuffer, sensor_to_camera
from stereorepro.io.exr import read_exr, write_exr

mi = pytest.importorskip("mitsuba")
mi.set_variant("scalar_rgb")

W, H = 64, 48


def _eye_cameras(frame: int):
    """Our (OpenCV) left and right cameras of a parallel rig whose head moves a little per frame."""
    t = lambda a: torch.tensor([a], dtype=torch.float64)  # noqa: E731
    head = look_at(t([0.4 + 0.05 * frame, 0.8, -3.2]), t([0.0, 0.3, 0.0]), t([0.0, 1.0, 0.0]))
    return StereoRig(0.065).cameras(head, intrinsics_from_fov(45.0, W, H, dtype=torch.float64), H, W)


def _scene(cam, spp: int, aov: bool):
    """A cube on a floor under a point light and a dim sky, seen by ``cam`` (ours) through a Mitsuba sensor."""
    fx = float(cam.K[0, 0, 0])
    x_fov = math.degrees(2 * math.atan(W / 2 / fx))
    to_world = np.linalg.inv(cam.cam_from_world[0].double().numpy()) @ FLIP  # our camera -> Mitsuba's frame
    integ = {"type": "path", "max_depth": 3}
    return mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "aov", "aovs": AOVS, "img": integ} if aov else integ,
            "sensor": {
                "type": "perspective",
                "fov_axis": "x",
                "fov": x_fov,
                "to_world": mi.ScalarTransform4f(to_world),
                "sampler": {
                    "type": "stratified" if aov else "independent",
                    "sample_count": spp,
                    **({"jitter": False} if aov else {}),
                },
                "film": {
                    "type": "hdrfilm",
                    "width": W,
                    "height": H,
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
    )


class TestMitsubaAdapter:
    def test_sensor_to_camera_round_trip(self):
        left, _ = _eye_cameras(0)
        got = sensor_to_camera(_scene(left, 1, False).sensors()[0])
        assert torch.allclose(got.K, left.K, atol=1e-4) and torch.allclose(
            got.cam_from_world, left.cam_from_world, atol=1e-5
        )

    def test_render_gbuffer_positions_at_pixel_centres(self):
        left, _ = _eye_cameras(0)
        f = render_gbuffer(_scene(left, 4, False), spp=4)
        hit = torch.isfinite(f["depth"])[0, 0]
        assert 0.3 < float(hit.float().mean()) < 1.0  # floor, cube and sky
        P = f["position"][0].double().reshape(3, -1)
        T, K = f["cam_from_world"][0], f["K"][0]
        q = T[:3, :3] @ P + T[:3, 3:]
        uv = ((K @ q)[:2] / q[2]).reshape(2, H, W)
        ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
        assert float((uv[0] - xs)[hit].abs().max()) < 1e-3 and float((uv[1] - ys)[hit].abs().max()) < 1e-3
        assert torch.allclose(q[2].reshape(H, W)[hit].float(), f["depth"][0, 0][hit], rtol=1e-5)  # camera z
        n = f["normal"][0].norm(dim=0)[hit]
        assert float((n - 1).abs().max()) < 1e-4

    def test_reproject_from_mitsuba(self, tmp_path, capsys):
        """A Mitsuba stereo sequence through `stereorepro reproject --from mitsuba`, no hand conversion: the
        left eye reprojected from the right is valid on >= 90 % of its surface pixels and closer to the left
        reference than the left 1-spp image."""
        d = tmp_path / "in"
        d.mkdir()
        frames = []
        refs = {}
        for i in range(2):
            left, right = _eye_cameras(i)
            frames.append(
                {
                    e: {"K": c.K[0].tolist(), "cam_from_world": c.cam_from_world[0].tolist()}
                    for e, c in (("left", left), ("right", right))
                }
            )
            for e, c in (("left", left), ("right", right)):
                # Mitsuba's own film: AOVs at the pixel centres (one unjittered stratified sample), written by
                # bitmap.write; its R, G, B replaced by a noisy 1-spp render (an unjittered sample gives the same
                # deterministic value for a surface point in both eyes: no noise to measure)
                scene = _scene(c, 1, True)
                mi.render(scene, spp=1)
                p = d / f"{i:04d}_{e}.exr"
                scene.sensors()[0].film().bitmap().write(str(p))
                noisy = np.array(mi.render(_scene(c, 1, False), spp=1, seed=11 * i + (e == "right")), np.float32)
                ch = read_exr(p)
                ch.update(R=noisy[..., 0], G=noisy[..., 1], B=noisy[..., 2])
                write_exr(p, ch)
            refs[i] = np.array(mi.render(_scene(left, 64, False), spp=64, seed=99), dtype=np.float32)[..., :3]
        (d / "cameras.json").write_text(
            json.dumps({"frames": frames, "reprojection": {"position_threshold": 0.03, "normal_threshold": 0.25}})
        )
        out = tmp_path / "out"
        assert (
            main(
                ["reproject", "--from", "mitsuba", "--input", str(d), "--out", str(out), "--mode", "stereo", "--quiet"]
            )
            == 0
        )
        assert capsys.readouterr().err == ""  # no convention warning on a correct sequence
        for i in range(2):
            res = read_exr(out / f"{i:04d}_left_reprojected.exr")
            src = read_exr(d / f"{i:04d}_left.exr")
            surface = src["dd.T"] > 0
            valid = res["valid"] > 0
            assert valid[surface].mean() >= 0.9, valid[surface].mean()
            rep = np.stack([res["R"], res["G"], res["B"]], -1)
            one = np.stack([src["R"], src["G"], src["B"]], -1)
            ref = refs[i]
            sel = valid & surface
            rmse_rep = float(np.sqrt(np.mean((rep[sel] - ref[sel]) ** 2)))
            rmse_one = float(np.sqrt(np.mean((one[sel] - ref[sel]) ** 2)))
            assert rmse_rep < rmse_one, (rmse_rep, rmse_one)

    def test_missing_aov_channels(self, tmp_path, capsys):
        d = tmp_path / "in"
        d.mkdir()
        left, right = _eye_cameras(0)
        for e, c in (("left", left), ("right", right)):
            scene = _scene(c, 1, False)
            mi.render(scene, spp=1)
            scene.sensors()[0].film().bitmap().write(str(d / f"0000_{e}.exr"))
        (d / "cameras.json").write_text(
            json.dumps(
                {
                    "frames": [
                        {
                            e: {"K": c.K[0].tolist(), "cam_from_world": c.cam_from_world[0].tolist()}
                            for e, c in (("left", left), ("right", right))
                        }
                    ]
                }
            )
        )
        assert (
            main(
                [
                    "reproject",
                    "--from",
                    "mitsuba",
                    "--input",
                    str(d),
                    "--out",
                    str(tmp_path / "o"),
                    "--position-threshold",
                    "0.03",
                    "--normal-threshold",
                    "0.25",
                    "--quiet",
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert "missing channel(s) dd.T" in err and "--from mitsuba" in err
