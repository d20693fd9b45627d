"""Motion vectors on the fast implementations: the torch fast path and the native kernels (temporal fused pass,
temporal with reasons, backward with confidence) give the torch general path's bytes, on realistic scenes with
moving objects and on hostile motion; ``backend="auto"`` picks native for motion inputs."""

from __future__ import annotations

import math

import pytest
import torch

from base import BaseTester
from stereorepro import History, TemporalReprojection, View, backward_reproject, camera_motion, temporal_reproject
from stereorepro._testing import example_inputs
from stereorepro.reproject import _native, functional

THR = (0.05, 0.25)


def moving_scene(height: int = 37, width: int = 61, batch: int = 1, seed: int = 0, hostile: bool = False):
    """A realistic temporal step (:func:`example_inputs`: head motion, occlusions, sky) whose motion vectors are the
    cameras' plus an object-like patch that moved (screen shift and the matching world motion), randomly perturbed
    (so that taps land anywhere in the pixel). ``hostile``: NaN / ±inf / huge entries in both motions, and points
    moved behind the previous camera. Returns (current, view, history, prev_view) in float32."""
    x = example_inputs(TemporalReprojection(*THR, backend="torch"), batch=batch, height=height, width=width, seed=seed)
    cur, depth, normal, K, T, hist, n, pdepth, pnormal, pK, pT = x
    g = torch.Generator().manual_seed(seed)
    motion = torch.nan_to_num(camera_motion(depth, K, T, pK, pT), nan=0.0)
    motion = motion + 0.3 * torch.randn(motion.shape, generator=g)
    motion_world = 0.002 * torch.randn(batch, 3, height, width, generator=g)
    patch = (slice(None), slice(None), slice(height // 4, height // 2), slice(width // 3, width // 2))
    motion[patch] += torch.tensor([-2.5, 1.25]).view(1, 2, 1, 1)
    motion_world[patch] += torch.tensor([0.05, -0.02, 0.01]).view(1, 3, 1, 1)
    if hostile:
        for m, p in ((motion, 0.05), (motion_world, 0.05)):
            odd = torch.rand(m.shape, generator=g) < p
            vals = torch.tensor([math.nan, math.inf, -math.inf, 1e30, -3e38])
            m[odd] = vals[torch.randint(0, len(vals), (int(odd.sum()),), generator=g)]
        motion_world[:, 2, :3] = -100.0  # moved behind the previous camera
    n = torch.rand(n.shape, generator=g) * 10.0
    return cur, View(depth, normal, K, T, motion, motion_world), History(hist, n), View(pdepth, pnormal, pK, pT)


def _half(scene, layout: str):
    """The scene with some planes in float16: ``engine`` (colours, normals, motion), ``all`` (every image)."""
    cur, view, hist, prev = scene
    if layout == "float32":
        return scene
    h = torch.float16
    depth = (lambda z: z.to(h)) if layout == "all" else (lambda z: z)
    view = View(
        depth(view.depth), view.normal.to(h), view.K, view.cam_from_world, view.motion.to(h), view.motion_world.to(h)
    )
    prev = View(depth(prev.depth), prev.normal.to(h), prev.K, prev.cam_from_world)
    return cur.to(h), view, History(hist.color.to(h), hist.length.to(h) if layout == "all" else hist.length), prev


def _run(scene, backend: str, sampling: str = "bilinear", return_reason: bool = True, world: bool = True):
    cur, view, hist, prev = scene
    if not world:
        view = View(view.depth, view.normal, view.K, view.cam_from_world, view.motion)
    with torch.no_grad():
        t = temporal_reproject(
            cur, view, hist, prev, THR, sampling=sampling, backend=backend, return_reason=return_reason
        )
        values = torch.cat([hist.color, hist.length.to(hist.color.dtype)], 1)
        b = backward_reproject(values, prev, view, THR, sampling=sampling, backend=backend)
    return [x for x in (*t, *b) if x is not None]


class TestMotionFastPaths(BaseTester):
    @pytest.mark.parametrize("sampling", ["bilinear", "nearest"])
    @pytest.mark.parametrize("hostile", [False, True], ids=["scene", "hostile"])
    @pytest.mark.parametrize("world", [True, False], ids=["world", "screen"])
    def test_matches_general_path(self, backend, sampling, hostile, world, monkeypatch):
        """Every implementation gives the general path's bytes (temporal with reasons, backward with confidence;
        native also the fused pass), batch of two with different seeds' cameras."""
        scene = moving_scene(batch=2, seed=3, hostile=hostile)
        monkeypatch.setattr(functional, "FAST_PATH", False)
        ref = _run(scene, "torch", sampling, world=world)
        monkeypatch.setattr(functional, "FAST_PATH", backend != "torch")
        got = _run(scene, self.backend_arg(backend), sampling, world=world)
        self.assert_identical(got, ref)
        assert 0.2 < float(ref[2].float().mean()) < 1.0  # some history kept, some discarded
        if backend == "native":
            self.assert_identical(_run(scene, "native", sampling, False, world)[:3], ref[:3])

    @pytest.mark.parametrize("layout", ["engine", "all"])
    def test_float16(self, backend, layout, monkeypatch):
        """float16 colours, normals and motion (and depths, history length: ``all``), read as they are."""
        scene = _half(moving_scene(seed=5, hostile=True), layout)
        monkeypatch.setattr(functional, "FAST_PATH", False)
        ref = _run(scene, "torch")
        monkeypatch.setattr(functional, "FAST_PATH", backend != "torch")
        self.assert_identical(_run(scene, self.backend_arg(backend)), ref)
        if backend == "native":
            self.assert_identical(_run(scene, "native", return_reason=False)[:3], ref[:3])

    def test_auto_runs_native_with_motion(self, monkeypatch):
        """``backend="auto"`` with motion vectors (float32 or float16, CPU, no grad) runs the native kernels and
        equals the torch general path byte for byte; the driver takes the same route."""
        if not _native.available():
            pytest.skip("stereorepro._core is not built")
        calls = {"temporal": 0, "reproject": 0}

        def counting(name, fn):
            def wrapped(*args, **kwargs):
                calls[name] += 1
                return fn(*args, **kwargs)

            return wrapped

        monkeypatch.delenv("STEREOREPRO_BACKEND", raising=False)
        monkeypatch.setattr(_native, "temporal_reproject", counting("temporal", _native.temporal_reproject))
        monkeypatch.setattr(_native, "reproject", counting("reproject", _native.reproject))
        scene = moving_scene(seed=7)
        got = _run(scene, "auto", return_reason=False)
        assert calls == {"temporal": 1, "reproject": 1}
        monkeypatch.setattr(functional, "FAST_PATH", False)
        ref = _run(scene, "torch", return_reason=False)
        self.assert_identical(got, ref)

        from stereorepro import SpatiotemporalReprojection

        cur, view, hist, prev = scene
        st = SpatiotemporalReprojection(*THR, stereo=False)
        st.right(hist.color, prev.depth, prev.normal, prev.K, prev.cam_from_world)
        out = st.right(cur, view.depth, view.normal, view.K, view.cam_from_world, view.motion, view.motion_world)
        assert calls == {"temporal": 1, "reproject": 2}  # the driver asks for reasons: warp, then blend
        with torch.no_grad():
            expected = temporal_reproject(
                cur, view, History(hist.color, torch.ones_like(hist.length)), prev, THR, backend="torch"
            )
        self.assert_identical([out], [expected.color])

    def test_auto_keeps_torch_where_native_cannot(self, monkeypatch):
        """float64 motion (or a motion that needs grad) keeps ``auto`` on torch; ``native`` says why."""
        if not _native.available():
            pytest.skip("stereorepro._core is not built")
        cur, view, hist, prev = moving_scene(height=9, width=11)
        v64 = View(view.depth, view.normal, view.K, view.cam_from_world, view.motion.double())
        with torch.no_grad():
            with pytest.raises(RuntimeError, match="float32 or float16"):
                temporal_reproject(cur, v64, hist, prev, THR, backend="native")
            out = temporal_reproject(cur, v64, hist, prev, THR)
        assert out.color.dtype == torch.float32
        grad = View(view.depth, view.normal, view.K, view.cam_from_world, view.motion.clone().requires_grad_(True))
        with pytest.raises(RuntimeError, match="requires grad"):
            temporal_reproject(cur, grad, hist, prev, THR, backend="native")

    def test_kernel_checks_motion_shapes(self):
        """Direct calls of the kernels check the motion planes' shapes and need the rotation with world motion."""
        if not _native.available():
            pytest.skip("stereorepro._core is not built")
        from stereorepro.camera import compose_warp

        cur, view, hist, prev = moving_scene(height=9, width=11)
        warp = compose_warp(prev.K, prev.cam_from_world, view.K, view.cam_from_world, torch.float32)
        args = (hist.color, prev.depth, prev.normal, warp, view.depth, view.normal, (0.01, 0.01), True)
        with pytest.raises(ValueError, match="motion"):
            _native.reproject(*args, motion=view.motion[:, :, :-1])
        with pytest.raises(ValueError, match="R"):
            from stereorepro import _core

            out = [
                torch.empty(1, 3, 9, 11),
                torch.empty(1, 1, 9, 11, dtype=torch.bool),
                torch.empty(1, 1, 9, 11, dtype=torch.uint8),
                None,
            ]
            _core.reproject(
                hist.color,
                prev.depth,
                prev.normal,
                *_native._warp_args(warp),
                view.depth,
                view.normal,
                0.1,
                0.1,
                True,
                *out,
                view.motion,
                view.motion_world,
                None,
            )
