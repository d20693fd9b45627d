"""Reprojection core: stereo and temporal backward warping with discard masks.

Inputs are analytic (fronto-parallel planes with exact pixel shifts, and the ray-cast scene of
stereorepro._testing), so expected answers are known without a renderer. Each class is one operation on
``BaseTester``; the forward tests run on every backend of the ``backend`` fixture (torch general path, torch fast
path, native), gradients and soft tests on torch.
"""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from base import BaseTester
from reference import reference_backward_reproject, reference_temporal_blend

from stereorepro import (
    Reason,
    StereoReprojection,
    TemporalReprojection,
    backward_reproject,
    export_onnx,
    reason_to_rgb,
    stereo_reproject,
    temporal_reproject,
)
from stereorepro.camera import compose_warp
from stereorepro.errors import ShapeError
from stereorepro.camera import PinholeCamera, look_at
from stereorepro.io.onnx import onnx_input_dims
from stereorepro._testing import camera_pair, default_scene, example_inputs, raycast

ARGS = [
    "src_color",
    "src_depth",
    "src_normal",
    "src_K",
    "src_cam_from_world",
    "dst_depth",
    "dst_normal",
    "dst_K",
    "dst_cam_from_world",
]


def plane_pair(H=6, W=8, shift_px=1.0, depth=2.0, dtype=torch.float32, f=64.0, B=1, seed=0):
    """Fronto-parallel plane at ``depth``; the source camera sits ``shift_px`` pixels to the right, so
    dst pixel x reads source pixel x - shift_px (exact in binary floating point for f = 64, depth = 2)."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]], dtype=dtype).expand(B, 3, 3).clone()
    T_dst = torch.eye(4, dtype=dtype).expand(B, 4, 4).clone()
    T_src = T_dst.clone()
    T_src[:, 0, 3] = -shift_px * depth / f
    d = torch.full((B, 1, H, W), depth, dtype=dtype)
    n = torch.zeros(B, 3, H, W, dtype=dtype)
    n[:, 2] = -1.0
    c = torch.rand(B, 3, H, W, generator=g, dtype=dtype)
    return dict(
        src_color=c,
        src_depth=d.clone(),
        src_normal=n.clone(),
        src_K=K,
        src_cam_from_world=T_src,
        dst_depth=d.clone(),
        dst_normal=n.clone(),
        dst_K=K.clone(),
        dst_cam_from_world=T_dst,
    )


def run(inp, pos=0.01, nrm=0.1, **kw):
    """stereo_reproject on ``inp``; pass ``backend=BaseTester.backend_arg(backend)`` to pick the implementation
    (default ``auto``). Runs without autograd unless an input requires grad (the native backend refuses it)."""
    return stereo_reproject(*[inp[a] for a in ARGS], pos, nrm, **kw)


def scene_pair(
    H=36,
    W=48,
    dtype=torch.float32,
    B=1,
    forward=0.0,
    yaw=0.0,
    baseline=0.065,
    seed=0,
    origin_offset=(0.0, 0.0, 0.0),
    cam_dtype=None,
):
    dst, src = camera_pair(H, W, B, baseline=baseline, forward=forward, yaw_deg=yaw, origin_offset=origin_offset)
    scene = default_scene(origin_offset)
    gd, gs = raycast(dst, scene), raycast(src, scene)
    cam_dtype = dtype if cam_dtype is None else cam_dtype
    inp = dict(
        src_color=gs.color.to(dtype),
        src_depth=gs.depth.to(dtype),
        src_normal=gs.normal.to(dtype),
        src_K=src.K.to(cam_dtype),
        src_cam_from_world=src.cam_from_world.to(cam_dtype),
        dst_depth=gd.depth.to(dtype),
        dst_normal=gd.normal.to(dtype),
        dst_K=dst.K.to(cam_dtype),
        dst_cam_from_world=dst.cam_from_world.to(cam_dtype),
    )
    return inp, gd, gs, dst, src


def onnx_runs(module, tmp_path, name):
    """Export ``module``, check its symbolic dims, and yield (input dims, torch outputs, onnxruntime outputs) on
    realistic inputs at two resolutions (B = 2)."""
    ort = pytest.importorskip("onnxruntime")
    path = export_onnx(module, tmp_path / f"{name}.onnx")
    dims = onnx_input_dims(path)
    sess = ort.InferenceSession(str(path))
    for h, w in [(36, 48), (71, 129)]:
        inp = example_inputs(module, batch=2, height=h, width=w, seed=h)
        ref = module(*inp)
        got = sess.run(None, {n: x.numpy() for n, x in zip(module.input_names, inp)})
        yield dims, ref, got


class TestStereoReproject(BaseTester):
    def test_smoke(self, device, dtype, backend):
        self.skip_unless_runs(backend, dtype, device)
        inp = {k: v.to(device) for k, v in plane_pair(dtype=dtype).items()}
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert out.shape == (1, 3, 6, 8) and valid.shape == (1, 1, 6, 8) and reason.shape == (1, 1, 6, 8)
        assert out.dtype == dtype and out.device.type == device.type

    def test_cardinality(self, dtype, backend):
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        src = plane_pair(H=6, W=8, B=2, dtype=dtype)
        dst = plane_pair(H=5, W=7, B=2, dtype=dtype)
        inp = {
            **{k: v for k, v in src.items() if k.startswith("src")},
            **{k: v for k, v in dst.items() if k.startswith("dst")},
        }
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert out.shape == (2, 3, 5, 7) and out.dtype == dtype
        assert valid.shape == (2, 1, 5, 7) and valid.dtype == torch.bool
        assert reason.shape == (2, 1, 5, 7) and reason.dtype == torch.uint8

    @pytest.mark.parametrize(
        "arg,bad,match",
        [
            ("src_color", torch.zeros(1, 3, 6), "src_color: expected 4-D"),
            ("src_color", torch.zeros(1, 4, 6, 8), r"src_color: expected shape \(B, 3, H, W\)"),
            ("src_depth", torch.zeros(1, 1, 5, 8), "src_depth"),
            ("src_normal", torch.zeros(1, 3, 6, 9), "src_normal"),
            ("dst_depth", torch.zeros(2, 1, 6, 8), "dst_depth"),
            ("dst_normal", torch.zeros(1, 2, 6, 8), "dst_normal"),
            ("src_K", torch.zeros(1, 4, 4), "src K"),
            ("dst_cam_from_world", torch.zeros(1, 3, 4), "dst cam_from_world"),
            ("src_color", torch.zeros(1, 3, 6, 8, dtype=torch.int32), "src_color: expected a floating-point"),
            ("dst_depth", "not a tensor", "dst_depth: expected a torch.Tensor"),
            ("src_depth", torch.zeros(1, 1, 6, 8, device="meta"), "one device"),
        ],
    )
    def test_exceptions(self, arg, bad, match):
        inp = plane_pair()
        inp[arg] = bad
        with pytest.raises((ShapeError, TypeError, ValueError), match=match):
            run(inp)

    def test_exceptions_options(self):
        with pytest.raises(ValueError, match="sampling"):
            run(plane_pair(), sampling="bicubic")
        with pytest.raises(ValueError, match="position_threshold"):
            StereoReprojection(-1e-3, 0.1)  # the one threshold rule: >= 0 (0 accepts only exact matches)
        with pytest.raises(ValueError, match="normal_threshold"):
            StereoReprojection(0.1, float("nan"))
        with pytest.raises(ValueError, match="sampling"):
            StereoReprojection(0.1, 0.1, sampling="cubic")

    def test_gradcheck(self):
        inp = plane_pair(H=4, W=5, shift_px=0.37, dtype=torch.float64)
        inp["src_depth"][..., 2] = 3.0  # a column of rejected taps
        inp["src_color"].requires_grad_(True)

        def f(c):
            return run({**inp, "src_color": c})[0]

        assert torch.autograd.gradcheck(f, (inp["src_color"],))

    def test_gradcheck_geometry(self):
        inp, *_ = scene_pair(H=6, W=8, dtype=torch.float64)
        depth = inp["dst_depth"].clone().requires_grad_(True)

        def f(d):
            return run({**inp, "dst_depth": d}, pos=10.0, nrm=2.0)[0]

        assert torch.autograd.gradcheck(f, (depth,), eps=1e-7, atol=1e-5)

    def test_gradcheck_soft_thresholds(self):
        inp, *_ = scene_pair(H=6, W=8, dtype=torch.float64, forward=0.3)
        thr = torch.tensor([0.05, 0.3], dtype=torch.float64, requires_grad=True)

        def f(t):
            return run(inp, pos=t[0], nrm=t[1], soft=True)[0]

        assert torch.autograd.gradcheck(f, (thr,))
        out = f(thr)
        out.sum().backward()
        assert thr.grad.abs().sum() > 0

    def test_module_equals_function(self, backend):
        inp, *_ = scene_pair()
        kws = [dict(), dict(sampling="nearest")] + ([dict(soft=True, temperature=0.2)] if backend != "native" else [])
        be = self.backend_arg(backend)
        for kw in kws:
            m = StereoReprojection(0.05, 0.2, backend=be, **kw)
            for a, b in zip(m(*[inp[a] for a in ARGS]), run(inp, 0.05, 0.2, backend=be, **kw)):
                assert torch.equal(a, b)

    @pytest.mark.onnx
    def test_onnx_parity(self, tmp_path):
        m = StereoReprojection(0.3, 0.3)  # ~2 pixel footprints at these small sizes
        for dims, ref, got in onnx_runs(m, tmp_path, "stereo"):
            assert dims["src_color"] == ["B", 3, "Hp", "Wp"] and dims["dst_depth"] == ["B", 1, "H", "W"]
            assert 0.5 < ref[1].float().mean() < 1.0  # realistic: some discards, mostly kept
            np.testing.assert_allclose(got[0], ref[0].numpy(), atol=1e-5, rtol=0)
            np.testing.assert_array_equal(got[1], ref[1].numpy())
            np.testing.assert_array_equal(got[2], ref[2].numpy())

    # --- hard cases -------------------------------------------------------------------------------------------
    def test_identity_warp_exact(self, dtype, backend):
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        inp, gd, *_ = scene_pair(dtype=dtype, baseline=0.065)
        dst, _ = camera_pair(36, 48)
        inp.update(
            src_color=gd.color.to(dtype),
            src_depth=gd.depth.to(dtype),
            src_normal=gd.normal.to(dtype),
            src_K=dst.K.to(dtype),
            src_cam_from_world=dst.cam_from_world.to(dtype),
        )
        for sampling in ("bilinear", "nearest"):
            out, valid, reason = run(inp, 1e-6, 1e-6, sampling=sampling, backend=self.backend_arg(backend))
            hit = torch.isfinite(inp["dst_depth"])
            assert torch.equal(out, torch.where(hit, inp["src_color"], 0.0))
            assert torch.equal(valid, hit) and int(reason[hit].max()) == 0

    @pytest.mark.parametrize("shift", [1, 3])
    @pytest.mark.parametrize("sampling", ["bilinear", "nearest"])
    def test_integer_shift_exact(self, shift, sampling, backend):
        inp = plane_pair(H=5, W=9, shift_px=shift)
        out, valid, reason = run(inp, sampling=sampling, backend=self.backend_arg(backend))
        assert torch.equal(out[..., shift:], inp["src_color"][..., :-shift])
        assert valid[..., shift:].all() and not valid[..., :shift].any()
        assert (reason[..., :shift] == Reason.OUT_OF_FRAME).all() and (reason[..., shift:] == 0).all()

    def test_no_surface_dst(self, backend):
        inp = plane_pair()
        for i, z in enumerate([float("inf"), float("nan"), 0.0, -1.0]):
            inp["dst_depth"][0, 0, i, 3] = z
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert not valid[0, 0, :4, 3].any() and (reason[0, 0, :4, 3] == Reason.NO_SURFACE_DST).all()
        assert (out[0, :, :4, 3] == 0).all() and torch.isfinite(out).all()

    def test_no_surface_src_taps(self, backend):
        inp = plane_pair(shift_px=1)
        inp["src_depth"][..., 4] = float("inf")
        inp["src_depth"][..., 2] = float("nan")
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert not valid[..., 5].any() and not valid[..., 3].any()
        assert (reason[..., 5] == Reason.NO_SURFACE_SRC).all() and (reason[..., 3] == Reason.NO_SURFACE_SRC).all()
        assert torch.isfinite(out).all()

    def test_points_behind_src_camera_rejected(self, backend):
        be = self.backend_arg(backend)
        inp = plane_pair()
        # Source camera turned around (180° about y): every destination point is behind it. A naive projection
        # would divide by a negative z and mirror the image back into the frame (kornia #4555).
        R = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))[None]
        inp["src_cam_from_world"] = R
        out, valid, reason = run(inp, pos=100.0, nrm=10.0, backend=be)
        assert not valid.any() and (reason == Reason.BEHIND_CAMERA).all() and (out == 0).all()
        # Source camera moved past the plane, still looking the same way: points behind it, also rejected.
        inp = plane_pair()
        inp["src_cam_from_world"] = inp["src_cam_from_world"].clone()
        inp["src_cam_from_world"][:, 2, 3] = -3.0
        _, valid, reason = run(inp, pos=100.0, nrm=10.0, backend=be)
        assert not valid.any() and (reason == Reason.BEHIND_CAMERA).all()

    @pytest.mark.parametrize("z", [0.0, 1e-12, -1e-12, float("inf"), -float("inf"), float("nan"), 1e30])
    def test_degenerate_depths(self, z, dtype, backend):
        """Forward on every backend; the gradient (torch) stays finite."""
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        inp = plane_pair(dtype=dtype)
        inp["dst_depth"][0, 0, 2, 3] = z
        inp["src_depth"][0, 0, 2, 2] = z
        with torch.no_grad():
            out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert torch.isfinite(out).all()
        r = Reason(int(reason[0, 0, 2, 3]))
        if not (z > 0 and math.isfinite(z)):
            assert r == Reason.NO_SURFACE_DST
        else:
            assert r in (Reason.OUT_OF_FRAME, Reason.BEHIND_CAMERA, Reason.POSITION)
        if backend == "torch":
            inp["src_color"].requires_grad_(True)
            out, *_ = run(inp)
            out.sum().backward()
            assert torch.isfinite(inp["src_color"].grad).all()

    def test_everything_out_of_frame(self, backend):
        inp = plane_pair()
        inp["src_cam_from_world"] = inp["src_cam_from_world"].clone()
        inp["src_cam_from_world"][:, 0, 3] = 100.0
        out, valid, reason = run(inp, pos=1e3, nrm=10.0, backend=self.backend_arg(backend))
        assert not valid.any() and (reason == Reason.OUT_OF_FRAME).all() and (out == 0).all()

    def test_nonfinite_radiance_in_rejected_or_zero_weight_tap_never_leaks(self, backend):
        inp = plane_pair(shift_px=1)
        # Column 7 is only read with zero bilinear weight (integer shift), column 2 is rejected by depth.
        inp["src_color"][..., 7] = float("nan")
        inp["src_color"][0, 0, :, 2] = float("inf")
        inp["src_depth"][..., 2] = 5.0
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert torch.isfinite(out).all()
        if backend == "torch":  # and the gradient
            inp["src_color"].requires_grad_(True)
            out, valid, reason = run(inp)
            assert torch.isfinite(out).all()
            out.sum().backward()
            assert torch.isfinite(inp["src_color"].grad).all()

    def test_nonfinite_radiance_in_accepted_tap_is_rejected(self, backend):
        # Policy: a NaN/Inf sample is discarded like an occluded one (reason NONFINITE); neighbours renormalise.
        be = self.backend_arg(backend)
        inp = plane_pair(shift_px=1)
        inp["src_color"][0, 1, 2, 4] = float("nan")
        out, valid, reason = run(inp, pos=0.1, backend=be)
        assert not valid[0, 0, 2, 5] and reason[0, 0, 2, 5] == Reason.NONFINITE
        assert torch.isfinite(out).all()
        inp = plane_pair(shift_px=0.5)
        inp["src_color"][0, 1, 2, 4] = float("inf")
        out, valid, reason = run(inp, pos=0.1, backend=be)
        assert valid[0, 0, 2, 5] and torch.isfinite(out).all()
        assert torch.allclose(out[0, :, 2, 5], inp["src_color"][0, :, 2, 5])  # only the finite tap remains

    def test_all_taps_rejected_finite_colour_and_gradient(self, backend):
        dtype = torch.float64 if backend != "native" else torch.float32
        inp = plane_pair(H=4, W=5, shift_px=0.5, dtype=dtype)
        inp["src_depth"] = inp["src_depth"] * 2  # every tap fails the position test
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert not valid.any() and (out == 0).all()
        assert ((reason == Reason.POSITION) | (reason == Reason.OUT_OF_FRAME)).all()
        if backend != "torch":
            return
        inp["src_color"].requires_grad_(True)
        out, valid, reason = run(inp)
        assert not valid.any() and (out == 0).all()
        out.sum().backward()
        assert torch.isfinite(inp["src_color"].grad).all() and (inp["src_color"].grad == 0).all()
        assert torch.autograd.gradcheck(lambda c: run({**inp, "src_color": c})[0], (inp["src_color"],))

    def test_grazing_angles(self, backend):
        # The camera looks almost along the floor: footprints stretch, taps 1 px apart are far apart in space.
        H, W = 24, 32
        K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]], dtype=torch.float64)
        head = look_at(
            torch.tensor([[0.0, 0.02, 0.0]], dtype=torch.float64),
            torch.tensor([[0.0, 0.0, -10.0]], dtype=torch.float64),
            torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64),
        )
        scene = default_scene()
        dst = PinholeCamera(K, head, H, W)
        moved = head.clone()
        moved[:, 0, 3] -= 0.01
        src = PinholeCamera(K, moved, H, W)
        gd, gs = raycast(dst, scene), raycast(src, scene)
        inp = dict(
            src_color=gs.color.float(),
            src_depth=gs.depth.float(),
            src_normal=gs.normal.float(),
            src_K=K,
            src_cam_from_world=moved,
            dst_depth=gd.depth.float(),
            dst_normal=gd.normal.float(),
            dst_K=K,
            dst_cam_from_world=head,
        )
        out, valid, reason = run(inp, pos=0.05, nrm=0.1, backend=self.backend_arg(backend))
        assert torch.isfinite(out).all() and valid.float().mean() > 0.5
        # wherever kept, the warped colour is close to the analytic colour
        err = (out - gd.color.float()).abs().amax(1, keepdim=True)[valid]
        assert err.median() < 0.02

    def test_far_from_origin_mm_threshold(self, backend):
        """A plane 1e4 units from the world origin, float64 cameras, float32 images, 1 mm threshold.

        Positions are compared in the source camera frame (camera matrices composed in float64), so precision
        depends on the distance to the camera, not to the origin: a 0.5 mm depth error is accepted and a 2 mm
        one rejected. (With float32 camera matrices a translation of 1e4 alone carries ~1e-3 of rounding.)
        """
        o = torch.tensor([12345.678, -9876.54321, 11111.1111], dtype=torch.float64)
        inp = plane_pair(H=6, W=9, shift_px=1.0)
        for k in ("src_cam_from_world", "dst_cam_from_world"):
            T = inp[k].double().clone()
            T[:, :3, 3] -= o  # camera centres moved by +o (rotation is identity)
            inp[k] = T
        be = self.backend_arg(backend)
        out, valid, reason = run(inp, pos=1e-3, nrm=0.01, backend=be)
        assert valid[..., 1:].all() and torch.allclose(out[..., 1:], inp["src_color"][..., :-1], atol=1e-6)
        near = dict(inp, src_depth=inp["src_depth"] + 5e-4)
        assert run(near, pos=1e-3, nrm=0.01, backend=be)[1][..., 1:].all()
        far = dict(inp, src_depth=inp["src_depth"] + 2e-3)
        _, valid, reason = run(far, pos=1e-3, nrm=0.01, backend=be)
        assert not valid.any() and (reason[..., 1:] == Reason.POSITION).all()

    @pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
    def test_half_precision(self, low, backend):
        if backend == "native" and low == torch.bfloat16:
            pytest.skip("native reads float16, not bfloat16")
        be = self.backend_arg(backend)
        inp, *_ = scene_pair()
        ref, vref, _ = run(inp, 0.05, 0.2, backend=be)
        half = {
            k: (v.to(low) if k not in ("src_K", "dst_K", "src_cam_from_world", "dst_cam_from_world") else v)
            for k, v in inp.items()
        }
        out, valid, reason = run(half, 0.05, 0.2, backend=be)
        assert out.dtype == low and torch.isfinite(out).all()
        agree = (valid == vref).float().mean()
        assert agree > 0.97
        both = (valid & vref).expand_as(ref)
        tol = 1e-2 if low == torch.float16 else 4e-2
        assert (out.float() - ref).abs()[both].max() < tol

    def test_per_item_cameras_in_batch(self, backend):
        be = self.backend_arg(backend)
        a, *_ = scene_pair(forward=0.0)
        b, *_ = scene_pair(forward=0.3, yaw=3.0)
        batch = {k: torch.cat([a[k], b[k]]) for k in ARGS}
        out, valid, reason = run(batch, 0.05, 0.2, backend=be)
        for i, single in enumerate([a, b]):
            o, v, r = run(single, 0.05, 0.2, backend=be)
            assert (
                torch.equal(out[i : i + 1], o)
                and torch.equal(valid[i : i + 1], v)
                and torch.equal(reason[i : i + 1], r)
            )

    def test_noncontiguous_and_channels_last(self, backend):
        be = self.backend_arg(backend)
        inp, *_ = scene_pair()
        ref = run(inp, 0.05, 0.2, backend=be)
        odd = dict(inp)
        for k in ("src_color", "src_normal", "dst_normal"):
            odd[k] = inp[k].contiguous(memory_format=torch.channels_last)
        odd["src_depth"] = inp["src_depth"].transpose(-1, -2).contiguous().transpose(-1, -2)  # non-contiguous
        assert not odd["src_depth"].is_contiguous()
        for a, b in zip(run(odd, 0.05, 0.2, backend=be), ref):
            assert torch.equal(a, b)

    @pytest.mark.parametrize("hw", [(1, 9), (7, 1), (1, 1)])
    def test_single_row_or_column(self, hw, backend):
        H, W = hw
        inp = plane_pair(H=H, W=W, shift_px=0.0 if W == 1 else 1.0)
        out, valid, reason = run(inp, backend=self.backend_arg(backend))
        assert out.shape == (1, 3, H, W) and torch.isfinite(out).all()
        if W > 1:
            assert torch.equal(out[..., 1:], inp["src_color"][..., :-1])
        else:
            assert torch.equal(out, inp["src_color"]) and valid.all()

    def test_nearest_vs_bilinear(self, backend):
        be = self.backend_arg(backend)
        inp = plane_pair(H=5, W=9, shift_px=1.25)
        near, vn, _ = run(inp, pos=0.1, sampling="nearest", backend=be)  # tap offsets up to 0.75 px = 0.023 units
        bil, vb, _ = run(inp, pos=0.1, sampling="bilinear", backend=be)
        # dst x reads u_s = x + 0.5 - 1.25: nearest pixel floor(u_s) = x - 1; bilinear mixes x-2 and x-1
        assert torch.equal(near[..., 2:], inp["src_color"][..., 1:-1])
        expected = 0.25 * inp["src_color"][..., :-2] + 0.75 * inp["src_color"][..., 1:-1]
        assert torch.allclose(bil[..., 2:], expected, atol=1e-6)

    def test_matches_grid_sample_when_all_accepted(self, backend):
        """Oracle: where all four taps are accepted, the warp equals F.grid_sample(bilinear, align_corners=False)
        at the source coordinates computed independently with PinholeCamera.project (float64 on torch; float32
        images on native, within float32 rounding)."""
        dtype = torch.float64 if backend != "native" else torch.float32
        inp, gd, gs, dst, src = scene_pair(H=36, W=48, forward=0.2, yaw=2.0, dtype=dtype, cam_dtype=torch.float64)
        out, valid, _ = run(inp, 1e9, 10.0, backend=self.backend_arg(backend))  # accept everything with a surface
        pts = dst.to(torch.float64).unproject(torch.where(torch.isfinite(gd.depth), gd.depth, 1.0))
        uv, z = src.to(torch.float64).project(pts)
        grid = torch.stack([uv[:, 0] / 48 * 2 - 1, uv[:, 1] / 36 * 2 - 1], -1)
        ref = F.grid_sample(inp["src_color"].double(), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        inner = (uv[:, 0:1] > 0.5) & (uv[:, 0:1] < 47.5) & (uv[:, 1:2] > 0.5) & (uv[:, 1:2] < 35.5)
        m = (inner & valid & torch.isfinite(gd.depth)).expand_as(out)
        assert m.float().mean() > 0.5
        assert torch.allclose(out[m].double(), ref[m], atol=1e-9 if dtype == torch.float64 else 1e-5)

    def test_kornia_oracle(self, backend):
        """kornia.geometry.depth.warp_frame_depth (warp only, integer pixel centres) on the same inputs."""
        kornia_depth = pytest.importorskip("kornia.geometry.depth")
        inp, gd, *_ = scene_pair(H=36, W=48, forward=0.1, yaw=1.0)
        out, valid, _ = run(inp, 1e9, 10.0, backend=self.backend_arg(backend))
        src_from_dst = inp["src_cam_from_world"] @ torch.linalg.inv(inp["dst_cam_from_world"])
        K_kornia = inp["dst_K"].clone()
        K_kornia[:, 0, 2] -= 0.5  # kornia puts pixel centres at integers
        K_kornia[:, 1, 2] -= 0.5
        depth = torch.where(torch.isfinite(inp["dst_depth"]), inp["dst_depth"], 1.0)
        ref = kornia_depth.warp_frame_depth(inp["src_color"], depth, src_from_dst, K_kornia)
        pts = PinholeCamera(inp["dst_K"], inp["dst_cam_from_world"], 36, 48).unproject(depth)
        uv, _ = PinholeCamera(inp["src_K"], inp["src_cam_from_world"], 36, 48).project(pts)
        inner = (uv[:, 0:1] > 1) & (uv[:, 0:1] < 47) & (uv[:, 1:2] > 1) & (uv[:, 1:2] < 35)
        m = (inner & valid).expand_as(out)
        assert m.float().mean() > 0.5
        assert (out[m] - ref[m]).abs().max() < 1e-4

    def test_analytic_scene_discards(self, backend):
        inp, gd, *_ = scene_pair(H=72, W=96, baseline=0.065)
        # ~2 pixel footprints at 5 units and 72 rows
        out, valid, reason = run(inp, 0.15, 0.2, backend=self.backend_arg(backend))
        counts = torch.bincount(reason.flatten().long(), minlength=len(Reason))
        assert 0.9 < valid.float().mean() < 1.0
        assert counts[Reason.OUT_OF_FRAME] > 0 and counts[Reason.POSITION] > 0  # frame edge and silhouettes
        err = (out - gd.color.float()).abs().amax(1, keepdim=True)[valid]
        assert err.median() < 0.01

    @settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(
        shift=st.floats(-3, 3),
        fwd=st.floats(-0.3, 0.3),
        yaw=st.floats(-4, 4),
        sampling=st.sampled_from(["bilinear", "nearest"]),
    )
    def test_property_convex_and_consistent(self, shift, fwd, yaw, sampling, backend):
        """(The backend fixture only switches the fast path off for ``torch``: the same for every example.)"""
        dtype = torch.float64 if backend != "native" else torch.float32
        dst, src = camera_pair(12, 16, baseline=0.065 + abs(shift) * 0.05, forward=fwd, yaw_deg=yaw)
        scene = default_scene()
        gd, gs = raycast(dst, scene), raycast(src, scene)
        col = torch.rand(1, 3, 12, 16, dtype=dtype)
        eps = 1e-12 if dtype == torch.float64 else 1e-6
        out, valid, reason, conf = backward_reproject(
            col,
            gs.depth.to(dtype),
            gs.normal.to(dtype),
            src.K,
            src.cam_from_world,
            gd.depth.to(dtype),
            gd.normal.to(dtype),
            dst.K,
            dst.cam_from_world,
            0.05,
            0.3,
            sampling,
            backend=self.backend_arg(backend),
        )
        assert torch.equal(valid, reason == 0)
        assert ((conf >= 0) & (conf <= 1 + eps)).all() and torch.equal(conf > 0, valid)
        lo, hi = col.amin(dim=(2, 3), keepdim=True), col.amax(dim=(2, 3), keepdim=True)
        v = valid.expand_as(out)
        assert ((out >= lo - eps) & (out <= hi + eps))[v].all()
        assert (out[~v] == 0).all()


def _sprinkle(inp, seed, frac=0.03):
    """Special values (NaN, ±inf, 0, negative, tiny, huge) at random pixels of every image input."""
    g = torch.Generator().manual_seed(seed)
    out = dict(inp)
    specials = torch.tensor([math.nan, math.inf, -math.inf, 0.0, -1.0, 1e-12, 1e30, -0.0])
    for k in ("src_color", "src_depth", "src_normal", "dst_depth", "dst_normal"):
        x = inp[k].clone()
        hit = torch.rand(x.shape, generator=g) < frac
        pick = torch.randint(len(specials), x.shape, generator=g)
        out[k] = torch.where(hit, specials[pick].to(x.dtype), x)
    return out


class TestFastPath(BaseTester):
    """Hard tests in inference take a fast path (padded source table, float accept tests, row blocks, reasons only
    for invalid pixels); its four outputs must equal the general path's exactly."""

    @staticmethod
    def _both(monkeypatch, args, block=None, **kw):
        from stereorepro.reproject import _fast, functional

        calls = []
        fast_impl = _fast.fast_reproject
        with monkeypatch.context() as m, torch.no_grad():
            m.setattr(_fast, "fast_reproject", lambda *a, **k: calls.append(1) or fast_impl(*a, **k))
            if block is not None:
                m.setattr(_fast, "FAST_BLOCK_PIXELS", block)
            fast = backward_reproject(*args, backend="torch", **kw)
        assert calls == [1], "the fast path was not taken"
        with monkeypatch.context() as m, torch.no_grad():
            m.setattr(functional, "inference_only", lambda inputs: False)
            general = backward_reproject(*args, backend="torch", **kw)
        assert calls == [1]
        return fast, general

    @staticmethod
    def _assert_same(fast, general):
        for f, g in zip(fast, general):
            assert f.dtype == g.dtype and f.shape == g.shape
            assert torch.equal(f, g), f"{int((f != g).sum())} of {f.numel()} differ"

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest"])
    @pytest.mark.parametrize("scene", [dict(), dict(forward=0.3, yaw=3.0), dict(forward=-0.2, yaw=-2.0, baseline=0.3)])
    def test_scenes(self, monkeypatch, dtype, sampling, scene):
        inp, *_ = scene_pair(H=37, W=50, dtype=dtype, **scene)
        for pos, nrm in [(0.05, 0.3), (1e-3, 1e-2), (3.0, 2.0)]:
            fast, general = self._both(
                monkeypatch,
                [inp[a] for a in ARGS],
                block=200,
                position_threshold=pos,
                normal_threshold=nrm,
                sampling=sampling,
            )  # 4 rows per block, then 1
            self._assert_same(fast, general)
            assert 0 < fast[1].float().mean() or pos < 0.01

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest"])
    @pytest.mark.parametrize("seed", range(4))
    def test_special_values(self, monkeypatch, sampling, seed):
        inp, *_ = scene_pair(H=24, W=32, forward=0.1, yaw=1.0)
        bad = _sprinkle(inp, seed)
        fast, general = self._both(
            monkeypatch,
            [bad[a] for a in ARGS],
            block=100,
            position_threshold=0.1,
            normal_threshold=1.5,
            sampling=sampling,
        )
        self._assert_same(fast, general)
        assert torch.isfinite(fast[0]).all()
        assert len(fast[2].unique()) >= 5  # kept, no surface (dst), behind, position, normal, non-finite, ...

    @pytest.mark.parametrize("shift", [0.0, 1.0, 1.25, -2.5])
    def test_rectified_planes(self, monkeypatch, shift):
        """fy = 0 everywhere: the fast path reads the y0 taps only."""
        from stereorepro.reproject import _fast

        inp = plane_pair(H=9, W=11, shift_px=shift, B=2)
        inp["src_depth"][0, 0, :, 4] = 2.5  # occluder: POSITION discards
        taps = []
        accept = _fast.fast_accept
        monkeypatch.setattr(_fast, "fast_accept", lambda t, *a: taps.append(t.shape[2:4]) or accept(t, *a))
        fast, general = self._both(
            monkeypatch, [inp[a] for a in ARGS], block=30, position_threshold=0.01, normal_threshold=0.1
        )
        self._assert_same(fast, general)
        assert set(taps) == {(1, 2)}

    def test_batch_sizes_and_layouts(self, monkeypatch):
        a, *_ = scene_pair(H=20, W=30, forward=0.0)
        b, *_ = scene_pair(H=20, W=30, forward=0.3, yaw=3.0)
        batch = {k: torch.cat([a[k], b[k]]) for k in ARGS}
        for k in ("src_color", "src_normal", "dst_normal"):
            batch[k] = batch[k].contiguous(memory_format=torch.channels_last)
        batch["dst_depth"] = batch["dst_depth"].transpose(-1, -2).contiguous().transpose(-1, -2)
        for block in (None, 1, 100):
            fast, general = self._both(
                monkeypatch, [batch[k] for k in ARGS], block=block, position_threshold=0.05, normal_threshold=0.2
            )
            self._assert_same(fast, general)

    @pytest.mark.parametrize("hw", [(1, 9), (7, 1), (1, 1)])
    def test_single_row_or_column(self, monkeypatch, hw):
        src = plane_pair(H=5, W=6, shift_px=0.5)
        dst = plane_pair(H=hw[0], W=hw[1])
        args = [src[a] if a.startswith("src") else dst[a] for a in ARGS]
        fast, general = self._both(monkeypatch, args, block=1, position_threshold=0.05, normal_threshold=0.2)
        self._assert_same(fast, general)

    @pytest.mark.parametrize("low", [torch.float16, torch.bfloat16])
    def test_half_precision(self, monkeypatch, low):
        inp, *_ = scene_pair(H=16, W=20, forward=0.1)
        half = {k: (v.to(low) if v.dim() == 4 else v) for k, v in inp.items()}
        fast, general = self._both(monkeypatch, [half[a] for a in ARGS], position_threshold=0.05, normal_threshold=0.2)
        self._assert_same(fast, general)
        assert fast[0].dtype == low

    def test_extra_channels_and_tensor_thresholds(self, monkeypatch):
        inp, *_ = scene_pair(H=18, W=22, forward=0.2, dtype=torch.float64)
        values = torch.cat([inp["src_color"], torch.rand(1, 2, 18, 22, dtype=torch.float64)], 1)
        args = [values] + [inp[a] for a in ARGS[1:]]
        fast, general = self._both(
            monkeypatch,
            args,
            block=50,
            position_threshold=torch.tensor(0.05),
            normal_threshold=torch.tensor(0.3, dtype=torch.float64),
        )
        self._assert_same(fast, general)

    def test_float64_table_indices(self, monkeypatch):
        """Source tables of 2^24 pixels or more index in float64 (forced here on a small image)."""
        from stereorepro.reproject import _fast

        monkeypatch.setattr(_fast, "_F32_EXACT", 100)
        inp, *_ = scene_pair(H=12, W=16, forward=0.2)
        fast, general = self._both(
            monkeypatch, [inp[a] for a in ARGS], block=40, position_threshold=0.05, normal_threshold=0.2
        )
        self._assert_same(fast, general)

    def test_not_taken(self, monkeypatch):
        """Gradients, soft tests and thresholds whose square is not finite take the general path."""
        from stereorepro.reproject import _fast

        monkeypatch.setattr(_fast, "fast_reproject", None)  # would raise if called
        inp, *_ = scene_pair(H=8, W=10)
        run(inp, 1e20, 0.3)
        run(inp, 0.05, 0.3, soft=True)
        with torch.enable_grad():
            run({**inp, "src_color": inp["src_color"].clone().requires_grad_(True)}, 0.05, 0.3)

    def test_temporal(self, monkeypatch):
        from stereorepro.reproject import _fast, functional

        m = TemporalReprojection(0.05, 0.3, backend="torch")
        args = example_inputs(m, batch=2, height=21, width=33, seed=5)
        calls = []
        fast_impl = _fast.fast_reproject
        with monkeypatch.context() as mp:
            mp.setattr(_fast, "fast_reproject", lambda *a, **k: calls.append(1) or fast_impl(*a, **k))
            mp.setattr(_fast, "FAST_BLOCK_PIXELS", 70)
            fast = m(*args)
        with monkeypatch.context() as mp, torch.no_grad():
            mp.setattr(functional, "inference_only", lambda inputs: False)
            general = m(*args)
        assert calls == [1]
        self._assert_same(fast, general)


