"""``stereorepro demo``: the main job on a built-in default — a quick run of the paper's experiment.

Runs :func:`stereorepro.experiment.run_experiment` on the built-in ``living_room`` scene at a small resolution,
few frames and a low reference spp (a few minutes on 2 cores), prints Tables 1 and 2 and the report's path.
Every setting can be overridden with the same options as ``stereorepro experiment``.
"""

from __future__ import annotations

from pathlib import Path

from .experiment import add_arguments, config_from_args, run_experiment, tables_markdown

DEFAULTS = dict(scene="living_room", frames=16, resolution=(240, 135), reference_spp=128, ladder_spp=16,
                out="runs/demo")


def _cmd(args) -> int:
    from .cli import UserError

    cfg = config_from_args(args)
    print(f"stereorepro demo: scene {cfg.scene}, {cfg.frames} frames at {cfg.width}x{cfg.height}, reference "
          f"{cfg.reference_spp} spp, ladder 1..{cfg.ladder_spp} spp -> {cfg.out}")
    try:
        results = run_experiment(cfg)
    except (ValueError, FileNotFoundError) as e:
        raise UserError(str(e)) from None
    print(tables_markdown(results))
    print(f"report: {Path(cfg.out) / 'report.md'} (figures and results.json beside it); wall {results['wall_s']:.0f} s")
    return 0


def register(sub) -> None:
    p = sub.add_parser("demo", help="quick run of the paper's experiment on a built-in scene")
    add_arguments(p, DEFAULTS)
    p.set_defaults(func=_cmd)
