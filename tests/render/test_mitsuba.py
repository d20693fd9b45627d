"""Cross-check of the path tracer against Mitsuba 3 (``scalar_rgb``) on one asymmetric diffuse scene.

Skipped when ``mitsuba`` is not importable (it is not a dependency; ``pip install mitsuba``). Only the
``scalar_rgb`` variant is used: the llvm variants abort the process on this machine.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stereorepro.render import PathTracer
from stereorepro.scenes import load_scene

from conftest_render import camera_looking, write_scene

mi = pytest.importorskip("mitsuba")

W, H = 48, 36
VFOV = 50.0
EYE, TARGET, UP = (0.6, 1.5, -4.2), (-0.2, 0.9, 0.6), (0.0, 1.0, 0.0)
RUNS, SPP = 8, 32  # independent runs x spp each, per renderer
BLOCKS = 4  # BLOCKS x BLOCKS image regions

# Albedo per material. The light quad is level with the tops of the walls, so nothing lies above it and our two-sided
# emitter's back face lights nothing (Mitsuba's is one-sided); its winding gives Mitsuba a downward normal.
MATERIALS = {"floor": (0.7, 0.7, 0.7), "back": (0.6, 0.6, 0.55), "left": (0.7, 0.12, 0.1), "block": (0.2, 0.5, 0.7)}
EMISSION = (9.0, 8.0, 6.5)


def _scene_file(tmp_path):
    mats = "\n".join(f"[materials.{k}]\nalbedo = {list(v)}" for k, v in MATERIALS.items())
    return write_scene(
        tmp_path,
        f"""
        effects = []
        num_frames = 1
        [geometry]
        quads = [
          {{corner = [-2.0, 0.0, -2.0], edge_u = [0.0, 0.0, 4.0], edge_v = [4.0, 0.0, 0.0], material = "floor"}},
          {{corner = [-2.0, 0.0, 2.0], edge_u = [4.0, 0.0, 0.0], edge_v = [0.0, 2.6, 0.0], material = "back"}},
          {{corner = [-2.0, 0.0, -2.0], edge_u = [0.0, 2.6, 0.0], edge_v = [0.0, 0.0, 4.0], material = "left"}},
          {{corner = [-1.3, 2.6, -0.4], edge_u = [1.1, 0.0, 0.0], edge_v = [0.0, 0.0, 1.2], material = "light"}},
        ]
        boxes = [{{min = [0.2, 0.0, 0.1], max = [1.1, 1.3, 1.0], material = "block"}}]
        {mats}
        [materials.light]
        albedo = [0.0, 0.0, 0.0]
        emission = {list(EMISSION)}
        """,
        "mitsuba_xcheck",
    )


def _mitsuba_scene(scene, tmp_path):
    """The same triangles as OBJ files (one per material), two-sided diffuse BSDFs, one area emitter."""
    geo = scene.geometry()
    names = scene.material_table()["names"]
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3, "hide_emitters": False},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": VFOV,
            "to_world": mi.ScalarTransform4f().look_at(origin=list(EYE), target=list(TARGET), up=list(UP)),
            "sampler": {"type": "independent", "sample_count": SPP},
            "film": {"type": "hdrfilm", "width": W, "height": H, "pixel_format": "rgb", "rfilter": {"type": "box"}},
        },
    }
    for m, name in enumerate(names):
        faces = geo.faces[geo.material_ids == m]
        if len(faces) == 0:
            continue
        path = tmp_path / f"{name}.obj"
        with open(path, "w") as f:
            for v in geo.vertices:
                f.write(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n")
            for t in faces:
                f.write(f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}\n")
        shape = {"type": "obj", "filename": str(path), "face_normals": True}
        if name == "light":
            shape["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": list(EMISSION)}}
        else:
            shape["bsdf"] = {
                "type": "twosided",
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(MATERIALS[name])}},
            }
        d[name] = shape
    return mi.load_dict(d)


def _blocks(img):
    """(R, H, W) images -> (R, BLOCKS * BLOCKS) means over all channels of each block."""
    r = img.shape[0]
    return img.reshape(r, BLOCKS, H // BLOCKS, BLOCKS, W // BLOCKS).mean(axis=(2, 4)).reshape(r, -1)


def test_matches_mitsuba_path_depth3(tmp_path):
    """Image mean and 4 x 4 block means agree with Mitsuba's ``path`` integrator (``max_depth = 3``).

    Statistics: 48 x 36 pixels; each renderer makes RUNS = 8 independent runs of SPP = 32 (Mitsuba: seeds 0-7;
    ours: disjoint ``sample_offset`` streams), 256 spp in all. The standard error of a block mean (12 x 9 pixels)
    is estimated from the spread of the 8 runs (std / sqrt(8), 7 degrees of freedom); the difference of the two
    renderers' means is compared with sigma = sqrt(se_ours^2 + se_mitsuba^2). Measured (seeds fixed, so the test is
    deterministic): block sigmas 0.23-4.6 % of the block means (the two top blocks hold the light's edge, partly
    covered pixels of radiance 9), largest |diff| / sigma 2.4 over the 16 blocks; image mean 0.2187 vs 0.2190,
    -0.16 % (0.5 sigma). The test asserts |diff| < 5 sigma for every block and for the image mean, and a relative
    image-mean difference below 2 %. Run time about 2 s. Expectations agree although the estimators differ (Mitsuba adds
    MIS-weighted NEE and BSDF-sampled emission at x2, we use unweighted NEE there). A left-right flip of Mitsuba's
    image must fail the block test by far (the scene is asymmetric: red wall, light and block on different sides;
    measured max z of the flipped comparison about 1900).
    """
    mi.set_variant("scalar_rgb")
    scene = load_scene(_scene_file(tmp_path))
    tr = PathTracer(scene, seed=11, clamp=None)
    cam = camera_looking(EYE, TARGET, UP, width=W, height=H, vfov=VFOV)
    ours = np.stack(
        [tr.render(cam, 0, SPP, sample_offset=k * SPP, gbuffers=False).radiance[0].mean(0).numpy() for k in range(RUNS)]
    ).astype(np.float64)  # (RUNS, H, W), channel mean
    msc = _mitsuba_scene(scene, tmp_path)
    theirs = np.stack([np.asarray(mi.render(msc, seed=k), np.float64).mean(-1) for k in range(RUNS)])

    def stats(a, b):
        ba, bb = _blocks(a), _blocks(b)
        diff = ba.mean(0) - bb.mean(0)
        sigma = np.sqrt(ba.var(0, ddof=1) / RUNS + bb.var(0, ddof=1) / RUNS)
        return diff, sigma, bb.mean(0)

    diff, sigma, ref = stats(ours, theirs)
    z = np.abs(diff) / sigma
    assert (z < 5).all(), (z.round(2), (diff / ref).round(4))
    img_o, img_m = ours.mean(axis=(1, 2)), theirs.mean(axis=(1, 2))
    d_img = img_o.mean() - img_m.mean()
    s_img = math.sqrt(img_o.var(ddof=1) / RUNS + img_m.var(ddof=1) / RUNS)
    assert abs(d_img) < 5 * s_img, (d_img, s_img)
    assert abs(d_img) / img_m.mean() < 0.02
    # sensitivity: the mirrored image does not match
    zf = np.abs(stats(ours, theirs[:, :, ::-1])[0]) / sigma
    assert zf.max() > 20, zf.max()
    # and the image is not trivially dark
    assert img_m.mean() > 0.05 and torch.isfinite(torch.from_numpy(ours)).all()
