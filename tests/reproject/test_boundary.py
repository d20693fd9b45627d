"""Regression tests of the reliability sweep at the ops' boundary: each failure it found, by name (the fuzz suite,
``test_fuzz.py``, searches for new ones)."""

from __future__ import annotations

import math

import pytest
import torch

from base import BaseTester
from stereorepro import intrinsics_from_fov
from stereorepro.errors import CameraError, ShapeError
from stereorepro.reproject import StereoReprojection, TemporalReprojection
from stereorepro.reproject.functional import backward_reproject, stereo_reproject, temporal_blend, temporal_reproject

H, W = 6, 8
FLT_MAX = torch.finfo(torch.float32).max


def scene(B=1, baseline=0.06):
    K = intrinsics_from_fov(60.0, W, H, batch=B)
    src = torch.eye(4).expand(B, 4, 4).clone()
    dst = src.clone()
    dst[:, 0, 3] = -baseline
    depth = torch.full((B, 1, H, W), 2.0)
    normal = torch.zeros(B, 3, H, W)
    normal[:, 2] = -1
    color = torch.rand(B, 3, H, W, generator=torch.Generator().manual_seed(0))
    return color, depth, normal, K, src, dst


def stereo_args(B=1):
    color, depth, normal, K, src, dst = scene(B)
    return color, depth, normal, K, src, depth.clone(), normal.clone(), K, dst


def temporal_args(history_len):
    color, depth, normal, K, src, dst = scene()
    return color, depth, normal, K, dst, color.flip(-1), history_len, depth, normal, K, src


class TestHistoryLength(BaseTester):
    """The native temporal kernel gave n = 0, -2 or -1e30 for negative history lengths (torch: 1)."""

    @pytest.mark.parametrize("value", [-1.0, -3.0, -1e30, math.nan, 0.0])
    def test_negative_history_len_restarts(self, backend, value):
        args = temporal_args(torch.full((1, 1, H, W), value))
        with torch.no_grad():
            color, n, valid = temporal_reproject(*args, 1.0, 0.5, backend=self.backend_arg(backend))
        kept = n[valid]
        if math.isnan(value):  # a NaN history value is rejected like any non-finite value
            assert kept.numel() == 0
        else:
            assert kept.numel() > 0 and bool((kept == 1).all()), n.unique()
        assert bool(((n >= 1) & (n <= 255)).all())

    def test_interpolated_negative_lengths_match_torch(self, backend, monkeypatch):
        """Each backend gives the bytes of the torch general path."""
        from stereorepro.reproject import functional

        n = torch.linspace(-4, 3, H * W).view(1, 1, H, W)
        args = temporal_args(n)
        with torch.no_grad():
            got = temporal_reproject(*args, 1.0, 0.5, backend=self.backend_arg(backend))
            monkeypatch.setattr(functional, "FAST_PATH", False)
            ref = temporal_reproject(*args, 1.0, 0.5, backend="torch")
        self.assert_identical(got, ref)


class TestSoftGradients(BaseTester):
    """Soft mode: a huge but finite source depth gave a NaN threshold gradient; fp32 depths <= 1e-19 gave NaN
    depth gradients."""

    @pytest.mark.parametrize("far", [3.7e12, 9e15, 1e30, FLT_MAX])
    @pytest.mark.parametrize("thr", [0.05, 1e-3])
    def test_huge_source_depth(self, far, thr):
        color, depth, normal, K, src, dst = scene()
        src_depth = depth.clone()
        src_depth[..., 2:4, :] = far
        t = torch.tensor(thr, requires_grad=True)
        dst_depth = depth.clone().requires_grad_(True)
        out, _, _ = stereo_reproject(color, src_depth, normal, K, src, dst_depth, normal, K, dst, t, 0.1, soft=True)
        gt, gd = torch.autograd.grad(out.sum(), [t, dst_depth])
        assert bool(torch.isfinite(gt)) and bool(torch.isfinite(gd).all())

    def test_infinite_threshold_accepts(self):
        args = stereo_args()
        out, valid, _ = stereo_reproject(*args, math.inf, math.inf, soft=True)
        assert bool(torch.isfinite(out).all()) and bool(valid.any())

    @pytest.mark.parametrize("soft", [False, True])
    @pytest.mark.parametrize("z", [1e-19, 1e-20, 1e-30, 1e-38])
    def test_tiny_depth_gradients(self, soft, z):
        color, depth, normal, K, src, dst = scene()
        dst_depth = torch.full_like(depth, z, requires_grad=True)
        out, _, _ = stereo_reproject(
            color, torch.full_like(depth, z), normal, K, src, dst_depth, normal, K, dst, 0.05, 0.1, soft=soft
        )
        (g,) = torch.autograd.grad(out.sum(), [dst_depth])
        assert bool(torch.isfinite(g).all())

    def test_tiny_depth_forward_unchanged(self, backend):
        """The gradient guard does not change the forward value: each backend without autograd gives the bytes of
        the torch path with autograd."""
        color, depth, normal, K, src, dst = scene()
        d = torch.rand_like(depth) * 3 + 0.5
        with torch.no_grad():
            ref = stereo_reproject(
                color, d, normal, K, src, d, normal, K, dst, 0.05, 0.1, backend=self.backend_arg(backend)
            )
        got = stereo_reproject(color, d, normal, K, src, d.clone().requires_grad_(True), normal, K, dst, 0.05, 0.1)
        for g, r in zip(got, ref):
            assert torch.equal(g.detach(), r)


