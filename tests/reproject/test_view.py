"""The ops' data model: View, Thresholds, Blend, History and the named results; the View forms of the ops equal
their deprecated flat forms bit for bit on every backend."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import pytest
import torch
from base import BaseTester

import stereorepro as sr
from stereorepro import (
    Blend,
    History,
    ReprojectionResult,
    TemporalResult,
    Thresholds,
    View,
    backward_reproject,
    intrinsics_from_fov,
    stereo_reproject,
    temporal_reproject,
)
from stereorepro.errors import CameraError, ShapeError
from stereorepro.reproject.view import VIEW_FIELDS, view_fields


def shifted(cam_from_world: torch.Tensor, dx: float = 0.0, dz: float = 0.0) -> torch.Tensor:
    """The camera moved by (dx, 0, dz) in its own axes."""
    out = cam_from_world.clone()
    out[:, 0, 3] -= dx
    out[:, 2, 3] -= dz
    return out


def make_views(B: int = 1, H: int = 9, W: int = 12, dtype=torch.float32, seed: int = 0):
    """Two views of a wavy surface with a step (occlusions), 3 cm apart with a little forward motion (fractional
    taps, out-of-frame taps), a background pixel without surface and a NaN normal; colours to carry."""
    g = torch.Generator().manual_seed(seed)
    K = intrinsics_from_fov(60.0, W, H, batch=B).to(dtype)
    T = torch.eye(4, dtype=dtype).expand(B, 4, 4).clone()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    depth = (2.0 + 0.1 * torch.sin(xs / 2.0) + 0.5 * (xs > W // 2)).expand(B, 1, H, W).clone()
    depth[:, :, 0, 0] = math.inf
    normal = torch.nn.functional.normalize(
        torch.randn(B, 3, H, W, generator=g, dtype=dtype) * 0.05
        + torch.tensor([0.0, 0.0, -1.0], dtype=dtype).view(1, 3, 1, 1),
        dim=1,
    )
    normal[:, :, 1, 1] = math.nan
    dst = View(depth, normal, K, T)
    src = View(depth.roll(1, -1), normal.roll(1, -1), K, shifted(T, dx=0.03, dz=0.02))
    color = torch.rand(B, 3, H, W, generator=g, dtype=dtype)
    return color, src, dst


def flat(view: View) -> tuple:
    return view.depth, view.normal, view.K, view.cam_from_world


def quiet(fn, *args, **kwargs):
    """Call a deprecated flat form without the warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return fn(*args, **kwargs)


