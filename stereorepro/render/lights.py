"""Light sources for next-event estimation: emissive triangles (area lights) and point lights.

Area lights are the scene's triangles whose material has an emission; they are two-sided (the shared meshes
have no consistent winding) and are sampled uniformly in area. One light is picked per shadow ray with
probability proportional to its power (``pi * lum(Le) * area`` for a triangle, ``4 pi * lum(I)`` for a point
light). Static emitters are tabulated once per tracer (:class:`EmitterTable`); point lights are merged per frame
(:class:`LightSet`), which is only redone for scenes that declare ``moving_light``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EmitterTable", "LightSet", "luminance"]


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of (..., 3) → (...)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


class EmitterTable:
    """Emissive triangles of a static scene.

    Args:
        vertices: (V, 3) float32; faces: (F, 3) int32; face_emission: (F, 3) float32 radiance (zeros = not a light).
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
            self.face_index[keep], self.v0[keep], self.e1[keep], self.e2[keep], self.area[keep])
        self.normal = (cross[keep] / dbl[keep, None]).astype(np.float32)
        self.radiance = face_emission[self.face_index].astype(np.float32)
        self.power = np.pi * lum[self.face_index] * self.area
        self.num_faces = len(faces)


class LightSet:
    """All lights of one frame, with the power-proportional selection distribution.

    Args:
        emitters: the static :class:`EmitterTable`.
        point_positions: (L, 3) world positions at this frame; point_intensity: (L, 3) radiant intensity (W/sr).
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
            self.pdf_area_face[emitters.face_index] = (self.prob[:self.num_area] / emitters.area).astype(np.float32)
        # One gather table per area light (float32): v0, e1, e2, normal, radiance (3 each), selection pdf / area.
        E = emitters
        self._table = np.concatenate([E.v0, E.e1, E.e2, E.normal, E.radiance,
                                      (self.prob[:self.num_area] / np.maximum(E.area, 1e-30))[:, None]],
                                     axis=1).astype(np.float32) if self.num_area else np.zeros((0, 16), np.float32)

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
            li[a] = T[:, 12:15] * np.where(ok, np.float32(1) / np.where(ok, pdf_a, np.float32(1)),
                                            np.float32(0))[:, None]
        if len(p):
            k = sel[p] - self.num_area
            ok = d2[p] > 0
            w = np.where(ok, np.float32(1) / (np.where(ok, d2[p], 1) * self.prob[self.num_area + k]), 0)
            li[p] = self.point_int[k] * w.astype(np.float32)[:, None]
        return target, wi, dist.astype(np.float32), li, pdf
