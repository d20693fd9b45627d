"""Tests for stereorepro.measure.metrics: pixel errors, SSIM, the ladder fit and the effective-spp estimator.

The synthetic validation (TestSyntheticValidation) simulates path tracing as truth + Gaussian noise: one sample
has per-pixel standard deviation SIGMA, an n-spp image averages n samples (variance SIGMA² / n), ladder rungs
are nested prefixes of one sample stream, and the method's "k-spp" image has variance SIGMA² / k for any real
k. With P pixel values, an MSE estimate has relative standard deviation sqrt(2 / P); the effective spp
compares two such estimates (method and ladder), so its relative standard deviation is about 2 / sqrt(P)
(measured over 40 seeds: 0.8-1.0 % at P = 49152, where 2 / sqrt(P) = 0.9 %). Tolerances are stated as
multiples of that.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from stereorepro.errors import ParameterError, ShapeError
from stereorepro.measure.metrics import (
    EFFECTIVE_SPP_FLAGS,
    EffectiveSppLadder,
    effective_spp,
    effective_spp_many,
    fit_ladder,
    ladder_rmse,
    mse,
    rmse,
    ssim,
    suggest_reference_spp,
)

F64 = torch.float64
SIGMA = 0.5


def _ideal_rmse(spp, a=1.0, b=0.0):
    """RMSE of the model MSE = a / n + b."""
    return [math.sqrt(a / n + b) for n in spp]


def _truth(h=128, w=128):
    y, x = torch.meshgrid(torch.linspace(0, 1, h, dtype=F64), torch.linspace(0, 1, w, dtype=F64), indexing="ij")
    return torch.stack([x, y, 0.5 + 0.3 * torch.sin(6 * x) * torch.cos(4 * y)])[None]  # 1x3xHxW


def _noisy(truth, spp, gen):
    return truth + torch.randn(truth.shape, generator=gen, dtype=F64) * (SIGMA / math.sqrt(spp))


def _nested_ladder(truth, n_max, gen):
    """(N, 1, C, H, W): rung n is the mean of the first n samples of one stream."""
    samples = torch.randn((n_max,) + truth.shape, generator=gen, dtype=F64) * SIGMA
    counts = torch.arange(1, n_max + 1, dtype=F64).view(-1, 1, 1, 1, 1)
    return truth + samples.cumsum(0) / counts


def _rel_sd(num_values: int) -> float:
    """Relative standard deviation of a synthetic effective spp estimate (module docstring)."""
    return 2.0 / math.sqrt(num_values)


# ----------------------------------------------------------------------------------------------------------
# Pixel errors
# ----------------------------------------------------------------------------------------------------------


class TestMse:
    def test_smoke(self):
        x = torch.zeros(2, 3, 4, 5)
        ref = torch.full((2, 3, 4, 5), 0.5)
        out = mse(x, ref)
        assert out.dtype == F64
        torch.testing.assert_close(out, torch.full((2,), 0.25, dtype=F64))

    def test_cardinality(self):
        x = torch.rand(3, 2, 6, 7)
        assert mse(x, torch.rand(3, 2, 6, 7)).shape == (3,)
        assert mse(x, torch.rand(1, 2, 6, 7)).shape == (3,)  # reference broadcast over the batch

    def test_per_item_and_mask(self):
        x = torch.zeros(2, 1, 2, 2, dtype=F64)
        ref = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]], [[[0.0, 0.0], [0.0, 2.0]]]], dtype=F64)
        mask = torch.tensor([[[[True, False], [False, True]]], [[[True, True], [True, True]]]])
        torch.testing.assert_close(mse(x, ref), torch.tensor([7.5, 1.0], dtype=F64))
        torch.testing.assert_close(mse(x, ref, mask), torch.tensor([8.5, 1.0], dtype=F64))

    def test_mask_counts_all_channels(self):
        x = torch.zeros(1, 3, 1, 2, dtype=F64)
        ref = torch.tensor([[[[1.0, 9.0]], [[2.0, 9.0]], [[3.0, 9.0]]]], dtype=F64)
        mask = torch.tensor([[[[True, False]]]])
        torch.testing.assert_close(mse(x, ref, mask), torch.tensor([14.0 / 3.0], dtype=F64))

    def test_exceptions(self):
        x = torch.rand(2, 3, 4, 4)
        with pytest.raises(ShapeError):
            mse(x, torch.rand(2, 3, 4, 5))
        with pytest.raises(ShapeError):
            mse(x, torch.rand(3, 3, 4, 4))
        with pytest.raises(ShapeError):
            mse(x[0], torch.rand(3, 4, 4))
        with pytest.raises(TypeError):
            mse(x, ref := torch.rand(2, 3, 4, 4), mask=torch.ones(2, 1, 4, 4))  # mask not bool
        with pytest.raises(TypeError):
            mse((x * 255).to(torch.uint8), ref)
        with pytest.raises(ValueError, match="nonfinite"):
            mse(x, ref, nonfinite="clamp")
        with pytest.raises(ValueError, match="no valid pixels"):
            mse(x, ref, mask=torch.zeros(2, 1, 4, 4, dtype=torch.bool))

    def test_nonfinite_raises_with_count(self):
        x = torch.rand(2, 3, 4, 4)
        x[1, 0, 0, 0] = float("nan")
        x[1, 2, 0, 0] = float("inf")  # same pixel: counted once
        x[0, 1, 3, 3] = -float("inf")
        with pytest.raises(ValueError, match=r"2 non-finite pixel\(s\).*\[0, 1\]"):
            mse(x, torch.rand(2, 3, 4, 4))

    def test_nonfinite_ignore(self):
        ref = torch.zeros(1, 1, 2, 2, dtype=F64)
        x = torch.tensor([[[[1.0, float("nan")], [3.0, float("inf")]]]], dtype=F64)
        torch.testing.assert_close(mse(x, ref, nonfinite="ignore"), torch.tensor([5.0], dtype=F64))
        # Masked-out non-finite pixels do not count under "raise".
        mask = torch.tensor([[[[True, False], [True, False]]]])
        torch.testing.assert_close(mse(x, ref, mask), torch.tensor([5.0], dtype=F64))
        with pytest.raises(ValueError, match="no valid pixels"):
            mse(torch.full((1, 1, 2, 2), float("nan")), ref, nonfinite="ignore")

    def test_nonfinite_reference_always_raises(self):
        ref = torch.zeros(1, 1, 2, 2)
        ref[0, 0, 1, 1] = float("nan")
        with pytest.raises(ValueError, match="reference has 1 non-finite"):
            mse(torch.zeros(1, 1, 2, 2), ref, nonfinite="ignore")
        mask = torch.tensor([[[[True, True], [True, False]]]])
        assert float(mse(torch.zeros(1, 1, 2, 2), ref, mask)) == 0.0

    def test_hard_cases(self):
        # float32 inputs with a large common offset: the difference is taken in float64.
        ref = torch.full((1, 3, 8, 8), 1.0e4, dtype=torch.float32)
        x = ref + 1.0
        torch.testing.assert_close(mse(x, ref), torch.tensor([1.0], dtype=F64))
        # Gradients flow (useful for losses).
        xg = torch.rand(1, 3, 4, 4, dtype=F64, requires_grad=True)
        mse(xg, torch.zeros(1, 3, 4, 4, dtype=F64)).sum().backward()
        torch.testing.assert_close(xg.grad, 2 * xg.detach() / 48)


class TestRmse:
    def test_smoke(self):
        x = torch.zeros(1, 3, 4, 4)
        torch.testing.assert_close(rmse(x, torch.full_like(x, 2.0)), torch.tensor([2.0], dtype=F64))

    def test_cardinality(self):
        x, ref = torch.rand(4, 3, 5, 5), torch.rand(4, 3, 5, 5)
        out = rmse(x, ref)
        assert out.shape == (4,)
        torch.testing.assert_close(out, mse(x, ref).sqrt())

    def test_exceptions(self):
        x = torch.rand(1, 3, 4, 4)
        x[0, 0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="1 non-finite"):
            rmse(x, torch.rand(1, 3, 4, 4))


class TestSsim:
    def test_smoke(self):
        x = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
        out = ssim(x, x)
        assert out.dtype == F64
        torch.testing.assert_close(out, torch.ones(2, dtype=F64), atol=1e-6, rtol=0)
        y = x + 0.2 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
        assert bool((ssim(y, x) < 0.9).all())

    def test_cardinality(self):
        x = torch.rand(3, 1, 12, 13)
        assert ssim(x, torch.rand(1, 1, 12, 13)).shape == (3,)
        assert ssim(x, torch.rand(3, 1, 12, 13), window_size=5).shape == (3,)

    def test_tonemap(self):
        gen = torch.Generator().manual_seed(2)
        ref = 2.0 + torch.rand(1, 3, 16, 16, generator=gen)  # all above the display range
        x = ref + 0.5 * torch.rand(1, 3, 16, 16, generator=gen)
        # Clamp: both display as white, identical.
        torch.testing.assert_close(ssim(x, ref), torch.ones(1, dtype=F64), atol=1e-6, rtol=0)
        # Reinhard keeps the highlights apart; "none" compares raw values with the caller's range.
        assert float(ssim(x, ref, tonemap="reinhard")) < 0.999
        assert float(ssim(x, ref, tonemap="none", max_val=4.0)) < 0.999

    def test_mask(self):
        gen = torch.Generator().manual_seed(3)
        ref = torch.rand(1, 1, 32, 32, generator=gen)
        x = ref.clone()
        x[..., :, 16:] = torch.rand(1, 1, 32, 16, generator=gen)  # right half differs
        mask = torch.zeros(1, 1, 32, 32, dtype=torch.bool)
        mask[..., :, :8] = True  # far from the differing half (window 11 reads 5 pixels around)
        torch.testing.assert_close(ssim(x, ref, mask), torch.ones(1, dtype=F64), atol=1e-6, rtol=0)
        assert float(ssim(x, ref)) < 0.9

    def test_exceptions(self):
        x = torch.rand(1, 3, 16, 16)
        with pytest.raises(ValueError, match="tonemap"):
            ssim(x, x, tonemap="aces")
        with pytest.raises(ValueError, match="odd"):
            ssim(x, x, window_size=4)
        with pytest.raises(ShapeError, match="too small"):
            ssim(torch.rand(1, 3, 4, 4), torch.rand(1, 3, 4, 4))
        y = x.clone()
        y[0, 1, 2, 2] = float("inf")
        with pytest.raises(ValueError, match="image has 1 non-finite"):
            ssim(y, x)
        with pytest.raises(ValueError, match="empty mask"):
            ssim(x, x, mask=torch.zeros(1, 1, 16, 16, dtype=torch.bool))
        with pytest.raises(ParameterError, match="max_val"):
            ssim(x, x, tonemap="none", max_val=0.0)

    def test_identical_images_are_exactly_one(self):
        """Identical images give 1 exactly, black ones too (with an epsilon in the ratio: 0.99998889)."""
        black = torch.zeros(2, 3, 16, 16)
        noise = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(3))
        assert ssim(black, black).tolist() == [1.0, 1.0]
        assert ssim(noise, noise).tolist() == [1.0]


class TestFlip:
    @pytest.fixture(autouse=True)
    def _needs_flip(self):
        from stereorepro.measure.metrics import flip_available

        if not flip_available():
            pytest.skip("flip-evaluator is not installed")

    def test_smoke_and_identity(self):
        from stereorepro.measure.metrics import flip

        a = torch.rand(2, 3, 20, 24, generator=torch.Generator().manual_seed(0))
        f = flip(a, a)
        assert f.shape == (2,) and f.dtype == torch.float64 and bool((f == 0).all())

    def test_more_noise_more_error(self):
        from stereorepro.measure.metrics import flip

        g = torch.Generator().manual_seed(1)
        ref = torch.rand(1, 3, 32, 32, generator=g) * 0.5 + 0.25
        noise = torch.randn(1, 3, 32, 32, generator=g)
        small, large = flip(ref + 0.02 * noise, ref), flip(ref + 0.2 * noise, ref)
        assert 0 < float(small) < float(large) <= 1

    def test_exceptions(self):
        from stereorepro.measure.metrics import flip

        with pytest.raises(ShapeError):
            flip(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 8))
        with pytest.raises(ShapeError):
            flip(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))

    def test_nonfinite_raises(self):
        """A non-finite image or reference raises as in mse and ssim (clamping read NaN as 0: 0.97 for all-NaN)."""
        from stereorepro.measure.metrics import flip

        x = torch.rand(1, 3, 16, 16)
        with pytest.raises(ParameterError, match="flip: image has 256 non-finite"):
            flip(torch.full_like(x, float("nan")), x)
        bad = x.clone()
        bad[0, 2, 3, 4] = float("inf")
        with pytest.raises(ParameterError, match="flip: reference has 1 non-finite"):
            flip(x, bad)


class TestLadderRmse:
    def test_smoke(self):
        ref = torch.zeros(1, 1, 2, 2, dtype=F64)
        ladder = torch.stack([torch.full_like(ref, v) for v in (3.0, 2.0, 1.0)])  # 3x1x1x2x2
        torch.testing.assert_close(ladder_rmse(ladder, ref), torch.tensor([[3.0, 2.0, 1.0]], dtype=F64))

    def test_cardinality(self):
        ref = torch.rand(2, 3, 5, 5)
        ladder = torch.rand(4, 2, 3, 5, 5)
        out = ladder_rmse(ladder, ref)
        assert out.shape == (2, 4)  # (B, N): one ladder per frame
        torch.testing.assert_close(ladder_rmse(list(ladder), ref), out)
        torch.testing.assert_close(out[1, 2], rmse(ladder[2], ref)[1])

    def test_exceptions(self):
        ref = torch.rand(1, 3, 5, 5)
        with pytest.raises(ValueError, match="no images"):
            ladder_rmse([], ref)
        with pytest.raises(ShapeError):
            ladder_rmse([torch.rand(1, 3, 5, 5), torch.rand(1, 3, 5, 4)], ref)
        with pytest.raises(ShapeError):
            ladder_rmse(torch.rand(2, 3, 5, 5), ref)  # 4-D: not a ladder
        bad = torch.rand(2, 1, 3, 5, 5)
        bad[1, 0, 0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="non-finite"):
            ladder_rmse(bad, ref)


# ----------------------------------------------------------------------------------------------------------
# Ladder fit and effective spp
# ----------------------------------------------------------------------------------------------------------

SPP16 = list(range(1, 17))


class TestFitLadder:
    def test_smoke(self):
        a, b = fit_ladder(SPP16, _ideal_rmse(SPP16, a=0.3, b=0.002))
        assert a.shape == () and b.shape == ()
        assert float(a) == pytest.approx(0.3, rel=1e-10)
        assert float(b) == pytest.approx(0.002, rel=1e-8)

    def test_cardinality(self):
        R = torch.tensor([_ideal_rmse(SPP16, a=1.0), _ideal_rmse(SPP16, a=2.0, b=0.01)], dtype=F64)
        a, b = fit_ladder(SPP16, R)
        assert a.shape == (2,) and b.shape == (2,)
        torch.testing.assert_close(a, torch.tensor([1.0, 2.0], dtype=F64))
        torch.testing.assert_close(b, torch.tensor([0.0, 0.01], dtype=F64), atol=1e-12, rtol=0)

    def test_exceptions(self):
        with pytest.raises(ValueError, match="does not decrease"):
            fit_ladder([1, 2, 3, 4], [0.5, 0.6, 0.7, 0.8])
        with pytest.raises(ValueError, match="strictly increasing"):
            fit_ladder([1, 1, 2], [1.0, 0.8, 0.7])
        with pytest.raises(ValueError, match="> 0"):
            fit_ladder([1, 2], [1.0, 0.0])
        with pytest.raises(ShapeError):
            fit_ladder([1, 2, 3], [1.0, 0.8])

    def test_hard_cases(self):
        # A negative floor is impossible: data bending the other way are fitted with b = 0.
        R = [math.sqrt(1.0 / n - 0.004) for n in SPP16]
        a, b = fit_ladder(SPP16, R)
        assert float(b) == 0.0 and float(a) > 0
        # One rung: b = 0, a = n * MSE.
        a, b = fit_ladder([4], [0.5])
        assert (float(a), float(b)) == (1.0, 0.0)
        # Scale-free: tiny errors fit as well as unit ones.
        a, b = fit_ladder(SPP16, _ideal_rmse(SPP16, a=1e-12, b=1e-15))
        assert float(a) == pytest.approx(1e-12, rel=1e-8) and float(b) == pytest.approx(1e-15, rel=1e-6)


class TestEffectiveSpp:
    def test_smoke(self):
        spp, flag = effective_spp(0.8, [1, 2, 3], [1.0, 0.7, 0.55])
        assert isinstance(spp, float) and flag == "interpolated"
        assert 1.0 < spp < 2.0

    def test_flags_are_documented(self):
        assert EFFECTIVE_SPP_FLAGS == (
            "exact",
            "interpolated",
            "extrapolated_low",
            "extrapolated_high",
            "beyond_floor",
            "fitted_nonmonotonic",
        )

    def test_exact_hit_of_rung(self):
        R = _ideal_rmse(SPP16)
        for interpolation in ("inverse_mse", "linear"):
            for n, r in zip(SPP16, R):
                assert effective_spp(r, SPP16, R, interpolation) == (float(n), "exact")
        # Non-integer rungs too.
        assert effective_spp(0.25, [0.5, 1.5, 4.25], [1.0, 0.25, 0.1]) == (1.5, "exact")

    def test_interpolated_inverse_mse_is_exact_on_ideal_ladder(self):
        R = _ideal_rmse(SPP16, a=0.7)
        for k in (1.6, 2.5, 7.25, 15.9):
            spp, flag = effective_spp(math.sqrt(0.7 / k), SPP16, R)
            assert flag == "interpolated"
            assert spp == pytest.approx(k, rel=1e-12)
        # Uneven rungs (the paper's figure shows 1, 2, 8, 16): still exact.
        rungs = [1, 2, 8, 16]
        assert effective_spp(1 / math.sqrt(5.0), rungs, _ideal_rmse(rungs))[0] == pytest.approx(5.0, rel=1e-12)

    def test_interpolated_linear(self):
        R = _ideal_rmse(SPP16)
        r = 1 / math.sqrt(1.6)
        spp, flag = effective_spp(r, SPP16, R, interpolation="linear")
        expected = 1 + (1 - r) / (1 - 1 / math.sqrt(2))  # linear in RMSE between rungs 1 and 2
        assert flag == "interpolated"
        assert spp == pytest.approx(expected, rel=1e-12)
        assert spp > 1.6  # RMSE is convex in n: the linear reading over-estimates between rungs

    def test_extrapolated_low(self):
        R = _ideal_rmse(SPP16)
        spp, flag = effective_spp(math.sqrt(2.0), SPP16, R)  # MSE 2 = 1 / 0.5
        assert flag == "extrapolated_low"
        assert spp == pytest.approx(0.5, rel=1e-12)
        # With a floor b, the 1/n law acts on MSE - b: still exact for MSE = 1/n + b.
        Rb = _ideal_rmse(SPP16, b=0.01)
        spp, flag = effective_spp(math.sqrt(1 / 0.25 + 0.01), SPP16, Rb)
        assert flag == "extrapolated_low" and spp == pytest.approx(0.25, rel=1e-9)

    def test_extrapolated_high(self):
        R = _ideal_rmse(SPP16)
        spp, flag = effective_spp(1 / math.sqrt(40.0), SPP16, R)
        assert flag == "extrapolated_high"
        assert spp == pytest.approx(40.0, rel=1e-9)
        Rb = _ideal_rmse(SPP16, a=1.0, b=0.004)
        spp, flag = effective_spp(math.sqrt(1 / 40 + 0.004), SPP16, Rb)
        assert flag == "extrapolated_high" and spp == pytest.approx(40.0, rel=1e-6)

    def test_beyond_floor(self):
        Rb = _ideal_rmse(SPP16, a=1.0, b=0.004)
        for mse_value in (0.0039, 0.003, 0.0):  # below the floor, perfect image
            spp, flag = effective_spp(math.sqrt(mse_value), SPP16, Rb)
            assert (spp, flag) == (math.inf, "beyond_floor")
        # Just above the floor: finite but large, never clamped.
        spp, flag = effective_spp(math.sqrt(0.004 + 1e-6), SPP16, Rb)
        assert flag == "extrapolated_high" and spp == pytest.approx(1e6, rel=1e-4)
        # Zero error against an ideal ladder (b = 0) is beyond the floor too.
        assert effective_spp(0.0, SPP16, _ideal_rmse(SPP16)) == (math.inf, "beyond_floor")

    def test_fitted_nonmonotonic(self):
        R = _ideal_rmse(SPP16, a=1.0, b=0.002)
        R[10], R[11] = R[11], R[10]  # noise made rungs 11 and 12 cross
        spp, flag = effective_spp(math.sqrt(1 / 6 + 0.002), SPP16, R)
        assert flag == "fitted_nonmonotonic"
        a, b = fit_ladder(SPP16, R)
        assert spp == pytest.approx(float(a) / (1 / 6 + 0.002 - float(b)), rel=1e-12)
        assert spp == pytest.approx(6.0, rel=0.02)
        # Below the fitted floor: inf, flagged beyond_floor.
        assert effective_spp(math.sqrt(0.5 * float(b)), SPP16, R) == (math.inf, "beyond_floor")
        # A tie is not strictly decreasing either.
        R2 = _ideal_rmse([1, 2, 3, 4])
        R2[2] = R2[1]
        assert effective_spp(0.6, [1, 2, 3, 4], R2)[1] == "fitted_nonmonotonic"

    def test_nan_input_raises(self):
        with pytest.raises(ValueError, match="finite"):
            effective_spp(float("nan"), SPP16, _ideal_rmse(SPP16))
        with pytest.raises(ValueError, match="finite"):
            effective_spp(torch.tensor(float("nan")), SPP16, _ideal_rmse(SPP16))

    def test_exceptions(self):
        R = _ideal_rmse(SPP16)
        with pytest.raises(ValueError):
            effective_spp(float("inf"), SPP16, R)
        with pytest.raises(ValueError, match=">= 0"):
            effective_spp(-0.1, SPP16, R)
        with pytest.raises(ValueError, match="interpolation"):
            effective_spp(0.5, SPP16, R, interpolation="cubic")
        with pytest.raises(ValueError, match="strictly increasing"):
            effective_spp(0.5, [1, 3, 2], [1.0, 0.6, 0.7])
        with pytest.raises(ValueError, match="> 0"):
            effective_spp(0.5, [0, 1], [1.0, 0.6])
        with pytest.raises(ValueError, match="finite and > 0"):
            effective_spp(0.5, [1, 2], [1.0, float("nan")])
        with pytest.raises(ShapeError):
            effective_spp(0.5, [1, 2, 3], [1.0, 0.6])
        with pytest.raises(ShapeError):
            effective_spp([0.5, 0.4], SPP16, R)
        with pytest.raises(ShapeError, match="effective_spp_many"):
            effective_spp(0.5, SPP16, [R, R])

    def test_hard_cases(self):
        R = _ideal_rmse(SPP16)
        # Continuity at every rung, from both sides.
        for n, r in zip(SPP16, R):
            for interpolation in ("inverse_mse", "linear"):
                up, _ = effective_spp(r * (1 + 1e-9), SPP16, R, interpolation)
                down, _ = effective_spp(r * (1 - 1e-9), SPP16, R, interpolation)
                assert up <= n <= down
                assert down - up < 1e-6 * n
        # A single-rung ladder: everything is an extrapolation of the 1/n law.
        assert effective_spp(0.5, [1], [1.0]) == (pytest.approx(4.0), "extrapolated_high")
        assert effective_spp(2.0, [1], [1.0]) == (pytest.approx(0.25), "extrapolated_low")
        # Tensor inputs of other dtypes are accepted.
        spp, flag = effective_spp(
            torch.tensor(0.5, dtype=torch.float32), torch.arange(1, 17), torch.tensor(R, dtype=torch.float32)
        )
        assert (spp, flag) == (4.0, "exact")  # 0.5 is the 4-spp rung in float32 as well
        spp, flag = effective_spp(
            torch.tensor(0.45, dtype=torch.float32), torch.arange(1, 17), torch.tensor(R, dtype=torch.float32)
        )
        assert flag == "interpolated" and spp == pytest.approx(1 / 0.45**2, rel=1e-6)

    @pytest.mark.parametrize("scale", [1e-300, 1e-160, 1e-155, 1e155, 1e160, 1e300])
    def test_ladders_near_the_float64_range(self, scale, capfd):
        """Effective spp is a ratio of MSEs: a ladder and values scaled by any factor float64 holds give the same
        result (their squares under- or overflowed: NaN at 1e-160, an MKL message on stdout and torch's INTERNAL
        ASSERT at 1e155). Inside the range the scaling is bit-exact."""
        R = _ideal_rmse(SPP16)
        want, flags = effective_spp_many([0.6, 0.2, 0.05], SPP16, R)
        got, got_flags = effective_spp_many([0.6 * scale, 0.2 * scale, 0.05 * scale], SPP16, [r * scale for r in R])
        assert got_flags == flags and torch.allclose(got, want, rtol=1e-12), (got, want)
        spp, flag = effective_spp(0.6 * scale, SPP16, [r * scale for r in R])
        assert flag == "interpolated" and spp == pytest.approx(1 / 0.36, rel=1e-12)
        assert capfd.readouterr().out == ""
        if scale > 1e150:  # the fit's MSE itself is beyond float64: a clear error, not inf
            with pytest.raises(ParameterError, match="beyond float64's range"):
                fit_ladder(SPP16, [r * scale for r in R])

    def test_power_of_two_scaling_is_bit_exact(self):
        """Scaling a ladder and its values by 2^k changes nothing, bit for bit (the estimator's unit scaling)."""
        g = torch.Generator().manual_seed(5)
        R = torch.tensor(_ideal_rmse(SPP16), dtype=torch.float64) * (
            1 + 0.03 * torch.randn(16, generator=g, dtype=torch.float64)
        )
        r = torch.rand(8, generator=g, dtype=torch.float64) * 1.2
        want = effective_spp_many(r, SPP16, R)
        for k in (-900, -40, 40, 900):
            got = effective_spp_many(r * 2.0**k, SPP16, R * 2.0**k)
            assert torch.equal(got[0], want[0]) and got[1] == want[1], k

    def test_ladder_wider_than_float64_squares(self):
        with pytest.raises(ParameterError, match="too wide a range"):
            effective_spp_many([1e-100], [1, 2], [1e160, 1e-160])


class TestEffectiveSppMany:
    def test_smoke(self):
        spp, flags = effective_spp_many([0.5, 0.3], [1, 2, 4], [1.0, 2**-0.5, 0.5])
        assert flags == ["exact", "extrapolated_high"]
        torch.testing.assert_close(spp, torch.tensor([4.0, 1 / 0.09], dtype=F64))

    def test_cardinality(self):
        R = _ideal_rmse(SPP16)
        values = torch.tensor([2.0, 1.0, 0.7, 0.3, 0.2, 0.0], dtype=F64)
        spp, flags = effective_spp_many(values, SPP16, R)
        assert spp.shape == (6,) and spp.dtype == F64 and len(flags) == 6
        assert flags == [
            "extrapolated_low",
            "exact",
            "interpolated",
            "interpolated",
            "extrapolated_high",
            "beyond_floor",
        ]
        # Same as the scalar version, value by value.
        for v, s_, f in zip(values.tolist(), spp.tolist(), flags):
            assert effective_spp(v, SPP16, R) == (s_, f)
        # Empty input.
        spp, flags = effective_spp_many(torch.zeros(0), SPP16, R)
        assert spp.shape == (0,) and flags == []

    def test_ladder_per_frame(self):
        R = torch.tensor([_ideal_rmse(SPP16, a=1.0), _ideal_rmse(SPP16, a=4.0)], dtype=F64)  # 2x16
        R_nonmono = R[1].clone()
        R_nonmono[3], R_nonmono[4] = R[1, 4], R[1, 3]
        R3 = torch.stack([R[0], R[1], R_nonmono])
        values = torch.stack([R[0, 2], R[1, 2], R[1, 2]])  # the 3-spp rungs
        spp, flags = effective_spp_many(values, SPP16, R3)
        assert flags == ["exact", "exact", "fitted_nonmonotonic"]
        torch.testing.assert_close(spp, torch.full((3,), 3.0, dtype=F64), rtol=0.05, atol=0)
        assert spp[0] == 3.0 and spp[1] == 3.0

    def test_exceptions(self):
        R = torch.tensor([_ideal_rmse(SPP16)] * 3, dtype=F64)
        with pytest.raises(ShapeError, match="F=2"):
            effective_spp_many([0.5, 0.4], SPP16, R)
        with pytest.raises(ShapeError):
            effective_spp_many([[0.5]], SPP16, R[0])
        with pytest.raises(ValueError, match=r"frame\(s\) \[1\]"):
            effective_spp_many([0.5, float("nan"), 0.3], SPP16, R[0])
        flat = R.clone()
        flat[2] = torch.linspace(0.5, 0.6, 16)
        with pytest.raises(ValueError, match=r"does not decrease.*\[2\]"):
            effective_spp_many([0.5, 0.4, 0.3], SPP16, flat)


class TestEffectiveSppLadder:
    def test_smoke(self):
        ladder = EffectiveSppLadder(torch.arange(1, 17), torch.tensor(_ideal_rmse(SPP16)))
        assert ladder(0.5) == (4.0, "exact")
        assert ladder.ladder_spp.dtype == F64
        a, b = ladder.fit
        assert a == pytest.approx(1.0) and b == 0.0
        spp, flags = ladder.many([1 / math.sqrt(2.5), 0.5])
        assert flags == ["interpolated", "exact"] and float(spp[0]) == pytest.approx(2.5)
        lin = EffectiveSppLadder(SPP16, _ideal_rmse(SPP16), interpolation="linear")
        assert lin(1 / math.sqrt(2.5))[0] > 2.5

    def test_from_images(self):
        ref = torch.zeros(1, 1, 2, 2, dtype=F64)
        images = [torch.full_like(ref, 1 / math.sqrt(n)) for n in (1, 2, 4)]
        ladder = EffectiveSppLadder.from_images([1, 2, 4], images, ref)
        assert ladder(1 / math.sqrt(3)) == (pytest.approx(3.0), "interpolated")
        with pytest.raises(ShapeError, match="B = 2"):
            EffectiveSppLadder.from_images([1, 2], torch.rand(2, 2, 1, 2, 2), torch.zeros(2, 1, 2, 2))

    def test_exceptions(self):
        with pytest.raises(ShapeError):
            EffectiveSppLadder(SPP16, [_ideal_rmse(SPP16)] * 2)
        with pytest.raises(ValueError, match="interpolation"):
            EffectiveSppLadder(SPP16, _ideal_rmse(SPP16), interpolation="spline")
        with pytest.raises(ValueError, match="does not decrease"):
            EffectiveSppLadder([1, 2, 3], [0.5, 0.6, 0.7])
        ladder = EffectiveSppLadder(SPP16, _ideal_rmse(SPP16))
        with pytest.raises(AttributeError):
            ladder.interpolation = "linear"  # frozen


class TestSuggestReferenceSpp:
    def test_smoke(self):
        assert suggest_reference_spp(16) == 16  # the study: inside the ladder a reference at its top is enough
        assert suggest_reference_spp(32) == 32
        assert suggest_reference_spp(16, ratio=8) == 128
        assert suggest_reference_spp(10, ratio=16) == 256  # 160 rounded up to a power of two
        assert suggest_reference_spp(10) == 16
        assert suggest_reference_spp(0.1, ratio=1) == 1

    def test_exceptions(self):
        for bad in (0, -1, math.inf, math.nan):
            with pytest.raises(ValueError):
                suggest_reference_spp(bad)
        with pytest.raises(ValueError):
            suggest_reference_spp(16, ratio=0.5)


# ----------------------------------------------------------------------------------------------------------
# Synthetic validation: simulated path tracing, known true spp
# ----------------------------------------------------------------------------------------------------------


class TestSyntheticValidation:
    """truth + Gaussian noise; a "k-spp" method image must measure k spp (module docstring for the tolerance)."""

    N_MAX = 16
    CASES = [
        (0.5, "extrapolated_low"),
        (1.6, "interpolated"),
        (4.0, "interpolated"),
        (9.0, "interpolated"),
        (24.0, "extrapolated_high"),
    ]

    def _measure(self, seed, n_ref, ks):
        gen = torch.Generator().manual_seed(seed)
        truth = _truth()
        ladder = _nested_ladder(truth, self.N_MAX, gen)
        ref = truth if n_ref is None else _noisy(truth, n_ref, gen)  # streams disjoint from the ladder's
        R = ladder_rmse(ladder, ref)  # 1xN
        r = torch.cat([rmse(_noisy(truth, k, gen), ref) for k in ks])
        return effective_spp_many(r, range(1, self.N_MAX + 1), R[0]), truth.numel()

    @staticmethod
    def _tol(k, flag, P, noisy_ref):
        # 5 standard deviations; extrapolation and a poor reference (N_ref = 2 n_last) get twice that.
        z = 10.0 if (flag == "extrapolated_high" or noisy_ref) else 5.0
        return z * _rel_sd(P) * k

    @pytest.mark.parametrize("n_ref", [None, 256, 32], ids=["exact_ref", "ref256", "ref32"])
    def test_measured_spp_matches_true_spp(self, n_ref):
        ks = [k for k, _ in self.CASES]
        (spp, flags), P = self._measure(seed=7, n_ref=n_ref, ks=ks)
        assert flags == [f for _, f in self.CASES]
        for k, s_, f in zip(ks, spp.tolist(), flags):
            tol = self._tol(k, f, P, n_ref is not None and n_ref < 256)
            assert abs(s_ - k) <= tol, f"k={k}: measured {s_:.4f}, tolerance ±{tol:.4f} ({f}, N_ref={n_ref})"

    def test_noisy_reference_cancels_but_naive_does_not(self):
        """With N_ref = 32 the reference adds SIGMA²/32 to every MSE: matched against a ladder scored on the same
        reference it cancels; scored against the *truth* ladder it would bias 9 spp down to ~7."""
        gen = torch.Generator().manual_seed(11)
        truth = _truth()
        ladder = _nested_ladder(truth, self.N_MAX, gen)
        ref = _noisy(truth, 32, gen)
        method = _noisy(truth, 9.0, gen)
        P = truth.numel()
        r = rmse(method, ref)
        good, flag = effective_spp(r, range(1, 17), ladder_rmse(ladder, ref)[0])
        naive, _ = effective_spp(r, range(1, 17), ladder_rmse(ladder, truth)[0])
        assert flag == "interpolated"
        assert abs(good - 9.0) <= 10 * _rel_sd(P) * 9.0
        expected_naive = 1 / (1 / 9 + 1 / 32)  # 7.02
        assert abs(naive - expected_naive) <= 10 * _rel_sd(P) * expected_naive
        assert naive < 9.0 - 10 * _rel_sd(P) * 9.0

    def test_nonmonotonic_ladder(self):
        """Rungs 1..64 from independent streams at P = 12288: neighbouring rungs differ by less than their noise,
        so the ladder is non-monotonic and the fit must recover the true spp."""
        gen = torch.Generator().manual_seed(5)
        truth = _truth(64, 64)
        spp_list = list(range(1, 65))
        ref = _noisy(truth, 1024, gen)
        R = ladder_rmse([_noisy(truth, n, gen) for n in spp_list], ref)[0]
        assert not bool((R[1:] < R[:-1]).all()), "precondition: the simulated ladder must be non-monotonic"
        ks = [6.0, 20.0, 40.0]
        r = torch.cat([rmse(_noisy(truth, k, gen), ref) for k in ks])
        spp, flags = effective_spp_many(r, spp_list, R)
        assert flags == ["fitted_nonmonotonic"] * 3
        P = truth.numel()
        for k, s_ in zip(ks, spp.tolist()):
            assert abs(s_ - k) <= 5 * _rel_sd(P) * k, f"k={k}: measured {s_:.3f}"


# ----------------------------------------------------------------------------------------------------------
# Properties
# ----------------------------------------------------------------------------------------------------------


@st.composite
def _monotonic_ladders(draw):
    n = draw(st.integers(1, 8))
    steps = draw(st.lists(st.floats(0.05, 8.0), min_size=n, max_size=n))
    spp = [sum(steps[: i + 1]) for i in range(n)]
    r0 = draw(st.floats(0.01, 10.0))
    factors = draw(st.lists(st.floats(0.3, 0.9999), min_size=n - 1, max_size=n - 1))
    rmse_ = [r0]
    for f in factors:
        rmse_.append(rmse_[-1] * f)
    return spp, rmse_


class TestMonotonicityProperty:
    @settings(max_examples=150, deadline=None)
    @given(
        ladder=_monotonic_ladders(),
        u=st.floats(0.0, 1.0),
        v=st.floats(0.0, 1.0),
        interpolation=st.sampled_from(["inverse_mse", "linear"]),
    )
    def test_lower_rmse_never_lower_spp(self, ladder, u, v, interpolation):
        spp_list, R = ladder
        lo_r, hi_r = sorted((u, v))
        top = 2.0 * R[0]
        values = [lo_r * top, hi_r * top] + list(R)  # include the rungs themselves
        spp, flags = effective_spp_many(values, spp_list, R, interpolation)
        assert set(flags) <= set(EFFECTIVE_SPP_FLAGS)
        assert "fitted_nonmonotonic" not in flags
        assert float(spp[0]) >= float(spp[1])
        assert bool((spp >= 0).all())
        # Sorting all values by RMSE sorts their spp the other way.
        order = torch.tensor(values, dtype=F64).argsort()
        s_sorted = spp[order]
        assert bool((s_sorted[1:] <= s_sorted[:-1]).all())

    @settings(max_examples=60, deadline=None)
    @given(a=st.floats(1e-4, 1e2), k=st.floats(1.0, 16.0))
    def test_ideal_ladder_recovers_spp(self, a, k):
        spp, flag = effective_spp(math.sqrt(a / k), SPP16, _ideal_rmse(SPP16, a=a))
        assert flag in ("exact", "interpolated")
        assert spp == pytest.approx(k, rel=1e-9)
