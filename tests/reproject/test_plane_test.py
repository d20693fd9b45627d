"""``Thresholds(position_test="plane")``: the slope-scaled plane-distance test (NVIDIA NRD's disocclusion test,
parallax-free) instead of the absolute distance test, on every implementation.

A tap passes iff ``|n_dst · (P_src − P_dst)| <= position · z_dst / (0.05 + 0.95·|n_dst · v_dst|)``. The definition
is checked against a numpy float64 reference written here in the world frame (not the implementations' source-frame
arithmetic), on hand-built views: a floor seen at a grazing angle (same-surface taps a pixel apart are far apart in
space: the absolute test rejects them, the plane test keeps them) and a step edge (two parallel planes: the plane
test rejects the far one's taps). Parity: the torch general path, its fast path, the native kernel and the export
formulation give the same bytes (the export's colours to rounding), stereo and temporal, every sampling, with motion.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from base import BaseTester
from stereorepro import (
    History,
    SpatiotemporalReprojection,
    StereoReprojection,
    TemporalReprojection,
    Thresholds,
    View,
    backward_reproject,
    export_onnx,
    stereo_reproject,
    temporal_reproject,
)
from stereorepro._testing import example_inputs
from stereorepro.camera import compose_warp, intrinsics_from_fov
from stereorepro.errors import ParameterError
from stereorepro.reproject import Reason, _general, _lean, _native, functional
from stereorepro.reproject.view import POSITION_TESTS

H, W = 24, 32
PLANE = "plane"


def _pose(tx: float = 0.0, ty: float = 0.0, tz: float = 0.0, yaw_deg: float = 0.0, dtype=torch.float64):
    """A (1, 4, 4) cam_from_world: the camera at (tx, ty, tz) turned by yaw about its y axis."""
    a = math.radians(yaw_deg)
    R = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]], dtype=dtype)
    T = torch.eye(4, dtype=dtype)
    T[:3, :3] = R
    T[:3, 3] = -R @ torch.tensor([tx, ty, tz], dtype=dtype)
    return T[None]


def _rays(K: torch.Tensor, cam_from_world: torch.Tensor):
    """World-space ray directions (3, H, W) of the pixel centres and the camera centre (3,)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype) + 0.5, torch.arange(W, dtype=K.dtype) + 0.5, indexing="ij")
    d_cam = torch.linalg.solve(K[0], torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1))
    R, t = cam_from_world[0, :3, :3], cam_from_world[0, :3, 3]
    return (R.T @ d_cam).reshape(3, H, W), -R.T @ t, d_cam[2].reshape(H, W)


def _view(K, cam_from_world, planes) -> View:
    """A view of the nearest of ``planes`` [(point, normal)] (world frame, normal towards the cameras), camera z."""
    d, c, dz = _rays(K, cam_from_world)
    best = torch.full((H, W), math.inf, dtype=K.dtype)
    normal = torch.zeros(3, H, W, dtype=K.dtype)
    for p, n in planes:
        p, n = torch.tensor(p, dtype=K.dtype), torch.tensor(n, dtype=K.dtype)
        denom = torch.einsum("i,ihw->hw", n, d)
        s = torch.einsum("i,i->", n, p - c) / denom  # ray parameter of the hit
        hit = (s > 0) & (s < best)
        best = torch.where(hit, s, best)
        normal = torch.where(hit[None], n.view(3, 1, 1), normal)
    depth = best * dz  # camera z of the hit
    return View(depth[None, None], normal[None], K, cam_from_world)


