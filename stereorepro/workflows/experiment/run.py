"""The experiment's run loop: per frame, render (or read from the cache) both eyes' inputs, run every scheme on
the same 1-spp inputs, and measure it against the reference as effective spp (and FLIP, SSIM and, from the second
frame on, the temporal error against the previous frame).

:func:`run_experiment` is four steps: :func:`_start` (checks, the scene, the render cache, a cluster's renders),
one :class:`_SchemeRun` per scheme of :func:`~.config.schemes` (its drivers and what it records),
:func:`_run_frames` (per frame: both eyes' inputs, then every scheme run and scored) and :func:`_assemble` (the
statistics over frames, an :class:`ExperimentResults`).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from ..._extras import require, require_all
from ..._version import __version__
from ...accumulate import SpatiotemporalReprojection
from ...camera import has_surface
from ...measure.anatomy import (
    block_standard_error,
    footprint_failures,
    footprint_regions,
    reference_noise_mse,
    split_bias,
    squared_error,
)
from ...measure.metrics import effective_spp_many, flip, flip_available, rmse, ssim
from ...measure.temporal import temporal_error
from ...reproject import View
from .cache import RenderCache
from .config import LEFT, RIGHT, ExperimentConfig, Scheme, metric_image, validate_config
from .config import schemes as all_schemes
from .inputs import (
    EyeData,
    RenderContext,
    RenderSpec,
    cache_footprint,
    estimate_cache_bytes,
    reference,
    render_eye,
    spec_for,
)
from .report import write_frame_exr, write_outputs

__all__ = ["run_experiment", "ExperimentResults"]


#: Frames before this one are the warm-up: every statistic is also reported over the frames from it on
#: (``avg_after_warmup``), where the histories have filled (an EMA at 20 % holds ~90 % of its weight in 10 frames).
WARMUP_FRAMES = 10


def _stats(xs) -> dict:
    warm = [x for x in xs[WARMUP_FRAMES:] if x is not None and math.isfinite(x)]
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    if not xs:
        return {"avg": None, "min": None, "max": None, "n": 0, "avg_after_warmup": None}
    return {
        "avg": float(np.mean(xs)),
        "min": float(np.min(xs)),
        "max": float(np.max(xs)),
        "n": len(xs),
        "avg_after_warmup": float(np.mean(warm)) if warm else None,
    }


#: Effective-spp flags of a frame whose error lies below the ladder's top rung: its value is extrapolated on a fit of
#: the ladder (or infinite), which on real ladders runs high (``bench/results/ladder_extrapolation.md``), so
#: :func:`_spp_stats` also bounds the average from below.
BEYOND_LADDER = ("extrapolated_high", "beyond_floor")


def _spp_stats(per_frame: list[dict], name: str, top: float) -> dict:
    """:func:`_stats` of scheme ``name``'s effective spp over the frames, plus ``beyond_ladder`` (frames flagged in
    :data:`BEYOND_LADDER`) and ``avg_lower_bound`` / ``avg_after_warmup_lower_bound``: the averages with those frames
    counted at the top rung ``top`` (a frame beyond it has less error than the top rung, so at least its spp);
    equal to ``avg`` / ``avg_after_warmup`` when no frame is beyond."""
    xs = [r["effective_spp"][name] for r in per_frame]
    beyond = [r["flags"].get(name) in BEYOND_LADDER for r in per_frame]
    bound = _stats([top if b else x for x, b in zip(xs, beyond)])
    return {
        **_stats(xs),
        "beyond_ladder": sum(beyond),
        "avg_lower_bound": bound["avg"],
        "avg_after_warmup_lower_bound": bound["avg_after_warmup"],
    }


@dataclass(frozen=True)
class ExperimentResults:
    """What a run measured: the content of ``results.json``, field by field in its order (:meth:`to_dict`). The
    statistics over frames (``table1``, ``table2``, ...) are ``{"avg", "min", "max", "n", "avg_after_warmup"}``
    dicts (``avg_after_warmup``: from frame :data:`WARMUP_FRAMES` on); the effective spp's (``table2``,
    ``table2_variants``) add ``beyond_ladder``, ``avg_lower_bound`` and ``avg_after_warmup_lower_bound``
    (:func:`_spp_stats`).

    Examples:
        >>> from dataclasses import fields
        >>> from stereorepro.workflows.experiment.run import ExperimentResults
        >>> empty = {f.name: None for f in fields(ExperimentResults)}
        >>> r = ExperimentResults(**empty | {"scene": "living_room", "frames": 2, "resolution": "8x6"})
        >>> d = r.to_dict()
        >>> d["scene"], d["resolution"], "moving_objects" in d, list(d)[:3]
        ('living_room', '8x6', False, ['scene', 'effects', 'frames'])
    """

    scene: str
    effects: list  #: the scene's effects, sorted
    frames: int
    resolution: str  #: ``"WxH"``
    reference_spp: int
    reference_chunk_spp: int | None
    ladder_spp: int
    warmup_frames: int
    #: reference spp (str) -> scheme -> effective-spp statistics against that prefix of the reference (chunked runs;
    #: the run's own reference last); None without chunks
    reference_study: dict | None
    seed: int
    metric: str  #: ``"ldr"`` or ``"hdr"``
    jitter: bool
    history_rounding: str  #: how the drivers store history lengths: ``"none"`` (floats) or ``"bmfr"`` (integers)
    footprint_weighting: bool  #: the drivers scale warped history lengths by the footprint quality
    option_variants: bool  #: Table 2 holds the option variants (``<scheme>_<option>``, see ``OPTION_VARIANTS``)
    perceptual_every: int  #: FLIP and SSIM scored on every K-th frame, counted back from the last
    thresholds: dict  #: ``position``, ``normal``, ``position_scene``, ``scale``
    table1: dict  #: scheme -> discarded pixels (%): the paper's Table 1 (stereo, temporal)
    flip: dict | None  #: scheme -> mean LDR FLIP statistics; None when not measured
    ssim: dict | None  #: paper scheme -> mean LDR SSIM statistics; None when not measured
    #: scheme -> temporal error statistics (:func:`~stereorepro.measure.temporal.temporal_error` against the previous
    #: frame, tonemapped as ``metric``), over frames 1.. (frame 0 has no previous frame); None for a one-frame run
    temporal_error: dict | None
    #: scenes with moving objects only: ``moving_pixels_pct`` and, per temporal scheme, discards on the moving
    #: objects' pixels and on the static rest (absent from :meth:`to_dict` otherwise)
    moving_objects: dict | None
    table2: dict  #: paper scheme -> effective spp: the paper's Table 2
    table2_variants: dict  #: every other scheme -> effective spp
    timing_ms: dict  #: median ms per frame of each timed step
    cost: list  #: rows of :func:`_cost_table`
    #: paper scheme -> the resampling bias (:func:`_bias_table`): ``bias_mse`` and its shares without the
    #: reference's noise (None for a reference in one chunk), the error anatomy by footprint; ``ladder_top_rmse``
    bias: dict
    per_frame: list  #: one dict per frame (every scheme's scores, discards, ladders)
    flags: dict  #: scheme -> effective-spp flag -> frames
    cache: dict  #: hits, misses, recomputed_corrupt, dir and the cache's footprint
    distributed: dict | None  #: the cluster's report (:func:`~.distributed.render_all`); None in-process
    wall_s: float
    version: str
    code: str  #: the renderer version in the cache keys

    def to_dict(self) -> dict:
        """The ``results.json`` content (``moving_objects`` only for scenes with moving objects)."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name != "moving_objects" or self.moving_objects is not None
        }


