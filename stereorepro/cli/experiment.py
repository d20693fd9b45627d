"""Sub-command ``stereorepro experiment``: the paper's experiment (:mod:`stereorepro.workflows.experiment`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..camera import DEFAULT_RESOLUTION
from ..errors import UserError
from ..workflows.experiment import ExperimentConfig, run_experiment, tables_markdown
from ..workflows.experiment.distributed import ClusterError
from ._args import alpha_list, parse_resolution, positive_int, threshold_scale

__all__ = ["add_arguments", "config_from_args", "run_command", "register"]


def add_arguments(p: argparse.ArgumentParser, defaults: dict | None = None) -> None:
    d = defaults or {}
    p.add_argument("--scene", default=d.get("scene"), required="scene" not in d, help="built-in name or .toml path")
    p.add_argument("--frames", type=positive_int, default=d.get("frames"), help="frames (default: the scene's)")
    p.add_argument("--resolution", type=parse_resolution, default=d.get("resolution", DEFAULT_RESOLUTION), help="WxH")
    p.add_argument(
        "--reference-spp", type=positive_int, default=d.get("reference_spp", 256), help=">= 4 and >= --ladder-spp"
    )
    p.add_argument("--ladder-spp", type=positive_int, default=d.get("ladder_spp", 16), help=">= 2")
    p.add_argument(
        "--reference-chunk-spp",
        type=positive_int,
        default=None,
        help="samples per reference render task (>= 4, divides --reference-spp; default: one task); the "
        "ladder is also scored against the power-of-two chunk prefixes (a reference-spp study for "
        "free)",
    )
    p.add_argument("--out", default=d.get("out"), required="out" not in d)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--alphas",
        type=alpha_list,
        default=(0.1, 0.5),
        help="extra EMA weights in (0, 1] measured beside 0.2, comma-separated (default 0.1,0.5)",
    )
    p.add_argument(
        "--threshold-scale",
        type=threshold_scale,
        default=None,
        help="'auto' (default) = max(1, 180/height), or a positive number",
    )
    p.add_argument("--workers", type=positive_int, default=None)
    p.add_argument("--exr", action="store_true", help="also write EXR frames of both eyes")
    p.add_argument("--force", action="store_true", help="recompute cached renders")
    p.add_argument("--cache-dir", default=None, help="render cache (default: OUT/cache); runs may share one")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--jitter",
        action="store_true",
        help="TAA-style Halton(2,3) sub-pixel jitter of the schemes' inputs (both eyes alike)",
    )
    p.add_argument(
        "--history-rounding",
        choices=("none", "bmfr"),
        default="none",
        help="how the temporal steps store history lengths: floats (none, default) or BMFR's integer counts (bmfr)",
    )
    p.add_argument(
        "--footprint-weighting",
        action="store_true",
        help="scale the warped history length by the footprint quality (NVIDIA NRD's rule)",
    )
    p.add_argument(
        "--option-variants",
        action="store_true",
        help="also run the paper's temporal and stereo+temporal schemes with each history option alone "
        "(footprint weighting, BMFR rounding, Catmull-Rom, ...), their bias measured too",
    )
    p.add_argument("--no-flip", action="store_true", help="skip the FLIP scores (seconds per image at 720p)")
    p.add_argument("--no-ssim", action="store_true", help="skip the SSIM scores (seconds per image at 720p)")
    p.add_argument(
        "--perceptual-every",
        type=int,
        default=1,
        metavar="K",
        help="score FLIP and SSIM on every K-th frame only, counted back from the last (default 1: every frame)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        help="render on Dask: 'local:N' (N worker processes here) or 'tcp://HOST:PORT' (a running "
        "scheduler whose workers share --cache-dir); default: in this process",
    )
    p.add_argument(
        "--metric",
        choices=("hdr", "ldr"),
        default="ldr",
        help="RMSE on linear radiance (hdr) or on values clamped to [0, 1] (ldr, display-referred)",
    )
    p.add_argument(
        "--renderer-version",
        default=None,
        help="cache key of a previous run's renderer (results.json 'code'): re-analyse its cached renders",
    )


def config_from_args(args) -> ExperimentConfig:
    w, h = args.resolution
    return ExperimentConfig(
        scene=args.scene,
        out=args.out,
        frames=args.frames,
        width=w,
        height=h,
        reference_spp=args.reference_spp,
        ladder_spp=args.ladder_spp,
        seed=args.seed,
        alphas=tuple(args.alphas),
        threshold_scale=args.threshold_scale,
        workers=args.workers,
        exr=args.exr,
        force=args.force,
        progress=not args.no_progress,
        renderer_version=args.renderer_version,
        cache_dir=args.cache_dir,
        metric=args.metric,
        reference_chunk_spp=args.reference_chunk_spp,
        flip=not args.no_flip,
        ssim=not args.no_ssim,
        perceptual_every=args.perceptual_every,
        scheduler=args.scheduler,
        jitter=args.jitter,
        history_rounding=args.history_rounding,
        footprint_weighting=args.footprint_weighting,
        option_variants=args.option_variants,
    )


def run_command(args) -> int:
    """Run the experiment of parsed ``args`` (shared by ``experiment`` and ``demo``); print the tables."""
    cfg = config_from_args(args)
    try:
        results = run_experiment(cfg)
    except (ValueError, FileNotFoundError, ClusterError) as e:  # SceneError and the config's checks are ValueErrors
        raise UserError(str(e)) from None
    print(tables_markdown(results))
    print(
        f"report: {Path(cfg.out) / 'report.md'} and report.html (figures and results.json beside it); wall {results['wall_s']:.0f} s"
    )
    return 0


def register(sub) -> None:
    p = sub.add_parser("experiment", help="the paper's experiment: effective spp, Tables 1-2, figures, time cost")
    add_arguments(p)
    p.set_defaults(func=run_command)
