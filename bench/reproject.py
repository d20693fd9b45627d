"""Reprojection speed at 1280×720: torch eager, native (when built; also on float16 colour and normals),
onnxruntime (the exported graph export_onnx writes, and the traced general path for comparison), kornia's bare
warp, and the copy floor, on the same realistic inputs, in one run; and each implementation's peak memory, measured
in a fresh process. Temporal reprojection runs camera-only and with motion vectors (``backend="auto"`` too, paired
against native camera-only, and checked byte for byte against the torch general path). Writes
bench/results/<name>.{json,md} (``--name``, default reproject), with the command that made them.

    python bench/reproject.py [--height 720 --width 1280 --repeats 7] [--no-onnx] [--no-memory]
                              [--cases temporal "temporal + motion vectors"] [--name reproject_temporal]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import (
    copy_floor,
    floor_bytes,
    header,
    paired_ratio,
    peak_rss_delta,
    save,  # noqa: E402
    time_interleaved,
)

from stereorepro import StereoReprojection, TemporalReprojection, export_onnx  # noqa: E402
from stereorepro._testing import example_inputs  # noqa: E402
from stereorepro.reproject import functional  # noqa: E402

#: (row label, module class, module keywords, head motion, floor). "stereo" is the paper's same-instant case (a
#: parallel rig, whose epipolar lines are rows); "stereo (rectified)" the same pair declared rectified
#: (StereoReprojection(rectified=True): two taps per pixel on every backend and in the exported graph); "stereo +
#: head motion" warps between eyes of different instants (the general case, as temporal reprojection does). The
#: stereo rows read and write the same bytes.
CASES = (
    ("stereo", StereoReprojection, {}, False, "stereo"),
    ("stereo (rectified)", StereoReprojection, {"rectified": True}, False, "stereo"),
    ("stereo + head motion", StereoReprojection, {}, True, "stereo"),
    ("temporal", TemporalReprojection, {}, True, "temporal"),
    ("temporal + motion vectors", TemporalReprojection, {"motion_vectors": True}, True, "temporal"),
)

#: The motion-vector case (example_inputs: the cameras' own motion vectors, zero world motion): timed with
#: backend="auto" as well, which must pick the native kernels.
MOTION_CASE = "temporal + motion vectors"
THRESHOLDS = dict(position_threshold=0.05, normal_threshold=0.3)

#: The paired timings: (record key, implementation a, implementation b (the ratio is b / a), table title, column
#: names of a and b).
PAIRED = (
    (
        "paired_onnxruntime_torch",
        "torch eager",
        "onnxruntime",
        "onnxruntime / torch eager, paired (the two called in alternation, {n} rounds after warm-up; the ratio of "
        "each round):",
        "torch eager",
        "onnxruntime",
    ),
    (
        "paired_native_fp16_fp32",
        "native eager",
        "native fp16",
        "native float16 / native float32, paired ({n} rounds, as above):",
        "native fp32",
        "native fp16",
    ),
)


def ort_session(module, path, lean: bool = True):
    """An onnxruntime session of ``module`` exported to ``path`` (``lean``: the export formulation, as
    export_onnx writes it; else the traced general path)."""
    import onnxruntime as ort

    saved = functional.EXPORT_LEAN
    functional.EXPORT_LEAN = lean
    try:
        path = export_onnx(module, path)
    finally:
        functional.EXPORT_LEAN = saved
    so = ort.SessionOptions()
    so.intra_op_num_threads = torch.get_num_threads()
    # onnxruntime's default spin-waiting between the graph's nodes (faster than none), stopped when a run ends
    # (spinning threads would take the cores from the calls timed next)
    so.add_session_config_entry("session.intra_op.allow_spinning", "1")
    so.add_session_config_entry("session.force_spinning_stop", "1")
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def memory_child(case: str, impl: str, H: int, W: int) -> dict:
    """In this (fresh) process: the peak resident memory one call of ``impl`` on ``case`` adds, the inputs built
    and the session created first (bench/_bench_common.peak_rss_delta); the bytes of its inputs and outputs."""
    name, cls, kw, motion, _ = next(c for c in CASES if c[0] == case)
    m = cls(**THRESHOLDS, **kw, backend="native" if impl == "native" else "torch")
    inp = example_inputs(m, batch=1, height=H, width=W, head_motion=motion)
    if impl == "onnxruntime":
        tmp = tempfile.TemporaryDirectory()
        sess = ort_session(m, Path(tmp.name) / "m.onnx")
        feed = {n: x.numpy() for n, x in zip(m.input_names, inp)}

        def call():
            return sess.run(None, feed)
    else:

        def call():
            with torch.inference_mode():
                return m(*inp)

    peak = peak_rss_delta(call)  # the first call: later ones reuse what the allocators kept
    out = call()
    nbytes = (lambda x: x.nbytes) if impl == "onnxruntime" else (lambda x: x.numel() * x.element_size())
    return {
        "case": case,
        "impl": impl,
        "peak_bytes": peak,
        "input_bytes": sum(x.numel() * x.element_size() for x in inp),
        "output_bytes": sum(nbytes(o) for o in out),
    }


def memory_rows(H: int, W: int, impls, cases=CASES) -> list[dict]:
    """:func:`memory_child` for every case and implementation, each in a fresh interpreter."""
    rows = []
    for case, *_ in cases:
        for impl in impls:
            res = subprocess.run(
                [sys.executable, __file__, "--memory-child", case, impl, "--height", str(H), "--width", str(W)],
                capture_output=True,
                text=True,
                check=True,
            )
            r = json.loads(res.stdout.strip().splitlines()[-1])
            io = r["input_bytes"] + r["output_bytes"]
            rows.append(
                {**r, "x_inputs_outputs": r["peak_bytes"] / io, "x_outputs": r["peak_bytes"] / r["output_bytes"]}
            )
    return rows


#: The images a real-time engine keeps in float16 (RGBA16F colour, normals, history length); depths stay float32.
HALF_INPUTS = {
    "src_color",
    "src_normal",
    "dst_normal",
    "current_color",
    "normal",
    "history_color",
    "history_len",
    "prev_normal",
}


def motion_check(fns: dict, cases, H: int, W: int, repeats: int) -> dict | None:
    """Temporal with motion vectors on ``backend="auto"`` against native camera-only, paired (the done-when ratio
    of motion on the fast paths), which backend auto ran, and whether its outputs equal the torch general path's
    (the reference: fast path off) byte for byte on the same inputs."""
    a, b = ("temporal", "native eager"), (MOTION_CASE, "auto eager")
    if not ({"temporal", MOTION_CASE} <= {c[0] for c in cases} and a in fns and b in fns):
        return None
    from stereorepro.reproject import _native

    ran = []
    saved_kernel = _native.temporal_reproject

    def spy(*args, **kwargs):
        ran.append("native")
        return saved_kernel(*args, **kwargs)

    m = TemporalReprojection(**THRESHOLDS, motion_vectors=True, backend="auto")
    inp = example_inputs(m, batch=1, height=H, width=W, head_motion=True)
    _native.temporal_reproject = spy
    try:
        with torch.inference_mode():
            got = m(*inp)
    finally:
        _native.temporal_reproject = saved_kernel
    functional.FAST_PATH, saved_fast = False, functional.FAST_PATH
    try:
        with torch.inference_mode():
            ref = TemporalReprojection(**THRESHOLDS, motion_vectors=True, backend="torch")(*inp)
    finally:
        functional.FAST_PATH = saved_fast
    same = all(
        g.dtype == r.dtype
        and torch.equal(g.contiguous().view(-1).view(torch.uint8), r.contiguous().view(-1).view(torch.uint8))
        for g, r in zip(got, ref)
    )
    with torch.inference_mode():
        res = paired_ratio(fns[a], fns[b], repeats)
    return {**res, "auto_ran": ran[0] if ran else "torch", "identical_to_torch_general": same}


def module_backends(cls, **kw):
    """(label, module) for each backend the module supports here (with motion vectors also ``auto``)."""
    out = []
    try:
        out.append(("torch", cls(**kw, backend="torch")))
        from stereorepro.reproject import _native as native

        if native.available():
            out.append(("native", cls(**kw, backend="native")))
        if kw.get("motion_vectors"):
            out.append(("auto", cls(**kw, backend="auto")))
    except TypeError:  # modules without a backend argument
        out.append(("torch", cls(**kw)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument(
        "--paired-repeats", type=int, default=21, help="rounds of the paired onnxruntime / torch eager timing"
    )
    ap.add_argument("--no-onnx", action="store_true")
    ap.add_argument("--no-memory", action="store_true")
    ap.add_argument(
        "--cases",
        nargs="+",
        choices=[c[0] for c in CASES],
        metavar="CASE",
        help=f"run only these rows (of {', '.join(repr(c[0]) for c in CASES)})",
    )
    ap.add_argument("--name", default="reproject", help="results file name: bench/results/NAME.{json,md}")
    ap.add_argument("--memory-child", nargs=2, metavar=("CASE", "IMPL"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    H, W, R = args.height, args.width, args.repeats
    if args.memory_child:
        print(json.dumps(memory_child(*args.memory_child, H, W)))
        return 0
    px = H * W
    nbytes = floor_bytes(px)  # float32, and float16 colour, normals and history length (HALF_INPUTS)
    cases = CASES if not args.cases else tuple(c for c in CASES if c[0] in args.cases)
    fns = {
        (op, "copy floor" + suffix): copy_floor(nbytes[op + suffix])
        for op in ("stereo", "temporal")
        for suffix in ("", " fp16")
    }
    floor_of = {}
    tmp = tempfile.TemporaryDirectory()
    for name, cls, kw, motion, floor in cases:
        floor_of[name] = floor
        for label, m in module_backends(cls, **THRESHOLDS, **kw):
            inp = example_inputs(m, batch=1, height=H, width=W, head_motion=motion)
            fns[(name, f"{label} eager")] = lambda m=m, inp=inp: m(*inp)
            if label == "native":
                half = tuple(x.half() if n in HALF_INPUTS else x for n, x in zip(m.input_names, inp))
                fns[(name, "native fp16")] = lambda m=m, inp=half: m(*inp)
        if not args.no_onnx:
            try:
                m = cls(**THRESHOLDS, **kw)
                inp = example_inputs(m, batch=1, height=H, width=W, head_motion=motion)
                feed = {n: x.numpy() for n, x in zip(m.input_names, inp)}
                for label, lean in (("onnxruntime", True), ("onnxruntime, general graph", False)):
                    sess = ort_session(m, Path(tmp.name) / f"{name}-{lean}.onnx", lean)
                    fns[(name, label)] = lambda sess=sess, feed=feed: sess.run(None, feed)
            except ImportError:
                pass
        if cls is StereoReprojection and not kw:
            try:
                from kornia.geometry.depth import warp_frame_depth

                m = StereoReprojection(0.05, 0.3)
                inp = dict(zip(m.input_names, example_inputs(m, batch=1, height=H, width=W, head_motion=motion)))
                src_from_dst = inp["src_cam_from_world"] @ torch.linalg.inv(inp["dst_cam_from_world"])
                depth = torch.where(torch.isfinite(inp["dst_depth"]), inp["dst_depth"], torch.ones(()))
                fns[(name, "kornia warp_frame_depth (warp only)")] = (
                    lambda c=inp["src_color"], d=depth, T=src_from_dst, K=inp["dst_K"]: warp_frame_depth(c, d, T, K)
                )
            except ImportError:
                pass
    # Each implementation is timed round-robin with the two copy floors (one call of each per round), so that the
    # floor sees the same cache pressure as the op (timed back to back on its own, part of it stays in the 32 MB L3
    # and it reads ~1.7x faster). Implementations are not interleaved with each other: torch's and _core's OpenMP
    # runtimes (and onnxruntime's pool) keep their threads spinning for a while after a call, which takes the cores
    # from whatever runs next in the same process.
    # native fp16 is timed with the floors of its own bytes ("copy floor fp16").
    floor_labels = ("copy floor", "copy floor fp16")
    impls = sorted({impl for (_, impl) in fns if impl not in floor_labels})
    rows, floor_rows = [], {}
    with torch.inference_mode():
        for impl in impls:
            fl = floor_labels[1] if impl.endswith("fp16") else floor_labels[0]
            floor_keys = [("stereo", fl), ("temporal", fl)]
            group = {k: fns[k] for k in floor_keys}
            group.update({k: f for k, f in fns.items() if k[1] == impl})
            times = time_interleaved(group, R)
            floors = {"stereo": times[floor_keys[0]], "temporal": times[floor_keys[1]]}
            floor_rows[impl] = floors
            for (op, i), t in times.items():
                if i == impl:
                    rows.append(
                        {
                            "op": op,
                            "impl": impl,
                            **t,
                            "x_floor": t["median_ms"] / floors[floor_of[op]]["median_ms"],
                            "floor_median_ms": floors[floor_of[op]]["median_ms"],
                        }
                    )
    tmp.cleanup()
    order = {name: i for i, (name, *_) in enumerate(cases)}
    rows.sort(key=lambda r: (order[r["op"]], impls.index(r["impl"])))
    ref = floor_rows.get("native eager") or next(iter(floor_rows.values()))
    out_rows = []
    for name, *_ in cases:
        out_rows += [r for r in rows if r["op"] == name]
        f = ref[floor_of[name]]
        out_rows.append({"op": name, "impl": "copy floor (timed with native)", **f, "x_floor": 1.0})
        if "native fp16" in floor_rows:
            f = floor_rows["native fp16"][floor_of[name]]
            out_rows.append({"op": name, "impl": "copy floor fp16 (timed with native fp16)", **f, "x_floor": 1.0})
    rows = out_rows
    for r in rows:  # ratio to torch eager on the same op, in this run
        t = next((x["median_ms"] for x in rows if x["op"] == r["op"] and x["impl"] == "torch eager"), None)
        r["x_torch_eager"] = r["median_ms"] / t if t else None
    # onnxruntime against torch eager, paired: the two called in alternation, the ratio taken per round (the groups
    # above are timed one after the other, so their ratio also carries the change of load between groups). Both
    # run ~60-120 ms, against which the other's spinning threads (< 1 ms) do not count. Native float16 against
    # native float32 the same way (both ~5-15 ms: the copy floors' bytes halve, the gathers and the arithmetic do
    # not).
    paired = {key: [] for key, *_ in PAIRED}
    with torch.inference_mode():
        for key, impl_a, impl_b, *_ in PAIRED:
            for name, *_ in cases:
                if (name, impl_a) in fns and (name, impl_b) in fns:
                    paired[key].append(
                        {"op": name, **paired_ratio(fns[(name, impl_a)], fns[(name, impl_b)], args.paired_repeats)}
                    )
    motion = motion_check(fns, cases, H, W, args.paired_repeats)
    mem = (
        []
        if args.no_memory
        else memory_rows(H, W, ["torch", "native", "onnxruntime"] if not args.no_onnx else ["torch", "native"], cases)
    )
    command = "python bench/reproject.py" + "".join(
        f" {a}" if a.startswith("-") or " " not in a else f' "{a}"'
        for a in (argv if argv is not None else sys.argv[1:])
    )
    record = {
        **header(),
        "command": command,
        "resolution": f"{W}x{H}",
        "rows": rows,
        **paired,
        "motion_vs_camera": motion,
        "memory": mem,
        "floor_bytes": nbytes,
    }
    lines = [
        "| op | implementation | median ms | min ms | × copy floor | × torch eager |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        xt = "" if r["x_torch_eager"] is None else f"{r['x_torch_eager']:.2f}"
        lines.append(
            f"| {r['op']} | {r['impl']} | {r['median_ms']:.1f} | {r['min_ms']:.1f} | {r['x_floor']:.1f} | {xt} |"
        )
    for key, _, _, title, col_a, col_b in PAIRED:
        if paired[key]:
            lines += [
                "",
                title.format(n=args.paired_repeats),
                "",
                f"| op | median | quartiles | min – max | {col_a} ms | {col_b} ms |",
                "|---|---:|---:|---:|---:|---:|",
            ]
            lines += [
                f"| {r['op']} | **{r['median']:.2f}** | {r['q1']:.2f} – {r['q3']:.2f} | {r['min']:.2f} – "
                f"{r['max']:.2f} | {r['a_median_ms']:.1f} | {r['b_median_ms']:.1f} |"
                for r in paired[key]
            ]
    if motion:
        lines += [
            "",
            'Temporal with motion vectors, backend="auto" / native camera-only, paired '
            f"({args.paired_repeats} rounds, as above), and auto's outputs against the torch general path's on "
            "the same inputs:",
            "",
            "| median | quartiles | min – max | native camera-only ms | auto with motion ms | byte-identical |",
            "|---:|---:|---:|---:|---:|---|",
            f"| **{motion['median']:.2f}** | {motion['q1']:.2f} – {motion['q3']:.2f} | {motion['min']:.2f} – "
            f"{motion['max']:.2f} | {motion['a_median_ms']:.1f} | {motion['b_median_ms']:.1f} | "
            f"{motion['identical_to_torch_general']} (auto ran {motion['auto_ran']}) |",
        ]
    if mem:
        lines += [
            "",
            "Peak memory of one call (the first, in a fresh process, inputs built and session created: the "
            "rise of VmHWM over VmRSS), against the bytes of its inputs and outputs:",
            "",
            "| op | implementation | peak MiB | inputs + outputs MiB | × inputs + outputs | × outputs |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for r in mem:
            io = (r["input_bytes"] + r["output_bytes"]) / 2**20
            lines.append(
                f"| {r['case']} | {r['impl']} | {r['peak_bytes'] / 2**20:.1f} | {io:.1f} "
                f"| {r['x_inputs_outputs']:.2f} | {r['x_outputs']:.2f} |"
            )
    table = (
        (
            f"`{command}`\n\n"
            f"Reprojection at {W}×{H}, B=1, float32 (native fp16: colour, normals and history length float16, "
            f"depths float32), median of {R} after warm-up; each implementation timed round-robin with the copy "
            f"floors (one call each per round), × copy floor against the floor of its own run (native fp16: the "
            f"floor of the bytes it reads and writes).\n\n"
        )
        + "\n".join(lines)
        + "\n"
    )
    j, md = save(args.name, record, table, script="reproject.py")
    print(table)
    print(f"wrote {j} and {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
