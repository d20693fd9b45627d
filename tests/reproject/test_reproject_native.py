"""Native kernels (stereorepro._core) against their torch twins, and backend selection.

Parity policy: colours within 1e-5; ``valid`` / ``reason`` identical except at exact threshold ties (a distance
that lands on the squared threshold and rounds differently), which are counted and must stay <= 0.01 % of the
pixels. The kernels follow the torch arithmetic operation by operation, so in practice there are none.

Temporal: ``_core.temporal_reproject`` warps [history colour, length] and blends in one fused pass.

float16 images (TestNativeFloat16): every output byte-identical to the torch reference on the same inputs (the
bits of float16 NaNs aside: see assert_bytes_equal).
"""

import math

import pytest
import torch

from base import BaseTester
from stereorepro import StereoReprojection, TemporalReprojection
from stereorepro._backend import ENV_VAR
from stereorepro.camera import compose_warp
from stereorepro.errors import ShapeError
from stereorepro.reproject import _native, functional
from stereorepro.reproject import (
    Reason,
    Thresholds,
    View,
    backward_reproject,
    native_unsupported,
    select_backend,
    stereo_reproject,
    temporal_reproject,
)
from stereorepro._testing import camera_pair, default_scene, raycast

if not _native.available():
    pytest.skip("stereorepro._core without the reprojection kernels", allow_module_level=True)

from stereorepro.reproject._native import _core  # noqa: E402
from test_reproject import ARGS, plane_pair, scene_pair  # noqa: E402  (tests/reproject/ is on sys.path)


def native_backward_reproject(*args, want_confidence: bool = True, **kwargs):
    """:func:`backward_reproject` on the native backend, flat arguments; ``want_confidence=False`` runs the kernel's
    variant without the confidence output (confidence None)."""
    if want_confidence:
        return backward_reproject(*args, backend="native", **kwargs)
    src, dst = View(*args[1:5]), View(*args[5:9])
    sampling = args[11] if len(args) > 11 else kwargs.get("sampling", "bilinear")
    return functional.warp_values(
        args[0], src, dst, Thresholds(*args[9:11]), sampling, False, "native", confidence=False
    )


def native_temporal_reproject(*args, **kwargs):
    """:func:`temporal_reproject` on the native backend, flat arguments."""
    return temporal_reproject(*args, backend="native", **kwargs)


MAX_TIE_FRACTION = 1e-4  # 0.01 %

#: The parity tests compare native with each torch implementation: the ``backend`` fixture restricted to the
#: torch general path (``torch``) and the torch fast path (``fast``), the reference side of every comparison.
AGAINST_TORCH = pytest.mark.parametrize("backend", ["torch", "fast"], indirect=True)


def assert_parity(ref, got, what=""):
    """ref / got: (values, valid, reason[, confidence]). Returns the number of valid/reason mismatches (ties)."""
    values_r, valid_r, reason_r = ref[:3]
    values_g, valid_g, reason_g = got[:3]
    assert values_g.shape == values_r.shape and values_g.dtype == values_r.dtype, what
    assert valid_g.dtype == torch.bool and reason_g.dtype == torch.uint8, what
    mismatch = (valid_r != valid_g) | (reason_r != reason_g)
    n_pix = valid_r.numel()
    n_bad = int(mismatch.sum())
    assert n_bad <= MAX_TIE_FRACTION * n_pix, f"{what}: {n_bad} valid/reason mismatches of {n_pix} pixels"
    same = (~mismatch).expand_as(values_r)
    assert torch.isfinite(values_g).all(), what
    err = (values_r - values_g).abs()[same]
    assert err.numel() == 0 or float(err.max()) <= 1e-5, f"{what}: colour error {float(err.max())}"
    if len(ref) > 3 and len(got) > 3:
        cerr = (ref[3] - got[3]).abs()[~mismatch]
        assert cerr.numel() == 0 or float(cerr.max()) <= 1e-6, what
    return n_bad


def both_stereo(inp, pos=0.01, nrm=0.1, sampling="bilinear"):
    """(torch, native) outputs: torch on the path the ``backend`` fixture chose (general or fast)."""
    args = [inp[a] for a in ARGS]
    ref = backward_reproject(*args, pos, nrm, sampling, backend="torch")
    got = native_backward_reproject(*args, pos, nrm, sampling)
    return ref, got


# --- the hard cases of tests/test_reproject.py, as input builders ------------------------------------------------
def _no_surface_dst():
    inp = plane_pair()
    for i, z in enumerate([float("inf"), float("nan"), 0.0, -1.0]):
        inp["dst_depth"][0, 0, i, 3] = z
    return inp, 0.01, 0.1


def _no_surface_src():
    inp = plane_pair(shift_px=1)
    inp["src_depth"][..., 4] = float("inf")
    inp["src_depth"][..., 2] = float("nan")
    return inp, 0.01, 0.1


def _behind_turned():
    inp = plane_pair()
    inp["src_cam_from_world"] = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))[None]
    return inp, 100.0, 10.0


def _behind_moved():
    inp = plane_pair()
    inp["src_cam_from_world"] = inp["src_cam_from_world"].clone()
    inp["src_cam_from_world"][:, 2, 3] = -3.0
    return inp, 100.0, 10.0


def _degenerate(z):
    def make():
        inp = plane_pair()
        inp["dst_depth"][0, 0, 2, 3] = z
        inp["src_depth"][0, 0, 2, 2] = z
        return inp, 0.01, 0.1

    return make


def _out_of_frame():
    inp = plane_pair()
    inp["src_cam_from_world"] = inp["src_cam_from_world"].clone()
    inp["src_cam_from_world"][:, 0, 3] = 100.0
    return inp, 1e3, 10.0


def _nonfinite_rejected():
    inp = plane_pair(shift_px=1)
    inp["src_color"][..., 7] = float("nan")
    inp["src_color"][0, 0, :, 2] = float("inf")
    inp["src_depth"][..., 2] = 5.0
    return inp, 0.01, 0.1


def _nonfinite_accepted(shift):
    def make():
        inp = plane_pair(shift_px=shift)
        inp["src_color"][0, 1, 2, 4] = float("nan") if shift == 1 else float("inf")
        inp["src_normal"][0, 0, 3, 3] = float("nan")
        inp["dst_normal"][0, 2, 4, 4] = float("inf")
        return inp, 0.1, 0.1

    return make


