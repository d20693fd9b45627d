"""Blender (Cycles) frames in, against real Blender renders: ``stereorepro.io.blender.write_cameras`` run in Blender's
Python and ``stereorepro reproject --from blender`` on Blender's own multilayer EXRs.

Blender runs in its own environment (``make test`` creates ``.venv/blender`` with ``bpy``: bpy 5.0.1 needs
numpy < 2, this project's environment has numpy 2), as a subprocess, like a user's Blender; its Python loads
``stereorepro/io/blender.py`` by path (no torch there). Skipped where that environment is missing; set
``STEREOREPRO_BLENDER_PYTHON`` to another Python with bpy.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from stereorepro import camera_motion
from stereorepro.cli import main
from stereorepro.errors import SequenceError
from stereorepro.io.exr import read_exr
from stereorepro.io.frames import load_sequence, read_frame

ROOT = Path(__file__).resolve().parents[2]
W, H = 64, 36


def blender_python() -> str:
    env = os.environ.get("STEREOREPRO_BLENDER_PYTHON")
    cand = Path(env) if env else ROOT / ".venv" / "blender" / "bin" / "python"
    if not cand.is_file():
        pytest.skip(f"no Python with bpy at {cand} (make test creates it; or set STEREOREPRO_BLENDER_PYTHON)")
    return str(cand)


SCRIPT = (
    textwrap.dedent("""
    import importlib.util, sys
    import bpy
    out, mode, pivot, spp, frames = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
    spec = importlib.util.spec_from_file_location("stereorepro_blender", sys.argv[6])
    blender = importlib.util.module_from_spec(spec); spec.loader.exec_module(blender)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"; sc.cycles.device = "CPU"; sc.cycles.samples = spp
    sc.cycles.use_denoising = False; sc.cycles.seed = spp
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = {W}, {H}, 100
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0.5))
    bpy.ops.mesh.primitive_plane_add(size=8.0)
    bpy.ops.object.light_add(type="POINT", location=(1, -1, 3)); bpy.context.object.data.energy = 500
    bpy.ops.object.camera_add(location=(0.5, -4, 1.5), rotation=(1.3, 0, 0.1))
    cam = bpy.context.object; sc.camera = cam
    vl = sc.view_layers[0]
    vl.use_pass_z = vl.use_pass_normal = vl.use_pass_position = vl.use_pass_vector = True
    sc.render.use_multiview = True; sc.render.views_format = "STEREO_3D"
    st = cam.data.stereo
    st.interocular_distance = 0.065; st.convergence_mode = mode; st.pivot = pivot
    sc.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    sc.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    sc.render.image_settings.color_depth = "32"
    sc.render.filepath = out + "/"
    sc.frame_start, sc.frame_end = 1, frames
    cam.keyframe_insert("location", frame=1); cam.location.x += 0.1; cam.keyframe_insert("location", frame=frames)
    bpy.ops.render.render(animation=True)
    blender.write_cameras(out + "/cameras.json", position_threshold=0.05, normal_threshold=0.25)
