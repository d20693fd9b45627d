"""The prepared GPU check: the CUDA tests, then the reprojection ops' speed on the GPU against its copy
floor (and onnxruntime's CUDAExecutionProvider when onnxruntime-gpu is installed), within a time budget.
Writes bench/results/gpu.{json,md}.

    bash bench/gpu.sh                                    # the whole check, <= 5 minutes
    python bench/gpu.py --device cpu --sizes 720p        # dry run of the code path on the CPU (writes nothing)

Without a CUDA device it says so and exits 0 without writing anything. It installs nothing.

Rows per size (1280x720, 1920x1080, 3840x2160; B = 1, float32, the realistic inputs of
:func:`stereorepro._testing.example_inputs`): "stereo" (a parallel rig, same instant: ``head_motion=False``),
"stereo + head motion" and "temporal" (head motion), each as torch eager (``backend="torch"``, inference mode) and
onnxruntime, against a device-to-device copy of the bytes the op reads and writes (bench/reproject.py's floor,
on the device). Times are medians after warm-up, the device synchronised before and after each call, every
implementation timed round-robin with its floor.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_common  # noqa: E402
from _bench_common import copy_floor, floor_bytes, header, save, time_interleaved  # noqa: E402

from stereorepro import StereoReprojection, TemporalReprojection, export_onnx  # noqa: E402
from stereorepro._testing import example_inputs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZES = {"720p": (1280, 720), "1080p": (1920, 1080), "2160p": (3840, 2160)}
THRESHOLDS = dict(position_threshold=0.05, normal_threshold=0.3)  # bench/reproject.py's


def parse_size(s: str) -> tuple[str, int, int]:
    """``720p`` / ``1080p`` / ``2160p`` or ``WxH``: (label, width, height)."""
    if s in SIZES:
        return (s, *SIZES[s])
    m = re.fullmatch(r"(\d+)x(\d+)", s)
    if not m or int(m[1]) < 1 or int(m[2]) < 1:
        raise argparse.ArgumentTypeError(f"size must be one of {', '.join(SIZES)} or WxH, got {s!r}")
    return (s, int(m[1]), int(m[2]))


def no_cuda_reason() -> str | None:
    """Why there is no usable CUDA device, or None."""
    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    if not torch.cuda.is_available():
        return f"torch {torch.__version__} (CUDA {torch.version.cuda}) finds no CUDA device"
    return None


def gpu_info() -> dict:
    p = torch.cuda.get_device_properties(0)
    info = {
        "name": p.name,
        "memory_gib": round(p.total_memory / 2**30, 1),
        "capability": f"{p.major}.{p.minor}",
        "count": torch.cuda.device_count(),
        "torch_cuda": torch.version.cuda,
    }
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        )
        info["driver"] = out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else None
    except (OSError, subprocess.TimeoutExpired):
        info["driver"] = None
    return info


# --------------------------------------------------------------------------------------------------- tests
def run_tests(timeout_s: float) -> dict:
    """The CUDA tests: every test parametrised on the ``device`` fixture's cuda value, and the named cuda tests
    (``pytest -k cuda``), fast suite only."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-k", "cuda", "-m", "not slow", "-p", "no:cacheprovider"]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=max(1.0, timeout_s))
        out, rc, timed_out = proc.stdout + proc.stderr, proc.returncode, False
    except subprocess.TimeoutExpired as e:
        out = (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        rc, timed_out = None, True
    lines = [ln for ln in out.strip().splitlines() if ln.strip()]
    summary = lines[-1] if lines else ""
    counts = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", summary)}
    ok = rc == 0 or rc == 5 and not counts.get("failed")  # 5: nothing selected (no cuda-parametrised tests)
    return {
        "command": shlex.join(["python", *cmd[1:]]),
        "returncode": rc,
        "timed_out": timed_out,
        "ok": bool(ok and not timed_out),
        "summary": summary,
        "counts": counts,
        "seconds": time.perf_counter() - t0,
        "failures": [ln for ln in lines if ln.startswith(("FAILED", "ERROR"))][:20],
    }


# --------------------------------------------------------------------------------------------------- timing
def case_inputs(width: int, height: int) -> dict:
    """Inputs of the three rows (CPU): the stereo modules' and the temporal module's, from two raycasts."""
    st_names, tp_names = StereoReprojection.input_names, TemporalReprojection.input_names
    both = SimpleNamespace(input_names=st_names + tp_names)  # one call: both ops see the same cameras and scene
    moving = example_inputs(both, height=height, width=width, head_motion=True)
    parallel = example_inputs(StereoReprojection(**THRESHOLDS), height=height, width=width, head_motion=False)
    return {"stereo": parallel, "stereo + head motion": moving[: len(st_names)], "temporal": moving[len(st_names) :]}


class OrtRunner:
    """One onnxruntime session per op class on ``provider``, inputs and outputs bound on the device (IO binding:
    no host copies inside the timed call)."""

    def __init__(self, device: torch.device, tmp: Path):
        import onnxruntime as ort

        self.ort, self.device = ort, device
        self.provider = "CUDAExecutionProvider" if device.type == "cuda" else "CPUExecutionProvider"
        self.version = ort.__version__
        if self.provider not in ort.get_available_providers():
            raise RuntimeError(
                f"onnxruntime {ort.__version__} has no {self.provider} (available: "
                f"{', '.join(ort.get_available_providers())}); install onnxruntime-gpu for it"
            )
        self.sessions = {}
        for cls in (StereoReprojection, TemporalReprojection):
            path = export_onnx(cls(**THRESHOLDS, backend="torch"), tmp / f"{cls.__name__}.onnx")
            so = ort.SessionOptions()
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
            sess = ort.InferenceSession(str(path), so, providers=[self.provider, "CPUExecutionProvider"])
            if sess.get_providers()[0] != self.provider:
                raise RuntimeError(
                    f"onnxruntime fell back to {sess.get_providers()} (the {self.provider} "
                    f"did not load: CUDA/cuDNN libraries?)"
                )
            self.sessions[cls] = sess

    def bind(self, cls, inputs: tuple):
        """A callable running ``cls``'s session on ``inputs`` (bound once), and a getter of its outputs (numpy)."""
        sess = self.sessions[cls]
        kind, dev_id = ("cuda", self.device.index or 0) if self.device.type == "cuda" else ("cpu", 0)
        binding = sess.io_binding()
        keep = []
        for name, x in zip(cls.input_names, inputs):
            v = self.ort.OrtValue.ortvalue_from_numpy(x.detach().cpu().contiguous().numpy(), kind, dev_id)
            keep.append(v)
            binding.bind_ortvalue_input(name, v)
        for o in sess.get_outputs():
            binding.bind_output(o.name, kind, dev_id)

        def run():
            sess.run_with_iobinding(binding)
            _ = keep  # the bound input values live as long as the binding

        return run, lambda: binding.copy_outputs_to_cpu()


def compare(cls, ref: tuple, got: list) -> dict:
    """onnxruntime's outputs against torch's: max |colour difference| where both kept a pixel, mask mismatches."""
    names = list(cls.output_names)
    vr = ref[names.index("valid")].cpu()
    vg = torch.from_numpy(got[names.index("valid")])
    both = (vr & vg).expand_as(ref[0].cpu())
    diff = (ref[0].cpu().double() - torch.from_numpy(got[0]).double()).abs()[both]
    return {
        "max_abs_diff_color": float(diff.max()) if diff.numel() else 0.0,
        "valid_mismatch_pixels": int((vr != vg).sum()),
    }


def bench_size(label: str, W: int, H: int, device: torch.device, args, ort_runner) -> tuple[list, dict]:
    px = W * H
    nbytes = floor_bytes(px)
    mods = {
        "stereo": StereoReprojection(**THRESHOLDS, backend="torch"),
        "stereo + head motion": StereoReprojection(**THRESHOLDS, backend="torch"),
        "temporal": TemporalReprojection(**THRESHOLDS, backend="torch"),
    }
    t0 = time.perf_counter()
    cpu_inputs = case_inputs(W, H)
    t_inputs = time.perf_counter() - t0
    inputs = {k: tuple(x.to(device) for x in v) for k, v in cpu_inputs.items()}
    floors = {"stereo": copy_floor(nbytes["stereo"], device), "temporal": copy_floor(nbytes["temporal"], device)}
    floor_of = {"stereo": "stereo", "stereo + head motion": "stereo", "temporal": "temporal"}
    impls = {"torch eager": {op: (lambda m=mods[op].to(device), x=inputs[op]: m(*x)) for op in mods}}
    checks = {}
    if ort_runner is not None:
        impls[f"onnxruntime {ort_runner.provider.replace('ExecutionProvider', '')}"] = runs = {}
        for op, m in mods.items():
            run, outputs = ort_runner.bind(type(m), cpu_inputs[op])
            runs[op] = run
            checks[op] = (run, outputs)
    rows = []
    with torch.inference_mode():
        for impl, fns in impls.items():
            group = {("floor", k): f for k, f in floors.items()}
            group.update({("op", op): f for op, f in fns.items()})
            times = time_interleaved(
                group, args.repeats, args.warmup, torch.cuda.synchronize if device.type == "cuda" else None
            )
            for op in fns:
                t, fl = times[("op", op)], times[("floor", floor_of[op])]
                rows.append(
                    {
                        "size": label,
                        "resolution": f"{W}x{H}",
                        "op": op,
                        "impl": impl,
                        **t,
                        "floor_median_ms": fl["median_ms"],
                        "x_floor": t["median_ms"] / fl["median_ms"],
                    }
                )
            for k in floors:
                rows.append(
                    {
                        "size": label,
                        "resolution": f"{W}x{H}",
                        "op": k,
                        "impl": f"copy floor (with {impl})",
                        **times[("floor", k)],
                        "x_floor": 1.0,
                        "bytes": nbytes[k],
                    }
                )
        agreement = {}
        for op, (run, outputs) in checks.items():
            run()
            agreement[op] = compare(type(mods[op]), mods[op](*inputs[op]), outputs())
    del inputs, floors, impls, checks
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return rows, {"inputs_seconds": t_inputs, "onnxruntime_vs_torch": agreement}


def table(rows: list, order: list) -> str:
    lines = ["| size | op | implementation | median ms | min ms | × copy floor |", "|---|---|---|---:|---:|---:|"]
    op_rank = {"stereo": 0, "stereo + head motion": 1, "temporal": 2}
    for size in order:
        rs = sorted((r for r in rows if r["size"] == size), key=lambda r: (op_rank[r["op"]], "floor" in r["impl"]))
        for r in rs:
            lines.append(
                f"| {r['resolution']} | {r['op']} | {r['impl']} | {r['median_ms']:.2f} | {r['min_ms']:.2f} | "
                f"{r['x_floor']:.1f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--device", choices=("cuda", "cpu"), default="cuda", help="cuda (the check) or cpu (a dry run of the code path)"
    )
    ap.add_argument("--sizes", default="720p,1080p,2160p", help="comma list of 720p, 1080p, 2160p or WxH")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument(
        "--budget-s",
        type=float,
        default=270.0,
        help="wall-clock budget of the whole run; sizes that would not fit are skipped (noted)",
    )
    ap.add_argument(
        "--tests",
        dest="tests",
        action="store_true",
        default=None,
        help="run the CUDA tests (default: on with --device cuda, off with --device cpu)",
    )
    ap.add_argument("--no-tests", dest="tests", action="store_false")
    ap.add_argument("--test-timeout-s", type=float, default=150.0)
    ap.add_argument("--no-onnx", action="store_true", help="skip onnxruntime")
    ap.add_argument(
        "--save",
        default=None,
        help="results name under the results folder (default: gpu with "
        "--device cuda; nothing is written by a cpu dry run unless this is given)",
    )
    ap.add_argument("--results-dir", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    try:
        sizes = [parse_size(s.strip()) for s in args.sizes.split(",") if s.strip()]
    except argparse.ArgumentTypeError as e:
        ap.error(str(e))
    if not sizes or args.repeats < 1 or args.warmup < 0:
        ap.error("need at least one size, --repeats >= 1 and --warmup >= 0")
    t_start = time.perf_counter()

    if args.device == "cuda":
        reason = no_cuda_reason()
        if reason:
            print(f"bench/gpu.py: no CUDA device ({reason}): nothing run, nothing written.")
            return 0
        device = torch.device("cuda", 0)
    else:
        device = torch.device("cpu")
    save_name = args.save if args.save is not None else ("gpu" if device.type == "cuda" else None)
    run_tests_now = args.tests if args.tests is not None else device.type == "cuda"
    notes = []
    if device.type == "cpu":
        notes.append("CPU dry run of the code path (--device cpu): not the GPU check")
    record = {
        **header(),
        "device": str(device),
        "gpu": gpu_info() if device.type == "cuda" else None,
        "sizes": [f"{w}x{h}" for _, w, h in sizes],
        "repeats": args.repeats,
        "warmup": args.warmup,
    }

    if run_tests_now:
        remaining = args.budget_s - (time.perf_counter() - t_start)
        print(
            f"CUDA tests: pytest -q -k cuda -m 'not slow' (timeout {min(args.test_timeout_s, remaining):.0f} s) ...",
            flush=True,
        )
        record["tests"] = tests = run_tests(min(args.test_timeout_s, remaining))
        print(
            f"  {tests['summary'] or '(no output)'}{' (TIMED OUT)' if tests['timed_out'] else ''} "
            f"in {tests['seconds']:.0f} s",
            flush=True,
        )
        for ln in tests["failures"]:
            print("  " + ln)
    else:
        record["tests"] = None

    ort_runner, tmp = None, tempfile.TemporaryDirectory()
    if args.no_onnx:
        notes.append("onnxruntime skipped (--no-onnx)")
    else:
        try:
            ort_runner = OrtRunner(device, Path(tmp.name))
            record["onnxruntime"] = {"version": ort_runner.version, "provider": ort_runner.provider}
        except ImportError:
            notes.append("onnxruntime is not importable: its rows are skipped")
        except RuntimeError as e:
            notes.append(f"onnxruntime skipped: {e}")
    for n in notes:
        print("note: " + n)

    rows, per_size, done, last = [], {}, [], None  # last: (seconds, pixels) of the previous size
    for label, W, H in sizes:
        elapsed = time.perf_counter() - t_start
        if last is not None:
            projected = last[0] * (W * H) / last[1]
            if elapsed + projected > args.budget_s:
                notes.append(
                    f"{label} ({W}x{H}) skipped: ~{projected:.0f} s projected, "
                    f"{args.budget_s - elapsed:.0f} s of the budget left"
                )
                print("note: " + notes[-1])
                continue
        t0 = time.perf_counter()
        print(f"{label} ({W}x{H}) ...", flush=True)
        try:
            r, info = bench_size(label, W, H, device, args, ort_runner)
        except torch.cuda.OutOfMemoryError as e:
            notes.append(f"{label}: out of device memory ({str(e).splitlines()[0]})")
            print("note: " + notes[-1])
            continue
        rows += r
        per_size[label] = {**info, "seconds": time.perf_counter() - t0}
        done.append(label)
        last = (time.perf_counter() - t0, W * H)
    tmp.cleanup()

    record.update(
        rows=rows,
        per_size=per_size,
        notes=notes,
        seconds=time.perf_counter() - t_start,
        floor_bytes={f"{w}x{h}": floor_bytes(w * h) for _, w, h in sizes},
    )
    dev = (
        f"{record['gpu']['name']} ({record['gpu']['memory_gib']} GiB, CUDA {record['gpu']['torch_cuda']}, "
        f"driver {record['gpu']['driver']})"
        if record["gpu"]
        else "CPU"
    )
    md = (
        f"Device: {dev}. B=1, float32, median of {args.repeats} after {args.warmup} warm-up rounds, the device "
        f"synchronised around every call; each implementation timed round-robin with the copy floors (a "
        f"device-to-device copy of the bytes the op reads and writes), × copy floor against its own run.\n\n"
    )
    md += table(rows, done)
    if record["tests"]:
        t = record["tests"]
        md += f"\nCUDA tests (`{t['command']}`): {t['summary']}{' — TIMED OUT' if t['timed_out'] else ''}\n"
    if record.get("onnxruntime"):
        agree = {s: v["onnxruntime_vs_torch"] for s, v in per_size.items()}
        worst = max((a["max_abs_diff_color"] for s in agree.values() for a in s.values()), default=0.0)
        mism = sum(a["valid_mismatch_pixels"] for s in agree.values() for a in s.values())
        md += (
            f"\nonnxruntime {record['onnxruntime']['version']} ({record['onnxruntime']['provider']}) vs torch "
            f"on the same inputs: max |colour difference| where both kept a pixel {worst:.2e}, valid-mask "
            f"mismatches {mism} pixels in all.\n"
        )
    if notes:
        md += "\n" + "\n".join(f"* {n}" for n in notes) + "\n"
    print()
    print(md)
    if save_name:
        if args.results_dir:
            _bench_common.RESULTS = Path(args.results_dir)
        j, m = save(save_name, record, md)
        print(f"wrote {j} and {m}")
    else:
        print("(dry run: nothing written; --save NAME writes bench/results/NAME.{json,md})")
    tests_ok = record["tests"] is None or record["tests"]["ok"]
    if not tests_ok:
        print("bench/gpu.py: the CUDA tests did not pass (see above)", file=sys.stderr)
    return 0 if tests_ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
