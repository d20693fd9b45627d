"""The package's edge to files: atomic writes (:mod:`.atomic`), EXR frames (:mod:`.exr`), the frame-sequence
directory format (:mod:`.frames`), running ``reproject`` over such a directory (:mod:`.sequence`) and ONNX export
(:mod:`.onnx`). Other renderers' conventions are converted here, once; the core sees only ours."""

from .atomic import atomic_path, atomic_write
from .exr import exr_to_tensors, read_exr, write_exr
from .onnx import export_onnx, onnx_input_dims

__all__ = ["atomic_path", "atomic_write", "read_exr", "write_exr", "exr_to_tensors", "export_onnx", "onnx_input_dims"]
