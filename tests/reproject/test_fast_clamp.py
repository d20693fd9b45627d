"""Fast-history clamping (NVIDIA NRD's RELAX): the op :func:`fast_history_clamp` against a numpy definition, its
module and ONNX export, the :class:`FastClamp` settings, and the temporal step that keeps a fast history beside
the slow one (:func:`stereorepro.accumulate.temporal_step` with ``TemporalReprojection.fast_clamp``) on every
backend. The stereo driver's use of it is tested in tests/test_accumulate.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from base import BaseTester
from stereorepro import (
    View,
    Blend,
    FastClamp,
    FastHistoryClamp,
    History,
    TemporalReprojection,
    export_onnx,
    fast_history_clamp,
    intrinsics_from_fov,
    temporal_reproject,
)
from stereorepro._testing import camera_pair, default_scene, raycast
from stereorepro.accumulate import EyeState, temporal_step, warp_history
from stereorepro.errors import ParameterError, ParameterTypeError, ShapeError

THR = (0.2, 0.3)


def numpy_clamp(color, fast, sigma, radius):
    """The definition, pixel by pixel: the finite in-frame values of ``fast`` in the (2r+1)² window, their mean
    and population standard deviation per channel; ``color`` clamped to mean ± sigma·std (unchanged where the
    window has no finite value)."""
    c, f = np.asarray(color, np.float64), np.asarray(fast, np.float64)
    out = c.copy()
    B, C, H, W = c.shape
    for b in range(B):
        for ch in range(C):
            for y in range(H):
                for x in range(W):
                    win = f[b, ch, max(0, y - radius) : y + radius + 1, max(0, x - radius) : x + radius + 1]
                    win = win[np.isfinite(win)]
                    if win.size:
                        mu, sd = win.mean(), win.std()
                        out[b, ch, y, x] = min(max(c[b, ch, y, x], mu - sigma * sd), mu + sigma * sd)
    return out


def _random(shape=(2, 3, 7, 9), seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=dtype), torch.rand(shape, generator=g, dtype=dtype)


class TestOp(BaseTester):
    @pytest.mark.parametrize("sigma, radius", [(2.0, 1), (0.5, 1), (1.0, 2), (2.0, 0), (0.0, 1), (1.5, 4)])
    def test_against_numpy(self, sigma, radius):
        """Random colours far outside and inside the boxes, every border case (radius 4 > half the height)."""
        color, fast = _random()
        color = 3 * color - 1  # some above, some below, some inside
        got = fast_history_clamp(color, fast, sigma, radius)
        np.testing.assert_allclose(got.numpy(), numpy_clamp(color, fast, sigma, radius), rtol=0, atol=1e-12)
        assert not torch.equal(got, color)

    def test_inside_the_box_is_the_identity(self):
        """A colour inside its box comes back bit for bit: a linear ramp is its own window mean in the interior
        and within one standard deviation at the borders."""
        y, x = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
        ramp = (0.1 * x + 0.05 * y)[None, None].expand(1, 3, 6, 8).contiguous()
        assert torch.equal(fast_history_clamp(ramp, ramp), ramp)
        assert torch.equal(fast_history_clamp(ramp.half(), ramp.half()), ramp.half())

    def test_radius_zero_and_sigma_zero(self):
        """radius 0: the box is the pixel's fast value (σ = 0); sigma 0: the window mean."""
        color, fast = _random()
        assert torch.equal(fast_history_clamp(color, fast, 2.0, 0), fast)
        mean = torch.nn.functional.avg_pool2d(fast, 3, 1, 1, count_include_pad=False)
        torch.testing.assert_close(fast_history_clamp(color, fast, 0.0, 1), mean, rtol=0, atol=1e-12)

    def test_nonfinite(self):
        """Non-finite fast values are left out of the moments; a window without a finite value leaves the colour
        as it is; a NaN colour stays NaN, ±inf is clamped to the box."""
        color, fast = _random(seed=1)
        fast[0, 0, 2, 3], fast[0, 1, 4, 4], fast[1, 2, 0, 0] = float("nan"), float("inf"), -float("inf")
        fast[1, 0, :3, :3] = float("nan")  # the corner pixel's whole 2x2 window, more around it
        color[0, 0, 1, 1], color[0, 2, 3, 3], color[1, 1, 5, 5] = float("nan"), float("inf"), -float("inf")
        got = fast_history_clamp(color, fast)
        np.testing.assert_allclose(got.numpy(), numpy_clamp(color, fast, 2.0, 1), rtol=0, atol=1e-12)
        assert torch.isnan(got[0, 0, 1, 1]) and torch.isfinite(got[0, 2, 3, 3]) and torch.isfinite(got[1, 1, 5, 5])
        assert float(got[1, 0, 0, 0]) == float(color[1, 0, 0, 0])  # no finite value in its window

    @pytest.mark.parametrize("radius", [1, 2])
    def test_finite_path_equals_masked_path(self, radius):
        """All-finite fast values take the path without finite masks: byte for byte what the masked path gives
        (a NaN at one pixel sends the call down the masked path; every window without it is unchanged), and on
        the numpy definition at the borders (radius 2 on a 7-pixel-high frame)."""
        color, fast = _random(dtype=torch.float32)
        color = 3 * color - 1
        plain = fast_history_clamp(color, fast, 2.0, radius)
        holed = fast.clone()
        holed[1, 2, 3, 4] = float("nan")
        masked = fast_history_clamp(color, holed, 2.0, radius)
        away = torch.ones_like(plain, dtype=torch.bool)
        away[1, 2, 3 - radius : 3 + radius + 1, 4 - radius : 4 + radius + 1] = False
        assert torch.equal(plain[away], masked[away]) and not torch.equal(plain, masked)
        np.testing.assert_allclose(plain.double().numpy(), numpy_clamp(color, fast, 2.0, radius), rtol=0, atol=1e-6)

    @pytest.mark.parametrize("radius", [0, 1, 2, 4])
    def test_backends_agree(self, backend, radius):
        """The native core gives torch's bytes: float32, float16 and mixed inputs, non-finite fast values (the
        masked path) and colours, every border (radius 4 on a 7-pixel-high frame)."""
        nan, inf = float("nan"), float("inf")
        color, fast = _random(dtype=torch.float32, seed=radius)
        color = 3 * color - 1
        color[0, 1, 1, 1], color[1, 1, 5, 5], color[0, 2, 3, 3] = nan, -inf, inf
        holed = fast.clone()
        holed[0, 0, 2, 3], holed[1, 2, 0, 0], holed[1, 0, :3, :3] = nan, inf, nan
        for c_dtype, f_dtype in ((torch.float32,) * 2, (torch.float16,) * 2, (torch.float16, torch.float32)):
            for f in (fast, holed):
                args = (color.to(c_dtype), f.to(f_dtype), 1.5, radius)
                want = fast_history_clamp(*args, backend="torch")
                got = fast_history_clamp(*args, backend=self.backend_arg(backend))
                nans = torch.isnan(want)  # NaN where NaN (the payload bits are the implementation's)
                assert torch.equal(torch.isnan(got), nans) and int(nans.sum()) == 1  # the NaN colour stays NaN
                self.assert_identical([got.masked_fill(nans, 0)], [want.masked_fill(nans, 0)])

    def test_backend_choice(self):
        """The one backend rule: native refuses autograd and float64 with the reason; auto falls back to torch."""
        color, fast = _random(dtype=torch.float32)
        with pytest.raises(RuntimeError, match="requires grad"):
            fast_history_clamp(color.clone().requires_grad_(), fast, backend="native")
        with pytest.raises(RuntimeError, match="float64"):
            fast_history_clamp(color.double(), fast.double(), backend="native")
        with pytest.raises(ParameterError, match="backend"):
            fast_history_clamp(color, fast, backend="cuda")
        grad = color.clone().requires_grad_()
        fast_history_clamp(grad, fast).sum().backward()  # auto: torch, differentiable
        assert grad.grad is not None

    def test_dtypes(self):
        color, fast = _random(dtype=torch.float32)
        for dtype in (torch.float16, torch.bfloat16, torch.float32):
            out = fast_history_clamp(color.to(dtype), fast.to(dtype))
            assert out.dtype == dtype
            ref = numpy_clamp(color.to(dtype).double(), fast.to(dtype).double(), 2.0, 1)
            np.testing.assert_allclose(out.double().numpy(), ref, rtol=0, atol=1e-2 if dtype != torch.float32 else 1e-6)

    def test_gradcheck(self):
        """float64 gradients in the colour, the fast history and a tensor sigma (inputs away from the kinks)."""
        color, fast = _random(shape=(1, 2, 4, 5), seed=2)
        color = (3 * color - 1).requires_grad_()
        fast = fast.requires_grad_()
        sigma = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda c, f, s: fast_history_clamp(c, f, s), (color, fast, sigma))

    def test_constant_window_has_finite_gradient(self):
        """σ = 0 (a constant window): the gradient is finite (the square root's is not taken there)."""
        fast = torch.full((1, 1, 4, 4), 0.5, dtype=torch.float64, requires_grad=True)
        color = torch.full((1, 1, 4, 4), 2.0, dtype=torch.float64, requires_grad=True)
        fast_history_clamp(color, fast).sum().backward()
        assert torch.isfinite(fast.grad).all() and torch.isfinite(color.grad).all()
        assert float(color.grad.abs().max()) == 0.0  # clamped everywhere

    def test_exceptions(self):
        color, fast = _random()
        with pytest.raises(ShapeError, match="fast_color"):
            fast_history_clamp(color, fast[:, :2])
        with pytest.raises(ShapeError, match="color"):
            fast_history_clamp(color[0], fast[0])
        with pytest.raises(ParameterTypeError, match="color"):
            fast_history_clamp(color.long(), fast)
        for sigma in (-1.0, float("nan"), float("inf")):
            with pytest.raises(ParameterError, match="sigma"):
                fast_history_clamp(color, fast, sigma)
        with pytest.raises(ParameterError, match="radius"):
            fast_history_clamp(color, fast, 2.0, -1)
        for radius in (1.0, True, "1"):
            with pytest.raises(ParameterTypeError, match="radius"):
                fast_history_clamp(color, fast, 2.0, radius)


