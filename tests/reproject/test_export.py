"""The export formulation (stereorepro.reproject._lean) and rectified pairs: what export_onnx writes for hard tests,
checked against the torch reference in eager, in onnxruntime, in onnx.checker and in onnx.reference (a second,
independent runtime), and the rectified declaration (two taps) on every backend."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereorepro import StereoReprojection, TemporalReprojection, export_onnx, stereo_reproject, temporal_blend
from stereorepro.camera import compose_warp, rectify_warp
from stereorepro.errors import CameraError
from stereorepro._testing import example_inputs
from stereorepro.io.onnx import onnx_input_dims
from stereorepro.reproject import _general, _lean, functional

from base import BaseTester
from test_reproject import ARGS, plane_pair  # tests/reproject/ is on sys.path

THR = (0.05, 0.3)


def stereo_case(H=36, W=48, B=2, head_motion=True, dtype=torch.float32, seed=0):
    m = StereoReprojection(*THR)
    return example_inputs(m, batch=B, height=H, width=W, dtype=dtype, seed=seed, head_motion=head_motion)


def both(inp, sampling="bilinear", rectified=False, values=None):
    """(general path, export formulation) on the same composed warp, in eager."""
    sc, sd, sn, sK, sT, dd, dn, dK, dT = inp
    if values is not None:
        sc = values
    warp = compose_warp(sK, sT, dK, dT, _general.compute_dtype(sc, dd))
    if rectified:
        warp = rectify_warp(warp, *dd.shape[-2:])
    ref = _general.general_reproject(sc, sd, sn, dd, dn, warp, *THR, sampling, False, 0.1, False)
    got = _lean.lean_reproject(sc, sd, sn, dd, dn, warp, *THR, sampling, rectified)
    return ref, got


def moving(inp: tuple, seed: int = 0, hostile: bool = False) -> tuple:
    """``inp`` (a motion module's example inputs: motion, motion_world last) with the motion of a moving patch
    added and perturbed (taps anywhere in the pixel); ``hostile``: NaN / ±inf / huge entries in both motions and
    points moved behind the previous camera."""
    *rest, motion, motion_world = inp
    B, _, H, W = motion.shape
    g = torch.Generator().manual_seed(seed)
    motion = torch.nan_to_num(motion, nan=0.0) + 0.3 * torch.randn(motion.shape, generator=g, dtype=motion.dtype)
    motion_world = motion_world + 0.002 * torch.randn(motion_world.shape, generator=g, dtype=motion.dtype)
    patch = (slice(None), slice(None), slice(H // 4, H // 2), slice(W // 3, W // 2))
    motion[patch] += torch.tensor([-2.5, 1.25], dtype=motion.dtype).view(1, 2, 1, 1)
    motion_world[patch] += torch.tensor([0.05, -0.02, 0.01], dtype=motion.dtype).view(1, 3, 1, 1)
    if hostile:
        specials = torch.tensor([float("nan"), float("inf"), -float("inf"), 1e30, -3e38], dtype=motion.dtype)
        for m in (motion, motion_world):
            odd = torch.rand(m.shape, generator=g) < 0.05
            m[odd] = specials[torch.randint(0, len(specials), (int(odd.sum()),), generator=g)]
        motion_world[:, 2, :2] = -100.0  # moved behind the previous camera
    return (*rest, motion, motion_world)


def both_motion(hostile: bool, sampling: str = "bilinear", world: bool = True, dtype=torch.float32):
    """(general path, export formulation) of a temporal case with motion vectors, on the same warp, in eager."""
    m = TemporalReprojection(*THR, motion_vectors=True)
    cur, dd, dn, dK, dT, hc, hl, sd, sn, sK, sT, mo, mw = moving(
        example_inputs(m, batch=2, height=29, width=43, dtype=dtype), seed=1, hostile=hostile
    )
    mw = mw if world else None
    values = torch.cat([hc, hl], 1)
    warp = compose_warp(sK, sT, dK, dT, _general.compute_dtype(values, dd))
    R = sT[:, :3, :3]
    ref = _general.general_reproject(values, sd, sn, dd, dn, warp, *THR, sampling, False, 0.1, False, mo, mw, R)
    got = _lean.lean_reproject(values, sd, sn, dd, dn, warp, *THR, sampling, False, mo, mw, R)
    return ref, got


def assert_same(ref, got, atol=1e-6):
    for name, r, g in zip(("values", "valid", "reason", "confidence"), ref, got):
        assert r.dtype == g.dtype and r.shape == g.shape, name
        if r.is_floating_point():
            torch.testing.assert_close(g, r, atol=atol, rtol=1e-6, msg=name)
        else:
            assert torch.equal(g, r), f"{name}: {int((g != r).sum())} pixels differ"


class TestLeanReproject(BaseTester):
    """lean_reproject (eager) against the general path: the same decisions on the same warp."""

    def test_smoke(self):
        ref, got = both(stereo_case())
        assert got[0].shape == (2, 3, 36, 48) and got[2].dtype == torch.uint8
        assert 0.5 < float(ref[1].float().mean()) < 1.0  # realistic: some discards, mostly kept

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @pytest.mark.parametrize("head_motion", [False, True])
    def test_equals_general(self, sampling, head_motion, dtype):
        assert_same(*both(stereo_case(head_motion=head_motion, dtype=dtype), sampling))

    def test_cardinality(self):
        """C = 4 values (temporal: colour and history length), a source of another size."""
        inp = list(stereo_case(H=20, W=30, B=1))
        small = stereo_case(H=13, W=17, B=1)
        inp[:5] = small[:5]
        values = torch.cat([inp[0], torch.rand(1, 1, 13, 17)], 1)
        ref, got = both(inp, values=values)
        assert got[0].shape == (1, 4, 20, 30)
        assert_same(ref, got)

    @pytest.mark.parametrize("sampling", ["bilinear", "nearest", "catmull_rom"])
    @pytest.mark.parametrize("hostile", [False, True], ids=["scene", "hostile"])
    @pytest.mark.parametrize("world", [True, False], ids=["world", "screen"])
    def test_motion_equals_general(self, sampling, hostile, world, dtype):
        """Motion vectors (taps at pixel + motion, the point moved by the world motion; non-finite motion out of
        frame, moved points behind the previous camera): the general path's decisions."""
        ref, got = both_motion(hostile, sampling, world, dtype)
        assert_same(ref, got)
        assert 0.2 < float(ref[1].float().mean()) < 1.0
        if hostile:
            assert ({2, 3, 5} if world else {3, 5}) <= set(ref[2].unique().tolist())  # behind, out of frame, position

    def test_rectified_equals_general(self):
        """On a rectified warp the vertical fraction is 0: the two taps of row y0 give the four taps' results."""
        assert_same(*both(stereo_case(head_motion=False), rectified=True))

    def test_hard_cases(self):
        """Non-finite and degenerate values in every input, and a source that fills none of the frame."""
        inp = list(stereo_case(H=12, W=16, B=1))
        g = torch.Generator().manual_seed(3)
        for i in (0, 1, 2, 5, 6):
            x = inp[i].clone()
            mask = torch.rand(x.shape, generator=g) < 0.15
            specials = torch.tensor([float("nan"), float("inf"), -float("inf"), 0.0, -1.0, 1e-30, 3e38])
            x[mask] = specials[torch.randint(0, len(specials), (int(mask.sum()),), generator=g)]
            inp[i] = x
        assert_same(*both(inp))
        inp[1] = torch.full_like(inp[1], float("nan"))  # no source surface anywhere
        ref, got = both(inp)
        assert_same(ref, got)
        assert not bool(got[1].any())


def plane_inputs(shift_px=1.0):
    """test_reproject's fronto-parallel plane pair (taps on exact pixels: fractions 0) as a list in the order of
    StereoReprojection.input_names."""
    inp = plane_pair(shift_px=shift_px)
    return [inp[a] for a in ARGS]


class TestLeanTies(BaseTester):
    """Exact ties, which realistic inputs never hit: comparisons at the threshold, taps of weight exactly 0."""

    def test_zero_thresholds(self):
        """Same camera, thresholds 0: every distance is exactly 0 and ``d <= 0`` accepts it."""
        inp = plane_inputs(shift_px=0.0)
        warp = compose_warp(inp[3], inp[4], inp[7], inp[8], torch.float32)
        ref = _general.general_reproject(*inp[:3], *inp[5:7], warp, 0.0, 0.0, "bilinear", False, 0.1, False)
        got = _lean.lean_reproject(*inp[:3], *inp[5:7], warp, 0.0, 0.0, "bilinear")
        assert bool(ref[1].all())
        assert_same(ref, got)

    def test_weightless_taps_do_not_report(self):
        """A one-pixel shift puts every pixel's taps on exact pixels (fx = fy = 0): the x0 + 1 and y0 + 1 taps
        weigh 0 and must not report their (here higher) codes: even source columns fail POSITION (too far),
        odd ones NONFINITE (NaN colour)."""
        inp = plane_inputs(shift_px=1.0)
        inp[0][..., 1::2] = float("nan")
        inp[1][..., 0::2] = 3.0
        warp = compose_warp(inp[3], inp[4], inp[7], inp[8], torch.float32)
        ref = _general.general_reproject(*inp[:3], *inp[5:7], warp, *THR, "bilinear", False, 0.1, False)
        got = _lean.lean_reproject(*inp[:3], *inp[5:7], warp, *THR, "bilinear")
        assert {5, 7} <= set(ref[2].unique().tolist())
        assert_same(ref, got)


class TestRectified(BaseTester):
    """rectified=True: declared parallel rigs read two taps per pixel on every backend, the same results."""

    def test_rectify_warp_exact_rows(self):
        inp = stereo_case(head_motion=False, B=1)
        warp = compose_warp(inp[3], inp[4], inp[7], inp[8], torch.float32)
        assert not bool((warp.P[:, 1:] == torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])).all())  # rounding
        r = rectify_warp(warp, 36, 48)
        assert torch.equal(r.P[:, 1:], torch.tensor([[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]]))
        assert torch.equal(r.kt[:, 1:], torch.zeros(1, 2, 1)) and torch.equal(r.P[:, 0], warp.P[:, 0])
        assert torch.equal(r.M, warp.M) and torch.equal(r.t, warp.t)

    def test_exceptions(self):
        inp = stereo_case(head_motion=True, B=1)  # the eyes of two instants: not a rectified pair
        with pytest.raises(CameraError, match="not a rectified pair"):
            stereo_reproject(*inp, *THR, rectified=True)
        with pytest.raises(CameraError, match="not a rectified pair"):
            StereoReprojection(*THR, rectified=True)(*inp)
        from stereorepro.reproject import backward_reproject

        with pytest.raises(ValueError, match="motion"):
            backward_reproject(
                *stereo_case(head_motion=False, B=1), *THR, rectified=True, motion=torch.zeros(1, 2, 36, 48)
            )

    def test_backends_agree(self, backend):
        inp = stereo_case(head_motion=False)
        ref = stereo_reproject(*inp, *THR, backend="torch", rectified=True)
        with torch.no_grad():
            got = stereo_reproject(*inp, *THR, backend=self.backend_arg(backend), rectified=True)
        self.assert_identical(got, ref)
        # and the declaration changes nothing but the rounding it removes
        plain = stereo_reproject(*inp, *THR, backend="torch")
        assert float((plain[1] != ref[1]).float().mean()) < 0.01

    def test_module_equals_function(self):
        inp = stereo_case(head_motion=False)
        m = StereoReprojection(*THR, rectified=True)
        assert "rectified=True" in repr(m)
        for a, b in zip(m(*inp), stereo_reproject(*inp, *THR, rectified=True)):
            assert torch.equal(a, b)


