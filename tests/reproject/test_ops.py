"""backward_reproject and temporal_blend as operations of their own (the stereo and temporal ops that build on them
are tested in test_reproject.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from base import BaseTester
from reference import reference_backward_reproject
from test_reproject import scene_pair
from stereorepro import StereoReprojection, TemporalReprojection, backward_reproject, stereo_reproject, temporal_blend
from stereorepro.errors import ParameterError, ShapeError
from stereorepro._testing import example_inputs
from stereorepro.reproject import Reason


def _stereo_inputs(dtype=torch.float32, device="cpu", H=12, W=16, seed=0, C=3):
    """backward_reproject inputs from the example scene: values with C channels, G-buffers, cameras."""
    m = StereoReprojection(0.05, 0.3)
    xs = dict(zip(m.input_names, example_inputs(m, height=H, width=W, seed=seed, dtype=torch.float64)))
    g = torch.Generator().manual_seed(seed)
    xs["src_color"] = torch.rand(1, C, H, W, generator=g, dtype=torch.float64)
    return [
        xs[n].to(
            device=device,
            dtype=dtype if n not in ("src_K", "dst_K", "src_cam_from_world", "dst_cam_from_world") else torch.float64,
        )
        for n in m.input_names
    ]


def _reference_cases() -> dict:
    """Tiny inputs (6x5 and 4x7 destinations) for the comparison with the reference: a moving stereo pair of the
    analytic scene (kept, position, normal and out-of-frame discards), the same with special values (NaN / inf /
    zero / negative depths, NaN / inf colours, NaN and inf normal components), a source camera turned so that part
    of the points are behind it, and a batch of two rigs with five channels and a smaller source image."""

    def scene(H=6, W=5, **kw):
        inp, *_ = scene_pair(H=H, W=W, **kw)
        return [
            inp[k]
            for k in (
                "src_color",
                "src_depth",
                "src_normal",
                "src_K",
                "src_cam_from_world",
                "dst_depth",
                "dst_normal",
                "dst_K",
                "dst_cam_from_world",
            )
        ]

    def special():
        a = [x.clone() for x in scene(forward=0.1, yaw=1.5, baseline=0.2)]
        a[0][0, 1, 2, 3], a[0][0, 0, 1, 1], a[0][0, 2, 4, 2] = float("nan"), float("inf"), -float("inf")
        a[1][0, 0, 0, 2], a[1][0, 0, 3, 4], a[1][0, 0, 2, 0] = float("nan"), 0.0, -1.0
        a[1][0, 0, 5, 4] = float("inf")
        a[2][0, 0, 1, 3], a[2][0, 2, 3, 3] = float("nan"), float("inf")
        a[2][0, :, 4, 1] = torch.tensor([1.0, 0.0, 0.0])  # a normal turned 90°
        a[5][0, 0, 1, 1], a[5][0, 0, 2, 4], a[5][0, 0, 4, 0] = float("nan"), 0.0, float("inf")
        a[6][0, 1, 0, 0] = float("nan")
        return a

    def turned():
        a = scene(baseline=0.1)
        c, s = math.cos(math.radians(100.0)), math.sin(math.radians(100.0))
        turn = torch.tensor([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]], dtype=a[4].dtype)
        a[4] = turn @ a[4]
        return a

    def batch():
        one, two = scene(H=4, W=7, forward=0.2, yaw=2.0), scene(H=4, W=7, baseline=0.4, yaw=-3.0)
        a = [torch.cat([x, y]) for x, y in zip(one, two)]
        src = [
            torch.cat([x, y])
            for x, y in zip(scene(H=5, W=5, forward=0.2, yaw=2.0), scene(H=5, W=5, baseline=0.4, yaw=-3.0))
        ]
        a[:5] = src[:5]
        a[0] = torch.rand(2, 5, 5, 5, generator=torch.Generator().manual_seed(3))
        return a

    return {
        "scene": (scene(forward=0.2, yaw=2.0, baseline=0.3), 0.3, 0.1, "bilinear"),
        "scene_nearest": (scene(forward=0.2, yaw=2.0, baseline=0.3), 0.3, 0.1, "nearest"),
        "tight": (scene(forward=-0.1, yaw=-1.0), 0.15, 0.05, "bilinear"),
        "special": (special(), 0.3, 0.1, "bilinear"),
        "special_nearest": (special(), 0.3, 0.1, "nearest"),
        "turned": (turned(), 1.0, 1.0, "bilinear"),
        "batch_channels": (batch(), 0.6, 0.1, "bilinear"),
        # loose thresholds: a tiny image's pixels are large, and all 16 taps must pass for the cubic to apply
        "scene_catmull_rom": (scene(H=10, W=12, forward=0.05, yaw=0.5, baseline=0.1), 5.0, 2.0, "catmull_rom"),
        "special_catmull_rom": (special(), 5.0, 2.0, "catmull_rom"),
        "batch_catmull_rom": (batch(), 5.0, 2.0, "catmull_rom"),
    }


REFERENCE_CASES = _reference_cases()
#: Decisions closer than this to their boundary (scene units, or pixels for the taps' edges) are not compared: there
#: float32 rounding may decide either way.
REFERENCE_MARGIN = 1e-4


def assert_matches_reference(got, ref, what="", min_compared=0.9):
    """``got``: a backend's (values, valid, reason, confidence); ``ref``: the reference's (values, valid, reason,
    confidence, margin). valid and reason exactly, values and confidence within float32 rounding, on every pixel
    whose decisions are not within REFERENCE_MARGIN of a boundary (at least ``min_compared`` of them)."""
    values, valid, reason, conf = (
        x.detach().cpu().double().numpy() if x.is_floating_point() else x.cpu().numpy() for x in got
    )
    r_values, r_valid, r_reason, r_conf, margin = ref
    sure = margin > REFERENCE_MARGIN
    assert sure.mean() >= min_compared, f"{what}: only {sure.mean():.2f} of the pixels are clear of the boundaries"
    assert (valid[sure] == r_valid[sure]).all(), f"{what}: valid differs at {np.argwhere(sure & (valid != r_valid))}"
    bad = sure & (reason != r_reason)
    assert not bad.any(), f"{what}: reason {reason[bad]} where the reference says {r_reason[bad]}"
    sure_c = np.broadcast_to(sure, values.shape)
    np.testing.assert_allclose(values[sure_c], r_values[sure_c], rtol=1e-5, atol=1e-6, err_msg=what)
    np.testing.assert_allclose(conf[sure], r_conf[sure], rtol=1e-5, atol=1e-6, err_msg=what)


class TestBackwardReproject(BaseTester):
    def test_smoke(self, device, dtype, backend):
        self.skip_unless_runs(backend, dtype, device)
        with torch.no_grad():
            values, valid, reason, conf = backward_reproject(
                *_stereo_inputs(dtype, device), 0.05, 0.3, backend=self.backend_arg(backend)
            )
        assert values.dtype == dtype and valid.dtype == torch.bool and reason.dtype == torch.uint8
        assert valid.any() and (~valid).any()
        assert torch.equal(valid, reason == int(Reason.KEPT))
        assert torch.equal(valid, conf > 0)

    @pytest.mark.parametrize("B,C,H,W", [(1, 1, 5, 7), (2, 4, 12, 16), (3, 8, 1, 9)])
    def test_cardinality(self, B, C, H, W, backend):
        args = [torch.cat([x] * B) for x in _stereo_inputs(H=H, W=W, C=C)]
        with torch.no_grad():
            values, valid, reason, conf = backward_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
        assert values.shape == (B, C, H, W)
        assert valid.shape == reason.shape == conf.shape == (B, 1, H, W)

    def test_exceptions(self):
        args = _stereo_inputs()
        with pytest.raises(ValueError, match="sampling"):
            backward_reproject(*args, 0.05, 0.3, sampling="bicubic")
        with pytest.raises(ValueError, match="backend"):
            backward_reproject(*args, 0.05, 0.3, backend="gpu")
        bad = list(args)
        bad[1] = bad[1][..., :-1]
        with pytest.raises(ShapeError, match="src_depth"):
            backward_reproject(*bad, 0.05, 0.3)
        with pytest.raises(RuntimeError, match="soft"):
            backward_reproject(*args, 0.05, 0.3, soft=True, backend="native")

    def test_gradcheck(self):
        args = _stereo_inputs(torch.float64, H=5, W=6, C=2)
        values = args[0].clone().requires_grad_(True)
        depth = args[5].clone().requires_grad_(True)

        def f(v, d):
            return backward_reproject(v, *args[1:5], d, *args[6:], 0.05, 0.3, soft=True, temperature=0.2)[0]

        assert torch.autograd.gradcheck(f, (values, depth), eps=1e-6, atol=1e-5)

    @pytest.mark.parametrize("case", sorted(REFERENCE_CASES))
    def test_matches_reference(self, case, backend, monkeypatch):
        """Each backend (torch general path, torch fast path, native) against the per-pixel reference of
        tests/reproject/reference.py, on tiny images where every reason code occurs."""
        from stereorepro.reproject import _fast

        args, pos, nrm, sampling = REFERENCE_CASES[case]
        calls = []
        fast = _fast.fast_reproject
        monkeypatch.setattr(_fast, "fast_reproject", lambda *a, **k: calls.append(1) or fast(*a, **k))
        with torch.no_grad():
            got = backward_reproject(*args, pos, nrm, sampling, backend=self.backend_arg(backend))
        assert bool(calls) == (backend == "fast"), "the backend fixture's path was not the one taken"
        ref = reference_backward_reproject(*args, pos, nrm, sampling)
        assert_matches_reference(got, ref, f"{backend} {case}")

    def test_reference_cases_cover_every_reason(self):
        """The cases above reach every discard reason of the reference (the comparison is not vacuous)."""
        seen = set()
        for args, pos, nrm, sampling in REFERENCE_CASES.values():
            _, valid, reason, _, margin = reference_backward_reproject(*args, pos, nrm, sampling)
            seen |= set(np.unique(reason[margin > REFERENCE_MARGIN]).tolist())
        assert seen == {int(r) for r in Reason if r != Reason.NO_HISTORY}, sorted(seen)

    def test_backends_identical(self, backend):
        """Each backend gives the bytes of the torch reference on a larger scene (hard tests; the torch reference
        itself is checked against the per-pixel reference in test_matches_reference)."""
        args = _stereo_inputs(H=20, W=28, seed=3)
        with torch.no_grad():
            got = backward_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
            ref = backward_reproject(*args, 0.05, 0.3, backend="torch")  # fast where it applies
        self.assert_identical(got[:3], ref[:3])
        torch.testing.assert_close(got[3], ref[3], atol=1e-6, rtol=0)

    def test_stereo_reproject_is_its_three_channel_case(self, backend):
        args = _stereo_inputs(seed=1)
        with torch.no_grad():
            full = backward_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
            stereo = stereo_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
        self.assert_identical(stereo, full[:3])

    def test_extra_channels_ride_along(self, backend):
        """Channels are warped independently: warping [a, b] equals warping a and b on their own."""
        args = _stereo_inputs(C=5, seed=2)
        with torch.no_grad():
            both = backward_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
            a = backward_reproject(args[0][:, :2], *args[1:], 0.05, 0.3, backend=self.backend_arg(backend))
        torch.testing.assert_close(both[0][:, :2], a[0], atol=1e-6, rtol=0)
        self.assert_identical(both[1:3], a[1:3])

    def test_nonfinite_values_never_leak(self, backend):
        args = _stereo_inputs(seed=4)
        args[0] = args[0].clone()
        args[0].view(-1)[::5] = float("nan")
        args[0].view(-1)[1::7] = float("inf")
        with torch.no_grad():
            values, valid, reason, _ = backward_reproject(*args, 0.05, 0.3, backend=self.backend_arg(backend))
        assert torch.isfinite(values).all()
        assert (reason == int(Reason.NONFINITE)).any()


class TestTemporalBlend(BaseTester):
    def _inputs(self, dtype=torch.float32, device="cpu", B=2, C=3, H=5, W=7, seed=0):
        g = torch.Generator().manual_seed(seed)
        cur = torch.rand(B, C, H, W, generator=g, dtype=dtype).to(device)
        hist = torch.rand(B, C, H, W, generator=g, dtype=dtype).to(device)
        n = torch.randint(0, 300, (B, 1, H, W), generator=g).to(device=device, dtype=dtype)
        valid = (torch.rand(B, 1, H, W, generator=g) > 0.3).to(device)
        return cur, hist, n, valid

    def test_smoke(self, device, dtype):
        cur, hist, n, valid = self._inputs(dtype, device)
        out, n_out = temporal_blend(cur, hist, n, valid)
        a = torch.maximum(1.0 / (n + 1.0), torch.tensor(0.2, dtype=dtype, device=device))
        torch.testing.assert_close(out, torch.where(valid, (1 - a) * hist + a * cur, cur))
        assert torch.equal(n_out, torch.where(valid, torch.clamp(n + 1, max=255.0), torch.ones_like(n)))

    @pytest.mark.parametrize("B,C,H,W", [(1, 1, 1, 1), (2, 3, 4, 5), (1, 8, 9, 2)])
    def test_cardinality(self, B, C, H, W):
        out, n = temporal_blend(*self._inputs(B=B, C=C, H=H, W=W))
        assert out.shape == (B, C, H, W) and n.shape == (B, 1, H, W)

    def test_exceptions(self):
        cur, hist, n, valid = self._inputs()
        with pytest.raises(ShapeError, match="temporal_blend: history_color"):  # named, not torch's broadcasting error
            temporal_blend(cur, hist[..., :-1], n, valid)
        with pytest.raises(ParameterError, match="temporal_blend: history_rounding must be one of"):
            temporal_blend(cur, hist, n, valid, history_rounding="nearest")

    @pytest.mark.parametrize("history_rounding", ["none", "bmfr"])
    def test_gradcheck(self, history_rounding):
        cur, hist, n, valid = self._inputs(torch.float64, H=3, W=4)
        n = n + 0.3  # interpolated counts
        conf = torch.rand(valid.shape, dtype=torch.float64)
        args = [x.clone().requires_grad_(True) for x in (cur, hist, conf)]
        alpha = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda c, h, s, a: temporal_blend(c, h, n, s, a, history_rounding=history_rounding)[0],
            (*args, alpha),
            eps=1e-6,
            atol=1e-5,
        )

    @pytest.mark.parametrize("history_rounding", ["none", "bmfr"])
    def test_module_equals_function(self, backend, history_rounding):
        """TemporalReprojection is backward_reproject of [history colour, length] followed by this blend."""
        m = TemporalReprojection(0.05, 0.3, backend=self.backend_arg(backend), history_rounding=history_rounding)
        xs = dict(zip(m.input_names, example_inputs(m, height=10, width=12)))
        g = torch.Generator().manual_seed(1)
        xs["history_len"] = torch.randint(1, 12, xs["history_len"].shape, generator=g).float()  # integer counts
        with torch.no_grad():
            color, n, valid = m(*[xs[k] for k in m.input_names])
            warped, valid_w, _, _ = backward_reproject(
                torch.cat([xs["history_color"], xs["history_len"]], 1),
                xs["prev_depth"],
                xs["prev_normal"],
                xs["prev_K"],
                xs["prev_cam_from_world"],
                xs["depth"],
                xs["normal"],
                xs["K"],
                xs["cam_from_world"],
                m.position_threshold,
                m.normal_threshold,
                backend=self.backend_arg(backend),
            )
            ref, n_ref = temporal_blend(
                xs["current_color"],
                warped[:, :3],
                warped[:, 3:],
                valid_w,
                m.alpha,
                m.warmup,
                m.max_history,
                history_rounding,
            )
        assert valid.any() and (~valid).any()
        assert bool((n == n.round()).all()) == (history_rounding == "bmfr")
        self.assert_identical((color, n, valid), (ref, n_ref, valid_w))

    def test_restart_where_discarded(self):
        cur, hist, n, valid = self._inputs()
        hist = torch.where(valid, hist, torch.full_like(hist, float("nan")))  # discarded history may be garbage
        out, n_out = temporal_blend(cur, hist, n, valid)
        assert torch.isfinite(out).all()
        assert torch.equal(out[~valid.expand_as(out)], cur[~valid.expand_as(cur)])
        assert (n_out[~valid] == 1).all()

    def test_fixed_ema_without_warmup(self):
        cur, hist, n, valid = self._inputs()
        out, _ = temporal_blend(cur, hist, n, torch.ones_like(valid), alpha=0.2, warmup=False)
        torch.testing.assert_close(out, 0.8 * hist + 0.2 * cur)
