"""The only module that imports embreex: a static triangle BVH with closest-hit and occlusion queries.

Traps of embreex (4.4) handled here:
* ``tnear`` is fixed at 0, so callers must offset ray origins (see :func:`ray_epsilon`).
* with ``output=1`` a passed ``dists`` array is overwritten and OCCLUDED results are garbage: closest-hit
  queries use ``output=1`` without ``dists``; occlusion queries pass a *copy* of ``dists`` and no ``output``.
* geometry added after the first ``run()`` is ignored: the BVH is built once, from all triangles, in
  ``__init__``; a changed geometry needs a new :class:`TriangleBVH`.
* ``Ng`` is unnormalised and its sign follows the winding: we ignore it and use our own unit face normals.

Queries release the GIL inside embreex's ray loop, so callers may run them from several threads.
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene as _rtcs
from embreex.mesh_construction import TriangleMesh as _TriangleMesh

__all__ = ["TriangleBVH"]


class TriangleBVH:
    """A static triangle scene.

    Args:
        vertices: (V, 3) float32 world positions.
        faces: (F, 3) int32 vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.int32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"TriangleBVH: expected vertices (V, 3) and faces (F>0, 3), got {v.shape}, {f.shape}")
        self._scene = _rtcs.EmbreeScene()
        self._mesh = _TriangleMesh(self._scene, v, f)  # keep a reference: the scene reads its buffers
        self.num_triangles = len(f)
        # First (empty) query commits the BVH now, not inside a worker thread.
        self.intersect(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest hits.

        Args:
            origins, directions: (N, 3) float32 (directions need not be unit; t is in their units).

        Returns:
            t: (N,) float32 ray parameter of the hit (undefined where prim < 0).
            prim: (N,) int32 triangle index, -1 for a miss.
        """
        if len(origins) == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int32)
        res = self._scene.run(np.ascontiguousarray(origins, np.float32),
                              np.ascontiguousarray(directions, np.float32), output=1)
        return res["tfar"], res["primID"]

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """Any-hit test on segments ``origin + t * direction``, t in [0, tmax).

        Args:
            origins, directions: (N, 3) float32.
            tmax: (N,) float32.

        Returns:
            (N,) bool, True where something blocks the segment.
        """
        if len(origins) == 0:
            return np.zeros(0, bool)
        res = self._scene.run(np.ascontiguousarray(origins, np.float32),
                              np.ascontiguousarray(directions, np.float32),
                              dists=np.array(tmax, dtype=np.float32, copy=True), query="OCCLUDED")
        return np.asarray(res) >= 0

    def raw_scene(self):
        """The underlying embreex scene (for benchmarks comparing against raw embreex)."""
        return self._scene
