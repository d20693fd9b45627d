"""Error anatomy (stereorepro.measure.anatomy): shares, concentration, two-rung effective spp, edges."""

import math

import pytest
import torch

from stereorepro.measure.anatomy import edge_mask, error_concentration, error_shares, squared_error, two_rung_spp


class TestAnatomy:
    def test_squared_error_is_the_mse_per_pixel(self):
        g = torch.Generator().manual_seed(0)
        a, b = torch.rand(1, 3, 8, 9, generator=g), torch.rand(1, 3, 8, 9, generator=g)
        se = squared_error(a, b)
        assert se.shape == (1, 1, 8, 9) and se.dtype == torch.float64
        assert float(se.mean()) == pytest.approx(float(((a.double() - b.double()) ** 2).mean()), rel=1e-12)

    def test_concentration(self):
        se = torch.zeros(1, 1, 10, 10, dtype=torch.float64)
        se.view(-1)[:1] = 99.0
        se.view(-1)[1:] = 1.0 / 99
        c = error_concentration(se)
        assert c["top_1pct"] == pytest.approx(99.0) and c["top_5pct"] == pytest.approx(99.0 + 4.0 / 99 / 1.0, rel=1e-3)

    def test_shares_of_a_partition_add_up(self):
        se = torch.rand(1, 1, 6, 7, dtype=torch.float64)
        m = torch.rand(1, 1, 6, 7) > 0.3
        s = error_shares(se, {"a": m, "b": ~m}, se_bias=se / 4)
        assert s["a"]["se_share_pct"] + s["b"]["se_share_pct"] == pytest.approx(100.0)
        assert s["a"]["pixels_pct"] + s["b"]["pixels_pct"] == pytest.approx(100.0)
        assert s["a"]["bias_pct_of_region"] == pytest.approx(25.0)
        empty = error_shares(se, {"none": torch.zeros_like(m)})
        assert empty["none"]["mse"] is None and empty["none"]["se_share_pct"] == 0.0

    @pytest.mark.parametrize("b", [0.0, 0.01])
    def test_two_rung_spp_inverts_the_law(self, b):
        v = 0.5
        law = lambda n: b + v / n  # noqa: E731
        assert two_rung_spp(law(7.0), law(1), law(32), 32) == pytest.approx(7.0)
        assert two_rung_spp(b, law(1), law(32), 32) == math.inf
        assert two_rung_spp(0.1, 0.2, 0.3, 32) is None  # more samples, more error: no fit

    def test_edge_mask(self):
        x = torch.zeros(1, 3, 20, 20)
        x[..., :, 10:] = 1.0  # one vertical edge: columns 9 and 10 have the contrast
        m = edge_mask(x, fraction=0.1)
        assert m.shape == (1, 1, 20, 20) and m.dtype == torch.bool
        assert bool(m[..., :, 9:11].all()) and int(m.sum()) == 40
