"""sampling="catmull_rom" (NRD's rule: the 16-tap Catmull-Rom sum where all 16 footprint taps pass the tests, else
the bilinear result, clamped at 0) on every implementation; its per-pixel definition is checked against the
reference of reference.py in test_ops.py::test_matches_reference."""

from __future__ import annotations

import math

import pytest
import torch

from base import BaseTester
from reference import _keys  # tests/reproject/ is on sys.path
from test_reproject import scene_pair
from stereorepro import (
    History,
    SpatiotemporalReprojection,
    Thresholds,
    View,
    backward_reproject,
    temporal_reproject,
)

KEYS = ("src_color", "src_depth", "src_normal", "src_K", "src_cam_from_world")
DST_KEYS = ("dst_depth", "dst_normal", "dst_K", "dst_cam_from_world")


def views(inp: dict) -> tuple[View, View]:
    """(source, destination) Views of a scene_pair / plane inputs dict."""
    src = View(inp["src_depth"], inp["src_normal"], inp["src_K"], inp["src_cam_from_world"])
    dst = View(*(inp[k] for k in DST_KEYS))
    return src, dst


def texture(x: torch.Tensor, y: torch.Tensor, period: float) -> torch.Tensor:
    """(3, ...) a smooth high-frequency colour pattern of world x, y (periods of a few pixels), values in [0.1, 0.9]."""
    w = 2 * math.pi / period
    a = torch.sin(w * x) * torch.cos(0.8 * w * y)
    b = torch.sin(0.7 * w * (x + y) + 1.0)
    c = torch.cos(1.3 * w * x - 0.4 * w * y)
    return 0.5 + 0.2 * torch.stack([a + 0.5 * b, b, 0.5 * (a + c)])


def plane_frame(t: int, H: int, W: int, step_px: tuple[float, float], depth: float = 2.0, f: float = 64.0):
    """Frame t of a camera sliding over a fronto-parallel textured plane by ``step_px`` pixels per frame: its View
    and its noise-free colour (the texture at each pixel centre's surface point), float64."""
    dtype = torch.float64
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]], dtype=dtype)[None]
    cx, cy = t * step_px[0] * depth / f, t * step_px[1] * depth / f
    T = torch.eye(4, dtype=dtype)[None].clone()
    T[0, 0, 3], T[0, 1, 3] = -cx, -cy
    normal = torch.zeros(1, 3, H, W, dtype=dtype)
    normal[:, 2] = -1.0
    view = View(torch.full((1, 1, H, W), depth, dtype=dtype), normal, K, T)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype) + 0.5, torch.arange(W, dtype=dtype) + 0.5, indexing="ij")
    x, y = (u - W / 2) / f * depth + cx, (v - H / 2) / f * depth + cy
    return view, texture(x, y, period=6.0 * depth / f)[None]


def accumulation_error(sampling: str, frames: int = 16, H: int = 40, W: int = 56) -> float:
    """Mean squared error of the last frame of a temporal accumulation of the noise-free textured plane against the
    texture at that frame, on the pixels whose history was kept throughout (away from the entering border)."""
    step = (0.37, 0.23)
    view, color = plane_frame(0, H, W, step)
    out = temporal_reproject(color, view, History.empty(view), view, Thresholds(0.2, 0.1), sampling=sampling)
    for t in range(1, frames):
        prev = view
        view, color = plane_frame(t, H, W, step)
        out = temporal_reproject(color, view, out.history, prev, Thresholds(0.2, 0.1), sampling=sampling)
    kept = out.history_len[0, 0] >= frames
    assert kept.float().mean() > 0.5
    return float((out.color - color)[0][:, kept].square().mean())