""")
    .replace("{W}", str(W))
    .replace("{H}", str(H))
)


def render(tmp_path: Path, name: str, mode="PARALLEL", pivot="CENTER", spp=1, frames=2) -> Path:
    out = tmp_path / name
    script = tmp_path / "render.py"
    script.write_text(SCRIPT)
    r = subprocess.run(
        [
            blender_python(),
            str(script),
            str(out),
            mode,
            pivot,
            str(spp),
            str(frames),
            str(ROOT / "stereorepro" / "io" / "blender.py"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def rgb(ch: dict, prefix="ViewLayer.Combined.") -> np.ndarray:
    return np.stack([ch[prefix + c] for c in "RGB"], -1)


class TestBlenderCameras:
    @pytest.mark.parametrize("mode, pivot", [("PARALLEL", "LEFT"), ("OFFAXIS", "LEFT"), ("OFFAXIS", "CENTER")])
    def test_positions_project_to_pixel_centres(self, tmp_path, mode, pivot):
        """write_cameras' K and cam_from_world put Cycles' Position pass at our pixel centres, and Depth is their
        camera z, for both eyes (a wrong eye offset, sign or off-axis shift is off by pixels)."""
        d = render(tmp_path, "f", mode, pivot)
        seq = load_sequence(d, source="blender")
        assert seq.frame_numbers == (1, 2) and (seq.height, seq.width) == (H, W)
        for i in range(2):
            for eye in ("left", "right"):
                ch, f = read_exr(seq.path(i, eye)), read_frame(seq, i, eye)
                P = np.stack([ch[f"ViewLayer.Position.{c}"] for c in "XYZ"]).reshape(3, -1).astype(np.float64)
                hit = np.isfinite(f.depth[0, 0].numpy()).reshape(-1)
                assert 0.5 < hit.mean() < 1.0
                T, K = f.cam_from_world[0].numpy(), f.K[0].numpy()
                q = T[:3, :3] @ P + T[:3, 3:]
                uv = (K @ q)[:2] / q[2]
                ys, xs = np.mgrid[0:H, 0:W]
                assert np.abs(uv[0] - (xs.reshape(-1) + 0.5))[hit].max() < 0.05
                assert np.abs(uv[1] - (ys.reshape(-1) + 0.5))[hit].max() < 0.05
                np.testing.assert_allclose(q[2][hit], f.depth[0, 0].numpy().reshape(-1)[hit], rtol=1e-4)
                n = f.normal[0].norm(dim=0).numpy().reshape(-1)[hit]
                assert np.abs(n - 1).max() < 1e-3  # renormalised where Blender averaged
                if i == 1:  # the Vector pass, read as our motion, equals the cameras' motion of this static scene
                    prev = read_frame(seq, 0, eye)
                    cm = camera_motion(f.depth, f.K, f.cam_from_world, prev.K, prev.cam_from_world)
                    ok = torch.isfinite(cm).all(1, keepdim=True).expand_as(cm)
                    assert float(cm[ok].abs().max()) > 1.0  # it did move
                    assert float((f.motion[ok] - cm[ok].float()).abs().max()) < 0.05


class TestReprojectFromBlender:
    def test_stereo_sequence(self, tmp_path, capsys):
        """A Blender stereo sequence through `stereorepro reproject --from blender` with no hand conversion: the
        left eye reprojected from the right is valid on >= 90 % of its surface pixels and closer to Blender's own
        left reference than the left 1-spp render; the right reference warped into the left is close to the
        left reference, and far from it with the eyes' cameras exchanged (a mirrored rig)."""
        d = render(tmp_path, "one", spp=1)
        ref = render(tmp_path, "ref", spp=64)
        out = tmp_path / "out"
        assert (
            main(
                ["reproject", "--from", "blender", "--input", str(d), "--out", str(out), "--mode", "stereo", "--quiet"]
            )
            == 0
        )
        assert capsys.readouterr().err == ""
        for i, n in enumerate((1, 2)):
            res = read_exr(out / f"{i:04d}_left_reprojected.exr")
            src = read_exr(d / f"{n:04d}_L.exr")
            left_ref = rgb(read_exr(ref / f"{n:04d}_L.exr"))
            surface = src["ViewLayer.Depth.Z"] < 1e9
            valid = res["valid"] > 0
            assert valid[surface].mean() >= 0.9, valid[surface].mean()
            sel = valid & surface
            rep = np.stack([res[c] for c in "RGB"], -1)
            rmse_rep = float(np.sqrt(np.mean((rep[sel] - left_ref[sel]) ** 2)))
            rmse_one = float(np.sqrt(np.mean((rgb(src)[sel] - left_ref[sel]) ** 2)))
            assert rmse_rep < rmse_one, (rmse_rep, rmse_one)
        # noise-free: the right reference warped into the left, with the rig as written and mirrored
        assert (
            main(
                [
                    "reproject",
                    "--from",
                    "blender",
                    "--input",
                    str(ref),
                    "--out",
                    str(tmp_path / "ref_out"),
                    "--mode",
                    "stereo",
                    "--quiet",
                ]
            )
            == 0
        )
        mirrored = tmp_path / "mirrored"
        shutil.copytree(ref, mirrored)
        doc = json.loads((mirrored / "cameras.json").read_text())
        for fr in doc["frames"]:
            fr["left"], fr["right"] = fr["right"], fr["left"]
        (mirrored / "cameras.json").write_text(json.dumps(doc))
        assert (
            main(
                [
                    "reproject",
                    "--from",
                    "blender",
                    "--input",
                    str(mirrored),
                    "--out",
                    str(tmp_path / "mir_out"),
                    "--mode",
                    "stereo",
                    "--quiet",
                ]
            )
            == 0
        )
        assert "swapped" in capsys.readouterr().err  # the diagnosis names it
        left_ref = rgb(read_exr(ref / "0001_L.exr"))
        good = read_exr(tmp_path / "ref_out" / "0000_left_reprojected.exr")
        bad = read_exr(tmp_path / "mir_out" / "0000_left_reprojected.exr")
        surface = read_exr(ref / "0001_L.exr")["ViewLayer.Depth.Z"] < 1e9

        def err(r):
            return float(np.sqrt(np.mean((np.stack([r[c] for c in "RGB"], -1)[surface] - left_ref[surface]) ** 2)))

        assert err(good) < 0.5 * err(bad), (err(good), err(bad))


def blender_file(path, shift=(0, 0), prefix="ViewLayer.", normal_size=(H, W)):
    """A Blender-like multilayer EXR (one part per pass) of a plane at depth 2; the Normal part's data window
    shifted by ``shift`` (x, y) and of ``normal_size``."""
    import OpenEXR

    full = np.ones((H, W), np.float32)
    nh, nw = normal_size
    window = (np.array(shift, np.int32), np.array([shift[0] + nw - 1, shift[1] + nh - 1], np.int32))
    display = (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))
    parts = [
        OpenEXR.Part({"name": prefix + "Combined"}, {f"{prefix}Combined.{c}": full * 0.5 for c in "RGBA"}),
        OpenEXR.Part({"name": prefix + "Depth"}, {f"{prefix}Depth.Z": full * 2}),
        OpenEXR.Part(
            {"name": prefix + "Normal", "dataWindow": window, "displayWindow": display},
            {f"{prefix}Normal.{c}": np.full((nh, nw), v, np.float32) for c, v in zip("XYZ", (0, 0, 1))},
        ),
    ]
    OpenEXR.File(parts).write(str(path))