def grazing_floor(dtype=torch.float64, noise: float = 0.0):
    """(src, dst): a floor 0.4 below a camera pair 6.5 cm apart, looking slightly down (grazing towards the horizon);
    ``noise``: relative depth noise of the source (fractions of view depth: plane distances that are not 0)."""
    K = intrinsics_from_fov(70.0, W, H).to(torch.float64)
    floor = [((0.0, 0.4, 0.0), (0.0, -1.0, 0.0))]
    src = _view(K, _pose(0.0, 0.0, 0.0), floor)
    dst = _view(K, _pose(-0.065, 0.0, 0.03, 0.7), floor)
    if noise:
        g = torch.Generator().manual_seed(5)
        src = src.replace(depth=src.depth * (1.0 + noise * torch.randn(src.depth.shape, generator=g, dtype=K.dtype)))
    return src.to(dtype), dst.to(dtype)


def step_edge(dtype=torch.float64):
    """(src, dst): two fronto-parallel planes, z = 1 left of x = 0 and z = 1.5 right of it (a box edge), seen by a
    camera pair 20 cm apart: destination pixels next to the edge read taps of the other plane only."""
    K = intrinsics_from_fov(60.0, W, H).to(torch.float64)
    pose_s, pose_d = _pose(0.0), _pose(0.2)
    views = []
    for pose in (pose_s, pose_d):
        near = _view(K, pose, [((0.0, 0.0, 1.0), (0.0, 0.0, -1.0))])
        far = _view(K, pose, [((0.0, 0.0, 1.5), (0.0, 0.0, -1.0))])
        d, c, dz = _rays(K, pose)
        x_world = c[0] + d[0] * (near.depth[0, 0] / dz)  # x of the near plane's hit
        left = (x_world < 0.0)[None, None]
        views.append(View(torch.where(left, near.depth, far.depth), near.normal, K, pose))
    return views[0].to(dtype), views[1].to(dtype)


def reference_valid(src: View, dst: View, position: float, normal: float, test: str):
    """numpy float64, world frame: (valid (H, W), margin (H, W)) of bilinear sampling, the margin being the
    smallest distance of a position decision to its threshold relative to it (inf where none was taken)."""
    Kd, Ks = dst.K[0].double().numpy(), src.K[0].double().numpy()
    Td, Ts = dst.cam_from_world[0].double().numpy(), src.cam_from_world[0].double().numpy()
    zd, nd = dst.depth[0, 0].double().numpy(), dst.normal[0].double().numpy()
    zs, ns = src.depth[0, 0].double().numpy(), src.normal[0].double().numpy()
    Td_inv, Ts_inv = np.linalg.inv(Td), np.linalg.inv(Ts)
    c_dst = Td_inv[:3, 3]
    valid = np.zeros((H, W), bool)
    margin = np.full((H, W), np.inf)
    for y in range(H):
        for x in range(W):
            z = zd[y, x]
            if not (0 < z < np.inf):
                continue
            p_dst = (Td_inv @ np.append(z * np.linalg.solve(Kd, [x + 0.5, y + 0.5, 1.0]), 1.0))[:3]
            q = Ts @ np.append(p_dst, 1.0)
            if q[2] <= 0:
                continue
            uvw = Ks @ q[:3]
            u, v = uvw[0] / uvw[2] - 0.5, uvw[1] / uvw[2] - 0.5
            x0, y0 = math.floor(u), math.floor(v)
            fx, fy = u - x0, v - y0
            n = nd[:, y, x]
            view_dir = (p_dst - c_dst) / np.linalg.norm(p_dst - c_dst)
            scale = z / (0.05 + 0.95 * abs(n @ view_dir))
            taps = [(x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy))]
            taps += [(x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)]
            for xi, yi, w in taps:
                if w <= 0 or not (0 <= xi < zs.shape[1] and 0 <= yi < zs.shape[0]) or not (0 < zs[yi, xi] < np.inf):
                    continue
                p_src = (Ts_inv @ np.append(zs[yi, xi] * np.linalg.solve(Ks, [xi + 0.5, yi + 0.5, 1.0]), 1.0))[:3]
                if test == PLANE:
                    dist, thr = abs(n @ (p_src - p_dst)), position * scale
                else:
                    dist, thr = np.linalg.norm(p_src - p_dst), position
                margin[y, x] = min(margin[y, x], abs(dist - thr) / thr)
                if dist <= thr and np.linalg.norm(ns[:, yi, xi] - n) <= normal:
                    valid[y, x] = True
    return valid, margin