def run_experiment(cfg: ExperimentConfig, log=print) -> dict:
    """Run the experiment and write its outputs into ``cfg.out``. Returns the ``results.json`` content
    (:meth:`ExperimentResults.to_dict`).

    Examples:
        >>> import os, tempfile
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> from stereorepro.workflows.experiment.run import run_experiment
        >>> with tempfile.TemporaryDirectory() as d:
        ...     cfg = ExperimentConfig(scene="living_room", out=d, frames=2, width=8, height=6, ladder_spp=2,
        ...                            reference_spp=4, flip=False, ssim=False, progress=False)
        ...     r = run_experiment(cfg, log=lambda message: None)  # a few seconds: most of it the four figures
        ...     print(sorted(os.listdir(d))[:4])
        ...     print(sorted(os.listdir(d))[4:])
        ['cache', 'fig1_discards.png', 'fig3_rmse.png', 'fig4_comparison.png']
        ['fig_cost.png', 'report.html', 'report.md', 'results.json', 'tables.md']
        >>> r["frames"], r["resolution"], sorted(r["table2"]), r["table2"]["stereo"]["n"]
        (2, '8x6', ['stereo', 'stereo_temporal', 'temporal'], 2)
    """
    needs = ["embreex", "tqdm", "matplotlib"] + ["kornia"] * cfg.ssim + ["OpenEXR"] * cfg.exr
    require_all(needs, "the experiment", "experiment")
    run = _start(cfg, log)
    schemes = [_SchemeRun.make(s, run) for s in all_schemes(cfg, run.moving)]
    per_frame, keep, timing = _run_frames(run, schemes)
    wall = time.perf_counter() - run.t_start
    results = _assemble(run, schemes, per_frame, timing, wall).to_dict()
    write_outputs(run.out, results, per_frame, keep, cfg)
    return results


@dataclass(frozen=True)
class _Run:
    """What every step of a run reads: its settings, the scene and thresholds, the renders' context."""

    cfg: ExperimentConfig
    scene: object
    frames: int
    out: Path
    scale: float  #: threshold scale for the resolution
    pos_thr: float
    nrm_thr: float
    cache_dir: Path
    spec: RenderSpec
    ctx: RenderContext
    use_flip: bool
    distributed: dict | None
    t_start: float  #: the wall time includes a cluster's renders

    @property
    def cache(self) -> RenderCache:
        return self.ctx.cache

    @property
    def moving(self) -> bool:
        return self.spec.moving

    @property
    def fig1_frame(self) -> int:
        return self.frames // 2


def _start(cfg: ExperimentConfig, log) -> _Run:
    """Check everything (with ``cfg.scheduler``: connect to the cluster and check its workers), then create the
    output folder and the render cache; with a cluster every render runs there first (the frame loop then reads the
    cache)."""
    from ...scenes import load_scene

    validate_config(cfg)
    scene = load_scene(cfg.scene)
    frames = scene.num_frames if cfg.frames is None else int(cfg.frames)
    if not 1 <= frames <= scene.num_frames:
        raise ValueError(f"frames must be in 1..{scene.num_frames} for scene {scene.name!r}, got {frames}")
    t_start = time.perf_counter()
    cluster = None
    if cfg.scheduler:  # an unreachable or unfit cluster fails here, before anything is created
        from .distributed import open_cluster

        cluster = open_cluster(cfg.scheduler)
    try:
        return _prepare(cfg, log, scene, frames, cluster, t_start)
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise


