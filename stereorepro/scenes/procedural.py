"""Procedural geometry for the built-in scenes (no external files): triangle soups tagged with material names.

Units are metres, +y is up. Every surface is two-sided. Generators return a :class:`MeshBuilder`; the scene
loader maps material names to the materials of the scene file.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MeshBuilder", "GENERATORS"]


class MeshBuilder:
    """Accumulates triangles with a material name each.

    Examples:
        >>> from stereorepro.scenes.procedural import MeshBuilder
        >>> b = MeshBuilder().quad([0, 0, 0], [1, 0, 0], [0, 0, 1], "floor").box([0, 0, 0], [1, 1, 1], "crate")
        >>> verts, faces, ids = b.build(["floor", "crate"])
        >>> verts.shape, faces.shape, ids.tolist().count(1), sorted(b.material_names)
        ((12, 3), (14, 3), 12, ['crate', 'floor'])
    """

    def __init__(self):
        self._verts: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._mats: list[tuple[str, int]] = []
        self._nv = 0

    def add(self, verts, faces, material: str):
        verts = np.asarray(verts, np.float64).reshape(-1, 3)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        self._verts.append(verts)
        self._faces.append(faces + self._nv)
        self._mats.append((material, len(faces)))
        self._nv += len(verts)
        return self

    def quad(self, p0, u, v, material: str):
        """Parallelogram with corner ``p0`` and edges ``u``, ``v`` (3-vectors)."""
        p0, u, v = (np.asarray(a, np.float64) for a in (p0, u, v))
        return self.add([p0, p0 + u, p0 + u + v, p0 + v], [[0, 1, 2], [0, 2, 3]], material)

    def box(self, lo, hi, material: str):
        """Axis-aligned box (12 triangles)."""
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        v = [
            [x0, y0, z0],
            [x1, y0, z0],
            [x1, y1, z0],
            [x0, y1, z0],
            [x0, y0, z1],
            [x1, y0, z1],
            [x1, y1, z1],
            [x0, y1, z1],
        ]
        f = [
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [3, 7, 6],
            [3, 6, 2],
            [0, 4, 7],
            [0, 7, 3],
            [1, 2, 6],
            [1, 6, 5],
        ]
        return self.add(v, f, material)

    def cylinder(
        self,
        base,
        radius: float,
        height: float,
        material: str,
        segments: int = 16,
        caps: bool = True,
        radius_top: float | None = None,
    ):
        """Vertical (frustum of a) cylinder standing on ``base``."""
        rt = radius if radius_top is None else radius_top
        a = np.linspace(0, 2 * math.pi, segments, endpoint=False)
        c, s = np.cos(a), np.sin(a)
        bx, by, bz = base
        bot = np.stack([bx + radius * c, np.full_like(a, by), bz + radius * s], 1)
        top = np.stack([bx + rt * c, np.full_like(a, by + height), bz + rt * s], 1)
        verts = [bot, top]
        i = np.arange(segments)
        j = (i + 1) % segments
        faces = [np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)]
        if caps:
            verts.append(np.array([[bx, by, bz], [bx, by + height, bz]]))
            cb, ct = 2 * segments, 2 * segments + 1
            faces += [
                np.stack([np.full_like(i, cb), j, i], 1),
                np.stack([np.full_like(i, ct), segments + i, segments + j], 1),
            ]
        return self.add(np.concatenate(verts), np.concatenate(faces), material)

    def arch(self, center, r_in: float, r_out: float, depth: float, axis: str, material: str, segments: int = 12):
        """Semicircular arch (half annulus) above ``center`` spanning along ``axis`` ('x' or 'z'), extruded by
        ``depth`` across it (centred)."""
        a = np.linspace(0, math.pi, segments + 1)
        cx, cy, cz = center
        verts, faces = [], []
        for side in (-0.5, 0.5):
            for r in (r_in, r_out):
                along = r * np.cos(a)
                up = cy + r * np.sin(a)
                if axis == "x":
                    pts = np.stack([cx + along, up, np.full_like(a, cz + side * depth)], 1)
                else:
                    pts = np.stack([np.full_like(a, cx + side * depth), up, cz + along], 1)
                verts.append(pts)
        n = segments + 1
        rings = [k * n for k in range(4)]  # (front in, front out, back in, back out)
        for k in range(segments):
            for ra, rb in ((rings[0], rings[1]), (rings[2], rings[3]), (rings[0], rings[2]), (rings[1], rings[3])):
                faces += [[ra + k, ra + k + 1, rb + k + 1], [ra + k, rb + k + 1, rb + k]]
        return self.add(np.concatenate(verts), faces, material)

    def build(self, material_names: list[str]):
        """Vertices (V, 3) float32, faces (F, 3) int32, material ids (F,) int32 (indices into ``material_names``)."""
        index = {n: i for i, n in enumerate(material_names)}
        missing = sorted({m for m, _ in self._mats} - set(index))
        if missing:
            raise KeyError(f"geometry uses materials not defined in the scene: {', '.join(missing)}")
        ids = (
            np.concatenate([np.full(c, index[m], np.int32) for m, c in self._mats])
            if self._mats
            else np.zeros(0, np.int32)
        )
        verts = np.concatenate(self._verts).astype(np.float32) if self._verts else np.zeros((0, 3), np.float32)
        faces = np.concatenate(self._faces).astype(np.int32) if self._faces else np.zeros((0, 3), np.int32)
        return verts, faces, ids

    @property
    def material_names(self) -> set[str]:
        return {m for m, _ in self._mats}


def _luminaire(
    b: MeshBuilder,
    x0: float,
    z0: float,
    size_x: float,
    size_z: float,
    ceiling_y: float,
    drop: float,
    emitter: str,
    housing: str,
):
    """Ceiling panel light: an emitting quad ``drop`` below the ceiling, closed above by four housing sides.

    Area lights are two-sided; a bare panel just under the ceiling lights the ceiling from its back side at grazing
    angles, a bright halo whose next-event estimates near the panel's edge have an unbounded 1/r^2 term (fireflies).
    The housing encloses the back side, so only the downward face can reach anything.
    """
    y = ceiling_y - drop
    b.quad((x0, y, z0), (size_x, 0, 0), (0, 0, size_z), emitter)
    for p0, u in (
        ((x0, y, z0), (size_x, 0, 0)),
        ((x0, y, z0 + size_z), (size_x, 0, 0)),
        ((x0, y, z0), (0, 0, size_z)),
        ((x0 + size_x, y, z0), (0, 0, size_z)),
    ):
        b.quad(p0, u, (0, drop, 0), housing)


def _table(b: MeshBuilder, x, z, y=0.0, top="wood", legs="metal", w=1.2, d=0.6, h=0.75):
    b.box((x - w / 2, y + h - 0.04, z - d / 2), (x + w / 2, y + h, z + d / 2), top)
    for sx in (-1, 1):
        for sz in (-1, 1):
            lx, lz = x + sx * (w / 2 - 0.05), z + sz * (d / 2 - 0.05)
            b.box((lx - 0.025, y, lz - 0.025), (lx + 0.025, y + h - 0.04, lz + 0.025), legs)


def _chair(b: MeshBuilder, x, z, facing=-1.0, seat="wood", frame="metal"):
    """Chair whose back is on the +z side when facing = -1 (sitter looks towards -z)."""
    b.box((x - 0.22, 0.43, z - 0.22), (x + 0.22, 0.47, z + 0.22), seat)
    bz = z - facing * 0.2
    b.box((x - 0.22, 0.47, bz - 0.02), (x + 0.22, 0.9, bz + 0.02), seat)
    for sx in (-1, 1):
        for sz in (-1, 1):
            lx, lz = x + sx * 0.19, z + sz * 0.19
            b.box((lx - 0.015, 0.0, lz - 0.015), (lx + 0.015, 0.43, lz + 0.015), frame)


def atrium() -> MeshBuilder:
    """Sponza-like arcaded atrium: a courtyard open to the sky, two storeys of column arcades with arches on both
    long sides, galleries behind them, end walls, banners and planters. About 10k triangles."""
    b = MeshBuilder()
    X, Zc, Zo = 12.0, 4.0, 7.0  # half length, courtyard half width, outer wall
    b.box((-X - 0.5, -0.2, -Zo - 0.5), (X + 0.5, 0.0, Zo + 0.5), "floor")
    b.box((-X - 0.5, 0.0, -Zo - 0.5), (X + 0.5, 10.0, -Zo), "wall")
    b.box((-X - 0.5, 0.0, Zo), (X + 0.5, 10.0, Zo + 0.5), "wall")
    b.box((-X - 0.5, 0.0, -Zo), (-X, 12.0, Zo), "wall_end")
    b.box((X, 0.0, -Zo), (X + 0.5, 12.0, Zo), "wall_end")
    for side in (-1, 1):
        z = side * Zc
        zin, zout = (z, side * Zo)
        lo, hi = min(zin, zout), max(zin, zout)
        b.box((-X, 5.6, lo), (X, 6.0, hi), "stone")  # gallery ceiling / upper floor
        b.box((-X, 9.6, lo), (X, 10.0, hi), "stone")  # roof over the upper gallery
        b.box((-X, 9.6, min(z, z + side * 0.0) - 0.3), (X, 10.4, max(z, z) + 0.3), "stone")  # cornice
        b.box((-X, 5.0, z - 0.3), (X, 5.6, z + 0.3), "stone")  # beam over the lower arches
        b.box((-X, 6.0, z - 0.15), (X, 6.9, z + 0.15), "stone")  # parapet of the upper gallery
        xs = np.arange(-10.0, 10.01, 2.5)
        for x in xs:
            b.cylinder((x, 0.0, z), 0.3, 3.6, "column", segments=24)
            b.box((x - 0.4, 0.0, z - 0.4), (x + 0.4, 0.25, z + 0.4), "stone")  # plinth
            b.box((x - 0.4, 3.6, z - 0.4), (x + 0.4, 3.8, z + 0.4), "stone")  # capital
            b.cylinder((x, 6.9, z), 0.2, 2.0, "column", segments=24)
            b.box((x - 0.3, 8.9, z - 0.3), (x + 0.3, 9.05, z + 0.3), "stone")
        for x0, x1 in zip(xs[:-1], xs[1:]):
            cx = 0.5 * (x0 + x1)
            b.arch((cx, 3.8, z), 0.85, 1.25, 0.6, "x", "stone", segments=14)
            b.arch((cx, 9.05, z), 0.9, 1.25, 0.4, "x", "stone", segments=10)
        # banners hanging in the upper arcade and planters along the courtyard
        for x in (-8.75, -3.75, 1.25, 6.25):
            b.quad((x - 0.6, 6.9, z - side * 0.2), (1.2, 0, 0), (0, -2.6, 0), "banner")
        for x in (-7.5, 0.0, 7.5):
            b.cylinder((x, 0.0, side * 2.6), 0.45, 0.7, "terracotta", segments=20, radius_top=0.6)
            b.cylinder((x, 0.7, side * 2.6), 0.5, 0.5, "plant", segments=10, radius_top=0.1)
    # doorways and niches on the end walls
    for x in (-X + 0.01, X - 0.01):
        s = 1 if x < 0 else -1
        for zc in (-2.5, 2.5):
            b.box((x, 0.0, zc - 0.8), (x + s * 0.3, 2.8, zc + 0.8), "door")
    b.cylinder((-8.0, 0.0, 0.0), 1.2, 0.6, "stone", segments=32)  # fountain basin at the far end
    b.cylinder((-8.0, 0.6, 0.0), 0.2, 1.2, "column", segments=16)
    b.cylinder((-8.0, 1.8, 0.0), 0.6, 0.15, "stone", segments=24)
    # sky above the courtyard opening (area light)
    b.quad((-X, 12.0, -Zc), (2 * X, 0, 0), (0, 0, 2 * Zc), "sky")
    return b


def living_room() -> MeshBuilder:
    """Furnished living room (about 6 x 2.8 x 7 m): sofa, armchair, coffee table, TV unit, bookshelf, lamp,
    plants, a window and a ceiling light."""
    b = MeshBuilder()
    W, Ht, D = 3.0, 2.8, 3.5
    b.box((-W, -0.1, -D), (W, 0.0, D), "floor")
    b.box((-W, Ht, -D), (W, Ht + 0.1, D), "ceiling")
    b.box((-W - 0.1, 0.0, -D), (-W, Ht, D), "wall")
    b.box((W, 0.0, -D), (W + 0.1, Ht, D), "wall")
    b.box((-W, 0.0, -D - 0.1), (W, Ht, -D), "wall")
    b.box((-W, 0.0, D), (W, Ht, D + 0.1), "wall")
    b.quad((W - 0.01, 0.9, -1.0), (0, 0, 2.0), (0, 1.4, 0), "window")  # window (sky light)
    # casing: sill, head and jambs touch the window's edges and close the 1 cm gap behind it (the emitter is
    # two-sided: open, its back lit the wall around it at grazing angles - a halo of fireflies)
    b.box((W - 0.08, 0.85, -1.05), (W, 0.9, 1.05), "trim")
    b.box((W - 0.08, 2.3, -1.05), (W, 2.35, 1.05), "trim")
    b.box((W - 0.08, 0.9, -1.05), (W, 2.3, -1.0), "trim")
    b.box((W - 0.08, 0.9, 1.0), (W, 2.3, 1.05), "trim")
    _luminaire(b, -0.6, -0.6, 1.2, 1.2, Ht, 0.01, "ceiling_light", "trim")
    b.box((-2.0, 0.0, -1.8), (1.6, 0.01, 1.2), "rug")
    # sofa against the back wall, facing +z
    b.box((-1.6, 0.0, -3.4), (1.2, 0.45, -2.5), "fabric")
    b.box((-1.6, 0.45, -3.4), (1.2, 1.0, -3.15), "fabric")
    for x in (-1.75, 1.2):
        b.box((x, 0.0, -3.4), (x + 0.15 + (0.0 if x > 0 else 0.0), 0.65, -2.5), "fabric")
    for x in (-1.3, -0.3, 0.7):
        b.box((x, 0.45, -3.1), (x + 0.45, 0.85, -2.95), "cushion")
    # armchair on the left, facing +x
    b.box((-2.8, 0.0, -1.2), (-2.0, 0.45, -0.4), "fabric")
    b.box((-2.8, 0.45, -1.2), (-2.6, 1.0, -0.4), "fabric")
    # coffee table with a few objects
    _table(b, -0.2, -1.2, top="wood_dark", legs="wood_dark", w=1.4, d=0.7, h=0.42)
    b.box((-0.6, 0.42, -1.35), (-0.2, 0.47, -1.05), "book")
    b.cylinder((0.2, 0.42, -1.2), 0.08, 0.25, "ceramic", segments=16)
    # TV unit on the front wall
    b.box((-1.2, 0.0, 3.1), (1.2, 0.5, 3.5), "wood_dark")
    b.box((-0.9, 0.8, 3.42), (0.9, 1.8, 3.47), "tv")
    # bookshelf on the left wall with books
    b.box((-3.0, 0.0, 1.0), (-2.65, 2.2, 2.8), "wood")
    rng = np.random.default_rng(7)
    for level in (0.3, 0.8, 1.3, 1.8):
        b.box((-2.99, level - 0.02, 1.02), (-2.64, level, 2.78), "wood_dark")
        z = 1.05
        while z < 2.7:
            w = float(rng.uniform(0.03, 0.07))
            h = float(rng.uniform(0.25, 0.38))
            b.box((-2.95, level, z), (-2.72, level + h, z + w), "book" if rng.random() < 0.6 else "book2")
            z += w + 0.005
    # floor lamp and plants
    b.cylinder((2.3, 0.0, -2.9), 0.18, 0.04, "metal", segments=16)
    b.cylinder((2.3, 0.04, -2.9), 0.02, 1.5, "metal", segments=8)
    b.cylinder((2.3, 1.5, -2.9), 0.25, 0.3, "shade", segments=20, radius_top=0.15)
    for x, z in ((2.5, 2.9), (-2.5, -3.0)):
        b.cylinder((x, 0.0, z), 0.2, 0.4, "ceramic", segments=16, radius_top=0.25)
        for k in range(6):
            a = k * math.pi / 3
            b.quad(
                (x, 0.4, z),
                (0.35 * math.cos(a), 0.6, 0.35 * math.sin(a)),
                (-0.1 * math.sin(a), 0.0, 0.1 * math.cos(a)),
                "plant",
            )
    # pictures on the walls
    b.box((-0.8, 1.4, -3.5), (0.4, 2.1, -3.47), "picture")
    b.box((2.97, 1.3, 1.6), (3.0, 2.0, 2.6), "picture")
    return b


def classroom() -> MeshBuilder:
    """Classroom (about 8 x 3.2 x 9 m): 5 rows of desks and chairs, a teacher's desk, blackboard, windows along
    the +x wall and ceiling light panels."""
    b = MeshBuilder()
    W, Ht, D = 4.0, 3.2, 4.5
    b.box((-W, -0.1, -D), (W, 0.0, D), "floor")
    b.box((-W, Ht, -D), (W, Ht + 0.1, D), "ceiling")
    b.box((-W - 0.1, 0.0, -D), (-W, Ht, D), "wall")
    b.box((-W, 0.0, -D - 0.1), (W, Ht, -D), "wall")
    b.box((-W, 0.0, D), (W, Ht, D + 0.1), "wall")
    # window wall at x = +W: wall pieces around three windows (sky light)
    b.box((W, 0.0, -D), (W + 0.1, 0.9, D), "wall")
    b.box((W, 2.6, -D), (W + 0.1, Ht, D), "wall")
    zs = [-4.5, -3.4, -1.6, -0.9, 0.9, 1.6, 3.4, 4.5]
    for z0, z1 in zip(zs[0::2], zs[1::2]):
        b.box((W, 0.9, z0), (W + 0.1, 2.6, z1), "wall")
    for z0 in (-3.4, -0.9, 1.6):
        b.quad((W + 0.1, 0.9, z0), (0, 0, 1.8), (0, 1.7, 0), "window")
        b.box((W - 0.25, 0.85, z0), (W, 0.9, z0 + 1.8), "trim")
    b.box((-2.0, 0.9, -D + 0.0), (2.0, 2.1, -D + 0.04), "blackboard")
    b.box((-2.05, 0.85, -D), (2.05, 0.9, -D + 0.1), "trim")
    for x in (-2.5, 0.0, 2.5):
        for z in (-2.0, 1.5):
            _luminaire(b, x - 0.6, z - 0.3, 1.2, 0.6, Ht, 0.02, "ceiling_light", "trim")
    _table(b, -1.8, -3.3, top="wood", legs="wood", w=1.6, d=0.8, h=0.78)  # teacher's desk
    _chair(b, -1.8, -3.9, facing=1.0)
    for row in range(5):
        z = -1.8 + row * 1.2
        for x in (-2.6, -1.2, 0.9, 2.3):
            _table(b, x, z, top="desk", legs="metal", w=1.1, d=0.5, h=0.74)
            for dx in (-0.27, 0.27):
                _chair(b, x + dx, z + 0.45)
    b.box((-3.95, 0.0, 3.6), (-3.4, 1.9, 4.45), "wood")  # cupboard
    b.cylinder((3.6, 0.0, 4.1), 0.18, 0.4, "metal", segments=14)  # bin
    return b


GENERATORS = {"atrium": atrium, "living_room": living_room, "classroom": classroom}