class TestView(BaseTester):
    def test_smoke(self):
        _, src, dst = make_views(B=2)
        assert (dst.batch_size, dst.height, dst.width) == (2, 9, 12)
        assert dst.camera.height == 9 and torch.equal(dst.camera.K, dst.K)
        assert [f.name for f in VIEW_FIELDS] == ["depth", "normal", "K", "cam_from_world"]
        assert dst.flat() == flat(dst)
        assert [f.name for f in view_fields("prev_", "Hp", "Wp", motion=True)][-2:] == [
            "prev_motion",
            "prev_motion_world",
        ]
        assert view_fields("src_", "Hp", "Wp")[0].shape == ("B", "1", "Hp", "Wp")

    def test_to(self):
        _, _, dst = make_views()
        d64 = dst.to(torch.float64)
        assert d64.depth.dtype == d64.K.dtype == torch.float64
        assert torch.equal(d64.depth.float(), dst.depth)

    def test_from_camera_and_render(self):
        _, _, dst = make_views()
        view = View.from_camera(dst.camera, dst.depth, dst.normal)
        assert torch.equal(view.depth, dst.depth) and torch.equal(view.cam_from_world, dst.cam_from_world)
        motion = torch.zeros(1, 2, 9, 12)
        result = SimpleNamespace(depth=dst.depth, normal=dst.normal, motion=motion, motion_world=None)
        assert View.from_render(result, dst.camera).motion is motion
        assert View.from_render(result, dst.camera, motion=False).motion is None
        with pytest.raises(ShapeError, match="from_camera"):
            View.from_camera(dst.camera, dst.depth[..., :5], dst.normal[..., :5])
        with pytest.raises(sr.UserError, match="G-buffers"):
            View.from_render(SimpleNamespace(depth=None, normal=None, motion=None), dst.camera)

    @pytest.mark.parametrize(
        "field, bad, error, match",
        [
            ("depth", torch.zeros(1, 2, 9, 12), ShapeError, r"View\.depth"),
            ("normal", torch.zeros(1, 3, 8, 12), ShapeError, r"View\.normal"),
            ("normal", torch.zeros(2, 3, 9, 12), ShapeError, r"View\.normal"),
            ("depth", torch.zeros(1, 1, 9, 12, dtype=torch.int32), TypeError, r"View\.depth: expected a floating"),
            ("K", torch.zeros(1, 4, 4), ShapeError, "K"),
            ("cam_from_world", 2.0 * torch.eye(4)[None], CameraError, "cam_from_world"),
            ("motion", torch.zeros(1, 3, 9, 12), ShapeError, r"View\.motion"),
            ("motion_world", torch.zeros(1, 3, 9, 12), ValueError, r"View\.motion_world needs View\.motion"),
        ],
    )
    def test_exceptions(self, field, bad, error, match):
        _, _, dst = make_views()
        with pytest.raises(error, match=match):
            dst.replace(**{field: bad})

    def test_unchecked_and_without_motion(self):
        _, _, dst = make_views()
        moving = View.unchecked(*flat(dst), torch.zeros(1, 2, 9, 12), torch.zeros(1, 3, 9, 12))
        still = moving.without_motion()
        assert still.motion is None and still.motion_world is None and still.depth is dst.depth
        assert dst.without_motion() is dst


class TestNamedResults(BaseTester):
    def test_cardinality(self):
        color, src, dst = make_views(B=2)
        out = stereo_reproject(color, src, dst, (0.05, 0.2))
        assert isinstance(out, ReprojectionResult) and out.confidence is None
        assert out.values.shape == (2, 3, 9, 12) and out.valid.dtype == torch.bool and out.reason.dtype == torch.uint8
        values = torch.cat([color, color[:, :1]], 1)
        back = backward_reproject(values, src, dst, Thresholds(0.05, 0.2))
        assert isinstance(back, ReprojectionResult) and back.values.shape == (2, 4, 9, 12)
        assert back.confidence.shape == (2, 1, 9, 12)
        tmp = temporal_reproject(color, dst, History(color, torch.full_like(src.depth, 2.0)), src, (0.05, 0.2))
        assert isinstance(tmp, TemporalResult) and tmp.reason is None
        assert tmp.history == History(tmp.color, tmp.history_len)
        with_reason = temporal_reproject(color, dst, tmp.history, dst, (0.05, 0.2), return_reason=True)
        assert with_reason.reason.dtype == torch.uint8

    def test_first_frame(self):
        color, _, dst = make_views()
        empty = History.empty(dst)
        assert empty.color.shape == (1, 3, 9, 12) and float(empty.length.abs().sum()) == 0.0
        out = temporal_reproject(color, dst, empty, dst, (0.05, 0.2))
        assert torch.equal(out.color, color) and bool((out.history_len == 1).all())


