"""Declarative scenes: scene files (TOML) and their loader.

The built-in scenes (:func:`list_scenes`) are files of the package, ``stereorepro/scenes/builtin/*.toml``, installed
with it; :func:`load_scene` takes their names or the path of any scene file. Two environment variables:

* ``STEREOREPRO_SCENES_DIR``: a folder that replaces the built-in one (:func:`scenes_dir`); a built-in name then
  loads ``$STEREOREPRO_SCENES_DIR/NAME.toml``. Unset: the package's own folder.
* ``STEREOREPRO_SHARED_SCENES``: the folder of the external meshes the ``shared_*`` scenes read
  (:func:`shared_scenes_dir`; the CLI's ``--shared-scenes`` sets it).

A scene file (TOML) declares geometry, materials, lights, a camera path over ``num_frames`` frames, the stereo
rig, the scene's reprojection thresholds and the ``effects`` it needs. Only declared effects are simulated (see
:class:`stereorepro.render.PathTracer`). Keys (unknown keys or wrong types are errors naming file, key and the
expected type)::

    name = "atrium"                 # default: the file name without .toml
    extends = "atrium.toml"         # optional base file (tables merged recursively, other values replaced)
    description = "..."
    effects = ["glossy"]            # subset of {"glossy", "moving_light", "moving_objects", "textures"}
    num_frames = 60

    [geometry]
    generator = "atrium"            # a built-in generator (stereorepro.render.procedural), or
    mesh = "$STEREOREPRO_SHARED_SCENES/classroom/classroom.ply"   # a trimesh-loadable file
    sidecar = "classroom.json"      # materials for the mesh's per-face ids (default: mesh path with .json)
    scale = 1.0
    [[geometry.quads]]              # extra parallelograms (e.g. area lights): corner, edge_u, edge_v, material
    [[geometry.boxes]]              # extra axis-aligned boxes: min, max, material

    [materials.NAME]                # albedo (diffuse RGB), specular + exponent (glossy lobe), emission (RGB)

    [textures.NAME]                 # procedural pattern of material NAME (effect "textures"): pattern
                                    #   ("checker" | "stripes"), scale, contrast, axis (stereorepro.scenes.textures)
    [[lights]]                      # point lights: intensity (W/sr RGB) and position, or keyframes (moving)
    [camera]                        # vfov_deg, up, positions = [[x,y,z],...], targets = [[x,y,z],...]
    [rig]                           # eye_separation (scene units), convergence_distance (optional)
    [reprojection]                  # position_threshold (scene units), normal_threshold (unit-normal distance)
    [render]                        # optional renderer settings of the scene:
    radiance_clamp = 0.0            #   firefly clamp on reflected radiance; 0 or absent = "auto" (see
                                    #   stereorepro.render.lights.radiance_bound); > 0 = this limit
    point_light_min_distance = 0.3  #   d_min of the auto rule for point lights (default: each light's distance
                                    #   to the nearest surface, per frame)

Camera and light keyframes are control points of a uniform Catmull-Rom spline over the sequence (frame 0 at the
first point, the last frame at the last point): smooth curves through the points.

``$STEREOREPRO_SHARED_SCENES`` in a mesh path expands to that environment variable, or to ``../shared/scenes``
beside the repository when it is unset.
"""

from __future__ import annotations

import difflib
import json
import math
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib
import torch

from .._extras import require
from ..camera import PinholeCamera, StereoRig, intrinsics_from_fov, look_at
from ..errors import SceneError
from .animation import parse_animations
from .textures import apply_textures, parse_textures

__all__ = [
    "Scene",
    "SceneError",
    "SceneGeometry",
    "list_scenes",
    "load_scene",
    "scenes_dir",
    "shared_scenes_dir",
    "SCENES_ENV",
    "KNOWN_EFFECTS",
    "THRESHOLD_ROWS",
    "threshold_scale",
]

KNOWN_EFFECTS = frozenset({"glossy", "moving_light", "moving_objects", "textures"})
BUILTIN_SCENES = (
    "atrium",
    "atrium_glossy",
    "atrium_moving_light",
    "living_room",
    "living_room_glossy",
    "living_room_moving_light",
    "classroom",
)
#: Built-in scenes beyond the paper's seven (effects the paper does not have).
BEYOND_PAPER_SCENES = ("living_room_moving_objects", "living_room_textured")
EXTERNAL_SCENES = ("shared_sponza", "shared_living_room", "shared_classroom")
SHARED_ENV = "STEREOREPRO_SHARED_SCENES"
#: Image rows for which scene files set their position thresholds (2–3 pixel footprints at a typical depth).
THRESHOLD_ROWS = 180


