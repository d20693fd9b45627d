"""Sub-commands ``stereorepro reproject`` (:func:`stereorepro.workflows.sequence.reproject_sequence`) and
``stereorepro export-sequence`` (:func:`stereorepro.workflows.export.export_sequence`)."""

from __future__ import annotations

import sys

import torch

from ..camera import DEFAULT_RESOLUTION
from .._checks import SAMPLINGS, check_thresholds
from ..errors import ParameterError, SceneError, SequenceError, UserError
from ..io.frames import SOURCES
from ..workflows.export import export_sequence
from ..workflows.sequence import MODES, reproject_sequence
from ._args import nonnegative_int, parse_resolution, positive_float, positive_int
from .render import RENDER_BYTES_PER_PIXEL, check_environment


def _cmd_reproject(args) -> int:
    if args.eye is not None and args.mode != "temporal":
        raise UserError(f"--eye applies to --mode temporal only (got --mode {args.mode})")
    check_environment("reproject")
    try:
        check_thresholds(
            0.0 if args.position_threshold is None else args.position_threshold,
            0.0 if args.normal_threshold is None else args.normal_threshold,
            tracing=False,
        )
    except ParameterError as e:
        raise UserError("--" + str(e).replace("_", "-", 1).split(";")[0]) from None  # the CLI takes no inf
    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        summary = reproject_sequence(
            args.input,
            args.out,
            args.mode,
            args.eye or "right",
            args.position_threshold,
            args.normal_threshold,
            args.alpha,
            args.sampling,
            device,
            log=None if args.quiet else print,
            warn=lambda m: print(f"stereorepro reproject: warning: {m}", file=sys.stderr),
            source=args.source,
        )
    except SequenceError as e:
        raise UserError(str(e)) from None
    if not args.quiet:
        mean = ", ".join(f"{e} {v:.1f} %" for e, v in summary["mean_discard_pct"].items() if v is not None)
        print(f"{args.out}: {summary['frames']} frame(s), {args.mode}; mean discarded: {mean}")
    return 0


def _cmd_export(args) -> int:
    from ..scenes import load_scene

    w, h = args.resolution
    if args.frames < 1 or args.spp < 1 or args.stride < 1 or args.start < 0:
        raise UserError("--frames, --spp and --stride must be >= 1 and --start >= 0")
    check_environment("export-sequence", w, h, 2 * RENDER_BYTES_PER_PIXEL)  # both eyes of a frame at once
    try:
        scene = load_scene(args.scene)
    except SceneError as e:
        raise UserError(str(e)) from None
    ids = [args.start + k * args.stride for k in range(args.frames)]
    if ids[-1] >= scene.num_frames:
        raise UserError(f"frames {ids[0]}..{ids[-1]} exceed the scene's {scene.num_frames} frames")
    export_sequence(scene, ids, w, h, args.out, args.spp, args.seed, args.workers)
    if not args.quiet:
        print(f"{args.out}: {len(ids)} stereo frame(s) of {scene.name} at {w}x{h}, {args.spp} spp")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "reproject",
        help="stereo/temporal reprojection of a directory of EXR frames",
        description="Reproject a directory of frames from any renderer (cameras.json + "
        "{frame:04d}_{left|right}.exr with R,G,B, Z, N.X/N.Y/N.Z).",
    )
    p.add_argument("--input", required=True, help="directory with cameras.json and the frames")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="both",
        help="stereo: right->left per frame; temporal: accumulation per eye; both: the paper's scheme",
    )
    p.add_argument(
        "--eye",
        choices=("left", "right", "both"),
        default=None,
        help="eyes accumulated in temporal mode (default right)",
    )
    p.add_argument(
        "--position-threshold",
        type=positive_float,
        default=None,
        help="max |P_src - P_dst| in scene units (default: cameras.json reprojection.position_threshold)",
    )
    p.add_argument(
        "--normal-threshold",
        type=positive_float,
        default=None,
        help="max |N_src - N_dst| of unit normals (default: cameras.json reprojection.normal_threshold)",
    )
    p.add_argument("--alpha", type=positive_float, default=0.2, help="minimum EMA weight of a new frame (paper: 0.2)")
    p.add_argument("--sampling", choices=SAMPLINGS, default="bilinear")
    p.add_argument(
        "--from",
        dest="source",
        choices=SOURCES,
        default="stereorepro",
        help="the renderer that wrote the EXRs: stereorepro (our channels), mitsuba (films of the aov "
        "integrator with aovs='dd:depth,nn:sh_normal,pp:position') or blender (its multilayer "
        "{frame:04d}_L/_R.exr; cameras.json from stereorepro.io.blender.write_cameras); "
        "cameras.json is ours (OpenCV)",
    )
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_reproject)

    p = subparsers.add_parser("export-sequence", help="trace a scene into a `stereorepro reproject` input directory")
    p.add_argument("--scene", required=True, help="built-in scene name or path to a .toml")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--frames", type=positive_int, default=8, help="number of frames")
    p.add_argument("--start", type=nonnegative_int, default=0, help="first scene frame")
    p.add_argument("--stride", type=positive_int, default=1, help="scene frames between exported frames")
    p.add_argument("--resolution", type=parse_resolution, default=DEFAULT_RESOLUTION, metavar="WxH")
    p.add_argument("--spp", type=positive_int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=positive_int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_export)
