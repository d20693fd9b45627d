"""Rigid animation of scene objects (the ``moving_objects`` effect).

A scene file declares each moving object as the group of faces of some materials, with keyframes::

    effects = ["moving_objects"]
    [[animations]]
    materials = ["mover"]                 # the object: every face of these materials
    pivot = [0.0, 0.5, 0.0]               # centre of rotation and scale (default: the object's bounding-box centre)
    frames = [0, 30, 59]                  # keyframe frame indices, increasing
    translate = [[0, 0, 0], [1, 0, 0], [0, 0, 0]]          # per keyframe (default: none)
    rotate = [[0, 1, 0, 0], [0, 1, 0, 90], [0, 1, 0, 0]]  # per keyframe: axis (3) and angle in degrees (default: none)
    scale = [1.0, 1.2, 1.0]               # per keyframe, uniform (default: 1)

The object's world position at frame ``f`` is ``x_f = t_f + pivot + s_f · R_f · (x_rest − pivot)``, with ``t`` and
``s`` interpolated linearly and ``R`` by spherical linear interpolation of quaternions between the surrounding
keyframes (held constant before the first and after the last). ``world_from_rest`` matrices are float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError

__all__ = ["RigidAnimation", "parse_animations", "quat_from_axis_angle", "quat_to_matrix", "slerp"]


def quat_from_axis_angle(axis, angle_deg: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation by ``angle_deg`` degrees about ``axis``.

    Examples:
        >>> from stereorepro.scenes.animation import quat_from_axis_angle
        >>> [round(float(c), 4) for c in quat_from_axis_angle([0, 0, 2], 90.0)]
        [0.7071, 0.0, 0.0, 0.7071]
    """
    a = np.asarray(axis, np.float64)
    n = float(np.linalg.norm(a))
    if angle_deg == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if not n > 0:
        raise ValueError("rotation axis is the zero vector")
    h = math.radians(angle_deg) / 2.0
    return np.concatenate([[math.cos(h)], math.sin(h) * a / n])


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (the shorter arc), ``u`` in [0, 1].

    Examples:
        >>> import numpy as np
        >>> from stereorepro.scenes.animation import quat_from_axis_angle, slerp
        >>> q = slerp(quat_from_axis_angle([0, 1, 0], 0.0), quat_from_axis_angle([0, 1, 0], 90.0), 0.5)
        >>> bool(np.allclose(q, quat_from_axis_angle([0, 1, 0], 45.0)))
        True
    """
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(min(1.0, d))
    return (math.sin((1.0 - u) * th) * q0 + math.sin(u * th) * q1) / math.sin(th)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a unit quaternion (w, x, y, z).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.scenes.animation import quat_from_axis_angle, quat_to_matrix
        >>> R = quat_to_matrix(quat_from_axis_angle([0, 0, 1], 90.0))
        >>> (R @ np.array([1.0, 0.0, 0.0])).round(6).tolist()
        [0.0, 1.0, 0.0]
    """
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class RigidAnimation:
    """One moving object: the faces of ``materials``, keyframed (see the module docstring).

    Attributes:
        materials: material names whose faces form the object.
        frames: (K,) int keyframe frame indices, increasing.
        translate: (K, 3); rotate: (K, 4) unit quaternions (w, x, y, z); scale: (K,).
        pivot: (3,) or None (then the caller passes the object's bounding-box centre).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.scenes.animation import RigidAnimation, quat_from_axis_angle
        >>> anim = RigidAnimation(("mover",), np.array([0, 10]), np.array([[0.0, 0, 0], [2.0, 0, 0]]),
        ...                   np.array([quat_from_axis_angle([0, 1, 0], 0.0)] * 2), np.ones(2))
        >>> anim.materials, anim.world_from_rest(5, pivot=np.zeros(3))[:3, 3].tolist()
        (('mover',), [1.0, 0.0, 0.0])
    """

    materials: tuple
    frames: np.ndarray
    translate: np.ndarray
    rotate: np.ndarray
    scale: np.ndarray
    pivot: np.ndarray | None = None

    def world_from_rest(self, frame: float, pivot: np.ndarray) -> np.ndarray:
        """(4, 4) float64 transform of the object at ``frame`` (any real number; clamped to the keyframes)."""
        fr = self.frames
        if frame <= fr[0] or len(fr) == 1:
            i, u = 0, 0.0
        elif frame >= fr[-1]:
            i, u = len(fr) - 2, 1.0
        else:
            i = int(np.searchsorted(fr, frame, side="right")) - 1
            u = (frame - fr[i]) / float(fr[i + 1] - fr[i])
        j = min(i + 1, len(fr) - 1)
        t = (1.0 - u) * self.translate[i] + u * self.translate[j]
        s = (1.0 - u) * self.scale[i] + u * self.scale[j]
        R = quat_to_matrix(slerp(self.rotate[i], self.rotate[j], u))
        p = self.pivot if self.pivot is not None else np.asarray(pivot, np.float64)
        T = np.eye(4)
        T[:3, :3] = s * R
        T[:3, 3] = t + p - s * R @ p
        return T