def threshold_scale(height: int) -> float:
    """The one rule for thresholds against resolution: the factor on a scene's position threshold at ``height``
    rows, ``max(1, THRESHOLD_ROWS / height)``.

    The position test compares a tap's surface point with the destination point, so a tap half a pixel away on a
    slanted surface differs by about half a pixel footprint. Below :data:`THRESHOLD_ROWS` rows a pixel covers more
    of the scene and the threshold grows with it, so that the test keeps its meaning in pixels; at and above it
    the scene's threshold is used as it is (it must not shrink below the geometric tolerance the scene needs).

    Examples:
        >>> from stereorepro.scenes.loader import threshold_scale
        >>> threshold_scale(90), threshold_scale(180), threshold_scale(720)
        (2.0, 1.0, 1.0)
    """
    if not height >= 1:
        raise ValueError(f"height must be >= 1, got {height}")
    return max(1.0, THRESHOLD_ROWS / float(height))


SCENES_ENV = "STEREOREPRO_SCENES_DIR"
#: The built-in scene files, shipped inside the package.
BUILTIN_DIR = Path(__file__).resolve().parent / "builtin"


def scenes_dir() -> Path:
    """Folder of the built-in scene files: ``$STEREOREPRO_SCENES_DIR`` when set, else the package's
    ``stereorepro/scenes/builtin``.

    Raises:
        SceneError: the folder does not exist.

    Examples:
        >>> from stereorepro.scenes.loader import scenes_dir
        >>> folder = scenes_dir()
        >>> folder.is_dir(), (folder / "atrium.toml").is_file()
        (True, True)
    """
    env = os.environ.get(SCENES_ENV)
    folder = Path(env).expanduser() if env else BUILTIN_DIR
    if not folder.is_dir():
        if env:
            raise SceneError(f"${SCENES_ENV} is {env!r}, which is not a folder (unset it to use the built-in scenes)")
        raise SceneError(f"the built-in scene folder {folder} is missing: reinstall stereorepro")
    return folder