def blender_dir(d, numbers=(1, 2), **kw):
    d.mkdir()
    cam = {"K": [[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]], "cam_from_world": np.eye(4).tolist()}
    for n in numbers:
        for e in "LR":
            blender_file(d / f"{n:04d}_{e}.exr", **kw)
    (d / "cameras.json").write_text(
        json.dumps({"frames": [{"left": cam, "right": cam}] * len(numbers), "meta": {"frame_numbers": list(numbers)}})
    )
    return d


class TestBlenderFilesRefused:
    """Malformed Blender files and sequences, each refused with one error naming the file (no Blender needed)."""

    def test_smoke(self, tmp_path):
        seq = load_sequence(blender_dir(tmp_path / "in"), source="blender")
        f = read_frame(seq, 1, "right")
        assert f.color.shape == (1, 3, H, W) and float(f.depth.max()) == 2.0 and f.motion is None

    def test_shifted_normal_part(self, tmp_path):
        """A Normal part of the right size whose data window is shifted by (5, 3): its normals would not line up
        with colour and depth (it was accepted)."""
        d = blender_dir(tmp_path / "in", shift=(5, 3))
        with pytest.raises(SequenceError, match=r"0001_L\.exr.*part 'ViewLayer\.Normal' has data window"):
            load_sequence(d, source="blender")
        with pytest.raises(ValueError, match="share one data window"):
            read_exr(d / "0001_L.exr")

    def test_shifted_single_part(self, tmp_path):
        """A whole image shifted against the display window (all parts alike) does not line up with the camera."""
        import OpenEXR

        d = blender_dir(tmp_path / "in")

        ch = read_exr(d / "0001_L.exr")
        OpenEXR.File(
            {
                "dataWindow": (np.array([2, 1], np.int32), np.array([W + 1, H], np.int32)),
                "displayWindow": (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32)),
            },
            ch,
        ).write(str(d / "0001_L.exr"))
        with pytest.raises(SequenceError, match=r"0001_L\.exr: data window .* differs from the display window"):
            load_sequence(d, source="blender")

    def test_duplicated_frame_numbers(self, tmp_path):
        d = blender_dir(tmp_path / "in")
        doc = json.loads((d / "cameras.json").read_text())
        doc["meta"]["frame_numbers"] = [1, 1]
        (d / "cameras.json").write_text(json.dumps(doc))
        with pytest.raises(SequenceError, match=r"frame_numbers lists frame\(s\) \[1\] more than once"):
            load_sequence(d, source="blender")

    def test_unlisted_frame_files(self, tmp_path):
        d = blender_dir(tmp_path / "in", numbers=(1, 2))
        blender_file(d / "0007_L.exr")
        doc = json.loads((d / "cameras.json").read_text())
        with pytest.raises(SequenceError, match=r"frame files not in its meta\.frame_numbers: 0007_L\.exr"):
            load_sequence(d, source="blender")
        (d / "0007_L.exr").unlink()
        doc["frames"], doc["meta"]["frame_numbers"] = doc["frames"][:1], [2]  # 0001_* now unlisted
        (d / "cameras.json").write_text(json.dumps(doc))
        with pytest.raises(SequenceError, match=r"0001_L\.exr, 0001_R\.exr"):
            load_sequence(d, source="blender")

    def test_no_view_layer_prefix(self, tmp_path):
        """Channels named Combined.R (no view layer): a message saying so (it said "missing Combined.R ... found:
        Combined.R")."""
        d = blender_dir(tmp_path / "in", prefix="")
        with pytest.raises(SequenceError, match=r"0001_L\.exr: channels without a view-layer prefix") as e:
            load_sequence(d, source="blender")
        assert "missing" not in str(e.value)

    def test_frame_from_channels_shapes(self, tmp_path):
        """A channel of another shape through the Python API: one SequenceError naming it (numpy's 'all input
        arrays must have the same shape' before)."""
        from stereorepro.io.blender import frame_from_channels

        blender_file(tmp_path / "f.exr")
        ch = read_exr(tmp_path / "f.exr")
        ch["ViewLayer.Normal.Y"] = ch["ViewLayer.Normal.Y"][:, :-1]
        with pytest.raises(SequenceError, match=rf"where: channel ViewLayer\.Normal\.Y is {W - 1}x{H}"):
            frame_from_channels(ch, "where")
        ch = read_exr(tmp_path / "f.exr")
        ch["ViewLayer.Vector.X"], ch["ViewLayer.Vector.Y"] = np.zeros((H, W), np.float32), np.zeros(3, np.float32)
        with pytest.raises(SequenceError, match=r"channel ViewLayer\.Vector\.Y has shape \(3,\)"):
            frame_from_channels(ch, "where")