class TestDefinition(BaseTester):
    def test_grazing_floor_kept(self, backend, dtype):
        """A floor at a grazing angle: at 0.5 % of view depth the plane test keeps every floor pixel that reads a
        floor tap (the numpy reference), where the absolute test at a tight 5 mm rejects most of them."""
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        src, dst = grazing_floor(dtype)
        values = torch.rand(1, 3, H, W, dtype=dtype, generator=torch.Generator().manual_seed(0))
        be = self.backend_arg(backend)
        plane = backward_reproject(values, src, dst, Thresholds(0.005, 0.1, position_test=PLANE), backend=be)
        absolute = backward_reproject(values, src, dst, Thresholds(0.005, 0.1), backend=be)
        expected, margin = reference_valid(src, dst, 0.005, 0.1, PLANE)
        floor = dst.depth[0, 0].isfinite()
        assert int(floor.sum()) > 100 and bool(expected[floor.numpy()].mean() > 0.9)
        sure = torch.from_numpy(margin > 1e-3)
        assert torch.equal(plane.valid[0, 0][sure], torch.from_numpy(expected)[sure])
        kept_plane, kept_abs = int(plane.valid[0, 0][floor].sum()), int(absolute.valid[0, 0][floor].sum())
        assert kept_abs < 0.6 * kept_plane, (kept_abs, kept_plane)
        assert bool((absolute.reason[0, 0][floor & ~absolute.valid[0, 0]] == Reason.POSITION).any())

    def test_noisy_floor_matches_reference(self, backend, dtype):
        """Depth noise of 2 % of view depth on the source: plane distances that are not 0, at every angle of the
        floor; the slope-scaled thresholds decide as the numpy reference does (about half the pixels kept)."""
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        src, dst = grazing_floor(dtype, noise=0.02)
        values = torch.rand(1, 3, H, W, dtype=dtype, generator=torch.Generator().manual_seed(0))
        thr = Thresholds(0.0005, 0.1, position_test=PLANE)
        out = backward_reproject(values, src, dst, thr, backend=self.backend_arg(backend))
        expected, margin = reference_valid(src, dst, 0.0005, 0.1, PLANE)
        floor = dst.depth[0, 0].isfinite()
        sure = torch.from_numpy(margin > 1e-3) & floor
        assert int(sure.sum()) > 0.8 * int(floor.sum())
        assert torch.equal(out.valid[0, 0][sure], torch.from_numpy(expected)[sure])
        kept = float(out.valid[0, 0][floor].float().mean())
        assert 0.2 < kept < 0.9, kept

    def test_step_edge_rejected(self, backend, dtype):
        """Two parallel planes 0.5 apart at 1 and 1.5: taps of the other plane are 33-50 % of view depth off the
        plane, rejected (POSITION) at 1 % where a pixel reads no tap of its own plane; same-plane pixels are kept."""
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        src, dst = step_edge(dtype)
        values = torch.rand(1, 3, H, W, dtype=dtype, generator=torch.Generator().manual_seed(0))
        out = backward_reproject(
            values, src, dst, Thresholds(0.01, 0.1, position_test=PLANE), backend=self.backend_arg(backend)
        )
        expected, margin = reference_valid(src, dst, 0.01, 0.1, PLANE)
        sure = torch.from_numpy(margin > 1e-3)
        assert torch.equal(out.valid[0, 0][sure], torch.from_numpy(expected)[sure])
        rejected = ~out.valid[0, 0] & dst.depth[0, 0].isfinite() & (out.reason[0, 0] != Reason.OUT_OF_FRAME)
        assert int(rejected.sum()) >= H  # a column of the edge at least
        assert bool((out.reason[0, 0][rejected] == Reason.POSITION).all())

    def test_unusable_normal_fails(self, backend):
        """A destination normal that is zero, NaN or shorter than 0.5 defines no plane: its pixels' taps fail the
        position test (the normal test alone would keep the zero and short normals at threshold 2)."""
        src, dst = grazing_floor(torch.float32)
        normal = dst.normal.clone()
        bad = {(14, 5): (0.0, 0.0, 0.0), (15, 9): (float("nan"), -1.0, 0.0), (16, 20): (0.0, -0.45, 0.0)}
        for (y, x), n in bad.items():
            normal[0, :, y, x] = torch.tensor(n)
        dst = dst.replace(normal=normal)
        values = torch.ones(1, 3, H, W)
        out = backward_reproject(
            values, src, dst, Thresholds(0.05, 2.0, position_test=PLANE), backend=self.backend_arg(backend)
        )
        for y, x in bad:
            assert not bool(out.valid[0, 0, y, x]) and int(out.reason[0, 0, y, x]) == Reason.POSITION
        assert bool(out.valid[0, 0, 14, 6]) and bool(out.valid[0, 0, 16, 21])  # their neighbours are kept

    def test_distance_is_the_default(self, backend):
        """position_test="distance" gives the bytes of Thresholds without the field."""
        src, dst = grazing_floor(torch.float32, noise=0.02)
        values = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0))
        be = self.backend_arg(backend)
        a = backward_reproject(values, src, dst, (0.01, 0.1), backend=be)
        b = backward_reproject(values, src, dst, Thresholds(0.01, 0.1, 0.1, "distance"), backend=be)
        self.assert_identical(b, a)
        assert Thresholds(0.01, 0.1).position_test == "distance" and POSITION_TESTS == ("distance", "plane")