def parse_animations(data: dict, file: str, materials: list, num_frames: int) -> list[RigidAnimation]:
    """The ``[[animations]]`` of a scene file, validated against its materials (names, emission) and frames.

    Raises:
        SceneError: naming the file and the key.

    Examples:
        >>> from types import SimpleNamespace
        >>> from stereorepro.scenes.animation import parse_animations
        >>> materials = [SimpleNamespace(name="mover", emission=(0.0, 0.0, 0.0))]
        >>> data = {"effects": ["moving_objects"], "animations": [{"materials": ["mover"], "frames": [0, 4],
        ...                                                     "translate": [[0, 0, 0], [0, 1, 0]]}]}
        >>> anims = parse_animations(data, "demo.toml", materials, num_frames=5)
        >>> len(anims), anims[0].frames.tolist(), anims[0].translate[1].tolist()
        (1, [0, 4], [0.0, 1.0, 0.0])
    """
    effects = set(data.get("effects", []))
    entries = data.get("animations", [])
    if entries and "moving_objects" not in effects:
        raise SceneError(f'{file}: animations: moving objects need effects = ["moving_objects"]')
    if "moving_objects" in effects and not entries:
        raise SceneError(f"{file}: key 'effects': declares 'moving_objects' but there are no [[animations]]")
    by_name = {m.name: m for m in materials}
    owner: dict[str, int] = {}
    out = []
    for i, a in enumerate(entries):
        where = f"{file}: animations[{i}]"
        if "materials" not in a or not a["materials"]:
            raise SceneError(f"{where}: missing key 'materials' (the object: the names of its faces' materials)")
        if "frames" not in a:
            raise SceneError(f"{where}: missing key 'frames' (keyframe frame indices)")
        for name in a["materials"]:
            if name not in by_name:
                raise SceneError(f"{where}.materials: unknown material {name!r}")
            if max(by_name[name].emission) > 0:
                raise SceneError(f"{where}.materials: {name!r} is emissive; moving emitters are not supported")
            if name in owner:
                raise SceneError(f"{where}.materials: {name!r} already moves with animations[{owner[name]}]")
            owner[name] = i
        frames = np.asarray(a["frames"], np.int64)
        K = len(frames)
        if np.any(np.diff(frames) <= 0) or frames[0] < 0:
            raise SceneError(f"{where}.frames: expected increasing frame indices >= 0, got {frames.tolist()}")
        for key, width in (("translate", 3), ("rotate", 4), ("scale", 1)):
            if key in a and len(a[key]) != K:
                raise SceneError(f"{where}.{key}: expected {K} entries (one per keyframe), got {len(a[key])}")
        translate = np.asarray(a.get("translate", [[0.0, 0.0, 0.0]] * K), np.float64)
        scale = np.asarray(a.get("scale", [1.0] * K), np.float64)
        if not np.all(scale > 0):
            raise SceneError(f"{where}.scale: expected positive numbers, got {scale.tolist()}")
        try:
            rotate = np.array([quat_from_axis_angle(r[:3], r[3]) for r in a.get("rotate", [[0, 1, 0, 0]] * K)])
        except ValueError as e:
            raise SceneError(f"{where}.rotate: {e}") from None
        pivot = np.asarray(a["pivot"], np.float64) if "pivot" in a else None
        out.append(RigidAnimation(tuple(a["materials"]), frames, translate, rotate, scale, pivot))
    return out
