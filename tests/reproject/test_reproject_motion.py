"""Temporal reprojection driven by motion vectors (moving objects): the op, its module, ONNX, and the hard cases."""

from __future__ import annotations

import math

import pytest
import torch

from base import BaseTester
from stereorepro import SpatiotemporalReprojection, TemporalReprojection, camera_motion, intrinsics_from_fov
from stereorepro.camera import world_motion_from_view_z
from stereorepro.errors import ShapeError
from stereorepro._testing import example_inputs
from stereorepro.reproject import Reason
from stereorepro.reproject.functional import backward_reproject, temporal_reproject

H, W = 16, 24
SHIFT = 3  # pixels the object moved to the right between the frames
THR = (0.05, 0.25)


def moving_object(dtype=torch.float64):
    """Two frames of one static camera: a background plane at z = 4 and an object patch at z = 2 that moved
    SHIFT pixels right. Returns (current args of temporal_reproject, motion, motion_world, masks)."""
    K = intrinsics_from_fov(60.0, W, H, dtype=dtype)
    T = torch.eye(4, dtype=dtype)[None]
    fx = float(K[0, 0, 0])
    g = torch.Generator().manual_seed(0)
    rows, cols = slice(4, 11), slice(6, 13)
    prev_depth = torch.full((1, 1, H, W), 4.0, dtype=dtype)
    prev_depth[..., rows, cols] = 2.0
    depth = torch.full((1, 1, H, W), 4.0, dtype=dtype)
    depth[..., rows, slice(6 + SHIFT, 13 + SHIFT)] = 2.0
    normal = torch.zeros(1, 3, H, W, dtype=dtype)
    normal[:, 2] = -1.0
    history = torch.rand(1, 3, H, W, generator=g, dtype=dtype)
    current = torch.rand(1, 3, H, W, generator=g, dtype=dtype)
    obj = depth == 2.0
    motion = torch.zeros(1, 2, H, W, dtype=dtype)
    motion[:, 0:1][obj] = -SHIFT
    motion_world = torch.zeros(1, 3, H, W, dtype=dtype)
    motion_world[:, 0:1][obj] = -SHIFT * 2.0 / fx  # the object's world motion at z = 2
    disoccluded = torch.zeros_like(obj)
    disoccluded[..., rows, slice(6, 6 + SHIFT)] = True
    args = (current, depth, normal, K, T, history, torch.full_like(depth, 4.0), prev_depth, normal, K, T)
    return args, motion, motion_world, obj, disoccluded


