"""ReprojectionDenoiser: temporal reprojection + a learned denoiser in one graph (stereorepro.denoise), and the
example that deploys it (examples/onnx_denoise_sequence.py) in smoke mode."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from torch import nn

from base import BaseTester
from conftest import load_script
from stereorepro import (
    CameraError,
    ReprojectionDenoiser,
    ShapeError,
    TemporalReprojection,
    backward_reproject,
    denoise_features,
    empty_history,
    export_onnx,
    reproject_denoise,
    reprojection_features,
    stereo_reproject,
    temporal_step,
)
from stereorepro.denoise import (
    ALBEDO_FEATURES,
    FEATURES,
    OTHER_NAMES,
    RECURRENT_FEATURES,
    STEREO_FEATURES,
    denoiser_example_inputs,
    empty_state,
    feature_channels,
    feature_names,
)
from stereorepro.errors import StereoreproError
from stereorepro.reproject import History, View
from stereorepro.io.onnx import onnx_input_dims
from stereorepro._testing import camera_pair, default_scene, raycast

THR = (0.05, 0.2)  # at these sizes about half the example inputs' pixels keep their history
H, W = 24, 32


class TinyDenoiser(nn.Module):
    """A residual two-layer CNN: (B, C_in, H, W) → (B, 3, H, W) (no ops the ONNX exporter lacks)."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, 8, 3, padding=1)
        self.out = nn.Conv2d(8, 3, 1)

    def forward(self, x):
        return x[:, :3] + self.out(torch.relu(self.conv(x)))


def make(stereo: bool = False, recurrent: bool = False, albedo: bool = False, seed: int = 0, **kw):
    """A ReprojectionDenoiser with a TinyDenoiser for the options' features (fixed seed)."""
    torch.manual_seed(seed)
    net = TinyDenoiser(feature_channels(stereo, recurrent, albedo))
    return ReprojectionDenoiser(net, *THR, stereo=stereo, recurrent=recurrent, albedo=albedo, **kw).eval()


#: (stereo, recurrent, albedo) of every variant with a recurrent or albedo input.
NEW_OPTIONS = [(s, r, a) for s in (False, True) for r in (False, True) for a in (False, True) if r or a]
OPTION_IDS = ["-".join(n for n, on in zip(("stereo", "recurrent", "albedo"), o) if on) for o in NEW_OPTIONS]


def inputs(model, height=H, width=W, dtype=torch.float32, seed=0, device="cpu"):
    return tuple(
        x.to(device) for x in denoiser_example_inputs(model, height=height, width=width, dtype=dtype, seed=seed)
    )


def frame(i):
    """G-buffer, camera and a noisy colour of frame i of a short head motion (forward and turning)."""
    _, cam = camera_pair(H, W, baseline=0.065, forward=0.03 * i, yaw_deg=0.3 * i)
    g = raycast(cam, default_scene())
    noise = 2 * torch.rand(g.color.shape, generator=torch.Generator().manual_seed(i), dtype=torch.float64)
    return dict(
        color=(g.color * noise).float(),
        depth=g.depth.float(),
        normal=g.normal.float(),
        K=cam.K.float(),
        cam_from_world=cam.cam_from_world.float(),
    )


def assert_parity(ref, got, atol=1e-4):
    """onnxruntime's (numpy) outputs against torch's: the denoised frame within ``atol``, the state within 1e-5."""
    for name, r, g in zip(ReprojectionDenoiser.output_names, ref, got):
        tol = atol if name == "denoised" else 1e-5
        assert g.shape == tuple(r.shape), (name, g.shape, r.shape)
        diff = float(np.abs(g.astype(np.float64) - r.detach().double().numpy()).max())
        assert diff <= tol, f"{name}: max |onnxruntime - torch| = {diff:.3g} > {tol:g}"