class TestLeanBlend(BaseTester):
    """The blend in the export formulation (``_lean.lean_blend``, arithmetic instead of Where) against
    temporal_blend, on what it is given: finite warped histories, hard masks; hostile current samples."""

    @staticmethod
    def case(seed=0, B=2, H=9, W=11):
        g = torch.Generator().manual_seed(seed)
        cur = torch.rand(B, 3, H, W, generator=g) * 4
        flat = cur.view(-1)
        pick = torch.randint(0, flat.numel(), (12,), generator=g)
        flat[pick] = torch.tensor([float("nan"), float("inf"), -float("inf"), 1e30, -0.0, 0.0] * 2)
        hist = torch.randn(B, 3, H, W, generator=g) * 3
        n = torch.tensor([-5.0, -0.0, 0.0, 0.5, 1.0, 7.0, 300.0])[torch.randint(0, 7, (B, 1, H, W), generator=g)]
        valid = torch.rand(B, 1, H, W, generator=g) < 0.6
        return cur, hist, n, valid

    def test_smoke(self):
        cur, hist, n, valid = self.case()
        out, n_out = _lean.lean_blend(cur, hist, n, valid, 0.2, True, 255.0)
        assert out.shape == cur.shape and n_out.shape == n.shape and out.dtype == cur.dtype

    @pytest.mark.parametrize("warmup", [True, False])
    @pytest.mark.parametrize("alpha", [0.2, 1.0, 1e-6])
    @pytest.mark.parametrize("max_history", [1.0, 8.0, float("inf")])
    @pytest.mark.parametrize("history_rounding", ["none", "bmfr"])
    def test_equals_temporal_blend(self, warmup, alpha, max_history, history_rounding):
        """Values equal to temporal_blend's (a zero's sign aside), NaN where it has NaN; counts identical."""
        for seed in range(3):
            cur, hist, n, valid = self.case(seed)
            ref = temporal_blend(cur, hist, n, valid, alpha, warmup, max_history, history_rounding)
            got = _lean.lean_blend(cur, hist, n, valid, alpha, warmup, max_history, history_rounding)
            torch.testing.assert_close(got[0], ref[0], atol=0, rtol=0, equal_nan=True)
            assert torch.equal(got[1], ref[1])

    def test_hard_cases(self):
        """Discarded history: the current sample exactly, non-finite ones included, whatever the weight."""
        cur, hist, n, _ = self.case(5)
        none = torch.zeros_like(n, dtype=torch.bool)
        out, n_out = _lean.lean_blend(cur, hist, n, none, 0.2, False, 255.0)
        torch.testing.assert_close(out, cur, atol=0, rtol=0, equal_nan=True)
        assert bool((n_out == 1).all())