class TestMotionReproject(BaseTester):
    def test_smoke(self, device, dtype, backend):
        """Motion vectors run on every backend (torch's general and fast paths, native: float32 on the CPU)."""
        self.skip_unless_runs(backend, dtype, device)
        args, motion, mw, obj, dis = moving_object(dtype)
        args, motion, mw = [a.to(device) for a in args], motion.to(device), mw.to(device)
        with torch.no_grad():
            c, n, valid, reason = temporal_reproject(
                *args, *THR, motion=motion, motion_world=mw, return_reason=True, backend=self.backend_arg(backend)
            )
        assert c.shape == (1, 3, H, W) and n.shape == valid.shape == reason.shape == (1, 1, H, W)
        assert c.dtype == dtype and c.device.type == device.type

    def test_moving_object_keeps_its_history(self):
        args, motion, mw, obj, dis = moving_object()
        _, _, cam_valid, cam_reason = temporal_reproject(*args, *THR, return_reason=True)
        moved_in = obj & (args[7] != 2.0)  # object pixels where the previous frame shows the background
        assert not bool(cam_valid[moved_in].any()) and bool((cam_reason[moved_in] == Reason.POSITION).all())
        warped, valid, reason, _ = backward_reproject(
            args[5],
            args[7],
            args[8],
            args[9],
            args[10],
            args[1],
            args[2],
            args[3],
            args[4],
            *THR,
            motion=motion,
            motion_world=mw,
        )
        assert bool(valid[obj].all())
        expected = torch.roll(args[5], SHIFT, dims=-1)  # the history, moved with the object
        assert torch.equal(warped[obj.expand_as(warped)], expected[obj.expand_as(expected)])
        c, n, valid_t, _ = temporal_reproject(*args, *THR, motion=motion, motion_world=mw, return_reason=True)
        assert torch.equal(valid_t, valid) and bool((n[obj] == 5).all())

    def test_disocclusion_still_rejected(self):
        args, motion, mw, obj, dis = moving_object()
        _, _, valid, reason = temporal_reproject(*args, *THR, motion=motion, motion_world=mw, return_reason=True)
        assert not bool(valid[dis].any()) and bool((reason[dis] == Reason.POSITION).all())
        background = ~obj & ~dis
        assert bool(valid[background].all())

    def test_without_world_motion_the_object_fails_the_position_test(self):
        args, motion, mw, obj, dis = moving_object()
        _, _, valid, reason = temporal_reproject(*args, *THR, motion=motion, return_reason=True)
        assert not bool(valid[obj].any()) and bool((reason[obj] == Reason.POSITION).all())

    @pytest.mark.parametrize("dtype, colour_tol", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
    def test_static_scene_equals_camera_warp(self, dtype, colour_tol, backend):
        """On static geometry, motion vectors from the cameras give the camera warp's masks exactly (the camera
        warp on each backend); the colour within 1e-9 in float64, within one ulp of the pixel coordinate times the
        contrast in float32 (u is formed as pixel + motion instead of by the projection: not bit-exact)."""
        self.skip_unless_runs(backend, dtype, torch.device("cpu"))
        m = TemporalReprojection(*THR, backend="torch")
        x = example_inputs(m, height=36, width=48, dtype=dtype)
        depth, K, T, pK, pT = x[1], x[3], x[4], x[9], x[10]
        motion = camera_motion(depth, K, T, pK, pT)
        with torch.no_grad():
            ref = temporal_reproject(*x, *THR, return_reason=True, backend=self.backend_arg(backend))
        got = temporal_reproject(*x, *THR, motion=motion, motion_world=torch.zeros_like(x[2]), return_reason=True)
        assert torch.equal(got[2], ref[2]) and torch.equal(got[3], ref[3]) and bool(ref[2].float().mean() > 0.3)
        assert float((got[0] - ref[0]).abs().max()) <= colour_tol
        assert float((got[1] - ref[1]).abs().max()) <= 1e-5

    def test_exceptions(self):
        args, motion, mw, obj, dis = moving_object()
        with pytest.raises(ValueError, match="motion_world needs motion"):
            temporal_reproject(*args, *THR, motion_world=mw)
        with pytest.raises(ShapeError, match="motion"):
            temporal_reproject(*args, *THR, motion=motion[:, :1])
        with pytest.raises(ShapeError, match="motion_world"):
            temporal_reproject(*args, *THR, motion=motion, motion_world=mw[..., :-1])
        with pytest.raises(TypeError, match="floating"):
            temporal_reproject(*args, *THR, motion=motion.long())
        f32 = [a.float() for a in args]
        with pytest.raises(RuntimeError, match="float32 or float16"):  # float64 motion: torch only
            with torch.no_grad():
                temporal_reproject(*f32, *THR, motion=motion.double(), backend="native")
        with pytest.raises(TypeError, match="needs `motion`"):
            TemporalReprojection(*THR, motion_vectors=True)(*args)

    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e30, -1e30])
    def test_hard_cases_nonfinite_and_huge_motion(self, bad):
        args, motion, mw, obj, dis = moving_object()
        m = motion.clone()
        m[..., 5, :] = bad
        c, n, valid, reason = temporal_reproject(*args, *THR, motion=m, motion_world=mw, return_reason=True)
        assert bool(torch.isfinite(c).all()) and bool(torch.isfinite(n).all())
        assert not bool(valid[..., 5, :].any()) and bool((reason[..., 5, :] == Reason.OUT_OF_FRAME).all())
        w = mw.clone()
        w[..., 6, :] = bad if not math.isfinite(bad) else w[..., 6, :]
        c, _, valid, reason = temporal_reproject(*args, *THR, motion=motion, motion_world=w, return_reason=True)
        if not math.isfinite(bad):
            assert bool((reason[..., 6, :] == Reason.OUT_OF_FRAME).all())
        assert bool(torch.isfinite(c).all())

    def test_hard_cases_out_of_frame_and_behind_a_surface(self):
        args, motion, mw, obj, dis = moving_object()
        m = motion.clone()
        m[:, 0, :, :4] = -10.0  # the left columns point out of the previous frame
        _, _, valid, reason = temporal_reproject(*args, *THR, motion=m, motion_world=mw, return_reason=True)
        assert bool((reason[..., :4] == Reason.OUT_OF_FRAME).all())
        # background pixels whose motion points onto the object: behind that surface, rejected by position
        m = motion.clone()
        m[:, 0, 2, 20] = 0.0
        m[:, 0:2, 12, 20] = torch.tensor([-12.0, -5.0], dtype=m.dtype).view(1, 2)  # onto the object at (7, 8)
        _, _, valid, reason = temporal_reproject(*args, *THR, motion=m, motion_world=mw, return_reason=True)
        assert not bool(valid[0, 0, 12, 20]) and int(reason[0, 0, 12, 20]) == Reason.POSITION
        # and the motion pointing behind the previous camera is not projected
        w = mw.clone()
        w[:, 2, 2, 2] = -10.0
        _, _, valid, reason = temporal_reproject(*args, *THR, motion=motion, motion_world=w, return_reason=True)
        assert int(reason[0, 0, 2, 2]) == Reason.BEHIND_CAMERA

    def test_gradcheck(self):
        args, motion, mw, obj, dis = moving_object(torch.float64)
        small = [a[..., :8, 4:14].contiguous() if a.dim() == 4 else a for a in args]
        m = (motion[..., :8, 4:14] + 0.3).contiguous().requires_grad_(True)  # fractional: away from tap edges
        hist = small[5].clone().requires_grad_(True)
        zero = torch.zeros_like(mw[..., :8, 4:14])
        K = intrinsics_from_fov(60.0, 10, 8, dtype=torch.float64)
        small[3] = small[9] = K

        def f(h, mo):
            a = list(small)
            a[5] = h
            return temporal_reproject(*a, 1e3, 2.0, motion=mo, motion_world=zero)[0]

        assert torch.autograd.gradcheck(f, (hist, m), eps=1e-6, atol=1e-5)

    def test_module_equals_function(self):
        args, motion, mw, obj, dis = moving_object()
        mod = TemporalReprojection(*THR, motion_vectors=True)
        assert mod.input_names[-2:] == ["motion", "motion_world"]
        ref = temporal_reproject(
            *args, mod.position_threshold, mod.normal_threshold, mod.alpha, motion=motion, motion_world=mw
        )
        for g, r in zip(mod(*args, motion, mw), ref):
            assert torch.equal(g, r)

    def test_driver_and_temporal_step(self):
        args, motion, mw, obj, dis = moving_object(torch.float32)
        st = SpatiotemporalReprojection(*THR, stereo=False)
        cur, depth, normal, K, T, hist, n, pdepth, pnormal, pK, pT = args
        st.right(hist, pdepth, pnormal, pK, pT)
        out = st.right(cur, depth, normal, K, T, motion, mw)
        ref = temporal_reproject(
            cur,
            depth,
            normal,
            K,
            T,
            hist,
            torch.ones_like(n),
            pdepth,
            pnormal,
            pK,
            pT,
            *THR,
            motion=motion,
            motion_world=mw,
        )[0]
        assert torch.equal(out, ref) and bool(st.right_valid[obj].all())

    @pytest.mark.onnx
    def test_onnx_parity(self, tmp_path):
        import onnxruntime as ort

        from stereorepro import export_onnx
        from stereorepro.io.onnx import onnx_input_dims

        mod = TemporalReprojection(*THR, motion_vectors=True, backend="torch")
        p = export_onnx(mod, tmp_path / "t.onnx")
        dims = onnx_input_dims(p)
        assert dims["motion"] == ["B", 2, "H", "W"] and dims["motion_world"] == ["B", 3, "H", "W"]
        sess = ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
        args, motion, mw, obj, dis = moving_object(torch.float32)
        inputs = list(args) + [motion, mw]
        got = sess.run(None, {n: a.numpy() for n, a in zip(mod.input_names, inputs)})
        with torch.no_grad():
            ref = mod(*inputs)
        assert torch.equal(torch.from_numpy(got[2]), ref[2]) and bool(ref[2][obj].all())
        assert float((torch.from_numpy(got[0]) - ref[0]).abs().max()) <= 1e-5
        assert float((torch.from_numpy(got[1]) - ref[1]).abs().max()) <= 1e-5


