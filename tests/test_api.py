"""The public API's shape: every public function a reader can hold (<= 12 parameters), the data model exported."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil

import pytest
from torch import nn

import stereorepro

#: The most parameters a public function or method may take (``inspect.signature``; ``*args`` / ``**kwargs`` count).
MAX_PARAMETERS = 12


def _public_modules():
    for info in pkgutil.walk_packages(stereorepro.__path__, "stereorepro."):
        if any(part.startswith("_") for part in info.name.split(".")[1:]):
            continue
        try:
            yield importlib.import_module(info.name)
        except ImportError as e:  # an optional dependency (OpenEXR, embreex, ...) missing: not this test's concern
            pytest.skip(f"{info.name}: {e}")


def _exempt(owner, name: str) -> bool:
    """Generated dataclass ``__init__``s (settings records: one keyword per field) and nn.Module forwards (flat
    tensors, what ONNX export needs) and their flat mirrors (``features``) are not held to the limit."""
    if owner is None:
        return False
    if name == "__init__" and dataclasses.is_dataclass(owner):
        return True
    return issubclass(owner, nn.Module) and name in ("forward", "features")


def public_signatures():
    """(qualified name, parameter count) of every public function and method defined in the package."""
    seen = set()
    for module in _public_modules():
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__ or id(obj) in seen:
                continue
            seen.add(id(obj))
            if inspect.isfunction(obj):
                yield f"{module.__name__}.{name}", len(inspect.signature(obj).parameters), None, name
            elif inspect.isclass(obj):
                for attr, fn in vars(obj).items():
                    bound = isinstance(fn, classmethod) or inspect.isfunction(fn)  # cls / self not counted
                    fn = fn.__func__ if isinstance(fn, (classmethod, staticmethod)) else fn
                    if inspect.isfunction(fn) and (not attr.startswith("_") or attr == "__init__"):
                        count = len(inspect.signature(fn).parameters) - bound
                        yield f"{module.__name__}.{name}.{attr}", count, obj, attr


def test_no_public_function_takes_more_than_twelve_parameters():
    too_long = [
        (qual, n) for qual, n, owner, attr in public_signatures() if n > MAX_PARAMETERS and not _exempt(owner, attr)
    ]
    assert not too_long, f"public functions over {MAX_PARAMETERS} parameters: {too_long}"


def test_the_count_sees_every_kind_of_callable():
    counts = {qual: n for qual, n, _, _ in public_signatures()}
    assert counts["stereorepro.reproject.functional.temporal_reproject"] <= MAX_PARAMETERS
    assert counts["stereorepro.reproject.view.View.from_camera"] == 5  # a classmethod, cls not counted
    assert counts["stereorepro.reproject.view.History.empty"] == 3
    assert counts["stereorepro.reproject.modules.TemporalReprojection.forward"] == 13  # flat for ONNX: exempt


def test_data_model_exported():
    for name in ("View", "Thresholds", "Blend", "History", "ReprojectionResult", "TemporalResult"):
        assert name in stereorepro.__all__ and getattr(stereorepro, name).__module__ == "stereorepro.reproject.view"
    for name in ("ReprojectionResult", "TemporalResult", "History", "Thresholds", "Blend"):
        assert issubclass(getattr(stereorepro, name), tuple)  # NamedTuples: unpacking keeps working