def _prepare(cfg: ExperimentConfig, log, scene, frames: int, cluster, t_start: float) -> _Run:
    """:func:`_start` once everything is checked: the output folder, the render cache, a cluster's renders."""
    from ...render import PathTracer
    from ...scenes import threshold_scale

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    scale = cfg.threshold_scale if cfg.threshold_scale is not None else threshold_scale(cfg.height)
    pos_thr, nrm_thr = scene.thresholds(cfg.height, scale)
    cache_dir = Path(cfg.cache_dir) if cfg.cache_dir else out / "cache"
    cache = RenderCache(cache_dir, force=cfg.force, log=log)
    spec = spec_for(cfg, scene, cache_dir)
    need, free = estimate_cache_bytes(spec, frames), shutil.disk_usage(cache_dir).free
    if need > free:  # a warning, not an error: the cache may already hold most of it
        log(
            f"warning: the render cache needs up to {need / 2**30:.1f} GiB for {frames} frames "
            f"({need / (2 * frames) / 2**20:.0f} MiB per eye and frame) and {cache_dir} has "
            f"{free / 2**30:.1f} GiB free"
        )
    distributed = None
    if cluster is not None:
        from .distributed import render_all

        distributed = render_all(spec, range(frames), cluster, force=cfg.force, progress=cfg.progress, log=log)
        cache = RenderCache(cache_dir, log=log, sweep_on_start=False)  # the entries are made: no recomputing
    ctx = RenderContext(spec, cache=cache, scene=scene, tracer=PathTracer(scene, seed=cfg.seed, workers=cfg.workers))
    return _Run(
        cfg,
        scene,
        frames,
        out,
        scale,
        pos_thr,
        nrm_thr,
        cache_dir,
        spec,
        ctx,
        bool(cfg.flip) and flip_available(),
        distributed,
        t_start,
    )