def noisy_case(dtype=torch.float32, seed=0, motion: bool = False):
    """A stereo (or, with ``motion``, temporal with motion vectors) example scene whose source depths carry 0.5 %
    noise and a 10 % step on a band of rows: the plane test rejects part of the taps at 1 % of view depth."""
    module = TemporalReprojection(0.05, 0.3, motion_vectors=True) if motion else StereoReprojection(0.05, 0.3)
    inp = list(example_inputs(module, batch=2, height=29, width=43, dtype=dtype, seed=seed))
    names = module.input_names
    k = names.index("prev_depth" if motion else "src_depth")
    g = torch.Generator().manual_seed(seed + 1)
    depth = inp[k] * (1.0 + 0.005 * torch.randn(inp[k].shape, generator=g, dtype=dtype))
    depth[:, :, 10:14] *= 1.1
    inp[k] = depth
    if motion:
        from test_export import moving  # tests/reproject/ is on sys.path

        inp = list(moving(tuple(inp), seed, hostile=False))
    return module, inp


def _stereo_views(inp):
    sc, sd, sn, sK, sT, dd, dn, dK, dT = inp
    return sc, View(sd, sn, sK, sT), View(dd, dn, dK, dT)


def _temporal_args(inp):
    cur, dd, dn, dK, dT, hc, hl, sd, sn, sK, sT, mo, mw = inp
    return cur, View(dd, dn, dK, dT, mo, mw), History(hc, hl), View(sd, sn, sK, sT)


SAMPLINGS = ["bilinear", "nearest", "catmull_rom"]


