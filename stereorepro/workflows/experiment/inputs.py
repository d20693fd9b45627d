"""One frame's inputs to the experiment, per eye, as **render tasks** whose results live in the render cache
(:class:`~.cache.RenderCache`).

Per frame and eye there are three kinds of task, each a function of a :class:`RenderSpec` (small and picklable:
what a Dask worker needs to rebuild the scene and the tracer) and of the frame and eye:

* :func:`gbuffer_task`: depth and normal (and, for scenes with moving objects, the motion to the previous frame and
  the objects' ids), from one centre ray per pixel;
* :func:`reference_chunk_task` ``i``: the mean of the samples ``[REFERENCE_OFFSET + i·c, REFERENCE_OFFSET +
  (i+1)·c)``, ``c = reference_chunk_spp``. The reference at ``n`` spp is the mean of its first ``n / c`` chunk
  means, summed in chunk order in float64 (:func:`reference`). **How chunking enters the cache key**: a chunk's
  key names its sample range (``spp = c``, ``offset``); the ladder's key names ``(reference_spp,
  reference_chunk_spp)``. Chunking changes the reference at rounding level (a sum of chunk means is not the
  renderer's own sum of samples), so a run is bit-identical to another run with the same chunking, on one machine
  or many. One chunk (the default, ``c = reference_spp``) is the renderer's own ``reference_spp`` render, under
  the key of an unchunked run.
* :func:`ladder_task`: the plain path-traced prefixes at 1..L spp of samples 0..L-1, rendered one sample at a time
  and kept **lean**: the 1-spp image (the schemes' input), the top rung (the figures), and every rung's RMSE
  against the reference and against each of its power-of-two chunk prefixes (:func:`reference_prefixes`), under
  both metrics. The rungs themselves are not stored (an eye-frame's cache holds three images and the scores,
  not one image per rung); the tables are the same as from stored rungs (tests/workflows/test_experiment.py).

In-process runs call the tasks directly (:func:`render_eye` returns the frame's :class:`EyeData`); distributed runs
submit them to a Dask cluster first (:mod:`.distributed`) and then read the same entries.
"""

from __future__ import annotations

import contextlib
import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..._checks import all_finite
from ...measure.metrics import rmse
from .cache import RenderCache
from .config import METRICS, REFERENCE_OFFSET, metric_image

__all__ = [
    "EyeData",
    "RenderSpec",
    "RenderContext",
    "render_eye",
    "gbuffer_task",
    "reference_chunk_task",
    "ladder_task",
    "jitter_gbuffer_task",
    "jitter_sample_task",
    "reference",
    "reference_prefixes",
    "eye_tasks",
    "worker_context",
    "estimate_cache_bytes",
    "spec_for",
    "cache_footprint",
]


@dataclass(frozen=True)
class RenderSpec:
    """What determines one run's renders; small and picklable (sent to Dask workers with every task).

    ``base_key`` is the JSON of the cache key's common part (scene fingerprint, renderer code, seed, resolution),
    computed once by the client so that every worker files its entries under the same keys.

    Examples:
        >>> from stereorepro.workflows.experiment.inputs import RenderSpec
        >>> spec = RenderSpec("living_room", 8, 6, seed=0, ladder_spp=2, reference_spp=4, reference_chunk_spp=2,
        ...                   base_key="{}", cache_dir="cache")
        >>> spec.chunks, spec.jitter
        (2, False)
    """

    scene: str
    width: int
    height: int
    seed: int
    ladder_spp: int
    reference_spp: int
    reference_chunk_spp: int
    base_key: str
    cache_dir: str
    workers: int | None = None
    moving: bool = False
    #: code_version() of the client's renderer: a worker whose own differs refuses the task (:mod:`.distributed`).
    client_code: str = ""
    #: TAA-style sub-pixel jitter of the schemes' inputs (:func:`jitter_gbuffer_task`, :func:`jitter_sample_task`).
    jitter: bool = False
    #: torch threads the ladder's RMSEs are reduced with: the client's count, on every worker. torch splits a large
    #: float64 sum by its thread count, so the last bits of an RMSE depend on it (Dask workers run single-threaded);
    #: None = this process's count.
    torch_threads: int | None = None

    @property
    def chunks(self) -> int:
        return self.reference_spp // self.reference_chunk_spp