class TestReprojectionDenoiser(BaseTester):
    @pytest.mark.parametrize("stereo", [False, True], ids=["temporal", "stereo"])
    def test_smoke(self, stereo, device, dtype, backend):
        self.skip_unless_runs(backend, dtype, device)
        model = make(stereo, backend=self.backend_arg(backend)).to(device=device, dtype=dtype)
        xs = inputs(model, dtype=dtype, device=device)
        assert len(xs) == len(model.input_names) == 11 + 5 * stereo
        with torch.no_grad():
            denoised, color, n = model(*xs)
        assert denoised.shape == color.shape == (1, 3, H, W) and n.shape == (1, 1, H, W)
        assert denoised.dtype == color.dtype == dtype and denoised.device.type == device.type
        assert torch.isfinite(denoised).all() and torch.isfinite(color).all()
        assert ((n >= 1) & (n <= 255)).all()

    def test_feature_layout(self):
        """The channels and their order, as documented in FEATURES / STEREO_FEATURES."""
        g = torch.Generator().manual_seed(0)
        color = torch.rand(2, 3, 5, 7, generator=g) * 4 - 1  # negative values are clamped before log1p
        n = torch.randint(1, 10, (2, 1, 5, 7), generator=g).float()
        valid = torch.rand(2, 1, 5, 7, generator=g) > 0.5
        depth = torch.rand(2, 1, 5, 7, generator=g) + 0.5
        depth[0, 0, 0, :3] = torch.tensor([float("inf"), 0.0, float("nan")])  # no surface
        normal = nn.functional.normalize(torch.randn(2, 3, 5, 7, generator=g), dim=1)
        normal[1, :, 2, 2] = float("nan")
        s_color, s_valid = torch.rand(2, 3, 5, 7, generator=g), torch.rand(2, 1, 5, 7, generator=g) > 0.5
        x = denoise_features(color, n, valid, depth, normal, 16.0, s_color, s_valid)
        assert x.shape == (2, feature_channels(True), 5, 7) == (2, len(FEATURES) + len(STEREO_FEATURES), 5, 7)
        torch.testing.assert_close(x[:, 0:3], torch.log1p(color.clamp_min(0)))
        torch.testing.assert_close(x[:, 3:4], n / 16.0)
        assert torch.equal(x[:, 4:5], valid.float())
        inv = torch.where(torch.isfinite(depth) & (depth > 0), 1 / depth, torch.zeros(()))
        torch.testing.assert_close(x[:, 5:6], inv)
        assert torch.equal(x[0, 5, 0, :3], torch.zeros(3))
        torch.testing.assert_close(x[:, 6:9], torch.nan_to_num(normal, nan=0.0))
        torch.testing.assert_close(x[:, 9:12], torch.log1p(s_color))
        assert torch.equal(x[:, 12:13], s_valid.float())
        assert torch.isfinite(x).all()
        assert denoise_features(color, n, valid, depth, normal, 16.0).shape[1] == feature_channels() == 9

    @pytest.mark.parametrize("stereo", [False, True], ids=["temporal", "stereo"])
    def test_module_equals_function(self, stereo, backend):
        be = self.backend_arg(backend)
        model = make(stereo, backend=be)
        xs = inputs(model)
        with torch.no_grad():
            got = model(*xs)
            other = xs[11:] if stereo else None
            ref = reproject_denoise(*xs[:11], model.denoiser, *THR, alpha=0.2, other=other, backend=be)
            feats, color, n = model.features(*xs)
        for g, r in zip(got, ref):
            assert torch.equal(g, r)
        assert torch.equal(model.denoiser(feats), got[0]) and torch.equal(color, got[1]) and torch.equal(n, got[2])

    def test_state_is_the_temporal_reprojection(self, backend):
        """The returned state and the valid channel are TemporalReprojection's, whatever the denoiser does."""
        be = self.backend_arg(backend)
        model = make(backend=be)
        xs = inputs(model)
        with torch.no_grad():
            feats, color, n = model.features(*xs)
            ref_color, ref_n, ref_valid = TemporalReprojection(*THR, alpha=0.2, backend=be)(*xs)
        assert torch.equal(color, ref_color) and torch.equal(n, ref_n)
        assert torch.equal(feats[:, 4:5], ref_valid.float())
        assert 0.05 < ref_valid.float().mean() < 0.95  # the inputs exercise both kept and discarded pixels

    def test_stereo_channels_are_the_stereo_reprojection(self, backend):
        be = self.backend_arg(backend)
        model = make(stereo=True, backend=be)
        xs = inputs(model)
        with torch.no_grad():
            feats, _, _ = model.features(*xs)
            s_color, s_valid, _ = stereo_reproject(*xs[11:], *xs[1:5], *THR, backend=be)
        torch.testing.assert_close(feats[:, 9:12], torch.log1p(s_color.clamp_min(0)))
        assert torch.equal(feats[:, 12:13], s_valid.float())
        assert 0.05 < s_valid.float().mean() < 1

    def test_sequence_feeds_back_like_temporal_step(self, backend):
        """Over a sequence, starting from empty_history, the state is temporal_step's (first frame: no state)."""
        model = make(backend=self.backend_arg(backend))
        state, history = None, None
        for i in range(4):
            f = frame(i)
            cur = (f["color"], f["depth"], f["normal"], f["K"], f["cam_from_world"])
            history = empty_history(*cur[1:]) if history is None else history
            with torch.no_grad():
                feats, color, n = model.features(*cur, *history)
            state, valid, _ = temporal_step(model.temporal, state, *cur)
            torch.testing.assert_close(color, state.color, atol=1e-6, rtol=1e-6)
            assert torch.equal(n, state.history_len)
            assert torch.equal(feats[:, 4:5], valid.float())
            if i == 0:  # no history: the colour itself, n = 1, nothing valid
                assert torch.equal(color, f["color"]) and (n == 1).all() and not valid.any()
            history = (color, n, *cur[1:])
        assert n.max() == 4  # the history was kept through the sequence

    def test_gradient_reaches_the_denoiser(self):
        model = make(stereo=True).train()
        xs = inputs(model)
        loss = model(*xs)[0].square().mean()
        loss.backward()
        params = list(model.denoiser.parameters())
        assert params and all(p.grad is not None and torch.isfinite(p.grad).all() for p in params)
        assert all(p.grad.abs().sum() > 0 for p in params)
        assert not any(p.requires_grad for name, p in model.named_parameters() if not name.startswith("denoiser."))

    def test_exceptions(self):
        model = make()
        xs = inputs(model)
        with pytest.raises(TypeError, match="denoiser"):
            ReprojectionDenoiser(lambda x: x[:, :3], *THR)
        with pytest.raises(ValueError, match="position_threshold"):
            ReprojectionDenoiser(TinyDenoiser(9), -1.0, 0.3)
        with pytest.raises(ValueError, match="alpha"):
            ReprojectionDenoiser(TinyDenoiser(9), *THR, alpha=0.0)
        with pytest.raises(ShapeError, match="denoiser: expected an output of shape"):
            ReprojectionDenoiser(nn.Conv2d(9, 4, 1), *THR)(*xs)
        with pytest.raises(ShapeError, match=r"denoiser: failed on the features.*C_in = 9"):
            ReprojectionDenoiser(TinyDenoiser(13), *THR)(*xs)  # built for the stereo features
        with pytest.raises(TypeError, match="denoiser: expected it to return a tensor"):
            reproject_denoise(*xs, lambda x: (x,), *THR)
        with pytest.raises(TypeError, match="denoiser"):
            reproject_denoise(*xs, None, *THR)
        with pytest.raises(ShapeError, match="current_color"):
            model(xs[0][:, :2], *xs[1:])
        with pytest.raises(TypeError, match="history_len"):
            model(*xs[:6], xs[6] > 0, *xs[7:])
        bad_K = xs[3].clone()
        bad_K[0, 0, 0] = 0.0
        with pytest.raises(CameraError, match="K"):
            model(*xs[:3], bad_K, *xs[4:])
        with pytest.raises(TypeError, match="stereo=True"):
            model(*xs, *inputs(make(True))[11:])
        stereo = make(True)
        sx = inputs(stereo)
        with pytest.raises(TypeError, match=", ".join(OTHER_NAMES[1:])):
            stereo(*sx[:12])
        with pytest.raises(ShapeError, match="other_color"):
            stereo(*sx[:11], sx[11][..., :-1], *sx[12:])
        with pytest.raises(ValueError, match="other"):
            reprojection_features(*sx[:11], *THR, other=sx[11:14])
        d = sx[1]
        with pytest.raises(ValueError, match="stereo_color and stereo_valid"):
            denoise_features(sx[0], d, d > 0, d, sx[2], 255.0, stereo_color=sx[0])
        with pytest.raises(ValueError, match="max_history"):
            denoise_features(sx[0], d, d > 0, d, sx[2], 0.5)
        with pytest.raises(ShapeError, match="depth"):
            empty_history(d[:, 0], sx[2], sx[3], sx[4])

    @pytest.mark.parametrize("index", range(11, 16))
    @pytest.mark.parametrize("bad", ["size", "batch", "dtype"])
    def test_stereo_errors_name_the_other_eye(self, index, bad):
        """A wrongly shaped, batched or typed other-eye input is named as the user passed it (other_depth, other K,
        ...), never as the stereo op's internal source (src_depth, src_K), in the flat forward and in the View form
        (other=(other_color, other_view)), where the stereo op would call the colour ``color``."""
        stereo = make(True)
        sx = list(inputs(stereo))
        t = sx[index]
        sx[index] = {"size": (t[..., :-1] if t.dim() == 4 else t[:, :2]), "batch": torch.cat([t, t]), "dtype": t.int()}[
            bad
        ]
        name = stereo.input_names[index]
        with pytest.raises((ShapeError, TypeError)) as info:
            stereo(*sx)
        msg = str(info.value)
        assert isinstance(info.value, StereoreproError) and "src" not in msg, msg
        assert msg.startswith((name, name.replace("other_", "other "))), msg

    def test_stereo_errors_name_the_other_eye_views(self):
        """The View form (other=(other_color, other_view)): the colour and the view's batch are named as the user
        passed them, not as the stereo op's ``color`` / ``src``."""
        sx = inputs(make(True))
        view, history, prev = View(*sx[1:5]), History(sx[5], sx[6]), View(*sx[7:11])
        o_view = View(*sx[12:16])
        two = View(*(torch.cat([t, t]) for t in sx[12:16]))
        for other, match in (
            ((sx[11][..., :-1], o_view), r"other_color \(the other eye's colour\): .* W=32"),
            ((sx[11][:, :2], o_view), r"other_color \(the other eye's colour\)"),
            ((sx[11].int(), o_view), "other_color: expected a floating"),
            ((torch.cat([sx[11], sx[11]]), two), "other_view: batch size 2"),
            ((sx[11], sx[12]), r"other: expected \(other_color, other_view: View\)"),
        ):
            with pytest.raises(StereoreproError, match=match):
                reprojection_features(sx[0], view, history, prev, THR, other=other)

    def test_stereo_step_keeps_the_position_test(self):
        """The other eye's stereo step uses the thresholds' own position test: with ``position_test="plane"`` the
        threshold is a fraction of view depth there too (read as a distance it keeps nothing here)."""
        from stereorepro import Blend, Thresholds, temporal_reproject

        sx = inputs(make(True))
        view, history, prev, o_view = View(*sx[1:5]), History(sx[5], sx[6]), View(*sx[7:11]), View(*sx[12:16])
        thr = Thresholds(0.005, 0.2, position_test="plane")
        got = reprojection_features(sx[0], view, history, prev, thr, other=(sx[11], o_view))
        t = temporal_reproject(sx[0], view, history, prev, thr)
        s = stereo_reproject(sx[11], o_view, view, thr)
        assert float(s.valid.float().mean()) > 0.9
        max_history = Blend().max_history
        want = denoise_features(t.color, t.history_len, t.valid, view.depth, view.normal, max_history, *s[:2])
        assert torch.equal(got.features, want)

    # ------------------------------------------------------------------------------------------------ ONNX
    @pytest.mark.onnx
    @pytest.mark.parametrize("stereo", [False, True], ids=["temporal", "stereo"])
    def test_onnx_parity(self, stereo, tmp_path):
        """One ONNX graph, exported at 12x16, run by onnxruntime at two other sizes (symbolic H, W): the denoised
        frame within 1e-4 of torch, the state within 1e-5."""
        ort = pytest.importorskip("onnxruntime")
        model = make(stereo)
        path = export_onnx(model, tmp_path / "m.onnx", inputs=inputs(model, 12, 16))
        dims = onnx_input_dims(path)
        assert dims["current_color"] == ["B", 3, "H", "W"] and dims["history_color"][2:] == ["Hp", "Wp"]
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        assert [o.name for o in sess.get_outputs()] == model.output_names
        for (h, w), seed in (((20, 28), 1), ((33, 47), 2)):
            xs = inputs(model, h, w, seed=seed)
            got = sess.run(None, {n: x.numpy() for n, x in zip(model.input_names, xs)})
            with torch.no_grad():
                ref = model(*xs)
            assert_parity(ref, got)

    def test_parity_check_can_fail(self):
        """assert_parity fails on a denoised frame off by 2e-4 and on a state off by 1e-4."""
        model = make()
        with torch.no_grad():
            ref = model(*inputs(model))
        got = [r.numpy().copy() for r in ref]
        assert_parity(ref, got)
        for i, delta in ((0, 2e-4), (1, 1e-4)):
            bad = list(got)
            bad[i] = bad[i] + np.float32(delta)
            with pytest.raises(AssertionError):
                assert_parity(ref, bad)


