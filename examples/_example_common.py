"""Shared by the training examples."""

from __future__ import annotations

import contextlib

import torch


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