def spec_for(cfg, scene, cache_dir: Path) -> RenderSpec:
    """The :class:`RenderSpec` of an :class:`~.config.ExperimentConfig` on a loaded scene: its cache key's common
    part (scene fingerprint, renderer version — ``cfg.renderer_version`` or the current one —, seed, resolution).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> import json
        >>> spec = ctx.spec
        >>> spec.width, spec.height, spec.chunks, spec.moving, sorted(json.loads(spec.base_key))
        (8, 6, 2, False, ['code', 'h', 'scene', 'seed', 'w'])
        >>> tmp.cleanup()
    """
    from .cache import code_version, scene_fingerprint

    code = cfg.renderer_version or code_version()
    base_key = {"scene": scene_fingerprint(scene), "code": code, "seed": cfg.seed, "w": cfg.width, "h": cfg.height}
    return RenderSpec(
        scene=cfg.scene,
        width=cfg.width,
        height=cfg.height,
        seed=cfg.seed,
        ladder_spp=cfg.ladder_spp,
        reference_spp=cfg.reference_spp,
        reference_chunk_spp=cfg.reference_chunk_spp or cfg.reference_spp,
        base_key=json.dumps(base_key, sort_keys=True),
        cache_dir=str(Path(cache_dir).resolve()),
        workers=cfg.workers,
        moving="moving_objects" in scene.effects,
        client_code=code_version(),
        jitter=bool(cfg.jitter),
        torch_threads=torch.get_num_threads(),
    )


def reference_prefixes(spec: RenderSpec) -> list[int]:
    """Reference sample counts every ladder is scored against: the chunk size times 1, 2, 4, ... below the
    reference's count, and the reference's count itself (a free reference-spp study on every chunked run).

    Examples:
        >>> from stereorepro.workflows.experiment.inputs import RenderSpec, reference_prefixes
        >>> spec = RenderSpec("living_room", 8, 6, seed=0, ladder_spp=2, reference_spp=4, reference_chunk_spp=2,
        ...                   base_key="{}", cache_dir="cache")
        >>> reference_prefixes(spec)
        [2, 4]
    """
    out, n = [], 1
    while n < spec.chunks:
        out.append(n * spec.reference_chunk_spp)
        n *= 2
    return out + [spec.reference_spp]


@dataclass
class RenderContext:
    """A spec with the objects that render it: the scene, its tracer and the cache (built lazily).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> type(ctx.scene).__name__, type(ctx.tracer).__name__, ctx.key(3, 1)["frame"]
        ('Scene', 'PathTracer', 3)
        >>> tmp.cleanup()
    """

    spec: RenderSpec
    cache: RenderCache | None = None
    scene: object = None
    tracer: object = None
    _cameras: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.scene is None:
            from ...scenes import load_scene

            self.scene = load_scene(self.spec.scene)
        if self.tracer is None:
            from ...render import PathTracer

            self.tracer = PathTracer(self.scene, seed=self.spec.seed, workers=self.spec.workers)
        if self.cache is None:
            self.cache = RenderCache(Path(self.spec.cache_dir), sweep_on_start=False)

    def key(self, frame: int, eye: int, **kw) -> dict:
        return dict(json.loads(self.spec.base_key), frame=frame, eye=int(eye), **kw)  # the key holds the eye's index

    def camera(self, frame: int, eye: int, jittered: bool = False):
        """(camera, previous frame's camera or None): the previous one only for scenes with moving objects.
        ``jittered``: both shifted by their frame's :func:`~stereorepro.camera.jitter_offset` (both eyes alike)."""
        k = (frame, int(eye), jittered)
        if k not in self._cameras:
            from ...camera import jitter_offset

            W, H = self.spec.width, self.spec.height
            cam = self.scene.stereo_cameras(frame, W, H)[int(eye)]
            prev = self.scene.stereo_cameras(frame - 1, W, H)[int(eye)] if self.spec.moving and frame > 0 else None
            if jittered:
                cam = cam.jittered(*jitter_offset(frame))
                prev = prev.jittered(*jitter_offset(frame - 1)) if prev is not None else None
            self._cameras[k] = (cam, prev)
        return self._cameras[k]


@functools.lru_cache(maxsize=4)
def worker_context(spec: RenderSpec) -> RenderContext:
    """The context a worker process renders ``spec`` with (one scene and tracer per spec and process)."""
    return RenderContext(spec)


def _gbuffer_key(ctx: RenderContext, frame: int, eye: int) -> dict:
    _, prev = ctx.camera(frame, eye)
    if ctx.spec.moving:
        return ctx.key(frame, eye, kind="gbuffer_motion", prev=prev is not None)
    return ctx.key(frame, eye, kind="gbuffer")


