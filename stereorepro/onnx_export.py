"""Former home of the ONNX export (kept importable): see :mod:`stereorepro.io.onnx`."""

from .io.onnx import example_inputs, export_onnx, onnx_input_dims  # noqa: F401

__all__ = ["export_onnx", "example_inputs", "onnx_input_dims"]
