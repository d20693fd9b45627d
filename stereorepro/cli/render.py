"""Sub-commands ``stereorepro scenes`` and ``stereorepro render``."""

from __future__ import annotations

import os

from .._checks import check_backend_env, check_resolution
from ..camera import DEFAULT_RESOLUTION, Eye
from ..errors import ParameterError, UserError
from ._args import nonnegative_int, parse_resolution, positive_int

#: Peak memory of ``render`` per pixel (a 1-spp render with G-buffers, then its EXR), with a margin: the estimate of
#: the resolution guard (:func:`stereorepro._checks.check_resolution`).
RENDER_BYTES_PER_PIXEL = 160
#: One more than the largest sample index the renderer counts (a 64-bit signed integer).
SAMPLE_LIMIT = 2**63


def check_environment(
    what: str, width: int | None = None, height: int | None = None, bytes_per_pixel: int = RENDER_BYTES_PER_PIXEL
) -> None:
    """A command's checks of the machine before it creates anything: ``STEREOREPRO_BACKEND`` names a backend and,
    given a resolution, its memory estimate fits (UserError naming the variable or the estimate)."""
    try:
        check_backend_env()
        if width is not None:
            check_resolution(width, height, bytes_per_pixel, what)
    except ParameterError as e:
        raise UserError(str(e)) from None


def _missing_mesh(scene):
    """The mesh file a scene reads that is not there (the shared scenes' meshes), or None."""
    from ..scenes import expand_path

    mesh = scene.spec.get("geometry", {}).get("mesh")
    path = expand_path(mesh, scene.source.parent) if mesh else None
    return path if path is not None and not path.is_file() else None


def _cmd_scenes(args) -> int:
    from ..scenes import SHARED_ENV, SceneError, list_scenes, load_scene

    if args.shared_scenes:
        os.environ[SHARED_ENV] = args.shared_scenes
    for name in list_scenes(include_external=True, beyond_paper=True):
        try:
            s = load_scene(name)
        except SceneError as e:
            print(f"{name:28s} unavailable: {e}")
            continue
        missing = _missing_mesh(s)
        if missing is not None:
            print(
                f"{name:28s} unavailable: mesh not found: {missing} (set ${SHARED_ENV} to the folder of the shared "
                "meshes, or pass --shared-scenes)"
            )
            continue
        effects = ",".join(sorted(s.effects)) or "diffuse"
        print(f"{name:28s} {effects:14s} frames={s.num_frames:<4d} {s.description}")
    return 0


def _cmd_render(args) -> int:
    from ..io.exr import write_exr
    from ..render import PathTracer
    from ..scenes import SceneError, load_scene

    if args.shared_scenes:
        os.environ["STEREOREPRO_SHARED_SCENES"] = args.shared_scenes
    if args.spp < 1:
        raise UserError(f"--spp must be >= 1, got {args.spp}")
    if not args.out.lower().endswith(".exr"):
        raise UserError(f"--out must be an .exr file, got {args.out}")
    if args.sample_offset + args.spp > SAMPLE_LIMIT:
        raise UserError(
            f"--sample-offset + --spp must be at most 2**63 (the renderer's 64-bit sample index), got "
            f"{args.sample_offset} + {args.spp}"
        )
    check_environment("render", *args.resolution)
    try:
        scene = load_scene(args.scene)
        if not (0 <= args.frame < scene.num_frames):
            raise UserError(f"--frame must be in [0, {scene.num_frames}) for scene {scene.name}, got {args.frame}")
        w, h = args.resolution
        left, right = scene.stereo_cameras(args.frame, w, h)
        cam = {"left": left, "right": right, "head": scene.camera(args.frame, w, h)}[args.eye]
        tracer = PathTracer(scene, seed=args.seed, workers=args.workers)
        res = tracer.render(
            cam,
            args.frame,
            args.spp,
            sample_offset=args.sample_offset,
            eye=Eye.RIGHT if args.eye == "right" else Eye.LEFT,
            progress=not args.quiet,
        )
    except SceneError as e:
        raise UserError(str(e)) from None
    write_exr(args.out, res)  # a full disk / permission error: exit 2 with one line (cli.main's policy)
    if not args.quiet:
        rays = sum(res.ray_counts.values())
        print(f"{args.out}: {w}x{h} {args.spp} spp in {res.time_s:.2f} s ({rays / res.time_s / 1e6:.2f} Mrays/s)")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "scenes", help="list the built-in scenes and the shared-mesh scenes, with their availability"
    )
    p.add_argument("--all", action="store_true", help="accepted for compatibility: every scene is listed")
    p.add_argument(
        "--shared-scenes", default=None, help="folder of the shared meshes (overrides $STEREOREPRO_SHARED_SCENES)"
    )
    p.set_defaults(func=_cmd_scenes)

    p = subparsers.add_parser("render", help="path trace one frame of a scene to an EXR")
    p.add_argument("--scene", required=True, help="built-in scene name or path to a .toml")
    p.add_argument("--frame", type=nonnegative_int, default=0)
    p.add_argument("--spp", type=positive_int, default=1)
    p.add_argument("--resolution", type=parse_resolution, default=DEFAULT_RESOLUTION, metavar="WxH")
    p.add_argument("--out", required=True, help="output .exr (R,G,B, Z, N.X/Y/Z, P.X/Y/Z)")
    p.add_argument("--eye", choices=("left", "right", "head"), default="left")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sample-offset", type=nonnegative_int, default=0)
    p.add_argument("--workers", type=positive_int, default=None)
    p.add_argument(
        "--shared-scenes", default=None, help="folder of the shared meshes (overrides $STEREOREPRO_SHARED_SCENES)"
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_render)