class TestViewFormsEqualFlat(BaseTester):
    """The View forms and the deprecated flat forms run the same code: identical bytes on every backend."""

    def test_stereo(self, backend):
        color, src, dst = make_views(B=2)
        b = self.backend_arg(backend)
        new = stereo_reproject(color, src, dst, (0.05, 0.2), backend=b)
        old = quiet(stereo_reproject, color, *flat(src), *flat(dst), 0.05, 0.2, backend=b)
        assert isinstance(old, tuple) and len(old) == 3
        self.assert_identical(new[:3], old)

    def test_backward_nearest(self, backend):
        color, src, dst = make_views()
        b = self.backend_arg(backend)
        new = backward_reproject(color, src, dst, (0.05, 0.2), sampling="nearest", backend=b)
        old = quiet(backward_reproject, color, *flat(src), *flat(dst), 0.05, 0.2, "nearest", backend=b)
        self.assert_identical(new, old)

    def test_temporal(self, backend):
        color, src, dst = make_views()
        b = self.backend_arg(backend)
        n = torch.full_like(src.depth, 3.0)
        for reason in (False, True):
            new = temporal_reproject(
                color,
                dst,
                History(color.flip(-1), n),
                src,
                (0.05, 0.2),
                blend=Blend(0.25, False, 8.0),
                backend=b,
                return_reason=reason,
            )
            old = quiet(
                temporal_reproject,
                color,
                *flat(dst),
                color.flip(-1),
                n,
                *flat(src),
                0.05,
                0.2,
                0.25,
                False,
                8.0,
                backend=b,
                return_reason=reason,
            )
            assert len(old) == (4 if reason else 3)
            self.assert_identical(new[: len(old)], old)

    def test_motion(self):
        color, src, dst = make_views()
        motion = torch.full((1, 2, 9, 12), 0.3)
        motion_world = torch.full((1, 3, 9, 12), 0.01)
        moving = dst.replace(motion=motion, motion_world=motion_world)
        n = torch.ones_like(src.depth)
        new = temporal_reproject(color, moving, (color, n), src, (0.05, 0.2), return_reason=True)
        old = quiet(
            temporal_reproject,
            color,
            *flat(dst),
            color,
            n,
            *flat(src),
            0.05,
            0.2,
            return_reason=True,
            motion=motion,
            motion_world=motion_world,
        )
        self.assert_identical(new, old)
        camera_only = temporal_reproject(color, dst, (color, n), src, (0.05, 0.2))
        assert not torch.equal(camera_only.color, new.color)  # the motion was used
        # the stereo op is same-instant: a view's motion is not used there
        self.assert_identical(
            stereo_reproject(color, src, moving, (0.05, 0.2))[:3], stereo_reproject(color, src, dst, (0.05, 0.2))[:3]
        )

    def test_module_equals_function(self):
        color, src, dst = make_views()
        module = sr.StereoReprojection(0.05, 0.2)
        self.assert_identical(module(color, *flat(src), *flat(dst)), stereo_reproject(color, src, dst, (0.05, 0.2))[:3])
        temporal = sr.TemporalReprojection(0.05, 0.2, alpha=0.3)
        n = torch.full_like(src.depth, 4.0)
        got = temporal(color, *flat(dst), color, n, *flat(src))
        want = temporal_reproject(color, dst, History(color, n), src, (0.05, 0.2), blend=Blend(0.3))
        self.assert_identical(got, want[:3])

    def test_gradcheck(self):
        color, src, dst = make_views(H=4, W=5, dtype=torch.float64)
        thr = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)

        def f(c, t):
            return backward_reproject(c, src, dst, Thresholds(t, 0.5, 0.2), soft=True, backend="torch").values

        assert torch.autograd.gradcheck(f, (color.requires_grad_(True), thr))


class TestDeprecation(BaseTester):
    def test_flat_forms_warn_and_name_the_new_call(self):
        color, src, dst = make_views()
        n = torch.ones_like(src.depth)
        with pytest.warns(DeprecationWarning, match=r"stereo_reproject\(src_color, src: View"):
            stereo_reproject(color, *flat(src), *flat(dst), 0.05, 0.2)
        with pytest.warns(DeprecationWarning, match=r"backward_reproject\(values, src: View"):
            backward_reproject(color, *flat(src), *flat(dst), 0.05, 0.2, check=False)
        with pytest.warns(DeprecationWarning, match=r"temporal_reproject\(current_color, view: View"):
            temporal_reproject(color, *flat(dst), color, n, *flat(src), position_threshold=0.05, normal_threshold=0.2)
        with warnings.catch_warnings():  # the View forms do not warn
            warnings.simplefilter("error", DeprecationWarning)
            stereo_reproject(color, src, dst, (0.05, 0.2))
            temporal_reproject(color, dst, (color, n), src, (0.05, 0.2))

    def test_flat_error_names_are_kept(self):
        color, src, dst = make_views()
        with pytest.raises(ShapeError, match="src_depth"):
            quiet(stereo_reproject, color, src.depth[..., :4], *flat(src)[1:], *flat(dst), 0.05, 0.2)


