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
    denoise_features,
    empty_history,
    export_onnx,
    reproject_denoise,
    reprojection_features,
    stereo_reproject,
    temporal_step,
)
from stereorepro.denoise import FEATURES, OTHER_NAMES, STEREO_FEATURES, denoiser_example_inputs, feature_channels
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


def make(stereo: bool = False, seed: int = 0, **kw) -> ReprojectionDenoiser:
    torch.manual_seed(seed)
    return ReprojectionDenoiser(TinyDenoiser(feature_channels(stereo)), *THR, stereo=stereo, **kw).eval()


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


# ---------------------------------------------------------------------------------------------- the example
def load_example(name: str):
    return load_script("examples", name)


@pytest.mark.onnx
def test_onnx_denoise_sequence_example(tmp_path):
    """Smoke run (64x36, 4 frames, 3 training steps, ~10 s): one graph in onnxruntime alone, within 1e-4."""
    res = load_example("onnx_denoise_sequence").main(["--smoke", "--steps", "3", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "onnx_denoise_sequence.json").read_text())
    assert saved["max_abs_diff"] == res["max_abs_diff"]
    assert saved["max_abs_diff_denoised"] <= 1e-4
    assert saved["max_abs_diff"]["color"] <= 1e-5 and saved["max_abs_diff"]["history_len"] <= 1e-5
    assert saved["onnxruntime_torch_in_process"] is False and saved["onnxruntime_stereorepro_in_process"] is False
    assert saved["frames"] == 4 and saved["training"]["steps"] == 3
    assert all(v > 0 and math.isfinite(v) for v in saved["ms_per_frame"].values())
    assert all(math.isfinite(v) for v in saved["rmse_vs_reference"].values())
    assert saved["features"] == list(FEATURES)
    for name in ("model.onnx", "sequence.npz", "onnxruntime_outputs.npz"):
        assert (tmp_path / name).is_file()
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # atomic writes left nothing
