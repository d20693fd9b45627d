"""``stereorepro reproject`` as a library function: stereo and/or temporal reprojection over a frame directory
(:mod:`stereorepro.io.frames`), written to an output directory with nothing partial.

Modes (``--mode``)
------------------
* ``stereo``: per frame, the right eye reprojected into the left (paper §4.1). Output ``{frame}_left``: the
  reprojected colour (0 where discarded: trace those pixels), ``valid``, ``reason``.
* ``temporal``: per eye (``--eye right|left|both``, default right), exponential accumulation over the sequence
  (EMA ``--alpha`` with warm-up). Output ``{frame}_{eye}``: accumulated colour, ``valid`` (history kept),
  ``reason``, ``history_len``.
* ``both``: the paper's combined scheme (:class:`~stereorepro.SpatiotemporalReprojection`): the right eye is
  accumulated, reprojected into the left, and the left eye's discarded pixels take the left EXR's own colour as
  the "traced" samples (accumulated with the left eye's own history). Outputs for both eyes; for the left eye
  ``valid``/``reason`` are the stereo test's.

Motion: where a frame's EXR has the motion channels ``M.X, M.Y`` (and ``MW.X, MW.Y, MW.Z``; see
:mod:`stereorepro.io.exr`), the temporal steps read the history through them (moving objects keep their history);
the stereo step always uses the cameras. ``summary.json`` says per frame and eye whether motion was used.

Outputs (``--out DIR``): ``{frame:04d}_{eye}_reprojected.exr`` with channels ``R, G, B``, ``valid`` (0/1),
``reason`` (:class:`~stereorepro.Reason` codes as floats; ``Reason.NO_HISTORY`` on the first frame of an accumulation)
and, for temporal and both, ``history_len``; and ``summary.json`` (per-frame discard percentage and counts per
reason). Everything is validated before anything is written; outputs are staged and moved into place only when
every frame has succeeded, so a failure leaves no partial output.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._checks import FLOAT32_MAX, SAMPLINGS
from ..accumulate import SpatiotemporalReprojection, temporal_step
from ..errors import SequenceError
from ..io.atomic import atomic_write, staged_outputs
from ..io.exr import write_exr
from ..io.frames import EYES, Frame, FrameSequence, load_sequence, read_frame
from ..reproject import Reason, StereoReprojection, TemporalReprojection, View
from .diagnose import diagnose_conventions

__all__ = ["MODES", "NO_HISTORY", "reproject_sequence"]

MODES = ("stereo", "temporal", "both")
#: ``reason`` value of a pixel with no history to reproject (first frame of a temporal accumulation).
NO_HISTORY = int(Reason.NO_HISTORY)


def _stats(valid: Tensor, reason: Tensor, frame: Frame | None = None) -> dict:
    codes = reason.flatten().to(torch.int64).bincount(minlength=256).tolist()
    names = {int(r): r.name for r in Reason}
    names[NO_HISTORY] = "NO_HISTORY"
    surface = reason != int(Reason.NO_SURFACE_DST)
    n_surface = int(surface.sum())
    out = {
        "discard_pct": 100.0 * (1.0 - float(valid.float().mean())),
        "surface_discard_pct": 100.0 * float((~valid & surface).sum()) / n_surface if n_surface else None,
        "reasons": {names.get(c, str(c)): n for c, n in enumerate(codes) if n and c != 0},
        "no_history": bool((reason == NO_HISTORY).all()),
    }
    if frame is not None:
        out["normals"] = frame.normal_stats
    return out


def _channels(color: Tensor, valid: Tensor, reason: Tensor, history_len: Tensor | None) -> dict:
    c = color[0].detach().float().cpu().numpy()
    out = {
        "R": c[0],
        "G": c[1],
        "B": c[2],
        "valid": valid[0, 0].float().cpu().numpy(),
        "reason": reason[0, 0].float().cpu().numpy(),
    }
    if history_len is not None:
        out["history_len"] = history_len[0, 0].detach().float().cpu().numpy()
    return out


def _view(frame: Frame) -> View:
    """The G-buffer view of a frame read by read_frame (with its motion when the file has motion channels)."""
    return View(frame.depth, frame.normal, frame.K, frame.cam_from_world, frame.motion, frame.motion_world)


def _process(
    seq: FrameSequence,
    mode: str,
    eyes: tuple[str, ...],
    pos: float,
    nrm: float,
    alpha: float,
    sampling: str,
    device,
    emit,
    log,
) -> list[dict]:
    """Run the mode over the sequence; ``emit(frame, eye, channels)`` receives every output frame."""
    per_frame = []
    if mode == "stereo":
        module = StereoReprojection(pos, nrm, sampling).to(device)
        for i in range(len(seq)):
            L, R = read_frame(seq, i, "left", device), read_frame(seq, i, "right", device)
            color, valid, reason = module(R.color, *_view(R).flat(), *_view(L).flat())
            emit(i, "left", _channels(color, valid, reason, None))
            per_frame.append({"frame": i, "left": _stats(valid, reason, L)})
            log(f"frame {i:4d}: left {per_frame[-1]['left']['discard_pct']:5.1f} % discarded")
    elif mode == "temporal":
        module = TemporalReprojection(pos, nrm, alpha, sampling=sampling).to(device)
        states: dict = {e: None for e in eyes}
        for i in range(len(seq)):
            rec = {"frame": i}
            for eye in eyes:
                cur = read_frame(seq, i, eye, device)
                states[eye], valid, reason = temporal_step(
                    module, states[eye], cur.color, *_view(cur).flat(motion=True)
                )
                emit(i, eye, _channels(states[eye].color, valid, reason, states[eye].history_len))
                rec[eye] = dict(_stats(valid, reason, cur), motion=cur.motion is not None)
            per_frame.append(rec)
            log(f"frame {i:4d}: " + ", ".join(f"{e} {rec[e]['discard_pct']:5.1f} %" for e in eyes) + " discarded")
    else:
        driver = SpatiotemporalReprojection(pos, nrm, alpha, sampling=sampling)
        for i in range(len(seq)):
            L, R = read_frame(seq, i, "left", device), read_frame(seq, i, "right", device)
            out_r = driver.right(R.color, *_view(R).flat(motion=True))
            if driver.right_valid is None:  # first frame: no history
                valid_r = torch.zeros_like(R.depth, dtype=torch.bool)
                reason_r = torch.full_like(R.depth, NO_HISTORY, dtype=torch.uint8)
            else:
                valid_r, reason_r = driver.right_valid, driver.right_reason
            driver.left_trace_mask(*_view(L).flat(motion=True))
            out_l = driver.left(L.color)  # the left EXR's own colour stands in for the traced discards
            emit(i, "right", _channels(out_r, valid_r, reason_r, driver.right_state.history_len))
            emit(i, "left", _channels(out_l, driver.stereo_valid, driver.stereo_reason, driver.left_state.history_len))
            per_frame.append(
                {
                    "frame": i,
                    "right": dict(_stats(valid_r, reason_r, R), motion=R.motion is not None),
                    "left": dict(_stats(driver.stereo_valid, driver.stereo_reason, L), motion=L.motion is not None),
                }
            )
            log(
                f"frame {i:4d}: right {per_frame[-1]['right']['discard_pct']:5.1f} %, "
                f"left (stereo) {per_frame[-1]['left']['discard_pct']:5.1f} % discarded"
            )
    return per_frame


def _check_output_dir(out: Path, input_root: Path) -> None:
    """``out`` may be a new or an existing directory, but neither a file nor the input directory itself (the
    outputs would mix with the inputs)."""
    if out.exists() and not out.is_dir():
        raise SequenceError(f"{out}: exists and is not a directory (--out needs a directory)")
    if out.resolve() == Path(input_root).resolve():
        raise SequenceError(f"{out}: is the input directory; write the outputs to another directory")


def _check_options(mode: str, eye: str, sampling: str, alpha: float) -> None:
    if mode not in MODES:
        raise SequenceError(f"mode must be one of {MODES}, got {mode!r}")
    if eye not in ("left", "right", "both"):
        raise SequenceError(f"eye must be left, right or both, got {eye!r}")
    if sampling not in SAMPLINGS:
        raise SequenceError(f"sampling must be one of {', '.join(SAMPLINGS)}, got {sampling!r}")
    if not (0.0 < float(alpha) <= 1.0):
        raise SequenceError(f"alpha must be in (0, 1], got {alpha}")


def _thresholds(
    seq: FrameSequence, position_threshold: float | None, normal_threshold: float | None
) -> tuple[float, float]:
    """The thresholds given, else those of ``cameras.json``; each required and positive."""
    pos = position_threshold if position_threshold is not None else seq.position_threshold
    nrm = normal_threshold if normal_threshold is not None else seq.normal_threshold
    for name, v in (("position_threshold", pos), ("normal_threshold", nrm)):
        if v is None:
            raise SequenceError(
                f"--{name.replace('_', '-')} is required ({seq.root / 'cameras.json'} has no reprojection.{name})"
            )
        if not (math.isfinite(v) and 0 < v <= FLOAT32_MAX):
            raise SequenceError(f"{name} must be a positive number within float32's range, got {v}")
    return pos, nrm


def _normal_warnings(per_frame: list[dict], eyes: tuple[str, ...]) -> list[dict]:
    """A warning per frame and eye whose normals are zero or not finite on more than 1 % of the surface."""
    out = []
    for f in per_frame:
        for e in eyes:
            ns = f[e]["normals"]
            if ns["surface"] and ns["invalid"] > 0.01 * ns["surface"]:
                out.append(
                    {
                        "test": "normals",
                        "frame": f["frame"],
                        "eye": e,
                        "message": f"frame {f['frame']} {e}: normals are zero or not finite on "
                        f"{100.0 * ns['invalid'] / ns['surface']:.1f} % of the surface pixels "
                        "(those pixels fail the normal test)",
                    }
                )
    return out


def reproject_sequence(
    input_dir,
    out_dir,
    mode: str = "both",
    eye: str = "right",
    position_threshold: float | None = None,
    normal_threshold: float | None = None,
    alpha: float = 0.2,
    sampling: str = "bilinear",
    device="cpu",
    log=None,
    warn=None,
    source: str = "stereorepro",
) -> dict:
    """Reproject a directory of frames (see the module docstring for the format and the modes).

    Args:
        input_dir: directory with ``cameras.json`` and ``{frame:04d}_{eye}.exr``.
        out_dir: output directory (created); receives ``{frame:04d}_{eye}_reprojected.exr`` and ``summary.json``.
        mode: ``"stereo"`` | ``"temporal"`` | ``"both"``.
        eye: eyes accumulated in ``"temporal"`` mode: ``"right"`` | ``"left"`` | ``"both"``.
        position_threshold, normal_threshold: accept limits; ``None`` takes ``cameras.json``'s ``reprojection``.
        alpha: minimum EMA weight of a new frame (temporal and both).
        sampling: one of :data:`~stereorepro._checks.SAMPLINGS` (``"bilinear"``, ``"nearest"``, ``"catmull_rom"``).
        device: torch device for the reprojection (EXRs are read on the CPU).
        log: ``print``-like callable for progress, or ``None``.
        warn: callable receiving each warning's message (likely convention mistakes, invalid normals), or None.
        source: the renderer that wrote the EXRs: ``"stereorepro"`` (our format) or ``"mitsuba"`` (films of the
            ``aov`` integrator, :mod:`stereorepro.io.mitsuba`); see :func:`~stereorepro.io.frames.load_sequence`.

    Returns:
        the summary written to ``summary.json``. Its ``mean_discard_pct`` (over all pixels) and
        ``mean_surface_discard_pct`` (over the pixels with a surface, the share the paper reports) average the frames
        that have a history
        (``NO_HISTORY`` frames, the first of an accumulation, are listed in ``no_history_frames``); ``warnings``
        lists the likely convention mistakes (:func:`stereorepro.workflows.diagnose.diagnose_conventions`) and frames
        whose normals are zero or not finite on more than 1 % of the surface pixels.

    Raises:
        SequenceError: the input is malformed or an option is invalid; nothing was written.

    Examples:
        >>> import os, tempfile
        >>> from stereorepro.workflows.export import export_sequence
        >>> tmp = tempfile.TemporaryDirectory()
        >>> src = export_sequence("living_room", 2, 8, 6, os.path.join(tmp.name, "in"))  # 2 frames of 8x6, 1 spp
        >>> from stereorepro.workflows.sequence import reproject_sequence
        >>> summary = reproject_sequence(src, os.path.join(tmp.name, "out"), mode="both")
        >>> summary["frames"], summary["width"], summary["height"], summary["position_threshold"]
        (2, 8, 6, 1.5)
        >>> sorted(f for f in os.listdir(os.path.join(tmp.name, "out")) if f.startswith("0001"))
        ['0001_left_reprojected.exr', '0001_right_reprojected.exr']
        >>> tmp.cleanup()
    """
    _check_options(mode, eye, sampling, alpha)
    eyes = (EYES if eye == "both" else (eye,)) if mode == "temporal" else EYES
    seq = load_sequence(input_dir, eyes, source)
    pos, nrm = _thresholds(seq, position_threshold, normal_threshold)
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SequenceError("device cuda asked for but torch.cuda.is_available() is False")
    log = log or (lambda *a, **k: None)
    warn = warn or (lambda *a, **k: None)
    warnings = diagnose_conventions(seq, mode, eyes, float(pos), float(nrm), sampling, device)

    out = Path(out_dir)
    _check_output_dir(out, seq.root)
    with staged_outputs(out, last=["summary.json"]) as staging:  # summary.json last: it marks a complete output

        def emit(frame, e, chans):
            write_exr(staging / f"{frame:04d}_{e}_reprojected.exr", chans)

        with torch.no_grad():
            per_frame = _process(seq, mode, eyes, float(pos), float(nrm), float(alpha), sampling, device, emit, log)
        eyes_out = ("left",) if mode == "stereo" else eyes
        warnings += _normal_warnings(per_frame, eyes_out)
        for w in warnings:
            warn(w["message"])

        def mean_over_history(key: str) -> dict:
            vals = {
                e: [f[e][key] for f in per_frame if not f[e]["no_history"] and f[e][key] is not None] for e in eyes_out
            }
            return {e: float(np.mean(v)) if v else None for e, v in vals.items()}

        summary = {
            "mode": mode,
            "eyes": list(eyes_out),
            "input": str(seq.root),
            "frames": len(seq),
            "width": seq.width,
            "height": seq.height,
            "position_threshold": float(pos),
            "normal_threshold": float(nrm),
            "alpha": float(alpha) if mode != "stereo" else None,
            "sampling": sampling,
            "source": source,
            "mean_discard_pct": mean_over_history("discard_pct"),
            "mean_surface_discard_pct": mean_over_history("surface_discard_pct"),
            "no_history_frames": {e: [f["frame"] for f in per_frame if f[e]["no_history"]] for e in eyes_out},
            "warnings": warnings,
            "per_frame": per_frame,
        }
        atomic_write(staging / "summary.json", json.dumps(summary, indent=1))
    return summary