class TestModule(BaseTester):
    def test_module_equals_function(self):
        color, fast = _random(dtype=torch.float32)
        m = FastHistoryClamp(1.5, 2)
        assert torch.equal(m(color, fast), fast_history_clamp(color, fast, 1.5, 2))
        assert "sigma=1.5, radius=2" in repr(m)

    def test_exceptions(self):
        with pytest.raises(ParameterError, match="FastHistoryClamp: sigma"):
            FastHistoryClamp(-1.0)
        with pytest.raises(ParameterError, match="FastHistoryClamp: radius"):
            FastHistoryClamp(2.0, -2)

    @pytest.mark.onnx
    def test_onnx_parity(self, tmp_path):
        """onnxruntime at sizes other than the export's (symbolic B, H, W), non-finite fast values included, and
        onnx.checker + the onnx.reference evaluator."""
        ort = pytest.importorskip("onnxruntime")
        onnx = pytest.importorskip("onnx")
        from onnx.reference import ReferenceEvaluator

        m = FastHistoryClamp(2.0, 1)
        example = tuple(x.float() for x in _random((1, 3, 6, 8)))
        path = export_onnx(m, tmp_path / "clamp.onnx", inputs=example)
        onnx.checker.check_model(onnx.load(str(path)), full_check=True)
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        reference = ReferenceEvaluator(str(path))
        for shape, seed in (((2, 3, 17, 23), 3), ((1, 3, 5, 4), 4)):
            color, fast = (x.float() for x in _random(shape, seed))
            color = 3 * color - 1
            fast[0, 0, 1, 1], fast[0, 1, 2, 2] = float("nan"), float("inf")
            want = m(color, fast).numpy()
            feeds = {"color": color.numpy(), "fast_color": fast.numpy()}
            np.testing.assert_allclose(sess.run(None, feeds)[0], want, rtol=0, atol=1e-5)  # E[x²] − μ² in float32
            np.testing.assert_allclose(reference.run(None, feeds)[0], want, rtol=0, atol=1e-5)


