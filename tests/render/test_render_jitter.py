"""Sub-pixel jitter in the tracer: ``PathTracer.render(pixel_sampling=...)`` with jittered cameras.

* ``pixel_sampling="box"`` (the default) is the tracer of previous versions, bit for bit: checksums recorded before
  the option existed, and the primary rays written out as the previous generate stage formed them;
* ``"center"``: every sample's primary ray is the G-buffer's ray (the same bytes handed to embree), so its first
  hit is the G-buffer's surface (an emission-only scene's radiance is exactly the emission of the G-buffer's
  material, silhouettes included); bit-identical across backends;
* a jittered camera's G-buffer follows :func:`stereorepro.camera.jitter_intrinsics`'s sign convention.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from stereorepro.camera import jitter_offset
from stereorepro.render import PathTracer
from stereorepro.render.rng import DIM, path_keys, stream_key, uniform
from stereorepro.render.tracer import ENV_VAR, PIXEL_SAMPLINGS, native_available
from stereorepro.scenes import load_scene

from conftest_render import camera_looking, write_scene

W, H = 24, 14
BACKENDS = [
    "numpy",
    pytest.param(
        "native",
        marks=pytest.mark.skipif(not native_available(), reason="stereorepro._core without the tracer kernels"),
    ),
]


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


@pytest.fixture(scope="module")
def scenes():
    return {name: load_scene(name) for name in ("living_room", "atrium_glossy", "living_room_glossy")}


class _Recorder:
    """Wraps a TriangleBVH and keeps copies of every closest-hit query (origins, directions)."""

    def __init__(self, bvh):
        self.bvh, self.calls = bvh, []

    def intersect(self, o, d):
        self.calls.append((np.array(o, np.float32), np.array(d, np.float32)))
        return self.bvh.intersect(o, d)

    def occluded(self, o, d, tmax):
        return self.bvh.occluded(o, d, tmax)


def _recorded(tr, *args, **kwargs):
    rec = _Recorder(tr._bvh)
    tr._bvh = rec
    try:
        r = tr.render(*args, **kwargs)
    finally:
        tr._bvh = rec.bvh
    return r, rec.calls


def _bits(x):
    return np.ascontiguousarray(x).view(np.uint32)


def _sha(t: torch.Tensor) -> str:
    return hashlib.sha256(np.ascontiguousarray(t.numpy()).tobytes()).hexdigest()[:16]


# (scene, config) -> (radiance, depth) sha256 prefixes, recorded with the tracer before `pixel_sampling` existed
# (commit 7b064f5; the same on both backends): W x H = 24 x 14, seed 3, workers 2, stereo_cameras(1, W, H), frame 1.
_RECORDED = {
    ("living_room", "spp1"): ("a049cb165895606c", "4239d4874b2faf7c"),
    ("living_room", "spp3_off5_eye1"): ("70ff07d15c421147", "48c1589c3265826e"),
    ("living_room", "mask_spp2"): ("8d412bc21a9eb9a3", "559268dfcfb86bd7"),
    ("atrium_glossy", "spp1"): ("4d7448c79e1214e2", "f2b65a3f0b076842"),
    ("atrium_glossy", "spp3_off5_eye1"): ("e9628b50b877b23c", "c277c7cb99f0dec4"),
    ("atrium_glossy", "mask_spp2"): ("4228b548ab744477", "8e22e81874d3a581"),
}


def _recorded_configs(tr, scene, **extra):
    left, right = scene.stereo_cameras(1, W, H)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[2:11, 3:19] = True
    mask[0, 0] = True
    return {
        "spp1": tr.render(left, 1, 1, **extra),
        "spp3_off5_eye1": tr.render(right, 1, 3, sample_offset=5, eye=1, **extra),
        "mask_spp2": tr.render(left, 1, 2, pixel_mask=mask, **extra),
    }


def emissive_scene(tmp_path):
    """Emitters only (albedo 0): a pixel sample's radiance is the emission of its first hit, nothing else."""
    return load_scene(
        write_scene(
            tmp_path,
            """
        effects = []
        num_frames = 1
        [geometry]
        quads = [{corner = [-1.5, -1.0, 2.0], edge_u = [3.0, 0.0, 0.0], edge_v = [0.0, 2.0, 0.0], material = "back"}]
        boxes = [{min = [-0.45, -0.35, 0.0], max = [0.35, 0.45, 0.8], material = "block"}]
        [materials.back]
        albedo = [0.0, 0.0, 0.0]
        emission = [1.0, 0.5, 0.25]
        [materials.block]
        albedo = [0.0, 0.0, 0.0]
        emission = [3.0, 2.0, 4.0]
        """,
            "emitters",
        )
    )