def _all_rejected():
    inp = plane_pair(H=4, W=5, shift_px=0.5)
    inp["src_depth"] = inp["src_depth"] * 2
    return inp, 0.01, 0.1


def _grazing():
    H, W = 24, 32
    from stereorepro.camera import PinholeCamera, look_at

    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]], dtype=torch.float64)
    head = look_at(
        torch.tensor([[0.0, 0.02, 0.0]], dtype=torch.float64),
        torch.tensor([[0.0, 0.0, -10.0]], dtype=torch.float64),
        torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64),
    )
    moved = head.clone()
    moved[:, 0, 3] -= 0.01
    scene = default_scene()
    gd, gs = raycast(PinholeCamera(K, head, H, W), scene), raycast(PinholeCamera(K, moved, H, W), scene)
    inp = dict(
        src_color=gs.color.float(),
        src_depth=gs.depth.float(),
        src_normal=gs.normal.float(),
        src_K=K,
        src_cam_from_world=moved,
        dst_depth=gd.depth.float(),
        dst_normal=gd.normal.float(),
        dst_K=K,
        dst_cam_from_world=head,
    )
    return inp, 0.05, 0.1


def _far_from_origin(dz):
    def make():
        o = torch.tensor([12345.678, -9876.54321, 11111.1111], dtype=torch.float64)
        inp = plane_pair(H=6, W=9, shift_px=1.0)
        for k in ("src_cam_from_world", "dst_cam_from_world"):
            T = inp[k].double().clone()
            T[:, :3, 3] -= o
            inp[k] = T
        inp["src_depth"] = inp["src_depth"] + dz
        return inp, 1e-3, 0.01

    return make


def _per_item_batch():
    a, *_ = scene_pair(forward=0.0)
    b, *_ = scene_pair(forward=0.3, yaw=3.0)
    return {k: torch.cat([a[k], b[k]]) for k in ARGS}, 0.05, 0.2


def _identity():
    inp, gd, *_ = scene_pair(baseline=0.065)
    dst, _ = camera_pair(36, 48)
    inp.update(
        src_color=gd.color.float(),
        src_depth=gd.depth.float(),
        src_normal=gd.normal.float(),
        src_K=dst.K.float(),
        src_cam_from_world=dst.cam_from_world.float(),
    )
    return inp, 1e-6, 1e-6


def _single(hw):
    def make():
        H, W = hw
        return plane_pair(H=H, W=W, shift_px=0.0 if W == 1 else 1.0), 0.01, 0.1

    return make


HARD_CASES = {
    "integer_shift_1": lambda: (plane_pair(H=5, W=9, shift_px=1), 0.01, 0.1),
    "integer_shift_3": lambda: (plane_pair(H=5, W=9, shift_px=3), 0.01, 0.1),
    "fractional_shift": lambda: (plane_pair(H=5, W=9, shift_px=1.25), 0.1, 0.1),
    "fractional_shift_b2": lambda: (plane_pair(H=5, W=9, shift_px=0.37, B=2), 0.01, 0.1),
    "no_surface_dst": _no_surface_dst,
    "no_surface_src": _no_surface_src,
    "behind_turned": _behind_turned,
    "behind_moved": _behind_moved,
    **{f"degenerate_{z}": _degenerate(z) for z in [0.0, 1e-12, -1e-12, math.inf, -math.inf, math.nan, 1e30]},
    "out_of_frame": _out_of_frame,
    "nonfinite_rejected": _nonfinite_rejected,
    "nonfinite_accepted_nan": _nonfinite_accepted(1),
    "nonfinite_accepted_inf": _nonfinite_accepted(0.5),
    "all_rejected": _all_rejected,
    "grazing": _grazing,
    "far_near": _far_from_origin(5e-4),
    "far_far": _far_from_origin(2e-3),
    "per_item_batch": _per_item_batch,
    "identity": _identity,
    "analytic_scene": lambda: (scene_pair(H=72, W=96)[0], 0.15, 0.2),
    "moving_scene": lambda: (scene_pair(H=36, W=48, forward=0.2, yaw=2.0)[0], 0.05, 0.3),
    **{f"single_{h}x{w}": _single((h, w)) for h, w in [(1, 9), (7, 1), (1, 1)]},
}


def random_scene(H, W, seed, B=1):
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(4, generator=g).tolist()
    dst, src = camera_pair(H, W, B, baseline=0.02 + 0.2 * r[0], forward=0.6 * r[1] - 0.3, yaw_deg=8 * r[2] - 4)
    scene = default_scene()
    gd, gs = raycast(dst, scene), raycast(src, scene)
    inp = dict(
        src_color=gs.color.float() * (0.5 + torch.rand(gs.color.shape, generator=g)),
        src_depth=gs.depth.float(),
        src_normal=gs.normal.float(),
        src_K=src.K,
        src_cam_from_world=src.cam_from_world,
        dst_depth=gd.depth.float(),
        dst_normal=gd.normal.float(),
        dst_K=dst.K,
        dst_cam_from_world=dst.cam_from_world,
    )
    pos, nrm = 0.01 + 0.2 * r[3], 0.05 + 0.5 * float(torch.rand((), generator=g))
    return inp, pos, nrm


RESOLUTIONS = [(1, 17), (13, 1), (1, 1), (36, 48), (71, 129), (97, 203)]


def count_native_calls(monkeypatch) -> list:
    """A list that records "s" for each native warp call and "t" for each fused native temporal call."""
    calls = []
    real_s, real_t = functional._native_backward, functional._native_temporal
    monkeypatch.setattr(functional, "_native_backward", lambda *a, **k: calls.append("s") or real_s(*a, **k))
    monkeypatch.setattr(functional, "_native_temporal", lambda *a, **k: calls.append("t") or real_t(*a, **k))
    return calls


