"""The only module that imports embreex: a static triangle BVH with closest-hit and occlusion queries.

Traps of embreex (4.4) handled here:
* ``tnear`` is fixed at 0, so callers must offset ray origins (see :func:`ray_epsilon`).
* with ``output=1`` a passed ``dists`` array is overwritten and OCCLUDED results are garbage: closest-hit
  queries use ``output=1`` without ``dists``; occlusion queries pass a *copy* of ``dists`` and no ``output``.
* geometry added after the first ``run()`` is ignored: the BVH is built once, from all triangles, in
  ``__init__``; a changed geometry needs a new :class:`TriangleBVH`.
* ``Ng`` is unnormalised and its sign follows the winding: we ignore it and use our own unit face normals.
* a hit at exactly ``tfar`` is accepted (``t <= tfar``), and so are occluders at exactly ``tmax``; among hits at the
  same ``t`` a BVH returns the one its traversal meets last (between leaves) or the leaf's first (within one), an
  order that depends on the whole tree.

Queries release the GIL inside embreex's ray loop, so callers may run them from several threads.
"""

from __future__ import annotations

import numpy as np

from .._extras import require

_rtcs = require("embreex.rtcore_scene", "the path tracer")
_TriangleMesh = require("embreex.mesh_construction", "the path tracer").TriangleMesh

__all__ = ["SplitBVH", "TriangleBVH"]


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
        res = self._scene.run(
            np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32), output=1
        )
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
        res = self._scene.run(
            np.ascontiguousarray(origins, np.float32),
            np.ascontiguousarray(directions, np.float32),
            dists=np.array(tmax, dtype=np.float32, copy=True),
            query="OCCLUDED",
        )
        return np.asarray(res) >= 0

    def raw_scene(self):
        """The underlying embreex scene (for benchmarks comparing against raw embreex)."""
        return self._scene


class SplitBVH:
    """The union of two triangle sets, each with its own BVH: ``static`` (built once, shared between frames) and
    ``moving`` (a small one, built per frame). Every query runs on both: closest hits keep the nearer one, occlusion
    is either BVH's. Triangle indices are those of the whole scene.

    Results equal one BVH of all the triangles (:class:`TriangleBVH`) but for what depends on a tree's shape: two
    hits at the same ``t`` (this class keeps the lower scene index, as one BVH does among the triangles of a leaf)
    and the rare ray that grazes a node's bounding box, where embree's traversal (not watertight) may find or miss a
    hit depending on the tree.

    Args:
        static: the BVH of the faces ``static_ids``.
        static_ids: (Fs,) int32 scene index of each of ``static``'s triangles.
        vertices: (V, 3) float32 world positions of the moving faces' vertices (this frame).
        faces: (Fm, 3) int32 the moving faces (indices into ``vertices``).
        moving_ids: (Fm,) int32 scene index of each moving face.
    """

    def __init__(
        self,
        static: TriangleBVH,
        static_ids: np.ndarray,
        vertices: np.ndarray,
        faces: np.ndarray,
        moving_ids: np.ndarray,
    ):
        self.static, self.moving = static, TriangleBVH(vertices, faces)
        self._static_ids = np.ascontiguousarray(static_ids, np.int32)
        self._moving_ids = np.ascontiguousarray(moving_ids, np.int32)
        self.num_triangles = static.num_triangles + self.moving.num_triangles

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest hits, as :meth:`TriangleBVH.intersect` (``t`` of a miss: that of a miss in both)."""
        ts, ps = self.static.intersect(origins, directions)
        tm, pm = self.moving.intersect(origins, directions)
        prim_s = np.where(ps >= 0, self._static_ids[np.maximum(ps, 0)], -1)
        prim_m = self._moving_ids[np.maximum(pm, 0)]
        take = (pm >= 0) & ((ps < 0) | (tm < ts) | ((tm == ts) & (prim_m < prim_s)))
        return np.where(take, tm, ts), np.where(take, prim_m, prim_s).astype(np.int32)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """Any-hit test, as :meth:`TriangleBVH.occluded`."""
        return self.static.occluded(origins, directions, tmax) | self.moving.occluded(origins, directions, tmax)