class TestComposeCameras(BaseTester):
    """Camera composition: numpy for plain CPU inference, torch ops under autograd / tracing; the same matrices."""

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_numpy_equals_torch(self, seed):

        m = StereoReprojection(0.05, 0.3)
        a = dict(zip(m.input_names, example_inputs(m, batch=4, height=8, width=8, seed=seed)))
        cams = [a["src_K"].clone(), a["src_cam_from_world"], a["dst_K"], a["dst_cam_from_world"]]
        cams[0][:, 0, 1] = 0.37 * (seed + 1)  # skew
        for dtype in (torch.float32, torch.float64):
            fast = compose_warp(*cams, dtype)
            graph = compose_warp(*(c.clone().requires_grad_() for c in cams), dtype)  # torch ops
            for f, g in zip(fast, graph):
                assert f.dtype == dtype and f.shape == g.shape
                if dtype == torch.float32:
                    assert torch.equal(f, g.detach())
                else:  # float64 matmuls may round the last bit differently
                    assert torch.allclose(f, g.detach(), rtol=1e-14, atol=1e-14)


class TestSoftReprojection(BaseTester):
    def test_low_temperature_approaches_hard(self):
        inp, *_ = scene_pair(forward=0.2)
        hard, valid, _ = run(inp, 0.05, 0.3)
        soft, valid_s, _ = run(inp, 0.05, 0.3, soft=True, temperature=1e-4)
        assert torch.equal(valid, valid_s)
        assert (soft - hard).abs()[valid.expand_as(hard)].median() < 1e-5

    def test_gradients_finite_when_nearly_rejected(self):
        """Soft weights of ~1e-30 (far beyond the thresholds) must not give inf/NaN gradients (num/den²)."""
        inp, *_ = scene_pair(forward=0.3, yaw=2.0)
        for dt in (torch.float32, torch.float64):
            thr = torch.tensor([2e-3, 1e-3], dtype=dt, requires_grad=True)
            x = {k: (v.to(dt) if v.is_floating_point() else v) for k, v in inp.items()}
            x["src_color"] = x["src_color"].clone().requires_grad_(True)
            out, *_ = run(x, pos=thr[0], nrm=thr[1], soft=True, temperature=0.05)
            (out.square().mean()).backward()
            assert torch.isfinite(out).all() and torch.isfinite(thr.grad).all()
            assert torch.isfinite(x["src_color"].grad).all()
        m = TemporalReprojection(1e-3, 1e-3, soft=True, temperature=0.05)
        t = dict(zip(TemporalReprojection.input_names, example_inputs(m, height=24, width=32)))
        t["current_color"].requires_grad_(True)
        color, n, _ = m(*t.values())
        (color.square().mean() + n.mean()).backward()
        for p in m.parameters():
            assert torch.isfinite(p.grad).all()

    def test_learnable_thresholds(self):
        m = StereoReprojection(0.05, 0.3, soft=True)
        assert {n for n, _ in m.named_parameters()} == {"position_threshold", "normal_threshold"}
        inp, gd, *_ = scene_pair(forward=0.2)
        out, *_ = m(*[inp[a] for a in ARGS])
        ((out - gd.color.float()) ** 2).mean().backward()
        assert m.position_threshold.grad is not None and torch.isfinite(m.position_threshold.grad)


