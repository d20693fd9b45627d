"""A wavefront path tracer over structure-of-arrays batches (numpy float32), intersecting with embreex.

Per sample (the paper's "one primary ray, one secondary ray, and two shadow rays"), the stages of
:data:`STAGES`, in this order, on a batch of paths at a time:

1. ``generate`` - a primary ray through a uniformly jittered position inside the pixel (``pixel_sampling="box"``,
   the default: box-filter antialiasing), or through the pixel centre, exactly the G-buffer's ray
   (``pixel_sampling="center"``: TAA's one sample per frame at the camera's jittered position, see
   :meth:`PathTracer.render`);
2. ``intersect_primary`` - closest hit ``x1`` (a miss adds nothing);
3. ``shade_x1`` - emitted radiance of ``x1`` (emitters seen directly); one light sample at ``x1`` (a shadow ray),
   MIS-weighted (balance heuristic) against BSDF sampling for area lights; the BSDF sample of the bounce;
4. ``intersect_bounce`` - closest hit ``x2`` of the secondary ray;
5. ``shade_x2`` - if ``x2`` is emissive, its emission with the complementary MIS weight; one light sample at
   ``x2`` (the second shadow ray), unweighted (no further bounce);
6. ``intersect_shadow`` - both shadow-ray sets tested in one occlusion query;
7. ``accumulate`` - the visible light samples, the firefly clamps (below) and the sample's sum.

This equals a path tracer with maximum path depth 3 (Mitsuba's ``path`` integrator with ``max_depth = 3``):
emission + direct light + one bounce of indirect light.

Firefly control (``PathTracer(clamp=...)``)
-------------------------------------------
Next-event estimation has a 1/r^2 geometry term: a vertex very close to an area light (or any point light) yields
rare samples thousands of times the median that dominate RMSE. Each *vertex's
reflected-radiance estimate* is therefore clamped to a per-scene limit ``C``, before it is multiplied by the
throughput of the vertices before it:

* ``L_r(x2)`` = NEE at ``x2`` (the radiance ``x2`` sends towards ``x1``, excluding its emission), then
* ``L_r(x1)`` = MIS-weighted NEE at ``x1`` + ``f cos / pdf * (MIS-weighted Le(x2) + clamped L_r(x2))``,

and the pixel sample is ``Le(x1) + clamped L_r(x1)``: emitters seen directly are never clamped (they are exact).
A clamped estimate is scaled as a whole, ``L *= C / max_c L_c`` when its largest channel exceeds ``C``: every
channel ends up <= ``C`` and the hue (channel ratios) of the sample is kept.

``C`` is an upper bound of the *true* reflected radiance (:func:`~stereorepro.render.lights.radiance_bound`: for
area lights the largest emitted radiance, since an energy-conserving BSDF reflects at most what fully surrounding
emitters send; a point light adds ``f I / d^2`` with ``f`` a material's largest BSDF value and ``d`` the light's
distance to the nearest surface of that material). Values
above ``C`` are therefore impossible as expectations and the clamp only trims rare samples; its bias is
``-E[(X - C)+]``, zero where no estimate exceeds ``C``. ``clamp=None`` gives the plain unbiased estimator (used
for analytic tests and the Mitsuba comparison).

G-buffers (depth, normal, position, albedo, material id) come from one unjittered primary ray per pixel centre,
deterministic and independent of ``spp``/``sample_offset``; they are counted as ``ray_counts["gbuffer"]``.

Random numbers are counter-based (:mod:`stereorepro.render.rng`), so results are bit-identical whatever the batch
size or number of workers. Work is split into contiguous pixel ranges, one per worker thread; every stage of a
range runs in its thread (embreex and numpy's large-array loops release the GIL).

Backends (``PathTracer(backend=...)``)
--------------------------------------
The stages other than intersection exist twice: in numpy (:class:`_NumpyStages`, the reference) and in C++
(:class:`_NativeStages`: ``stereorepro._core``'s ``tracer_generate`` and ``TracerShader.shade1/shade2/accumulate``
from ``cpp_ext/src/shade_tracer.cpp``). Both fill in the one sequence :meth:`PathTracer._trace_paths` runs; the
intersection stages are theirs in common, in embreex (:mod:`._embree`), on compacted structure-of-arrays batches.
Both use the same random numbers and the same float32 operations in the same order (transcendentals in float64,
see :mod:`.bsdf`), so radiance, ray counts and the rays themselves are bit-identical
(``tests/render/test_render_native.py``).

* ``backend="auto"`` (default): native when ``_core`` has the tracer kernels, else numpy;
* ``"numpy"``: the reference; ``"native"``: the C++ stages (RuntimeError when ``_core`` lacks them);
* the environment variable ``STEREOREPRO_BACKEND`` (``auto`` | ``numpy`` | ``native`` | ``torch``), when set,
  overrides the argument, as it does for the reprojection kernels; ``"torch"`` there names the project's reference
  path, which for the tracer is numpy (``"torch"`` is mapped to ``"numpy"``).

The native kernels are single-threaded: parallelism is the worker threads over pixel ranges (one level), each
running its own embreex queries and kernels with the GIL released.
"""

from __future__ import annotations

import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .. import _backend
from .._extras import require
from ..camera import PinholeCamera
from ..errors import ParameterError
from . import bsdf as _bsdf
from ._embree import SplitBVH, TriangleBVH
from .lights import EmitterTable, LightSet, TriangleDistances, luminance, radiance_bound
from .rng import DIM, path_keys, stream_key, uniform

try:  # optional: the package works without the compiled core
    from .. import _core
except ImportError:  # pragma: no cover - depends on the build
    _core = None

__all__ = [
    "PathTracer",
    "RenderResult",
    "ray_epsilon",
    "native_available",
    "resolve_backend",
    "BACKENDS",
    "ENV_VAR",
    "PIXEL_SAMPLINGS",
]

BACKENDS = _backend.TRACER_NAMES
#: ``PathTracer.render(pixel_sampling=...)``: a uniform position in the pixel per sample, or the pixel centre.
PIXEL_SAMPLINGS = ("box", "center")
ENV_VAR = _backend.ENV_VAR


def native_available() -> bool:
    """True when ``stereorepro._core`` is importable and has the tracer kernels.

    Examples:
        >>> from stereorepro.render.tracer import native_available
        >>> isinstance(native_available(), bool)
        True
    """
    return _core is not None and hasattr(_core, "TracerShader") and hasattr(_core, "tracer_generate")


def resolve_backend(backend: str = "auto") -> str:
    """``"numpy"`` or ``"native"`` for a requested tracer backend, by the package's one backend rule
    (:mod:`stereorepro._backend`: ``STEREOREPRO_BACKEND`` overrides the argument; ``"torch"`` and ``"reference"``
    name the reference path, which for the tracer is numpy). Raises ValueError for an unknown name and
    RuntimeError when ``"native"`` is asked for but ``_core`` lacks the kernels.

    Examples:
        >>> from stereorepro.render.tracer import resolve_backend
        >>> resolve_backend("auto") in ("numpy", "native")
        True
        >>> try:
        ...     resolve_backend("cuda")
        ... except ValueError as e:
        ...     print(type(e).__name__)
        ParameterError
    """
    why = "stereorepro._core with the tracer kernels is not built or not importable"
    chosen = _backend.resolve(backend, BACKENDS, lambda: None if native_available() else why, who="PathTracer: ")
    return "native" if chosen == "native" else "numpy"


def _tick(times: dict | None, name: str, t0: float) -> float:
    """Stage profiling (off unless ``PathTracer._stage_times`` is a dict): add the time since ``t0`` to ``name``."""
    if times is None:
        return t0
    t = time.perf_counter()
    times[name] = times.get(name, 0.0) + (t - t0)
    return t