def shared_scenes_dir() -> Path:
    """Folder of the external meshes: ``$STEREOREPRO_SHARED_SCENES`` or ``../shared/scenes`` beside the repo.

    Examples:
        >>> from pathlib import Path
        >>> from stereorepro.scenes.loader import shared_scenes_dir
        >>> isinstance(shared_scenes_dir(), Path)
        True
    """
    env = os.environ.get(SHARED_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent.parent.parent / "shared" / "scenes"


def list_scenes(include_external: bool = False, beyond_paper: bool = False) -> list[str]:
    """Names of the built-in scenes (the paper's seven variants); with ``include_external`` also the scenes that
    need the shared meshes (``shared_*``); with ``beyond_paper`` also the built-in scenes of effects the paper
    does not have (``living_room_moving_objects``).

    Examples:
        >>> from stereorepro import list_scenes
        >>> list_scenes()[:3], "living_room" in list_scenes(), len(list_scenes())
        (['atrium', 'atrium_glossy', 'atrium_moving_light'], True, 7)
    """
    return (
        list(BUILTIN_SCENES)
        + (list(BEYOND_PAPER_SCENES) if beyond_paper else [])
        + (list(EXTERNAL_SCENES) if include_external else [])
    )


_VEC3 = "vec3"
_SCHEMA = {
    "name": "str",
    "extends": "str",
    "description": "str",
    "effects": "strlist",
    "num_frames": "int",
    "geometry": (
        "table",
        {
            "generator": "str",
            "mesh": "str",
            "sidecar": "str",
            "scale": "float",
            "quads": ("tablelist", {"corner": _VEC3, "edge_u": _VEC3, "edge_v": _VEC3, "material": "str"}),
            "boxes": ("tablelist", {"min": _VEC3, "max": _VEC3, "material": "str"}),
        },
    ),
    "materials": ("tablemap", {"albedo": _VEC3, "specular": _VEC3, "exponent": "float", "emission": _VEC3}),
    "textures": ("tablemap", {"pattern": "str", "scale": "float", "contrast": "float", "axis": "str"}),
    "lights": ("tablelist", {"type": "str", "intensity": _VEC3, "position": _VEC3, "keyframes": "vec3list"}),
    "camera": ("table", {"vfov_deg": "float", "up": _VEC3, "positions": "vec3list", "targets": "vec3list"}),
    "rig": ("table", {"eye_separation": "float", "convergence_distance": "float"}),
    "reprojection": ("table", {"position_threshold": "float", "normal_threshold": "float"}),
    "render": ("table", {"radiance_clamp": "float", "point_light_min_distance": "float"}),
    "animations": (
        "tablelist",
        {
            "materials": "strlist",
            "pivot": _VEC3,
            "frames": "intlist",
            "translate": "vec3list",
            "rotate": "vec4list",
            "scale": "floatlist",
        },
    ),
}
_DESCR = {
    "str": "a string",
    "int": "an integer",
    "float": "a number",
    "strlist": "a list of strings",
    _VEC3: "a list of 3 numbers",
    "vec3list": "a non-empty list of [x, y, z] lists",
    "intlist": "a non-empty list of integers",
    "floatlist": "a non-empty list of numbers",
    "vec4list": "a non-empty list of [axis_x, axis_y, axis_z, angle_deg] lists",
    "table": "a table",
    "tablelist": "an array of tables ([[...]])",
    "tablemap": "a table of tables",
}


def _num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _type_ok(kind: str, v) -> bool:
    if kind == "str":
        return isinstance(v, str)
    if kind == "int":
        return isinstance(v, int) and not isinstance(v, bool)
    if kind == "float":
        return _num(v)
    if kind == "strlist":
        return isinstance(v, list) and all(isinstance(s, str) for s in v)
    if kind == _VEC3:
        return isinstance(v, list) and len(v) == 3 and all(_num(a) for a in v)
    if kind == "vec3list":
        return isinstance(v, list) and len(v) > 0 and all(_type_ok(_VEC3, p) for p in v)
    if kind == "vec4list":
        return (
            isinstance(v, list)
            and len(v) > 0
            and all(isinstance(p, list) and len(p) == 4 and all(_num(a) for a in p) for p in v)
        )
    if kind == "intlist":
        return isinstance(v, list) and len(v) > 0 and all(_type_ok("int", a) for a in v)
    if kind == "floatlist":
        return isinstance(v, list) and len(v) > 0 and all(_num(a) for a in v)
    raise AssertionError(kind)


def _validate(data: dict, schema: dict, file: str, prefix: str = "") -> None:
    for key, value in data.items():
        path = f"{prefix}{key}"
        if key not in schema:
            raise SceneError(f"{file}: unknown key '{path}' (expected one of: {', '.join(sorted(schema))})")
        spec = schema[key]
        if isinstance(spec, tuple):
            kind, sub = spec
            if kind == "table":
                if not isinstance(value, dict):
                    raise SceneError(f"{file}: key '{path}': expected {_DESCR[kind]}, got {type(value).__name__}")
                _validate(value, sub, file, path + ".")
            elif kind == "tablelist":
                if not (isinstance(value, list) and all(isinstance(t, dict) for t in value)):
                    raise SceneError(f"{file}: key '{path}': expected {_DESCR[kind]}, got {type(value).__name__}")
                for i, t in enumerate(value):
                    _validate(t, sub, file, f"{path}[{i}].")
            elif kind == "tablemap":
                if not (isinstance(value, dict) and all(isinstance(t, dict) for t in value.values())):
                    raise SceneError(f"{file}: key '{path}': expected {_DESCR[kind]}, got {type(value).__name__}")
                for name, t in value.items():
                    _validate(t, sub, file, f"{path}.{name}.")
        elif not _type_ok(spec, value):
            raise SceneError(f"{file}: key '{path}': expected {_DESCR[spec]}, got {value!r}")


def _merge(base: dict, child: dict) -> dict:
    out = dict(base)
    for k, v in child.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read_toml(path: Path, seen=()) -> dict:
    if path in seen:
        raise SceneError(f"{path}: 'extends' forms a cycle")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise SceneError(f"{path}: scene file not found") from None
    except IsADirectoryError:
        raise SceneError(f"{path}: is a directory, expected a .toml scene file") from None
    except UnicodeDecodeError as e:  # a binary file
        raise SceneError(f"{path}: not a text (UTF-8) TOML file: {e.reason} at byte {e.start}") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: invalid TOML: {e}") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot read: {e.strerror or e}") from None
    _validate(data, _SCHEMA, str(path))
    if "extends" in data:
        base_path = (path.parent / data["extends"]).resolve()
        base = _read_toml(base_path, seen + (path,))
        base.pop("name", None)
        data = _merge(base, {k: v for k, v in data.items() if k != "extends"})
    return data


def _req(data: dict, key: str, file: str, what: str):
    cur = data
    for part in key.split("."):
        if not isinstance(cur, dict) or part not in cur:
            raise SceneError(f"{file}: missing key '{key}' ({what})")
        cur = cur[part]
    return cur


def catmull_rom(points: np.ndarray, t: float) -> np.ndarray:
    """Point at ``t`` in [0, 1] on the uniform Catmull-Rom spline through ``points`` (P, 3) (ends clamped)."""
    P = np.asarray(points, np.float64)
    if len(P) == 1:
        return P[0].copy()
    s = min(max(float(t), 0.0), 1.0) * (len(P) - 1)
    i = min(int(math.floor(s)), len(P) - 2)
    u = s - i
    p0, p1, p2, p3 = P[max(i - 1, 0)], P[i], P[i + 1], P[min(i + 2, len(P) - 1)]
    if i == 0:
        p0 = 2 * p1 - p2
    if i + 2 > len(P) - 1:
        p3 = 2 * p2 - p1
    u2, u3 = u * u, u * u * u
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u3)