class TestSettings(BaseTester):
    def test_defaults(self):
        assert FastClamp() == (0.5, 2.0, 1)
        m = TemporalReprojection(*THR)
        assert m.fast_clamp is None
        m.fast_clamp = FastClamp(0.25)
        assert m.fast_clamp.alpha == 0.25 and "fast_clamp=FastClamp(alpha=0.25" in repr(m)

    @pytest.mark.parametrize(
        "value, match, error",
        [
            (FastClamp(alpha=0.0), "fast_clamp.alpha", ParameterError),
            (FastClamp(alpha=1.5), "fast_clamp.alpha", ParameterError),
            (FastClamp(alpha=float("nan")), "fast_clamp.alpha", ParameterError),
            (FastClamp(sigma=-1.0), "fast_clamp.sigma", ParameterError),
            (FastClamp(sigma=float("inf")), "fast_clamp.sigma", ParameterError),
            (FastClamp(radius=-1), "fast_clamp: radius", ParameterError),
            (FastClamp(radius=1.5), "fast_clamp: radius", ParameterTypeError),
            (FastClamp(alpha="0.5"), "fast_clamp.alpha", ParameterTypeError),
            ((0.5, 2.0, 1), "fast_clamp must be None or a FastClamp", ParameterError),
            (True, "fast_clamp must be None or a FastClamp", ParameterError),
        ],
    )
    def test_exceptions(self, value, match, error):
        from stereorepro import SpatiotemporalReprojection

        m = TemporalReprojection(*THR)
        with pytest.raises(error, match=f"TemporalReprojection: {match}"):
            m.fast_clamp = value
        assert m.fast_clamp is None
        st = SpatiotemporalReprojection(*THR)
        with pytest.raises(error, match=f"SpatiotemporalReprojection: {match}"):
            st.fast_clamp = value

    def test_forward_refuses(self):
        """The module's forward carries one history: with a fast clamp set it raises instead of ignoring it."""
        m = TemporalReprojection(*THR)
        m.fast_clamp = FastClamp()
        d = torch.full((1, 1, 2, 2), 2.0)
        n = torch.zeros(1, 3, 2, 2)
        n[:, 2] = -1
        view = (d, n, intrinsics_from_fov(60.0, 2, 2), torch.eye(4)[None])
        with pytest.raises(ParameterError, match="fast_clamp"):
            m(torch.ones(1, 3, 2, 2), *view, torch.ones(1, 3, 2, 2), torch.ones(1, 1, 2, 2), *view)


