import os

import pytest
import torch

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def _devices():
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda")
    return devs


@pytest.fixture(params=_devices())
def device(request):
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["fp32", "fp64"])
def dtype(request):
    return request.param


def pytest_collection_modifyitems(config, items):
    # Tests that need onnxruntime are skipped (not failed) where it is absent.
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        skip = pytest.mark.skip(reason="onnxruntime not installed")
        for item in items:
            if "onnx" in item.name:
                item.add_marker(skip)
