"""bench/ladder_extrapolation.py: a cut ladder's extrapolation against the full ladder's interpolation."""

from __future__ import annotations

import math

import pytest
from conftest import load_script

le = load_script("bench", "ladder_extrapolation")


def _results(ladder: list[float], rmse: float, spp: float) -> dict:
    row = {
        "rmse": {"stereo_temporal": rmse},
        "effective_spp": {"stereo_temporal": spp},
        "flags": {"stereo_temporal": "interpolated"},
        "ladder_rmse": {"left": ladder, "right": ladder},
    }
    return {"ladder_spp": len(ladder), "per_frame": [row]}


class TestLadderExtrapolation:
    def test_ideal_ladder_extrapolates_exactly(self):
        ladder = [math.sqrt(0.5 / n) for n in range(1, 33)]  # a / n, no floor
        errs, floor, skipped = le.cut_ladder_errors(_results(ladder, math.sqrt(0.5 / 20), 20.0), 2)
        assert errs == [pytest.approx(0.0, abs=1e-9)] and floor == 0 and skipped == 0

    def test_a_bent_ladder_is_measured_high_and_misfits_skipped(self):
        ladder = [math.sqrt(0.5 / n + 0.01 / math.sqrt(n)) for n in range(1, 33)]  # not a / n + b
        from stereorepro.measure.metrics import effective_spp

        rmse = math.sqrt(0.5 / 24 + 0.01 / math.sqrt(24))
        spp, _ = effective_spp(rmse, list(range(1, 33)), ladder)
        errs, _, skipped = le.cut_ladder_errors(_results(ladder, rmse, spp), 2)
        assert len(errs) == 1 and errs[0] > 0.01 and skipped == 0
        assert le.cut_ladder_errors(_results(ladder, rmse, spp + 1.0), 2)[2] == 1  # not this ladder's value
        assert le.cut_ladder_errors(_results(ladder, rmse, 12.0), 2)[0] == []  # inside the cut ladder: not counted
