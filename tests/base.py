"""The base class of the op test classes (one class per operation, the same method names in each: test_smoke,
test_cardinality, test_exceptions, test_gradcheck, test_module_equals_function, test_onnx_parity, hard cases).

It works with the fixtures of ``conftest.py``: ``device``, ``dtype`` (float32 / float64) and ``backend``
(torch | fast | native)."""

from __future__ import annotations

import torch

from conftest import backend_arg


class BaseTester:
    def backend_arg(self, backend: str) -> str:
        return backend_arg(backend)

    def skip_unless_runs(self, backend: str, dtype: torch.dtype, device: torch.device) -> None:
        """The native backend runs float32 on the CPU only: other combinations are not that backend's job."""
        import pytest

        if backend == "native" and (dtype != torch.float32 or device.type != "cpu"):
            pytest.skip("native runs float32 on the CPU")

    @staticmethod
    def assert_identical(got, ref) -> None:
        """Same dtype, shape and bytes (NaN where NaN)."""
        for g, r in zip(got, ref):
            assert g.dtype == r.dtype and g.shape == r.shape, (g.dtype, r.dtype, g.shape, r.shape)
            assert torch.equal(
                g.detach().cpu().contiguous().view(-1).view(torch.uint8),
                r.detach().cpu().contiguous().view(-1).view(torch.uint8),
            )
