"""The used-by examples in smoke mode, and the device/dtype support table of docs/support.md.

Each example is imported from ``examples/`` as a module and run as ``main(["--smoke", "--out", tmp])`` (< 60 s
each on 2 cores); assertions are on the JSON it writes.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

from conftest import load_script
from stereorepro import StereoReprojection, TemporalReprojection, export_onnx, temporal_reproject
from stereorepro._testing import example_inputs


def load_example(name: str):
    return load_script("examples", name)


class TestExamples:
    @pytest.mark.onnx
    def test_onnx_deploy(self, tmp_path):
        res = load_example("onnx_deploy").main(["--smoke", "--out", str(tmp_path)])
        saved = json.loads((tmp_path / "onnx_deploy.json").read_text())
        assert saved["max_abs_diff_all"] == res["max_abs_diff_all"]
        assert saved["max_abs_diff_all"] <= 1e-5
        assert all(v == 0 for v in saved["mask_mismatch_pixels"].values())
        assert saved["onnxruntime_imported_torch"] is False  # the deployment process ran without torch

    # ~25 s of CPU on an idle 2-core machine: part of CI's fast suite (the issue asks every example to run in CI)
    def test_mitsuba_stereo(self, tmp_path):
        pytest.importorskip("mitsuba")
        res = load_example("mitsuba_stereo").main(["--smoke", "--out", str(tmp_path)])
        assert res["exit_code"] == 0 and res["warnings"] == []
        assert json.loads((tmp_path / "mitsuba_stereo.json").read_text()) == res
        assert (tmp_path / "reprojected" / "0001_left_reprojected.exr").is_file()

    def test_oidn_denoise(self, tmp_path):
        pytest.importorskip("pyoidn")
        doc = load_example("oidn_denoise").main(["--smoke", "--out", str(tmp_path)])
        r = doc["results"][0]
        assert json.loads((tmp_path / "oidn_denoise.json").read_text())["table"] == doc["table"]
        m = r["methods"]
        assert m["1 spp"]["effective_spp"] == pytest.approx(1.0, abs=0.05)  # the ladder's first rung itself
        assert m["OIDN(1 spp)"]["rmse"] < m["1 spp"]["rmse"]  # OIDN works on our frames and aux images
        assert m["stereo+temporal"]["rmse"] < m["1 spp"]["rmse"]
        assert all(np.isfinite(v["rmse"]) for v in m.values())

    def test_denoiser_preprocess(self, tmp_path):
        load_example("denoiser_preprocess").main(["--smoke", "--out", str(tmp_path)])
        res = json.loads((tmp_path / "denoiser_preprocess.json").read_text())
        methods = res["methods"]
        assert set(methods) == {"unet_plain", "unet_reprojected", "input_1spp", "accumulated"}
        assert methods["unet_plain"]["input_channels"] == 9 and methods["unet_reprojected"]["input_channels"] == 14
        for m in methods.values():
            assert np.isfinite(m["rmse_mean"]) and m["rmse_mean"] > 0
            assert m["effective_spp_median"] > 0
        assert methods["input_1spp"]["effective_spp_median"] == 1.0  # the input is the ladder's first rung

    def test_denoiser_preprocess_input_order(self):
        """The channels the example feeds its U-Nets are those of its docstring, in that order: (a) log1p of the
        1-spp colour, albedo, shading normal (9); (b) the same, then log1p of the accumulated colour, the valid
        mask and log1p(history length) / log(256) (14). Its U-Net is a residual on channels 0-2: untrained (zero
        head) it returns the 1-spp input. In stereorepro.denoise's layout (FEATURES) channels 0-2 are the
        accumulated colour, so the same U-Net inside ReprojectionDenoiser starts from the accumulation."""
        from stereorepro import ReprojectionDenoiser
        from stereorepro.denoise import FEATURES, denoiser_example_inputs, feature_channels

        ex = load_example("denoiser_preprocess")
        g = torch.Generator().manual_seed(0)
        F, H, W = 2, 6, 8
        clip = {
            "color": torch.rand(F, 3, H, W, generator=g) * 3 - 0.5,
            "albedo": torch.rand(F, 3, H, W, generator=g),
            "normal": torch.nn.functional.normalize(torch.randn(F, 3, H, W, generator=g), dim=1),
            "accumulated": torch.rand(F, 3, H, W, generator=g) * 2 - 0.2,
            "valid": (torch.rand(F, 1, H, W, generator=g) > 0.5).float(),
            "history_len": torch.randint(1, 256, (F, 1, H, W), generator=g).float(),
        }
        documented = [
            torch.log1p(clip["color"].clamp_min(0)),
            clip["albedo"],
            clip["normal"],
            torch.log1p(clip["accumulated"].clamp_min(0)),
            clip["valid"],
            torch.log1p(clip["history_len"]) / np.log(256.0),
        ]
        plain, reprojected = ex.features(clip, False), ex.features(clip, True)
        assert plain.shape[1] == 9 and reprojected.shape[1] == 14
        assert torch.equal(plain, torch.cat(documented[:3], 1))
        torch.testing.assert_close(reprojected, torch.cat(documented, 1), rtol=0, atol=0)
        with torch.no_grad():
            for x in (plain, reprojected):
                torch.testing.assert_close(ex.UNet(x.shape[1])(x), clip["color"].clamp_min(0), rtol=1e-6, atol=1e-6)

        assert FEATURES[:3] == ("log1p_color_r", "log1p_color_g", "log1p_color_b")
        model = ReprojectionDenoiser(ex.UNet(feature_channels()), 0.05, 0.2).eval()
        with torch.no_grad():
            denoised, accumulated, _ = model(*denoiser_example_inputs(model, height=12, width=16))
        torch.testing.assert_close(denoised, accumulated.clamp_min(0), rtol=1e-6, atol=1e-6)

    def test_train_thresholds(self, tmp_path):
        load_example("train_thresholds").main(["--smoke", "--out", str(tmp_path)])
        res = json.loads((tmp_path / "train_thresholds.json").read_text())
        learned, hand = res["learned"], res["hand_set"]
        assert learned["position_threshold"] > 0 and learned["normal_threshold"] > 0
        assert 0 < learned["alpha"] <= 1
        assert learned != hand  # the optimiser moved them
        for label in ("hand_set", "learned"):
            h = res["held_out"][label]
            assert np.isfinite(h["rmse_mean"]) and h["effective_spp_median"] > 0

    def test_train_thresholds_learned_beat_hand_set(self, tmp_path):
        """What the example shows (docs/guides/denoisers.md): given enough training frames, the learned thresholds and alpha
        beat the hand-set ones on held-out frames (with hard tests). A fixed small case: 64x36, 60 Adam steps over
        10-frame windows of frames 0-29, held-out frames 40-49, 32-spp references, seed 0. Measured: RMSE 0.1930
        (hand-set) -> 0.1911 (learned), effective spp 3.82 -> 3.89, the same in repeated runs. (The smoke run
        trains on 16 frames for 40 steps: too little, its learned values are slightly worse, as the docs say.)"""
        ex = load_example("train_thresholds")
        settings = ex.Settings(64, 36, (0, 30), (36, 50), 4, 10, 32, 8, 60)
        args = argparse.Namespace(smoke=True, out=str(tmp_path), scene="living_room_moving_light", seed=0)
        with ex.cpu_training_threads():
            res = ex._run(settings, args)
        hand, learned = res["held_out"]["hand_set"], res["held_out"]["learned"]
        assert res["nonfinite_steps"] == [] and res["learned"] != res["hand_set"]
        assert learned["rmse_mean"] < hand["rmse_mean"] - 1e-3, (learned["rmse_mean"], hand["rmse_mean"])
        assert learned["effective_spp_median"] > hand["effective_spp_median"]
        assert learned["rmse_mean"] < res["held_out"]["input_1spp"]["rmse_mean"] / 1.5


# ---------------------------------------------------------------------------------------------- support table
MODULES = {
    "stereo": lambda: StereoReprojection(0.05, 0.2, backend="torch"),
    "temporal": lambda: TemporalReprojection(0.05, 0.2, backend="torch"),
}
LOW = {"float16": torch.float16, "bfloat16": torch.bfloat16}


def _inputs(module, dtype, device, cameras=torch.float64):
    """Synthetic inputs: images in ``dtype``, cameras in ``cameras``."""
    xs = example_inputs(module, height=24, width=32, dtype=torch.float64)
    return tuple((x.to(cameras) if x.shape[-2:] in ((3, 3), (4, 4)) else x.to(dtype)).to(device) for x in xs)


class TestSupportTable:
    """Backs the ✅ of docs/support.md: every cell marked tested here is one of these tests."""

    @pytest.mark.parametrize("kind", sorted(MODULES))
    def test_float(self, kind, device, dtype):
        module = MODULES[kind]().to(device)
        out = module(*_inputs(module, dtype, device))
        ref = module.cpu()(*_inputs(module, torch.float64, "cpu"))
        assert out[0].dtype == dtype and out[0].device.type == device.type
        torch.testing.assert_close(out[0].double().cpu(), ref[0], atol=1e-4, rtol=1e-4)
        assert torch.equal(out[-1].cpu(), ref[-1])

    @pytest.mark.parametrize("kind", sorted(MODULES))
    @pytest.mark.parametrize("low", sorted(LOW))
    def test_low_precision_color(self, kind, low, device):
        """float16/bfloat16 colour with float32 G-buffers: same decisions, output in the colour's dtype."""
        module = MODULES[kind]().to(device)
        ref = module(*_inputs(module, torch.float32, device))
        xs = tuple(
            x.to(LOW[low]) if name.endswith("color") else x
            for name, x in zip(module.input_names, _inputs(module, torch.float32, device))
        )
        out = module(*xs)
        assert out[0].dtype == LOW[low] and torch.equal(out[-1], ref[-1])
        tol = 2e-3 if low == "float16" else 1.6e-2  # half an ulp at 1.0, relative
        torch.testing.assert_close(out[0].float(), ref[0], atol=tol, rtol=tol)

    @pytest.mark.parametrize("kind", sorted(MODULES))
    @pytest.mark.parametrize("low", sorted(LOW))
    def test_low_precision_all(self, kind, low, device):
        """Every image input in float16/bfloat16 runs, but depth quantisation flips accept decisions near the
        limits (measured on these inputs: float16 ~2 %, bfloat16 ~11 % of pixels): keep depth in float32."""
        module = MODULES[kind]().to(device)
        out = module(*_inputs(module, LOW[low], device))
        ref = module(*_inputs(module, torch.float32, device))
        assert out[0].dtype == LOW[low] and torch.isfinite(out[0]).all()
        assert (out[-1] == ref[-1]).float().mean() > (0.95 if low == "float16" else 0.8)

    def test_autograd(self):
        """Soft tests: gradients w.r.t. thresholds and alpha, checked numerically in float64."""
        m = TemporalReprojection(0.05, 0.2, soft=True)
        xs = _inputs(m, torch.float64, "cpu", cameras=torch.float64)
        xs = tuple(x[..., :12, :16] if x.dim() == 4 else x for x in xs)  # small crop: fast gradcheck

        def f(pos, nrm, alpha):
            return temporal_reproject(*xs, pos, nrm, alpha, soft=True, temperature=0.3)[0]

        # alpha away from the warm-up kink at 1/(n+1) = 0.25 (history length 3 in the example inputs)
        params = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (0.08, 0.3, 0.35)]
        assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-5)
        loss = m(*_inputs(m, torch.float32, "cpu"))[0].square().mean()
        loss.backward()
        assert all(p.grad is not None and torch.isfinite(p.grad) for p in m.parameters())

    @pytest.mark.onnx
    @pytest.mark.parametrize("kind", sorted(MODULES))
    @pytest.mark.parametrize("dt", ["float32", "float64", "float16"])
    def test_onnx(self, kind, dt, tmp_path):
        ort = pytest.importorskip("onnxruntime")
        dtype = getattr(torch, dt)
        module = MODULES[kind]()
        xs = example_inputs(module, height=12, width=16, dtype=dtype)
        path = export_onnx(module, tmp_path / "m.onnx", inputs=xs)
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        xs2 = example_inputs(module, height=20, width=28, dtype=dtype, seed=1)  # another size: symbolic H, W
        outs = sess.run(None, {n: x.numpy() for n, x in zip(module.input_names, xs2)})
        with torch.no_grad():
            ref = module(*xs2)
        for o, r in zip(outs, ref):
            assert o.dtype == r.numpy().dtype
            np.testing.assert_allclose(o.astype(np.float64), r.double().numpy(), atol=1e-5, rtol=0)

    @staticmethod
    def _assert_outputs_agree(module, ref, got):
        """``got`` (another device's outputs) against ``ref``: valid masks agree on > 99.9 % of the pixels and the
        colours agree where both are valid."""
        names = list(module.output_names)
        valid_r, valid_g = ref[names.index("valid")], got[names.index("valid")].cpu()
        assert valid_r.dtype == torch.bool and valid_g.dtype == torch.bool
        assert (valid_r == valid_g).float().mean() > 0.999
        both = (valid_r & valid_g).expand_as(ref[0])
        assert both.any(), "nothing valid to compare"
        torch.testing.assert_close(got[0].cpu()[both], ref[0][both], atol=1e-4, rtol=1e-4)

    def test_device_check_can_fail(self):
        """The comparison used for CUDA fails on a colour off by 1e-3 where valid (checked on the CPU)."""
        for kind in sorted(MODULES):
            module = MODULES[kind]()
            ref = module(*_inputs(module, torch.float32, "cpu"))
            self._assert_outputs_agree(module, ref, ref)
            bad = (ref[0] + 1e-3,) + tuple(ref[1:])
            with pytest.raises(AssertionError):
                self._assert_outputs_agree(module, ref, bad)

    def test_cuda_matches_cpu(self):
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device")
        for kind in sorted(MODULES):
            module = MODULES[kind]()
            cpu = module(*_inputs(module, torch.float32, "cpu"))
            gpu = module.cuda()(*_inputs(module, torch.float32, "cuda"))
            assert gpu[0].is_cuda
            self._assert_outputs_agree(module, cpu, gpu)