# --- the temporal step --------------------------------------------------------------------------------------------

H, W = 24, 32


def _static_camera(h=H, w=W):
    depth = torch.full((1, 1, h, w), 2.0)
    normal = torch.zeros(1, 3, h, w)
    normal[:, 2] = -1
    return depth, normal, intrinsics_from_fov(60.0, w, h), torch.eye(4)[None]


def _step_response(alpha, fast_clamp, noise=0.3, frames=50, step_at=20, seed=0):
    """A static light switched from 0.2 to 0.8 at ``step_at``, seen by a still camera with uniform relative noise
    ±``noise``: the mean error of the accumulated colour per frame after the step."""
    m = TemporalReprojection(0.03, 0.2, alpha=alpha, backend="torch")
    m.fast_clamp = fast_clamp
    cam = _static_camera()
    g = torch.Generator().manual_seed(seed)
    state, errors = None, []
    for f in range(frames):
        level = 0.2 if f < step_at else 0.8
        current = level * (1 + noise * (2 * torch.rand(1, 3, H, W, generator=g) - 1))
        state, _, _ = temporal_step(m, state, current, *cam)
        if f >= step_at:
            errors.append(abs(float(state.color.mean()) - level))
    return errors


def _frames_to(errors, tolerance):
    """Frames after the step until the error stays below ``tolerance``."""
    return next(i for i in range(len(errors)) if max(errors[i:]) < tolerance) + 1