@dataclass
class _FrameData:
    """One frame's inputs and the row of ``per_frame`` the schemes fill in."""

    frame: int
    eyes: dict  #: LEFT / RIGHT -> EyeData
    surface: dict  #: LEFT / RIGHT -> (1, 1, H, W) bool
    row: dict
    ladder_spp: list  #: 1..ladder_spp
    prefixes: list  #: smaller references of the reference-spp study (chunked runs)
    prefix_refs: dict  #: eye -> prefix spp -> metric image of that reference
    #: LEFT / RIGHT -> the reference's two independent halves (1, 3, H, W) (:func:`_reference_halves`); None for a
    #: reference in one chunk
    halves: dict | None = None
    half_spp: tuple = ()  #: the halves' sample counts
    previous: dict | None = None  #: LEFT / RIGHT -> EyeData of the previous frame; None at the first frame
    footprints: dict = field(default_factory=dict)  #: step -> footprint failures of this frame (shared by schemes)

    def ladder(self, eye: int, metric: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The eye's ladder: spp (L,) and RMSE (L,) float64."""
        return (
            torch.tensor(self.ladder_spp, dtype=torch.float64),
            torch.tensor(self.eyes[eye].ladder_rmse[metric], dtype=torch.float64),
        )


def _frame_inputs(run: _Run, f: int, timing: dict) -> _FrameData:
    """Both eyes' inputs at frame ``f`` (rendered or from the cache), their timings, and the frame's row."""
    cfg, ctx = run.cfg, run.ctx
    eyes = {LEFT: render_eye(ctx, f, LEFT), RIGHT: render_eye(ctx, f, RIGHT)}
    L, R = eyes[LEFT], eyes[RIGHT]
    timing["trace_1spp_ms"] += [L.ms_per_spp, R.ms_per_spp]
    timing["gbuffer_ms"] += [L.ms_gbuffer, R.ms_gbuffer]
    timing["reference_ms"] += [L.ms_reference, R.ms_reference]
    surface = {e: has_surface(d.depth) for e, d in eyes.items()}
    row = {
        "frame": f,
        "discard_pct": {},
        "rmse": {},
        "effective_spp": {},
        "flags": {},
        "ladder_rmse": {},
        "no_surface_pct": {},
        "rmse_noise_free": {},
        "flip": {},
        "ssim": {},
        "temporal_error": {},
        "reference_study": {},
        "bias_mse": {},
        "bias_mse_se": {},
        "reference_noise_mse": {},
        "anatomy": {},
    }
    if run.moving:
        row.update(
            discard_pct_moving={},
            discard_pct_static={},
            moving_pct=100.0 * float(((R.object_id >= 0) & surface[RIGHT]).float().mean()),
        )
    prefixes = L.prefix_spp[:-1]
    prefix_refs = {e: {p: metric_image(reference(ctx, f, e, p)[0], cfg.metric) for p in prefixes} for e in eyes}
    for e, d in eyes.items():
        side = str(e)
        row["ladder_rmse"][side] = d.ladder_rmse[cfg.metric]
        row["no_surface_pct"][side] = 100.0 * float((~surface[e]).float().mean())
    halves, half_spp = _reference_halves(ctx, f)
    return _FrameData(
        f, eyes, surface, row, list(range(1, cfg.ladder_spp + 1)), prefixes, prefix_refs, halves, half_spp
    )


def _reference_halves(ctx: RenderContext, f: int) -> tuple[dict | None, tuple]:
    """Each eye's reference split into two independent halves: the mean of its first ``chunks // 2`` chunks and
    the mean of the rest (disjoint sample ranges), summed in float64; ``(None, ())`` for a reference in one
    chunk. Returns ``({LEFT: (a, b), RIGHT: (a, b)}, (spp_a, spp_b))``."""
    n, c = ctx.spec.chunks, ctx.spec.reference_chunk_spp
    if n < 2:
        return None, ()
    k = n // 2
    halves = {
        e: (reference(ctx, f, e, k * c)[0], reference(ctx, f, e, (n - k) * c, first_chunk=k)[0]) for e in (LEFT, RIGHT)
    }
    return halves, (k * c, (n - k) * c)


def _run_frames(run: _Run, schemes: list[_SchemeRun]) -> tuple[list[dict], dict, dict]:
    """Every frame: its inputs, then every scheme run and scored on them. Returns the rows, the frames kept for the
    figures and the timings (lists of ms per timed step)."""
    tqdm = require("tqdm.auto", "the experiment's progress bar", extra="experiment").tqdm

    cfg = run.cfg
    timing = {
        k: [] for k in ("trace_1spp_ms", "gbuffer_ms", "trace_left_discards_ms", "reference_ms", "temporal_error_ms")
    }
    timing.update({f"reproject_{s.scheme.name}_ms": [] for s in schemes})
    per_frame, keep, previous = [], {}, None
    drivers = {s.scheme.name: s.driver for s in schemes}
    bar = tqdm(
        range(run.frames), desc=f"{run.scene.name} {cfg.width}x{cfg.height}", unit="frame", disable=not cfg.progress
    )
    for f in bar:
        fd = _frame_inputs(run, f, timing)
        fd.previous = previous
        for s in schemes:
            s.score(run, fd, timing, keep)
        previous = fd.eyes  # one frame back only: fd.previous is dropped with fd
        if cfg.exr:
            write_frame_exr(run.out / "exr", f, fd.eyes, drivers)
        per_frame.append(fd.row)
        bar.set_postfix(
            st=f"{fd.row['effective_spp']['stereo_temporal']:.1f}spp", cache=f"{run.cache.hits}/{run.cache.misses}"
        )
    return per_frame, keep, timing


def _motion(eye: EyeData, scheme: Scheme) -> tuple:
    """The eye's motion vectors for a scheme that steps through them, else ``(None, None)``."""
    return (eye.motion, eye.motion_world) if scheme.motion else (None, None)


def _view(eye: EyeData) -> View:
    """The eye's G-buffer and camera as a :class:`~stereorepro.View`, with its motion vectors to the previous frame
    when the scene has moving objects (the known motion the temporal error follows)."""
    motion_world = eye.motion_world if eye.motion is not None else None
    return View(eye.depth, eye.normal, eye.K, eye.cam_from_world, eye.motion, motion_world)


@dataclass
class _SchemeRun:
    """One scheme in a run: its driver on the 1-spp inputs and, for the paper's schemes, the same scheme fed with
    the references: ``clean`` the whole reference (scored against itself, its error is the resampling bias plus
    a copy of the reference's noise) and ``halves`` each of its two independent halves (their errors' mean
    product is the bias alone, :func:`~stereorepro.measure.anatomy.split_bias`): bilinear blur compounded over
    frames, edges - the part of the error that more samples cannot remove."""

    scheme: Scheme
    driver: SpatiotemporalReprojection
    clean: SpatiotemporalReprojection | None
    #: the evaluated eye's output of the previous frame (the temporal error's previous image; one frame only)
    prev_image: torch.Tensor | None = None
    #: the scheme fed each half of the reference (paper schemes, references in two chunks or more)
    halves: tuple | None = None

    @classmethod
    def make(cls, s: Scheme, run: _Run) -> _SchemeRun:
        pos_thr = run.pos_thr if s.position_threshold is None else s.position_threshold

        def driver(alternate: bool) -> SpatiotemporalReprojection:  # the config's history options, then the scheme's
            d = SpatiotemporalReprojection(
                pos_thr,
                run.nrm_thr,
                alpha=s.alpha,
                sampling=s.sampling,
                stereo=s.stereo,
                temporal=s.temporal,
                left_mode=s.left_mode,
                alternate=alternate,
            )
            d.history_rounding = run.cfg.history_rounding
            d.footprint_weighting = run.cfg.footprint_weighting
            for name, value in s.options:
                setattr(d, name, value)
            return d

        def fed():  # fed references through right()/left(): the right eye traced in full every frame
            if s.alternate:
                raise ValueError(f"scheme {s.name}: the bias of an alternating scheme is not measured")
            return driver(False)

        drv = driver(s.alternate)
        clean = fed() if s.paper else None
        halves = (fed(), fed()) if (s.paper or s.bias) and run.spec.chunks >= 2 else None
        return cls(s, drv, clean, halves=halves)

    def reproject(self, fd: _FrameData) -> tuple[torch.Tensor, torch.Tensor, float]:
        """Run the scheme on the frame: (the evaluated eye's image, the reprojected eye's trace mask, ms of the
        evaluated eye's own steps). The fully traced eye is the right one, or every other frame the left one
        with ``alternate``; the reprojected one's 1-spp samples are read only where the mask says "trace"."""
        s, drv = self.scheme, self.driver
        L, R = fd.eyes[LEFT], fd.eyes[RIGHT]
        right_traced = drv.fully_traced_eye() == "right"
        F, O = (R, L) if right_traced else (L, R)
        t0 = time.perf_counter()
        full_out = drv.full(F.sample, F.depth, F.normal, F.K, F.cam_from_world, *_motion(F, s))
        t1 = time.perf_counter()
        mask = drv.other_trace_mask(O.depth, O.normal, O.K, O.cam_from_world, *_motion(O, s))
        other_out = drv.other(O.sample)
        t2 = time.perf_counter()
        left_out = other_out if right_traced else full_out
        right_out = full_out if right_traced else other_out
        # per-eye accounting: a stereo scheme's left eye pays for its own steps, the right eye for its own
        ms = (t2 - t1) * 1e3 if s.stereo else (t1 - t0) * 1e3
        return (left_out if s.eye == LEFT else right_out), mask, ms

    def score(self, run: _Run, fd: _FrameData, timing: dict, keep: dict) -> None:
        """Run the scheme on the frame and write its scores into the frame's row (RMSE, effective spp and its
        flag, FLIP, SSIM, the temporal error, the noise-free RMSE, the reference-spp study, the discards it
        reports)."""
        s, cfg, row = self.scheme, run.cfg, fd.row
        img, mask, ms = self.reproject(fd)
        timing[f"reproject_{s.name}_ms"].append(ms)
        ref = fd.eyes[s.eye].reference
        err = float(rmse(metric_image(img, cfg.metric), metric_image(ref, cfg.metric))[0])
        spp, flags = effective_spp_many(torch.tensor([err]), *fd.ladder(s.eye, cfg.metric))
        row["rmse"][s.name] = err
        # FLIP and SSIM (LDR, clamped; SSIM of the paper's three schemes): seconds per image at 720p
        perceptual = (run.frames - 1 - fd.frame) % cfg.perceptual_every == 0
        if run.use_flip and perceptual:
            row["flip"][s.name] = float(flip(img, ref)[0])
        if cfg.ssim and s.paper and perceptual:
            row["ssim"][s.name] = float(ssim(img, ref, tonemap="clamp")[0])
        if fd.previous is not None and self.prev_image is not None:
            row["temporal_error"][s.name] = self.temporal_error(run, fd, img, timing)
        self.prev_image = img
        if self.clean is not None:
            row["rmse_noise_free"][s.name] = self.noise_free_rmse(fd, cfg.metric)
        if self.clean is not None or self.halves is not None:
            self.bias(run, fd, img)
        row["effective_spp"][s.name] = float(spp[0])
        if s.paper and fd.prefixes:
            self.reference_study(fd, img, cfg.metric)
        row["flags"][s.name] = flags[0]
        if s.discards is not None:
            _DISCARDS[s.discards](self, run, fd, mask, timing, keep)
        if s.figure4 and fd.frame == run.frames - 1:
            L = fd.eyes[LEFT]
            keep["fig4"] = {
                "method": img.clone(),
                "one": L.sample.clone(),
                "ref": L.reference.clone(),
                "top": L.top.clone(),
                "spp": row["effective_spp"][s.name],
            }
        if fd.frame == run.frames - 1:  # report.html: every scheme's image at the last frame, with its eye's inputs
            last = keep.setdefault("last_frame", {"images": {}, "eyes": {}, "references": {}, "one_spp": {}})
            eye, data = str(s.eye), fd.eyes[s.eye]
            last["images"][s.name], last["eyes"][s.name] = img.clone(), eye
            last["references"][eye], last["one_spp"][eye] = data.reference.clone(), data.sample.clone()

    def temporal_error(self, run: _Run, fd: _FrameData, img: torch.Tensor, timing: dict) -> float | None:
        """The evaluated eye's temporal error against the previous frame (None where no pixel could be warped)."""
        now, before = fd.eyes[self.scheme.eye], fd.previous[self.scheme.eye]
        t0 = time.perf_counter()
        err = temporal_error(
            img,
            now.reference,
            self.prev_image,
            before.reference,
            _view(now),
            _view(before),
            (run.pos_thr, run.nrm_thr),
            tonemap="clamp" if run.cfg.metric == "ldr" else "none",
        )
        timing["temporal_error_ms"].append((time.perf_counter() - t0) * 1e3)
        value = float(err[0])
        return value if math.isfinite(value) else None

    def fed(self, drv: SpatiotemporalReprojection, fd: _FrameData, right: torch.Tensor, left: torch.Tensor):
        """The scheme's evaluated eye with ``drv`` fed ``right`` and ``left`` (instead of 1-spp images)."""
        s = self.scheme
        L, R = fd.eyes[LEFT], fd.eyes[RIGHT]
        c_right = drv.right(right, R.depth, R.normal, R.K, R.cam_from_world, *_motion(R, s))
        drv.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world, *_motion(L, s))
        c_left = drv.left(left)
        return c_left if s.eye == LEFT else c_right

    def noise_free_rmse(self, fd: _FrameData, metric: str) -> float:
        """The RMSE of the scheme fed the whole reference against that reference (bias plus reference noise)."""
        img = self.fed(self.clean, fd, fd.eyes[RIGHT].reference, fd.eyes[LEFT].reference)
        return float(rmse(metric_image(img, metric), metric_image(fd.eyes[self.scheme.eye].reference, metric))[0])

    def bias(self, run: _Run, fd: _FrameData, img: torch.Tensor) -> None:
        """The resampling bias without the reference's noise (with the reference's halves) and the error anatomy
        by footprint, into the frame's row."""
        s, metric, row = self.scheme, run.cfg.metric, fd.row
        bias_map = None
        if self.halves is not None:
            eye = fd.halves[s.eye]
            errors = []
            for i, drv in enumerate(self.halves):
                out = self.fed(drv, fd, fd.halves[RIGHT][i], fd.halves[LEFT][i])
                errors.append(metric_image(out, metric) - metric_image(eye[i], metric))
            bias_map = split_bias(*errors)
            row["bias_mse"][s.name] = float(bias_map.mean())
            row["bias_mse_se"][s.name] = block_standard_error(bias_map)
            row["reference_noise_mse"][s.name] = reference_noise_mse(
                metric_image(eye[0], metric), metric_image(eye[1], metric), *fd.half_spp
            )
        regions = self.footprint_regions(run, fd)
        if regions is not None:
            se = squared_error(metric_image(img, metric), metric_image(fd.eyes[s.eye].reference, metric))
            row["anatomy"][s.name] = _anatomy_shares(regions, se, bias_map)

    def footprint_regions(self, run: _Run, fd: _FrameData) -> dict | None:
        """The evaluated eye's pixels by the outcome of the scheme's reprojection into it and its 4×4 footprint
        (:func:`~stereorepro.measure.anatomy.footprint_regions`): the stereo step (right -> left) for the
        stereo schemes, the temporal step (previous -> current right frame) for temporal; None without one
        (temporal's first frame)."""
        s, drv = self.scheme, self.driver
        thr = (run.pos_thr, run.nrm_thr)
        if s.stereo:
            L, R = fd.eyes[LEFT], fd.eyes[RIGHT]
            if "stereo" not in fd.footprints:
                src = View(R.depth, R.normal, R.K, R.cam_from_world)
                fd.footprints["stereo"] = footprint_failures(src, View(L.depth, L.normal, L.K, L.cam_from_world), thr)
            return footprint_regions(fd.footprints["stereo"], drv.stereo_valid, fd.surface[LEFT])
        if fd.previous is None or drv.right_valid is None:
            return None
        key = "temporal_motion" if s.motion else "temporal"
        if key not in fd.footprints:
            P, R = fd.previous[RIGHT], fd.eyes[RIGHT]
            motion, motion_world = _motion(R, s)
            dst = View(R.depth, R.normal, R.K, R.cam_from_world, motion, motion_world)
            fd.footprints[key] = footprint_failures(View(P.depth, P.normal, P.K, P.cam_from_world), dst, thr)
        return footprint_regions(fd.footprints[key], drv.right_valid, fd.surface[RIGHT])

    def reference_study(self, fd: _FrameData, img: torch.Tensor, metric: str) -> None:
        """The same image scored against each smaller reference, with the ladder scored on that reference."""
        s = self.scheme
        lad = torch.as_tensor(fd.eyes[s.eye].prefix_ladder_rmse[metric], dtype=torch.float64)
        spp = torch.tensor(fd.ladder_spp, dtype=torch.float64)
        for i, p in enumerate(fd.prefixes):
            e_p = rmse(metric_image(img, metric), fd.prefix_refs[s.eye][p])
            spp_p, _ = effective_spp_many(e_p, spp, lad[i : i + 1])
            fd.row["reference_study"].setdefault(str(p), {})[s.name] = float(spp_p[0])


