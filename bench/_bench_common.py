"""Shared benchmark plumbing: machine/commit record, timing (median after warm-up), atomic JSON + markdown."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import torch

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "platform": platform.platform(),
    }


def commit() -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def header() -> dict:
    return {
        "machine": machine(),
        "commit": commit(),
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


def time_ms(fn, repeats: int = 7, warmup: int = 2) -> dict:
    """Median (and min/max) wall time of ``fn()`` in ms over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return {"median_ms": statistics.median(ts), "min_ms": min(ts), "max_ms": max(ts), "repeats": repeats}


def time_interleaved(fns: dict, repeats: int = 7, warmup: int = 2, sync=None) -> dict:
    """Like :func:`time_ms` for several callables, timed round-robin (one call of each per round), so that every
    one sees the same machine state and cache pressure: name -> {median_ms, min_ms, max_ms, repeats}.

    ``sync``: called before and after every timed call (e.g. ``torch.cuda.synchronize``, so that a call's time is
    its own kernels, not the queue before it)."""
    ts = time_rounds(fns, repeats, warmup, sync)
    return {
        name: {"median_ms": statistics.median(v), "min_ms": min(v), "max_ms": max(v), "repeats": repeats}
        for name, v in ts.items()
    }


def paired_ratio(fn_a, fn_b, repeats: int = 7, warmup: int = 2) -> dict:
    """Time ``fn_a`` and ``fn_b`` in alternation and return the ratio b / a of each round (the two calls back to
    back see the same load): {median, min, max, q1, q3, rounds, a_median_ms, b_median_ms}. A ratio of medians
    of separately timed groups moves with the load between the groups; this one only with the load within a
    round."""
    ts = time_rounds({"a": fn_a, "b": fn_b}, repeats, warmup)
    r = sorted(b / a for a, b in zip(ts["a"], ts["b"]))
    q = statistics.quantiles(r, n=4) if len(r) > 1 else [r[0]] * 3
    return {
        "median": statistics.median(r),
        "min": r[0],
        "max": r[-1],
        "q1": q[0],
        "q3": q[2],
        "rounds": repeats,
        "a_median_ms": statistics.median(ts["a"]),
        "b_median_ms": statistics.median(ts["b"]),
    }


def time_rounds(fns: dict, repeats: int = 7, warmup: int = 2, sync=None) -> dict:
    """The round-robin of :func:`time_interleaved`: name -> the ``repeats`` times in ms, in round order."""
    sync = sync or (lambda: None)
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    sync()
    ts = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            sync()
            t0 = time.perf_counter()
            fn()
            sync()
            ts[name].append((time.perf_counter() - t0) * 1e3)
    return ts


def floor_bytes(px: int) -> dict[str, int]:
    """Bytes the reprojection ops must read + write for ``px`` destination pixels: float32 images, bool valid,
    uint8 reason; ``... fp16``: float16 colour, normals and history length (the colour output float16 too), depths
    and the output history length float32."""
    return {
        "stereo": px * 4 * (3 + 1 + 3 + 1 + 3 + 3) + px * 2,
        "temporal": px * 4 * (3 + 1 + 3 + 1 + 3 + 3 + 1 + 3 + 1) + px * 1,
        "stereo fp16": px * 2 * (3 + 3 + 3 + 3) + px * 4 * 2 + px * 2,
        "temporal fp16": px * 2 * (3 + 3 + 3 + 3 + 1 + 3) + px * 4 * (1 + 1 + 1) + px * 1,
    }


def copy_floor(n_bytes: int, device="cpu"):
    """A copy of ``n_bytes`` on ``device`` (the bytes an op must read and write), as a callable to time."""
    import torch

    src = torch.empty(n_bytes // 4, dtype=torch.float32, device=device).uniform_()
    dst = torch.empty_like(src)
    return lambda: dst.copy_(src)


def _status_bytes(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise OSError(f"{key} not in /proc/self/status")


def peak_rss_delta(fn) -> int:
    """Bytes by which the process's peak resident set rises above its current one while ``fn()`` runs (Linux:
    the peak is reset through ``/proc/self/clear_refs``, then read as ``VmHWM``). Call it on a fresh process's
    first call of ``fn`` (inputs built, session created): later calls reuse what allocators kept. Free heap
    pages that glibc keeps resident (left by building the inputs) are returned first (``malloc_trim``), so that
    reusing them counts."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: the measure may undercount reused heap pages
        pass
    base = _status_bytes("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
    out = fn()
    peak = _status_bytes("VmHWM") - base
    del out
    return peak


def write_atomic(path: Path, text: str) -> None:
    from stereorepro.io.atomic import atomic_write  # the package's one atomic write

    atomic_write(path, text)


def save(name: str, record: dict, table_md: str, script: str | None = None) -> tuple[Path, Path]:
    """Write bench/results/<name>.json and .md (the markdown names ``script``, default ``<name>.py``)."""
    j = RESULTS / f"{name}.json"
    m = RESULTS / f"{name}.md"
    write_atomic(j, json.dumps(record, indent=2) + "\n")
    h = record["machine"]
    md = (
        f"<!-- generated by bench/{script or name + '.py'} -->\n"
        f"Machine: {h['cpu']}, {h['cores']} cores, torch {h['torch']} ({h['torch_threads']} threads); "
        f"commit `{record['commit']}`; {record['date']}.\n\n" + table_md
    )
    write_atomic(m, md)
    return j, m
