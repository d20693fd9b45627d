"""Procedural textures of scene files: the ``textures`` effect.

A scene that declares ``effects = ["textures"]`` may give materials a world-space pattern::

    [textures.floor]                # the material it applies to
    pattern = "checker"             # "checker" (3-D cells of side `scale`) or "stripes" (slabs across `axis`)
    scale = 0.1                     # cell / stripe width in scene units (> 0)
    contrast = 0.6                  # the second colour's albedo (and specular) = the material's × (1 − contrast)
    axis = "x"                      # stripes only: "x", "y" or "z" (default "x")

The pattern is resolved exactly in the geometry: each triangle of a textured material is cut along the pattern's
cell boundaries (planes ``axis = k·scale``) into convex pieces, and each piece takes the material or its second
colour (a material named ``NAME~texture``) by the parity of its cell. Both tracers (numpy and native), the
G-buffer albedo, the light tables and the radiance bound then see the texture as ordinary per-face materials, and
nothing is evaluated for scenes that do not declare the effect: their geometry and renders are unchanged.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError

__all__ = ["PATTERNS", "TEXTURE_SUFFIX", "Texture", "apply_textures", "parse_textures"]

#: The procedural patterns.
PATTERNS = ("checker", "stripes")
#: Suffix of the material holding a textured material's second colour.
TEXTURE_SUFFIX = "~texture"
_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Texture:
    """One ``[textures.NAME]`` table.

    Attributes:
        material: the textured material's name; pattern: one of :data:`PATTERNS`; scale: cell width (scene
        units); contrast: the second colour is the material's albedo × (1 − contrast); axis: 0, 1, 2 (stripes).

    Examples:
        >>> from stereorepro.scenes.textures import Texture
        >>> Texture("floor", "checker", 0.1, 0.5).cut_axes()
        (0, 1, 2)
    """

    material: str
    pattern: str
    scale: float
    contrast: float
    axis: int = 0

    def cut_axes(self) -> tuple[int, ...]:
        """The world axes whose planes ``k·scale`` bound the pattern's cells."""
        return (0, 1, 2) if self.pattern == "checker" else (self.axis,)

    def second(self, point: np.ndarray) -> bool:
        """Whether world point (3,) lies in a cell of the second colour."""
        cells = sum(math.floor(float(point[a]) / self.scale) for a in self.cut_axes())
        return cells % 2 == 1


def parse_textures(data: dict, file: str, effects: frozenset, materials: list) -> tuple[list[Texture], list]:
    """The scene's ``[textures.NAME]`` tables and the second-colour materials they add (appended to the scene's).

    Args:
        data: the scene file's contents; file: its path (for messages); effects: the declared effects;
            materials: the scene's materials (dataclasses with ``name``, ``albedo``, ``specular`` fields).

    Returns:
        (textures, new materials).

    Raises:
        SceneError: textures without the effect (or the effect without textures), an unknown material, pattern
            or axis, a scale <= 0 or a contrast outside [0, 1].

    Examples:
        >>> from dataclasses import dataclass
        >>> from stereorepro.scenes.textures import parse_textures
        >>> @dataclass(frozen=True)
        ... class Material:
        ...     name: str
        ...     albedo: tuple
        ...     specular: tuple = (0.0, 0.0, 0.0)
        >>> floor = Material("floor", (0.5, 0.4, 0.3))
        >>> data = {"textures": {"floor": {"pattern": "checker", "scale": 0.1, "contrast": 0.5}}}
        >>> textures, extra = parse_textures(data, "scene.toml", frozenset({"textures"}), [floor])
        >>> textures[0].scale, extra[0].name, extra[0].albedo
        (0.1, 'floor~texture', (0.25, 0.2, 0.15))
    """
    table = data.get("textures", {})
    if table and "textures" not in effects:
        raise SceneError(
            f"{file}: key 'textures': textured materials need the scene to declare effects = [\"textures\"]"
        )
    if "textures" in effects and not table:
        raise SceneError(f"{file}: key 'effects': declares 'textures' but no [textures.NAME] table")
    by_name = {m.name: m for m in materials}
    textures, extra = [], []
    for name, t in table.items():
        where = f"{file}: textures.{name}"
        if name not in by_name:
            raise SceneError(f"{where}: no material named {name!r}")
        pattern = t.get("pattern", "checker")
        if pattern not in PATTERNS:
            raise SceneError(f"{where}.pattern: expected one of {list(PATTERNS)}, got {pattern!r}")
        scale, contrast = float(t.get("scale", 0.1)), float(t.get("contrast", 0.5))
        if not scale > 0:
            raise SceneError(f"{where}.scale: expected a number > 0, got {scale}")
        if not 0.0 <= contrast <= 1.0:
            raise SceneError(f"{where}.contrast: expected a number in [0, 1], got {contrast}")
        axis = t.get("axis", "x")
        if axis not in _AXES:
            raise SceneError(f"{where}.axis: expected one of {sorted(_AXES)}, got {axis!r}")
        textures.append(Texture(name, pattern, scale, contrast, _AXES[axis]))
        m, k = by_name[name], 1.0 - contrast
        extra.append(
            dataclasses.replace(
                m,
                name=name + TEXTURE_SUFFIX,
                albedo=tuple(k * c for c in m.albedo),
                specular=tuple(k * c for c in m.specular),
            )
        )
    return textures, extra


