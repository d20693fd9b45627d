"""Light sources for next-event estimation: emissive triangles (area lights) and point lights.

Area lights are the scene's triangles whose material has an emission; they are two-sided (the shared meshes
have no consistent winding) and are sampled uniformly in area. One light is picked per shadow ray with
probability proportional to its power (``pi * lum(Le) * area`` for a triangle, ``4 pi * lum(I)`` for a point
light). Static emitters are tabulated once per tracer (:class:`EmitterTable`); point lights are merged per frame
(:class:`LightSet`), which is only redone for scenes that declare ``moving_light``.

:func:`radiance_bound` gives the firefly-clamp limit of :class:`~stereorepro.render.PathTracer` (an upper bound on
the reflected radiance of any vertex of the depth-3 estimator) and :func:`point_mesh_distance` the distance from
point lights to the nearest surface that it needs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EmitterTable", "LightSet", "TriangleDistances", "luminance", "point_mesh_distance", "radiance_bound"]


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of (..., 3) → (...).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import luminance
        >>> [round(float(x), 4) for x in luminance(np.array([[1.0, 1.0, 1.0], [0.0, 1.0, 0.0]]))]
        [1.0, 0.7152]
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


class EmitterTable:
    """Emissive triangles of a static scene.

    Args:
        vertices: (V, 3) float32; faces: (F, 3) int32; face_emission: (F, 3) float32 radiance (zeros = not a light).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import EmitterTable
        >>> vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
        >>> faces = np.array([[0, 1, 2], [0, 1, 3]], np.int32)
        >>> emission = np.array([[0, 0, 0], [2, 2, 2]], np.float32)  # only face 1 emits
        >>> table = EmitterTable(vertices, faces, emission)
        >>> table.face_index.tolist(), table.area.tolist(), round(float(table.power[0]), 4)
        ([1], [0.5], 3.1416)
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, face_emission: np.ndarray):
        lum = luminance(face_emission)
        self.face_index = np.nonzero(lum > 0)[0].astype(np.int64)
        tri = vertices[faces[self.face_index]].astype(np.float64)  # (E, 3, 3)
        self.v0 = tri[:, 0].astype(np.float32)
        self.e1 = (tri[:, 1] - tri[:, 0]).astype(np.float32)
        self.e2 = (tri[:, 2] - tri[:, 0]).astype(np.float32)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        dbl = np.linalg.norm(cross, axis=1)
        self.area = 0.5 * dbl
        keep = self.area > 0
        self.face_index, self.v0, self.e1, self.e2, self.area = (
            self.face_index[keep],
            self.v0[keep],
            self.e1[keep],
            self.e2[keep],
            self.area[keep],
        )
        self.normal = (cross[keep] / dbl[keep, None]).astype(np.float32)
        self.radiance = face_emission[self.face_index].astype(np.float32)
        self.power = np.pi * lum[self.face_index] * self.area
        self.num_faces = len(faces)


