import importlib.util
import os
import sys
from pathlib import Path

import pytest
import torch

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture(autouse=True)
def _isolated_environment():
    """Each test sees the environment variables it started with: a test that runs the CLI in this process
    (``--shared-scenes`` sets ``STEREOREPRO_SHARED_SCENES``, for one) leaves nothing behind for the next."""
    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


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


ROOT = Path(__file__).resolve().parent.parent


def load_script(folder: str, name: str):
    """``<folder>/<name>.py`` of the repository (a bench or example script) as the module ``<folder>_<name>``, run
    as the script would run: its folder first on ``sys.path`` while it imports (its helpers, ``_bench_common`` or
    ``_example_common``, have names of their own, so the folders' helpers never shadow each other). The folder
    stays on ``sys.path`` only where the script puts it there itself."""
    spec = importlib.util.spec_from_file_location(f"{folder}_{name}", ROOT / folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    sys.path.insert(0, str(ROOT / folder))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / folder))  # the first entry: this one, or the script's own insertion
    return module


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