@dataclass(frozen=True)
class RenderResult:
    """One rendered image of one camera (B = 1). All tensors are float32 on the CPU unless noted.

    Attributes:
        radiance: (1, 3, H, W) linear RGB, the mean of ``spp`` samples; 0 where ``pixel_mask`` is False.
        depth: (1, 1, H, W) camera-space z of the surface at the pixel centre; ``+inf`` where there is no surface
            (a miss or a pixel outside ``pixel_mask``). ``None`` when G-buffers were not requested.
        normal: (1, 3, H, W) unit world-space shading normal, flipped to face the camera; 0 without surface.
        position: (1, 3, H, W) world position of the surface; 0 without surface.
        albedo: (1, 3, H, W) diffuse albedo of the surface; 0 without surface.
        material_id: (1, 1, H, W) int32 material index of the scene; -1 without surface.
        ray_counts: rays traced per kind: ``primary``, ``secondary``, ``shadow``, ``gbuffer``.
        spp: samples per pixel of ``radiance``.
        time_s: wall time of the call in seconds.
        motion: (1, 2, H, W) screen-space motion to the previous frame in pixels, ``prev_pixel = pixel + motion``
            (OpenCV axes, pixel centres at +0.5): where the surface point seen at the pixel centre was in the
            previous camera's image. NaN where there is no surface, or where the point was not in front of the
            previous camera. ``None`` unless ``prev_camera`` was given.
        motion_world: (1, 3, H, W) world-space motion of that surface point, ``P_prev = P + motion_world`` (0 on
            static geometry); NaN where there is no surface. ``None`` unless ``prev_camera`` was given.
        object_id: (1, 1, H, W) int32 index of the moving object seen at the pixel (-1: static geometry or no
            surface); ``None`` unless the scene declares ``moving_objects``.

    Examples:
        >>> from stereorepro import PathTracer, load_scene
        >>> scene = load_scene("living_room")
        >>> result = PathTracer(scene, workers=1).render(scene.camera(0, 8, 6), frame=0, spp=1)
        >>> tuple(result.radiance.shape), tuple(result.normal.shape), result.spp, result.ray_counts["primary"]
        ((1, 3, 6, 8), (1, 3, 6, 8), 1, 48)
        >>> result.motion is None  # no prev_camera given
        True
    """

    radiance: Tensor
    depth: Tensor | None
    normal: Tensor | None
    position: Tensor | None
    albedo: Tensor | None
    material_id: Tensor | None
    ray_counts: dict = field(default_factory=dict)
    spp: int = 0
    time_s: float = 0.0
    motion: Tensor | None = None
    motion_world: Tensor | None = None
    object_id: Tensor | None = None


_GBUFFER_FIELDS = ("depth", "normal", "position", "albedo", "material_id", "motion", "motion_world", "object_id")


def ray_epsilon(vertices: np.ndarray) -> float:
    """Origin offset along the normal for secondary and shadow rays, scaled to the scene.

    ``2e-5 * bbox diagonal`` covers the intersection error (relative to the ray length) and ``4e-7 * max |coord|``
    (about 3 float32 ulps) covers the rounding of positions far from the origin.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.tracer import ray_epsilon
        >>> f"{ray_epsilon(np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]])):.2e}"
        '1.02e-04'
    """
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    return 2e-5 * diag + 4e-7 * float(np.abs(v).max()) + 1e-30


def _dot(a, b):
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _clamp_radiance(rad: np.ndarray, limit: float | None) -> np.ndarray:
    """Scale rows of ``rad`` (N, 3) whose largest channel exceeds ``limit`` down to it (hue kept); in place."""
    if limit is None or len(rad) == 0:
        return rad
    m = rad.max(axis=1)
    over = m > np.float32(limit)
    if over.any():
        rad[over] *= (np.float32(limit) / m[over])[:, None]
    return rad


def _normalize(v):
    n = np.sqrt(_dot(v, v))
    return v / np.where(n > 0, n, np.float32(1))[:, None]


def _check_render_args(spp, sample_offset, pixel_sampling) -> None:
    if int(spp) < 1:
        raise ValueError(f"render: spp must be >= 1, got {spp}")
    if int(sample_offset) < 0:
        raise ParameterError(f"render: sample_offset must be >= 0, got {sample_offset}")
    if int(sample_offset) + int(spp) > 2**63:  # the 64-bit sample index would wrap
        raise ParameterError(
            f"render: sample_offset + spp must be at most 2**63 (the 64-bit sample index), got "
            f"{int(sample_offset) + int(spp)}"
        )
    if not (isinstance(pixel_sampling, str) and pixel_sampling in PIXEL_SAMPLINGS):
        raise ValueError(f"render: pixel_sampling must be one of {PIXEL_SAMPLINGS}, got {pixel_sampling!r}")


class _PixelSums:
    """A frame's radiance as its samples arrive, per range of pixels. With ``spp = 1`` the one sample is the pixel
    value (``0 + x / 1`` in float64 and back is ``x``, but for -0 -> +0, hence the ``+ 0``): written straight into the
    planar image. Otherwise samples are summed per pixel in float64, in a fixed order (bit-identical whatever the
    chunking), and divided by ``spp`` at the end."""

    def __init__(self, pixels: np.ndarray, H: int, W: int, spp: int, full: bool):
        self.pixels, self.H, self.W, self.spp = pixels, H, W, spp
        self.full = full  # pixels = arange(H * W): ranges of pixels are column ranges of the image
        self.rad = np.zeros((3, H * W), np.float32)  # planar, the layout of the output tensor
        self.acc = None if spp == 1 else np.zeros((len(pixels), 3), np.float64)

    def add(self, lo: int, hi: int, contrib: np.ndarray) -> None:
        """Samples (kk, hi - lo, 3) float32 of the pixels ``pixels[lo:hi]``, sample by sample."""
        if self.acc is None:
            if self.full:
                np.add(contrib[0].T, np.float32(0), out=self.rad[:, lo:hi])
            else:
                self.rad[:, self.pixels[lo:hi]] = contrib[0].T + np.float32(0)
            return
        view = self.acc[lo:hi]
        for j in range(len(contrib)):
            view += contrib[j]

    def image(self) -> Tensor:
        """The mean of the samples, (1, 3, H, W) float32; 0 at pixels not traced."""
        if self.acc is not None:
            self.rad[:, self.pixels] = (self.acc / self.spp).astype(np.float32).T
        return torch.from_numpy(self.rad.reshape(1, 3, self.H, self.W))


@dataclass
class _Frame:
    """Per-render constants."""

    key: int
    width: int
    center: np.ndarray  # (3,) float32 camera centre (world)
    dir_from_pix: np.ndarray  # (3, 3) float64: world direction (camera z = 1) = M @ [u, v, 1]
    lights: LightSet
    limit: float | None = None  # firefly clamp C (None: off)
    shader: object = None  # _core.TracerShader of the frame's lights (native backend)
    M32: np.ndarray | None = None  # (9,) float32 dir_from_pix, as _camera_dirs rounds it
    geom: "_Geometry" = None  # the frame's triangles (moving objects placed)
    center_rays: bool = False  # pixel_sampling="center": primary rays are the G-buffer's rays (see _center_dirs)


@dataclass(frozen=True)
class _Geometry:
    """The triangles of one frame: positions, unit face normals and their BVH (one per tracer for static scenes,
    one per frame with moving objects)."""

    frame: int | None  # None: static (valid for every frame)
    vertices: np.ndarray  # (V, 3) float32
    face_normal: np.ndarray  # (F, 3) float32
    bvh: TriangleBVH | SplitBVH


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces].astype(np.float64)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(fn, axis=1, keepdims=True)
    return (fn / np.where(ln > 0, ln, 1.0)).astype(np.float32)