def _gbuffer_entry(ctx: RenderContext, key: dict, frame: int, cam, prev):
    """The cache entry ``key`` holding the G-buffer of ``cam`` (with motion to ``prev``): (data, meta)."""

    def make():
        r = ctx.tracer.gbuffer(cam, frame, prev_camera=prev)
        out = {"depth": r.depth.numpy(), "normal": r.normal.numpy()}
        for name in ("motion", "motion_world", "object_id"):
            if getattr(r, name) is not None:
                out[name] = getattr(r, name).numpy()
        return out, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    return ctx.cache.get_or_make(key, make)


def gbuffer_task(ctx: RenderContext, frame: int, eye: int):
    """Ensure the G-buffer entry of (frame, eye) is in the cache; returns (data, meta).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, gbuffer_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> data, meta = gbuffer_task(ctx, 0, 0)
        >>> sorted(data), data["depth"].shape, ctx.cache.misses
        (['depth', 'normal'], (1, 1, 6, 8), 1)
        >>> _ = gbuffer_task(ctx, 0, 0); ctx.cache.hits  # the second call reads the entry back
        1
        >>> tmp.cleanup()
    """
    return _gbuffer_entry(ctx, _gbuffer_key(ctx, frame, eye), frame, *ctx.camera(frame, eye))


def _jitter_key(ctx, frame: int, eye: int, kind: str) -> dict:
    from ...camera import jitter_offset

    return dict(_gbuffer_key(ctx, frame, eye), kind=kind, jitter=list(jitter_offset(frame)))


def jitter_gbuffer_task(ctx: RenderContext, frame: int, eye: int):
    """The G-buffer of (frame, eye) through the frame's jittered camera (motion: to the previous frame's jittered
    camera, so the vectors include the change of jitter); returns (data, meta).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, jitter_gbuffer_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> data, meta = jitter_gbuffer_task(ctx, 1, 0)
        >>> sorted(data), data["normal"].shape
        (['depth', 'normal'], (1, 3, 6, 8))
        >>> tmp.cleanup()
    """
    return _gbuffer_entry(
        ctx, _jitter_key(ctx, frame, eye, "gbuffer_jitter"), frame, *ctx.camera(frame, eye, jittered=True)
    )


def jitter_sample_task(ctx: RenderContext, frame: int, eye: int):
    """The schemes' 1-spp input of (frame, eye) with jitter: one sample per pixel through the jittered camera's
    pixel centre (``pixel_sampling="center"``, the G-buffer's own ray), TAA's one sample per frame.

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, jitter_sample_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> data, meta = jitter_sample_task(ctx, 1, 0)
        >>> data["radiance"].shape, data["radiance"].dtype
        ((1, 3, 6, 8), dtype('float32'))
        >>> tmp.cleanup()
    """
    cam, _ = ctx.camera(frame, eye, jittered=True)

    def make():
        r = ctx.tracer.render(cam, frame, 1, sample_offset=0, eye=eye, gbuffers=False, pixel_sampling="center")
        return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    return ctx.cache.get_or_make(_jitter_key(ctx, frame, eye, "sample_jitter"), make)


def _chunk_key(ctx: RenderContext, frame: int, eye: int, i: int) -> dict:
    c = ctx.spec.reference_chunk_spp
    return ctx.key(frame, eye, kind="spp", spp=c, offset=REFERENCE_OFFSET + i * c)


def reference_chunk_task(ctx: RenderContext, frame: int, eye: int, i: int):
    """Ensure reference chunk ``i`` of (frame, eye) is in the cache; returns (data, meta).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, reference_chunk_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> data, meta = reference_chunk_task(ctx, 0, 0, 1)  # samples [REFERENCE_OFFSET + 2, REFERENCE_OFFSET + 4)
        >>> sorted(data), data["radiance"].shape
        (['radiance'], (1, 3, 6, 8))
        >>> tmp.cleanup()
    """
    cam, _ = ctx.camera(frame, eye)
    c = ctx.spec.reference_chunk_spp

    def make():
        r = ctx.tracer.render(
            cam, frame, c, sample_offset=REFERENCE_OFFSET + i * c, eye=eye, gbuffers=False, progress=False
        )
        return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    return ctx.cache.get_or_make(_chunk_key(ctx, frame, eye, i), make)


