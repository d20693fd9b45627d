"""``history_rounding="bmfr"`` against a transliteration of BMFR's accumulation (Koskela et al. 2019, the paper's
group's code: the OpenCL kernel ``accumulate_noisy_data`` of github.com/maZZZu/bmfr), written here from its
published source as plain per-pixel loops, and the option's own contract (gradients, errors).

What the kernel does per pixel of a frame after the first (``bmfr_step``): project the pixel's world position into
the previous frame, take the 2×2 bilinear taps around it; a tap counts if it lies inside the frame, its world
position is within the position limit and its normal within the normal limit (squared distances, strict ``<``);
the counted taps' weights, colours and stored sample counts are summed and the colour and count divided by the
summed weight. With a counted tap the blend weight is ``max(1/(spp + 1), BLEND_ALPHA)`` of the *unrounded*
interpolated count ``spp``, else 1; the new colour is ``w·current + (1 − w)·previous``. The stored count (an 8-bit
buffer) is 1 where the weight is 1, 255 where ``spp > 254``, else ``round_half_even(spp) + 1``.

Two deviations, both outside what the option changes: a pixel or tap without a surface counts as discarded (BMFR's
scenes have a surface at every pixel; ours have background), and BMFR's camera-jitter offset is zero here (the
analytic G-buffers sample pixel centres). The comparison runs our op in float64 so that no accept decision sits
within float32 rounding of a threshold.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from base import BaseTester
from stereorepro import Blend, History, TemporalReprojection, View, temporal_blend, temporal_reproject
from stereorepro.camera import PinholeCamera, intrinsics_from_fov, look_at
from stereorepro.errors import ParameterError
from stereorepro._testing import default_scene, raycast

H, W, FRAMES = 30, 40, 8
POS, NRM, ALPHA = 0.2, 0.3, 0.2  # 0.2: about a pixel's footprint at this size


def camera(t: int) -> PinholeCamera:
    """Frame t of a camera that slides sideways and forward while it turns (float64)."""
    dt = torch.float64
    eye = torch.tensor([[0.3 + 0.04 * t, 1.4 - 0.01 * t, 1.5 - 0.05 * t]], dtype=dt)
    target = torch.tensor([[0.0 + 0.07 * t, 0.8, -3.0]], dtype=dt)
    K = intrinsics_from_fov(60.0, W, H, dtype=dt)
    return PinholeCamera(K, look_at(eye, target, torch.tensor([[0.0, 1.0, 0.0]], dtype=dt)), H, W)


def sequence(seed: int = 0):
    """Per frame: (camera, G-buffer, noisy 1-spp-like colour (1, 3, H, W) float64)."""
    scene = default_scene()
    g = torch.Generator().manual_seed(seed)
    out = []
    for t in range(FRAMES):
        cam = camera(t)
        gb = raycast(cam, scene)
        noise = 0.25 + 1.5 * torch.rand(gb.color.shape, generator=g, dtype=torch.float64)
        out.append((cam, gb, gb.color * noise))
    return out


def bmfr_step(cur, pos, nrm, hit, prev, cam_prev_P, alpha=ALPHA, pos_limit=POS, nrm_limit=NRM):
    """One frame of BMFR's accumulation, pixel by pixel (numpy float64).

    cur: (H, W, 3) this frame's samples; pos, nrm: (H, W, 3) world positions and normals; hit: (H, W) bool;
    prev: None on the first frame, else (color (H, W, 3), spp (H, W) uint8, pos, nrm, hit) of the previous frame;
    cam_prev_P: (3, 4) the previous frame's K·[R|t]. Returns (color (H, W, 3), spp (H, W) uint8).
    """
    color, spp = cur.copy(), np.ones(cur.shape[:2], np.uint8)
    if prev is None:
        return color, spp
    p_color, p_spp, p_pos, p_nrm, p_hit = prev
    for y in range(H):
        for x in range(W):
            if not hit[y, x]:
                continue
            uvw = cam_prev_P @ np.append(pos[y, x], 1.0)
            if uvw[2] <= 0:
                continue
            fx, fy = uvw[0] / uvw[2] - 0.5, uvw[1] / uvw[2] - 0.5  # continuous index of the previous pixel
            x0, y0 = math.floor(fx), math.floor(fy)
            ax, ay = fx - x0, fy - y0
            total, acc_spp, acc_color = 0.0, 0.0, np.zeros(3)
            for dx, dy, w in (
                (0, 0, (1 - ax) * (1 - ay)),
                (1, 0, ax * (1 - ay)),
                (0, 1, (1 - ax) * ay),
                (1, 1, ax * ay),
            ):
                sx, sy = x0 + dx, y0 + dy
                if not (0 <= sx < W and 0 <= sy < H) or not p_hit[sy, sx]:
                    continue
                if np.sum((p_pos[sy, sx] - pos[y, x]) ** 2) >= pos_limit**2:
                    continue
                if np.sum((p_nrm[sy, sx] - nrm[y, x]) ** 2) >= nrm_limit**2:
                    continue
                total += w
                acc_spp += w * float(p_spp[sy, sx])
                acc_color += w * p_color[sy, sx]
            weight = 1.0
            if total > 0:
                acc_color /= total
                acc_spp /= total
                weight = max(1.0 / (acc_spp + 1.0), alpha)
            if weight < 1.0:
                spp[y, x] = 255 if acc_spp > 254 else int(np.rint(acc_spp)) + 1  # np.rint: half to even
            color[y, x] = weight * cur[y, x] + (1 - weight) * acc_color
    return color, spp


def run_bmfr(seq):
    """BMFR over the sequence: [(color (H, W, 3), spp (H, W))] per frame."""

    def hwc(x):
        return x[0].permute(1, 2, 0).numpy()

    out, prev, P_prev = [], None, None
    for cam, gb, noisy in seq:
        hit = torch.isfinite(gb.depth)[0, 0].numpy()
        color, spp = bmfr_step(hwc(noisy), hwc(gb.position), hwc(gb.normal), hit, prev, P_prev)
        out.append((color, spp))
        prev = (color, spp, hwc(gb.position), hwc(gb.normal), hit)
        P_prev = (cam.K[0] @ cam.cam_from_world[0, :3]).numpy()  # this frame's K·[R|t], for the next one
    return out


def run_ours(seq, history_rounding: str, backend: str = "torch", dtype=torch.float64):
    """temporal_reproject over the sequence (the first frame from an empty history): [(color, length)] per frame."""
    out, history, prev_view = [], None, None
    blend = Blend(ALPHA, True, 255.0, history_rounding)
    for cam, gb, noisy in seq:
        view = View(gb.depth.to(dtype), gb.normal.to(dtype), cam.K.to(dtype), cam.cam_from_world.to(dtype))
        if history is None:
            history, prev_view = History.empty(view), view
        with torch.no_grad():
            res = temporal_reproject(
                noisy.to(dtype), view, history, prev_view, (POS, NRM), blend=blend, backend=backend
            )
        history, prev_view = res.history, view
        out.append((res.color[0].permute(1, 2, 0).double().numpy(), res.history_len[0, 0].double().numpy()))
    return out


@pytest.fixture(scope="module")
def seq():
    return sequence()


@pytest.fixture(scope="module")
def bmfr(seq):
    return run_bmfr(seq)


class TestAgainstBmfr(BaseTester):
    def test_bmfr_equals_transliteration(self, seq, bmfr):
        """Every frame: lengths identical, colours equal to float rounding (float64 on both sides)."""
        ours = run_ours(seq, "bmfr")
        for t, ((c_ref, n_ref), (c, n)) in enumerate(zip(bmfr, ours)):
            assert np.array_equal(n, n_ref.astype(np.float64)), f"frame {t}: {int((n != n_ref).sum())} lengths differ"
            assert np.abs(c - c_ref).max() <= 1e-12, f"frame {t}: colour error {np.abs(c - c_ref).max()}"
        last = bmfr[-1][1]
        assert last.max() >= FRAMES - 1 and (last == 1).any() and (last > 1).mean() > 0.5  # kept, restarted, mixed

    def test_none_differs(self, seq, bmfr):
        """The float length (default) drifts from BMFR's: a few per cent of the pixels of the last frame."""
        c_ref = bmfr[-1][0]
        c, n = run_ours(seq, "none")[-1]
        differ = np.abs(c - c_ref).max(axis=-1) > 1e-6
        assert 0.01 < differ.mean() < 0.5, differ.mean()
        assert not np.array_equal(n, bmfr[-1][1].astype(np.float64))

    @pytest.mark.parametrize("impl", ["torch", "fast", "native"])
    def test_float32_backends_follow(self, seq, bmfr, impl, monkeypatch):
        """float32 on each implementation: lengths equal BMFR's but at accept decisions within float32 rounding
        of a threshold (none here), colours within 1e-5."""
        from stereorepro.reproject import _native, functional

        if impl == "native" and not _native.available():
            pytest.skip("native core not built")
        monkeypatch.setattr(functional, "FAST_PATH", impl == "fast")
        ours = run_ours(seq, "bmfr", backend="native" if impl == "native" else "torch", dtype=torch.float32)
        for t, ((c_ref, n_ref), (c, n)) in enumerate(zip(bmfr, ours)):
            assert np.array_equal(n, n_ref.astype(np.float64)), f"frame {t}: {int((n != n_ref).sum())} lengths differ"
            assert np.abs(c - c_ref).max() <= 1e-5, f"frame {t}"


