"""``stereorepro demo``: the main job on a built-in default — a quick run of the paper's experiment.

Runs :func:`stereorepro.workflows.experiment.run_experiment` on the built-in ``living_room`` scene at a small
resolution, few frames and a low reference spp (a few minutes on 2 cores), prints Tables 1 and 2 and the report's path.
Every setting can be overridden with the same options as ``stereorepro experiment``.
"""

from __future__ import annotations

from .experiment import add_arguments, run_command

DEFAULTS = dict(
    scene="living_room", frames=24, resolution=(240, 135), reference_spp=128, ladder_spp=16, out="runs/demo"
)


def _cmd(args) -> int:
    print(
        f"stereorepro demo: scene {args.scene}, {args.frames} frames at {args.resolution[0]}x{args.resolution[1]}, "
        f"reference {args.reference_spp} spp, ladder 1..{args.ladder_spp} spp -> {args.out}"
    )
    return run_command(args)


def register(sub) -> None:
    p = sub.add_parser("demo", help="quick run of the paper's experiment on a built-in scene")
    add_arguments(p, DEFAULTS)
    p.set_defaults(func=_cmd)