class PathTracer:
    """Path tracer for one scene (static geometry: the BVH is built once, at construction).

    Args:
        scene: a scene from :func:`stereorepro.load_scene`.
        seed: RNG seed (the first field of every random number's key).
        workers: threads (default: the usable CPU count).
        max_batch: most paths one worker traces at once: frames are split into pixel ranges of at most this many
            pixels (see :meth:`_ranges`). It bounds memory (about 1 KiB per path) and keeps a batch's arrays and the
            BVH in cache (the default is chosen by ``bench/tracer.py``; see docs/performance.md). Results do not depend on it.
        clamp: firefly clamp on reflected radiance (see the module docstring): ``"auto"`` (default) uses the
            scene's ``[render] radiance_clamp`` when it is > 0, else the bound of
            :func:`~stereorepro.render.lights.radiance_bound` (per frame for moving lights); a positive number is
            the limit itself; ``None`` disables clamping (unbiased). :meth:`radiance_limit` reports the value.
        backend: ``"auto"`` (default), ``"numpy"`` (reference), ``"native"`` (C++ shading stages) or ``"torch"``
            (= ``"numpy"``); ``STEREOREPRO_BACKEND`` overrides it (see the module docstring). The resolved choice is
            :attr:`backend` (``"numpy"`` or ``"native"``); both give bit-identical results.

    Only the effects the scene declares are simulated: the glossy lobe is evaluated only when ``"glossy" in
    scene.effects``; lights are merged once per tracer unless ``"moving_light" in scene.effects`` (then once per
    frame). ``stats`` counts these preparations (``bvh_builds``, ``light_prepare``).

    Examples:
        >>> from stereorepro import PathTracer, load_scene
        >>> scene = load_scene("living_room")
        >>> tracer = PathTracer(scene, seed=0, workers=1)
        >>> result = tracer.render(scene.camera(0, 8, 6), frame=0, spp=1)  # 8x6 pixels, 1 sample each
        >>> tuple(result.radiance.shape), tuple(result.depth.shape), tracer.stats["bvh_builds"]
        ((1, 3, 6, 8), (1, 1, 6, 8), 1)
    """

    def __init__(
        self,
        scene,
        seed: int = 0,
        workers: int | None = None,
        max_batch: int = 1 << 15,
        clamp: str | float | None = "auto",
        backend: str = "auto",
    ):
        self.backend = resolve_backend(backend)
        if workers is None:
            try:
                workers = len(os.sched_getaffinity(0))
            except AttributeError:  # pragma: no cover
                workers = os.cpu_count() or 1
        if int(workers) < 1:
            raise ValueError(f"PathTracer: workers must be >= 1, got {workers}")
        if int(max_batch) < 1:
            raise ValueError(f"PathTracer: max_batch must be >= 1, got {max_batch}")
        if clamp is not None and clamp != "auto":
            if isinstance(clamp, str) or isinstance(clamp, bool) or not (float(clamp) > 0):
                raise ValueError(f"PathTracer: clamp must be 'auto', None or a positive number, got {clamp!r}")
            if not math.isfinite(float(clamp)):
                clamp = None
            else:
                clamp = float(clamp)
        self.clamp = clamp
        self.scene = scene
        self.seed = int(seed)
        self.workers = int(workers)
        self.max_batch = int(max_batch)
        self.stats = {"bvh_builds": 0, "light_prepare": 0}
        self.glossy = "glossy" in scene.effects
        self.moving_light = "moving_light" in scene.effects
        self.moving_objects = "moving_objects" in scene.effects

        geo = scene.geometry()
        mats = scene.material_table()
        vertices = np.ascontiguousarray(geo.vertices, np.float32)
        faces = np.ascontiguousarray(geo.faces, np.int32)
        #: (F,) int32 index of the moving object of each face, -1 for static faces.
        self.face_object = scene.face_objects() if self.moving_objects else np.full(len(faces), -1, np.int32)
        if self.moving_objects:  # moving faces get vertices of their own, so that moving them moves nothing else
            moving = np.flatnonzero(self.face_object >= 0)
            idx = faces[moving].reshape(-1)
            faces = faces.copy()
            faces[moving] = (len(vertices) + np.arange(len(idx), dtype=np.int32)).reshape(-1, 3)
            vertices = np.concatenate([vertices, vertices[idx]])
            self._vertex_object = np.full(len(vertices), -1, np.int32)
            self._vertex_object[faces[moving].reshape(-1)] = np.repeat(self.face_object[moving], 3)
        self.vertices = vertices  # at rest (frame-independent for static scenes)
        self.faces = faces
        self.face_material = np.ascontiguousarray(geo.material_ids, np.int32)
        self.face_normal = _face_normals(self.vertices, self.faces)
        self.kd = np.asarray(mats["albedo"], np.float32).reshape(-1, 3)
        self.emission = np.asarray(mats["emission"], np.float32).reshape(-1, 3)
        self.mat_emissive = luminance(self.emission) > 0
        if self.glossy:
            self.ks = np.asarray(mats["specular"], np.float32).reshape(-1, 3)
            self.exponent = np.asarray(mats["exponent"], np.float32).reshape(-1)
            ld, ls = luminance(self.kd), luminance(self.ks)
            self.p_spec = np.where(ld + ls > 0, ls / np.maximum(ld + ls, 1e-12), 0).astype(np.float32)
        self.eps = np.float32(ray_epsilon(self.vertices))

        self._static_bvh()
        self._geom_cache: _Geometry | None = None  # the last frame's geometry (moving objects)
        self._emitters = EmitterTable(self.vertices, self.faces, self.emission[self.face_material])
        self._materials = mats
        self._lights_cache: tuple | None = None
        self._lock = threading.Lock()
        self._stage_times: dict | None = None  # set to {} to accumulate per-stage seconds (profiling)
        self._triangle_distances: tuple | None = None  # (frame, TriangleDistances), built on first use by _limit
        self._ws_free: list[dict] = []  # scratch arrays of the native stages, one set per concurrent worker
        self._stages = _NativeStages(self) if self.backend == "native" else _NumpyStages(self)

    # ------------------------------------------------------------------ geometry
    def _static_bvh(self) -> None:
        """The BVH built once, at construction: of every face for static scenes, of the faces that never move with
        ``moving_objects`` (none when every face moves); sets ``_bvh``, ``_static_ids`` and ``_moving_ids``."""
        moving = self.face_object >= 0
        self._static_ids = np.flatnonzero(~moving).astype(np.int32)
        self._moving_ids = np.flatnonzero(moving).astype(np.int32)
        #: first vertex of the moving faces (their vertices are the last ones, see __init__)
        self._moving_v0 = len(self.vertices) - 3 * len(self._moving_ids)
        self._bvh = None
        if len(self._static_ids):
            static = self.faces if not self.moving_objects else self.faces[self._static_ids]
            self._bvh = TriangleBVH(self.vertices, static)
            self.stats["bvh_builds"] += 1

    def geometry(self, frame: int) -> "_Geometry":
        """The triangles of ``frame``: the tracer's one BVH for static scenes; with ``moving_objects`` the moving
        faces placed by :meth:`~stereorepro.scenes.Scene.object_transforms`, their own BVH built for that frame and
        queried together with the static faces' BVH (:class:`~._embree.SplitBVH`; embreex has no instancing and no
        vertex updates; the last frame's geometry is kept)."""
        if not self.moving_objects:
            return _Geometry(None, self.vertices, self.face_normal, self._bvh)
        frame = int(frame)
        with self._lock:
            cached = self._geom_cache
            if cached is not None and cached.frame == frame:
                return cached
        v = self.object_vertices(frame)
        mv, v0 = self._moving_ids, self._moving_v0
        fn = self.face_normal.copy()
        fn[mv] = _face_normals(v, self.faces[mv])
        if self._bvh is None:
            bvh = TriangleBVH(v, self.faces)
        else:
            bvh = SplitBVH(self._bvh, self._static_ids, v[v0:], self.faces[mv] - v0, mv)
        geom = _Geometry(frame, v, fn, bvh)
        with self._lock:
            self.stats["bvh_builds"] += 1
            self._geom_cache = geom
        return geom

    def object_vertices(self, frame: float) -> np.ndarray:
        """(V, 3) float32 vertex positions at ``frame`` (moving objects placed; the rest as they are)."""
        if not self.moving_objects:
            return self.vertices
        T = self.scene.object_transforms(frame)
        v0 = self._moving_v0
        v = self.vertices[v0:].astype(np.float64)
        obj = self._vertex_object[v0:]
        out = self.vertices.copy()
        for o in range(len(T)):
            sel = obj == o
            out[v0:][sel] = (v[sel] @ T[o, :3, :3].T + T[o, :3, 3]).astype(np.float32)
        return out

    # ------------------------------------------------------------------ lights
    def lights(self, frame: int) -> LightSet:
        """The :class:`LightSet` of ``frame`` (built once for static lights, per frame for moving ones)."""
        return self._prepare_lights(frame)[0]

    def radiance_limit(self, frame: int = 0) -> float | None:
        """The firefly clamp ``C`` used at ``frame`` (``None`` when clamping is disabled)."""
        return self._prepare_lights(frame)[1]

    def _prepare_lights(self, frame: int) -> tuple[LightSet, float | None]:
        return self._prepare_lights_full(frame)[:2]

    def _prepare_lights_full(self, frame: int) -> tuple[LightSet, float | None, object]:
        key = int(frame) if (self.moving_light or self.moving_objects) else None
        cache = self._lights_cache
        if cache is not None and cache[0] == key:
            return cache[1], cache[2], cache[3]
        pos, inten = self.scene.point_lights(0 if key is None else key)
        ls = LightSet(self._emitters, pos, inten)
        limit = self._limit(pos, inten, int(frame))
        shader = self._make_shader(ls, self.geometry(frame)) if self.backend == "native" else None
        self.stats["light_prepare"] += 1
        self._lights_cache = (key, ls, limit, shader)
        return ls, limit, shader

    def _make_shader(self, ls: LightSet, geom: "_Geometry"):
        """The native stages' tables (scene materials + this light set), as contiguous arrays."""
        nm = len(self.kd)
        f32 = np.float32
        if self.glossy:
            ks, ex, ps = self.ks, self.exponent, self.p_spec
        else:
            ks, ex, ps = np.zeros((nm, 3), f32), np.zeros(nm, f32), np.zeros(nm, f32)
        c = np.ascontiguousarray
        return _core.TracerShader(
            c(geom.face_normal, f32),
            c(self.face_material, np.int32),
            c(self.kd, f32),
            c(ks, f32),
            c(ex, f32),
            c(ps, f32),
            c(self.emission, f32),
            c(self.mat_emissive, bool),
            float(self.eps),
            bool(self.glossy),
            bool(ls.empty),
            c(ls.cdf, np.float64),
            c(ls.prob, np.float64),
            c(ls._table, f32),
            int(ls.num_area),
            c(ls.point_pos, f32),
            c(ls.point_int, f32),
            c(ls.pdf_area_face, f32),
        )

    def _limit(self, pos: np.ndarray, inten: np.ndarray, frame: int) -> float | None:
        if self.clamp is None:
            return None
        if self.clamp != "auto":
            return self.clamp
        declared = float(getattr(self.scene, "radiance_clamp", 0.0) or 0.0)
        if declared > 0:
            return declared
        dmin = getattr(self.scene, "point_light_min_distance", None)
        if len(pos) == 0:
            dist = np.zeros(0)
        elif dmin is not None:
            dist = np.full(len(pos), float(dmin))
        else:  # distance of each light to the nearest surface of each material (L, M)
            geom = self.geometry(frame)
            if self._triangle_distances is None or self._triangle_distances[0] != geom.frame:
                # per-face data once per tracer (moving lights ask every frame), per frame for moving objects
                self._triangle_distances = (geom.frame, TriangleDistances(geom.vertices, self.faces))
            dist = self._triangle_distances[1].grouped(pos, self.face_material, len(self.kd))
        m = self._materials
        c = radiance_bound(
            m["emission"],
            m["albedo"],
            m["specular"] if self.glossy else np.zeros_like(m["albedo"]),
            m["exponent"],
            inten,
            dist,
        )
        return c if math.isfinite(c) else None

    # ------------------------------------------------------------------ public API
    def render(
        self,
        camera: PinholeCamera,
        frame: int,
        spp: int,
        sample_offset: int = 0,
        pixel_mask: Tensor | None = None,
        eye: int = 0,
        gbuffers: bool = True,
        progress: bool = False,
        prev_camera: PinholeCamera | None = None,
        prev_frame: int | None = None,
        pixel_sampling: str = "box",
    ) -> RenderResult:
        """Render radiance (and G-buffers) of one camera.

        Args:
            camera: :class:`PinholeCamera` with batch size 1.
            frame: frame index in ``[0, scene.num_frames)`` (lights and the RNG key depend on it).
            spp: samples per pixel (>= 1).
            sample_offset: first sample index of the stream (disjoint streams for disjoint ranges).
            pixel_mask: optional bool (H, W) or (1, 1, H, W); only True pixels are traced (others cost no rays,
                get radiance 0 and no G-buffer).
            eye: RNG key field (0 = left, 1 = right).
            gbuffers: also compute the G-buffers (from separate centre rays; radiance is unchanged).
            progress: show a tqdm progress bar.
            prev_camera: the same eye's camera at the previous frame: the G-buffers then include ``motion`` and
                ``motion_world`` (see :class:`RenderResult`).
            prev_frame: the frame ``motion`` refers to (default ``max(frame - 1, 0)``).
            pixel_sampling: where in its pixel each sample's primary ray goes. ``"box"`` (default): a uniformly
                random position in [x, x+1) × [y, y+1) per sample (box-filter antialiasing; the renders of previous
                versions, bit for bit). ``"center"``: the pixel centre, with exactly the G-buffer's ray (same origin
                and direction handed to embree, then normalised), so every sample's first hit is the G-buffer's
                surface; the samples of a pixel differ only after the first hit. With a jittered camera
                (:meth:`~stereorepro.camera.PinholeCamera.jittered`, :func:`~stereorepro.camera.jitter_offset`) this
                is TAA's one sample per frame at the jittered position, consistent with that camera's G-buffer.

        Returns:
            :class:`RenderResult` with (1, C, H, W) tensors.
        """
        t0 = time.perf_counter()
        _check_render_args(spp, sample_offset, pixel_sampling)
        fr, pixels, H, W = self._setup(camera, frame, pixel_mask, eye)
        fr.center_rays = pixel_sampling == "center"
        counts = {"primary": 0, "secondary": 0, "shadow": 0, "gbuffer": 0}
        sums = _PixelSums(pixels, H, W, int(spp), full=pixel_mask is None)
        bar = None
        if progress:
            tqdm = require("tqdm", "the renderer's progress bar").tqdm
            bar = tqdm(total=int(spp) * len(pixels), unit="path", unit_scale=True, desc="render")

        def work(lo_hi):
            return self._trace_range(fr, pixels, lo_hi, int(spp), int(sample_offset), sums, bar)

        for c in self._run(work, self._ranges(len(pixels))):
            for name, v in c.items():
                counts[name] += v
        if bar is not None:
            bar.close()
        radiance = sums.image()
        g = self._gbuffer_full(fr, frame, pixels, H, W, counts, prev_camera, prev_frame) if gbuffers else {}
        return RenderResult(
            radiance=radiance,
            ray_counts=counts,
            spp=int(spp),
            time_s=time.perf_counter() - t0,
            **{k: g.get(k) for k in _GBUFFER_FIELDS},
        )

    def _trace_range(
        self,
        fr: _Frame,
        pixels: np.ndarray,
        lo_hi: tuple[int, int],
        spp: int,
        sample_offset: int,
        sums: "_PixelSums",
        bar,
    ) -> dict:
        """All ``spp`` samples of the pixels ``pixels[lo:hi]`` (one worker), in batches of at most ``max_batch``
        paths (several samples per batch when the range is short); returns the rays traced per kind."""
        lo, hi = lo_hi
        c = {"primary": 0, "secondary": 0, "shadow": 0}
        m = hi - lo
        k = max(1, self.max_batch // max(m, 1))
        with self._workspace_slot() as slot:
            for s0 in range(0, spp, k):
                kk = min(k, spp - s0)
                pix = pixels[lo:hi] if kk == 1 else np.tile(pixels[lo:hi], kk)
                samp = np.repeat(np.arange(s0, s0 + kk, dtype=np.int64) + sample_offset, m)
                contrib = self._trace_paths(fr, pix, samp, c, slot).reshape(kk, m, 3)
                t0 = time.perf_counter() if self._stage_times is not None else 0.0
                sums.add(lo, hi, contrib)
                _tick(self._stage_times, "accumulate_frame", t0)
                if bar is not None:
                    with self._lock:
                        bar.update(kk * m)
        return c

    def gbuffer(
        self,
        camera: PinholeCamera,
        frame: int,
        pixel_mask: Tensor | None = None,
        prev_camera: PinholeCamera | None = None,
        prev_frame: int | None = None,
    ) -> RenderResult:
        """G-buffers only (radiance zeros, ``spp = 0``, only ``gbuffer`` rays); same values as :meth:`render`."""
        t0 = time.perf_counter()
        fr, pixels, H, W = self._setup(camera, frame, pixel_mask, 0, need_lights=False)
        counts = {"primary": 0, "secondary": 0, "shadow": 0, "gbuffer": 0}
        g = self._gbuffer_full(fr, frame, pixels, H, W, counts, prev_camera, prev_frame)
        return RenderResult(
            radiance=torch.zeros(1, 3, H, W),
            ray_counts=counts,
            spp=0,
            time_s=time.perf_counter() - t0,
            **{k: g.get(k) for k in _GBUFFER_FIELDS},
        )

    def _gbuffer_full(self, fr, frame, pixels, H, W, counts, prev_camera, prev_frame) -> dict:
        """The G-buffer stage, then (with ``prev_camera``) the motion stage and (moving objects) object ids."""
        if prev_camera is not None:
            if not isinstance(prev_camera, PinholeCamera) or prev_camera.batch_size != 1:
                raise TypeError("render: prev_camera must be a PinholeCamera with batch size 1")
            prev_frame = max(int(frame) - 1, 0) if prev_frame is None else int(prev_frame)
            if not (0 <= prev_frame < int(self.scene.num_frames)):
                raise ValueError(f"render: prev_frame must be in [0, {self.scene.num_frames}), got {prev_frame}")
        g = self._gbuffer(fr, pixels, H, W, counts)
        prim = g.pop("_prim")
        if prev_camera is not None:
            g["motion"], g["motion_world"] = self._motion(g["position"], prim, frame, prev_camera, prev_frame, H, W)
        if self.moving_objects:
            obj = np.where(prim >= 0, self.face_object[np.maximum(prim, 0)], -1).astype(np.int32)
            g["object_id"] = torch.from_numpy(obj.reshape(1, 1, H, W))
        return g

    def _motion(
        self,
        position: Tensor,
        prim: np.ndarray,
        frame: int,
        prev_camera: PinholeCamera,
        prev_frame: int,
        H: int,
        W: int,
    ) -> tuple[Tensor, Tensor]:
        """The motion stage: ``motion`` (1, 2, H, W) and ``motion_world`` (1, 3, H, W) (see :class:`RenderResult`),
        from the G-buffer's positions and hit triangles, in float64."""
        hit = prim >= 0
        P = position[0].reshape(3, -1).T.double().numpy()  # (HW, 3)
        mw = np.zeros_like(P)
        if self.moving_objects:
            T_cur, T_prev = self.scene.object_transforms(frame), self.scene.object_transforms(prev_frame)
            obj = np.where(hit, self.face_object[np.maximum(prim, 0)], -1)
            for o in range(len(T_cur)):
                sel = obj == o
                if sel.any():
                    D = T_prev[o] @ np.linalg.inv(T_cur[o])  # world at frame -> world at prev_frame
                    mw[sel] = P[sel] @ D[:3, :3].T + D[:3, 3] - P[sel]
        P_prev = P + mw
        T = prev_camera.cam_from_world[0].detach().double().numpy()
        K = prev_camera.K[0].detach().double().numpy()
        q = P_prev @ T[:3, :3].T + T[:3, 3]
        front = hit & (q[:, 2] > 0)
        z = np.where(front, q[:, 2], 1.0)
        u = (K[0, 0] * q[:, 0] + K[0, 1] * q[:, 1]) / z + K[0, 2]
        v = K[1, 1] * q[:, 1] / z + K[1, 2]
        idx = np.arange(H * W)
        motion = np.stack([u - (idx % W + 0.5), v - (idx // W + 0.5)])
        motion[:, ~front] = np.nan
        mw[~hit] = np.nan
        return (
            torch.from_numpy(motion.astype(np.float32).reshape(1, 2, H, W)),
            torch.from_numpy(np.ascontiguousarray(mw.T).astype(np.float32).reshape(1, 3, H, W)),
        )

    # ------------------------------------------------------------------ internals
    def _setup(self, camera, frame, pixel_mask, eye, need_lights=True):
        if not isinstance(camera, PinholeCamera):
            raise TypeError(f"render: camera must be a PinholeCamera, got {type(camera).__name__}")
        if camera.batch_size != 1:
            raise ValueError(f"render: camera must have batch size 1, got {camera.batch_size}")
        n = int(self.scene.num_frames)
        if not (0 <= int(frame) < n):
            raise ValueError(f"render: frame must be in [0, {n}), got {frame}")
        H, W = camera.height, camera.width
        if pixel_mask is None:
            pixels = np.arange(H * W, dtype=np.int64)
        else:
            if not isinstance(pixel_mask, Tensor) or pixel_mask.dtype != torch.bool:
                raise TypeError("render: pixel_mask must be a bool tensor of shape (H, W) or (1, 1, H, W)")
            if tuple(pixel_mask.shape) not in ((H, W), (1, 1, H, W)):
                raise ValueError(
                    f"render: pixel_mask must have shape ({H}, {W}) or (1, 1, {H}, {W}), got {tuple(pixel_mask.shape)}"
                )
            pixels = np.flatnonzero(pixel_mask.reshape(-1).cpu().numpy()).astype(np.int64)
        K = camera.K[0].detach().cpu().double().numpy()
        wfc = camera.world_from_cam[0].detach().cpu().double().numpy()
        M = wfc[:3, :3] @ np.linalg.inv(K)
        lights, limit, shader = self._prepare_lights_full(frame) if need_lights else (None, None, None)
        fr = _Frame(
            stream_key(self.seed, int(frame), int(eye)),
            W,
            wfc[:3, 3].astype(np.float32),
            M,
            lights,
            limit,
            shader,
            np.ascontiguousarray(M.astype(np.float32).reshape(9)),
            self.geometry(frame),
        )
        return fr, pixels, H, W

    def _ranges(self, n):
        """[lo, hi) ranges of n pixels, none longer than max_batch, sizes within one; with several workers at least
        two per worker, handed out as workers free up (parts of an image can differ in cost)."""
        per_worker = 2 if self.workers > 1 else 1
        parts = max(1, min(n, max(self.workers * per_worker, -(-n // self.max_batch))))
        edges = [n * i // parts for i in range(parts + 1)]
        return [(edges[i], edges[i + 1]) for i in range(parts) if edges[i + 1] > edges[i]]

    def _run(self, fn, items):
        if self.workers == 1 or len(items) <= 1:
            return [fn(it) for it in items]
        with ThreadPoolExecutor(max_workers=min(self.workers, len(items))) as ex:
            return list(ex.map(fn, items))

    def _camera_dirs(self, fr: _Frame, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """World directions (N, 3) float32 with camera z = 1 through continuous pixel positions (N,)."""
        M = fr.dir_from_pix.astype(np.float32)
        d = np.empty((len(px), 3), np.float32)
        for r in range(3):
            d[:, r] = M[r, 0] * px + M[r, 1] * py + M[r, 2]
        return d

    def _center_dirs(self, fr: _Frame, pix: np.ndarray) -> np.ndarray:
        """Primary-ray directions (N, 3) float32 of ``pixel_sampling="center"``: the G-buffer's ray of each pixel
        (direction with camera z = 1 through the pixel centre, as :meth:`_gbuffer` and ``_core.tracer_gbuffer_rays``
        form it; the origin is the camera centre). The stage ``intersect_primary`` intersects them as they are, so
        the first hit is the G-buffer's, then makes them unit and rescales ``t`` to them (``t * |d|``), as the
        shading stages expect. One numpy function for both backends, so they hand embree the same rays."""
        px = (pix % fr.width).astype(np.float32) + np.float32(0.5)
        py = (pix // fr.width).astype(np.float32) + np.float32(0.5)
        return self._camera_dirs(fr, px, py)

    def _surface(self, fr: _Frame, prim, d):
        """Material ids (N,) and shading normals (N, 3) of hits ``prim`` (N,) facing against directions ``d``."""
        fn = fr.geom.face_normal[prim]
        sign = np.where(_dot(fn, d) > 0, np.float32(-1), np.float32(1))
        return self.face_material[prim], fn * sign[:, None]

    def _gbuffer(self, fr: _Frame, pixels, H, W, counts) -> dict:
        if self.backend == "native":
            return self._gbuffer_native(fr, pixels, H, W, counts)
        depth = np.full(H * W, np.inf, np.float32)
        normal = np.zeros((H * W, 3), np.float32)
        position = np.zeros((H * W, 3), np.float32)
        albedo = np.zeros((H * W, 3), np.float32)
        matid = np.full(H * W, -1, np.int32)
        prim_img = np.full(H * W, -1, np.int32)

        def work(lo_hi):
            lo, hi = lo_hi
            pix = pixels[lo:hi]
            px = (pix % W).astype(np.float32) + np.float32(0.5)
            py = (pix // W).astype(np.float32) + np.float32(0.5)
            d = self._camera_dirs(fr, px, py)
            o = np.broadcast_to(fr.center, d.shape)
            t, prim = fr.geom.bvh.intersect(o, d)
            hit = prim >= 0
            p, tp, dp = pix[hit], t[hit], d[hit]
            mat, n = self._surface(fr, prim[hit], dp)
            depth[p] = tp
            normal[p] = n
            position[p] = fr.center + tp[:, None] * dp
            albedo[p] = self.kd[mat]
            matid[p] = mat
            prim_img[p] = prim[hit]
            return len(pix)

        for c in self._run(work, [(a, b) for a, b in self._ranges(len(pixels))]):
            counts["gbuffer"] += c

        def img(x, C):
            return torch.from_numpy(np.ascontiguousarray(x.reshape(H * W, C).T).reshape(1, C, H, W))

        return {
            "depth": img(depth, 1),
            "normal": img(normal, 3),
            "position": img(position, 3),
            "albedo": img(albedo, 3),
            "material_id": img(matid, 1),
            "_prim": prim_img,
        }

    def _gbuffer_native(self, fr: _Frame, pixels, H, W, counts) -> dict:
        """:meth:`_gbuffer` with the ray set-up and the writes in ``_core`` (same values; planar outputs, no
        transposes)."""
        HW = H * W
        depth = np.full(HW, np.inf, np.float32)
        planes = {k: np.zeros((3, HW), np.float32) for k in ("normal", "position", "albedo")}
        matid = np.full(HW, -1, np.int32)
        prim_img = np.full(HW, -1, np.int32)
        pixels = np.ascontiguousarray(pixels, np.int64)
        fn, fm, kd = (np.ascontiguousarray(x) for x in (fr.geom.face_normal, self.face_material, self.kd))

        def work(lo_hi):
            lo, hi = lo_hi
            pix = pixels[lo:hi]
            o = np.empty((len(pix), 3), np.float32)
            d = np.empty((len(pix), 3), np.float32)
            _core.tracer_gbuffer_rays(W, pix, fr.M32, fr.center, o, d)
            t, prim = fr.geom.bvh.intersect(o, d)
            _core.tracer_gbuffer_write(
                pix,
                d,
                np.ascontiguousarray(t, np.float32),
                np.ascontiguousarray(prim, np.int32),
                fr.center,
                fn,
                fm,
                kd,
                depth,
                planes["normal"],
                planes["position"],
                planes["albedo"],
                matid,
            )
            prim_img[pix] = prim
            return len(pix)

        for c in self._run(work, self._ranges(len(pixels))):
            counts["gbuffer"] += c
        out = {k: torch.from_numpy(v.reshape(1, 3, H, W)) for k, v in planes.items()}
        out["depth"] = torch.from_numpy(depth.reshape(1, 1, H, W))
        out["material_id"] = torch.from_numpy(matid.reshape(1, 1, H, W))
        out["_prim"] = prim_img
        return out

    # ------------------------------------------------------------------ BSDF and light sampling (numpy stages)
    def _bsdf_eval(self, mat, n, wo, wi):
        """f (N, 3), cos_i (N,), pdf (N,) of the surface BSDF; Lambert only unless the scene is glossy."""
        if self.glossy:
            f, pdf, cos_i = _bsdf.mixture_eval(
                self.kd[mat], self.ks[mat], self.exponent[mat], self.p_spec[mat], n, wo, wi
            )
            return f, cos_i, pdf
        cos_i = _dot(n, wi)
        return self.kd[mat] * np.float32(1 / math.pi), cos_i, _bsdf.lambert_pdf(cos_i)

    def _bsdf_sample(self, mat, n, wo, keys):
        u1, u2 = uniform(keys, DIM["bsdf_u"]), uniform(keys, DIM["bsdf_v"])
        if self.glossy:
            return _bsdf.mixture_sample(
                self.kd[mat],
                self.ks[mat],
                self.exponent[mat],
                self.p_spec[mat],
                n,
                wo,
                uniform(keys, DIM["lobe"]),
                u1,
                u2,
            )
        wi, cos_i = _bsdf.lambert_sample(n, u1, u2)
        ok = cos_i > 0
        return wi, self.kd[mat] * ok[:, None], _bsdf.lambert_pdf(cos_i)

    def _nee(self, fr, P, n, wo, mat, keys, dims, mis: bool):
        """Light sample at points P (N, 3): shadow-ray origins, directions, tmax and unoccluded contribution."""
        ls = fr.lights
        u_sel = uniform(keys, dims[0])
        u1, u2 = uniform(keys, dims[1]), uniform(keys, dims[2])
        o = P + n * self.eps
        target, wi, dist, li, pdf_l = ls.sample(o, u_sel, u1, u2)
        f, cos_i, pdf_b = self._bsdf_eval(mat, n, wo, wi)
        val = f * (li * np.maximum(cos_i, np.float32(0))[:, None])
        if mis:
            with np.errstate(invalid="ignore", divide="ignore"):
                w = np.where(np.isinf(pdf_l), np.float32(1), pdf_l / (pdf_l + pdf_b))
            val = val * w.astype(np.float32)[:, None]
        ok = (cos_i > 0) & (dist > 2 * self.eps) & (val.max(axis=1) > 0)
        tmax = dist - np.float32(2) * self.eps
        return ok, o, wi, tmax, val

    # ------------------------------------------------------------------ one wavefront batch
    def _trace_paths(
        self, fr: _Frame, pix: np.ndarray, samp: np.ndarray, counts: dict, slot: dict | None = None
    ) -> np.ndarray:
        """Radiance (N, 3) float32 of one sample per path (flat pixel ``pix`` (N,), sample index ``samp`` (N,)):
        the :data:`STAGES` in order, as the tracer's backend implements them; ray counts are added to ``counts``.
        ``slot`` holds the worker's scratch arrays (native backend, see :meth:`_workspace_slot`)."""
        if len(pix) == 0:
            return np.zeros((0, 3), np.float32)
        stages = self._stages
        batch = stages.start(fr, pix, samp, counts, slot)
        tm = self._stage_times
        t0 = time.perf_counter() if tm is not None else 0.0
        for name in STAGES:
            getattr(stages, name)(batch)
            t0 = _tick(tm, name, t0)
        return batch.L

    def _workspace(self, n: int, ws: dict | None = None) -> dict:
        """Scratch arrays of the native stages for batches of up to ``n`` paths: ``ws`` when it is large enough, else
        new ones (reused between batches and renders through ``_ws_free``, about 150 bytes per path: fresh
        multi-megabyte arrays cost page faults on every batch)."""
        if ws is None or len(ws["keys"]) < n:
            f32, rows = np.float32, lambda k, c=3: np.empty((k, c), f32)
            ws = {
                "keys": np.empty(n, np.uint64),
                "o": rows(n),
                "d": rows(n),
                "thr": rows(n),
                "pdfb": np.empty(n, f32),
                "sh_o": rows(2 * n),
                "sh_d": rows(2 * n),
                "sh_val": rows(2 * n),
                "sh_t": np.empty(2 * n, f32),
                "sh_path": np.empty(2 * n, np.int32),
                "b_o": rows(n),
                "b_d": rows(n),
                "b_path": np.empty(n, np.int32),
                "E2": rows(n),
                "hit2": np.empty(n, np.uint8),
            }
        return ws

    @contextmanager
    def _workspace_slot(self):
        """One worker's scratch arrays of the native stages, ``{"ws": dict | None}``, taken from the pool and given
        back when the worker is done (``None`` for the numpy backend, which allocates per batch)."""
        if self.backend != "native":
            yield None
            return
        with self._lock:
            slot = {"ws": self._ws_free.pop() if self._ws_free else None}
        try:
            yield slot
        finally:
            if slot["ws"] is not None:
                with self._lock:
                    self._ws_free.append(slot["ws"])


#: The stages of one wavefront batch of paths, in the order they run (the sequence of pbrt-v4's wavefront
#: integrator): camera rays; their closest hits ``x1`` (misses add nothing); shading at ``x1`` (emission seen
#: directly, a light sample, the BSDF sample of the bounce); the bounce rays' closest hits ``x2``; shading at ``x2``
#: (MIS-weighted emission, a light sample); one occlusion query for both light samples' shadow rays; the sample's
#: sum with the firefly clamps. :class:`_NumpyStages` and :class:`_NativeStages` implement every stage; the three
#: ``intersect_*`` stages are theirs in common (embreex, :class:`_Stages`).
STAGES = ("generate", "intersect_primary", "shade_x1", "intersect_bounce", "shade_x2", "intersect_shadow", "accumulate")

_X1_DIMS = (DIM["light1"], DIM["light1_u"], DIM["light1_v"])
_X2_DIMS = (DIM["light2"], DIM["light2_u"], DIM["light2_v"])


@dataclass
class _Batch:
    """One wavefront batch of N paths as a structure of arrays, filled in stage by stage. These are the fields the
    shared stages read or write; each backend's subclass adds its intermediate arrays."""

    fr: _Frame
    pix: np.ndarray  # (N,) int64 flat pixel index
    samp: np.ndarray  # (N,) int64 sample index
    counts: dict  # rays traced per kind, added to by the intersect stages
    L: np.ndarray  # (N, 3) float32 the sample of each path (the result)
    keys: np.ndarray | None = None  # (N,) uint64 path keys                             generate
    o: np.ndarray | None = None  # (N, 3) float32 primary-ray origins                   generate
    d: np.ndarray | None = None  # (N, 3) float32 primary-ray directions                generate
    t: np.ndarray | None = None  # (N,) float32 distance to x1 (unit d)                 intersect_primary
    prim: np.ndarray | None = None  # (N,) int32 triangle of x1, -1: a miss             intersect_primary
    bounce_o: np.ndarray | None = None  # (nb, 3) bounce rays of the paths that go on   shade_x1
    bounce_d: np.ndarray | None = None
    t2: np.ndarray | None = None  # (nb,) their closest hits x2                         intersect_bounce
    prim2: np.ndarray | None = None
    shadow_o: np.ndarray | None = None  # (ns, 3) shadow rays of both light samples     shade_x1, shade_x2
    shadow_d: np.ndarray | None = None
    shadow_t: np.ndarray | None = None  # (ns,) their tmax
    occluded: np.ndarray | None = None  # (ns,) bool                                    intersect_shadow


class _Stages:
    """The stages both backends share: the embreex queries (each skipped, as a query, when it has no rays)."""

    def __init__(self, tracer: PathTracer):
        self.tr = tracer

    def intersect_primary(self, b: _Batch) -> None:
        t, prim = b.fr.geom.bvh.intersect(b.o, b.d)
        b.counts["primary"] += len(b.pix)
        if b.fr.center_rays:  # the G-buffer's rays, intersected as they are, then made unit (see _center_dirs)
            n = np.sqrt(_dot(b.d, b.d))
            n = np.where(n > 0, n, np.float32(1))
            b.d, t = b.d / n[:, None], np.asarray(t, np.float32) * n
        b.t, b.prim = t, prim

    def intersect_bounce(self, b: _Batch) -> None:
        if len(b.bounce_o):
            b.t2, b.prim2 = b.fr.geom.bvh.intersect(b.bounce_o, b.bounce_d)
            b.counts["secondary"] += len(b.bounce_o)
        else:
            b.t2, b.prim2 = np.zeros(0, np.float32), np.zeros(0, np.int32)

    def intersect_shadow(self, b: _Batch) -> None:
        if len(b.shadow_o):
            b.occluded = b.fr.geom.bvh.occluded(b.shadow_o, b.shadow_d, b.shadow_t)
            b.counts["shadow"] += len(b.shadow_o)
        else:
            b.occluded = np.zeros(0, bool)


@dataclass
class _NumpyBatch(_Batch):
    i1: np.ndarray | None = None  # (n1,) paths whose primary ray hit x1
    k1: np.ndarray | None = None  # (n1,) their keys
    R1: np.ndarray | None = None  # (n1, 3) reflected-radiance estimate of x1
    weight: np.ndarray | None = None  # (n1, 3) BSDF weight f cos / pdf of the bounce
    pdf_b: np.ndarray | None = None  # (n1,) its pdf
    live: np.ndarray | None = None  # (nb,) local (i1) index of the bounce rays
    j2: np.ndarray | None = None  # (n2,) local (i1) index of the paths whose bounce hit x2
    E2: np.ndarray | None = None  # (n2, 3) MIS-weighted emission of x2
    R2: np.ndarray | None = None  # (n2, 3) reflected-radiance estimate of x2 (before the throughput)
    shadow_sets: list = field(default_factory=list)  # (local index, o, d, tmax, value) per light sample: x1, x2


class _NumpyStages(_Stages):
    """The reference implementation of :data:`STAGES` (numpy float32, transcendentals in float64)."""

    def start(self, fr: _Frame, pix, samp, counts, slot) -> _NumpyBatch:
        return _NumpyBatch(fr, pix, samp, counts, np.zeros((len(pix), 3), np.float32))

    def generate(self, b: _NumpyBatch) -> None:
        fr, pix = b.fr, b.pix
        b.keys = path_keys(fr.key, pix, b.samp)
        if fr.center_rays:
            b.d = self.tr._center_dirs(fr, pix)
        else:
            px = (pix % fr.width).astype(np.float32) + uniform(b.keys, DIM["jitter_x"])
            py = (pix // fr.width).astype(np.float32) + uniform(b.keys, DIM["jitter_y"])
            b.d = _normalize(self.tr._camera_dirs(fr, px, py))
        b.o = np.broadcast_to(fr.center, b.d.shape)

    def shade_x1(self, b: _NumpyBatch) -> None:
        """Emission seen directly (never clamped), the MIS-weighted light sample, the BSDF sample of the bounce."""
        tr, fr = self.tr, b.fr
        b.i1 = i1 = np.flatnonzero(b.prim >= 0)
        b.R1 = np.zeros((len(i1), 3), np.float32)
        if len(i1) == 0:
            b.k1, b.weight, b.live = b.keys[i1], np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
            b.bounce_o = b.bounce_d = np.zeros((0, 3), np.float32)
            return
        d1, b.k1 = b.d[i1], b.keys[i1]
        P1 = fr.center + b.t[i1, None] * d1
        mat1, n1 = tr._surface(fr, b.prim[i1], d1)
        wo1 = -d1
        if tr.mat_emissive[mat1].any():
            b.L[i1] += tr.emission[mat1]
        if not fr.lights.empty:
            b.shadow_sets.append(self._light_sample(fr, P1, n1, wo1, mat1, b.k1, _X1_DIMS, mis=True))
        wi2, b.weight, b.pdf_b = tr._bsdf_sample(mat1, n1, wo1, b.k1)
        b.live = live = np.flatnonzero(b.weight.max(axis=1) > 0)
        b.bounce_o = P1[live] + n1[live] * tr.eps
        b.bounce_d = wi2[live]

    def shade_x2(self, b: _NumpyBatch) -> None:
        """The MIS-weighted emission of x2 and its light sample (no MIS, no further bounce); then the shadow rays of
        both light samples as one batch."""
        tr, fr = self.tr, b.fr
        h = np.flatnonzero(b.prim2 >= 0)
        b.j2 = b.live[h]
        b.E2 = np.zeros((len(h), 3), np.float32)
        b.R2 = np.zeros((len(h), 3), np.float32)
        if len(h):
            d2, t2, p2 = b.bounce_d[h], b.t2[h], b.prim2[h]
            P2 = b.bounce_o[h] + t2[:, None] * d2
            mat2, n2 = tr._surface(fr, p2, d2)
            self._emission_x2(b, mat2, p2, d2, t2)
            if not fr.lights.empty:
                b.shadow_sets.append(self._light_sample(fr, P2, n2, -d2, mat2, b.k1[b.j2], _X2_DIMS, mis=False))
        sets = b.shadow_sets
        if sum(len(s[0]) for s in sets):
            b.shadow_o, b.shadow_d, b.shadow_t = (np.concatenate([s[k] for s in sets]) for k in (1, 2, 3))
        else:
            b.shadow_o = b.shadow_d = np.zeros((0, 3), np.float32)
            b.shadow_t = np.zeros(0, np.float32)

    def accumulate(self, b: _NumpyBatch) -> None:
        """Visible light samples into x1's and x2's estimates; x2's clamped estimate through the bounce's weight;
        x1's whole clamped estimate into the sample."""
        sets, vis = b.shadow_sets, ~b.occluded
        if len(vis):  # each path has at most one shadow ray per set: plain fancy-index adds are exact
            n_first = len(sets[0][0])
            a = np.flatnonzero(vis[:n_first])
            b.R1[sets[0][0][a]] += sets[0][4][a]
            if len(sets) > 1:
                c = np.flatnonzero(vis[n_first:])
                b.R2[sets[1][0][c]] += sets[1][4][c]
        limit = b.fr.limit
        if len(b.j2):
            b.R1[b.j2] += b.weight[b.j2] * (b.E2 + _clamp_radiance(b.R2, limit))
        b.L[b.i1] += _clamp_radiance(b.R1, limit)

    def _light_sample(self, fr, P, n, wo, mat, keys, dims, mis):
        """One light sample per shading point, only the shadow rays needed: (path index local to the points,
        origins, directions, tmax, unoccluded values)."""
        ok, so, sd, st, val = self.tr._nee(fr, P, n, wo, mat, keys, dims, mis=mis)
        return np.flatnonzero(ok), so[ok], sd[ok], st[ok], val[ok]

    def _emission_x2(self, b: _NumpyBatch, mat2, p2, d2, t2) -> None:
        """``b.E2``: emission of x2 weighted against the light sample that could have found it (balance heuristic,
        area-light pdf per solid angle); unweighted when the scene has no lights to sample."""
        tr, fr = self.tr, b.fr
        em2 = tr.mat_emissive[mat2]
        if not em2.any():
            return
        e = np.flatnonzero(em2)
        if fr.lights.empty:
            b.E2[e] = tr.emission[mat2[e]]
            return
        cos_l = np.abs(_dot(fr.geom.face_normal[p2[e]], d2[e]))
        pdf_l = fr.lights.pdf_area_face[p2[e]] * t2[e] * t2[e] / np.maximum(cos_l, np.float32(1e-12))
        pb = b.pdf_b[b.j2[e]]
        w = np.where(pb > 0, pb / (pb + pdf_l), np.float32(0)).astype(np.float32)
        b.E2[e] = tr.emission[mat2[e]] * w[:, None]


@dataclass
class _NativeBatch(_Batch):
    ws: dict | None = None  # the worker's scratch arrays (PathTracer._workspace)
    n1: int = 0  # shadow rays of x1's light sample (the first n1 of the shadow batch)
    bounce_path: np.ndarray | None = None  # (nb,) int32 path of each bounce ray


class _NativeStages(_Stages):
    """:data:`STAGES` with the kernels of ``stereorepro._core`` (``cpp_ext/src/shade_tracer.cpp``) between the
    shared embreex queries; same values as :class:`_NumpyStages`, bit for bit."""

    def start(self, fr: _Frame, pix, samp, counts, slot) -> _NativeBatch:
        N = len(pix)
        slot["ws"] = self.tr._workspace(N, slot["ws"])
        return _NativeBatch(
            fr,
            np.ascontiguousarray(pix, np.int64),
            np.ascontiguousarray(samp, np.int64),
            counts,
            np.empty((N, 3), np.float32),
            ws=slot["ws"],
        )  # L: never a workspace buffer

    def generate(self, b: _NativeBatch) -> None:
        fr, N = b.fr, len(b.pix)
        b.keys, b.o, b.d = b.ws["keys"][:N], b.ws["o"][:N], b.ws["d"][:N]
        if fr.center_rays:  # the G-buffer's rays (the numpy stages' function), keys from _core
            _core.rng_path_keys(fr.key, b.pix, b.samp, b.keys)
            b.d = self.tr._center_dirs(fr, b.pix)
            b.o[:] = fr.center
        else:
            _core.tracer_generate(fr.key, fr.width, b.pix, b.samp, fr.M32, fr.center, b.keys, b.o, b.d)

    def shade_x1(self, b: _NativeBatch) -> None:
        N, ws = len(b.pix), b.ws
        b.t, b.prim = np.ascontiguousarray(b.t, np.float32), np.ascontiguousarray(b.prim, np.int32)
        b_o, b_d, b_path = ws["b_o"][:N], ws["b_d"][:N], ws["b_path"][:N]
        b.n1, nb = b.fr.shader.shade1(
            b.keys,
            b.d,
            b.t,
            b.prim,
            b.fr.center,
            b.L,
            ws["thr"][:N],
            ws["pdfb"][:N],
            *self._shadow_buffers(b),
            b_o,
            b_d,
            b_path,
        )
        b.bounce_o, b.bounce_d, b.bounce_path = b_o[:nb], b_d[:nb], b_path[:nb]

    def shade_x2(self, b: _NativeBatch) -> None:
        N, ws, ns = len(b.pix), b.ws, b.n1
        E2, hit2 = ws["E2"][:N], ws["hit2"][:N]
        if len(b.bounce_o):
            ns += b.fr.shader.shade2(
                b.keys,
                b.bounce_o,
                b.bounce_d,
                b.bounce_path,
                np.ascontiguousarray(b.t2, np.float32),
                np.ascontiguousarray(b.prim2, np.int32),
                ws["pdfb"][:N],
                E2,
                hit2,
                *self._shadow_buffers(b),
                b.n1,
            )
        else:
            E2.fill(0)
            hit2.fill(0)
        b.shadow_o, b.shadow_d, b.shadow_t = ws["sh_o"][:ns], ws["sh_d"][:ns], ws["sh_t"][:ns]

    def accumulate(self, b: _NativeBatch) -> None:
        N, ws, ns, limit = len(b.pix), b.ws, len(b.shadow_o), b.fr.limit
        b.fr.shader.accumulate(
            b.prim,
            ws["hit2"][:N],
            ws["thr"][:N],
            ws["E2"][:N],
            ws["sh_path"][:ns],
            ws["sh_val"][:ns],
            np.ascontiguousarray(b.occluded, bool),
            b.n1,
            float(np.float32(limit)) if limit is not None else 0.0,
            limit is not None,
            b.L,
        )

    @staticmethod
    def _shadow_buffers(b: _NativeBatch):
        """The shadow-ray batch (o, d, tmax, value, path), room for one ray per path and light sample."""
        cap = 2 * len(b.pix)
        return (b.ws[k][:cap] for k in ("sh_o", "sh_d", "sh_t", "sh_val", "sh_path"))
