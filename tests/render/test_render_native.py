"""Native tracer stages (``stereorepro._core``, cpp_ext/src/shade_tracer.cpp) against the numpy reference.

The claim is bit-identity: the same uint32/uint64 random numbers, the same rays handed to embreex at every query
(primary, bounce, shadow: origins, directions, tmax), the same ray counts, G-buffers and radiance (``torch.equal``)
for every built-in scene, with and without the firefly clamp and a pixel mask. Backend selection
(``PathTracer(backend=...)``, ``STEREOREPRO_BACKEND``) is tested at the end.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereorepro.render import PathTracer
from stereorepro.render import tracer as tracer_mod
from stereorepro.render.rng import DIM, path_keys, stream_key, uniform
from stereorepro.render.tracer import ENV_VAR, native_available, resolve_backend
from stereorepro.scenes import list_scenes, load_scene

pytestmark = pytest.mark.skipif(not native_available(), reason="stereorepro._core without the tracer kernels")
_core = tracer_mod._core

W, H = 40, 24


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


@pytest.fixture(scope="module")
def tracers():
    """(scene, numpy tracer, native tracer) per built-in scene, built once."""
    out = {}
    for name in list_scenes():
        scene = load_scene(name)
        with pytest.MonkeyPatch.context() as mp:
            mp.delenv(ENV_VAR, raising=False)
            out[name] = (scene, PathTracer(scene, seed=7, backend="numpy"), PathTracer(scene, seed=7, backend="native"))
    return out


class _Recorder:
    """Wraps a TriangleBVH and keeps copies of every query."""

    def __init__(self, bvh):
        self.bvh, self.calls = bvh, []

    def intersect(self, o, d):
        self.calls.append(("intersect", np.array(o, np.float32), np.array(d, np.float32), None))
        return self.bvh.intersect(o, d)

    def occluded(self, o, d, tmax):
        self.calls.append(("occluded", np.array(o, np.float32), np.array(d, np.float32), np.array(tmax, np.float32)))
        return self.bvh.occluded(o, d, tmax)


def _bits(x):
    return np.ascontiguousarray(x).view(np.uint32)


class TestRng:
    def test_path_keys_equal(self):
        rng = np.random.default_rng(0)
        pix = rng.integers(0, 1 << 40, 200_000, dtype=np.int64)
        samp = rng.integers(0, 1 << 40, 200_000, dtype=np.int64)
        pix[:4] = [0, 1, (1 << 62), 7]
        samp[:4] = [0, (1 << 62), 0, 123456789]
        for seed, frame, eye in [(0, 0, 0), (3, 59, 1), (2**63 + 5, 12345, 7)]:
            key = stream_key(seed, frame, eye)
            out = np.empty(len(pix), np.uint64)
            _core.rng_path_keys(key, pix, samp, out)
            assert np.array_equal(out, path_keys(key, pix, samp))

    def test_uniform_equal(self):
        keys = np.random.default_rng(1).integers(0, 2**64 - 1, 300_000, dtype=np.uint64, endpoint=True)
        keys[:3] = [0, 2**64 - 1, 0x9E3779B97F4A7C15]
        out = np.empty(len(keys), np.float32)
        for dim in list(DIM.values()) + [11, 1000, 2**63]:
            _core.rng_uniform(keys, dim, out)
            ref = uniform(keys, dim)
            assert np.array_equal(_bits(out), _bits(ref)), dim
            assert out.min() >= 0 and out.max() < 1

    def test_noconvert_outputs(self):
        keys = np.zeros(4, np.uint64)
        with pytest.raises(TypeError):
            _core.rng_uniform(keys, 0, np.empty(4, np.float64))  # a converted copy would lose the result
        with pytest.raises(TypeError):
            _core.rng_uniform(keys, 0, np.empty(8, np.float32)[::2])


def _surface_batch(tr, scene, n=4000, seed=0):
    """Shading points (P, n, wo, mat, keys) on real surfaces: the G-buffer of a camera, random path keys."""
    cam = scene.stereo_cameras(0, 80, 50)[0]
    g = tr.gbuffer(cam, 0)
    hit = torch.isfinite(g.depth).reshape(-1).numpy()
    P = g.position[0].reshape(3, -1).T.numpy()[hit]
    nrm = g.normal[0].reshape(3, -1).T.numpy()[hit]
    mat = g.material_id.reshape(-1).numpy()[hit].astype(np.int32)
    c = tr.scene.stereo_cameras(0, 80, 50)[0].world_from_cam[0, :3, 3].numpy().astype(np.float32)
    wo = c - P
    wo = (wo / np.linalg.norm(wo, axis=1, keepdims=True)).astype(np.float32)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(P), n)
    keys = path_keys(stream_key(seed, 0, 0), rng.integers(0, 1 << 20, n), rng.integers(0, 64, n))
    c = np.ascontiguousarray
    return c(P[idx], np.float32), c(nrm[idx], np.float32), c(wo[idx]), c(mat[idx]), keys


class TestStages:
    @pytest.mark.parametrize("name", ["living_room_glossy", "atrium_glossy", "atrium_moving_light", "classroom"])
    def test_bsdf_sample_and_nee(self, tracers, name):
        scene, ref, nat = tracers[name]
        P, n, wo, mat, keys = _surface_batch(ref, scene)
        N = len(mat)
        wi, wt, pdf = ref._bsdf_sample(mat, n, wo, keys)
        out = [np.empty((N, 3), np.float32), np.empty((N, 3), np.float32), np.empty(N, np.float32)]
        fr, _, _, _ = nat._setup(scene.stereo_cameras(0, 8, 8)[0], 0, None, 0)
        fr.shader.bsdf_sample(mat, n, wo, keys, *out)
        for a, b in zip((wi, wt, pdf), out):
            assert np.array_equal(_bits(a), _bits(b))
        fr_ref, _, _, _ = ref._setup(scene.stereo_cameras(0, 8, 8)[0], 0, None, 0)
        for second, mis in [(0, True), (1, False), (0, False)]:
            dims = (
                (DIM["light2"], DIM["light2_u"], DIM["light2_v"])
                if second
                else (DIM["light1"], DIM["light1_u"], DIM["light1_v"])
            )
            ok, o, d, tmax, val = ref._nee(fr_ref, P, n, wo, mat, keys, dims, mis)
            res = [
                np.empty(N, bool),
                np.empty((N, 3), np.float32),
                np.empty((N, 3), np.float32),
                np.empty(N, np.float32),
                np.empty((N, 3), np.float32),
            ]
            fr.shader.nee(P, n, wo, mat, keys, second, mis, *res)
            assert np.array_equal(ok, res[0])
            assert ok.mean() > 0.2
            for a, b in zip((o, d, tmax, val), res[1:]):
                assert np.array_equal(_bits(a), _bits(b)), (second, mis)

    @pytest.mark.parametrize("name", ["living_room", "atrium_glossy", "living_room_moving_light"])
    def test_every_embree_query_identical(self, tracers, name):
        """Per stage: the rays after generate (primary), shade1 (bounce), shade1 + shade2 (shadow) are identical."""
        scene = tracers[name][0]
        ref, nat = (PathTracer(scene, seed=7, backend=be, workers=1) for be in ("numpy", "native"))
        frame = 1 % scene.num_frames
        cam = scene.stereo_cameras(frame, W, H)[0]
        calls = []
        for tr in (ref, nat):
            rec = _Recorder(tr._bvh)
            tr._bvh = rec
            try:
                tr.render(cam, frame, 2, gbuffers=False)
            finally:
                tr._bvh = rec.bvh
            calls.append(rec.calls)
        assert [c[0] for c in calls[0]] == [c[0] for c in calls[1]]
        assert len(calls[0]) == 3  # one worker, one batch: primary, bounce, shadow (2 spp fit into one batch)
        for a, b in zip(*calls):
            for x, y in zip(a[1:], b[1:]):
                if x is not None:
                    assert x.shape == y.shape and np.array_equal(_bits(x), _bits(y))


class TestStageSequence:
    @pytest.mark.parametrize("backend", ["numpy", "native"])
    def test_one_sequence_of_named_stages(self, tracers, backend):
        """Both backends run tracer.STAGES, each once per batch, in that order (one worker, one batch), and the
        stage profile names exactly those stages (plus the frame's accumulation)."""
        scene = tracers["living_room"][0]
        tr = PathTracer(scene, seed=7, backend=backend, workers=1)
        cam = scene.stereo_cameras(0, W, H)[0]
        calls = []
        for name in tracer_mod.STAGES:
            real = getattr(tr._stages, name)
            setattr(tr._stages, name, lambda b, _real=real, _name=name: calls.append(_name) or _real(b))
        tr._stage_times = {}
        r = tr.render(cam, 0, 2, gbuffers=False)
        assert calls == list(tracer_mod.STAGES)
        assert set(tr._stage_times) == set(tracer_mod.STAGES) | {"accumulate_frame"}
        assert r.ray_counts["primary"] == 2 * W * H and r.ray_counts["shadow"] > 0


class TestFrames:
    @pytest.mark.parametrize("clamp", ["auto", None])
    def test_whole_frame_bit_identical(self, tracers, clamp):
        for name, (scene, ref, nat) in tracers.items():
            a = PathTracer(scene, seed=7, backend="numpy", clamp=clamp) if clamp is None else ref
            b = PathTracer(scene, seed=7, backend="native", clamp=clamp) if clamp is None else nat
            for frame in sorted({0, scene.num_frames - 1}):
                cam = scene.stereo_cameras(frame, W, H)[1]
                ra = a.render(cam, frame, 2, sample_offset=5, eye=1)
                rb = b.render(cam, frame, 2, sample_offset=5, eye=1)
                assert torch.equal(ra.radiance, rb.radiance), (name, frame, clamp)
                assert ra.ray_counts == rb.ray_counts, name
                for g in ("depth", "normal", "position", "albedo", "material_id"):
                    assert torch.equal(getattr(ra, g), getattr(rb, g)), (name, g)
                assert ra.radiance.mean() > 0

    def test_clamp_changes_something_and_stays_identical(self, tracers):
        scene, _, _ = tracers["atrium"]
        cam = scene.stereo_cameras(0, W, H)[0]
        r = {
            be: PathTracer(scene, seed=7, backend=be, clamp=0.05).render(cam, 0, 2, gbuffers=False).radiance
            for be in ("numpy", "native")
        }
        free = PathTracer(scene, seed=7, backend="native", clamp=None).render(cam, 0, 2, gbuffers=False).radiance
        assert torch.equal(r["numpy"], r["native"])
        assert not torch.equal(r["native"], free)

    def test_pixel_mask(self, tracers):
        scene, ref, nat = tracers["living_room_glossy"]
        cam = scene.stereo_cameras(2, W, H)[0]
        mask = torch.rand(H, W, generator=torch.Generator().manual_seed(1)) < 0.1
        ra, rb = ref.render(cam, 2, 3, pixel_mask=mask), nat.render(cam, 2, 3, pixel_mask=mask)
        assert torch.equal(ra.radiance, rb.radiance) and ra.ray_counts == rb.ray_counts
        assert (rb.radiance[0, :, ~mask] == 0).all()
        ga, gb = ref.gbuffer(cam, 2, pixel_mask=mask), nat.gbuffer(cam, 2, pixel_mask=mask)
        for g in ("depth", "normal", "position", "albedo", "material_id"):
            assert torch.equal(getattr(ra, g), getattr(rb, g)), g
            assert torch.equal(getattr(ga, g), getattr(gb, g)), g
            assert getattr(gb, g).is_contiguous()
        assert torch.isinf(gb.depth[0, 0, ~mask]).all() and (gb.material_id[0, 0, ~mask] == -1).all()
        empty = nat.render(cam, 2, 1, pixel_mask=torch.zeros(H, W, dtype=torch.bool))
        assert empty.ray_counts["primary"] == 0 and (empty.radiance == 0).all()

    def test_determinism_across_workers_and_batches(self, tracers):
        scene, ref, _ = tracers["classroom"]
        cam = scene.stereo_cameras(0, W, H)[0]
        base = ref.render(cam, 0, 3, gbuffers=False).radiance
        for workers, max_batch in [(1, 1 << 16), (2, 1 << 16), (2, 97), (3, 1000)]:
            r = PathTracer(scene, seed=7, backend="native", workers=workers, max_batch=max_batch)
            assert torch.equal(r.render(cam, 0, 3, gbuffers=False).radiance, base), (workers, max_batch)

    def test_no_lights_and_misses(self, tmp_path):
        """A scene without emitters or point lights: no shadow rays, zero radiance, both backends."""
        from conftest_render import write_scene

        p = write_scene(
            tmp_path,
            """
            effects = []
            num_frames = 1
            [geometry]
            boxes = [{min = [-1.0, -1.0, 2.0], max = [1.0, 1.0, 3.0], material = "wall"}]
            [materials.wall]
            albedo = [0.5, 0.5, 0.5]
            """,
        )
        scene = load_scene(p)
        cam = scene.stereo_cameras(0, 16, 12)[0]
        ra = PathTracer(scene, backend="numpy").render(cam, 0, 2)
        rb = PathTracer(scene, backend="native").render(cam, 0, 2)
        assert torch.equal(ra.radiance, rb.radiance) and ra.ray_counts == rb.ray_counts
        assert rb.ray_counts["shadow"] == 0 and (rb.radiance == 0).all()


class TestBackendSelection:
    def test_auto_picks_native(self, tracers):
        scene, _, _ = tracers["living_room"]
        assert PathTracer(scene).backend == "native"
        assert resolve_backend("auto") == "native"

    @pytest.mark.parametrize(
        "env,want",
        [("numpy", "numpy"), ("torch", "numpy"), ("native", "native"), ("auto", "native"), (" Torch ", "numpy")],
    )
    def test_env_overrides(self, monkeypatch, env, want):
        monkeypatch.setenv(ENV_VAR, env)
        assert resolve_backend("native") == want
        assert resolve_backend("numpy") == want

    def test_errors(self, monkeypatch):
        with pytest.raises(ValueError, match="backend"):
            resolve_backend("cuda")
        monkeypatch.setenv(ENV_VAR, "gpu")
        with pytest.raises(ValueError, match=ENV_VAR):
            resolve_backend("auto")
        monkeypatch.delenv(ENV_VAR)
        monkeypatch.setattr(tracer_mod, "_core", None)
        assert resolve_backend("auto") == "numpy"
        assert resolve_backend("torch") == "numpy"
        with pytest.raises(RuntimeError, match="native"):
            resolve_backend("native")