def _anatomy_shares(regions: dict, se: torch.Tensor, bias_map: torch.Tensor | None) -> dict:
    """Per region: its share of the pixels, of the squared error and (with ``bias_map``) of the bias, in %."""
    total_se, total_bias = float(se.sum()), None if bias_map is None else float(bias_map.sum())
    out = {}
    for name, m in regions.items():
        out[name] = {
            "pixels_pct": 100.0 * float(m.sum()) / m.numel(),
            "mse_share_pct": 100.0 * float(se[m].sum()) / total_se if total_se > 0 else None,
            "bias_share_pct": (
                100.0 * float(bias_map[m].sum()) / total_bias if total_bias is not None and total_bias > 0 else None
            ),
        }
    return out


def _stereo_discards(sr: _SchemeRun, run: _Run, fd: _FrameData, mask, timing: dict, keep: dict) -> None:
    """Table 1 and Figure 1 (a): the left eye's pixels traced because reprojection rejected them, over its surface
    pixels; at the figure's frame also the masked trace the paper counts, timed for real (the same samples as the
    full 1-spp render, which the row checks)."""
    name, row, L, surf = sr.scheme.name, fd.row, fd.eyes[LEFT], fd.surface[LEFT]
    row["discard_pct"][name] = 100.0 * float((mask & surf).sum() / surf.sum().clamp_min(1))
    if fd.frame != run.fig1_frame:
        return
    keep["fig1_" + name] = sr.driver.stereo_reason.clone()
    r = run.ctx.tracer.render(
        L.camera,
        fd.frame,
        1,
        sample_offset=0,
        eye=LEFT,
        gbuffers=False,
        pixel_mask=mask[0, 0],
        pixel_sampling=L.pixel_sampling,
    )
    timing["trace_left_discards_ms"].append(r.time_s * 1e3)
    row["masked_trace_matches"] = bool(
        torch.equal(torch.where(mask, r.radiance, 0.0), torch.where(mask, L.sample, 0.0))
    )