class TestDefaultUnchanged:
    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("name", ["living_room", "atrium_glossy"])
    def test_checksums_recorded_before_the_option(self, scenes, name, backend):
        scene = scenes[name]
        tr = PathTracer(scene, seed=3, workers=2, backend=backend)
        got = _recorded_configs(tr, scene)
        if any(_sha(r.depth) != _RECORDED[(name, k)][1] for k, r in got.items()):
            # the G-buffer's code path is not the subject here: a different depth means embree on this machine
            # rounds hits otherwise (another ISA), so the recorded radiance cannot be compared either;
            # test_box_rays_are_the_previous_formula checks the default without recorded values
            pytest.skip("embree here gives other G-buffer depths than where the checksums were recorded")
        for k, r in got.items():
            assert _sha(r.radiance) == _RECORDED[(name, k)][0], (name, k)
        explicit = _recorded_configs(tr, scene, pixel_sampling="box")
        for k in got:
            assert torch.equal(explicit[k].radiance, got[k].radiance), k

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_box_rays_are_the_previous_formula(self, scenes, backend):
        """The default's primary rays, bit for bit, as the previous generate stage wrote them (written out here)."""
        scene = scenes["living_room"]
        tr = PathTracer(scene, seed=3, workers=1, backend=backend)
        cam = scene.stereo_cameras(1, W, H)[1]
        spp, offset, eye = 2, 4, 1
        _, calls = _recorded(tr, cam, 1, spp, sample_offset=offset, eye=eye, gbuffers=False)
        o, d = calls[0]  # one worker, one batch: the primary query comes first
        pix = np.tile(np.arange(H * W, dtype=np.int64), spp)
        samp = np.repeat(np.arange(spp, dtype=np.int64) + offset, H * W)
        keys = path_keys(stream_key(3, 1, eye), pix, samp)
        px = (pix % W).astype(np.float32) + uniform(keys, DIM["jitter_x"])
        py = (pix // W).astype(np.float32) + uniform(keys, DIM["jitter_y"])
        K = cam.K[0].double().numpy()
        wfc = cam.world_from_cam[0].double().numpy()
        M = (wfc[:3, :3] @ np.linalg.inv(K)).astype(np.float32)
        v = np.stack([M[r, 0] * px + M[r, 1] * py + M[r, 2] for r in range(3)], 1)
        n = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
        want = v / np.where(n > 0, n, np.float32(1))[:, None]
        assert d.shape == want.shape and np.array_equal(_bits(d), _bits(want))
        assert np.array_equal(_bits(o), _bits(np.broadcast_to(wfc[:3, 3].astype(np.float32), o.shape)))


class TestCenterSampling:
    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("jitter", [None, (0.3125, -0.4)])
    def test_primary_rays_are_the_gbuffer_rays(self, scenes, backend, jitter):
        scene = scenes["living_room"]
        tr = PathTracer(scene, seed=3, workers=1, backend=backend)
        cam = scene.stereo_cameras(1, W, H)[0]
        cam = cam if jitter is None else cam.jittered(*jitter)
        spp = 3
        _, calls = _recorded(tr, cam, 1, spp, pixel_sampling="center")
        o_p, d_p = calls[0]  # primary (one worker, one batch), ..., the G-buffer's query last
        o_g, d_g = calls[-1]
        assert len(o_g) == H * W and len(o_p) == spp * H * W
        for s in range(spp):
            sl = slice(s * H * W, (s + 1) * H * W)
            assert np.array_equal(_bits(d_p[sl]), _bits(d_g)) and np.array_equal(_bits(o_p[sl]), _bits(o_g))

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_emitters_only_first_hit_is_the_gbuffer_surface(self, tmp_path, backend):
        """Radiance = emission of the G-buffer's material, exactly, at every pixel (silhouettes and misses too)."""
        scene = emissive_scene(tmp_path)
        tr = PathTracer(scene, seed=1, backend=backend)
        emission = torch.from_numpy(tr.emission)
        cam = camera_looking((0.1, 0.05, -3.0), (0.0, 0.0, 0.0), width=40, height=30)
        for dx, dy in [(0.0, 0.0), jitter_offset(3), (-0.49, 0.49)]:
            jc = cam.jittered(dx, dy)
            for spp in (1, 3):
                r = tr.render(jc, 0, spp, pixel_sampling="center")
                mat = r.material_id[0, 0].long()
                want = torch.where(mat >= 0, emission[mat.clamp(min=0)].permute(2, 0, 1), torch.zeros(())).unsqueeze(0)
                assert torch.equal(r.radiance, want), (dx, dy, spp)
                assert (mat == -1).any() and len(torch.unique(mat)) == 3  # misses, back wall and block
        # box sampling averages across the silhouettes: the check above is not vacuous
        r = tr.render(cam, 0, 8)
        mat = r.material_id[0, 0].long()
        want = torch.where(mat >= 0, emission[mat.clamp(min=0)].permute(2, 0, 1), torch.zeros(()))
        assert not torch.equal(r.radiance[0], want)

    def test_backends_bit_identical(self, scenes):
        if not native_available():
            pytest.skip("stereorepro._core without the tracer kernels")
        scene = scenes["living_room_glossy"]
        cam = scene.stereo_cameras(2, W, H)[1].jittered(*jitter_offset(2))
        mask = torch.rand(H, W, generator=torch.Generator().manual_seed(2)) < 0.3
        out = {}
        for backend in ("numpy", "native"):
            tr = PathTracer(scene, seed=5, backend=backend, workers=2, max_batch=100)
            out[backend] = (
                tr.render(cam, 2, 3, sample_offset=2, eye=1, pixel_sampling="center"),
                tr.render(cam, 2, 2, pixel_mask=mask, pixel_sampling="center"),
            )
        for a, b in zip(out["numpy"], out["native"]):
            assert torch.equal(a.radiance, b.radiance) and a.ray_counts == b.ray_counts
            assert torch.equal(a.depth, b.depth)
        assert (out["native"][1].radiance[0, :, ~mask] == 0).all()
        assert out["native"][0].radiance.mean() > 0

    def test_samples_differ_only_after_the_first_hit(self, scenes):
        """Deterministic, independent of workers and batches, nested prefixes; not the box image."""
        scene = scenes["living_room"]
        cam = scene.stereo_cameras(0, W, H)[0]
        base = PathTracer(scene, seed=2, workers=1).render(cam, 0, 4, pixel_sampling="center")
        for workers, max_batch in [(2, 1 << 15), (2, 50)]:
            r = PathTracer(scene, seed=2, workers=workers, max_batch=max_batch).render(
                cam, 0, 4, pixel_sampling="center"
            )
            assert torch.equal(r.radiance, base.radiance), (workers, max_batch)
        box = PathTracer(scene, seed=2, workers=1).render(cam, 0, 4)
        assert not torch.equal(box.radiance, base.radiance)
        assert torch.equal(box.depth, base.depth)  # the G-buffer does not depend on the option

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_jittered_camera_gbuffer_sign(self, tmp_path, backend):
        """The jittered camera's pixel centre sees the unjittered image at centre + (dx, dy)."""
        quad = '{corner = [-20.0, -20.0, 3.0], edge_u = [40.0, 0.0, 0.0], edge_v = [0.0, 40.0, 0.0], material = "m"}'
        scene = load_scene(
            write_scene(
                tmp_path,
                """
            effects = []
            num_frames = 1
            [geometry]
            quads = [QUAD]
            [materials.m]
            albedo = [0.5, 0.5, 0.5]
            """.replace("QUAD", quad),
                "wall",
            )
        )
        cam = camera_looking((0.2, 0.1, -1.0), (0.5, 0.3, 3.0), width=20, height=12)
        dx, dy = 0.3125, -0.4
        g = PathTracer(scene, backend=backend).gbuffer(cam.jittered(dx, dy), 0)
        assert torch.isfinite(g.depth).all()
        uv, _ = cam.project(g.position.double())
        centres = torch.stack(torch.meshgrid(torch.arange(12.0), torch.arange(20.0), indexing="ij")[::-1]) + 0.5
        err = uv[0] - (centres.double() + torch.tensor([dx, dy], dtype=torch.float64).view(2, 1, 1))
        assert err.abs().max() < 2e-3, float(err.abs().max())  # float32 positions; a wrong sign errs by 0.6+ px

    def test_exceptions(self, scenes):
        scene = scenes["living_room"]
        tr = PathTracer(scene, seed=0)
        cam = scene.stereo_cameras(0, 8, 6)[0]
        for bad in ("centre", "Center", "", None, 1, ("center",)):
            with pytest.raises(ValueError, match=r"pixel_sampling must be one of \('box', 'center'\)"):
                tr.render(cam, 0, 1, pixel_sampling=bad)
        assert PIXEL_SAMPLINGS == ("box", "center")
        for bad in (float("nan"), float("inf"), -float("inf")):
            with pytest.raises(ValueError, match="dx .*finite"):
                cam.jittered(bad, 0.0)
            with pytest.raises(ValueError, match="dy .*finite"):
                cam.jittered(0.0, bad)