class LightSet:
    """All lights of one frame, with the power-proportional selection distribution.

    Args:
        emitters: the static :class:`EmitterTable`.
        point_positions: (L, 3) world positions at this frame; point_intensity: (L, 3) radiant intensity (W/sr).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import EmitterTable, LightSet
        >>> vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        >>> table = EmitterTable(vertices, np.array([[0, 1, 2]], np.int32), np.ones((1, 3), np.float32))
        >>> lights = LightSet(table, np.array([[0.0, 0.0, 2.0]]), np.full((1, 3), 0.125))
        >>> [round(float(p), 4) for p in lights.prob]
        [0.5, 0.5]
        >>> target, wi, dist, li, pdf = lights.sample(np.zeros((2, 3), np.float32), np.array([0.1, 0.9], np.float32),
        ...                                          np.full(2, 0.5, np.float32), np.full(2, 0.5, np.float32))
        >>> [round(float(d), 4) for d in dist], bool(np.isinf(pdf[1]))  # an area light, then the point light
        ([0.5, 2.0], True)
    """

    def __init__(self, emitters: EmitterTable, point_positions: np.ndarray, point_intensity: np.ndarray):
        self.emitters = emitters
        self.point_pos = np.asarray(point_positions, np.float32).reshape(-1, 3)
        self.point_int = np.asarray(point_intensity, np.float32).reshape(-1, 3)
        power = np.concatenate([emitters.power, 4 * np.pi * luminance(self.point_int)])
        total = power.sum()
        self.num_area = len(emitters.power)
        self.empty = not (total > 0)
        self.prob = power / total if not self.empty else power
        self.cdf = np.cumsum(self.prob)
        if not self.empty:
            self.cdf[-1] = 1.0
        # Per scene triangle: selection probability / area (the area pdf used by MIS when a ray hits it).
        self.pdf_area_face = np.zeros(emitters.num_faces, np.float32)
        if self.num_area:
            self.pdf_area_face[emitters.face_index] = (self.prob[: self.num_area] / emitters.area).astype(np.float32)
        # One gather table per area light (float32): v0, e1, e2, normal, radiance (3 each), selection pdf / area.
        E = emitters
        self._table = (
            np.concatenate(
                [
                    E.v0,
                    E.e1,
                    E.e2,
                    E.normal,
                    E.radiance,
                    (self.prob[: self.num_area] / np.maximum(E.area, 1e-30))[:, None],
                ],
                axis=1,
            ).astype(np.float32)
            if self.num_area
            else np.zeros((0, 16), np.float32)
        )

    def sample(self, points: np.ndarray, u_sel: np.ndarray, u1: np.ndarray, u2: np.ndarray):
        """Sample one light per shading point.

        Args:
            points: (N, 3) shading points; u_sel, u1, u2: (N,) uniforms.

        Returns:
            target: (N, 3) sampled light position; wi: (N, 3) unit direction to it; dist: (N,) distance;
            li: (N, 3) ``Le cos_l / (d^2 pdf_area)`` (area) or ``I / (d^2 p_sel)`` (point): incident radiance
            divided by the solid-angle pdf; pdf_light: (N,) solid-angle pdf (``inf`` for point lights).
        """
        n = len(points)
        sel = np.searchsorted(self.cdf, u_sel.astype(np.float64), side="right")
        sel = np.minimum(sel, len(self.cdf) - 1)
        target = np.empty((n, 3), np.float32)
        li = np.zeros((n, 3), np.float32)
        pdf = np.full(n, np.inf, np.float32)
        is_area = sel < self.num_area
        all_area = len(self.point_pos) == 0
        a = slice(None) if all_area else np.nonzero(is_area)[0]
        na = n if all_area else len(a)
        if na:
            T = self._table[sel[a]]  # one gather: (na, 16)
            su = np.sqrt(u1[a])
            b1 = (su * (np.float32(1) - u2[a]))[:, None]
            b2 = (su * u2[a])[:, None]
            target[a] = T[:, 0:3] + b1 * T[:, 3:6] + b2 * T[:, 6:9]
        p = np.zeros(0, np.int64) if all_area else np.nonzero(~is_area)[0]
        if len(p):
            target[p] = self.point_pos[sel[p] - self.num_area]
        delta = target - points
        d2 = delta[:, 0] * delta[:, 0] + delta[:, 1] * delta[:, 1] + delta[:, 2] * delta[:, 2]
        dist = np.sqrt(d2)
        safe = np.where(dist > 0, dist, np.float32(1))
        wi = delta / safe[:, None]
        if na:
            wa = wi[a]
            cos_l = np.abs(T[:, 9] * wa[:, 0] + T[:, 10] * wa[:, 1] + T[:, 11] * wa[:, 2])
            d2a = d2[a]
            pdf_a = T[:, 15] * d2a / np.maximum(cos_l, np.float32(1e-12))
            ok = (cos_l > 1e-7) & (d2a > 0)
            pdf[a] = np.where(ok, pdf_a, np.float32(np.inf))
            li[a] = (
                T[:, 12:15] * np.where(ok, np.float32(1) / np.where(ok, pdf_a, np.float32(1)), np.float32(0))[:, None]
            )
        if len(p):
            k = sel[p] - self.num_area
            ok = d2[p] > 0
            w = np.where(ok, np.float32(1) / (np.where(ok, d2[p], 1) * self.prob[self.num_area + k]), 0)
            li[p] = self.point_int[k] * w.astype(np.float32)[:, None]
        return target, wi, dist.astype(np.float32), li, pdf


