"""``Blend(footprint_weighting=True)``: the warped history length scaled by the footprint quality (NVIDIA NRD's
rule), ``n ← n·(0.5 + 0.5·q)`` with ``q`` the accepted bilinear weight of the 2×2 taps before renormalisation,
then the blend of :func:`temporal_blend` with the scaled ``n`` (warm-up weight, cap, rounding).

The hand-built case: a fronto-parallel plane whose motion vectors move every pixel by (0.25, 0.25) px, so the taps
of a destination pixel carry the bilinear weights 9/16, 3/16, 3/16 and 1/16; previous-frame depths far off the
plane reject chosen taps by the position test. Parity with the native kernel and the export formulation lives in
test_reproject_native.py and test_export.py (their parametrisations).
"""

from __future__ import annotations

import pytest
import torch

from base import BaseTester
from stereorepro import Blend, History, SpatiotemporalReprojection, TemporalReprojection, View, temporal_reproject
from stereorepro.camera import intrinsics_from_fov
from stereorepro.errors import ParameterError
from stereorepro.reproject import Thresholds

H, W = 8, 10
N_HIST, ALPHA = 8.0, 0.05


def _plane_case(dtype=torch.float32, rejected=((2, 3), (3, 2), (3, 3))):
    """(view, prev_view, history): destination pixel (y=2, x=2) reads taps (2,2) 9/16, (2,3) 3/16, (3,2) 3/16,
    (3,3) 1/16 (y, x); the previous depth is off the plane at ``rejected``."""
    depth = torch.full((1, 1, H, W), 2.0, dtype=dtype)
    normal = torch.zeros(1, 3, H, W, dtype=dtype)
    normal[:, 2] = -1.0
    K = intrinsics_from_fov(60.0, W, H).to(dtype)
    pose = torch.eye(4, dtype=dtype)[None]
    motion = torch.full((1, 2, H, W), 0.25, dtype=dtype)
    view = View(depth, normal, K, pose, motion=motion)
    prev_depth = depth.clone()
    for y, x in rejected:
        prev_depth[..., y, x] = 5.0
    prev_view = View(prev_depth, normal, K, pose)
    history = History(torch.ones(1, 3, H, W, dtype=dtype), torch.full((1, 1, H, W), N_HIST, dtype=dtype))
    return view, prev_view, history


def _run(footprint: bool, backend: str, dtype=torch.float32, **case):
    view, prev_view, history = _plane_case(dtype, **case)
    blend = Blend(ALPHA, True, 255.0, footprint_weighting=footprint)
    cur = torch.zeros(1, 3, H, W, dtype=dtype)
    return temporal_reproject(cur, view, history, prev_view, Thresholds(1.0, 0.1), blend=blend, backend=backend)


