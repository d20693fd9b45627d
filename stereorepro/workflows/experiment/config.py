"""Settings of an experiment run and the schemes it measures."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from ..._checks import check_backend_env, check_resolution
from ...camera import DEFAULT_RESOLUTION, Eye
from ...reproject import FastClamp
from ...scenes import THRESHOLD_ROWS

__all__ = [
    "REFERENCE_OFFSET",
    "THRESHOLD_ROWS",
    "LEFT",
    "RIGHT",
    "METRICS",
    "Scheme",
    "SCHEMES",
    "MOTION_SCHEMES",
    "OPTION_VARIANTS",
    "PLANE_POSITION_THRESHOLD",
    "ExperimentConfig",
    "schemes",
    "validate_config",
    "metric_image",
    "MIN_REFERENCE_SPP",
    "EXPERIMENT_BYTES_PER_PIXEL",
]

#: First sample index of reference renders (ladders use 0..L-1: disjoint streams).
REFERENCE_OFFSET = 1 << 24
LEFT, RIGHT = Eye.LEFT, Eye.RIGHT
#: The fewest samples of a reference the ladder is scored against (the reference and each chunk prefix): below it the
#: reference's noise, and the ldr metric's clamp of a noisy sample, make the ladder's error stop decreasing with spp
#: (a ladder 1..2 against 2 spp, 1..16 against a 1-spp prefix) and effective spp is undefined.
MIN_REFERENCE_SPP = 4
#: Peak memory of a run per pixel (both eyes' renders and the previous frame's, every scheme's state and previous
#: output, the scores and the figures), with a margin: the estimate of the resolution guard
#: (:func:`stereorepro._checks.check_resolution`).
EXPERIMENT_BYTES_PER_PIXEL = 3072

#: The experiment's image metrics: ``"ldr"`` scores images clamped to [0, 1], ``"hdr"`` linear radiance.
METRICS = ("ldr", "hdr")


def metric_image(x, metric: str):
    """The image the metric scores: ``x`` clamped to [0, 1] for ``"ldr"``, ``x`` itself for ``"hdr"``.

    Examples:
        >>> import torch
        >>> from stereorepro.workflows.experiment.config import metric_image
        >>> x = torch.tensor([-0.5, 0.25, 2.0])
        >>> metric_image(x, "ldr").tolist(), metric_image(x, "hdr").tolist()
        ([0.0, 0.25, 1.0], [-0.5, 0.25, 2.0])
    """
    return x.clamp(0.0, 1.0) if metric == "ldr" else x


@dataclass(frozen=True)
class Scheme:
    """One measured scheme: its name, which reprojections it uses, the eye it is scored on and its settings.

    Examples:
        >>> from stereorepro.workflows.experiment.config import SCHEMES, Scheme
        >>> s = next(s for s in SCHEMES if s.name == "stereo_temporal")
        >>> s.stereo, s.temporal, s.eye.name, s.alpha, s.paper
        (True, True, 'LEFT', 0.2, True)
        >>> isinstance(s, Scheme)
        True
    """

    name: str
    stereo: bool
    temporal: bool
    eye: Eye  # evaluated eye
    sampling: str = "bilinear"
    alpha: float = 0.2
    paper: bool = False  # one of the paper's three Table 2 columns
    motion: bool = False  # temporal steps through the tracer's motion vectors (scenes with moving objects)
    #: The left eye's rule (:class:`~stereorepro.SpatiotemporalReprojection`): ``"fill"`` (the paper: the
    #: reprojected right eye where accepted, the own history only under traced discards) or ``"blend"`` (the
    #: follow-up: both histories blended at every pixel).
    left_mode: str = "fill"
    #: Trace the right eye in full on even frames and the left on odd ones, each reprojected into the other
    #: (the ray budget of ``stereo_temporal``).
    alternate: bool = False
    #: The discards the run reports for this scheme (Table 1, Figure 1): ``"stereo"``, the left eye's pixels traced
    #: because reprojection rejected them; ``"temporal"``, the right eye's pixels whose history was rejected (and,
    #: with moving objects, split into moving and static pixels); None: none.
    discards: str | None = None
    #: The scheme of Figure 4 (its evaluated eye at the last frame beside 1 spp, the reference and the top rung).
    figure4: bool = False
    #: Driver settings of this scheme over the run's (``(attribute, value)`` pairs set on its
    #: :class:`~stereorepro.SpatiotemporalReprojection` drivers): the option variants of :data:`OPTION_VARIANTS`.
    options: tuple[tuple[str, object], ...] = ()
    #: Also measure the resampling bias without reference noise (the paper's schemes always do).
    bias: bool = False
    #: The scheme's own position threshold, in the units of its position test (``"plane"``: a fraction of view
    #: depth), instead of the scene's (scaled) one; None: the scene's.
    position_threshold: float | None = None


SCHEMES = (
    Scheme("stereo", True, False, LEFT, paper=True, discards="stereo"),
    Scheme("temporal", False, True, RIGHT, paper=True, discards="temporal"),
    Scheme("stereo_temporal", True, True, LEFT, paper=True, figure4=True),
    Scheme("stereo_nearest", True, False, LEFT, "nearest"),
    Scheme("temporal_nearest", False, True, RIGHT, "nearest"),
    Scheme("stereo_temporal_nearest", True, True, LEFT, "nearest"),
    # beyond the paper: its authors' follow-up (IEEE Access 2020) blends traced and stereo-reprojected data
    Scheme("stereo_temporal_blend", True, True, LEFT, left_mode="blend"),
    Scheme("alternate", True, True, LEFT, alternate=True),
    Scheme("alternate_blend", True, True, LEFT, left_mode="blend", alternate=True),
)


@dataclass(frozen=True)
class ExperimentConfig:
    """Settings of one experiment run (see ``stereorepro experiment --help``).

    Examples:
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig
        >>> cfg = ExperimentConfig(scene="cornell", out="runs/a", width=8, height=6, frames=2)
        >>> cfg.width, cfg.height, cfg.reference_spp, cfg.ladder_spp, cfg.metric
        (8, 6, 256, 16, 'ldr')
    """

    scene: str
    out: str
    frames: int | None = None  #: None = the scene's own frame count
    width: int = DEFAULT_RESOLUTION[0]
    height: int = DEFAULT_RESOLUTION[1]
    reference_spp: int = 256  #: >= ladder_spp and >= MIN_REFERENCE_SPP
    ladder_spp: int = 16
    #: Samples per reference chunk (a render task of its own; distributed runs spread the chunks over workers);
    #: None = one chunk of ``reference_spp``. Must divide ``reference_spp``, >= MIN_REFERENCE_SPP; see :mod:`.inputs` for how chunking
    #: enters the reference's value and the cache key.
    reference_chunk_spp: int | None = None
    seed: int = 0
    alphas: tuple[float, ...] = (0.1, 0.5)  #: extra EMA weights measured beside the paper's 0.2
    threshold_scale: float | None = None  #: None = auto: stereorepro.scenes.threshold_scale(height)
    workers: int | None = None
    exr: bool = False
    force: bool = False
    progress: bool = True
    cache_dir: str | None = None  #: default: <out>/cache
    #: Renderer version used in cache keys; None = a hash of the current renderer sources. Set it to a run's
    #: recorded ``code`` to re-analyse that run's cached renders after the renderer changed (no re-rendering).
    renderer_version: str | None = None
    #: ``"hdr"``: RMSE of linear radiance; ``"ldr"``: RMSE after clamping to [0, 1] (display-referred), applied alike
    #: to the method's images, the ladder and the reference.
    metric: str = "ldr"
    #: Also report the mean LDR FLIP per scheme and frame (when ``flip-evaluator`` is installed; see
    #: :func:`stereorepro.measure.metrics.flip`). Effective spp stays MSE-based.
    flip: bool = True
    #: Also report the mean LDR SSIM (:func:`stereorepro.measure.metrics.ssim`, clamp) of the paper's three schemes
    #: per frame.
    ssim: bool = True
    #: Score FLIP and SSIM on every K-th frame only, counted back from the last (K = 1: every frame). Each costs
    #: about a second per image at 1280x720 on a CPU, for every scheme and frame; a stride samples the same averages
    #: (their statistics' ``n`` says how many frames). RMSE, effective spp and the temporal error stay per frame.
    perceptual_every: int = 1
    #: Where renders run: None = in this process; ``"local:N"`` = a Dask LocalCluster of N worker processes;
    #: ``"tcp://HOST:PORT"`` = a running Dask scheduler (workers must share ``cache_dir``). See :mod:`.distributed`.
    scheduler: str | None = None
    #: TAA-style sub-pixel camera jitter of the schemes' inputs (Halton(2, 3) per frame, both eyes alike,
    #: :func:`stereorepro.camera.jitter_offset`): their G-buffers and 1-spp samples come from the jittered cameras,
    #: one sample through each pixel centre; the ladders and the references stay unjittered (box-filtered pixels).
    jitter: bool = False
    #: How every scheme's temporal steps store history lengths: ``"none"`` (floats) or ``"bmfr"`` (BMFR's integer
    #: counts, :attr:`stereorepro.SpatiotemporalReprojection.history_rounding`).
    history_rounding: str = "none"
    #: Every scheme's temporal steps scale the warped history length by the footprint quality (NVIDIA NRD's rule,
    #: :attr:`stereorepro.SpatiotemporalReprojection.footprint_weighting`).
    footprint_weighting: bool = False
    #: Add Table 2's option variants (:data:`OPTION_VARIANTS`): the paper's temporal and stereo+temporal schemes
    #: with each option of the history alone, their bias measured like the paper's schemes'.
    option_variants: bool = False


#: The position threshold of the plane-distance test's variant (``Thresholds(position_test="plane")``): the
#: tap's distance to the destination pixel's plane, as a fraction of its view depth (slope-scaled).
PLANE_POSITION_THRESHOLD = 0.005

#: Table 2's option variants (``stereorepro experiment --option-variants``): the paper's temporal and
#: stereo+temporal schemes, each with one option of the history on, named ``<scheme>_<suffix>``: suffix ->
#: (sampling, driver settings, position threshold or None for the scene's). Each measures its resampling bias too.
OPTION_VARIANTS: dict[str, tuple[str, tuple[tuple[str, object], ...], float | None]] = {
    "footprint": ("bilinear", (("footprint_weighting", True),), None),
    "bmfr": ("bilinear", (("history_rounding", "bmfr"),), None),
    "catmull_rom": ("catmull_rom", (), None),
    "plane": ("bilinear", (("position_test", "plane"),), PLANE_POSITION_THRESHOLD),
    # the plane test lets whole 4x4 footprints pass on most surfaces: where Catmull-Rom reads act
    "plane_catmull_rom": ("catmull_rom", (("position_test", "plane"),), PLANE_POSITION_THRESHOLD),
    "clamp": ("bilinear", (("fast_clamp", FastClamp()),), None),
}


#: Variants of scenes with moving objects: the temporal steps read the history through the motion vectors.
MOTION_SCHEMES = (
    Scheme("temporal_mv", False, True, RIGHT, motion=True, discards="temporal"),
    Scheme("stereo_temporal_mv", True, True, LEFT, motion=True),
)


def schemes(cfg: ExperimentConfig, moving_objects: bool = False) -> list[Scheme]:
    """The paper's schemes and the variants, with alpha variants (temporal, stereo+temporal, blended) for each
    extra ``cfg.alphas`` weight, and the motion-vector variants when the scene has moving objects.

    Examples:
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig, schemes
        >>> cfg = ExperimentConfig(scene="cornell", out="runs/a", alphas=(0.5,))
        >>> names = [s.name for s in schemes(cfg)]
        >>> len(names), names[:3], "temporal_alpha0.5" in names
        (12, ['stereo', 'temporal', 'stereo_temporal'], True)
        >>> "temporal_mv" in [s.name for s in schemes(cfg, moving_objects=True)]
        True
        >>> [s.name for s in schemes(ExperimentConfig(scene="cornell", out="runs/a", option_variants=True))][-2:]
        ['temporal_clamp', 'stereo_temporal_clamp']
    """
    out = list(SCHEMES) + (list(MOTION_SCHEMES) if moving_objects else [])
    for a in cfg.alphas:
        if abs(a - 0.2) > 1e-12:
            out.append(Scheme(f"temporal_alpha{a:g}", False, True, RIGHT, alpha=a))
            out.append(Scheme(f"stereo_temporal_alpha{a:g}", True, True, LEFT, alpha=a))
            out.append(Scheme(f"stereo_temporal_blend_alpha{a:g}", True, True, LEFT, alpha=a, left_mode="blend"))
    if cfg.option_variants:
        for suffix, (sampling, options, pos) in OPTION_VARIANTS.items():
            kw = dict(options=options, bias=True, position_threshold=pos)
            out.append(Scheme(f"temporal_{suffix}", False, True, RIGHT, sampling, **kw))
            out.append(Scheme(f"stereo_temporal_{suffix}", True, True, LEFT, sampling, **kw))
    return out


def validate_config(cfg: ExperimentConfig) -> None:
    """ValueError naming the setting and what it expects (the run checks this before it writes anything).

    Examples:
        >>> import tempfile
        >>> from stereorepro.workflows.experiment.config import ExperimentConfig, validate_config
        >>> with tempfile.TemporaryDirectory() as d:
        ...     print(validate_config(ExperimentConfig(scene="cornell", out=d, width=8, height=6)))
        None
        >>> try:
        ...     validate_config(ExperimentConfig(scene="cornell", out="runs/a", ladder_spp=1))
        ... except ValueError as e:
        ...     print(e)
        ladder_spp must be an integer >= 2, got 1
    """

    def need(ok: bool, what: str) -> None:
        if not ok:
            raise ValueError(what)

    def is_int(x) -> bool:
        return isinstance(x, int) and not isinstance(x, bool)

    need(cfg.metric in ("hdr", "ldr"), f"metric must be 'hdr' or 'ldr', got {cfg.metric!r}")
    need(
        is_int(cfg.width) and is_int(cfg.height) and cfg.width >= 1 and cfg.height >= 1,
        f"resolution must be positive integers, got {cfg.width}x{cfg.height}",
    )
    need(is_int(cfg.ladder_spp) and cfg.ladder_spp >= 2, f"ladder_spp must be an integer >= 2, got {cfg.ladder_spp}")
    need(
        is_int(cfg.reference_spp) and cfg.reference_spp >= cfg.ladder_spp,
        f"reference_spp must be an integer >= ladder_spp ({cfg.ladder_spp}), got {cfg.reference_spp}",
    )
    need(
        cfg.reference_chunk_spp is None
        or (
            is_int(cfg.reference_chunk_spp)
            and cfg.reference_chunk_spp >= 1
            and cfg.reference_spp % cfg.reference_chunk_spp == 0
        ),
        f"reference_chunk_spp must be a positive integer dividing reference_spp ({cfg.reference_spp}), "
        f"got {cfg.reference_chunk_spp}",
    )
    need(
        cfg.scheduler is None or (isinstance(cfg.scheduler, str) and _scheduler_ok(cfg.scheduler)),
        f"scheduler must be 'local:N' (N >= 1) or 'tcp://HOST:PORT' (PORT in 1..65535), got {cfg.scheduler!r}",
    )
    _check_ladder_noise(cfg)
    need(
        cfg.frames is None or (is_int(cfg.frames) and cfg.frames >= 1),
        f"frames must be an integer >= 1, got {cfg.frames}",
    )
    need(
        cfg.workers is None or (is_int(cfg.workers) and cfg.workers >= 1),
        f"workers must be an integer >= 1, got {cfg.workers}",
    )
    need(is_int(cfg.seed), f"seed must be an integer, got {cfg.seed!r}")
    for a in cfg.alphas:
        need(
            isinstance(a, (int, float)) and math.isfinite(a) and 0.0 < a <= 1.0,
            f"alphas must be numbers in (0, 1], got {a!r}",
        )
    need(
        is_int(cfg.perceptual_every) and cfg.perceptual_every >= 1,
        f"perceptual_every must be an integer >= 1, got {cfg.perceptual_every!r}",
    )
    need(
        cfg.history_rounding in ("none", "bmfr"),
        f"history_rounding must be 'none' or 'bmfr', got {cfg.history_rounding!r}",
    )
    need(
        isinstance(cfg.footprint_weighting, bool),
        f"footprint_weighting must be True or False, got {cfg.footprint_weighting!r}",
    )
    need(
        isinstance(cfg.option_variants, bool),
        f"option_variants must be True or False, got {cfg.option_variants!r}",
    )
    need(
        cfg.threshold_scale is None or (math.isfinite(cfg.threshold_scale) and cfg.threshold_scale > 0),
        f"threshold_scale must be a positive number, got {cfg.threshold_scale!r}",
    )
    for name, value in (("out", cfg.out), ("cache_dir", cfg.cache_dir)):
        if value is not None:
            p = Path(value)
            need(not p.exists() or p.is_dir(), f"{name}: {p} exists and is not a directory")
    check_backend_env()
    check_resolution(cfg.width, cfg.height, EXPERIMENT_BYTES_PER_PIXEL, "the experiment")


def _check_ladder_noise(cfg: ExperimentConfig) -> None:
    """ValueError naming the option when a reference the ladder is scored against (the reference, and with chunks
    each power-of-two chunk prefix, the smallest being ``reference_chunk_spp``) has fewer than
    :data:`MIN_REFERENCE_SPP` samples."""
    for name, p in (
        ("reference_spp (--reference-spp)", cfg.reference_spp),
        ("reference_chunk_spp (--reference-chunk-spp)", cfg.reference_chunk_spp),
    ):
        if p is not None and p < MIN_REFERENCE_SPP:
            raise ValueError(
                f"{name} must be >= {MIN_REFERENCE_SPP}, got {p}: the ladder is scored against a "
                f"{p}-spp reference, whose own noise (and, under the ldr metric, the clamp of a noisy "
                "sample) keeps the ladder's error from decreasing, and effective spp needs it to"
            )


def _scheduler_ok(s: str) -> bool:
    if s.startswith("local:"):
        n = s[len("local:") :]
        return n.isdigit() and int(n) >= 1
    if s.startswith("tcp://"):
        host, _, port = s[len("tcp://") :].rpartition(":")
        return bool(host) and port.isdigit() and 1 <= int(port) <= 65535
    return False