class TestCatmullRom(BaseTester):
    def test_backends_identical(self, backend):
        """backward_reproject and the fused temporal op on every backend give the torch general path's bytes, on
        a scene where the cubic replaces the bilinear value on part of the pixels only."""
        inp, *_ = scene_pair(H=40, W=56, forward=0.05, yaw=0.5, baseline=0.1)
        src, dst = views(inp)
        values = torch.rand(1, 4, 40, 56, generator=torch.Generator().manual_seed(0)) * 2
        thr = Thresholds(0.5, 0.5)
        with torch.no_grad():
            got = backward_reproject(values, src, dst, thr, sampling="catmull_rom", backend=self.backend_arg(backend))
            bil = backward_reproject(values, src, dst, thr, backend="torch")
        with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
            from stereorepro.reproject import functional

            mp.setattr(functional, "FAST_PATH", False)
            ref = backward_reproject(values, src, dst, thr, sampling="catmull_rom", backend="torch")
            history = History(values[:, :3], torch.randint(1, 20, (1, 1, 40, 56)).float())
            t_ref = temporal_reproject(values[:, 1:], dst, history, src, thr, sampling="catmull_rom", backend="torch")
        with torch.no_grad():
            t_got = temporal_reproject(
                values[:, 1:], dst, history, src, thr, sampling="catmull_rom", backend=self.backend_arg(backend)
            )
        changed = (ref.values != bil.values).any(1)
        assert 0.2 < float(changed.float().mean()) < 0.9, "the cubic applies on part of the pixels"
        self.assert_identical(got, ref)
        self.assert_identical(t_got[:3], t_ref[:3])

    def test_motion_vectors_identical(self, backend):
        """With motion vectors (a moving patch; NaN / inf / huge motion in the hostile case) every backend gives the
        general path's bytes."""
        from test_export import moving

        from stereorepro import TemporalReprojection
        from stereorepro._testing import example_inputs

        m = TemporalReprojection(1.0, 1.0, motion_vectors=True)
        for hostile in (False, True):
            inp = moving(example_inputs(m, batch=2, height=29, width=43), seed=1, hostile=hostile)
            cur, dd, dn, dK, dT, hc, hl, sd, sn, sK, sT, mo, mw = inp
            src, dst = View(sd, sn, sK, sT), View(dd, dn, dK, dT, motion=mo, motion_world=mw)
            values, thr = torch.cat([hc, hl], 1), Thresholds(1.0, 1.0)
            with torch.no_grad():
                got = backward_reproject(
                    values, src, dst, thr, sampling="catmull_rom", backend=self.backend_arg(backend)
                )
                bil = backward_reproject(values, src, dst, thr, backend="torch")
                with pytest.MonkeyPatch.context() as mp:
                    from stereorepro.reproject import functional

                    mp.setattr(functional, "FAST_PATH", False)
                    ref = backward_reproject(values, src, dst, thr, sampling="catmull_rom", backend="torch")
            assert float((ref.values != bil.values).any(1).float().mean()) > 0.05
            self.assert_identical(got, ref)

    def test_occluding_edge_is_bilinear(self, backend):
        """At an occluding edge (a nearer plane over the left half of the source), every pixel whose 4×4 footprint
        reaches across the edge keeps the bilinear value exactly; pixels away from it get the cubic."""
        H, W, f = 24, 40, 64.0
        inp, *_ = scene_pair(H=H, W=W)  # cameras and K replaced below
        K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])[None]
        T_src = torch.eye(4)[None].clone()
        T_src[0, 0, 3], T_src[0, 1, 3] = -0.013, 0.007  # a fractional-pixel move (0.4 px, 0.2 px on the far plane)
        depth = torch.full((1, 1, H, W), 2.0)
        depth[..., : W // 2] = 1.0  # the near plane: the source sees it up to column W/2
        normal = torch.zeros(1, 3, H, W)
        normal[:, 2] = -1.0
        color = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(1))
        src = View(depth, normal, K, T_src)
        dst = View(depth, normal, K, torch.eye(4)[None])
        thr = Thresholds(0.2, 0.1)
        with torch.no_grad():
            cubic = backward_reproject(color, src, dst, thr, sampling="catmull_rom", backend=self.backend_arg(backend))
            bil = backward_reproject(color, src, dst, thr, backend=self.backend_arg(backend))
        self.assert_identical(cubic[1:], bil[1:])
        # the source columns a destination pixel's footprint covers: x0 - 1 .. x0 + 2, x0 = floor(u - 0.5)
        u = torch.arange(W) + 0.5 - torch.where(torch.arange(W) < W // 2, 0.013 * f / 1.0, 0.013 * f / 2.0)
        x0 = torch.floor(u - 0.5)
        straddles = (x0 - 1 < W // 2) & (x0 + 2 >= W // 2)
        rows = slice(2, H - 2)
        same = (cubic.values == bil.values).all(1)[0, rows]
        assert int(straddles.sum()) >= 3
        assert bool(same[:, straddles].all()), "a footprint across the edge must keep the bilinear value"
        inside = ~straddles & (x0 >= 1) & (x0 + 2 <= W - 1)
        assert float((~same[:, inside]).float().mean()) > 0.9

    def test_negative_lobes_clamped(self, backend):
        """A one-pixel spike on black seen by a camera moved by (0.4, 0.3) pixels over a plane: the result is
        Keys' kernel (reference.py) around the spike, its negative lobes clamped to 0 per channel."""
        H, W = 20, 24
        dst, _ = plane_frame(0, H, W, (0.4, 0.3))
        src, _ = plane_frame(1, H, W, (0.4, 0.3))
        src, dst = (View(v.depth.float(), v.normal.float(), v.K, v.cam_from_world) for v in (src, dst))
        spike = torch.tensor([1.0, 2.0, 0.5])
        values = torch.zeros(1, 3, H, W)
        values[0, :, 10, 12] = spike
        with torch.no_grad():
            out = backward_reproject(
                values, src, dst, (1.0, 0.5), sampling="catmull_rom", backend=self.backend_arg(backend)
            )
        us = torch.arange(W, dtype=torch.float64) + 0.5 - 0.4  # source coordinates of the destination pixels
        vs = torch.arange(H, dtype=torch.float64) + 0.5 - 0.3
        kx = torch.tensor([_keys(12.5 - float(u)) for u in us])
        ky = torch.tensor([_keys(10.5 - float(v)) for v in vs])
        unclamped = spike.double().view(3, 1, 1) * ky.view(1, H, 1) * kx.view(1, 1, W)
        assert (unclamped < -0.01).any(), "the example has negative lobes"
        assert bool(out.valid.all())
        torch.testing.assert_close(out.values[0].double(), unclamped.clamp_min(0), atol=1e-6, rtol=1e-5)

    def test_gradcheck(self):
        """Differentiable in the values (float64), hard and soft tests."""
        inp, *_ = scene_pair(H=10, W=12, forward=0.05, yaw=0.5, baseline=0.1, dtype=torch.float64)
        src, dst = views(inp)
        values = torch.rand(1, 2, 10, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
        values.requires_grad_(True)
        for soft in (False, True):

            def f(v):
                return backward_reproject(v, src, dst, (5.0, 2.0), sampling="catmull_rom", soft=soft).values

            with torch.no_grad():
                cubic, bil = f(values), backward_reproject(values, src, dst, (5.0, 2.0), soft=soft).values
            assert (cubic != bil).any()
            assert torch.autograd.gradcheck(f, (values,), eps=1e-6, atol=1e-7)

    def test_accumulation_keeps_texture(self):
        """16 frames of temporal accumulation of a noise-free textured plane under fractional-pixel camera motion:
        Catmull-Rom history reads keep at least 3× less error than bilinear ones (the accumulated resampling
        blur)."""
        bilinear, cubic = accumulation_error("bilinear"), accumulation_error("catmull_rom")
        assert bilinear > 3 * cubic, (bilinear, cubic)

    def test_driver(self, backend):
        """The stereo + temporal driver reads both eyes' histories with Catmull-Rom on every backend (the torch
        general path's colours)."""
        outs = {}
        for name, be in (("ref", "torch"), ("got", self.backend_arg(backend))):
            acc = SpatiotemporalReprojection(0.5, 0.5, sampling="catmull_rom", backend=be)
            outs[name] = _drive(acc)
        for a, b in zip(outs["got"], outs["ref"]):
            torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def _drive(acc: SpatiotemporalReprojection) -> list[torch.Tensor]:
    """Three stereo frames of a moving rig through the driver: both eyes' colours of the last frame."""
    for t in range(3):
        inp, *_ = scene_pair(H=24, W=32, forward=0.03 * t, yaw=0.4 * t, baseline=0.065, seed=t)
        g = torch.Generator().manual_seed(t)
        with torch.no_grad():
            right = acc.right(torch.rand(1, 3, 24, 32, generator=g), *(inp[k] for k in KEYS[1:]))
            acc.left_trace_mask(*(inp[k] for k in DST_KEYS))
            left = acc.left(torch.rand(1, 3, 24, 32, generator=g))
    return [right, left]
