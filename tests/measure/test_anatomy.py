"""Error anatomy (stereorepro.measure.anatomy): shares, concentration, two-rung effective spp, edges, the split
bias estimator and the reprojection's footprint."""

import math

import pytest
import torch

from stereorepro import View, backward_reproject
from stereorepro._testing import camera_pair, default_scene, raycast
from stereorepro.camera import has_surface
from stereorepro.errors import ParameterError, ShapeError
from stereorepro.measure.anatomy import (
    block_standard_error,
    edge_mask,
    error_concentration,
    error_shares,
    footprint_failures,
    footprint_regions,
    reference_noise_mse,
    split_bias,
    squared_error,
    two_rung_spp,
)
from stereorepro.reproject import Reason


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


class TestBiasEstimator:
    def test_split_bias_is_the_product_of_the_errors(self):
        g = torch.Generator().manual_seed(4)
        a, b = torch.randn(1, 3, 5, 6, generator=g), torch.randn(1, 3, 5, 6, generator=g)
        p = split_bias(a, b)
        assert p.shape == (1, 1, 5, 6) and p.dtype == torch.float64
        assert float(p.mean()) == pytest.approx(float((a.double() * b.double()).mean()), rel=1e-12)
        with pytest.raises(ShapeError, match="error_a"):
            split_bias(a, b[..., :5])

    def test_block_standard_error(self):
        x = torch.zeros(1, 1, 16, 24, dtype=torch.float64)
        assert block_standard_error(x) == 0.0  # no spread
        x[..., 8:, :] = 2.0  # 6 tiles: three at 0, three at 2
        se = block_standard_error(x, block=8)
        assert se == pytest.approx(float(torch.tensor([0.0, 0, 0, 2, 2, 2]).std()) / 6**0.5)
        assert block_standard_error(x[..., :8, :8]) == 0.0  # one tile: no estimate
        with pytest.raises(ParameterError, match="block"):
            block_standard_error(x, block=0)

    def test_reference_noise_of_two_halves(self):
        g = torch.Generator().manual_seed(5)
        sigma, r = 0.2, torch.rand(1, 3, 64, 64, generator=g, dtype=torch.float64)
        a = r + sigma / 2 * torch.randn(r.shape, generator=g, dtype=torch.float64)  # 4 samples
        b = r + sigma / 4**0.5 / 2 * torch.randn(r.shape, generator=g, dtype=torch.float64)  # 16 samples
        assert reference_noise_mse(a, b, 4, 16) == pytest.approx(sigma**2 / 20, rel=0.05)
        with pytest.raises(ParameterError, match="spp"):
            reference_noise_mse(a, b, 0, 4)


def _views(**motion):
    """The default test scene seen by a stereo pair (with head motion: occlusions, disocclusions, edges)."""
    dst, src = camera_pair(36, 48, **motion)
    scene = default_scene()
    gd, gs = raycast(dst, scene, torch.float32), raycast(src, scene, torch.float32)
    view = lambda g, cam: View(g.depth, g.normal, cam.K.float(), cam.cam_from_world.float())  # noqa: E731
    return view(gs, src), view(gd, dst)


class TestFootprint:
    THR = (0.08, 0.3)

    def test_the_bilinear_footprint_is_the_reprojections_test(self):
        src, dst = _views(forward=0.05, yaw_deg=0.5)
        r = backward_reproject(torch.zeros_like(dst.depth), src, dst, self.THR)
        fails2 = footprint_failures(src, dst, self.THR, size=2)
        inner = r.reason != int(Reason.OUT_OF_FRAME)
        surface = has_surface(dst.depth)
        # kept pixels have an accepted tap (fewer than 4 fail); a rejected surface pixel inside the frame has a tap
        # that fails, or all its accepted taps carry no weight
        assert bool((fails2[r.valid] < 4).all())
        assert bool((fails2[~r.valid & surface & inner] >= 1).float().mean() > 0.95)
        fails4 = footprint_failures(src, dst, self.THR, size=4)
        assert bool((fails4 >= fails2).all()) and int(fails4.max()) <= 16
        # the 4×4 footprint flags more kept pixels as near an edge than the 2×2 one
        assert int((r.valid & (fails4 > 0)).sum()) > int((r.valid & (fails2 > 0)).sum()) > 0

    def test_out_of_frame_taps_do_not_fail(self):
        src, _ = _views()  # every pixel has a surface (walls and floor behind the spheres)
        assert bool(has_surface(src.depth).all())
        fails = footprint_failures(src, src, (1e9, 1e9))  # tests that accept every surface tap
        assert int(fails.max()) == 0  # the border pixels' footprints reach out of the frame: those taps don't count

    def test_regions_partition_the_pixels(self):
        src, dst = _views(forward=0.05, yaw_deg=0.5)
        thr = (0.3, 0.3)  # the default 0.08 rejects every outer tap at 48×36 (pixels ~0.13 apart): no interior
        r = backward_reproject(torch.zeros_like(dst.depth), src, dst, thr)
        regions = footprint_regions(footprint_failures(src, dst, thr), r.valid, has_surface(dst.depth))
        total = sum(m.to(torch.int64) for m in regions.values())
        assert bool((total == 1).all()) and set(regions) == {"interior", "edge", "discarded", "no surface"}
        assert all(int(regions[k].sum()) > 0 for k in ("interior", "edge", "discarded"))

    def test_size_is_checked(self):
        src, dst = _views()
        with pytest.raises(ParameterError, match="size"):
            footprint_failures(src, dst, self.THR, size=3)
