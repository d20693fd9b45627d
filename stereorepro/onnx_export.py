"""Former home of the ONNX export (kept importable): see :mod:`stereorepro.io.onnx`."""

from ._testing import example_inputs  # noqa: F401
from .io.onnx import export_onnx, onnx_input_dims  # noqa: F401

__all__ = ["export_onnx", "example_inputs", "onnx_input_dims"]
