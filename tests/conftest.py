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


@pytest.fixture(params=["torch", "fast", "native"])
def backend(request, monkeypatch):
    """The reprojection implementation a test runs: ``torch`` (the general path: the fast path switched off),
    ``fast`` (torch with its inference fast path where it applies) or ``native`` (``_core``; skipped where it is
    not built). Pass the value of ``backend_arg(backend)`` as the ops' ``backend`` argument."""
    from stereorepro.reproject import _native, functional

    monkeypatch.delenv("STEREOREPRO_BACKEND", raising=False)
    if request.param == "native" and not _native.available():
        pytest.skip("stereorepro._core is not built")
    if request.param == "torch":
        monkeypatch.setattr(functional, "FAST_PATH", False)
    return request.param


def backend_arg(backend: str) -> str:
    """The ops' ``backend`` argument for a value of the ``backend`` fixture."""
    return "native" if backend == "native" else "torch"


def pytest_collection_modifyitems(config, items):
    # Tests marked `onnx` need onnx and onnxruntime: skipped (not failed) where they are absent.
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        skip = pytest.mark.skip(reason="onnx / onnxruntime not installed")
        for item in items:
            if item.get_closest_marker("onnx"):
                item.add_marker(skip)