def _temporal_discards(sr: _SchemeRun, run: _Run, fd: _FrameData, mask, timing: dict, keep: dict) -> None:
    """Table 1 and Figure 1 (b): the right eye's pixels whose history was rejected, over its surface pixels; with
    moving objects also on the moving objects' pixels and on the static rest."""
    name, drv, row = sr.scheme.name, sr.driver, fd.row
    if drv.right_valid is None:
        return
    surf = fd.surface[RIGHT]
    row["discard_pct"][name] = 100.0 * float((~drv.right_valid & surf).sum() / surf.sum().clamp_min(1))
    if run.moving:
        mov = (fd.eyes[RIGHT].object_id >= 0) & surf
        for part, sel in (("discard_pct_moving", mov), ("discard_pct_static", surf & ~mov)):
            row[part][name] = 100.0 * float((~drv.right_valid & sel).sum() / sel.sum()) if bool(sel.any()) else None
    if fd.frame == run.fig1_frame:
        keep["fig1_" + name] = drv.right_reason.clone()


#: The discards a scheme reports (:attr:`~.config.Scheme.discards`) and how they are measured.
_DISCARDS = {"stereo": _stereo_discards, "temporal": _temporal_discards}


def _assemble(
    run: _Run, schemes: list[_SchemeRun], per_frame: list[dict], timing: dict, wall: float
) -> ExperimentResults:
    """The statistics over frames of everything the rows hold, and the run's settings, as one record."""
    cfg, scene = run.cfg, run.scene
    stats = {s.scheme.name: _spp_stats(per_frame, s.scheme.name, cfg.ladder_spp) for s in schemes}
    paper = [s.scheme for s in schemes if s.scheme.paper]
    timing_ms = {k: float(np.median(v)) if v else None for k, v in timing.items()}
    return ExperimentResults(
        scene=scene.name,
        effects=sorted(scene.effects),
        frames=run.frames,
        resolution=f"{cfg.width}x{cfg.height}",
        reference_spp=cfg.reference_spp,
        reference_chunk_spp=run.spec.reference_chunk_spp,
        ladder_spp=cfg.ladder_spp,
        warmup_frames=WARMUP_FRAMES,
        reference_study=_reference_study(per_frame, stats, cfg) or None,
        seed=cfg.seed,
        metric=cfg.metric,
        jitter=bool(cfg.jitter),
        history_rounding=cfg.history_rounding,
        footprint_weighting=bool(cfg.footprint_weighting),
        option_variants=bool(cfg.option_variants),
        perceptual_every=cfg.perceptual_every,
        thresholds={
            "position": run.pos_thr,
            "normal": run.nrm_thr,
            "position_scene": float(scene.position_threshold),
            "scale": run.scale,
        },
        table1={s.name: _stats([r["discard_pct"].get(s.name) for r in per_frame]) for s in paper if s.discards},
        flip=(
            {s.scheme.name: _stats([r["flip"].get(s.scheme.name) for r in per_frame]) for s in schemes}
            if run.use_flip
            else None
        ),
        ssim=({s.name: _stats([r["ssim"].get(s.name) for r in per_frame]) for s in paper} if cfg.ssim else None),
        temporal_error=(
            {s.scheme.name: _stats([r["temporal_error"].get(s.scheme.name) for r in per_frame]) for s in schemes}
            if run.frames > 1
            else None
        ),
        moving_objects=_moving_table(schemes, per_frame) if run.moving else None,
        table2={s.name: stats[s.name] for s in paper},
        table2_variants={k: v for k, v in stats.items() if k not in {s.name for s in paper}},
        timing_ms=timing_ms,
        cost=_cost_table([s.scheme for s in schemes], stats, timing_ms, cfg),
        bias=_bias_table(schemes, per_frame),
        per_frame=per_frame,
        flags=_flag_counts(per_frame),
        cache={
            "hits": run.cache.hits,
            "misses": run.cache.misses,
            "recomputed_corrupt": run.cache.corrupt,
            "dir": str(run.cache_dir),
            **cache_footprint(run.ctx, run.frames),
        },
        distributed=run.distributed,
        wall_s=wall,
        version=__version__,
        code=json.loads(run.spec.base_key)["code"],
    )