class TestRecurrentDenoiser:
    """examples/recurrent_denoiser.py: the smoke run's outputs, and what each variant's network sees."""

    def test_smoke(self, tmp_path):
        pytest.importorskip("pyoidn")
        pytest.importorskip("flip_evaluator")
        ex = load_example("recurrent_denoiser")
        res = ex.main(["--smoke", "--out", str(tmp_path)])
        saved = json.loads((tmp_path / "recurrent_denoiser.json").read_text())
        assert saved["table"] == res["table"] and saved["smoke"] is True
        assert len(saved["commit"]) == 40 and saved["machine"]["cpu"]
        assert {"data", "training", "evaluation", "report", "total"} <= set(saved["seconds"])
        assert saved["in_channels"] == 19 and saved["groups"] == ["held-out frames", "held-out scene"]
        methods = saved["methods"]
        assert list(methods) == [*ex.BASELINES, "U-Net recurrent", "U-Net per_frame"]
        one = methods["1 spp"]["metrics"]["all"]
        assert one["effective_spp_median"] == pytest.approx(1.0, abs=0.05)  # the ladder's first rung itself
        assert methods["accumulation"]["metrics"]["all"]["temporal_error"] < one["temporal_error"]
        for name in ("U-Net recurrent", "U-Net per_frame"):
            rec = methods[name]
            assert list(rec["seeds"]) == ["0"]
            for group in ("all", "held-out frames", "held-out scene", "left eye", "right eye"):
                for key in ("rmse", "flip", "temporal_error"):
                    sp = rec["spread"][group][key]
                    assert np.isfinite(sp["mean"]) and sp["min"] <= sp["mean"] <= sp["max"] and sp["n"] == 1
        for variant in ex.VARIANTS:
            ckpt = torch.load(tmp_path / f"{variant}_seed0.pt", weights_only=False)
            assert ckpt["network"]["name"] == "recurrent_denoiser.build_network"
            assert ckpt["feature_options"] == {"stereo": True, "recurrent": True, "albedo": True}
            assert json.loads(json.dumps(ckpt["settings"])) == saved["settings"]
            assert set(ckpt["thresholds"]) == set(saved["thresholds"])
            ex.build_network(**ckpt["network"]["kwargs"]).load_state_dict(ckpt["state_dict"])
        assert (tmp_path / "recurrent_denoiser.md").read_text().count("| U-Net recurrent |") == 4  # 3 groups, where
        assert (tmp_path / "report.html").read_text().startswith("<!DOCTYPE html>")

    @staticmethod
    def _clip(frames: int = 3, height: int = 6, width: int = 8) -> dict:
        """Both eyes of a static wall 2 units ahead, the left camera 0.1 to the left of the right one."""
        from stereorepro import intrinsics_from_fov

        g = torch.Generator().manual_seed(0)
        clip = {"thresholds": torch.tensor([0.1, 0.3], dtype=torch.float64)}
        for eye, x in (("left", 0.1), ("right", 0.0)):
            T = torch.eye(4, dtype=torch.float64).repeat(frames, 1, 1)
            T[:, 0, 3] = x
            normal = torch.zeros(frames, 3, height, width)
            normal[:, 2] = -1
            clip[eye] = {
                "color": torch.rand(frames, 3, height, width, generator=g),
                "albedo": torch.rand(frames, 3, height, width, generator=g),
                "depth": torch.full((frames, 1, height, width), 2.0),
                "normal": normal,
                "K": intrinsics_from_fov(60.0, width, height).double().repeat(frames, 1, 1),
                "T": T,
            }
        return clip

    def test_per_frame_state_hides_the_warped_inputs(self):
        """Per-frame: every warped channel (valid, stereo, previous output) is 0 at every frame and eye, so the
        network sees only this frame. Recurrent: from the second frame the previous output is there, and the left
        eye sees the right eye's output; the first frame is a cold start like the per-frame state."""
        from stereorepro.denoise import feature_names

        ex = load_example("recurrent_denoiser")
        names = feature_names(**ex.FEATURE_OPTIONS)
        warped = [names.index(n) for n in names if n == "valid" or "stereo" in n or "previous" in n]
        assert len(names) == ex.in_channels() == 19 and len(warped) == 8
        seen = []

        def net(x):
            seen.append(x)
            return torch.expm1(x[:, :3])

        clip = self._clip()
        stereo = [i for i in warped if "stereo" in names[i]]
        temporal = [i for i in warped if i not in stereo]  # valid and the previous output
        for recurrent in (False, True):
            seen.clear()
            list(ex.sequence(net, clip, torch.zeros(1, dtype=torch.long), 3, recurrent))
            assert len(seen) == 6  # 3 frames x (right, left)
            for i, x in enumerate(seen):
                frame, left = divmod(i, 2)
                has_temporal, has_stereo = recurrent and frame > 0, recurrent and left == 1
                assert bool(x[:, temporal].abs().max() > 0) == has_temporal, (recurrent, i)
                assert bool(x[:, stereo].abs().max() > 0) == has_stereo, (recurrent, i)