class TestNativeStereo(BaseTester):
    def test_smoke(self):
        values, valid, reason, conf = native_backward_reproject(*[plane_pair()[a] for a in ARGS], 0.01, 0.1)
        assert values.shape == (1, 3, 6, 8) and valid.dtype == torch.bool and reason.dtype == torch.uint8
        assert conf.shape == (1, 1, 6, 8) and conf.dtype == torch.float32

    @AGAINST_TORCH
    def test_cardinality(self, backend):
        src = plane_pair(H=6, W=8, B=2)
        dst = plane_pair(H=5, W=7, B=2)
        inp = {
            **{k: v for k, v in src.items() if k.startswith("src")},
            **{k: v for k, v in dst.items() if k.startswith("dst")},
        }
        for C in (1, 3, 5):
            inp["src_color"] = torch.rand(2, C, 6, 8)
            ref, got = both_stereo(inp)
            assert got[0].shape == (2, C, 5, 7)
            assert_parity(ref, got, f"C={C}")

    def test_exceptions(self):
        inp = plane_pair()
        args = [inp[a] for a in ARGS]
        with pytest.raises(RuntimeError, match="float32"):  # backend="native" says why it is not possible
            native_backward_reproject(*[a.double() if a.dim() == 4 else a for a in args], 0.01, 0.1)
        with pytest.raises(RuntimeError, match="soft"):
            native_backward_reproject(*args, 0.01, 0.1, soft=True)
        with pytest.raises(ValueError, match="sampling"):
            native_backward_reproject(*args, 0.01, 0.1, sampling="bicubic")
        bad = dict(inp, src_depth=torch.zeros(1, 1, 5, 8))
        with pytest.raises(ShapeError, match="src_depth"):
            native_backward_reproject(*[bad[a] for a in ARGS], 0.01, 0.1)
        # direct kernel calls: shapes are checked, outputs must be exactly right (noconvert: no hidden copies)
        B, C, H, W = 1, 3, 6, 8
        M, t, P, kt, Ki = [
            x.reshape(1, -1).contiguous()
            for x in compose_warp(
                *[inp[a] for a in ("src_K", "src_cam_from_world", "dst_K", "dst_cam_from_world")], torch.float32
            )
        ]
        ins = [
            inp["src_color"],
            inp["src_depth"],
            inp["src_normal"],
            P,
            kt,
            M,
            t,
            Ki,
            inp["dst_depth"],
            inp["dst_normal"],
            1e-4,
            1e-2,
            True,
        ]
        outs = [
            torch.empty(B, C, H, W),
            torch.empty(B, 1, H, W, dtype=torch.bool),
            torch.empty(B, 1, H, W, dtype=torch.uint8),
            torch.empty(B, 1, H, W),
        ]
        _core.reproject(*ins, *outs)
        with pytest.raises(ValueError, match="out_values"):
            _core.reproject(*ins, torch.empty(B, C, H, W + 1), *outs[1:])
        with pytest.raises(ValueError, match="src_normal"):
            _core.reproject(*ins[:2], torch.empty(B, 3, H, W + 1), *ins[3:], *outs)
        with pytest.raises(TypeError):  # non-contiguous output: rejected, not written to a temporary
            _core.reproject(*ins, torch.empty(B, C, W, H).transpose(-1, -2), *outs[1:])
        with pytest.raises(TypeError):  # wrong output dtype
            _core.reproject(*ins, outs[0], outs[1].to(torch.uint8), *outs[2:])
        with pytest.raises(TypeError):  # non-contiguous input: the Python layer must make it contiguous
            _core.reproject(inp["src_color"].transpose(-1, -2).contiguous().transpose(-1, -2), *ins[1:], *outs)

    def test_noncontiguous_inputs_handled(self):
        inp, *_ = scene_pair()
        odd = dict(inp)
        for k in ("src_color", "src_normal", "dst_normal"):
            odd[k] = inp[k].contiguous(memory_format=torch.channels_last)
        odd["src_depth"] = inp["src_depth"].transpose(-1, -2).contiguous().transpose(-1, -2)
        odd["dst_depth"] = torch.cat([inp["dst_depth"], inp["dst_depth"]], 1)[:, :1]
        assert not odd["src_depth"].is_contiguous() and not odd["src_color"].is_contiguous()
        got = native_backward_reproject(*[odd[a] for a in ARGS], 0.05, 0.2)
        ref = native_backward_reproject(*[inp[a] for a in ARGS], 0.05, 0.2)
        for a, b in zip(got, ref):
            assert torch.equal(a, b)

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @pytest.mark.parametrize("case", sorted(HARD_CASES))
    @AGAINST_TORCH
    def test_parity_hard_cases(self, case, sampling, backend):
        inp, pos, nrm = HARD_CASES[case]()
        ref, got = both_stereo(inp, pos, nrm, sampling)
        assert_parity(ref, got, case)

    def test_exact_where_torch_is_exact(self):
        for shift in (1, 3):
            inp = plane_pair(H=5, W=9, shift_px=shift)
            out, valid, reason, _ = native_backward_reproject(*[inp[a] for a in ARGS], 0.01, 0.1)
            assert torch.equal(out[..., shift:], inp["src_color"][..., :-shift])
            assert (reason[..., :shift] == Reason.OUT_OF_FRAME).all() and valid[..., shift:].all()

    @pytest.mark.parametrize("hw", RESOLUTIONS)
    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @AGAINST_TORCH
    def test_parity_random_scenes(self, hw, sampling, backend):
        for seed in range(3):
            inp, pos, nrm = random_scene(*hw, seed=seed + 17 * hw[0] + hw[1])
            ref, got = both_stereo(inp, pos, nrm, sampling)
            assert_parity(ref, got, f"{hw} seed {seed}")

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @AGAINST_TORCH
    def test_parity_rectified_rig(self, sampling, backend):
        # A parallel rig's epipolar lines are rows: every tap row has fy = 0, so the kernel's vector path skips the
        # zero-weight y1 taps. Widths that are multiples of 8 (vector path only) and not (scalar tail).
        for H, W, baseline in ((40, 64, 0.065), (41, 75, 0.13), (16, 128, 0.3)):
            inp, *_ = scene_pair(H=H, W=W, baseline=baseline)
            ref, got = both_stereo(inp, 0.05, 0.3, sampling)
            assert_parity(ref, got, f"rectified {H}x{W}")
            assert (~got[1]).any() and got[1].any()  # both kept and discarded pixels

    def test_confidence_optional(self):
        inp, *_ = scene_pair(forward=0.1)
        args = [inp[a] for a in ARGS]
        full = native_backward_reproject(*args, 0.05, 0.3)
        lean = native_backward_reproject(*args, 0.05, 0.3, want_confidence=False)
        assert lean[3] is None
        assert all(torch.equal(a, b) for a, b in zip(full[:3], lean[:3]))

    @AGAINST_TORCH
    def test_parity_different_source_size(self, backend):
        src, *_ = scene_pair(H=40, W=56, forward=0.1)
        dst, *_ = scene_pair(H=33, W=47)
        inp = {
            **{k: v for k, v in src.items() if k.startswith("src")},
            **{k: v for k, v in dst.items() if k.startswith("dst")},
        }
        ref, got = both_stereo(inp, 0.1, 0.3)
        assert_parity(ref, got, "Hs != H")

    @AGAINST_TORCH
    def test_module(self, backend):
        inp, *_ = scene_pair(forward=0.1)
        args = [inp[a] for a in ARGS]
        with torch.no_grad():
            got = StereoReprojection(0.05, 0.3, backend="native")(*args)
            ref = StereoReprojection(0.05, 0.3, backend="torch")(*args)
        assert_parity(ref, got, "module")