def _ort_session(path):
    ort = pytest.importorskip("onnxruntime")
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def _compare(module, outputs, inputs, atol=1e-5):
    with torch.no_grad():
        ref = module(*inputs)
    for name, r, g in zip(module.output_names, ref, outputs):
        g = np.asarray(g)
        if r.is_floating_point():
            np.testing.assert_allclose(g, r.numpy(), atol=atol, rtol=0, err_msg=name)
        else:
            np.testing.assert_array_equal(g, r.numpy(), err_msg=name)


def _with_footprint(m: TemporalReprojection) -> TemporalReprojection:
    m.footprint_weighting = True
    return m


MODULES = {
    "stereo": lambda: StereoReprojection(*THR),
    "stereo_nearest": lambda: StereoReprojection(*THR, sampling="nearest"),
    "stereo_rectified": lambda: StereoReprojection(*THR, rectified=True),
    "temporal": lambda: TemporalReprojection(*THR),
    "temporal_fixed_alpha": lambda: TemporalReprojection(*THR, warmup=False),
    "temporal_motion": lambda: TemporalReprojection(*THR, motion_vectors=True),
    "temporal_bmfr": lambda: TemporalReprojection(*THR, history_rounding="bmfr"),
    "temporal_footprint": lambda: _with_footprint(TemporalReprojection(*THR)),
    # thresholds loose enough for whole 4x4 footprints to pass on the example scene (the cubic then applies)
    "stereo_catmull_rom": lambda: StereoReprojection(0.3, 0.5, sampling="catmull_rom"),
    "temporal_catmull_rom": lambda: TemporalReprojection(0.3, 0.5, sampling="catmull_rom"),
}