class TestParity(BaseTester):
    """The general path (FAST_PATH off) against the fast path, the native kernel and the export formulation."""

    @pytest.mark.parametrize("sampling", SAMPLINGS)
    def test_stereo(self, backend, dtype, sampling):
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        _, inp = noisy_case(dtype)
        values, src, dst = _stereo_views(inp)
        thr = Thresholds(0.01, 0.3, position_test=PLANE)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(functional, "FAST_PATH", False)
            ref = backward_reproject(values, src, dst, thr, sampling=sampling, backend="torch")
        got = backward_reproject(values, src, dst, thr, sampling=sampling, backend=self.backend_arg(backend))
        kept = float(ref.valid.float().mean())
        assert 0.4 < kept < 0.95, kept
        assert int((ref.reason == Reason.POSITION).sum()) > 50
        plain = backward_reproject(values, src, dst, (0.01, 0.3), sampling=sampling, backend="torch")
        assert not torch.equal(plain.valid, ref.valid)
        self.assert_identical(got, ref)

    @pytest.mark.parametrize("sampling", SAMPLINGS)
    def test_temporal_with_motion(self, backend, sampling):
        """temporal_reproject with motion vectors (world motion: the moved point's plane distance), return_reason
        and the fused native pass."""
        _, inp = noisy_case(torch.float32, seed=2, motion=True)
        cur, view, history, prev = _temporal_args(inp)
        thr = Thresholds(0.01, 0.3, position_test=PLANE)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(functional, "FAST_PATH", False)
            ref = temporal_reproject(
                cur, view, history, prev, thr, sampling=sampling, backend="torch", return_reason=True
            )
        be = self.backend_arg(backend)
        got = temporal_reproject(cur, view, history, prev, thr, sampling=sampling, backend=be, return_reason=True)
        fused = temporal_reproject(cur, view, history, prev, thr, sampling=sampling, backend=be)
        assert 0.3 < float(ref.valid.float().mean()) < 0.95
        self.assert_identical(got, ref)
        self.assert_identical(fused[:3], ref[:3])

    @pytest.mark.parametrize("sampling", SAMPLINGS)
    @pytest.mark.parametrize("motion", [False, True], ids=["stereo", "motion"])
    def test_export_formulation(self, dtype, sampling, motion):
        """_lean.lean_reproject in eager: valid, reason and confidence identical, colours to rounding."""
        _, inp = noisy_case(dtype, seed=3, motion=motion)
        if motion:
            cur, view, history, prev = _temporal_args(inp)
            values, src, dst = torch.cat([history.color, history.length], 1), prev, view
        else:
            values, src, dst = _stereo_views(inp)
        warp = compose_warp(src.K, src.cam_from_world, dst.K, dst.cam_from_world, dtype)
        R = src.cam_from_world[:, :3, :3]
        mo, mw = dst.motion, dst.motion_world
        args = (values, src.depth, src.normal, dst.depth, dst.normal, warp, 0.01, 0.3, sampling)
        ref = _general.general_reproject(*args, False, 0.1, False, mo, mw, R, PLANE)
        got = _lean.lean_reproject(*args, False, mo, mw, R, PLANE)
        for name, r, g in zip(("values", "valid", "reason", "confidence"), ref, got):
            if r.is_floating_point():
                torch.testing.assert_close(g, r, atol=1e-6, rtol=1e-6, msg=name)
            else:
                assert torch.equal(g, r), name

    @pytest.mark.skipif(not _native.available(), reason="stereorepro._core is not built")
    def test_native_float16_layouts(self):
        """float16 images (read as they are by the native kernel) give torch's results on their float32 upcast."""
        _, inp = noisy_case(torch.float32)
        values, src, dst = _stereo_views(inp)
        half = [x.half() for x in (values, src.depth, src.normal, dst.depth, dst.normal)]
        src16 = View(half[1], half[2], src.K, src.cam_from_world)
        dst16 = View(half[3], half[4], dst.K, dst.cam_from_world)
        thr = Thresholds(0.01, 0.3, position_test=PLANE)
        got = backward_reproject(half[0], src16, dst16, thr, backend="native")
        src32 = View(half[1].float(), half[2].float(), src.K, src.cam_from_world)
        dst32 = View(half[3].float(), half[4].float(), dst.K, dst.cam_from_world)
        ref = backward_reproject(half[0].float(), src32, dst32, thr, backend="torch")
        assert torch.equal(got.valid, ref.valid) and torch.equal(got.reason, ref.reason)
        assert torch.equal(got.values, ref.values.half())