class TestNativeTemporal(BaseTester):
    NAMES = TemporalReprojection.input_names

    def _inputs(self, H=36, W=48, seed=0, n=3.0, forward=0.1):
        inp, *_ = scene_pair(H=H, W=W, forward=forward)
        g = torch.Generator().manual_seed(seed)
        return dict(
            current_color=torch.rand(1, 3, H, W, generator=g),
            depth=inp["dst_depth"],
            normal=inp["dst_normal"],
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=inp["src_color"],
            history_len=torch.randint(0, 20, (1, 1, H, W), generator=g).float()
            if n is None
            else torch.full((1, 1, H, W), n),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"],
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )

    def _both(self, inp, pos=0.05, nrm=0.3, **kw):
        args = [inp[n] for n in self.NAMES]
        ref = temporal_reproject(*args, pos, nrm, backend="torch", **kw)
        got = native_temporal_reproject(*args, pos, nrm, **kw)
        return ref, got

    def _parity(self, ref, got, what=""):
        color_r, n_r, valid_r = ref
        color_g, n_g, valid_g = got
        u8 = torch.uint8
        assert_parity((color_r, valid_r, valid_r.to(u8)), (color_g, valid_g, valid_g.to(u8)), what)
        same = valid_r == valid_g
        assert float((n_r - n_g).abs()[same].max()) <= 1e-5, what

    def test_smoke(self):
        color, n, valid = native_temporal_reproject(*[self._inputs()[k] for k in self.NAMES], 0.05, 0.3)
        assert color.shape == (1, 3, 36, 48) and n.shape == (1, 1, 36, 48) and valid.dtype == torch.bool

    def test_exceptions(self):
        inp = self._inputs()
        args = [inp[k] for k in self.NAMES]
        with pytest.raises(RuntimeError, match="float64"):  # backend="native" says why it is not possible
            native_temporal_reproject(
                *[a.double() if k == "history_len" else a for k, a in zip(self.NAMES, args)], 0.05, 0.3
            )
        with pytest.raises(RuntimeError, match="soft"):
            native_temporal_reproject(*args, 0.05, 0.3, soft=True)
        with pytest.raises(ShapeError, match="history_len"):  # checked by temporal_reproject before dispatch
            temporal_reproject(
                *[torch.zeros(1, 2, 36, 48) if k == "history_len" else a for k, a in zip(self.NAMES, args)],
                0.05,
                0.3,
                backend="native",
            )
        odd = {
            k: (v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 and v.shape[1] == 3 else v)
            for k, v in inp.items()
        }
        for a, b in zip(
            native_temporal_reproject(*[odd[k] for k in self.NAMES], 0.05, 0.3),
            native_temporal_reproject(*args, 0.05, 0.3),
        ):
            assert torch.equal(a, b)

    @pytest.mark.parametrize(
        "kw",
        [
            dict(),
            dict(alpha=0.5, warmup=False),
            dict(alpha=1.0),
            dict(alpha=1e-9),
            dict(max_history=4.0),
            dict(sampling="nearest"),
            dict(sampling="catmull_rom"),
            dict(history_rounding="bmfr"),
            dict(history_rounding="bmfr", alpha=1.0),
            dict(history_rounding="bmfr", max_history=4.0),
            dict(history_rounding="bmfr", alpha=0.5, warmup=False),
            dict(footprint_weighting=True),
            dict(footprint_weighting=True, sampling="nearest"),
            dict(footprint_weighting=True, sampling="catmull_rom"),
            dict(footprint_weighting=True, history_rounding="bmfr", max_history=4.0),
            dict(footprint_weighting=True, alpha=0.5, warmup=False),
        ],
        ids=str,
    )
    @AGAINST_TORCH
    def test_parity(self, kw, backend):
        for seed, n in [(0, 3.0), (1, 0.0), (2, None), (3, 1e9)]:
            inp = self._inputs(seed=seed, n=n)
            self._parity(*self._both(inp, **kw), f"{kw} n={n}")

    @AGAINST_TORCH
    def test_parity_hard_cases(self, backend):
        inp = self._inputs(n=4.0)
        inp["history_color"] = inp["history_color"].clone()
        inp["history_color"][..., 2, 2] = float("nan")
        inp["history_color"][..., 5, 5] = float("inf")
        inp["history_len"] = inp["history_len"].clone()
        inp["history_len"][..., 7, 7] = float("nan")
        inp["history_len"][..., 8, 8] = -3.0
        inp["prev_depth"] = inp["prev_depth"].clone()
        inp["prev_depth"][..., :3] = 40.0
        inp["depth"] = inp["depth"].clone()
        inp["depth"][..., 4, :] = float("nan")
        self._parity(*self._both(inp), "hard")

    @pytest.mark.parametrize("hw", RESOLUTIONS)
    @AGAINST_TORCH
    def test_parity_random_scenes(self, hw, backend):
        for seed in range(2):
            s, pos, nrm = random_scene(*hw, seed=seed + 31 * hw[0] + hw[1])
            g = torch.Generator().manual_seed(seed)
            inp = dict(
                current_color=torch.rand(s["dst_depth"].shape[:1] + (3,) + hw, generator=g),
                depth=s["dst_depth"],
                normal=s["dst_normal"],
                K=s["dst_K"],
                cam_from_world=s["dst_cam_from_world"],
                history_color=s["src_color"],
                history_len=torch.randint(0, 30, s["src_depth"].shape, generator=g).float(),
                prev_depth=s["src_depth"],
                prev_normal=s["src_normal"],
                prev_K=s["src_K"],
                prev_cam_from_world=s["src_cam_from_world"],
            )
            self._parity(*self._both(inp, pos, nrm), f"{hw} seed {seed}")

    @AGAINST_TORCH
    def test_module(self, backend):
        inp = self._inputs(n=None)
        args = [inp[k] for k in self.NAMES]
        with torch.no_grad():
            got = TemporalReprojection(0.05, 0.3, backend="native")(*args)
            ref = TemporalReprojection(0.05, 0.3, backend="torch")(*args)
        self._parity(ref, got, "module")


