"""backward_reproject and temporal_blend as operations of their own (the stereo and temporal ops that build on them
are tested in test_reproject.py)."""

from __future__ import annotations

import pytest
import torch

from base import BaseTester
from stereorepro import StereoReprojection, TemporalReprojection, backward_reproject, stereo_reproject, temporal_blend
from stereorepro.errors import ShapeError
from stereorepro.io.onnx import example_inputs
from stereorepro.reproject import Reason


def _stereo_inputs(dtype=torch.float32, device="cpu", H=12, W=16, seed=0, C=3):
    """backward_reproject inputs from the example scene: values with C channels, G-buffers, cameras."""
    m = StereoReprojection(0.05, 0.3)
    xs = dict(zip(m.input_names, example_inputs(m, height=H, width=W, seed=seed, dtype=torch.float64)))
    g = torch.Generator().manual_seed(seed)
    xs["src_color"] = torch.rand(1, C, H, W, generator=g, dtype=torch.float64)
    return [xs[n].to(device=device, dtype=dtype if n not in ("src_K", "dst_K", "src_cam_from_world",
                                                             "dst_cam_from_world") else torch.float64)
            for n in m.input_names]


class TestBackwardReproject(BaseTester):
    def test_smoke(self, device, dtype, backend):
        self.skip_unless_runs(backend, dtype, device)
        with torch.no_grad():
            values, valid, reason, conf = backward_reproject(*_stereo_inputs(dtype, device), 0.05, 0.3,
                                                             backend=self.backend_arg(backend))
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

    def test_backends_identical(self, backend):
        """Each backend gives the bytes of the torch general path (hard tests)."""
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
        with pytest.raises(RuntimeError):
            temporal_blend(cur, hist[..., :-1], n, valid)

    def test_gradcheck(self):
        cur, hist, n, valid = self._inputs(torch.float64, H=3, W=4)
        conf = torch.rand(valid.shape, dtype=torch.float64)
        args = [x.clone().requires_grad_(True) for x in (cur, hist, conf)]
        alpha = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda c, h, s, a: temporal_blend(c, h, n, s, a)[0], (*args, alpha),
                                        eps=1e-6, atol=1e-5)

    def test_module_equals_function(self, backend):
        """TemporalReprojection is backward_reproject of [history colour, length] followed by this blend."""
        m = TemporalReprojection(0.05, 0.3, backend=self.backend_arg(backend))
        xs = dict(zip(m.input_names, example_inputs(m, height=10, width=12)))
        with torch.no_grad():
            color, n, valid = m(*[xs[k] for k in m.input_names])
            warped, valid_w, _, _ = backward_reproject(
                torch.cat([xs["history_color"], xs["history_len"]], 1), xs["prev_depth"], xs["prev_normal"],
                xs["prev_K"], xs["prev_cam_from_world"], xs["depth"], xs["normal"], xs["K"], xs["cam_from_world"],
                m.position_threshold, m.normal_threshold, backend=self.backend_arg(backend))
            ref, n_ref = temporal_blend(xs["current_color"], warped[:, :3], warped[:, 3:], valid_w, m.alpha,
                                        m.warmup, m.max_history)
        assert valid.any() and (~valid).any()
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