def reference(
    ctx: RenderContext, frame: int, eye: int, spp: int | None = None, first_chunk: int = 0
) -> tuple[torch.Tensor, float]:
    """The (1, 3, H, W) reference of (frame, eye) at ``spp`` (a multiple of the chunk size; default the run's) and
    its render time in ms: the mean of its chunk means, summed in chunk order in float64. ``first_chunk`` starts
    it at a later chunk (an independent part of the run's reference: samples disjoint from the chunks before it).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, reference
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> ref, ms = reference(ctx, 0, 0)  # the mean of the two 2-spp chunks
        >>> tuple(ref.shape), ref.dtype, tuple(reference(ctx, 0, 0, spp=2)[0].shape)
        ((1, 3, 6, 8), torch.float32, (1, 3, 6, 8))
        >>> halves = reference(ctx, 0, 0, spp=2)[0], reference(ctx, 0, 0, spp=2, first_chunk=1)[0]
        >>> bool(torch.allclose((halves[0] + halves[1]) / 2, ref))
        True
        >>> tmp.cleanup()
    """
    n = (spp or ctx.spec.reference_spp) // ctx.spec.reference_chunk_spp
    total, ms = None, 0.0
    for i in range(first_chunk, first_chunk + n):
        d, meta = reference_chunk_task(ctx, frame, eye, i)
        x = torch.from_numpy(d["radiance"])
        if n == 1:  # the renderer's own reference, as it is
            return x, meta["ms"]
        total = x.double() if total is None else total + x.double()
        ms += meta["ms"]
    return (total / n).float(), ms


def _ladder_key(ctx: RenderContext, frame: int, eye: int) -> dict:
    s = ctx.spec
    return ctx.key(
        frame,
        eye,
        kind="ladder",
        ladder_spp=s.ladder_spp,
        reference_spp=s.reference_spp,
        reference_chunk_spp=s.reference_chunk_spp,
    )


def ladder_task(ctx: RenderContext, frame: int, eye: int):
    """Ensure the lean ladder entry of (frame, eye) is in the cache (rendering the reference's chunks first when
    they are missing); returns (data, meta). ``data``: ``first`` and ``top`` (1, 3, H, W) float32, ``prefix_spp``
    (P,) and ``rmse_ldr`` / ``rmse_hdr`` (P, L) float64: row p scores rungs 1..L against the reference at
    ``prefix_spp[p]`` spp.

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, ladder_task
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> data, meta = ladder_task(ctx, 0, 0)
        >>> data["top"].shape, data["prefix_spp"].tolist(), data["rmse_ldr"].shape
        ((1, 3, 6, 8), [2, 4], (2, 2))
        >>> tmp.cleanup()
    """
    cam, _ = ctx.camera(frame, eye)
    L = ctx.spec.ladder_spp

    def make():
        with _torch_threads(ctx.spec.torch_threads):
            return score()

    def score():
        prefixes = reference_prefixes(ctx.spec)
        refs = [reference(ctx, frame, eye, n)[0] for n in prefixes]
        scored = {m: [_Scored(metric_image(r, m)) for r in refs] for m in METRICS}
        err = {m: np.zeros((len(prefixes), L)) for m in METRICS}
        total, times, first, rung = None, [], None, None
        for s in range(L):
            r = ctx.tracer.render(cam, frame, 1, sample_offset=s, eye=eye, gbuffers=False)
            times.append(r.time_s * 1e3)
            x = r.radiance.double()
            total = x if total is None else total + x
            rung = (total / (s + 1)).float()
            if s == 0:
                first = rung
            for m in METRICS:
                img = _Scored(metric_image(rung, m))
                for p, ref in enumerate(scored[m]):
                    err[m][p, s] = img.rmse(ref)
        data = {
            "first": first.numpy(),
            "top": rung.numpy(),
            "prefix_spp": np.asarray(prefixes, np.int64),
            **{f"rmse_{m}": err[m] for m in METRICS},
        }
        return data, {"ms": float(np.sum(times)), "ms_per_spp": float(np.mean(times))}

    return ctx.cache.get_or_make(_ladder_key(ctx, frame, eye), make)


@contextlib.contextmanager
def _torch_threads(n: int | None):
    old = torch.get_num_threads()
    if n is not None and n != old:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != old:
            torch.set_num_threads(old)