class TestFunctionBoundary(BaseTester):
    """Function-level checks the modules had and the functions lacked."""

    def test_empty_batch(self, backend):
        backend = self.backend_arg(backend)
        args = [a[:0] for a in stereo_args()]
        color, valid, reason = stereo_reproject(*args, 0.05, 0.1, backend=backend)
        assert color.shape == (0, 3, H, W) and valid.shape == reason.shape == (0, 1, H, W)
        values, valid, reason, conf = backward_reproject(*args, 0.05, 0.1, backend=backend)
        assert values.shape == (0, 3, H, W) and conf.shape == (0, 1, H, W)
        t = [a[:0] for a in temporal_args(torch.ones(1, 1, H, W))]
        color, n, valid, reason = temporal_reproject(*t, 0.05, 0.1, backend=backend, return_reason=True)
        assert color.shape == (0, 3, H, W) and n.shape == (0, 1, H, W)

    def test_empty_source_image(self):
        color, depth, normal, K, src, dst = scene()
        with pytest.raises(ShapeError, match="at least one pixel"):
            stereo_reproject(color[..., :0], depth[..., :0], normal[..., :0], K, src, depth, normal, K, dst, 0.05, 0.1)

    @pytest.mark.parametrize(
        "bad, match",
        [(torch.tensor([0.05, 0.1]), "one-element"), (-0.01, r"\[0, inf\]"), (math.nan, "got nan"), ("0.1", "number")],
    )
    def test_bad_thresholds(self, bad, match):
        with pytest.raises((ValueError, TypeError), match=match):
            stereo_reproject(*stereo_args(), bad, 0.1)
        with pytest.raises((ValueError, TypeError), match=match):
            stereo_reproject(*stereo_args(), 0.05, bad)
        with pytest.raises((ValueError, TypeError), match=match):
            temporal_reproject(*temporal_args(torch.ones(1, 1, H, W)), bad, 0.1)

    def test_one_element_threshold_tensor(self, backend):
        be = self.backend_arg(backend)
        ref = stereo_reproject(*stereo_args(), 0.05, 0.1, backend=be)
        got = stereo_reproject(*stereo_args(), torch.tensor([0.05]), torch.tensor([[0.1]]), backend=be)
        for g, r in zip(got, ref):
            assert torch.equal(g, r)

    @pytest.mark.parametrize(
        "name, value", [("alpha", math.nan), ("alpha", math.inf), ("max_history", math.nan), ("max_history", 0.5)]
    )
    def test_bad_blend_scalars(self, backend, name, value):
        with pytest.raises(ValueError, match=name):
            temporal_reproject(
                *temporal_args(torch.ones(1, 1, H, W)), 0.05, 0.1, backend=self.backend_arg(backend), **{name: value}
            )
        color, *_ = scene()
        with pytest.raises(ValueError, match=name):
            temporal_blend(
                color, color, torch.ones(1, 1, H, W), torch.ones(1, 1, H, W, dtype=torch.bool), **{name: value}
            )

    def test_modules_reject_what_functions_reject(self):
        with pytest.raises(ValueError, match="position_threshold"):
            StereoReprojection(-0.1, 0.1)
        with pytest.raises(ValueError, match="alpha"):
            TemporalReprojection(0.05, 0.1, alpha=math.nan)


class TestCameraChecks(BaseTester):
    """Non-rigid / mirrored extrinsics and singular intrinsics were accepted by the library (only the CLI
    checked): a scaled camera gave 0 valid pixels, a mirrored one looked fine."""

    @staticmethod
    def _call(src_K=None, dst_cam=None):
        color, depth, normal, K, src, dst = scene()
        return stereo_reproject(
            color,
            depth,
            normal,
            K if src_K is None else src_K,
            src,
            depth,
            normal,
            K,
            dst if dst_cam is None else dst_cam,
            0.05,
            0.1,
        )

    @pytest.mark.parametrize(
        "edit, match",
        [
            (lambda T: T[:, :3, :3].mul_(2.0), "scaled or sheared"),
            (lambda T: T[:, 0, :3].neg_(), "mirror / axis flip"),
            (lambda T: T[:, 3, 0].fill_(0.5), r"last row \[0, 0, 0, 1\]"),
            (lambda T: T[:, 0, 3].fill_(math.nan), "finite"),
        ],
    )
    def test_extrinsics(self, edit, match):
        _, _, _, _, _, dst = scene()
        edit(dst)
        with pytest.raises(CameraError, match=r"dst_cam_from_world\[0\]: .*" + match):
            self._call(dst_cam=dst)

    @pytest.mark.parametrize(
        "edit, match",
        [
            (lambda K: K[:, 0, 0].fill_(0.0), "focal lengths must be > 0"),
            (lambda K: K[:, 1, 1].fill_(-5.0), "axis flip"),
            (lambda K: K[:, 2, 0].fill_(1.0), "pinhole"),
            (lambda K: K[:, 0, 2].fill_(math.inf), "finite"),
        ],
    )
    def test_intrinsics(self, edit, match):
        K = intrinsics_from_fov(60.0, W, H)
        edit(K)
        with pytest.raises(CameraError, match=r"src_K\[0\]: .*" + match):
            self._call(src_K=K)

    def test_rigid_within_rounding_accepted(self):
        _, _, _, _, _, dst = scene()
        dst[:, :3, :3] += 1e-6  # float32 rounding of a composed rotation
        self._call(dst_cam=dst)

    def test_temporal_names_the_current_camera(self):
        args = list(temporal_args(torch.ones(1, 1, H, W)))
        args[4] = args[4].clone()
        args[4][:, :3, :3] *= 2
        with pytest.raises(CameraError, match=r"^cam_from_world\[0\]"):
            temporal_reproject(*args, 0.05, 0.1)