def _cut(p: np.ndarray, q: np.ndarray, axis: int, c: float) -> np.ndarray:
    """The point of segment pq on the plane ``axis = c``, computed from the endpoints in a fixed order (so that the
    two triangles sharing an edge cut it at the same point: no cracks)."""
    a, b = (p, q) if tuple(p) <= tuple(q) else (q, p)
    t = (c - a[axis]) / (b[axis] - a[axis])
    x = a + t * (b - a)
    x[axis] = c
    return x


def _split(poly: list, axis: int, c: float) -> list:
    """A convex polygon (list of (3,) points) cut by the plane ``axis = c`` (which crosses its interior)."""
    below, above = [], []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        dp, dq = p[axis] - c, q[axis] - c
        if dp <= 0:
            below.append(p)
        if dp >= 0:
            above.append(p)
        if (dp < 0 < dq) or (dq < 0 < dp):
            x = _cut(p, q, axis, c)
            below.append(x)
            above.append(x)
    return [below, above]


def _pieces(tri: np.ndarray, texture: Texture) -> list:
    """Convex pieces of a triangle (3, 3) float64, each inside one cell of the pattern."""
    polys = [list(tri)]
    s = texture.scale
    for axis in texture.cut_axes():
        out = []
        for poly in polys:
            lo, hi = min(p[axis] for p in poly), max(p[axis] for p in poly)
            parts = [poly]
            for k in range(math.floor(lo / s) + 1, math.ceil(hi / s)):
                c = k * s
                if lo < c < hi:
                    last = parts.pop()
                    parts.extend(_split(last, axis, c))
            out.extend(parts)
        polys = out
    return [p for p in polys if len(p) >= 3]


def apply_textures(
    vertices: np.ndarray, faces: np.ndarray, material_ids: np.ndarray, textures: list[Texture], names: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene geometry with the textured materials' triangles cut into the pattern's cells.

    Faces of other materials keep their vertices, indices and order; each textured triangle is replaced by the
    fan triangulations of its pieces (same winding, appended after the untouched faces), with the material or its
    ``NAME~texture`` second colour by the cell parity of the piece's centroid.

    Args:
        vertices: (V, 3) float32; faces: (F, 3) int32; material_ids: (F,) int32 indices into ``names``;
            textures: from :func:`parse_textures`; names: the scene's material names (second colours included).

    Returns:
        (vertices, faces, material_ids) of the same dtypes.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.scenes.textures import Texture, apply_textures
        >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1]], np.float32); f = np.array([[0, 1, 2]], np.int32)
        >>> v2, f2, m2 = apply_textures(v, f, np.zeros(1, np.int32), [Texture("a", "stripes", 0.5, 1.0)],
        ...                             ["a", "a~texture"])
        >>> len(f2), sorted(set(m2.tolist()))
        (3, [0, 1])
    """
    keep = np.ones(len(faces), bool)
    new_v, new_f, new_m = [], [], []
    nv = len(vertices)
    for tex in textures:
        first, second = names.index(tex.material), names.index(tex.material + TEXTURE_SUFFIX)
        sel = np.flatnonzero(material_ids == first)
        keep[sel] = False
        for tri in vertices[faces[sel]].astype(np.float64):
            for poly in _pieces(tri, tex):
                centroid = np.mean(poly, axis=0)
                mat = second if tex.second(centroid) else first
                new_v.extend(poly)
                new_f.extend([nv, nv + i, nv + i + 1] for i in range(1, len(poly) - 1))
                new_m.extend([mat] * (len(poly) - 2))
                nv += len(poly)
    if not new_f:
        return vertices, faces[keep], material_ids[keep]
    return (
        np.concatenate([vertices, np.asarray(new_v, np.float32)]),
        np.concatenate([faces[keep], np.asarray(new_f, np.int32)]).astype(np.int32),
        np.concatenate([material_ids[keep], np.asarray(new_m, np.int32)]).astype(np.int32),
    )