def _moving_table(schemes: list[_SchemeRun], per_frame: list[dict]) -> dict:
    """Temporal discards on moving-object pixels vs the static background, camera-only vs motion vectors."""
    temporal = [s.scheme.name for s in schemes if s.scheme.discards == "temporal"]
    return {
        "moving_pixels_pct": _stats([r["moving_pct"] for r in per_frame]),
        **{
            k: {part: _stats([r[f"discard_pct_{part}"].get(k) for r in per_frame]) for part in ("moving", "static")}
            for k in temporal
        },
    }


#: The regions of the error anatomy (:func:`~stereorepro.measure.anatomy.footprint_regions`) and what each reports.
ANATOMY_REGIONS = ("interior", "edge", "discarded", "no surface")
ANATOMY_FIELDS = ("pixels_pct", "mse_share_pct", "bias_share_pct")


def _bias_table(schemes: list[_SchemeRun], per_frame: list[dict]) -> dict:
    """Per paper scheme (and option variant: :attr:`~.config.Scheme.bias`), statistics over frames of:

    * ``bias_mse``: the squared resampling bias without the reference's noise, the mean product of the scheme's
      errors on the reference's two independent halves (:func:`~stereorepro.measure.anatomy.split_bias`), and
      ``bias_mse_se`` its standard error (8×8 tiles); ``bias_share``: ``bias_mse`` over the scheme's MSE (what
      the tables score, against the run's reference); ``reference_noise_mse``: the noise the run's reference
      still carries (from its halves' spread), and ``bias_share_without_reference_noise``: ``bias_mse`` over
      the scheme's MSE less that noise. None (``n`` 0) for a reference in one chunk;
    * ``anatomy``: region (``interior``, ``edge``, ``discarded``, ``no surface``) -> its share of the pixels, of
      the scheme's squared error and of the bias (%), by the scheme's reprojection into the evaluated eye and its
      4×4 footprint (:func:`~stereorepro.measure.anatomy.footprint_regions`);
    * ``rmse_noise_free`` and ``bias_share_of_mse``: the scheme fed the whole reference and scored against it,
      which counts a copy of the reference's noise as bias (the former estimate, kept for its readers; the paper's
      schemes only, ``n`` 0 for the others).

    ``ladder_top_rmse``: the left eye's top-rung RMSE, for scale."""

    def ratio(r, k, noise: bool):
        b, mse = r["bias_mse"].get(k), r["rmse"][k] ** 2
        den = mse - r["reference_noise_mse"][k] if noise and b is not None else mse
        return b / den if b is not None and den > 0 else None

    bias = {}
    for k in (s.scheme.name for s in schemes if s.clean is not None or s.halves is not None):
        rows = [r for r in per_frame if k in r["anatomy"]]
        bias[k] = {
            "rmse_noise_free": _stats([r["rmse_noise_free"].get(k) for r in per_frame]),
            "bias_share_of_mse": _stats(
                [(r["rmse_noise_free"][k] / r["rmse"][k]) ** 2 for r in per_frame if r["rmse"][k] > 0]
                if k in per_frame[0]["rmse_noise_free"]
                else []
            ),
            "bias_mse": _stats([r["bias_mse"].get(k) for r in per_frame]),
            "bias_mse_se": _stats([r["bias_mse_se"].get(k) for r in per_frame]),
            "bias_share": _stats([ratio(r, k, False) for r in per_frame]),
            "reference_noise_mse": _stats([r["reference_noise_mse"].get(k) for r in per_frame]),
            "bias_share_without_reference_noise": _stats([ratio(r, k, True) for r in per_frame]),
            "anatomy": {
                g: {f: _stats([r["anatomy"][k][g][f] for r in rows]) for f in ANATOMY_FIELDS} for g in ANATOMY_REGIONS
            },
        }
    bias["ladder_top_rmse"] = _stats([r["ladder_rmse"]["left"][-1] for r in per_frame])
    return bias