class TestBackendSelection(BaseTester):
    def _stereo_inputs(self):
        inp, *_ = scene_pair(H=12, W=16)
        return inp

    def test_select(self, monkeypatch):
        monkeypatch.delenv(ENV_VAR, raising=False)
        inp = self._stereo_inputs()
        imgs = [inp[a] for a in ARGS if inp[a].dim() == 4]
        cams = [inp[a] for a in ARGS if inp[a].dim() == 3]
        assert select_backend("auto", imgs, cams) == "native"
        assert select_backend("torch", imgs, cams) == "torch"
        assert select_backend("native", imgs, cams) == "native"
        assert select_backend("auto", imgs, cams, soft=True) == "torch"
        assert select_backend("auto", [x.double() for x in imgs], cams) == "torch"
        assert select_backend("auto", [x.half() for x in imgs], cams) == "native"
        assert select_backend("auto", [x.bfloat16() for x in imgs], cams) == "torch"
        grad = [imgs[0].clone().requires_grad_(True)] + imgs[1:]
        assert select_backend("auto", grad, cams) == "torch"
        with torch.no_grad():
            assert select_backend("auto", grad, cams) == "native"
        thr = torch.tensor(0.05, requires_grad=True)
        assert select_backend("auto", imgs, cams + [thr]) == "torch"
        with pytest.raises(RuntimeError, match="float32"):
            select_backend("native", [x.double() for x in imgs], cams)
        with pytest.raises(RuntimeError, match="soft"):
            select_backend("native", imgs, cams, soft=True)
        with pytest.raises(RuntimeError, match="requires grad"):
            select_backend("native", grad, cams)
        with pytest.raises(RuntimeError, match="CPU"):
            select_backend("native", imgs + [torch.zeros(1, device="meta")], cams)
        with pytest.raises(ValueError, match="backend"):
            select_backend("cuda", imgs, cams)
        with pytest.raises(ValueError, match="backend"):
            StereoReprojection(0.05, 0.3, backend="fast")

    def test_env_var(self, monkeypatch):
        inp = self._stereo_inputs()
        imgs = [inp[a] for a in ARGS if inp[a].dim() == 4]
        monkeypatch.setenv(ENV_VAR, "torch")
        assert select_backend("native", imgs) == "torch"
        monkeypatch.setenv(ENV_VAR, "native")
        assert select_backend("torch", imgs) == "native"
        with pytest.raises(RuntimeError, match=ENV_VAR):
            select_backend("auto", [x.double() for x in imgs])
        monkeypatch.setenv(ENV_VAR, "AUTO")
        assert select_backend("torch", imgs) == "native"
        monkeypatch.setenv(ENV_VAR, "gpu")
        with pytest.raises(ValueError, match=ENV_VAR):
            select_backend("auto", imgs)

    def test_dispatch(self, monkeypatch):
        """Which implementation the functions and modules run, observed by counting native calls."""
        monkeypatch.delenv(ENV_VAR, raising=False)
        calls = count_native_calls(monkeypatch)
        inp = self._stereo_inputs()
        args = [inp[a] for a in ARGS]
        StereoReprojection(0.05, 0.3)(*args)
        assert calls == ["s"]
        StereoReprojection(0.05, 0.3, backend="torch")(*args)
        StereoReprojection(0.05, 0.3, soft=True)(*args)
        stereo_reproject(*[a.double() for a in args], 0.05, 0.3)
        stereo_reproject(args[0].clone().requires_grad_(True), *args[1:], 0.05, 0.3)
        assert calls == ["s"]
        monkeypatch.setenv(ENV_VAR, "torch")
        StereoReprojection(0.05, 0.3, backend="native")(*args)
        assert calls == ["s"]
        monkeypatch.delenv(ENV_VAR)
        t = TestNativeTemporal()._inputs(H=12, W=16)
        TemporalReprojection(0.05, 0.3)(*[t[k] for k in TemporalReprojection.input_names])
        assert calls == ["s", "t"]
        TemporalReprojection(0.05, 0.3, soft=True)(*[t[k] for k in TemporalReprojection.input_names])
        assert calls == ["s", "t"]

    def test_without_core(self, monkeypatch):
        monkeypatch.delenv(ENV_VAR, raising=False)
        monkeypatch.setattr(_native, "_core", None)
        assert not _native.available()
        inp = self._stereo_inputs()
        args = [inp[a] for a in ARGS]
        out = StereoReprojection(0.05, 0.3)(*args)  # auto: torch
        ref = StereoReprojection(0.05, 0.3, backend="torch")(*args)
        assert all(torch.equal(a, b) for a, b in zip(out, ref))
        with pytest.raises(RuntimeError, match="not built"):
            StereoReprojection(0.05, 0.3, backend="native")(*args)

    @pytest.mark.onnx
    def test_onnx_export_uses_torch(self, monkeypatch, tmp_path):
        """Even with native forced, export traces the torch path: a graph of standard ONNX ops only, whose
        onnxruntime outputs equal the torch reference's."""
        import onnx
        import onnxruntime as ort

        from stereorepro import export_onnx
        from stereorepro._testing import example_inputs

        monkeypatch.setenv(ENV_VAR, "native")
        module = StereoReprojection(0.3, 0.3)
        path = export_onnx(module, tmp_path / "s.onnx")
        graph = onnx.load(str(path)).graph
        assert {n.domain for n in graph.node} <= {"", "ai.onnx"}
        xs = example_inputs(module, height=10, width=14)
        outs = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
            None, {n: x.numpy() for n, x in zip(module.input_names, xs)}
        )
        monkeypatch.delenv(ENV_VAR)
        with torch.no_grad():
            ref = StereoReprojection(0.3, 0.3, backend="torch")(*xs)
        for o, r in zip(outs, ref):
            assert o.dtype == r.numpy().dtype
            torch.testing.assert_close(torch.from_numpy(o).double(), r.double(), atol=1e-5, rtol=0)