def split(model, xs):
    """(current_color, view, history, prev_view, other, prev_denoised, albedo) of ``model``'s flat inputs ``xs``."""
    named = dict(zip(model.input_names, xs))
    other = (named["other_color"], View(*(named[n] for n in OTHER_NAMES[1:]))) if model.stereo else None
    return (
        xs[0],
        View(*xs[1:5]),
        History(xs[5], xs[6]),
        View(*xs[7:11]),
        other,
        named.get("prev_denoised"),
        named.get("albedo"),
    )


class TestRecurrentAndAlbedo(BaseTester):
    """The recurrent input (the denoiser's previous output, warped like the history) and the albedo input."""

    @pytest.mark.parametrize("options", NEW_OPTIONS, ids=OPTION_IDS)
    def test_channel_order(self, options):
        """FEATURES [+ STEREO] [+ RECURRENT] [+ ALBEDO]; the first 9 (13) channels are those of the variant
        without the new inputs, bit for bit."""
        stereo, recurrent, albedo = options
        model = make(*options)
        xs = inputs(model)
        with torch.no_grad():
            feats = model.features(*xs)[0]
            base = make(stereo).features(*xs[: 11 + 5 * stereo])[0]
        names = feature_names(*options)
        assert feats.shape[1] == model.in_channels == feature_channels(*options) == len(names)
        assert names == FEATURES + STEREO_FEATURES * stereo + RECURRENT_FEATURES * recurrent + ALBEDO_FEATURES * albedo
        assert model.feature_names == names and model.input_names[11 + 5 * stereo :] == (
            ["prev_denoised"] * recurrent + ["albedo"] * albedo
        )
        assert torch.equal(feats[:, : base.shape[1]], base)
        if albedo:
            assert torch.equal(feats[:, -3:], xs[-1])
        if recurrent:
            i = names.index("log1p_previous_r")
            assert feats[:, i : i + 3].abs().max() > 0

    def test_recurrent_channels_are_backward_reproject(self, backend):
        """log1p of backward_reproject(previous_output, prev_view → view) where it is valid, 0 elsewhere; valid
        exactly where the history was kept (the same geometry and tests)."""
        be = self.backend_arg(backend)
        model = make(recurrent=True, backend=be)
        xs = inputs(model)
        color, view, history, prev_view, _, previous, _ = split(model, xs)
        with torch.no_grad():
            feats = reprojection_features(color, view, history, prev_view, THR, previous_output=previous, backend=be)[0]
            ref = backward_reproject(previous, prev_view, view, THR, backend=be)
        valid = ref.valid.expand(-1, 3, -1, -1)
        expected = torch.where(valid, torch.log1p(ref.values.clamp_min(0)), torch.zeros(()))
        torch.testing.assert_close(feats[:, 9:12], expected, rtol=1e-6, atol=1e-6)
        assert torch.equal(feats[:, 9:12][~valid], torch.zeros(int((~valid).sum())))
        assert torch.equal(feats[:, 4:5].bool(), ref.valid)
        assert 0.05 < ref.valid.float().mean() < 0.95  # both kept and discarded pixels

    def test_albedo_channels(self):
        model = make(albedo=True)
        xs = list(inputs(model))
        albedo = xs[-1].clone()
        albedo[0, :, 0, :3] = torch.tensor([float("nan"), float("inf"), -float("inf")])
        with torch.no_grad():
            feats = model.features(*xs[:-1], albedo)[0]
        assert torch.equal(feats[:, 9:12], torch.nan_to_num(albedo, nan=0.0, posinf=0.0, neginf=0.0))

    def test_per_frame_state_zeroes_every_warped_channel(self):
        """empty_state (and empty_history(recurrent=True) for the module): the network sees this frame only."""
        model = make(True, recurrent=True, albedo=True)
        xs = inputs(model)
        color, view, _, _, other, previous, albedo = split(model, xs)
        state = empty_state(view, recurrent=True, stereo=True)
        for prev in (state.previous_output, previous):  # zeros, or any previous output: no surface to read it from
            with torch.no_grad():
                out = reprojection_features(
                    color,
                    view,
                    state.history,
                    state.prev_view,
                    THR,
                    other=state.other,
                    previous_output=prev,
                    albedo=albedo,
                )
            feats = out.features
            assert torch.equal(feats[:, 4], torch.zeros_like(feats[:, 4]))  # valid
            assert torch.equal(feats[:, 9:16], torch.zeros_like(feats[:, 9:16]))  # stereo, recurrent
            assert torch.equal(feats[:, 0:3], torch.log1p(color.clamp_min(0))) and (out.history_len == 1).all()
            assert torch.equal(feats[:, 16:19], albedo)
        flat = empty_history(*xs[1:5], recurrent=True)
        assert len(empty_history(*xs[1:5])) == 6 and len(flat) == 7 and torch.equal(flat[6], torch.zeros_like(color))
        no_other = dict(zip(OTHER_NAMES, (state.other[0], state.other[1].depth, state.other[1].normal, *xs[14:16])))
        with torch.no_grad():
            module_feats = model.features(*xs[:5], *flat[:6], **no_other, prev_denoised=flat[6], albedo=albedo)[0]
        assert torch.equal(module_feats, feats)

    def test_gradcheck(self):
        """float64 gradcheck of the new channels w.r.t. previous_output and albedo (backend "auto")."""
        model = make(recurrent=True, albedo=True)
        xs = inputs(model, 6, 8, dtype=torch.float64)
        color, view, history, prev_view, _, previous, albedo = split(model, xs)

        def f(prev, alb):
            out = reprojection_features(color, view, history, prev_view, THR, previous_output=prev, albedo=alb)
            return out.features[:, 9:]

        prev = previous.clone().requires_grad_(True)
        alb = albedo.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(f, (prev, alb))
        assert f(prev, alb)[:, :3].abs().max() > 0  # some of the previous output is kept

    def test_auto_backend_differentiates_the_previous_output(self):
        """float32 on the CPU (where "auto" would run native): with grad the previous output's warp runs torch."""
        model = make(recurrent=True, albedo=True)
        xs = inputs(model)
        color, view, history, prev_view, _, previous, albedo = split(model, xs)
        prev = previous.clone().requires_grad_(True)
        out = reproject_denoise(
            color, view, history, prev_view, model.denoiser, THR, previous_output=prev, albedo=albedo
        )
        out.denoised.sum().backward()
        assert prev.grad is not None and torch.isfinite(prev.grad).all() and prev.grad.abs().sum() > 0

    @pytest.mark.parametrize("options", NEW_OPTIONS, ids=OPTION_IDS)
    def test_module_equals_function(self, options, backend):
        be = self.backend_arg(backend)
        model = make(*options, backend=be)
        xs = inputs(model)
        color, view, history, prev_view, other, previous, albedo = split(model, xs)
        with torch.no_grad():
            got = model(*xs)
            by_name = model(*xs[:11], **dict(zip(model.input_names[11:], xs[11:])))
            ref = reproject_denoise(
                color,
                view,
                history,
                prev_view,
                model.denoiser,
                THR,
                backend=be,
                other=other,
                previous_output=previous,
                albedo=albedo,
            )
        for g, n, r in zip(got, by_name, ref):
            assert torch.equal(g, r) and torch.equal(n, r)

    def test_recurrent_unroll(self, backend):
        """Three frames through the module (state and denoised fed back) equal the function's unroll; gradients
        of the last frame reach the first frame's output (training unrolls through time)."""
        be = self.backend_arg(backend)
        model = make(recurrent=True, albedo=True, backend=be)
        albedo = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(5))
        state = None
        with torch.set_grad_enabled(be != "native"):  # native runs without autograd only
            for i in range(3):
                f = frame(i)
                cur = (f["color"], f["depth"], f["normal"], f["K"], f["cam_from_world"])
                view = View(*cur[1:])
                if state is None:
                    flat = empty_history(*cur[1:], recurrent=True)
                    s = empty_state(view, recurrent=True)
                    state = (s.history, s.prev_view, s.previous_output)
                got = model(*cur, *flat, albedo)
                ref = reproject_denoise(
                    cur[0],
                    view,
                    state[0],
                    state[1],
                    model.denoiser,
                    THR,
                    backend=be,
                    previous_output=state[2],
                    albedo=albedo,
                )
                for g, r in zip(got, ref):
                    assert torch.equal(g, r)
                if i == 0:
                    first = got[0]
                flat = (got[1], got[2], *cur[1:], got[0])
                state = (ref.history, view, ref.denoised)
        if be != "native":
            (grad,) = torch.autograd.grad(got[0].square().mean(), first)
            assert grad.abs().sum() > 0

    @pytest.mark.onnx
    @pytest.mark.parametrize("options", NEW_OPTIONS, ids=OPTION_IDS)
    def test_onnx_parity(self, options, tmp_path):
        """Every variant exports to one graph whose inputs are input_names (symbolic sizes), run by onnxruntime at
        another size: every output within 1e-5 of torch (float32)."""
        ort = pytest.importorskip("onnxruntime")
        model = make(*options)
        path = export_onnx(model, tmp_path / "m.onnx", inputs=inputs(model, 12, 16))
        dims = onnx_input_dims(path)
        assert list(dims) == model.input_names
        if model.recurrent:
            assert dims["prev_denoised"] == ["B", 3, "Hp", "Wp"]
        if model.albedo:
            assert dims["albedo"] == ["B", 3, "H", "W"]
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        xs = inputs(model, 20, 28, seed=1)
        got = sess.run(None, {n: x.numpy() for n, x in zip(model.input_names, xs)})
        with torch.no_grad():
            ref = model(*xs)
        assert_parity(ref, got, atol=1e-5)

    def test_exceptions(self):
        model = make(True, recurrent=True, albedo=True)
        xs = inputs(model)
        color, view, history, prev_view, other, previous, albedo = split(model, xs)
        args = (color, view, history, prev_view, THR)
        with pytest.raises(ShapeError, match=r"previous_output \(the previous frame's denoised output\)"):
            reprojection_features(*args, previous_output=previous[..., :-1])
        with pytest.raises(ShapeError, match=r"^albedo"):
            reprojection_features(*args, albedo=albedo[:, :2])
        with pytest.raises(TypeError, match="^albedo: expected a floating"):
            reprojection_features(*args, albedo=albedo.int())
        with pytest.raises(ShapeError, match="warped_previous"):
            denoise_features(color, xs[6], xs[6] > 0, xs[1], xs[2], warped_previous=color[..., :-1])
        with pytest.raises(TypeError, match="needs prev_denoised, albedo"):
            model(*xs[:16])
        with pytest.raises(ShapeError, match=r"^prev_denoised"):
            model(*xs[:16], previous[:, :, :-1], albedo)
        with pytest.raises(TypeError, match="twice"):
            model(*xs, albedo=albedo)
        with pytest.raises(TypeError, match="got prev_denoised: construct it with recurrent=True"):
            make()(*xs[:11], prev_denoised=previous)
        with pytest.raises(TypeError, match="albedo=True"):
            make(recurrent=True)(*xs[:11], previous, albedo)
        with pytest.raises(TypeError, match="unexpected arguments with View inputs"):
            reprojection_features(*args, "bilinear")
        with pytest.raises(TypeError, match="view: expected a stereorepro.View"):
            empty_state(xs[1])
        with pytest.raises(ShapeError, match=r"C_in = 19: .*albedo_b"):
            ReprojectionDenoiser(TinyDenoiser(9), *THR, stereo=True, recurrent=True, albedo=True)(*xs)