@dataclass(frozen=True)
class SceneGeometry:
    """Triangle soup of a scene.

    Attributes:
        vertices: (V, 3) float32 world positions; faces: (F, 3) int32; material_ids: (F,) int32.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.scenes.loader import SceneGeometry
        >>> geo = SceneGeometry(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), np.zeros(1, np.int32))
        >>> geo.faces.shape, geo.material_ids.tolist()
        ((1, 3), [0])
    """

    vertices: np.ndarray
    faces: np.ndarray
    material_ids: np.ndarray


@dataclass(frozen=True)
class _Material:
    name: str
    albedo: tuple
    specular: tuple = (0.0, 0.0, 0.0)
    exponent: float = 1.0
    emission: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class _PointLight:
    intensity: np.ndarray  # (3,)
    keyframes: np.ndarray  # (P, 3); one row = static


@dataclass
class Scene:
    """A loaded scene. Build with :func:`load_scene`.

    Attributes:
        name: scene name; effects: frozenset of declared effects; num_frames: frames of the camera path.
        vfov_deg: vertical field of view; rig: :class:`~stereorepro.camera.StereoRig`.
        position_threshold: reprojection limit on ``|P_src - P_dst|`` (scene units).
        normal_threshold: reprojection limit on ``|N_src - N_dst|`` (unit normals).
        source: the scene file.
        radiance_clamp: ``[render] radiance_clamp``: 0 = "auto" (the renderer derives the limit), else the limit.
        point_light_min_distance: ``[render] point_light_min_distance`` or None (nearest-surface distance).

    Examples:
        >>> from stereorepro.scenes import load_scene
        >>> scene = load_scene("atrium")
        >>> scene.name, scene.num_frames, scene.thresholds(180)
        ('atrium', 60, (0.15, 0.3))
        >>> scene.geometry().vertices.dtype
        dtype('float32')
    """

    name: str
    effects: frozenset
    num_frames: int
    vfov_deg: float
    rig: StereoRig
    position_threshold: float
    normal_threshold: float
    source: Path
    description: str = ""
    radiance_clamp: float = 0.0
    point_light_min_distance: float | None = None
    _data: dict = field(default_factory=dict, repr=False)
    _materials: list = field(default_factory=list, repr=False)
    _lights: list = field(default_factory=list, repr=False)
    _geometry: SceneGeometry | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _animations: list = field(default_factory=list, repr=False)
    _textures: list = field(default_factory=list, repr=False)
    _pivots: np.ndarray | None = field(default=None, repr=False)

    @property
    def spec(self) -> dict:
        """The scene file's contents, with the files it ``extends`` merged in (what the scene was built from)."""
        return self._data

    def thresholds(self, height: int, scale: float | None = None) -> tuple[float, float]:
        """(position, normal) thresholds for images of ``height`` rows: the position threshold times ``scale``,
        by default :func:`threshold_scale` (``max(1, 180 / height)``); the normal threshold as it is."""
        s = threshold_scale(height) if scale is None else float(scale)
        return float(self.position_threshold) * s, float(self.normal_threshold)

    def _t(self, frame: int) -> float:
        if not (0 <= int(frame) < self.num_frames):
            raise ValueError(f"scene {self.name}: frame must be in [0, {self.num_frames}), got {frame}")
        return int(frame) / max(self.num_frames - 1, 1)

    def head_pose(self, frame: int) -> torch.Tensor:
        """``cam_from_world`` (1, 4, 4) float64 of the head (cyclopean eye) at ``frame``."""
        cam = self._data["camera"]
        t = self._t(frame)
        eye = catmull_rom(np.array(cam["positions"]), t)
        target = catmull_rom(np.array(cam["targets"]), t)
        up = np.array(cam.get("up", [0.0, 1.0, 0.0]), np.float64)
        as_t = lambda a: torch.tensor(a, dtype=torch.float64).reshape(1, 3)  # noqa: E731
        return look_at(as_t(eye), as_t(target), as_t(up))

    def intrinsics(self, width: int, height: int) -> torch.Tensor:
        """K (1, 3, 3) float64 of the scene's field of view at the given image size."""
        return intrinsics_from_fov(self.vfov_deg, width, height, dtype=torch.float64)

    def camera(self, frame: int, width: int, height: int) -> PinholeCamera:
        """The head (cyclopean) camera, B = 1."""
        return PinholeCamera(self.intrinsics(width, height), self.head_pose(frame), height, width)

    def stereo_cameras(self, frame: int, width: int, height: int) -> tuple[PinholeCamera, PinholeCamera]:
        """(left, right) :class:`PinholeCamera` (B = 1, float64) of the stereo rig at ``frame``."""
        return self.rig.cameras(self.head_pose(frame), self.intrinsics(width, height), height, width)

    def point_lights(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Point lights at ``frame``: positions (L, 3) and intensities (L, 3), float32."""
        t = self._t(frame)
        pos = [catmull_rom(li.keyframes, t) for li in self._lights]
        inten = [li.intensity for li in self._lights]
        return (np.array(pos, np.float32).reshape(-1, 3), np.array(inten, np.float32).reshape(-1, 3))

    def material_table(self) -> dict:
        """Materials as arrays: ``names`` (M,), ``albedo``/``specular``/``emission`` (M, 3), ``exponent`` (M,)."""
        ms = self._materials
        return {
            "names": [m.name for m in ms],
            "albedo": np.array([m.albedo for m in ms], np.float32).reshape(-1, 3),
            "specular": np.array([m.specular for m in ms], np.float32).reshape(-1, 3),
            "exponent": np.array([m.exponent for m in ms], np.float32).reshape(-1),
            "emission": np.array([m.emission for m in ms], np.float32).reshape(-1, 3),
        }

    def face_objects(self) -> np.ndarray:
        """(F,) int32: for each face of :meth:`geometry`, the index of the animation that moves it (its object),
        or -1 for static faces (all of them unless the scene declares ``moving_objects``)."""
        geo = self.geometry()
        out = np.full(len(geo.faces), -1, np.int32)
        names = [m.name for m in self._materials]
        for o, anim in enumerate(self._animations):
            ids = [names.index(n) for n in anim.materials]
            out[np.isin(geo.material_ids, ids)] = o
        return out

    def object_transforms(self, frame: float) -> np.ndarray:
        """(O, 4, 4) float64 ``world_from_rest`` of each moving object at ``frame`` (O = 0 for static scenes);
        see :mod:`stereorepro.scenes.animation`."""
        if not self._animations:
            return np.zeros((0, 4, 4))
        pivots = self._object_pivots()
        return np.stack([a.world_from_rest(float(frame), pivots[o]) for o, a in enumerate(self._animations)])

    def _object_pivots(self) -> np.ndarray:
        """(O, 3): each object's bounding-box centre at rest (the default pivot), computed once."""
        if self._pivots is None:
            geo, objs = self.geometry(), self.face_objects()
            piv = np.zeros((len(self._animations), 3))
            for o in range(len(self._animations)):
                v = geo.vertices[geo.faces[objs == o].reshape(-1)].astype(np.float64)
                if len(v) == 0:
                    raise SceneError(
                        f"{self.source}: animations[{o}]: no faces have materials {list(self._animations[o].materials)}"
                    )
                piv[o] = 0.5 * (v.min(0) + v.max(0))
            self._pivots = piv
        return self._pivots

    def geometry(self) -> SceneGeometry:
        """The scene's triangles at rest (loaded or generated once, then cached); moving objects are placed per
        frame by :meth:`object_transforms`."""
        with self._lock:
            if self._geometry is None:
                self._geometry = _build_geometry(self)
            return self._geometry


def _vec(v) -> tuple:
    return tuple(float(a) for a in v)


_SIDECAR_GLOSSY = {"plastic": (0.04, 200.0), "glossy_black": (0.04, 100.0)}


def _sidecar_materials(path: Path, glossy: bool, file: str) -> tuple[list[_Material], set[int]]:
    """Materials of a shared-scene JSON sidecar. Returns (materials by id, ids whose faces are dropped).

    Mapping: diffuse → Lambert; plastic / glossy_black → Lambert + a dielectric-like lobe (ks 0.04) when glossy;
    metal → a glossy lobe with the base colour when glossy (Lambert otherwise); emitter → emission;
    dielectric (glass) → dropped (no refraction here: windows let light through).
    """
    try:
        side = json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneError(f"{file}: geometry.sidecar: file not found: {path}") from None
    except json.JSONDecodeError as e:
        raise SceneError(f"{file}: geometry.sidecar: invalid JSON in {path}: {e}") from None
    mats, dropped = [], set()
    for i, m in enumerate(side.get("materials", [])):
        base = tuple(min(float(c), 0.95) for c in m.get("base_color_linear", [0.5, 0.5, 0.5]))
        kind = m.get("type", "diffuse")
        name = str(m.get("name", f"mat{i}"))
        if kind == "emitter":
            mats.append(_Material(name, (0.0, 0.0, 0.0), emission=_vec(m.get("emission_linear", [1, 1, 1]))))
        elif kind == "dielectric":
            dropped.add(i)
            mats.append(_Material(name, base))
        elif glossy and kind in _SIDECAR_GLOSSY:
            ks, e = _SIDECAR_GLOSSY[kind]
            mats.append(_Material(name, tuple(c * (1 - ks) for c in base), (ks, ks, ks), e))
        elif glossy and kind == "metal":
            mats.append(_Material(name, tuple(0.1 * c for c in base), tuple(0.85 * c for c in base), 300.0))
        else:
            mats.append(_Material(name, base))
    return mats, dropped


def expand_path(s: str, base: Path) -> Path:
    """A path as a scene file writes it: ``$STEREOREPRO_SHARED_SCENES`` (or ``${...}``) and ``~`` expanded; a
    relative path is relative to ``base`` (the scene file's folder)."""
    s = s.replace("${" + SHARED_ENV + "}", str(shared_scenes_dir())).replace("$" + SHARED_ENV, str(shared_scenes_dir()))
    p = Path(os.path.expanduser(s))
    return p if p.is_absolute() else (base / p)


def _build_geometry(scene: Scene) -> SceneGeometry:
    from .procedural import GENERATORS, MeshBuilder

    data, file = scene._data, str(scene.source)
    geo = data.get("geometry", {})
    names = [m.name for m in scene._materials]
    verts, faces, mids = [], [], []
    nv = 0
    if "generator" in geo:
        gen = geo["generator"]
        if gen not in GENERATORS:
            raise SceneError(
                f"{file}: geometry.generator: unknown generator {gen!r} "
                f"(expected one of: {', '.join(sorted(GENERATORS))})"
            )
        b = GENERATORS[gen]()
        try:
            v, f, m = b.build(names)
        except KeyError as e:
            raise SceneError(f"{file}: materials: {e.args[0]}") from None
        verts.append(v), faces.append(f), mids.append(m)
        nv += len(v)
    if "mesh" in geo:
        v, f, m = _load_mesh(scene, geo, file)
        verts.append(v), faces.append(f + nv), mids.append(m)
        nv += len(v)
    extra = MeshBuilder()
    for q in geo.get("quads", []):
        extra.quad(q["corner"], q["edge_u"], q["edge_v"], q["material"])
    for bx in geo.get("boxes", []):
        extra.box(bx["min"], bx["max"], bx["material"])
    if extra.material_names:
        try:
            v, f, m = extra.build(names)
        except KeyError as e:
            raise SceneError(f"{file}: geometry: {e.args[0]}") from None
        verts.append(v), faces.append(f + nv), mids.append(m)
    if not faces or sum(len(f) for f in faces) == 0:
        raise SceneError(f"{file}: geometry: the scene has no triangles")
    V = np.concatenate(verts).astype(np.float32)
    scale = float(geo.get("scale", 1.0))
    if scale != 1.0:
        V = V * np.float32(scale)
    F, M = np.concatenate(faces).astype(np.int32), np.concatenate(mids).astype(np.int32)
    if scene._textures:  # the declared patterns, cut into the geometry (stereorepro.scenes.textures)
        V, F, M = apply_textures(V, F, M, scene._textures, names)
    return SceneGeometry(V, F, M)


def _load_mesh(scene: Scene, geo: dict, file: str):
    trimesh = require("trimesh", "a scene's geometry.mesh")

    path = expand_path(geo["mesh"], scene.source.parent)
    if not path.is_file():
        raise SceneError(
            f"{file}: geometry.mesh: file not found: {path} (set {SHARED_ENV} to the folder of the "
            "shared scenes, or pass --shared-scenes to the CLI)"
        )
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as e:  # trimesh raises many types
        raise SceneError(f"{file}: geometry.mesh: cannot load {path}: {e}") from None
    offset = scene._mesh_material_offset
    if isinstance(loaded, trimesh.Scene):  # OBJ/GLB with several parts: one material per geometry, in order
        parts = list(loaded.dump()) if hasattr(loaded, "dump") else list(loaded.geometry.values())
        vs, fs, ms, n = [], [], [], 0
        for i, g in enumerate(parts):
            vs.append(np.asarray(g.vertices)), fs.append(np.asarray(g.faces) + n)
            ms.append(np.full(len(g.faces), min(i, scene._mesh_material_count - 1) + offset))
            n += len(g.vertices)
        v, f, m = np.concatenate(vs), np.concatenate(fs), np.concatenate(ms)
    else:
        v, f = np.asarray(loaded.vertices), np.asarray(loaded.faces)
        raw = loaded.metadata.get("_ply_raw", {}).get("face", {}).get("data") if hasattr(loaded, "metadata") else None
        if raw is not None and "material_id" in getattr(raw, "dtype", np.dtype([])).names:
            m = np.asarray(raw["material_id"]).astype(np.int64).reshape(-1)
            if len(m) != len(f):
                raise SceneError(f"{file}: geometry.mesh: {path} has {len(f)} faces but {len(m)} material ids")
            if len(m) and m.max() >= scene._mesh_material_count:
                raise SceneError(
                    f"{file}: geometry.mesh: material id {int(m.max())} in {path} has no material in the sidecar"
                )
            m = m + offset
        else:
            m = np.full(len(f), offset)
    keep = ~np.isin(m - offset, list(scene._mesh_dropped)) if scene._mesh_dropped else np.ones(len(f), bool)
    return v.astype(np.float32), f[keep].astype(np.int32), m[keep].astype(np.int32)


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """Load a built-in scene by name (:func:`list_scenes`) or a scene file by path.

    Raises:
        SceneError: unknown name, missing file, unknown key, wrong type or inconsistent declaration.

    Examples:
        >>> from stereorepro import load_scene
        >>> scene = load_scene("living_room")
        >>> scene.name, scene.num_frames, tuple(scene.camera(0, 8, 6).K.shape)
        ('living_room', 60, (1, 3, 3))
    """
    path = _scene_path(name_or_path)
    data = _read_toml(path)
    file = str(path)
    effects, num_frames = _effects_and_frames(data, file)
    geo = _req(data, "geometry", file, "geometry.generator or geometry.mesh")
    if "generator" not in geo and "mesh" not in geo and not geo.get("quads") and not geo.get("boxes"):
        raise SceneError(f"{file}: key 'geometry': expected 'generator', 'mesh', 'quads' or 'boxes'")
    glossy = "glossy" in effects
    materials, mesh_count, mesh_dropped = _mesh_materials(geo, path, glossy, file)
    materials += [
        _parse_material(m, f"{file}: materials.{name}", name, glossy) for name, m in data.get("materials", {}).items()
    ]
    if glossy and not any(max(m.specular) > 0 for m in materials):
        raise SceneError(f"{file}: key 'effects': declares 'glossy' but no material has a specular lobe")
    textures, second_colours = parse_textures(data, file, effects, materials)
    materials += second_colours
    lights = [_parse_light(li, f"{file}: lights[{i}]", effects) for i, li in enumerate(data.get("lights", []))]
    if "moving_light" in effects and not any(len(li.keyframes) > 1 for li in lights):
        raise SceneError(f"{file}: key 'effects': declares 'moving_light' but no light has keyframes")
    vfov, stereo = _camera_and_rig(data, file)
    pt, nt = _thresholds(data, file)
    clamp, dmin = _render_settings(data, file)
    scene = Scene(
        name=data.get("name", path.stem),
        effects=effects,
        num_frames=num_frames,
        vfov_deg=vfov,
        rig=stereo,
        position_threshold=pt,
        normal_threshold=nt,
        source=path,
        description=data.get("description", ""),
        radiance_clamp=clamp,
        point_light_min_distance=dmin,
        _data=data,
        _materials=materials,
        _lights=lights,
    )
    scene._mesh_material_offset = 0  # the mesh's materials come first
    scene._mesh_material_count = mesh_count
    scene._mesh_dropped = mesh_dropped
    scene._animations = parse_animations(data, file, materials, num_frames)
    scene._textures = textures
    moving = {n for a in scene._animations for n in a.materials} & {t.material for t in textures}
    if moving:
        raise SceneError(f"{file}: textures: materials {sorted(moving)} also move (animations): not supported")
    _check_camera_path(scene, file)
    return scene


def _scene_path(name_or_path: str | os.PathLike) -> Path:
    """The scene file of a built-in name or a path (resolved)."""
    s = str(name_or_path)
    if s.endswith(".toml") or os.sep in s or "/" in s:
        path = Path(s)
    elif s in BUILTIN_SCENES or s in BEYOND_PAPER_SCENES or s in EXTERNAL_SCENES:
        path = scenes_dir() / f"{s}.toml"
    else:
        names = list_scenes(True, True)
        close = difflib.get_close_matches(s, names, n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise SceneError(f"unknown scene {s!r}: {hint}expected one of {', '.join(names)} or a .toml path")
    return path.resolve()


def _effects_and_frames(data: dict, file: str) -> tuple[frozenset, int]:
    effects = frozenset(data.get("effects", []))
    bad = sorted(effects - KNOWN_EFFECTS)
    if bad:
        raise SceneError(
            f"{file}: key 'effects': unknown effect(s) {bad} (expected a subset of {sorted(KNOWN_EFFECTS)})"
        )
    num_frames = int(data.get("num_frames", 60))
    if num_frames < 1:
        raise SceneError(f"{file}: key 'num_frames': expected a positive integer, got {num_frames}")
    return effects, num_frames


def _mesh_materials(geo: dict, path: Path, glossy: bool, file: str) -> tuple[list[_Material], int, set[int]]:
    """The materials of ``geometry.mesh`` (from its sidecar, else one grey default), how many the mesh's material
    ids index, and the sidecar materials whose faces are dropped; none without a mesh."""
    if "mesh" not in geo:
        return [], 1, set()
    materials: list[_Material] = []
    dropped: set[int] = set()
    count = 1
    mesh_path = expand_path(geo["mesh"], path.parent)
    side = expand_path(geo["sidecar"], path.parent) if "sidecar" in geo else mesh_path.with_suffix(".json")
    if side.is_file() or "sidecar" in geo:
        materials, dropped = _sidecar_materials(side, glossy, file)
        count = max(len(materials), 1)
    if not materials:
        materials = [_Material("mesh_default", (0.6, 0.6, 0.6))]
    return materials, count, dropped


def _parse_material(m: dict, where: str, name: str, glossy: bool) -> _Material:
    """``[materials.NAME]``: albedo + specular within [0, 1] per channel, a glossy lobe only in glossy scenes."""
    albedo = _vec(m.get("albedo", [0.0, 0.0, 0.0]))
    spec = _vec(m.get("specular", [0.0, 0.0, 0.0]))
    if min(albedo + spec) < 0 or max(a + b for a, b in zip(albedo, spec)) > 1.0:
        raise SceneError(
            f"{where}: expected albedo + specular in [0, 1] per channel (energy conservation), "
            f"got albedo {albedo} and specular {spec}"
        )
    if max(spec) > 0 and not glossy:
        raise SceneError(f'{where}.specular: a glossy lobe needs the scene to declare effects = ["glossy"]')
    exponent = float(m.get("exponent", 1.0))
    if exponent < 0:
        raise SceneError(f"{where}.exponent: expected a number >= 0, got {exponent}")
    emission = _vec(m.get("emission", [0.0, 0.0, 0.0]))
    if min(emission) < 0:
        raise SceneError(f"{where}.emission: expected non-negative values, got {emission}")
    return _Material(name, albedo, spec, exponent, emission)


def _parse_light(li: dict, where: str, effects: frozenset) -> _PointLight:
    """``[[lights]]``: a point light with an intensity and a position, or keyframes (``moving_light`` scenes)."""
    if li.get("type", "point") != "point":
        raise SceneError(f"{where}.type: expected 'point', got {li['type']!r}")
    inten = np.array(_req(li, "intensity", where, "RGB intensity in W/sr"), np.float64)
    if "position" in li and "keyframes" in li:
        raise SceneError(f"{where}: expected either 'position' or 'keyframes', not both")
    if "keyframes" in li:
        if "moving_light" not in effects:
            raise SceneError(f'{where}.keyframes: a moving light needs effects = ["moving_light"]')
        kf = np.array(li["keyframes"], np.float64)
    else:
        kf = np.array([_req(li, "position", where, "position or keyframes")], np.float64)
    return _PointLight(inten, kf)


def _camera_and_rig(data: dict, file: str) -> tuple[float, StereoRig]:
    """``[camera]`` (its keys present, the vertical field of view) and the ``[rig]``."""
    cam = _req(data, "camera", file, "camera path")
    for k in ("positions", "targets", "vfov_deg"):
        _req(cam, k, f"{file}: camera", k)
    vfov = float(cam["vfov_deg"])
    if not (0 < vfov < 180):
        raise SceneError(f"{file}: camera.vfov_deg: expected a number in (0, 180), got {vfov}")
    rig = data.get("rig", {})
    try:
        stereo = StereoRig(float(rig.get("eye_separation", 0.065)), rig.get("convergence_distance"))
    except ValueError as e:
        raise SceneError(f"{file}: rig: {e}") from None
    return vfov, stereo


def _thresholds(data: dict, file: str) -> tuple[float, float]:
    """``[reprojection]``: the position and normal thresholds, both positive."""
    rep = _req(data, "reprojection", file, "position_threshold and normal_threshold")
    pt = float(_req(rep, "position_threshold", f"{file}: reprojection", "scene units"))
    nt = float(_req(rep, "normal_threshold", f"{file}: reprojection", "unit-normal distance"))
    if not (pt > 0 and nt > 0):
        raise SceneError(f"{file}: reprojection: thresholds must be positive, got {pt}, {nt}")
    return pt, nt


def _render_settings(data: dict, file: str) -> tuple[float, float | None]:
    """``[render]``: the radiance clamp (0 = auto) and the point lights' minimum distance (None = per frame)."""
    ren = data.get("render", {})
    clamp = float(ren.get("radiance_clamp", 0.0))
    if clamp < 0:
        raise SceneError(f"{file}: render.radiance_clamp: expected a number >= 0 (0 = auto), got {clamp}")
    dmin = ren.get("point_light_min_distance")
    if dmin is not None and not float(dmin) > 0:
        raise SceneError(f"{file}: render.point_light_min_distance: expected a positive number, got {dmin}")
    return clamp, None if dmin is None else float(dmin)


def _check_camera_path(scene: Scene, file: str) -> None:
    """Every frame's head pose is a valid look-at (the path is interpolated: a keyframe check is not enough)."""
    for f in range(scene.num_frames):
        try:
            scene.head_pose(f)
        except ValueError as e:
            raise SceneError(f"{file}: camera (positions / targets / up) at frame {f}: {e}") from None