# --- float16 images --------------------------------------------------------------------------------------------
# The kernels read float16 planes as they are (F16C in the vector path, a bit-exact scalar conversion in the
# scalar one: widths < 8 and the last W % 8 pixels of a row), compute in float32 and round the colour output to
# nearest even, as torch computes on the float32 upcast and casts back: every output is byte-identical to
# backend="torch" on the same inputs (NaN bits aside: assert_bytes_equal). Each dtype layout names the images that
# are float16 (the rest float32).
STEREO_HALF = {
    "colour+normals": ("src_color", "src_normal", "dst_normal"),  # depth float32: the recommended layout
    "all": ("src_color", "src_normal", "dst_normal", "src_depth", "dst_depth"),
    "mixed": ("src_color", "src_depth", "dst_normal"),
    "fp32 colour": ("src_normal", "dst_depth"),
}
TEMPORAL_HALF = {
    "colour+normals": ("current_color", "history_color", "history_len", "normal", "prev_normal"),
    "all": ("current_color", "history_color", "history_len", "normal", "prev_normal", "depth", "prev_depth"),
    "mixed": ("history_color", "normal", "prev_depth"),  # float32 current colour: float32 output
    "fp16 current": ("current_color", "normal", "prev_normal"),  # float32 history, float16 output
}


def to_half(inp: dict, names) -> dict:
    return {k: (v.half() if k in names else v) for k, v in inp.items()}


def assert_bytes_equal(ref, got, what=""):
    """Same dtype, shape and bytes for every output (None where None), except the bits of float16 NaNs: NaN where
    NaN. (torch's float16 -> float32 conversion gives a NaN the F16C pattern in its vectorised loop and 0x7FFFFFFF
    in the loop's scalar tail, so the NaN bits of its output depend on the element's position in the tensor; the
    kernels always give the F16C pattern: sign and payload kept, quiet bit set.)"""
    assert len(ref) == len(got), what
    for i, (r, g) in enumerate(zip(ref, got)):
        if r is None or g is None:
            assert r is None and g is None, f"{what}: output {i}"
            continue
        assert g.dtype == r.dtype and g.shape == r.shape, (what, i, g.dtype, r.dtype, g.shape, r.shape)
        if r.dtype == torch.float16:
            nan = torch.isnan(r)
            assert torch.equal(nan, torch.isnan(g)), f"{what}: output {i} has NaN elsewhere than torch's"
            r, g = r.masked_fill(nan, 0.0), g.masked_fill(nan, 0.0)
        rb, gb = r.contiguous().view(torch.uint8), g.contiguous().view(torch.uint8)
        if not torch.equal(rb, gb):
            bad = int((r != g).sum()) if r.is_floating_point() else int((rb != gb).sum())
            raise AssertionError(f"{what}: output {i} ({r.dtype}) differs from torch's at {bad} elements")


def hdr(inp: dict, seed: int, key="src_color") -> dict:
    """Colours spread over float16's range: per-pixel scales 2^-20 .. 2^12 (subnormal to large results)."""
    g = torch.Generator().manual_seed(seed)
    x = inp[key]
    e = torch.randint(-20, 13, x.shape[:1] + (1,) + x.shape[2:], generator=g).to(x.dtype)
    return dict(inp, **{key: x * torch.exp2(e)})