# ---------------------------------------------------------------------------------------------- the example
def load_example(name: str):
    return load_script("examples", name)


@pytest.mark.onnx
def test_onnx_denoise_sequence_example(tmp_path):
    """Smoke run (64x36, 4 frames x 2 eyes, 3 training steps): the recurrent one-graph denoiser (stereo, own
    warped output, albedo) in onnxruntime alone, within 1e-4 of torch on every frame, its RMSE reported beside
    plain accumulation's."""
    res = load_example("onnx_denoise_sequence").main(["--smoke", "--steps", "3", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "onnx_denoise_sequence.json").read_text())
    assert saved["max_abs_diff"] == res["max_abs_diff"]
    assert saved["max_abs_diff_denoised"] <= 1e-4
    per_frame = saved["max_abs_diff_denoised_per_frame"]
    assert set(per_frame) == {"right", "left"} and all(len(v) == 4 and max(v) <= 1e-4 for v in per_frame.values())
    assert saved["max_abs_diff"]["color"] <= 1e-5 and saved["max_abs_diff"]["history_len"] <= 1e-5
    assert saved["onnxruntime_torch_in_process"] is False and saved["onnxruntime_stereorepro_in_process"] is False
    assert saved["frames"] == 4 and saved["training"]["steps"] == 3
    assert all(v > 0 and math.isfinite(v) for v in saved["ms_per_frame"].values())
    assert all(math.isfinite(v) for v in saved["rmse_vs_reference"].values())
    assert saved["rmse"]["ldr/after_warmup"]["both_eyes"].keys() == {"input_1spp", "accumulated", "denoised"}
    assert saved["denoised_beats_accumulation"] == all(saved["beats_accumulation"].values())
    assert saved["features"] == list(feature_names(stereo=True, recurrent=True, albedo=True))
    assert saved["input_names"][11:] == [*OTHER_NAMES, "prev_denoised", "albedo"]
    for name in ("model.onnx", "sequence.npz", "onnxruntime_outputs.npz"):
        assert (tmp_path / name).is_file()
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # atomic writes left nothing
