"""The exception family: every documented user mistake of the library raises a StereoreproError subclass that also
derives from the built-in it refines (``ValueError``; ``TypeError`` for wrong kinds such as integer tensors), so
``except StereoreproError`` catches them all and ``except ValueError`` code keeps working; messages name the
argument. (The command line's side of the policy is tests/cli/test_errors.py.)"""

from __future__ import annotations

import math
import re

import pytest
import torch

import stereorepro as sr
from stereorepro import Blend, History, View, intrinsics_from_fov
from stereorepro._checks import FLOAT32_MAX, check_blend_inputs
from stereorepro.errors import CameraError, ParameterError, ParameterTypeError, ShapeError, StereoreproError

H, W = 6, 8
THR = (0.1, 0.25)


def _view(tx: float = 0.0, batch: int = 1) -> View:
    depth = torch.full((batch, 1, H, W), 2.0)
    normal = torch.zeros(batch, 3, H, W)
    normal[:, 2] = -1
    T = torch.eye(4)[None].repeat(batch, 1, 1)
    T[:, 0, 3] = tx
    return View(depth, normal, intrinsics_from_fov(60.0, W, H).repeat(batch, 1, 1), T)


SRC, DST = _view(0.065), _view(0.0)
COLOR = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0))
HIST = History(COLOR, torch.ones(1, 1, H, W))


def _temporal(blend: Blend):
    return sr.temporal_reproject(COLOR, DST, HIST, SRC, THR, blend=blend)


#: (what, call, the built-in it refines, the family class, a fragment of the message naming the argument)
MISTAKES = [
    (
        "negative threshold",
        lambda: sr.stereo_reproject(COLOR, SRC, DST, (-1.0, 0.25)),
        ValueError,
        ParameterError,
        "position_threshold",
    ),
    (
        "NaN threshold",
        lambda: sr.stereo_reproject(COLOR, SRC, DST, (0.1, math.nan)),
        ValueError,
        ParameterError,
        "normal_threshold",
    ),
    (
        "threshold beyond float32",
        lambda: sr.stereo_reproject(COLOR, SRC, DST, (1e39, 0.25)),
        ValueError,
        ParameterError,
        "position_threshold: 1e+39 is beyond float32's range",
    ),
    ("alpha NaN", lambda: _temporal(Blend(math.nan)), ValueError, ParameterError, "alpha"),
    ("alpha inf", lambda: _temporal(Blend(math.inf)), ValueError, ParameterError, "alpha"),
    ("max_history 0.5", lambda: _temporal(Blend(0.2, True, 0.5)), ValueError, ParameterError, "max_history"),
    ("max_history NaN", lambda: _temporal(Blend(0.2, True, math.nan)), ValueError, ParameterError, "max_history"),
    (
        "max_history 1e300",
        lambda: _temporal(Blend(0.2, True, 1e300)),
        ValueError,
        ParameterError,
        "max_history: 1e+300 is beyond float32's range",
    ),
    (
        "motion_world without motion",
        lambda: View(DST.depth, DST.normal, DST.K, DST.cam_from_world, None, torch.zeros(1, 3, H, W)),
        ValueError,
        ParameterError,
        "motion_world needs",
    ),
    (
        "integer colour",
        lambda: sr.stereo_reproject(COLOR.int(), SRC, DST, THR),
        TypeError,
        ParameterTypeError,
        "floating-point",
    ),
    (
        "integer depth",
        lambda: View(DST.depth.int(), DST.normal, DST.K, DST.cam_from_world),
        TypeError,
        ParameterTypeError,
        "View.depth",
    ),
    (
        "not a tensor",
        lambda: View("depth", DST.normal, DST.K, DST.cam_from_world),
        TypeError,
        ParameterTypeError,
        "View.depth",
    ),
    (
        "StereoReprojection threshold",
        lambda: sr.StereoReprojection(-1.0, 0.25),
        ValueError,
        ParameterError,
        "position_threshold",
    ),
    (
        "StereoReprojection threshold beyond float32",
        lambda: sr.StereoReprojection(1e39, 0.25),
        ValueError,
        ParameterError,
        "beyond float32's range",
    ),
    (
        "StereoReprojection sampling",
        lambda: sr.StereoReprojection(0.1, 0.25, sampling="cubic"),
        ValueError,
        ParameterError,
        "sampling",
    ),
    (
        "StereoReprojection temperature",
        lambda: sr.StereoReprojection(0.1, 0.25, soft=True, temperature=0.0),
        ValueError,
        ParameterError,
        "temperature",
    ),
    (
        "TemporalReprojection alpha",
        lambda: sr.TemporalReprojection(0.1, 0.25, alpha=2.0),
        ValueError,
        ParameterError,
        "alpha",
    ),
    (
        "TemporalReprojection alpha NaN",
        lambda: sr.TemporalReprojection(0.1, 0.25, alpha=math.nan),
        ValueError,
        ParameterError,
        "alpha",
    ),
    (
        "TemporalReprojection max_history",
        lambda: sr.TemporalReprojection(0.1, 0.25, max_history=0.5),
        ValueError,
        ParameterError,
        "max_history",
    ),
    (
        "TemporalReprojection max_history 1e300",
        lambda: sr.TemporalReprojection(0.1, 0.25, max_history=1e300),
        ValueError,
        ParameterError,
        "max_history",
    ),
    (
        "SpatiotemporalReprojection left_mode",
        lambda: sr.SpatiotemporalReprojection(0.1, 0.25, left_mode="mix"),
        ValueError,
        ParameterError,
        "left_mode",
    ),
    (
        "SpatiotemporalReprojection max_history",
        lambda: sr.SpatiotemporalReprojection(0.1, 0.25, max_history=0.5),
        ValueError,
        ParameterError,
        "max_history",
    ),
    (
        "camera_motion K*0",
        lambda: sr.camera_motion(DST.depth, DST.K * 0, DST.cam_from_world, DST.K, DST.cam_from_world),
        ValueError,
        CameraError,
        "camera_motion: K[0]: focal lengths",
    ),
    (
        "temporal_blend inputs",
        lambda: check_blend_inputs(COLOR, COLOR[:, :2], HIST.length, HIST.length > 0),
        ValueError,
        ShapeError,
        "temporal_blend: history_color",
    ),
]