def _segment_distance2(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distance from point ``p`` (3,) to segments ``a``-``b`` (F, 3) → (F,), float64."""
    ab = b - a
    t = np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    q = a + np.clip(t, 0.0, 1.0)[:, None] * ab
    d = p - q
    return np.einsum("ij,ij->i", d, d)


class TriangleDistances:
    """Exact Euclidean distances from points to every triangle of a fixed mesh; the per-face data (corners, normal)
    are computed once, so a moving light's distances cost one vectorised pass per light and frame.

    Args:
        vertices: (V, 3); faces: (F, 3) int.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import TriangleDistances
        >>> tris = TriangleDistances(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
        >>> above, beside = np.array([0.25, 0.25, 2.0]), np.array([-1.0, 0.0, 0.0])
        >>> len(tris), tris.squared(above).tolist(), tris.squared(beside).tolist()
        (1, [4.0], [1.0])
        >>> tris.grouped(np.array([[0.25, 0.25, 2.0]]), np.array([0]), 2).tolist()
        [[2.0, inf]]
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        V = np.asarray(vertices, np.float64)
        Fc = np.asarray(faces, np.int64).reshape(-1, 3)
        tri = V[Fc]  # (F, 3, 3)
        self.a, self.b, self.c = tri[:, 0], tri[:, 1], tri[:, 2]
        self.n = np.cross(self.b - self.a, self.c - self.a)
        self.nn = np.einsum("ij,ij->i", self.n, self.n)
        self.ok = self.nn > 0
        self.nn_safe = np.where(self.ok, self.nn, 1.0)

    def __len__(self) -> int:
        return len(self.a)

    def squared(self, p: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """Squared distance from the point ``p`` (3,) to each triangle (or to triangles ``idx``) → (F,) float64."""
        p = np.asarray(p, np.float64).reshape(3)
        a, b, c, n, ok, nn = self.a, self.b, self.c, self.n, self.ok, self.nn_safe
        if idx is not None:
            a, b, c, n, ok, nn = a[idx], b[idx], c[idx], n[idx], ok[idx], nn[idx]
        # inside the triangle's prism: the distance is the distance to its plane
        s = np.einsum("ij,ij->i", p - a, n)
        q = p - (s / nn)[:, None] * n  # projection onto the plane
        w0 = np.einsum("ij,ij->i", np.cross(b - q, c - q), n)
        w1 = np.einsum("ij,ij->i", np.cross(c - q, a - q), n)
        w2 = np.einsum("ij,ij->i", np.cross(a - q, b - q), n)
        inside = ok & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        d2 = np.minimum(
            np.minimum(_segment_distance2(p, a, b), _segment_distance2(p, b, c)), _segment_distance2(p, c, a)
        )
        return np.where(inside, s * s / nn, d2)

    def grouped(self, points: np.ndarray, group: np.ndarray, num_groups: int) -> np.ndarray:
        """Distance from each point to the nearest triangle of each group (e.g. material) → (L, G) float64,
        ``inf`` for a group without triangles. ``group``: (F,) int in [0, num_groups).

        Only triangles that can hold a group's minimum are evaluated exactly: a triangle whose plane lies farther
        than the group's nearest vertex (by a margin far above rounding) cannot; the result is the same as
        evaluating all of them.
        """
        P = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.full((len(P), num_groups), np.inf)
        group = np.asarray(group, np.int64)
        if len(group) == 0:
            return out
        order = np.argsort(group, kind="stable")
        present, starts = np.unique(group[order], return_index=True)
        for i, p in enumerate(P):
            dv = [np.einsum("ij,ij->i", p - v, p - v) for v in (self.a, self.b, self.c)]
            ub = np.minimum.reduceat(np.minimum(np.minimum(dv[0], dv[1]), dv[2])[order], starts)  # per group
            ub_face = np.full(num_groups, np.inf)
            ub_face[present] = ub
            s = np.einsum("ij,ij->i", p - self.a, self.n)
            lb = np.where(self.ok, s * s / self.nn_safe, 0.0)  # squared plane distance <= squared distance
            # margins far above rounding (relative to the bound, and to the face's scale |p - a|^2)
            cand = np.flatnonzero((lb <= ub_face[group] * (1 + 1e-9) + 1e-9 * dv[0])[order])
            d2 = np.full(len(order), np.inf)
            d2[cand] = self.squared(p, order[cand])
            out[i, present] = np.sqrt(np.minimum.reduceat(d2, starts))
        return out


def point_mesh_distance(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 1 << 16
) -> np.ndarray:
    """Exact Euclidean distance from each point to the nearest triangle of a mesh (brute force, chunked).

    Args:
        points: (L, 3); vertices: (V, 3); faces: (F, 3) int.

    Returns:
        (L,) float64 distances (``inf`` for an empty mesh).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import point_mesh_distance
        >>> vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> points = np.array([[0.25, 0.25, 3.0], [2.0, 0.0, 0.0]])
        >>> point_mesh_distance(points, vertices, np.array([[0, 1, 2]])).tolist()
        [3.0, 1.0]
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    Fc = np.asarray(faces, np.int64).reshape(-1, 3)
    out = np.full(len(P), np.inf)
    for lo in range(0, len(Fc), chunk):
        tris = TriangleDistances(vertices, Fc[lo : lo + chunk])
        for i, p in enumerate(P):
            out[i] = min(out[i], float(np.sqrt(tris.squared(p).min())))
    return out


def radiance_bound(
    emission: np.ndarray,
    albedo: np.ndarray,
    specular: np.ndarray,
    exponent: np.ndarray,
    point_intensity: np.ndarray,
    point_distance: np.ndarray,
) -> float:
    """Upper bound ``C`` on the reflected radiance of any vertex of the depth-3 estimator (the firefly clamp).

    Rule (all quantities per scene, maxima over RGB channels)::

        C = (1 + rho_e) * (Le_max + P) + P,    P = sum_l max_m f_m I_l / d_lm^2

    * ``Le_max`` - the largest emitted radiance of any material (area lights);
    * ``rho_e``  - the largest albedo (``kd + ks``) of an *emissive* material (0 for the usual black emitters);
    * ``f_m``   - the largest BSDF value of material ``m``: ``kd/pi + ks (e + 2)/(2 pi)`` (``1/pi`` for a white
      Lambertian surface; a glossy lobe's peak is higher);
    * ``I_l``, ``d_lm`` - intensity of point light ``l`` and its distance to the nearest surface of material ``m``.

    Why: an energy-conserving BSDF (albedo <= 1) reflects at most the largest radiance arriving over the hemisphere,
    and a point light adds at most ``f_m I / d^2`` at a surface of material ``m`` at distance ``d``. At the second vertex ``x2`` (direct light only) that gives
    ``L_r(x2) <= Le_max + P``; the radiance leaving ``x2`` towards ``x1`` is ``Le(x2) + L_r(x2) <= (1 + rho_e)(Le_max
    + P)`` (an emitter reflects too only when its albedo is non-zero), and ``x1`` adds its own point-light term
    ``P``. The true value never exceeds ``C``, so clamping an estimate at ``C`` only removes the part of a rare
    sample (a 1/r^2 spike of next-event estimation) that no pixel can legitimately reach.

    Args:
        emission, albedo, specular: (M, 3) per material; exponent: (M,) Phong exponents.
        point_intensity: (L, 3) point-light intensities; point_distance: (L, M) distance of light ``l`` to the
            nearest surface of material ``m`` (``inf`` for an unused material), or (L,) one distance per light
            (e.g. a declared minimum distance) used for every material.

    Returns:
        ``C`` (a positive float; ``inf`` when a point light touches a surface, i.e. no bound).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.lights import radiance_bound
        >>> emission = np.array([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])  # material 1 is the (black) emitter
        >>> albedo = np.array([[0.8, 0.8, 0.8], [0.0, 0.0, 0.0]])
        >>> no_lights = np.zeros((0, 3))
        >>> radiance_bound(emission, albedo, np.zeros((2, 3)), np.ones(2), no_lights, np.zeros((0, 2)))
        5.0
        >>> c = radiance_bound(emission, albedo, np.zeros((2, 3)), np.ones(2), np.full((1, 3), np.pi), np.array([1.0]))
        >>> round(c, 4)
        6.6
    """
    em = np.asarray(emission, np.float64).reshape(-1, 3)
    kd = np.asarray(albedo, np.float64).reshape(-1, 3)
    ks = np.asarray(specular, np.float64).reshape(-1, 3)
    e = np.asarray(exponent, np.float64).reshape(-1)
    emissive = em.max(axis=1) > 0
    le_max = float(em.max()) if len(em) else 0.0
    rho_e = float((kd + ks)[emissive].max()) if emissive.any() else 0.0
    inten = np.asarray(point_intensity, np.float64).reshape(-1, 3)
    p = 0.0
    if len(inten):
        f = (kd / np.pi + ks * ((e + 2) / (2 * np.pi))[:, None]).max(axis=1)  # (M,)
        d = np.asarray(point_distance, np.float64).reshape(len(inten), -1)
        d = np.broadcast_to(d, (len(inten), len(f)))
        with np.errstate(divide="ignore", invalid="ignore"):
            per = np.where(f[None, :] > 0, f[None, :] * inten.max(axis=1)[:, None] / np.square(d), 0.0)
        p = float(per.max(axis=1).sum())
    c = (1.0 + rho_e) * (le_max + p) + p
    return c if c > 0 else float("inf")