class TestOpExceptions(BaseTester):
    def test_exceptions(self):
        color, src, dst = make_views()
        with pytest.raises(TypeError, match="thresholds"):
            stereo_reproject(color, src, dst, 0.05)
        with pytest.raises(ValueError, match="position_threshold"):
            stereo_reproject(color, src, dst, (-1.0, 0.2))
        with pytest.raises(ValueError, match="normal_threshold"):
            stereo_reproject(color, src, dst, Thresholds(0.1, math.nan))
        with pytest.raises(ShapeError, match="color"):
            stereo_reproject(color[..., :5], src, dst, (0.05, 0.2))
        with pytest.raises(ShapeError, match="batch sizes differ"):
            _, src2, _ = make_views(B=2)
            backward_reproject(torch.cat([color, color]), src2, dst, (0.05, 0.2))
        with pytest.raises(TypeError, match="unexpected arguments"):
            stereo_reproject(color, src, dst, (0.05, 0.2), "bilinear")
        with pytest.raises(TypeError, match="history"):
            temporal_reproject(color, dst, color, src, (0.05, 0.2))
        with pytest.raises(ShapeError, match="history.length"):
            temporal_reproject(color, dst, (color, color), src, (0.05, 0.2))
        with pytest.raises(ValueError, match="alpha"):
            temporal_reproject(color, dst, (color, src.depth), src, (0.05, 0.2), blend=Blend(math.nan))
        with pytest.raises(ValueError, match="rectified"):
            backward_reproject(color, src, dst.replace(motion=torch.zeros(1, 2, 9, 12)), (0.05, 0.2), rectified=True)


class TestInputDescription(BaseTester):
    """The modules describe their flat inputs once (input_fields); ONNX input names and symbolic axes come from it."""

    def test_fields(self):
        from stereorepro.io.onnx import symbolic_axes

        stereo = sr.StereoReprojection(0.05, 0.2)
        assert stereo.input_names == [f.name for f in stereo.input_fields]
        axes = symbolic_axes(stereo.input_fields)
        assert axes["src_color"] == {0: "B", 2: "Hp", 3: "Wp"} and axes["dst_normal"] == {0: "B", 2: "H", 3: "W"}
        assert axes["src_K"] == {0: "B"} and axes["dst_cam_from_world"] == {0: "B"}
        temporal = sr.TemporalReprojection(0.05, 0.2, motion_vectors=True)
        axes = symbolic_axes(temporal.input_fields)
        assert temporal.input_names[-2:] == ["motion", "motion_world"] and axes["motion"] == {0: "B", 2: "H", 3: "W"}
        assert axes["history_len"] == {0: "B", 2: "Hp", 3: "Wp"} and axes["prev_depth"] == {0: "B", 2: "Hp", 3: "Wp"}
        denoiser = sr.ReprojectionDenoiser(torch.nn.Conv2d(13, 3, 1), 0.05, 0.2, stereo=True)
        assert symbolic_axes(denoiser.input_fields)["other_depth"] == {0: "B", 2: "H", 3: "W"}
        assert denoiser.input_names[-5:] == list(sr.denoise.OTHER_NAMES)

    def test_exceptions(self, tmp_path):
        class NoFields(torch.nn.Module):
            input_names = ["x"]
            output_names = ["y"]

            def forward(self, x):
                return x

        with pytest.raises(TypeError, match="input_fields"):
            sr.export_onnx(NoFields(), tmp_path / "x.onnx", inputs=(torch.zeros(1),))
        assert not (tmp_path / "x.onnx").exists()


class TestChannels(BaseTester):
    def test_many_channels_fall_back_to_torch(self):
        from stereorepro.reproject import _native

        color, src, dst = make_views()
        values = torch.rand(1, 20, 9, 12)  # more than the native kernels carry
        auto = backward_reproject(values, src, dst, (0.05, 0.2))
        self.assert_identical(auto, backward_reproject(values, src, dst, (0.05, 0.2), backend="torch"))
        if _native.available():
            with pytest.raises(RuntimeError, match="at most 16 value channels"):
                backward_reproject(values, src, dst, (0.05, 0.2), backend="native")