class TestNativeFloat16(BaseTester):
    NAMES = TemporalReprojection.input_names

    def _stereo_both(self, inp, pos, nrm, sampling="bilinear", confidence=False):
        args = [inp[a] for a in ARGS]
        if confidence:
            ref = backward_reproject(*args, pos, nrm, sampling, backend="torch")
            got = backward_reproject(*args, pos, nrm, sampling, backend="native")
        else:
            ref = stereo_reproject(*args, pos, nrm, sampling, backend="torch")
            got = stereo_reproject(*args, pos, nrm, sampling, backend="native")
        return ref, got

    def _temporal_both(self, inp, pos=0.05, nrm=0.3, **kw):
        args = [inp[n] for n in self.NAMES]
        ref = temporal_reproject(*args, pos, nrm, backend="torch", **kw)
        got = temporal_reproject(*args, pos, nrm, backend="native", **kw)
        return ref, got

    def _temporal_inputs(self, H, W, seed, forward=0.1):
        inp, *_ = scene_pair(H=H, W=W, forward=forward, yaw=1.0)
        g = torch.Generator().manual_seed(seed)
        return dict(
            current_color=torch.rand(1, 3, H, W, generator=g) * 4,
            depth=inp["dst_depth"],
            normal=inp["dst_normal"],
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=hdr(inp, seed)["src_color"],
            history_len=torch.randint(-2, 40, (1, 1, H, W), generator=g).float(),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"],
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )

    @pytest.mark.parametrize("layout", sorted(STEREO_HALF))
    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @AGAINST_TORCH
    def test_parity_stereo(self, layout, sampling, backend):
        for hw in RESOLUTIONS:
            for seed in range(2):
                inp, pos, nrm = random_scene(*hw, seed=seed + 7 * hw[1])
                inp = to_half(hdr(inp, seed), STEREO_HALF[layout])
                ref, got = self._stereo_both(inp, pos, nrm, sampling)
                assert got[0].dtype == inp["src_color"].dtype
                assert_bytes_equal(ref, got, f"{layout} {hw} seed {seed}")

    @pytest.mark.parametrize("layout", sorted(STEREO_HALF))
    @AGAINST_TORCH
    def test_parity_backward_confidence(self, layout, backend):
        for C in (1, 3, 5):
            for hw in ((36, 48), (29, 67)):
                inp, pos, nrm = random_scene(*hw, seed=C + hw[1])
                g = torch.Generator().manual_seed(C)
                inp["src_color"] = torch.rand(1, C, *hw, generator=g) * 3
                inp = to_half(inp, STEREO_HALF[layout])
                ref, got = self._stereo_both(inp, pos, nrm, confidence=True)
                assert got[3].dtype == torch.float32 and got[0].dtype == inp["src_color"].dtype
                assert_bytes_equal(ref, got, f"{layout} C={C} {hw}")

    @pytest.mark.parametrize("layout", ["colour+normals", "all"])
    @pytest.mark.parametrize("case", sorted(HARD_CASES))
    @AGAINST_TORCH
    def test_parity_hard_cases(self, case, layout, backend):
        inp, pos, nrm = HARD_CASES[case]()
        inp = to_half(inp, STEREO_HALF[layout])
        for sampling in ("bilinear", "nearest", "catmull_rom"):
            assert_bytes_equal(*self._stereo_both(inp, pos, nrm, sampling, confidence=True), f"{case} {sampling}")

    @pytest.mark.parametrize("layout", sorted(TEMPORAL_HALF))
    @pytest.mark.parametrize(
        "kw",
        [
            dict(),
            dict(alpha=0.5, warmup=False),
            dict(alpha=1.0),
            dict(max_history=4.0),
            dict(sampling="nearest"),
            dict(sampling="catmull_rom"),
            dict(return_reason=True),
            dict(history_rounding="bmfr"),
            dict(history_rounding="bmfr", alpha=1.0),
            dict(footprint_weighting=True),
            dict(footprint_weighting=True, return_reason=True),
            dict(footprint_weighting=True, sampling="catmull_rom", history_rounding="bmfr"),
        ],
        ids=str,
    )
    @AGAINST_TORCH
    def test_parity_temporal(self, layout, kw, backend):
        for hw in ((36, 48), (23, 61), (5, 7)):
            inp = to_half(self._temporal_inputs(*hw, seed=hw[1]), TEMPORAL_HALF[layout])
            ref, got = self._temporal_both(inp, **kw)
            assert got[0].dtype == inp["current_color"].dtype and got[1].dtype == torch.float32
            assert_bytes_equal(ref, got, f"{layout} {kw} {hw}")

    @pytest.mark.parametrize("W", [7, 64, 69])
    @AGAINST_TORCH
    def test_every_half_exact(self, W, backend):
        """Every float16 bit pattern through an exact warp (integer shift: one tap of weight 1): finite values come
        out as they went in (widening and narrowing are exact), non-finite ones are discarded (NONFINITE)."""
        bits = torch.arange(-32768, 32768, dtype=torch.int32).to(torch.int16)
        H = -(-bits.numel() // (3 * (W - 1)))
        inp = plane_pair(H=H, W=W, shift_px=1)
        src = torch.zeros(3 * H * (W - 1), dtype=torch.int16)
        src[: bits.numel()] = bits
        colour = torch.zeros(1, 3, H, W, dtype=torch.float16)
        colour[..., :-1] = src.view(torch.float16).view(1, 3, H, W - 1)
        inp = to_half(dict(inp, src_color=colour), STEREO_HALF["colour+normals"])
        ref, got = self._stereo_both(inp, 0.01, 0.1, confidence=True)
        assert_bytes_equal(ref, got, f"W={W}")
        out, valid, reason = got[0][..., 1:], got[1][..., 1:], got[2][..., 1:]
        finite = torch.isfinite(colour[..., :-1]).all(1, keepdim=True)
        assert torch.equal(valid, finite) and bool((reason[~finite] == Reason.NONFINITE).all())
        assert torch.equal(out.float()[finite.expand_as(out)], colour[..., :-1].float()[finite.expand_as(out)])

    @pytest.mark.parametrize("W", [7, 64, 69])
    @AGAINST_TORCH
    def test_rounding_to_half(self, W, backend):
        """The colour output's float32 -> float16 rounding, probed through temporal with alpha = 0 (no warmup): the
        output is then the float32 history itself, rounded to the float16 current colour's dtype. Values around
        every rounding boundary: ties to even, subnormals, underflow to 0, 65504 and the overflow at 65520."""
        g = torch.Generator().manual_seed(W)
        halves = torch.arange(0, 0x7C00, dtype=torch.int32).to(torch.int16).view(torch.float16).float()  # finite
        nxt = torch.cat([halves[1:], torch.tensor([65536.0])])
        mid = (halves + nxt) / 2  # exact ties (float32 holds them), and their neighbours
        probes = torch.cat(
            [
                mid,
                torch.nextafter(mid, torch.zeros(())),
                torch.nextafter(mid, nxt),
                torch.rand(20000, generator=g) * 1e-4,
                torch.tensor([65504.0, 65519.996, 65520.0, 1e9, 3.4e38, 2.0**-25, 2.0**-26]),
            ]
        )
        probes = torch.cat([probes, -probes])
        H = -(-probes.numel() // (3 * (W - 1)))
        inp = plane_pair(H=H, W=W, shift_px=1)
        hist = torch.zeros(1, 3, H, W)
        flat = torch.zeros(3 * H * (W - 1))
        flat[: probes.numel()] = probes
        hist[..., :-1] = flat.view(1, 3, H, W - 1)
        t = dict(
            current_color=torch.zeros(1, 3, H, W, dtype=torch.float16),
            depth=inp["dst_depth"],
            normal=inp["dst_normal"].half(),
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=hist,
            history_len=torch.full((1, 1, H, W), 5.0),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"].half(),
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )
        ref, got = self._temporal_both(t, 0.01, 0.1, alpha=0.0, warmup=False)
        assert_bytes_equal(ref, got, f"W={W}")
        assert bool(got[2][..., 1:].all())
        assert torch.equal(got[0][..., 1:], hist[..., :-1].half())  # torch's rounding of the float32 history

    @pytest.mark.parametrize("W", [6, 40, 45])
    @AGAINST_TORCH
    def test_nonfinite_and_huge_colour(self, W, backend):
        """NaN / ±inf / 65504 / -65504 / subnormal float16 colours, in the source (stereo) and in the history and the
        current frame (temporal; a float32 history overflows the float16 output)."""
        H = 9
        inp = plane_pair(H=H, W=W, shift_px=1.25)
        c = inp["src_color"].clone() * 100
        specials = [math.nan, math.inf, -math.inf, 65504.0, -65504.0, 6e-8, -6e-8, 1e-5, 65000.0]
        for i, v in enumerate(specials):
            c[0, i % 3, i % H, (3 * i) % W] = v
            c[0, :, (i + 4) % H, (5 * i + 1) % W] = v
        inp = to_half(dict(inp, src_color=c), STEREO_HALF["colour+normals"])
        assert torch.isinf(inp["src_color"]).any() and (inp["src_color"].abs() == 65504).any()
        for sampling in ("bilinear", "nearest", "catmull_rom"):
            ref, got = self._stereo_both(inp, 0.1, 0.1, sampling, confidence=True)
            assert_bytes_equal(ref, got, f"stereo {sampling}")
            assert bool(torch.isfinite(got[0]).all())
        t = dict(
            current_color=(torch.rand(1, 3, H, W) * 6e4).half(),
            depth=inp["dst_depth"],
            normal=inp["dst_normal"],
            K=inp["dst_K"],
            cam_from_world=inp["dst_cam_from_world"],
            history_color=c * 700,
            history_len=torch.full((1, 1, H, W), 2.0),
            prev_depth=inp["src_depth"],
            prev_normal=inp["src_normal"],
            prev_K=inp["src_K"],
            prev_cam_from_world=inp["src_cam_from_world"],
        )
        t["current_color"][0, 1, 2, :] = torch.tensor([math.inf, -math.inf, 65504.0] * W)[:W]
        t["current_color"][0, 2, 3, :] = math.nan  # passes through where the history is discarded
        t["current_color"][0, 2, H - 1, W - 3 :] = math.nan  # in torch's scalar tail (see assert_bytes_equal)
        for kw in (dict(), dict(alpha=0.5, warmup=False), dict(return_reason=True)):
            ref, got = self._temporal_both(t, 0.1, 0.1, **kw)
            assert_bytes_equal(ref, got, f"temporal {kw}")
            assert bool(torch.isinf(got[0]).any())  # a float32 history of up to 4.6e7 overflows float16
        t16 = dict(t, history_color=c.half(), history_len=t["history_len"].half())
        assert_bytes_equal(*self._temporal_both(t16, 0.1, 0.1), "temporal, float16 history")

    @pytest.mark.parametrize("W", [7, 48])
    @AGAINST_TORCH
    def test_zero_and_nan_normals(self, W, backend):
        """Zero, NaN and ±inf float16 normals (source and destination) read as zero vectors: NORMAL."""
        inp = plane_pair(H=6, W=W, shift_px=1)
        sn, dn = inp["src_normal"].clone(), inp["dst_normal"].clone()
        sn[..., 1, :] = 0.0
        sn[0, 2, 2, :] = math.nan  # the z component: the normal (0, 0, -1) becomes (0, 0, 0)
        dn[0, 2, 3, :] = -math.inf
        dn[..., 4, :] = 0.0
        inp = to_half(dict(inp, src_normal=sn, dst_normal=dn), STEREO_HALF["all"])
        ref, got = self._stereo_both(inp, 0.01, 0.1, confidence=True)
        assert_bytes_equal(ref, got, "normals")
        reason = got[2][0, 0, :, 1:]
        assert bool((reason[[1, 2, 3, 4]] == Reason.NORMAL).all()) and bool((reason[[0, 5]] == Reason.KEPT).all())

    def test_auto_picks_native(self, monkeypatch):
        monkeypatch.delenv(ENV_VAR, raising=False)
        calls = count_native_calls(monkeypatch)
        inp, *_ = scene_pair(H=12, W=16)
        for layout, names in STEREO_HALF.items():
            with torch.no_grad():
                StereoReprojection(0.05, 0.3)(*[to_half(inp, names)[a] for a in ARGS])
            assert calls[-1:] == ["s"], layout
        t = self._temporal_inputs(12, 16, 0)
        for layout, names in TEMPORAL_HALF.items():
            calls.clear()
            with torch.no_grad():
                TemporalReprojection(0.05, 0.3)(*[to_half(t, names)[k] for k in self.NAMES])
            assert calls == ["t"], layout
        calls.clear()
        bf = {k: (v.bfloat16() if k == "src_color" else v) for k, v in inp.items()}
        stereo_reproject(*[bf[a] for a in ARGS], 0.05, 0.3)
        assert calls == []  # bfloat16: torch
        imgs = [inp[a].half() for a in ARGS if inp[a].dim() == 4]
        assert select_backend("auto", imgs) == "native"
        assert native_unsupported(imgs) is None
        assert "bfloat16" in native_unsupported([x.bfloat16() for x in imgs])
        with pytest.raises(RuntimeError, match="bfloat16"):
            select_backend("native", [x.bfloat16() for x in imgs])

    def test_kernel_dtypes_checked(self):
        """Direct kernel calls: image arrays float32 or float16 (TypeError otherwise), no hidden conversions."""
        inp = plane_pair()
        B, C, H, W = 1, 3, 6, 8
        cams = [
            x.reshape(1, -1).contiguous()
            for x in compose_warp(
                *[inp[a] for a in ("src_K", "src_cam_from_world", "dst_K", "dst_cam_from_world")], torch.float32
            )
        ]
        M, t, P, kt, Ki = cams
        ins = [
            inp["src_color"].half(),
            inp["src_depth"],
            inp["src_normal"].half(),
            P,
            kt,
            M,
            t,
            Ki,
            inp["dst_depth"],
            inp["dst_normal"].half(),
            1e-4,
            1e-2,
            True,
        ]
        outs = [
            torch.empty(B, C, H, W, dtype=torch.float16),
            torch.empty(B, 1, H, W, dtype=torch.bool),
            torch.empty(B, 1, H, W, dtype=torch.uint8),
            None,
        ]
        _core.reproject(*ins, *outs)
        assert torch.equal(outs[0][..., 1:], inp["src_color"].half()[..., :-1])
        with pytest.raises(TypeError, match="src_values"):
            _core.reproject(inp["src_color"].bfloat16(), *ins[1:], *outs)
        with pytest.raises(TypeError, match="dst_depth"):
            _core.reproject(*ins[:8], inp["dst_depth"].double(), *ins[9:], *outs)
        with pytest.raises(TypeError, match="out_values"):
            _core.reproject(*ins, outs[0].bfloat16(), *outs[1:])
        with pytest.raises(TypeError):  # non-contiguous float16 input: refused, not copied
            _core.reproject(ins[0].transpose(-1, -2).contiguous().transpose(-1, -2), *ins[1:], *outs)
