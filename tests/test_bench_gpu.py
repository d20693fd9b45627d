"""bench/gpu.sh and bench/gpu.py (the prepared GPU check) on a machine without a GPU: the no-device exit and the
CPU dry run of the code path."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"


def _stamp() -> dict:
    return {n: (RESULTS / n).stat().st_mtime_ns if (RESULTS / n).exists() else None for n in ("gpu.json", "gpu.md")}


def test_no_cuda_device_exits_cleanly_writing_nothing():
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present: this is the no-device path")
    before = _stamp()
    proc = subprocess.run(
        ["bash", str(ROOT / "bench" / "gpu.sh")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHON": sys.executable},
    )
    assert proc.returncode == 0, proc.stderr
    assert "no CUDA device" in proc.stdout and "nothing written" in proc.stdout
    assert _stamp() == before


@pytest.mark.onnx
def test_cpu_dry_run(tmp_path):
    """The timing, onnxruntime and save code paths on the CPU at a tiny size (the GPU run differs in the device)."""
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "gpu.py"),
            "--device",
            "cpu",
            "--sizes",
            "48x32",
            "--repeats",
            "2",
            "--warmup",
            "1",
            "--save",
            "gpu_test",
            "--results-dir",
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    rec = json.loads((tmp_path / "gpu_test.json").read_text())
    assert rec["device"] == "cpu" and rec["gpu"] is None and rec["tests"] is None
    ops = {(r["op"], r["impl"]) for r in rec["rows"]}
    for op in ("stereo", "stereo + head motion", "temporal"):
        assert (op, "torch eager") in ops and (op, "onnxruntime CPU") in ops
    assert all(r["median_ms"] > 0 for r in rec["rows"])
    agree = rec["per_size"]["48x32"]["onnxruntime_vs_torch"]
    assert all(a["valid_mismatch_pixels"] == 0 and a["max_abs_diff_color"] <= 1e-5 for a in agree.values())
    assert "| 48x32 | temporal | torch eager |" in (tmp_path / "gpu_test.md").read_text()


def test_bad_size_is_a_usage_error():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "gpu.py"), "--device", "cpu", "--sizes", "720"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "720p, 1080p, 2160p or WxH" in proc.stderr
