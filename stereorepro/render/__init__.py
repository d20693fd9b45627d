"""The path tracer: an embreex wavefront tracer producing radiance and G-buffers (depth, normal, position).

Stages (:mod:`.tracer`): generate → intersect → shade + NEE → bounce → shadow, over structure-of-arrays batches;
:mod:`.bsdf`, :mod:`.lights` and :mod:`.rng` hold their maths, :mod:`._embree` is the only importer of embreex.
Scenes are loaded by :func:`stereorepro.scenes.load_scene`; frames are written by :mod:`stereorepro.io.exr`.
"""

from .tracer import PathTracer, RenderResult, ray_epsilon

__all__ = ["PathTracer", "RenderResult", "ray_epsilon"]