class TestTemporalReproject(BaseTester):
    NAMES = TemporalReprojection.input_names

    def _static(self, H=8, W=10, dtype=torch.float32, n=3.0, seed=0):
        inp = plane_pair(H=H, W=W, shift_px=0.0, dtype=dtype, seed=seed)
        g = torch.Generator().manual_seed(seed + 1)
        return dict(
            current_color=torch.rand(1, 3, H, W, generator=g, dtype=dtype),
            depth=inp["dst_depth"],
            normal=inp["dst_normal"],
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=inp["src_color"],
            history_len=torch.full((1, 1, H, W), n, dtype=dtype),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"],
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )

    def _run(self, inp, pos=0.01, nrm=0.1, backend=None, **kw):
        """temporal_reproject on ``inp``, on the ``backend`` fixture's implementation (None: ``auto``)."""
        be = "auto" if backend is None else self.backend_arg(backend)
        return temporal_reproject(*[inp[n] for n in self.NAMES], pos, nrm, backend=be, **kw)

    def test_smoke(self, device, dtype, backend):
        self.skip_unless_runs(backend, dtype, device)
        inp = {k: v.to(device) for k, v in self._static(dtype=dtype).items()}
        color, n, valid = self._run(inp, backend=backend)
        assert color.shape == (1, 3, 8, 10) and n.shape == (1, 1, 8, 10) and valid.all()
        assert color.dtype == dtype and color.device.type == device.type

    def test_cardinality(self, dtype, backend):
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        inp = self._static(dtype=dtype)
        inp = {k: torch.cat([v, v]) for k, v in inp.items()}
        color, n, valid = self._run(inp, backend=backend)
        assert color.shape == (2, 3, 8, 10) and color.dtype == dtype
        assert n.shape == (2, 1, 8, 10) and valid.dtype == torch.bool

    @pytest.mark.parametrize(
        "arg,bad,match",
        [
            ("current_color", torch.zeros(1, 3, 8), "current_color"),
            ("history_color", torch.zeros(2, 3, 8, 10), "history_color"),
            ("history_len", torch.zeros(1, 2, 8, 10), "history_len"),
            ("history_len", torch.zeros(1, 1, 8, 10, dtype=torch.int64), "history_len: expected a floating-point"),
            ("prev_K", torch.zeros(1, 3), "prev K"),
        ],
    )
    def test_exceptions(self, arg, bad, match):
        inp = self._static()
        inp[arg] = bad
        with pytest.raises((ShapeError, TypeError, ValueError), match=match):
            self._run(inp)
        with pytest.raises(ValueError, match="alpha"):
            TemporalReprojection(0.1, 0.1, alpha=0.0)

    def test_gradcheck(self):
        inp = self._static(H=4, W=5, dtype=torch.float64)
        inp["prev_depth"] = inp["prev_depth"].clone()
        inp["prev_depth"][..., 1] = 3.0  # rejected column: restarts from current

        def f(cur, hist):
            return self._run({**inp, "current_color": cur, "history_color": hist})[0]

        args = (inp["current_color"].requires_grad_(True), inp["history_color"].requires_grad_(True))
        assert torch.autograd.gradcheck(f, args)

    def test_gradcheck_soft_alpha_thresholds(self):
        inp, *_ = scene_pair(H=6, W=8, dtype=torch.float64, forward=0.3)
        t = dict(
            current_color=inp["dst_depth"].new_ones(1, 3, 6, 8) * 0.3,
            depth=inp["dst_depth"],
            normal=inp["dst_normal"],
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=inp["src_color"],
            history_len=torch.full_like(inp["src_depth"], 10.0),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"],
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )
        p = torch.tensor([0.05, 0.3, 0.2], dtype=torch.float64, requires_grad=True)

        def f(p):
            return self._run(t, p[0], p[1], alpha=p[2], soft=True)[0]

        assert torch.autograd.gradcheck(f, (p,))

    def test_module_equals_function(self, backend):
        inp = self._static()
        kws = [dict(), dict(alpha=0.5, warmup=False)] + ([dict(soft=True)] if backend != "native" else [])
        for kw in kws:
            m = TemporalReprojection(0.01, 0.1, backend=self.backend_arg(backend), **kw)
            for a, b in zip(m(*[inp[n] for n in self.NAMES]), self._run(inp, backend=backend, **kw)):
                assert torch.equal(a, b)

    @pytest.mark.onnx
    def test_onnx_parity(self, tmp_path):
        m = TemporalReprojection(0.3, 0.3)
        for dims, ref, got in onnx_runs(m, tmp_path, "temporal"):
            assert dims["current_color"] == ["B", 3, "H", "W"] and dims["history_color"] == ["B", 3, "Hp", "Wp"]
            assert 0.5 < ref[2].float().mean() < 1.0
            np.testing.assert_allclose(got[0], ref[0].numpy(), atol=1e-5, rtol=0)
            np.testing.assert_allclose(got[1], ref[1].numpy(), atol=1e-5, rtol=0)
            np.testing.assert_array_equal(got[2], ref[2].numpy())

    # --- hard cases -------------------------------------------------------------------------------------------
    @pytest.mark.parametrize("case", ["scene", "special", "batch_channels", "turned"])
    @pytest.mark.parametrize(
        "kw", [dict(), dict(alpha=0.5, warmup=False), dict(max_history=4.0), dict(sampling="nearest")], ids=str
    )
    def test_matches_reference(self, case, kw, backend):
        """Each backend against the per-pixel reference (tests/reproject/reference.py): the warp of [history
        colour, history length] (a non-finite length discards its tap like a non-finite colour), then the blend;
        random lengths with negative and NaN ones, on the tiny cases of test_ops.py."""
        from test_ops import REFERENCE_CASES, assert_matches_reference

        args, pos, nrm, sampling = REFERENCE_CASES[case]
        sampling = kw.get("sampling", sampling)
        src_color, src_depth, src_normal, src_K, src_T, depth, normal, K, T = args
        B, _, H, W = depth.shape
        g = torch.Generator().manual_seed(len(case))
        history = src_color[:, :3]
        n = torch.randint(-2, 30, (B, 1) + src_depth.shape[-2:], generator=g).float()
        n.view(-1)[::7] = float("nan")
        current = torch.rand(B, 3, H, W, generator=g)
        with torch.no_grad():
            color, n_out, valid, reason = temporal_reproject(
                current,
                depth,
                normal,
                K,
                T,
                history,
                n,
                src_depth,
                src_normal,
                src_K,
                src_T,
                pos,
                nrm,
                return_reason=True,
                backend=self.backend_arg(backend),
                **kw,
            )
        warped, r_valid, r_reason, conf, margin = reference_backward_reproject(
            torch.cat([history, n], 1), src_depth, src_normal, src_K, src_T, depth, normal, K, T, pos, nrm, sampling
        )
        assert_matches_reference(
            (torch.cat([color, n_out], 1), valid, reason, valid.double()),
            (
                np.concatenate(
                    reference_temporal_blend(
                        current,
                        warped[:, :3],
                        warped[:, 3:],
                        r_valid,
                        **{k: v for k, v in kw.items() if k != "sampling"},
                    ),
                    1,
                ),
                r_valid,
                r_reason,
                r_valid.astype(np.float64),
                margin,
            ),
            f"{backend} {case} {kw}",
        )

    def test_first_frame_returns_current(self, backend):
        inp = self._static(n=0.0)
        inp["history_color"] = torch.full_like(inp["history_color"], float("nan"))
        color, n, valid = self._run(inp, backend=backend)
        assert torch.equal(color, inp["current_color"]) and (n == 1).all()

    def test_alpha_one_returns_current(self, backend):
        inp = self._static(n=50.0)
        color, n, _ = self._run(inp, alpha=1.0, backend=backend)
        assert torch.equal(color, inp["current_color"])

    def test_warmup_is_running_mean_then_ema(self, backend):
        """Static camera: with warm-up and alpha → 0 the output is the exact running mean of the frames."""
        inp = self._static(n=0.0)
        frames = [torch.rand(1, 3, 8, 10, generator=torch.Generator().manual_seed(i)) for i in range(6)]
        hist, n = inp["history_color"], inp["history_len"]
        for f in frames:
            hist, n, _ = self._run(
                {**inp, "current_color": f, "history_color": hist, "history_len": n}, alpha=1e-9, backend=backend
            )
        assert torch.allclose(hist, torch.stack(frames).mean(0), atol=1e-6) and (n == 6).all()
        # with alpha = 0.2 the weight stops falling at 0.2 after 4 frames: a fixed EMA from then on
        hist, n = inp["history_color"], inp["history_len"]
        ref = None
        for i, f in enumerate(frames):
            hist, n, _ = self._run(
                {**inp, "current_color": f, "history_color": hist, "history_len": n}, alpha=0.2, backend=backend
            )
            a = max(1.0 / (i + 1), 0.2)
            ref = f if ref is None else (1 - a) * ref + a * f
        assert torch.allclose(hist, ref, atol=1e-6)

    def test_fixed_ema_without_warmup(self, backend):
        inp = self._static(n=0.0)
        color, n, _ = self._run(inp, alpha=0.2, warmup=False, backend=backend)
        assert torch.allclose(color, 0.8 * inp["history_color"] + 0.2 * inp["current_color"])

    def test_history_len_at_cap(self, backend):
        inp = self._static(n=255.0)
        color, n, _ = self._run(inp, max_history=255.0, backend=backend)
        assert (n == 255).all()
        inp = self._static(n=1e9)
        color, n, _ = self._run(inp, alpha=0.0 + 1e-9, max_history=255.0, backend=backend)
        assert (n == 255).all() and torch.isfinite(color).all()

    def test_discarded_pixels_restart(self, backend):
        inp = self._static(n=7.0)
        inp["prev_depth"] = inp["prev_depth"].clone()
        inp["prev_depth"][..., :3] = 4.0  # occluded: history discarded
        color, n, valid = self._run(inp, backend=backend)
        assert not valid[..., :3].any() and valid[..., 3:].all()
        assert torch.equal(color[..., :3], inp["current_color"][..., :3]) and (n[..., :3] == 1).all()
        assert (n[..., 3:] == 8).all()

    def test_nonfinite_history_does_not_leak(self, backend):
        inp = self._static(n=4.0)
        inp["history_color"] = inp["history_color"].clone()
        inp["history_color"][..., 2, 2] = float("nan")
        inp["history_color"][..., 5, 5] = float("inf")
        color, n, valid = self._run(inp, backend=backend)
        assert torch.isfinite(color).all() and torch.isfinite(n).all()
        assert not valid[0, 0, 2, 2] and not valid[0, 0, 5, 5]


class TestReasonToRgb(BaseTester):
    def test_colors(self):
        reason = torch.tensor([[[[0, 3, 5, 6]]]], dtype=torch.uint8)
        rgb = reason_to_rgb(reason)
        assert rgb.shape == (1, 3, 1, 4)
        assert rgb[0, :, 0, 1].tolist() == [1, 0, 0] and rgb[0, :, 0, 2].tolist() == [0, 1, 0]
        assert rgb[0, :, 0, 3].tolist() == [0, 1, 1] and rgb[0, :, 0, 0].tolist() == [0, 0, 0]