class TestOption(BaseTester):
    def _blend_inputs(self, seed=0):
        g = torch.Generator().manual_seed(seed)
        cur = torch.rand(1, 3, 4, 5, generator=g, dtype=torch.float64)
        hist = torch.rand(1, 3, 4, 5, generator=g, dtype=torch.float64)
        n = torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64) * 20
        return cur, hist, n

    def test_definition(self):
        """round-half-even of the interpolated count, then + 1, capped; the colour weight from the unrounded n."""
        n = torch.tensor([0.0, 0.5, 1.5, 2.5, 2.4999, 3.7, 254.6, 300.0], dtype=torch.float64).view(1, 1, 1, 8)
        cur, hist = torch.ones(1, 3, 1, 8, dtype=torch.float64), torch.zeros(1, 3, 1, 8, dtype=torch.float64)
        valid = torch.ones(1, 1, 1, 8, dtype=torch.bool)
        plain = temporal_blend(cur, hist, n, valid)
        out = temporal_blend(cur, hist, n, valid, history_rounding="bmfr")
        assert out.length.flatten().tolist() == [1.0, 1.0, 3.0, 3.0, 3.0, 5.0, 255.0, 255.0]
        assert torch.equal(out.color, plain.color)
        fixed = temporal_blend(cur, hist, n, valid, alpha=1.0, history_rounding="bmfr")  # weight 1: one sample
        assert bool((fixed.length == 1).all()) and torch.equal(fixed.color, cur)
        assert torch.equal(temporal_blend(cur, hist, n, ~valid, history_rounding="bmfr").length, torch.ones_like(n))

    def test_gradcheck(self):
        """The colour is differentiable as with "none" (the same values); round() has a zero gradient, so the
        length's gradient is zero."""
        cur, hist, n = self._blend_inputs()
        conf = torch.rand(n.shape, dtype=torch.float64)
        args = [x.clone().requires_grad_(True) for x in (cur, hist, conf)]
        alpha = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)

        def colour(c, h, s, a):
            return temporal_blend(c, h, n, s, a, history_rounding="bmfr")[0]

        assert torch.autograd.gradcheck(colour, (*args, alpha), eps=1e-6, atol=1e-5)
        n_req = n.clone().requires_grad_(True)
        valid = torch.ones_like(n, dtype=torch.bool)
        (grad,) = torch.autograd.grad(temporal_blend(cur, hist, n_req, valid, history_rounding="bmfr")[1].sum(), n_req)
        assert bool((grad == 0).all())

    def test_exceptions(self):
        cur, hist, n = self._blend_inputs()
        valid = torch.ones_like(n, dtype=torch.bool)
        with pytest.raises(ParameterError, match="temporal_blend: history_rounding must be one of .*'round'"):
            temporal_blend(cur, hist, n, valid, history_rounding="round")
        cam, gb, noisy = sequence()[0]
        view = View(gb.depth, gb.normal, cam.K, cam.cam_from_world)
        with pytest.raises(ParameterError, match="temporal_reproject: blend: history_rounding.*'BMFR'"):
            temporal_reproject(noisy, view, History.empty(view), view, (POS, NRM), blend=Blend(history_rounding="BMFR"))
        with pytest.raises(ParameterError, match="TemporalReprojection: history_rounding.*None"):
            TemporalReprojection(POS, NRM, history_rounding=None)
        m = TemporalReprojection(POS, NRM)
        with pytest.raises(ParameterError, match="TemporalReprojection: history_rounding"):
            m.history_rounding = "floor"
        assert m.history_rounding == "none" and "history_rounding" not in repr(m)
        m.history_rounding = "bmfr"
        assert m.blend.history_rounding == "bmfr" and "history_rounding='bmfr'" in repr(m)

    def test_old_blend_triple(self):
        """A (alpha, warmup, max_history) triple still works where a Blend is taken: the float length."""
        cam, gb, noisy = sequence()[1]
        view = View(gb.depth, gb.normal, cam.K, cam.cam_from_world)
        hist = History(noisy, torch.full_like(gb.depth, 2.5))
        a = temporal_reproject(noisy, view, hist, view, (POS, NRM), blend=(0.2, True, 255.0))
        b = temporal_reproject(noisy, view, hist, view, (POS, NRM), blend=Blend())
        self.assert_identical(a[:3], b[:3])
        assert float(a.history_len.max()) == 3.5