def _inputs(name, module, seed=0, **kw):
    inp = example_inputs(module, head_motion=name != "stereo_rectified", seed=seed, **kw)
    if name in ("temporal_bmfr", "temporal_footprint"):  # counts that differ between taps
        k = module.input_names.index("history_len")
        g = torch.Generator().manual_seed(seed)
        inp = (*inp[:k], torch.randint(1, 30, inp[k].shape, generator=g).to(inp[k].dtype), *inp[k + 1 :])
    return moving(inp, seed, hostile=True) if name == "temporal_motion" else inp


def _computed_where(model) -> list[str]:
    """Names of the Where nodes of a model with a computed (not constant) value operand."""
    consts = {o for n in model.graph.node if n.op_type == "Constant" for o in n.output}
    consts |= {i.name for i in model.graph.initializer}
    return [n.name for n in model.graph.node if n.op_type == "Where" and not set(n.input[1:]) <= consts]


@pytest.mark.onnx
class TestExportedGraph:
    """The file export_onnx writes: lean, valid ONNX, the same results in onnxruntime and onnx.reference."""

    @pytest.mark.parametrize("name", sorted(MODULES))
    def test_onnx_parity(self, name, tmp_path):
        """onnxruntime at two sizes other than the export's (symbolic B/H/W), B = 2: valid and reason identical,
        colour within 1e-5."""
        m = MODULES[name]()
        path = export_onnx(m, tmp_path / f"{name}.onnx")
        dims = onnx_input_dims(path)
        assert dims[m.input_names[0]][0] == "B" and isinstance(dims[m.input_names[0]][2], str)
        sess = _ort_session(path)
        for h, w in [(36, 48), (71, 129)]:
            inp = _inputs(name, m, batch=2, height=h, width=w, seed=h)
            got = sess.run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)})
            _compare(m, got, inp)

    @pytest.mark.parametrize("which", ["src", "dst"])
    def test_nonfinite_normals(self, which, tmp_path):
        """Non-finite normal components count as 0 (finite_or_zero) in the graph too: NaN, +inf and -inf in the x
        component of pixels whose normal is nearly along z, so that the zeroed normals pass the normal test."""
        m = StereoReprojection(*THR)
        path = export_onnx(m, tmp_path / "stereo.onnx")
        inp = list(example_inputs(m, batch=2, height=24, width=32, seed=3))
        k = m.input_names.index(f"{which}_normal")
        normal = inp[k].clone()
        facing = normal[:, 0].abs() < 0.05
        specials = torch.tensor([float("nan"), float("inf"), -float("inf")])
        flat = normal[:, 0][facing]
        normal[:, 0][facing] = specials[torch.arange(flat.numel()) % 3]
        inp[k] = normal
        got = _ort_session(path).run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)})
        _compare(m, got, inp)
        with torch.no_grad():
            valid = m(*inp)[1][:, 0]
        assert int(facing.sum()) > 50 and int((valid & facing).sum()) > 0.5 * int(facing.sum())

    @pytest.mark.parametrize("name", sorted(MODULES))
    def test_reference_evaluator(self, name, tmp_path):
        """onnx.checker (full check) and the onnx.reference evaluator, an independent runtime, on a tiny input.

        onnx 1.23's reference GatherElements goes through ``np.choose``, which takes at most 32 choices along the
        gathered axis, and its fallback mis-reshapes: the test gives it the operator as the spec defines it
        (``np.take_along_axis``); every other operator is the reference's own."""
        onnx = pytest.importorskip("onnx")
        from onnx.reference import ReferenceEvaluator
        from onnx.reference.op_run import OpRun

        class GatherElements(OpRun):
            def _run(self, data, indices, axis=None):
                idx = indices.astype(np.int64)
                idx = np.where(idx < 0, idx + data.shape[axis], idx)  # negative indices count from the end
                return (np.take_along_axis(data, idx, axis=axis),)

        m = MODULES[name]()
        path = export_onnx(m, tmp_path / f"{name}.onnx")
        model = onnx.load(str(path))
        onnx.checker.check_model(model, full_check=True)
        inp = _inputs(name, m, batch=2, height=6, width=8, seed=1)
        evaluator = ReferenceEvaluator(model, new_ops=[GatherElements])
        got = evaluator.run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)})
        _compare(m, got, inp)

    def test_lean_graph(self, tmp_path):
        """What makes it lean: no Expand-built GatherElements index the size of image × taps × channels, no
        NonZero, few Where nodes (none in the taps), and far fewer elements moved than the traced general path."""
        onnx = pytest.importorskip("onnx")
        m = StereoReprojection(*THR)
        model = onnx.load(str(export_onnx(m, tmp_path / "lean.onnx")))
        ops = [n.op_type for n in model.graph.node]
        assert "Expand" not in {n.op_type for n in model.graph.node if any("GatherElements" in c for c in n.output)}
        assert "NonZero" not in ops and ops.count("GatherElements") >= 4 * 8
        # Where with a computed (not constant) value operand costs ~1 ns per element in onnxruntime: only the
        # camera composition's snapping (3 x 3 matrices) keeps one; none on an image, in the temporal blend neither
        computed = _computed_where(model)
        assert len(computed) <= 3, computed
        temporal = onnx.load(str(export_onnx(TemporalReprojection(*THR), tmp_path / "temporal.onnx")))
        assert len(_computed_where(temporal)) <= len(computed), _computed_where(temporal)
        with_motion = onnx.load(
            str(export_onnx(TemporalReprojection(*THR, motion_vectors=True), tmp_path / "motion.onnx"))
        )
        assert len(_computed_where(with_motion)) <= len(computed), _computed_where(with_motion)
        assert "NonZero" not in [n.op_type for n in with_motion.graph.node]
        # the general formulation, still available, is what the benchmark compares against
        functional.EXPORT_LEAN = False
        try:
            general = onnx.load(str(export_onnx(m, tmp_path / "general.onnx")))
        finally:
            functional.EXPORT_LEAN = True
        assert len(_computed_where(general)) > 3 * len(computed)

    def test_general_export_still_exact(self, tmp_path):
        """EXPORT_LEAN = False (the traced general path) gives the same outputs."""
        m = StereoReprojection(*THR)
        functional.EXPORT_LEAN = False
        try:
            path = export_onnx(m, tmp_path / "general.onnx")
        finally:
            functional.EXPORT_LEAN = True
        inp = example_inputs(m, batch=1, height=20, width=24)
        _compare(m, _ort_session(path).run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)}), inp)

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float16], ids=["fp64", "fp16"])
    def test_other_dtypes(self, dtype, tmp_path):
        """A float64 export computes in float64 and keeps Where for the sanitising (onnxruntime's
        ThresholdedRelu is float32 only); float16 inputs are widened to float32 inside the graph."""
        for m in (StereoReprojection(*THR), TemporalReprojection(*THR)):
            inp = example_inputs(m, batch=1, height=10, width=12, dtype=dtype)
            path = export_onnx(m, tmp_path / f"{type(m).__name__}.onnx", inputs=inp)
            _compare(
                m,
                _ort_session(path).run(None, {n: x.numpy() for n, x in zip(m.input_names, inp)}),
                inp,
                atol=1e-5 if dtype == torch.float64 else 1e-3,
            )
