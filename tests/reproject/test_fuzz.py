"""Fuzz suite of the public reprojection ops (hypothesis, derandomized: CI runs the same examples every time).

Every op on every backend — the torch general path, the torch fast path, the native kernels (float32 and float16 on
the CPU), the export formulation run eagerly and, for the exported modules, onnxruntime — on random, often hostile inputs: random and near-degenerate
cameras, depths with 0 / negative / ±inf / NaN / 1e-12 / 1e30 / FLT_MAX, normals non-unit / zero / NaN, colours with
NaN / Inf, H or W = 1, B = 0, float16 / bfloat16 / float32 / float64. Properties:

* no exception on valid-shaped inputs;
* no NaN/Inf in any output colour (temporal: wherever the current sample is finite, see ``temporal_blend``);
* masks and reason codes in their documented ranges (``valid`` exactly where ``reason == KEPT``; temporal
  history length in [1, max_history]);
* every backend gives the same bytes as the torch reference;
* finite gradients for finite colours.

Example counts per CI run (``make test``) are in :data:`EXAMPLES`; ``STEREOREPRO_FUZZ_SCALE`` multiplies them,
and the ``slow`` tests run 10× more. ``STEREOREPRO_FUZZ_COUNTS=FILE`` writes the calls made per op and backend.
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stereorepro import intrinsics_from_fov
from stereorepro.reproject import Reason, _native, functional
from stereorepro.reproject.functional import backward_reproject, stereo_reproject, temporal_blend, temporal_reproject

SCALE = float(os.environ.get("STEREOREPRO_FUZZ_SCALE", "1"))

#: Examples per test in one default run; each example runs every backend that applies to it.
EXAMPLES = {
    "stereo": 2000,
    "backward": 2000,
    "temporal": 2000,
    "blend": 2000,
    "temporal_motion": 600,
    "grad_stereo": 300,
    "grad_temporal": 300,
    "onnx_stereo": 400,
    "onnx_temporal": 400,
    "onnx_temporal_motion": 300,
    "lean": 500,
}

FLT_MAX = float(np.finfo(np.float32).max)
SPECIAL_DEPTHS = (0.0, -1.0, math.inf, -math.inf, math.nan, 1e-12, 1e30, FLT_MAX, 1e-20, 1e-38)
DTYPES = (torch.float32, torch.float32, torch.float16, torch.bfloat16, torch.float64)
CAMERAS = (
    "same",
    "stereo",
    "stereo",
    "rotated",
    "random",
    "tiny_fx",
    "huge_fx",
    "far",
    "huge_baseline",
    "behind",
    "off_centre",
)
HAS_NATIVE = _native.available()
COUNTS: Counter = Counter()  # (op, backend) -> calls


@pytest.fixture(scope="module", autouse=True)
def _write_counts():
    yield
    path = os.environ.get("STEREOREPRO_FUZZ_COUNTS")
    if path:
        with open(path, "w") as f:
            json.dump({f"{op} / {be}": n for (op, be), n in sorted(COUNTS.items())}, f, indent=1)


MAX_REASON = max(int(r) for r in Reason)


def fuzz_settings(name: str, slow: bool = False):
    n = max(1, int(EXAMPLES[name] * SCALE * (10 if slow else 1)))
    return settings(
        max_examples=n,
        derandomize=True,
        database=None,
        deadline=None,
        print_blob=True,
        suppress_health_check=list(HealthCheck),
    )


@dataclass
class Case:
    seed: int
    B: int
    H: int
    W: int
    Hs: int
    Ws: int
    dtype: torch.dtype
    cam_dtype: torch.dtype
    camera: str
    special: float  # share of pixels with a special depth
    normals: str
    bad_colour: float  # share of pixels with NaN / Inf colour
    thr_p: float
    thr_n: float
    sampling: str


@st.composite
def cases(draw, dtypes=DTYPES, max_side: int = 6) -> Case:
    """Random cases with image sides 1 .. ``max_side`` (above 8 the native kernels' 8-pixel vector path runs)."""
    H, W = draw(st.integers(1, max_side)), draw(st.integers(1, max_side))
    same = draw(st.booleans())
    return Case(
        seed=draw(st.integers(0, 2**31 - 1)),
        B=draw(st.sampled_from((0, 1, 1, 1, 2))),
        H=H,
        W=W,
        Hs=H if same else draw(st.integers(1, max_side)),
        Ws=W if same else draw(st.integers(1, max_side)),
        dtype=draw(st.sampled_from(dtypes)),
        cam_dtype=draw(st.sampled_from((torch.float32, torch.float64))),
        camera=draw(st.sampled_from(CAMERAS)),
        special=draw(st.sampled_from((0.0, 0.0, 0.1, 0.5, 1.0))),
        normals=draw(st.sampled_from(("unit", "unit", "non_unit", "zero_nan"))),
        bad_colour=draw(st.sampled_from((0.0, 0.0, 0.2))),
        thr_p=draw(st.sampled_from((0.0, 1e-3, 0.05, 0.05, 1.0, math.inf)) | st.floats(0.0, 10.0)),
        thr_n=draw(st.sampled_from((0.0, 0.1, 0.1, 0.5, 2.0, math.inf)) | st.floats(0.0, 3.0)),
        sampling=draw(st.sampled_from(("bilinear", "bilinear", "nearest"))),
    )


def _rotation(rng, angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis) + 1e-30
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def make_cameras(c: Case, rng) -> tuple[torch.Tensor, ...]:
    """(src_K, src_cam_from_world, dst_K, dst_cam_from_world) for the case's camera mode."""

    def K_for(w, h, fov=60.0, fx=None, cx_shift=0.0):
        K = intrinsics_from_fov(fov, w, h, dtype=torch.float64)[0]
        if fx is not None:
            K[0, 0] = K[1, 1] = fx
        K[0, 2] += cx_shift
        return K

    fx = {"tiny_fx": 1e-4, "huge_fx": 1e6}.get(c.camera)
    shift = rng.uniform(-50, 50) if c.camera == "off_centre" else 0.0
    sK, dK = K_for(c.Ws, c.Hs, fx=fx, cx_shift=shift), K_for(c.W, c.H, fx=fx)
    src, dst = np.eye(4), np.eye(4)
    if c.camera in ("stereo", "tiny_fx", "huge_fx", "off_centre"):
        dst[0, 3] = rng.uniform(0.0, 0.2)
    elif c.camera == "rotated":
        dst[:3, :3] = _rotation(rng, rng.uniform(0, 0.3))
        dst[:3, 3] = rng.normal(size=3) * 0.1
    elif c.camera == "random":
        src[:3, :3] = _rotation(rng, rng.uniform(0, math.pi))
        src[:3, 3] = rng.normal(size=3)
        dst[:3, :3] = _rotation(rng, rng.uniform(0, math.pi))
        dst[:3, 3] = rng.normal(size=3)
    elif c.camera == "far":  # both cameras far from the world origin
        src[:3, 3] = 1e4
        dst[:3, 3] = 1e4
        dst[0, 3] += 0.06
    elif c.camera == "huge_baseline":
        dst[0, 3] = 1e6
    elif c.camera == "behind":  # the source looks the other way
        src[:3, :3] = _rotation(rng, math.pi) if rng.uniform() < 0.5 else np.diag([-1.0, 1.0, -1.0])
    B = c.B
    cast = lambda a: torch.tensor(np.array(a), dtype=torch.float64).to(c.cam_dtype)  # noqa: E731
    return (
        cast(np.broadcast_to(sK.numpy(), (B, 3, 3))),
        cast(np.broadcast_to(src, (B, 4, 4))),
        cast(np.broadcast_to(dK.numpy(), (B, 3, 3))),
        cast(np.broadcast_to(dst, (B, 4, 4))),
    )


def make_depth(c: Case, rng, B, H, W, base: float) -> torch.Tensor:
    d = np.full((B, 1, H, W), base) + rng.normal(scale=0.01, size=(B, 1, H, W)) * (rng.uniform() < 0.5)
    mask = rng.uniform(size=d.shape) < c.special
    d[mask] = rng.choice(SPECIAL_DEPTHS, size=int(mask.sum()))
    return torch.from_numpy(d).to(c.dtype)


def make_normal(c: Case, rng, B, H, W) -> torch.Tensor:
    n = np.zeros((B, 3, H, W))
    n[:, 2] = -1.0
    n += rng.normal(scale=0.05, size=n.shape)
    if c.normals == "unit":
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    elif c.normals == "non_unit":
        n *= rng.uniform(0.0, 3.0, size=(B, 1, H, W))
    else:
        bad = rng.uniform(size=(B, 1, H, W)) < 0.3
        n[np.broadcast_to(bad, n.shape)] = 0.0
        nan = rng.uniform(size=n.shape) < 0.1
        n[nan] = rng.choice([math.nan, math.inf, -math.inf], size=int(nan.sum()))
    return torch.from_numpy(n).to(c.dtype)


def make_colour(c: Case, rng, B, C, H, W) -> torch.Tensor:
    x = rng.uniform(0.0, 4.0, size=(B, C, H, W))
    bad = rng.uniform(size=x.shape) < c.bad_colour
    x[bad] = rng.choice([math.nan, math.inf, -math.inf, 1e30], size=int(bad.sum()))
    return torch.from_numpy(x).to(c.dtype)


def stereo_inputs(c: Case) -> tuple:
    rng = np.random.default_rng(c.seed)
    base = float(rng.uniform(0.5, 5.0))
    sK, sT, dK, dT = make_cameras(c, rng)
    return (
        make_colour(c, rng, c.B, 3, c.Hs, c.Ws),
        make_depth(c, rng, c.B, c.Hs, c.Ws, base),
        make_normal(c, rng, c.B, c.Hs, c.Ws),
        sK,
        sT,
        make_depth(c, rng, c.B, c.H, c.W, base),
        make_normal(c, rng, c.B, c.H, c.W),
        dK,
        dT,
    )


def temporal_inputs(c: Case) -> tuple:
    """temporal_reproject's positional inputs (current, depth, normal, K, T, history, history_len, prev_depth,
    prev_normal, prev_K, prev_T) and (alpha, warmup, max_history)."""
    rng = np.random.default_rng(c.seed + 1)
    src_color, sd, sn, sK, sT, dd, dn, dK, dT = stereo_inputs(c)
    n = rng.uniform(-5.0, 300.0, size=(c.B, 1, c.Hs, c.Ws))
    odd = rng.uniform(size=n.shape) < 0.2
    n[odd] = rng.choice([math.nan, math.inf, -math.inf, -1e30, 0.0, -1.0], size=int(odd.sum()))
    history_len = torch.from_numpy(n).to(c.dtype)
    current = make_colour(c, rng, c.B, 3, c.H, c.W)
    alpha = float(rng.choice([0.2, 1.0, 1e-6, rng.uniform()]))
    max_history = float(rng.choice([1.0, 8.0, 255.0, math.inf]))
    return (
        (current, dd, dn, dK, dT, src_color, history_len, sd, sn, sK, sT),
        (alpha, bool(rng.uniform() < 0.7), max_history),
    )


def _bytes_equal(a: torch.Tensor, b: torch.Tensor, half_nan_bits: bool = True) -> bool:
    """Same dtype, shape and bytes. ``half_nan_bits=False``: float16 NaNs only need to be NaN in both (see
    :func:`assert_same`)."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype == torch.float16 and not half_nan_bits:
        nan = torch.isnan(a)
        if not torch.equal(nan, torch.isnan(b)):
            return False
        a, b = a.masked_fill(nan, 0.0), b.masked_fill(nan, 0.0)
    return torch.equal(a.contiguous().view(-1).view(torch.uint8), b.contiguous().view(-1).view(torch.uint8))


def run_backends(fn, native_ok: bool, op: str):
    """fn(backend) on the torch general path, the torch fast path and (where it runs) the native kernels."""
    out = {}
    saved = functional.FAST_PATH
    try:
        functional.FAST_PATH = False
        out["torch"] = fn("torch")
        functional.FAST_PATH = True
        out["fast"] = fn("torch")
    finally:
        functional.FAST_PATH = saved
    if native_ok:
        out["native"] = fn("native")
    for name in out:
        COUNTS[(op, name)] += 1
    return out


def assert_same(outs: dict, what: str) -> None:
    """Every backend's outputs byte for byte as the torch reference's, except the bits of a NaN in a float16
    output of native (a NaN current colour passing through temporal): torch's own float16 -> float32 conversion
    gives a NaN the F16C pattern (sign and payload kept, quiet bit set) in its vectorised loop but 0x7FFFFFFF in
    the loop's scalar tail, so the NaN bits torch returns depend on where the element lies in the tensor; the
    native kernels always give the F16C pattern."""
    ref = outs["torch"]
    for name, got in outs.items():
        for i, (g, r) in enumerate(zip(got, ref)):
            assert _bytes_equal(g, r, half_nan_bits=name != "native"), (
                f"{what}: output {i} of {name} differs from the torch reference"
            )


def assert_masks(valid: torch.Tensor, reason: torch.Tensor, dst_depth: torch.Tensor) -> None:
    assert valid.dtype == torch.bool and reason.dtype == torch.uint8
    assert int(reason.max()) <= MAX_REASON if reason.numel() else True
    assert torch.equal(valid, reason == int(Reason.KEPT))
    has = torch.isfinite(dst_depth.double()) & (dst_depth.double() > 0)
    assert not bool((valid & ~has).any()), "a destination pixel without a surface was reported valid"


def motion_inputs(c: Case) -> tuple[torch.Tensor, torch.Tensor]:
    """Random motion (B, 2, H, W) and world motion (B, 3, H, W) in the case's dtype: small to large screen motion,
    10 % NaN / ±inf / 1e30 entries in each."""
    rng = np.random.default_rng(c.seed + 4)
    mo = rng.normal(scale=float(rng.choice([0.5, 3.0, 50.0])), size=(c.B, 2, c.H, c.W))
    mw = rng.normal(scale=0.05, size=(c.B, 3, c.H, c.W)) * (rng.uniform() < 0.5)
    for a in (mo, mw):
        odd = rng.uniform(size=a.shape) < 0.1
        a[odd] = rng.choice([math.nan, math.inf, -math.inf, 1e30], size=int(odd.sum()))
    return torch.from_numpy(mo).to(c.dtype), torch.from_numpy(mw).to(c.dtype)


def _native_ok(c: Case) -> bool:
    return HAS_NATIVE and c.dtype in _native.DTYPES


@pytest.mark.parametrize("slow", [pytest.param(False), pytest.param(True, marks=pytest.mark.slow)], ids=["ci", "long"])
class TestFuzz:
    """One test per public op; ``long`` runs 10× the examples (``-m slow``)."""

    def test_stereo_reproject(self, slow):
        @fuzz_settings("stereo", slow)
        @given(cases())
        def check(c):
            args = stereo_inputs(c)
            with torch.no_grad():
                outs = run_backends(
                    lambda be: stereo_reproject(*args, c.thr_p, c.thr_n, c.sampling, backend=be),
                    _native_ok(c),
                    "stereo_reproject",
                )
            color, valid, reason = outs["torch"]
            assert color.shape == (c.B, 3, c.H, c.W) and color.dtype == c.dtype
            assert bool(torch.isfinite(color).all()), "non-finite output colour"
            assert_masks(valid, reason, args[5])
            assert_same(outs, "stereo_reproject")

        check()

    def test_backward_reproject(self, slow):
        @fuzz_settings("backward", slow)
        @given(cases(), st.integers(1, 5), st.booleans())
        def check(c, C, soft):
            rng = np.random.default_rng(c.seed + 2)
            args = list(stereo_inputs(c))
            args[0] = make_colour(c, rng, c.B, C, c.Hs, c.Ws)
            with torch.no_grad():
                outs = run_backends(
                    lambda be: backward_reproject(*args, c.thr_p, c.thr_n, c.sampling, soft=soft, backend=be),
                    _native_ok(c) and not soft,
                    "backward_reproject",
                )
            values, valid, reason, conf = outs["torch"]
            assert values.shape == (c.B, C, c.H, c.W)
            assert bool(torch.isfinite(values).all()), "non-finite output values"
            assert bool(((conf >= 0) & (conf <= 1 + 1e-6)).all()), "confidence outside [0, 1]"
            assert_masks(valid, reason, args[5])
            assert_same(outs, "backward_reproject")

        check()

    def test_temporal_reproject(self, slow):
        @fuzz_settings("temporal", slow)
        @given(cases(), st.booleans())
        def check(c, with_reason):
            args, (alpha, warmup, max_history) = temporal_inputs(c)
            with torch.no_grad():
                outs = run_backends(
                    lambda be: temporal_reproject(
                        *args,
                        c.thr_p,
                        c.thr_n,
                        alpha,
                        warmup,
                        max_history,
                        c.sampling,
                        backend=be,
                        return_reason=with_reason,
                    ),
                    _native_ok(c),
                    "temporal_reproject",
                )
            color, n, valid = outs["torch"][:3]
            current = args[0]
            assert color.shape == current.shape and color.dtype == current.dtype
            finite_in = torch.isfinite(current).all(1, keepdim=True).expand_as(current)
            assert bool(torch.isfinite(color[finite_in]).all()), "non-finite colour where the sample is finite"
            assert bool(torch.isfinite(n).all()) and bool(((n >= 1) & (n <= max_history)).all()), (
                f"history length outside [1, {max_history}]: {n.unique()}"
            )
            assert not bool((valid & ~(torch.isfinite(args[1].double()) & (args[1].double() > 0))).any())
            if with_reason:
                assert_masks(valid, outs["torch"][3], args[1])
            assert_same(outs, "temporal_reproject")

        check()

    def test_temporal_reproject_motion(self, slow):
        """With motion vectors on every backend (general path, fast path, native; the fused native pass without
        reasons too): random, huge and non-finite motion and world motion, images up to 20 pixels a side (the
        native vector path)."""

        @fuzz_settings("temporal_motion", slow)
        @given(cases(max_side=20), st.booleans())
        def check(c, with_reason):
            args, (alpha, warmup, max_history) = temporal_inputs(c)
            motion, motion_world = motion_inputs(c)
            if c.seed % 3 == 0:
                motion_world = None
            with torch.no_grad():
                outs = run_backends(
                    lambda be: temporal_reproject(
                        *args,
                        c.thr_p,
                        c.thr_n,
                        alpha,
                        warmup,
                        max_history,
                        c.sampling,
                        backend=be,
                        return_reason=with_reason,
                        motion=motion,
                        motion_world=motion_world,
                    ),
                    _native_ok(c),
                    "temporal_reproject with motion",
                )
            color, n, valid = outs["torch"][:3]
            finite_in = torch.isfinite(args[0]).all(1, keepdim=True).expand_as(args[0])
            assert bool(torch.isfinite(color[finite_in]).all())
            assert bool(((n >= 1) & (n <= max_history)).all())
            if with_reason:
                assert_masks(valid, outs["torch"][3], args[1])
            assert_same(outs, "temporal_reproject with motion")

        check()

    def test_temporal_blend(self, slow):
        @fuzz_settings("blend", slow)
        @given(cases(), st.sampled_from(("bool", "float")))
        def check(c, kind):
            rng = np.random.default_rng(c.seed + 3)
            (current, *_), (alpha, warmup, max_history) = temporal_inputs(c)
            history = make_colour(c, rng, c.B, 3, c.H, c.W)
            n = torch.from_numpy(
                rng.choice([-1e30, -1.0, 0.0, 1.0, 7.5, 300.0, math.nan, math.inf], size=(c.B, 1, c.H, c.W))
            ).to(c.dtype)
            u = torch.from_numpy(rng.uniform(size=(c.B, 1, c.H, c.W)))
            confidence = u < 0.5 if kind == "bool" else torch.where(u < 0.3, 0.0, u).to(c.dtype)
            color, n_out = temporal_blend(current, history, n, confidence, alpha, warmup, max_history)
            COUNTS[("temporal_blend", "torch")] += 1
            finite_in = torch.isfinite(current).all(1, keepdim=True)
            finite_hist = torch.isfinite(history).all(1, keepdim=True)
            keep = (confidence > 0) if kind == "float" else confidence
            ok = finite_in & (finite_hist | ~keep)
            assert bool(torch.isfinite(color)[ok.expand_as(color)].all())
            assert bool(((n_out >= 1) & (n_out <= max_history)).all()), n_out.unique()

        check()


@pytest.mark.parametrize("soft", [False, True], ids=["hard", "soft"])
class TestFuzzGradients:
    """Finite gradients w.r.t. colour, depths and (soft) thresholds for finite colours, whatever the depths,
    normals and cameras hold."""

    def test_stereo_gradients(self, soft):
        @fuzz_settings("grad_stereo")
        @given(cases(dtypes=(torch.float32, torch.float64)).filter(lambda c: c.B > 0))
        def check(c):
            c.bad_colour = 0.0
            args = [a.clone().requires_grad_(i in (0, 1, 5)) for i, a in enumerate(stereo_inputs(c))]
            thr_p = torch.tensor(
                max(c.thr_p, 1e-3) if math.isfinite(c.thr_p) else 0.05, dtype=c.dtype, requires_grad=soft
            )
            color, _, _ = stereo_reproject(*args, thr_p, c.thr_n, c.sampling, soft=soft, backend="torch")
            COUNTS[("stereo_reproject gradients", "soft" if soft else "hard")] += 1
            weights = torch.linspace(0.5, 1.5, color.numel(), dtype=color.dtype).view_as(color)
            grads = torch.autograd.grad(
                (color * weights).sum(), [args[0], args[1], args[5]] + ([thr_p] if soft else []), allow_unused=True
            )
            for name, g in zip(("src_color", "src_depth", "dst_depth", "position_threshold"), grads):
                assert g is None or bool(torch.isfinite(g).all()), f"non-finite gradient w.r.t. {name}"

        check()

    def test_temporal_gradients(self, soft):
        @fuzz_settings("grad_temporal")
        @given(cases(dtypes=(torch.float32, torch.float64)).filter(lambda c: c.B > 0))
        def check(c):
            c.bad_colour = 0.0
            args, (alpha, warmup, max_history) = temporal_inputs(c)
            args = [a.clone() for a in args]
            args[6] = torch.nan_to_num(args[6], nan=0.0, posinf=300.0, neginf=0.0)
            for i in (0, 1, 5, 7):
                args[i].requires_grad_(True)
            a = torch.tensor(alpha, dtype=c.dtype, requires_grad=soft)
            color, n, _ = temporal_reproject(
                *args,
                max(c.thr_p, 1e-3) if math.isfinite(c.thr_p) else 0.05,
                c.thr_n,
                a,
                warmup,
                max_history,
                c.sampling,
                soft=soft,
                backend="torch",
            )
            COUNTS[("temporal_reproject gradients", "soft" if soft else "hard")] += 1
            grads = torch.autograd.grad(
                color.sum() + n.sum(), [args[0], args[1], args[5], args[7]] + ([a] if soft else []), allow_unused=True
            )
            for name, g in zip(("current_color", "depth", "history_color", "prev_depth", "alpha"), grads):
                assert g is None or bool(torch.isfinite(g).all()), f"non-finite gradient w.r.t. {name}"

        check()


@pytest.mark.onnx
class TestFuzzOnnx:
    """The exported modules in onnxruntime on the fuzz inputs (float32: onnxruntime's type), against torch."""

    @staticmethod
    def _session(module, tmp_path_factory):
        import onnxruntime as ort

        from stereorepro.io.onnx import export_onnx

        path = tmp_path_factory.mktemp("fuzz_onnx") / f"{type(module).__name__}.onnx"
        export_onnx(module, path)
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        opts.intra_op_num_threads = 1
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

    def test_stereo_onnxruntime(self, tmp_path_factory):
        from stereorepro.reproject import StereoReprojection

        thr = (0.05, 0.1)
        module = StereoReprojection(*thr, backend="torch")
        sess = self._session(module, tmp_path_factory)
        names = [i.name for i in sess.get_inputs()]

        @fuzz_settings("onnx_stereo")
        @given(cases(dtypes=(torch.float32,)).filter(lambda c: c.B > 0 and c.sampling == "bilinear"))
        def check(c):
            args = [a.float() for a in stereo_inputs(c)]
            with torch.no_grad():
                ref = module(*args)
            got = sess.run(None, {n: a.numpy() for n, a in zip(names, args)})
            COUNTS[("StereoReprojection", "onnxruntime")] += 1
            color = torch.from_numpy(got[0])
            assert bool(torch.isfinite(color).all())
            assert torch.equal(torch.from_numpy(got[1]), ref[1]) and torch.equal(torch.from_numpy(got[2]), ref[2])
            assert torch.allclose(color, ref[0], atol=1e-5, rtol=1e-5)

        check()

    def test_temporal_onnxruntime(self, tmp_path_factory):
        from stereorepro.reproject import TemporalReprojection

        module = TemporalReprojection(0.05, 0.1, backend="torch")
        sess = self._session(module, tmp_path_factory)
        names = [i.name for i in sess.get_inputs()]

        @fuzz_settings("onnx_temporal")
        @given(cases(dtypes=(torch.float32,)).filter(lambda c: c.B > 0 and c.sampling == "bilinear"))
        def check(c):
            args = [a.float() for a in temporal_inputs(c)[0]]
            with torch.no_grad():
                ref = module(*args)
            got = [torch.from_numpy(g) for g in sess.run(None, {n: a.numpy() for n, a in zip(names, args)})]
            COUNTS[("TemporalReprojection", "onnxruntime")] += 1
            finite_in = torch.isfinite(args[0]).all(1, keepdim=True).expand_as(args[0])
            assert bool(torch.isfinite(got[0][finite_in]).all())
            assert torch.equal(got[2], ref[2])
            assert torch.allclose(got[0], ref[0], atol=1e-5, rtol=1e-5, equal_nan=True)
            assert torch.allclose(got[1], ref[1], atol=1e-5, rtol=1e-5)

        check()

    def test_temporal_motion_onnxruntime(self, tmp_path_factory):
        """The motion-vector graph (the export formulation with motion) on random and non-finite motion, sides up
        to 20: valid identical, colour and count within 1e-5."""
        from stereorepro.reproject import TemporalReprojection

        module = TemporalReprojection(0.05, 0.1, motion_vectors=True, backend="torch")
        sess = self._session(module, tmp_path_factory)
        names = [i.name for i in sess.get_inputs()]

        @fuzz_settings("onnx_temporal_motion")
        @given(cases(dtypes=(torch.float32,), max_side=20).filter(lambda c: c.B > 0 and c.sampling == "bilinear"))
        def check(c):
            args = [a.float() for a in temporal_inputs(c)[0]] + list(motion_inputs(c))
            with torch.no_grad():
                ref = module(*args)
            got = [torch.from_numpy(g) for g in sess.run(None, {n: a.numpy() for n, a in zip(names, args)})]
            COUNTS[("TemporalReprojection with motion", "onnxruntime")] += 1
            finite_in = torch.isfinite(args[0]).all(1, keepdim=True).expand_as(args[0])
            assert bool(torch.isfinite(got[0][finite_in]).all())
            assert torch.equal(got[2], ref[2])
            assert torch.allclose(got[0], ref[0], atol=1e-5, rtol=1e-5, equal_nan=True)
            assert torch.allclose(got[1], ref[1], atol=1e-5, rtol=1e-5)

        check()


class TestFuzzExportFormulation:
    """The export formulation (what export_onnx writes for hard tests, :mod:`stereorepro.reproject._lean`) run
    eagerly against the general path on every fuzz input, thresholds 0 and inf included (the onnxruntime tests
    above fix them in the exported module): valid and reason identical, values and confidence within rounding."""

    def test_lean_reproject(self):
        from stereorepro.camera import compose_warp, rectify_warp
        from stereorepro.reproject import _general, _lean

        @fuzz_settings("lean")
        @given(cases().filter(lambda c: c.B > 0), st.integers(1, 4), st.booleans())
        def check(c, C, rectified):
            rng = np.random.default_rng(c.seed + 3)
            args = list(stereo_inputs(c))
            args[0] = make_colour(c, rng, c.B, C, c.Hs, c.Ws)
            src, dst = args[:3], args[5:7]
            wdt = _general.compute_dtype(*src, *dst)
            warp = compose_warp(*args[3:5], *args[7:9], wdt)
            rectified = rectified and c.sampling == "bilinear"
            if rectified:  # rectify whatever the cameras: the formulation must match on that warp
                warp = rectify_warp(warp, c.H, c.W, check=False)
            with torch.no_grad():
                ref = _general.general_reproject(*src, *dst, warp, c.thr_p, c.thr_n, c.sampling, False, 0.1, False)
                got = _lean.lean_reproject(*src, *dst, warp, c.thr_p, c.thr_n, c.sampling, rectified)
            COUNTS[("lean_reproject", "torch eager")] += 1
            for i in (1, 2):
                assert _bytes_equal(got[i], ref[i]), f"{('valid', 'reason')[i - 1]} of the export formulation differs"
            for i in (0, 3):  # values and confidence: sums over the taps, accumulated in another order
                assert got[i].dtype == ref[i].dtype and bool(torch.isfinite(got[i]).all())
                torch.testing.assert_close(got[i].double(), ref[i].double(), atol=1e-5, rtol=1e-5)

        check()


class TestFuzzReaders:
    """The EXR and frame readers on mutated files (random bytes overwritten, truncated), from several threads at
    once: every read gives (H, W) float32 channels or one ``ValueError`` (``SequenceError`` from the frame
    reader), prints nothing, and leaves the process's standard streams as they were (descriptors 1 and 2 and
    ``sys.stdout`` / ``sys.stderr``: the readers swap them to capture OpenEXR's messages)."""

    EXAMPLES = 150  #: per CI run (``STEREOREPRO_FUZZ_SCALE`` multiplies it)

    @staticmethod
    def _settings():
        return settings(
            max_examples=max(1, int(TestFuzzReaders.EXAMPLES * SCALE)),
            derandomize=True,
            database=None,
            deadline=None,
            print_blob=True,
            suppress_health_check=list(HealthCheck),
        )

    @pytest.fixture(scope="class")
    def sequence(self, tmp_path_factory):
        """A valid two-frame sequence of our format (8x6, with motion channels on frame 1)."""
        from stereorepro.io.exr import write_exr

        d = tmp_path_factory.mktemp("fuzz_frames")
        rng = np.random.default_rng(0)
        for i in range(2):
            for e in ("left", "right"):
                ch = {c: rng.random((6, 8)).astype(np.float32) for c in ("R", "G", "B", "N.X", "N.Y", "N.Z")}
                ch["Z"] = (1 + rng.random((6, 8))).astype(np.float32)
                if i:
                    ch.update({"M.X": np.zeros((6, 8), np.float32), "M.Y": np.zeros((6, 8), np.float32)})
                write_exr(d / f"{i:04d}_{e}.exr", ch)
        cam = {"K": [[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]], "cam_from_world": np.eye(4).tolist()}
        (d / "cameras.json").write_text(
            json.dumps(
                {
                    "frames": [{"left": cam, "right": cam}] * 2,
                    "reprojection": {"position_threshold": 0.1, "normal_threshold": 0.25},
                }
            )
        )
        return d

    @staticmethod
    def mutations():
        edit = st.tuples(st.floats(0, 1), st.integers(0, 255), st.integers(1, 16))
        return st.tuples(st.lists(edit, max_size=6), st.one_of(st.none(), st.floats(0, 1)))

    @staticmethod
    def mutate(data: bytes, mutation) -> bytes:
        edits, cut = mutation
        out = bytearray(data)
        for where, value, length in edits:
            at = int(where * (len(out) - 1))
            out[at : at + length] = bytes([value]) * len(out[at : at + length])
        return bytes(out[: int(cut * len(out))] if cut is not None else out)

    def test_read_exr_threads(self, sequence, tmp_path_factory, capfd):
        import contextlib
        import sys
        from concurrent.futures import ThreadPoolExecutor

        from stereorepro.io.exr import exr_header, read_exr

        original = (sequence / "0001_right.exr").read_bytes()
        folder = tmp_path_factory.mktemp("fuzz_exr")
        streams = (sys.stdout, sys.stderr, os.fstat(1).st_ino, os.fstat(2).st_ino)

        def read(path):
            try:
                ch = read_exr(path)
            except ValueError as e:
                assert str(path) in str(e)
                return "refused"
            assert all(
                v.dtype == np.float32 and v.ndim == 2 and v.shape == next(iter(ch.values())).shape for v in ch.values()
            )
            with contextlib.suppress(ValueError):
                exr_header(path)
            return "read"

        @self._settings()
        @given(st.lists(self.mutations(), min_size=4, max_size=4))
        def check(mutations):
            paths = []
            for i, m in enumerate(mutations):
                paths.append(folder / f"{i}.exr")
                paths[-1].write_bytes(self.mutate(original, m))
            with ThreadPoolExecutor(4) as ex:
                list(ex.map(read, paths))
            assert (sys.stdout, sys.stderr, os.fstat(1).st_ino, os.fstat(2).st_ino) == streams

        check()
        assert capfd.readouterr() == ("", "")  # OpenEXR's messages were folded into the errors, never printed

    def test_read_frame(self, sequence, tmp_path_factory, capfd):
        import shutil

        from stereorepro.errors import SequenceError
        from stereorepro.io.frames import Frame, load_sequence, read_frame

        work = tmp_path_factory.mktemp("fuzz_seq") / "in"
        shutil.copytree(sequence, work)
        original = (sequence / "0001_left.exr").read_bytes()

        @self._settings()
        @given(self.mutations())
        def check(mutation):
            (work / "0001_left.exr").write_bytes(self.mutate(original, mutation))
            try:
                seq = load_sequence(work)
                frames = [read_frame(seq, i, e) for i in range(2) for e in ("left", "right")]
            except SequenceError as e:
                assert "0001_left.exr" in str(e)
                return
            assert all(isinstance(f, Frame) and f.color.shape == (1, 3, 6, 8) for f in frames)

        check()
        assert capfd.readouterr() == ("", "")