class TestFootprintWeighting(BaseTester):
    @pytest.mark.parametrize(
        "rejected, q",
        [(((2, 3), (3, 2), (3, 3)), 9 / 16), (((2, 2), (2, 3), (3, 2)), 1 / 16), ((), 1.0)],
        ids=["one-of-four-9/16", "one-of-four-1/16", "all-four"],
    )
    def test_definition(self, backend, rejected, q):
        """One accepted tap of weight w: the length n·(0.5 + 0.5·w) + 1, the colour weight 1/(n·(0.5 + 0.5·w) + 1)
        (warm-up above alpha); all four taps: n + 1, as without the option."""
        out = _run(True, self.backend_arg(backend), rejected=rejected)
        n = N_HIST * (0.5 + 0.5 * q)
        assert bool(out.valid[0, 0, 2, 2])
        assert float(out.history_len[0, 0, 2, 2]) == pytest.approx(n + 1.0, rel=1e-6)
        assert float(out.color[0, 0, 2, 2]) == pytest.approx(1.0 - 1.0 / (n + 1.0), rel=1e-6)
        plain = _run(False, self.backend_arg(backend), rejected=rejected)
        assert float(plain.history_len[0, 0, 2, 2]) == pytest.approx(N_HIST + 1.0, rel=1e-6)

    def test_cap_and_rounding_after_the_scaling(self):
        """max_history caps the scaled length + 1; "bmfr" rounds the scaled length (8·(0.5 + 0.5·9/16) = 6.25 → 6)."""
        view, prev_view, history = _plane_case()
        cur = torch.zeros(1, 3, H, W)
        thr = Thresholds(1.0, 0.1)
        capped = temporal_reproject(cur, view, history, prev_view, thr, blend=Blend(ALPHA, True, 7.0, "none", True))
        assert float(capped.history_len[0, 0, 2, 2]) == 7.0  # min(6.25 + 1, 7)
        rounded = temporal_reproject(cur, view, history, prev_view, thr, blend=Blend(ALPHA, True, 255.0, "bmfr", True))
        assert float(rounded.history_len[0, 0, 2, 2]) == 7.0  # round(6.25) + 1
        assert float(rounded.color[0, 0, 2, 2]) == pytest.approx(1.0 - 1.0 / 7.25, rel=1e-6)  # weight from 6.25

    def test_off_is_unchanged(self, backend):
        """footprint_weighting=False gives the bytes of a Blend without the field."""
        view, prev_view, history = _plane_case()
        cur = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0))
        be = self.backend_arg(backend)
        a = temporal_reproject(cur, view, history, prev_view, Thresholds(1.0, 0.1), blend=Blend(ALPHA), backend=be)
        b = temporal_reproject(
            cur, view, history, prev_view, Thresholds(1.0, 0.1), blend=(ALPHA, True, 255.0), backend=be
        )
        self.assert_identical(tuple(a[:3]), tuple(b[:3]))

    def test_gradcheck(self):
        """Differentiable (float64, torch reference) in the current colour, the history colour and alpha."""
        view, prev_view, history = _plane_case(torch.float64)
        g = torch.Generator().manual_seed(3)
        cur = torch.rand(1, 3, H, W, dtype=torch.float64, generator=g, requires_grad=True)
        hist = torch.rand(1, 3, H, W, dtype=torch.float64, generator=g, requires_grad=True)
        alpha = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)

        def f(c, h, a):
            blend = Blend(a, True, 255.0, footprint_weighting=True)
            hs = History(h, history.length)
            return temporal_reproject(c, view, hs, prev_view, Thresholds(1.0, 0.1), blend=blend, backend="torch")[0]

        assert torch.autograd.gradcheck(f, (cur, hist, alpha), eps=1e-6, atol=1e-5)

    @pytest.mark.parametrize("value", [1, "yes", None])
    def test_not_a_bool(self, value):
        """A non-bool footprint_weighting raises ParameterError naming where."""
        view, prev_view, history = _plane_case()
        cur = torch.zeros(1, 3, H, W)
        with pytest.raises(
            ParameterError, match="temporal_reproject: blend: footprint_weighting must be True or False"
        ):
            temporal_reproject(
                cur, view, history, prev_view, Thresholds(1.0, 0.1), blend=Blend(footprint_weighting=value)
            )
        with pytest.raises(ParameterError, match="TemporalReprojection: footprint_weighting"):
            TemporalReprojection(0.05, 0.1).footprint_weighting = value
        with pytest.raises(ParameterError, match="SpatiotemporalReprojection: footprint_weighting"):
            SpatiotemporalReprojection(0.05, 0.1).footprint_weighting = value

    def test_module_and_driver(self, backend):
        """The module's attribute reaches its blend; the driver's property is the temporal module's."""
        m = TemporalReprojection(1.0, 0.1, alpha=ALPHA, backend=self.backend_arg(backend))
        m.footprint_weighting = True
        assert m.blend.footprint_weighting and "footprint_weighting=True" in repr(m)
        view, prev_view, history = _plane_case()
        cur = torch.zeros(1, 3, H, W)
        geometry = (view.depth, view.normal, view.K, view.cam_from_world)
        prev = (prev_view.depth, prev_view.normal, prev_view.K, prev_view.cam_from_world)
        got = m(cur, *geometry, *history, *prev, motion=view.motion)
        ref = _run(True, self.backend_arg(backend))
        self.assert_identical(tuple(got), tuple(ref[:3]))
        st = SpatiotemporalReprojection(0.05, 0.1)
        st.footprint_weighting = True
        assert st.temporal_module.footprint_weighting is True

    def test_blended_scheme_history(self, backend):
        """warp_history (the blended scheme's own history) scales the warped length the same way: n·(0.5 + 0.5·w)
        at the pixel whose one accepted tap has weight 9/16, n elsewhere inside the plane."""
        from stereorepro.accumulate import EyeState, warp_history

        view, prev_view, history = _plane_case()
        state = EyeState(*history, prev_view.depth, prev_view.normal, prev_view.K, prev_view.cam_from_world)
        m = TemporalReprojection(1.0, 0.1, backend=self.backend_arg(backend))
        geometry = (view.depth, view.normal, view.K, view.cam_from_world)
        plain = warp_history(m, state, *geometry, view.motion)[1]
        m.footprint_weighting = True
        scaled = warp_history(m, state, *geometry, view.motion)[1]
        assert float(plain[0, 0, 2, 2]) == pytest.approx(N_HIST, rel=1e-6)
        assert float(scaled[0, 0, 2, 2]) == pytest.approx(N_HIST * (0.5 + 0.5 * 9 / 16), rel=1e-6)
        assert torch.equal(plain[..., 5:7, 5:8], scaled[..., 5:7, 5:8])  # all four taps accepted: n unchanged
