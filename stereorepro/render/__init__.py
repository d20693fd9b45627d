"""The path tracer: an embreex wavefront tracer producing radiance and G-buffers (depth, normal, position).

Stages (:mod:`.tracer`): generate → intersect → shade + NEE → bounce → shadow, over structure-of-arrays batches;
:mod:`.bsdf`, :mod:`.lights` and :mod:`.rng` hold their maths, :mod:`._embree` is the only importer of embreex.
Scenes are loaded by :func:`stereorepro.scenes.load_scene`; frames are written by :mod:`stereorepro.io.exr`
(``read_exr`` / ``write_exr`` stay importable from here).
"""

from ..io.exr import exr_to_tensors, read_exr, write_exr  # noqa: F401
from .tracer import PathTracer, RenderResult, ray_epsilon  # noqa: F401

__all__ = ["PathTracer", "RenderResult", "ray_epsilon", "read_exr", "write_exr", "exr_to_tensors"]