class TestGradients(BaseTester):
    def test_gradcheck(self):
        """float64, hard and soft: differentiable in the values; soft also in the (relative) threshold."""
        src, dst = grazing_floor(torch.float64, noise=0.02)
        values = torch.rand(1, 2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
        values.requires_grad_(True)
        thr = torch.tensor(0.0005, dtype=torch.float64, requires_grad=True)
        for soft in (False, True):

            def f(v, t):
                th = Thresholds(t, 0.3, 0.1, PLANE)
                return backward_reproject(v, src, dst, th, soft=soft, backend="torch").values

            assert torch.autograd.gradcheck(f, (values, thr), eps=1e-7, atol=1e-6)
        out = backward_reproject(values, src, dst, Thresholds(thr, 0.3, 0.1, PLANE), soft=True).values
        (grad,) = torch.autograd.grad(out.sum(), thr)
        assert math.isfinite(float(grad)) and float(grad) != 0.0

    def test_soft_matches_hard_when_cold(self):
        """A low temperature: the soft plane test's weights approach the hard decisions."""
        src, dst = grazing_floor(torch.float64, noise=0.02)
        values = torch.rand(1, 3, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
        hard = backward_reproject(values, src, dst, Thresholds(0.0005, 0.3, 0.1, PLANE))
        soft = backward_reproject(values, src, dst, Thresholds(0.0005, 0.3, 1e-4, PLANE), soft=True)
        assert torch.equal(soft.valid, hard.valid)
        close = (soft.confidence - hard.confidence).abs() < 1e-3
        assert float(close.float().mean()) > 0.97


class TestConfiguration(BaseTester):
    def test_bad_position_test(self):
        src, dst = grazing_floor(torch.float32)
        values = torch.ones(1, 3, H, W)
        with pytest.raises(ParameterError, match="backward_reproject: thresholds: position_test must be one of"):
            backward_reproject(values, src, dst, Thresholds(0.01, 0.1, position_test="planar"))
        with pytest.raises(ParameterError, match="stereo_reproject"):
            stereo_reproject(values, src, dst, Thresholds(0.01, 0.1, position_test=None))
        with pytest.raises(ParameterError, match="temporal_reproject"):
            temporal_reproject(values, dst, History.empty(src), src, (0.01, 0.1, 0.1, "Plane"))
        m = StereoReprojection(0.01, 0.1)
        with pytest.raises(ParameterError, match="StereoReprojection: position_test"):
            m.position_test = "bogus"
        with pytest.raises(ParameterError, match="TemporalReprojection: position_test"):
            TemporalReprojection(0.01, 0.1).position_test = 1
        st = SpatiotemporalReprojection(0.01, 0.1)
        with pytest.raises(ParameterError, match="SpatiotemporalReprojection: position_test"):
            st.position_test = "planes"
        assert st.position_test == "distance" and m.position_test == "distance"

    @pytest.mark.parametrize("kind", ["stereo", "temporal"])
    def test_module_equals_function(self, kind):
        module, inp = noisy_case(torch.float32, seed=4, motion=kind == "temporal")
        module.position_test = PLANE
        assert "position_test='plane'" in repr(module)
        with torch.no_grad():
            out = module(*inp)
        thr = Thresholds(0.05, 0.3, position_test=PLANE)
        if kind == "stereo":
            values, src, dst = _stereo_views(inp)
            ref = stereo_reproject(values, src, dst, thr)
        else:
            cur, view, history, prev = _temporal_args(inp)
            ref = temporal_reproject(cur, view, history, prev, thr)
        self.assert_identical(out, ref[:3])

    def test_driver(self, backend):
        """SpatiotemporalReprojection.position_test reaches the stereo step and the temporal steps: its outputs
        differ from the distance test's, and every backend gives the torch general path's bytes."""
        src, dst = grazing_floor(torch.float32, noise=0.02)
        g = torch.Generator().manual_seed(6)
        frames = [(torch.rand(1, 3, H, W, generator=g), torch.rand(1, 3, H, W, generator=g)) for _ in range(3)]

        def drive(test: str, be: str):
            st = SpatiotemporalReprojection(0.0005 if test == PLANE else 0.01, 0.3, backend=be)
            st.position_test = test
            out = []
            for right_c, left_c in frames:
                out.append(st.right(right_c, src.depth, src.normal, src.K, src.cam_from_world))
                st.left_trace_mask(dst.depth, dst.normal, dst.K, dst.cam_from_world)
                out += [st.stereo_valid, st.left(left_c)]
            return out

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(functional, "FAST_PATH", False)
            ref = drive(PLANE, "torch")
        got = drive(PLANE, self.backend_arg(backend))
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
        distance = drive("distance", "torch")
        assert not torch.equal(distance[-2], ref[-2])  # the stereo step's keep mask


def _inputs(module, seed, h, w):
    """Noisy source depths for an exported module's inputs (see :func:`noisy_case`)."""
    inp = list(example_inputs(module, batch=2, height=h, width=w, seed=seed))
    k = module.input_names.index("prev_depth" if isinstance(module, TemporalReprojection) else "src_depth")
    g = torch.Generator().manual_seed(seed)
    inp[k] = inp[k] * (1.0 + 0.005 * torch.randn(inp[k].shape, generator=g))
    return inp


def _planar(module):
    module.position_test = PLANE
    return module


EXPORTED = {
    "stereo_plane": lambda: _planar(StereoReprojection(0.01, 0.3)),
    "stereo_plane_catmull_rom": lambda: _planar(StereoReprojection(0.02, 0.5, sampling="catmull_rom")),
    "stereo_plane_rectified": lambda: _planar(StereoReprojection(0.01, 0.3, rectified=True)),
    "temporal_plane": lambda: _planar(TemporalReprojection(0.01, 0.3)),
    "temporal_plane_nearest": lambda: _planar(TemporalReprojection(0.01, 0.3, sampling="nearest")),
}


@pytest.mark.onnx
class TestExported:
    @pytest.mark.parametrize("name", sorted(EXPORTED))
    def test_onnx_parity(self, name, tmp_path):
        """The exported graph honours the plane test: onnxruntime at two sizes, valid and reason identical to the
        module, colour within 1e-5; and it differs from the distance test's graph."""
        from test_export import _compare, _ort_session

        m = EXPORTED[name]()
        sess = _ort_session(export_onnx(m, tmp_path / f"{name}.onnx"))
        for h, w in [(36, 48), (29, 67)]:
            if "rectified" in name:
                inp = list(example_inputs(m, batch=2, height=h, width=w, seed=h, head_motion=False))
            else:
                inp = _inputs(m, h, h, w)
            got = sess.run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)})
            _compare(m, got, inp)
        m.position_test = "distance"
        with torch.no_grad():
            assert not np.array_equal(m(*inp)[-1].numpy(), got[-1]) or "rectified" in name

    @pytest.mark.parametrize("name", ["stereo_plane", "temporal_plane"])
    def test_reference_evaluator(self, name, tmp_path):
        """onnx.checker (full check) and onnx.reference on a tiny input."""
        onnx = pytest.importorskip("onnx")
        from onnx.reference import ReferenceEvaluator
        from onnx.reference.op_run import OpRun

        from test_export import _compare

        class GatherElements(OpRun):  # the spec's operator (see test_export.py's test_reference_evaluator)
            def _run(self, data, indices, axis=None):
                idx = indices.astype(np.int64)
                idx = np.where(idx < 0, idx + data.shape[axis], idx)
                return (np.take_along_axis(data, idx, axis=axis),)

        m = EXPORTED[name]()
        path = export_onnx(m, tmp_path / f"{name}.onnx")
        model = onnx.load(str(path))
        onnx.checker.check_model(model, full_check=True)
        inp = _inputs(m, 1, 6, 8)
        got = ReferenceEvaluator(model, new_ops=[GatherElements]).run(
            None, {n: x.numpy() for n, x in zip(m.input_names, inp)}
        )
        _compare(m, got, inp)