class _Scored:
    """An image held in float64 once, for many RMSEs: ``a.rmse(b)`` is bit for bit
    ``float(metrics.rmse(a.image, b.image)[0])`` (the same float64 difference, square and sum; every pixel valid),
    without converting both images again for every pair (a ladder scores L rungs against each reference prefix,
    so the conversions would otherwise dominate the scoring time). Images with a non-finite value go through
    ``metrics.rmse`` itself (its checks and messages)."""

    def __init__(self, image: torch.Tensor):
        self.image = image
        self.finite = all_finite(image)
        self.x64 = image.to(torch.float64) if self.finite else None

    def rmse(self, ref: "_Scored") -> float:
        if not (self.finite and ref.finite and self.image.shape == ref.image.shape and self.image.shape[0] == 1):
            return float(rmse(self.image, ref.image)[0])
        diff = self.x64 - ref.x64
        n = torch.tensor([diff[0, 0].numel()], dtype=torch.float64) * diff.shape[1]
        return float(((diff * diff).flatten(1).sum(1) / n).sqrt()[0])


def eye_tasks(spec: RenderSpec, frame: int, eye: int) -> list[tuple[str, tuple, dict]]:
    """The render tasks of one (frame, eye) in dependency order: (function name, args, cache key).

    Examples:
        >>> from stereorepro.workflows.experiment.inputs import RenderSpec, eye_tasks
        >>> spec = RenderSpec("living_room", 8, 6, seed=0, ladder_spp=2, reference_spp=4, reference_chunk_spp=2,
        ...                   base_key="{}", cache_dir="cache")
        >>> for name, args, _ in eye_tasks(spec, 0, 1):
        ...     print(name, args)
        gbuffer_task (0, 1)
        reference_chunk_task (0, 1, 0)
        reference_chunk_task (0, 1, 1)
        ladder_task (0, 1)
    """
    ctx_free = _KeyOnly(spec)
    tasks = [("gbuffer_task", (frame, eye), _gbuffer_key(ctx_free, frame, eye))]
    tasks += [
        ("reference_chunk_task", (frame, eye, i), _chunk_key(ctx_free, frame, eye, i)) for i in range(spec.chunks)
    ]
    tasks.append(("ladder_task", (frame, eye), _ladder_key(ctx_free, frame, eye)))
    if spec.jitter:
        tasks += [
            (f"jitter_{k}_task", (frame, eye), _jitter_key(ctx_free, frame, eye, f"{k}_jitter"))
            for k in ("gbuffer", "sample")
        ]
    return tasks


def estimate_cache_bytes(spec: RenderSpec, frames: int) -> int:
    """Upper estimate of the cache bytes a run of ``frames`` frames writes (both eyes; npz overhead included):
    per eye-frame the G-buffer (depth, normal; motion, world motion and ids for moving objects), the reference's
    chunks and the lean ladder (two images), all float32.

    Examples:
        >>> from stereorepro.workflows.experiment.inputs import RenderSpec, estimate_cache_bytes
        >>> spec = RenderSpec("living_room", 8, 6, seed=0, ladder_spp=2, reference_spp=4, reference_chunk_spp=2,
        ...                   base_key="{}", cache_dir="cache")
        >>> estimate_cache_bytes(spec, frames=1)
        22528
    """
    px = spec.width * spec.height
    planes = 1 + 3 + (2 + 3 + 1 if spec.moving else 0) + 3 * spec.chunks + 2 * 3
    return 2 * frames * (4 * px * planes + 8 * 1024)


def cache_footprint(ctx: RenderContext, frames: int) -> dict:
    """Measured bytes of this run's cache entries: total and per eye-frame (what ``--cache-dir`` holds per
    frame and eye).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, cache_footprint, render_eye
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> _ = render_eye(ctx, 0, 0), render_eye(ctx, 0, 1)
        >>> fp = cache_footprint(ctx, frames=1)
        >>> fp["bytes"] > 0, fp["bytes_per_eye_frame"] == fp["bytes"] / 2
        (True, True)
        >>> tmp.cleanup()
    """
    total, n = 0, 0
    for f in range(frames):
        for eye in (0, 1):
            for _, _, key in eye_tasks(ctx.spec, f, eye):
                p = ctx.cache.path(key)
                total += p.stat().st_size if p.exists() else 0
            n += 1
    return {"bytes": total, "bytes_per_eye_frame": total / max(n, 1)}


