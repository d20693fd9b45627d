"""Path tracer (embreex wavefront), EXR frame I/O and procedural scene geometry.

Public names: :class:`PathTracer`, :class:`RenderResult`, :func:`read_exr`, :func:`write_exr`,
:func:`exr_to_tensors`. Scenes are loaded by :func:`stereorepro.scenes.load_scene`.
"""

from .exr import exr_to_tensors, read_exr, write_exr  # noqa: F401
from .tracer import PathTracer, RenderResult, ray_epsilon  # noqa: F401

__all__ = ["PathTracer", "RenderResult", "ray_epsilon", "read_exr", "write_exr", "exr_to_tensors"]