def _rotation_about(axis: torch.Tensor, angle: float) -> torch.Tensor:
    a = axis / axis.norm()
    k = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


class TestWorldMotionFromViewZ(BaseTester):
    """2.5D motion (screen motion + view-z delta) converted into world motion at the boundary."""

    @staticmethod
    def rigid_case(B=2, H=18, W=26):
        """A realistic frame pair (moving cameras) whose geometry also moved rigidly, P_prev = R·P + t: the true
        world motion and the 2.5D motion a renderer would write for it."""
        m = TemporalReprojection(*THR, motion_vectors=True, backend="torch")
        x = example_inputs(m, batch=B, height=H, width=W, dtype=torch.float64)
        depth, K, T, pK, pT = x[1], x[3], x[4], x[9], x[10]
        from stereorepro.camera import invert_rigid, project, unproject

        R = _rotation_about(torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64), 0.05)
        t = torch.tensor([0.04, -0.02, 0.1], dtype=torch.float64).view(1, 3, 1)
        p_cam = unproject(depth, K).reshape(B, 3, -1)
        wfc = invert_rigid(T)
        P = wfc[:, :3, :3] @ p_cam + wfc[:, :3, 3:]
        P_prev = R @ P + t
        q = (pT[:, :3, :3] @ P_prev + pT[:, :3, 3:]).reshape(B, 3, H, W)
        uv, z_prev = project(q, pK)
        from stereorepro.camera import pixel_centers

        motion = uv - pixel_centers(H, W, dtype=torch.float64)
        truth = (P_prev - P).reshape(B, 3, H, W)
        return x, motion, z_prev - depth, truth

    def test_smoke(self):
        x, motion, dz, truth = self.rigid_case()
        mw = world_motion_from_view_z(x[1], motion, dz, x[3], x[4], x[9], x[10])
        assert mw.shape == truth.shape and mw.dtype == motion.dtype
        assert world_motion_from_view_z(x[1], motion.float(), dz, x[3], x[4], x[9], x[10]).dtype == torch.float32

    def test_rigid_motion_gives_the_3d_motion(self):
        """Rotation + translation of the geometry, cameras moving too: the conversion recovers the world motion
        (float64 within 1e-12 scene units; float32 2.5D inputs within their rounding)."""
        x, motion, dz, truth = self.rigid_case()
        surface = torch.isfinite(x[1]) & (x[1] > 0)
        mw = world_motion_from_view_z(x[1], motion, dz, x[3], x[4], x[9], x[10])
        s = surface.expand_as(mw)
        assert bool(surface.float().mean() > 0.5) and float(truth[s].abs().max()) > 0.05
        assert float((mw[s] - truth[s]).abs().max()) < 1e-12
        assert bool(torch.isnan(mw[~s]).all())
        mw32 = world_motion_from_view_z(
            x[1].float(), motion.float(), dz.float(), *(c.float() for c in (x[3], x[4], x[9], x[10]))
        )
        assert float((mw32.double()[s] - truth[s]).abs().max()) < 1e-5

    def test_ops_give_the_3d_result(self, backend):
        """A moving object (moving_object: a patch moved SHIFT pixels at z = 2, world motion known): 2.5D motion
        converted gives the 3D motion's outputs, history kept on the object."""
        args, motion, mw, obj, dis = moving_object(torch.float64)
        depth, K, T, pK, pT = args[1], args[3], args[4], args[9], args[10]
        converted = world_motion_from_view_z(depth, motion, torch.zeros_like(depth), K, T, pK, pT)
        assert float((converted - mw).abs().max()) < 1e-12
        f32 = [a.float() for a in args]
        with torch.no_grad():
            ref = temporal_reproject(
                *f32, *THR, motion=motion.float(), motion_world=mw.float(), return_reason=True, backend="torch"
            )
            got = temporal_reproject(
                *f32,
                *THR,
                motion=motion.float(),
                motion_world=converted.float(),
                return_reason=True,
                backend=self.backend_arg(backend),
            )
        self.assert_identical(got, ref)
        assert bool(got[2][obj].all())

    def test_hard_cases(self):
        """No surface, non-finite motion or delta, a previous z <= 0: NaN (the ops read no history there)."""
        x, motion, dz, truth = self.rigid_case(B=1)
        depth, motion, dz = x[1].clone(), motion.clone(), dz.clone()
        depth[..., 0, 0] = 0.0
        motion[:, 0, 1, 1] = math.nan
        dz[..., 2, 2] = math.inf
        dz[..., 3, 3] = -depth[..., 3, 3] - 1.0
        mw = world_motion_from_view_z(depth, motion, dz, x[3], x[4], x[9], x[10])
        for y in range(4):
            assert bool(torch.isnan(mw[0, :, y, y]).all())
        assert bool(torch.isfinite(mw[0, :, 4, 5]).all())

    def test_exceptions(self):
        x, motion, dz, truth = self.rigid_case(B=1)
        with pytest.raises(ShapeError, match="motion"):
            world_motion_from_view_z(x[1], motion[:, :1], dz, x[3], x[4], x[9], x[10])
        with pytest.raises(ShapeError, match="view_z_delta"):
            world_motion_from_view_z(x[1], motion, dz[..., :-1], x[3], x[4], x[9], x[10])
        with pytest.raises(ShapeError, match="previous camera"):
            world_motion_from_view_z(x[1], motion, dz, x[3], x[4], x[9][:, :2], x[10])