class TestExceptionFamily:
    @pytest.mark.parametrize("what, call, builtin, family, fragment", MISTAKES, ids=[m[0] for m in MISTAKES])
    def test_exceptions(self, what, call, builtin, family, fragment):
        with pytest.raises(family, match=re.escape(fragment)) as info:
            call()
        assert isinstance(info.value, StereoreproError) and isinstance(info.value, builtin), type(info.value)

    def test_float32_bound(self):
        """The largest finite float32 is accepted (it converts exactly), the next double above is not; inf is."""
        sr.stereo_reproject(COLOR, SRC, DST, (FLOAT32_MAX, 0.25))
        sr.stereo_reproject(COLOR, SRC, DST, (math.inf, math.inf))
        with pytest.raises(ParameterError, match="pass inf for no limit"):
            sr.stereo_reproject(COLOR, SRC, DST, (math.nextafter(FLOAT32_MAX, math.inf), 0.25))
        _temporal(Blend(0.2, True, math.inf))

    def test_hierarchy(self):
        assert issubclass(ParameterError, ValueError) and issubclass(ParameterTypeError, TypeError)
        assert not issubclass(ParameterTypeError, ValueError) and not issubclass(ParameterError, TypeError)


class TestFamilyAtTheEdges:
    """The last places that raised plain built-ins or raw torch errors."""

    def test_temporal_blend_shapes(self):
        n, v = torch.ones(1, 1, H, W), torch.ones(1, 1, H, W, dtype=torch.bool)
        with pytest.raises(ShapeError, match="temporal_blend: history_color"):
            sr.temporal_blend(COLOR, COLOR[:, :2], n, v)
        with pytest.raises(ParameterTypeError, match="confidence"):
            sr.temporal_blend(COLOR, COLOR, n, v.to(torch.int32))

    def test_backend_names(self, monkeypatch):
        with pytest.raises(ParameterError, match="backend must be one of"):
            sr.StereoReprojection(0.1, 0.1, backend="x")
        monkeypatch.setenv("STEREOREPRO_BACKEND", "bogus")
        with pytest.raises(ParameterError, match="STEREOREPRO_BACKEND"):
            sr.stereo_reproject(COLOR, SRC, DST, THR)

    def test_sample_index_range(self):
        from stereorepro.render.tracer import _check_render_args

        _check_render_args(2, 2**63 - 2, "box")
        with pytest.raises(ParameterError, match="2\\*\\*63"):
            _check_render_args(2, 2**63 - 1, "box")


class TestAllFinite:
    @pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
    def test_agrees_with_isfinite(self, dtype):
        """The sum-first test gives ``isfinite(t).all()`` for every placement of NaN / ±inf, in every float dtype,
        and for finite values whose sum overflows (the fallback)."""
        from stereorepro._checks import all_finite

        g = torch.Generator().manual_seed(0)
        for _ in range(40):
            t = torch.randn(3, 5, 7, generator=g).to(dtype)
            k = int(torch.randint(0, 4, (1,), generator=g))
            if k:
                t.view(-1)[int(torch.randint(0, t.numel(), (1,), generator=g))] = (
                    float("nan"),
                    float("inf"),
                    -float("inf"),
                )[k - 1]
            assert all_finite(t) == bool(torch.isfinite(t).all())
        big = torch.full((4,), torch.finfo(dtype).max, dtype=dtype)
        assert all_finite(big) and not bool(torch.isfinite(big.sum()))
        assert all_finite(torch.zeros(0)) and all_finite(torch.ones(3, dtype=torch.int64))
