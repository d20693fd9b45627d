"""Shared by the training examples."""

from __future__ import annotations

import contextlib
import os
import platform
import subprocess
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent


@contextlib.contextmanager
def cpu_training_threads():
    """One intra-op thread with denormals flushed, restored on exit (tests call the examples' ``main()``).

    ``set_flush_denormal`` only reaches the calling thread, and denormal Adam statistics early in training made a
    second thread ~30x slower on this CPU.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        torch.set_flush_denormal(False)


def provenance(*code_paths: str) -> dict:
    """What a result was measured with: the commit (and whether ``code_paths``, relative to the repository, had
    uncommitted changes), the machine (CPU model, core count, platform) and the Python and torch versions."""

    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return "unknown"

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    dirty = git("status", "--porcelain", "--", *code_paths) if code_paths else ""
    return {
        "commit": git("rev-parse", "HEAD"),
        "uncommitted_changes_in_code": bool(dirty) if dirty != "unknown" else None,
        "machine": {"platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count()},
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