class _KeyOnly:
    """The key-making part of a context (no scene or tracer): the client names tasks without rendering."""

    def __init__(self, spec: RenderSpec):
        self.spec = spec

    key = RenderContext.key

    def camera(self, frame: int, eye: int, jittered: bool = False):
        return None, (object() if self.spec.moving and frame > 0 else None)


@dataclass
class EyeData:
    """One eye's inputs at one frame (all tensors batch 1).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, EyeData, render_eye
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> e = render_eye(ctx, 0, 1)
        >>> isinstance(e, EyeData), tuple(e.normal.shape), tuple(e.K.shape), e.pixel_sampling
        (True, (1, 3, 6, 8), (1, 3, 3), 'box')
        >>> tmp.cleanup()
    """

    depth: torch.Tensor  # (1, 1, H, W)
    normal: torch.Tensor  # (1, 3, H, W)
    K: torch.Tensor  # (1, 3, 3)
    cam_from_world: torch.Tensor  # (1, 4, 4)
    sample: torch.Tensor  # (1, 3, H, W): the 1-spp input of the schemes (the ladder's first rung; with jitter
    # its own centre-sampled render through the jittered camera)
    top: torch.Tensor  # (1, 3, H, W): the ladder's top rung (figures)
    ladder_rmse: dict  # metric -> list of L floats: rungs 1..L against the reference
    reference: torch.Tensor  # (1, 3, H, W)
    prefix_spp: list  # reference sample counts the ladder was also scored against (the last is the reference)
    prefix_ladder_rmse: dict  # metric -> (P, L) float64 array
    ms_gbuffer: float
    ms_per_spp: float  # mean wall time of one 1-spp full-frame render
    ms_reference: float
    camera: object = None  # the camera of ``sample`` and the G-buffer (jittered with jitter)
    pixel_sampling: str = "box"  # how ``sample`` was traced
    motion: torch.Tensor | None = None  # (1, 2, H, W) to the previous frame (moving objects, frame > 0)
    motion_world: torch.Tensor | None = None  # (1, 3, H, W)
    object_id: torch.Tensor | None = None  # (1, 1, H, W) int32, -1 static (moving objects)


def render_eye(ctx: RenderContext, frame: int, eye: int) -> EyeData:
    """One eye's inputs, from the cache or rendered now (G-buffer, reference chunks, lean ladder; with
    ``spec.jitter`` the G-buffer and the 1-spp sample of the jittered camera).

    Examples:
        >>> import tempfile
        >>> from stereorepro.scenes import load_scene
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.inputs import RenderContext, spec_for, render_eye
        >>> tmp = tempfile.TemporaryDirectory()
        >>> cfg = ExperimentConfig(scene="living_room", out=tmp.name, width=8, height=6, ladder_spp=2,
        ...                        reference_spp=4, reference_chunk_spp=2)
        >>> scene = load_scene(cfg.scene)
        >>> ctx = RenderContext(spec_for(cfg, scene, tmp.name), scene=scene)
        >>> e = render_eye(ctx, 0, 0)
        >>> tuple(e.depth.shape), tuple(e.sample.shape), e.prefix_spp, len(e.ladder_rmse["ldr"])
        ((1, 1, 6, 8), (1, 3, 6, 8), [2, 4], 2)
        >>> tmp.cleanup()
    """
    jit = ctx.spec.jitter
    cam, _ = ctx.camera(frame, eye, jittered=jit)
    g, gmeta = gbuffer_task(ctx, frame, eye)
    lad, lmeta = ladder_task(ctx, frame, eye)
    ref, ms_ref = reference(ctx, frame, eye)
    sample = torch.from_numpy(lad["first"])
    if jit:
        g, gmeta = jitter_gbuffer_task(ctx, frame, eye)
        sample = torch.from_numpy(jitter_sample_task(ctx, frame, eye)[0]["radiance"])
    opt = {k: torch.from_numpy(g[k]) for k in ("motion", "motion_world", "object_id") if k in g}
    return EyeData(
        torch.from_numpy(g["depth"]),
        torch.from_numpy(g["normal"]),
        cam.K.float(),
        cam.cam_from_world.double(),
        sample,
        torch.from_numpy(lad["top"]),
        {m: lad[f"rmse_{m}"][-1].tolist() for m in METRICS},
        ref,
        lad["prefix_spp"].tolist(),
        {m: lad[f"rmse_{m}"] for m in METRICS},
        gmeta["ms"],
        lmeta["ms_per_spp"],
        ms_ref,
        cam,
        "center" if jit else "box",
        **opt,
    )