def _reference_study(per_frame: list[dict], table2: dict, cfg: ExperimentConfig) -> dict:
    """Effective spp against each smaller reference (chunked runs), the run's own reference last for comparison;
    empty without chunks."""
    study = {
        p: {k: _stats([r["reference_study"][p][k] for r in per_frame]) for k in per_frame[0]["reference_study"][p]}
        for p in per_frame[0]["reference_study"]
    }
    if study:
        study[str(cfg.reference_spp)] = {k: table2[k] for k in next(iter(study.values()))}
    return study


def _flag_counts(per_frame) -> dict:
    counts: dict = {}
    for r in per_frame:
        for k, fl in r["flags"].items():
            counts.setdefault(k, {}).setdefault(fl, 0)
            counts[k][fl] += 1
    return counts


def _cost_table(schemes, table2, t, cfg) -> list[dict]:
    """ms per frame of the evaluated eye for each scheme and for plain path tracing at n spp.

    Per-eye cost accounting: the stereo schemes' left eye costs its G-buffer, the reprojection and the traced
    discards (the right eye is paid for once, by itself); temporal's right eye costs its 1-spp trace, its G-buffer
    and the reprojection. G-buffers are counted although a real renderer gets them with the primary ray.
    """
    spp_ms = t["trace_1spp_ms"]
    gb = t["gbuffer_ms"]
    masked = t["trace_left_discards_ms"] or 0.0
    rows = [
        {"scheme": f"path tracing {n} spp", "ms": n * spp_ms, "effective_spp": float(n), "ms_per_effective_spp": spp_ms}
        for n in (1, 2, 4, 8, 16)
        if n <= cfg.ladder_spp
    ]
    for s in schemes:
        rep = t[f"reproject_{s.name}_ms"]
        if s.stereo:
            ms = gb + rep + masked
        else:
            ms = spp_ms + gb + rep
        st = table2[s.name]
        beyond = st.get("beyond_ladder") or 0
        e = st["avg_lower_bound"] if beyond else st["avg"]  # frames beyond the ladder: at least, not extrapolated
        rows.append(
            {
                "scheme": s.name,
                "ms": ms,
                "effective_spp": e,
                "ms_per_effective_spp": (ms / e) if e else None,
                "reprojection_ms": rep,
                "beyond_ladder": beyond,
            }
        )
    return rows