def _moving(frames=4, seed=0):
    """A moving camera over the analytic scene: per frame (colour, depth, normal, K, cam_from_world), the colour
    the scene's noisy shading (1-spp-like), so that kept, discarded and clamped pixels all occur."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(frames):
        _, cam = camera_pair(H, W, forward=0.03 * i, yaw_deg=0.4 * i)
        gb = raycast(cam, default_scene())
        noisy = gb.color * (2 * torch.rand(gb.color.shape, generator=g, dtype=torch.float64))
        if i == frames - 1:
            noisy = noisy * 3  # the light brightens on the last frame: the clamp acts
        out.append((noisy.float(), gb.depth.float(), gb.normal.float(), cam.K, cam.cam_from_world))
    return out


def _run_steps(module, frames, state=None):
    states = []
    for f in frames:
        state, valid, reason = temporal_step(module, state, *f)
        states.append((state, valid, reason))
    return states


def _module(backend="torch", fast_clamp=FastClamp(), **kw):
    m = TemporalReprojection(*THR, backend=backend, **kw)
    m.fast_clamp = fast_clamp
    return m


class TestTemporalStep(BaseTester):
    def test_step_change_converges_faster(self):
        """The static light's step (0.2 → 0.8, ±30 % noise): frames until the mean error stays within 10 % of the
        step. Measured: slow EMA 0.1: 22 unclamped, 12 clamped (fast alpha 0.5, 2σ, 3×3); 0.2: 11 and 8. A
        constant light keeps no lag and no bias with the clamp."""
        for alpha, slow_frames, fast_frames in ((0.1, 22, 12), (0.2, 11, 8)):
            plain = _frames_to(_step_response(alpha, None), 0.06)
            clamped = _frames_to(_step_response(alpha, FastClamp(0.5)), 0.06)
            assert plain >= slow_frames - 1, (alpha, plain)
            assert clamped <= fast_frames + 1, (alpha, clamped)
        constant = _step_response(0.1, FastClamp(0.5), frames=20, step_at=0)
        assert max(constant[10:]) < 0.005

    def test_equals_two_temporal_reproject_calls(self):
        """The fused step is the function-level recipe: two temporal_reproject calls sharing the length, the
        slow one clamped where kept (torch backend: the same bytes)."""
        frames = _moving(5)
        m = _module(alpha=0.1, fast_clamp=FastClamp(0.33, 1.5, 2))
        states = _run_steps(m, frames)
        (color, *gbuffer), (first, *_) = frames[0], states[0]
        prev = View(*gbuffer)
        slow = fast = History(color, torch.ones_like(gbuffer[0]))
        assert torch.equal(first.color, color) and torch.equal(first.fast_color, color)
        for (color, *gbuffer), (state, valid, _) in zip(frames[1:], states[1:]):
            view = View(*gbuffer)
            s = temporal_reproject(color, view, slow, prev, THR, blend=Blend(0.1), backend="torch")
            f = temporal_reproject(color, view, History(fast.color, slow.length), prev, THR, blend=Blend(0.33))
            slow = History(torch.where(s.valid, fast_history_clamp(s.color, f.color, 1.5, 2), s.color), s.history_len)
            fast, prev = f.history, view
            assert torch.equal(state.color, slow.color) and torch.equal(state.history_len, slow.length)
            assert torch.equal(state.fast_color, fast.color) and torch.equal(valid, s.valid)
        assert int(states[-1][1].sum()) > 0.5 * H * W and int((~states[-1][1]).sum()) > 0  # kept and discarded

    def test_backends_agree(self, backend):
        """torch (general path), its fast path and the native kernel: the same step, clamp on, footprint
        weighting and BMFR rounding with it."""
        frames = _moving(4)
        for kw in ({}, {"history_rounding": "bmfr"}):
            m = _module(self.backend_arg(backend), **kw)
            m.footprint_weighting = bool(kw)
            ref = _module("torch", **kw)
            ref.footprint_weighting = bool(kw)
            from stereorepro.reproject import functional

            fast_path = functional.FAST_PATH
            functional.FAST_PATH = False
            try:
                want = _run_steps(ref, frames)
            finally:
                functional.FAST_PATH = fast_path
            got = _run_steps(m, frames)
            for (a, va, ra), (b, vb, rb) in zip(got, want):
                assert torch.equal(va, vb) and torch.equal(ra, rb)
                assert torch.equal(a.color, b.color) and torch.equal(a.fast_color, b.fast_color)
                assert torch.equal(a.history_len, b.history_len)

    def test_off_is_unchanged(self, backend):
        """fast_clamp None gives the bytes of a module that never had one, also from a state carrying a fast
        history; the state then carries none."""
        frames = _moving(3)
        plain = _run_steps(TemporalReprojection(*THR, backend=self.backend_arg(backend)), frames)
        m = _module(self.backend_arg(backend))
        m.fast_clamp = None
        off = _run_steps(m, frames)
        for (a, *_), (b, *_) in zip(plain, off):
            assert torch.equal(a.color, b.color) and torch.equal(a.history_len, b.history_len)
            assert b.fast_color is None
        carried = EyeState(
            *[getattr(plain[0][0], k) for k in ("color", "history_len", "depth", "normal", "K")],
            plain[0][0].cam_from_world,
            torch.rand(1, 3, H, W),
        )
        again = temporal_step(m, carried, *frames[1])[0]
        assert torch.equal(again.color, plain[1][0].color) and again.fast_color is None

    def test_restarts_and_first_frame(self):
        """First frame: the fast history is the current frame; discarded pixels restart both histories with the
        current sample, unclamped; the lengths are those of the unclamped step."""
        frames = _moving(3)
        m = _module()
        states = _run_steps(m, frames)
        assert torch.equal(states[0][0].fast_color, frames[0][0]) and torch.equal(states[0][0].color, frames[0][0])
        state, valid, _ = states[-1]
        cur = frames[-1][0]
        gone = ~valid.expand_as(cur)
        assert torch.equal(state.color[gone], cur[gone]) and torch.equal(state.fast_color[gone], cur[gone])
        plain = _run_steps(TemporalReprojection(*THR, backend="torch"), frames)
        assert torch.equal(plain[-1][0].history_len, state.history_len)  # n only depends on the warps
        assert not torch.equal(plain[-1][0].color, state.color)

    def test_state_without_fast_history(self):
        """A state with no fast history (the clamp switched on mid-sequence) starts it from the slow colour."""
        frames = _moving(3)
        plain = _run_steps(TemporalReprojection(*THR, backend="torch"), frames[:2])
        m = _module()
        got = temporal_step(m, plain[-1][0], *frames[2])[0]
        seeded = EyeState(
            *[getattr(plain[-1][0], k) for k in ("color", "history_len", "depth", "normal", "K")],
            plain[-1][0].cam_from_world,
            plain[-1][0].color,
        )
        assert torch.equal(got.color, temporal_step(m, seeded, *frames[2])[0].color)
        bad = EyeState(
            *[getattr(plain[-1][0], k) for k in ("color", "history_len", "depth", "normal", "K")],
            plain[-1][0].cam_from_world,
            torch.ones(1, 2, H, W),
        )
        with pytest.raises(ShapeError, match="fast_color"):
            temporal_step(m, bad, *frames[2])

    def test_warp_history_carries_the_fast_colour(self):
        """warp_history(return_fast=True) warps the fast history in the same warp; without it the 4-tuple."""
        frames = _moving(2)
        m = _module()
        state = _run_steps(m, frames[:1])[0][0]
        state = EyeState(
            state.color, state.history_len, state.depth, state.normal, state.K, state.cam_from_world, 2 * state.color
        )
        gb = frames[1][1:]
        color, n, valid, reason, fast = warp_history(m, state, *gb, return_fast=True)
        assert torch.equal(fast, 2 * color)
        assert len(warp_history(m, state, *gb)) == 4
        assert torch.equal(warp_history(m, state, *gb)[0], color)

    def test_gradients(self):
        """A soft module in float64: gradcheck of the step in the current colour of an interior patch, through
        both blends and the clamp."""
        frames = [tuple(x.double() if x.is_floating_point() else x for x in f) for f in _moving(2)]
        m = _module(soft=True)
        state = temporal_step(m, None, *frames[0])[0]
        color = frames[1][0]

        def step(patch):
            full = color.clone()
            full[..., 8:11, 12:16] = patch
            return temporal_step(m, state, full, *frames[1][1:])[0].color

        patch = color[..., 8:11, 12:16].clone().requires_grad_()
        assert torch.autograd.gradcheck(step, (patch,), fast_mode=True)
