"""``stereorepro reproject``: stereo and/or temporal reprojection over a directory of frames from any renderer.

Input directory (``--input DIR``)
---------------------------------
``DIR/cameras.json``::

    {"frames": [{"left":  {"K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "cam_from_world": [[...4 numbers...] x 4]},
                 "right": {"K": ..., "cam_from_world": ...}},
                ...],
     "reprojection": {"position_threshold": 0.25, "normal_threshold": 0.25},   # optional defaults
     "meta": {...}}                                                             # optional, ignored

and ``DIR/{frame:04d}_{left|right}.exr`` for every listed frame (frame = index into ``frames``), with 32-bit
float channels ``R, G, B`` (linear radiance), ``Z`` (camera-space z, **not** ray length; NaN, ±inf or <= 0 where
there is no surface) and ``N.X, N.Y, N.Z`` (unit world-space shading normals). Extra channels are ignored; our
tracer's EXR output (:func:`stereorepro.render.write_exr`) is valid input. All files share one size. Cameras follow
:mod:`stereorepro.camera`: OpenCV axes (x right, y down, z forward), ``K`` maps camera space to pixel coordinates
whose pixel centres are at +0.5, ``cam_from_world`` is rigid. Unknown keys are errors (a typo is not silence).

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

Outputs (``--out DIR``): ``{frame:04d}_{eye}_reprojected.exr`` with channels ``R, G, B``, ``valid`` (0/1),
``reason`` (:class:`~stereorepro.Reason` codes as floats; ``Reason.NO_HISTORY`` on the first frame of an accumulation)
and, for temporal and both, ``history_len``; and ``summary.json`` (per-frame discard percentage and counts per
reason). Everything is validated before anything is written; outputs are staged and moved into place only when
every frame has succeeded, so a failure leaves no partial output.

:func:`export_sequence` (and ``stereorepro export-sequence``) writes such a directory from our path tracer.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .cli import parse_resolution
from .reproject import Reason

__all__ = ["REQUIRED_CHANNELS", "NO_HISTORY", "SequenceError", "EyeCamera", "FrameSequence", "load_sequence",
           "read_frame", "reproject_sequence", "export_sequence", "register"]

#: Channels every input EXR must have (others are ignored).
REQUIRED_CHANNELS = ("R", "G", "B", "Z", "N.X", "N.Y", "N.Z")
#: ``reason`` value of a pixel with no history to reproject (first frame of a temporal accumulation).
NO_HISTORY = int(Reason.NO_HISTORY)
EYES = ("left", "right")
MODES = ("stereo", "temporal", "both")
_FILE_RE = re.compile(r"^(\d{4,})_(left|right)\.exr$")


class SequenceError(ValueError):
    """A malformed input directory; the message names the file (and the frame/key)."""


@dataclass(frozen=True)
class EyeCamera:
    """One eye's camera of one frame.

    Attributes:
        K: (1, 3, 3) float64 intrinsics (pixel centres at +0.5).
        cam_from_world: (1, 4, 4) float64 rigid extrinsics (OpenCV axes).
    """

    K: Tensor
    cam_from_world: Tensor


@dataclass(frozen=True)
class FrameSequence:
    """A validated input directory.

    Attributes:
        root: the directory.
        cameras: per frame, eye name → :class:`EyeCamera` (only the eyes that were asked for).
        height, width: the common image size.
        position_threshold, normal_threshold: defaults from ``cameras.json`` (``None`` when absent).
    """

    root: Path
    cameras: tuple
    height: int
    width: int
    position_threshold: float | None = None
    normal_threshold: float | None = None

    def __len__(self) -> int:
        return len(self.cameras)

    def path(self, frame: int, eye: str) -> Path:
        return self.root / f"{frame:04d}_{eye}.exr"


# ----------------------------------------------------------------------------------------------- validation
def _matrix(value, rows: int, where: str) -> np.ndarray:
    ok = (isinstance(value, list) and len(value) == rows
          and all(isinstance(r, list) and len(r) == rows for r in value)
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for r in value for x in r))
    if not ok:
        raise SequenceError(f"{where}: expected a {rows}x{rows} list of numbers, got {json.dumps(value)[:80]}")
    a = np.asarray(value, np.float64)
    if not np.isfinite(a).all():
        raise SequenceError(f"{where}: values must be finite, got {a.tolist()}")
    return a


def _check_K(K: np.ndarray, where: str) -> None:
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])):
        raise SequenceError(f"{where}: expected pinhole intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with "
                            f"fx, fy > 0, got {K.tolist()}")


def _check_rigid(T: np.ndarray, where: str, tol: float = 1e-4) -> None:
    R = T[:3, :3]
    rigid = (np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) and np.allclose(R.T @ R, np.eye(3), atol=tol)
             and np.linalg.det(R) > 0)
    if not rigid:
        raise SequenceError(f"{where}: expected a rigid transform (rotation + translation, last row [0, 0, 0, 1]), "
                            f"got {T.tolist()}")


def _threshold(table, key: str, where: str) -> float | None:
    if key not in table:
        return None
    v = table[key]
    if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
        raise SequenceError(f"{where}.{key}: expected a positive number, got {v!r}")
    return float(v)


def _parse_cameras(path: Path, eyes: tuple[str, ...]) -> tuple[list[dict], dict]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SequenceError(f"{path}: not found (the input directory needs cameras.json)") from None
    except OSError as e:
        raise SequenceError(f"{path}: cannot read: {e}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise SequenceError(f"{path}: malformed JSON: {e}") from None
    if not isinstance(data, dict):
        raise SequenceError(f"{path}: expected an object {{\"frames\": [...]}}, got {type(data).__name__}")
    unknown = set(data) - {"frames", "reprojection", "meta"}
    if unknown:
        raise SequenceError(f"{path}: unknown key(s) {sorted(unknown)} (expected frames, reprojection, meta)")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SequenceError(f"{path}: 'frames' must be a non-empty list, got {json.dumps(frames)[:80]}")
    out = []
    for i, fr in enumerate(frames):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict):
            raise SequenceError(f"{where}: expected an object with 'left'/'right', got {type(fr).__name__}")
        unknown = set(fr) - set(EYES)
        if unknown:
            raise SequenceError(f"{where}: unknown key(s) {sorted(unknown)} (expected left, right)")
        cams = {}
        for eye in EYES:
            if eye not in fr:
                if eye in eyes:
                    raise SequenceError(f"{where}: missing key '{eye}'")
                continue
            cam = fr[eye]
            if not isinstance(cam, dict):
                raise SequenceError(f"{where}.{eye}: expected an object with 'K' and 'cam_from_world'")
            unknown = set(cam) - {"K", "cam_from_world"}
            if unknown:
                raise SequenceError(f"{where}.{eye}: unknown key(s) {sorted(unknown)} (expected K, cam_from_world)")
            for key in ("K", "cam_from_world"):
                if key not in cam:
                    raise SequenceError(f"{where}.{eye}: missing key '{key}'")
            K = _matrix(cam["K"], 3, f"{where}.{eye}.K")
            _check_K(K, f"{where}.{eye}.K")
            T = _matrix(cam["cam_from_world"], 4, f"{where}.{eye}.cam_from_world")
            _check_rigid(T, f"{where}.{eye}.cam_from_world")
            if eye in eyes:
                cams[eye] = EyeCamera(torch.from_numpy(K)[None], torch.from_numpy(T)[None])
        out.append(cams)
    rep = data.get("reprojection", {})
    if not isinstance(rep, dict) or set(rep) - {"position_threshold", "normal_threshold"}:
        raise SequenceError(f"{path}: 'reprojection' must be an object with position_threshold and/or "
                            f"normal_threshold, got {json.dumps(rep)[:80]}")
    thr = {k: _threshold(rep, k, f"{path}: reprojection") for k in ("position_threshold", "normal_threshold")}
    return out, thr


def _exr_header(path: Path) -> tuple[list[str], int, int]:
    import OpenEXR

    try:
        h = OpenEXR.File(str(path), header_only=True).header()
        names = [c.name for c in h["channels"]]
        lo, hi = h["dataWindow"]
    except Exception as e:  # noqa: BLE001 - any reader failure is a bad file
        raise SequenceError(f"{path}: not a readable EXR: {e}") from None
    return names, int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)


def load_sequence(input_dir, eyes: tuple[str, ...] = EYES) -> FrameSequence:
    """Validate an input directory without reading pixels: ``cameras.json`` (shapes, rigidity, keys), the frame
    files present against the frames listed, and every needed EXR's channels and size (from its header).

    Args:
        input_dir: the directory.
        eyes: the eyes whose cameras and files are needed.

    Raises:
        SequenceError: naming the file, and the frame and key for ``cameras.json``.
    """
    root = Path(input_dir)
    if not root.is_dir():
        raise SequenceError(f"{root}: not a directory")
    cams, thr = _parse_cameras(root / "cameras.json", tuple(eyes))
    n = len(cams)
    beyond = sorted(p.name for p in root.iterdir() if (m := _FILE_RE.match(p.name)) and int(m.group(1)) >= n)
    if beyond:
        raise SequenceError(f"{root / 'cameras.json'}: lists {n} frame(s) but {root} has frame files beyond them: "
                            f"{', '.join(beyond[:4])}{' ...' if len(beyond) > 4 else ''}")
    size = None
    first = None
    for i in range(n):
        for eye in eyes:
            p = root / f"{i:04d}_{eye}.exr"
            if not p.is_file():
                raise SequenceError(f"{p}: missing (cameras.json lists {n} frame(s); frame {i} needs {eye} eye)")
            names, H, W = _exr_header(p)
            missing = [c for c in REQUIRED_CHANNELS if c not in names]
            if missing:
                raise SequenceError(f"{p}: missing channel(s) {', '.join(missing)} (required: "
                                    f"{', '.join(REQUIRED_CHANNELS)}; found: {', '.join(sorted(names))})")
            if size is None:
                size, first = (H, W), p
            elif (H, W) != size:
                raise SequenceError(f"{p}: size {W}x{H} differs from {first.name}: {size[1]}x{size[0]} "
                                    "(all frames and eyes must have one size)")
    return FrameSequence(root, tuple(cams), size[0], size[1], thr["position_threshold"], thr["normal_threshold"])


def read_frame(seq: FrameSequence, frame: int, eye: str, device=None) -> dict[str, Tensor]:
    """Read one eye of one frame.

    Returns:
        dict with ``color`` (1, 3, H, W), ``depth`` (1, 1, H, W), ``normal`` (1, 3, H, W) float32 and ``K``
        (1, 3, 3), ``cam_from_world`` (1, 4, 4) float64, on ``device``.
    """
    from .render.exr import read_exr

    p = seq.path(frame, eye)
    try:
        ch = read_exr(p)
    except (FileNotFoundError, ValueError) as e:
        raise SequenceError(str(e)) from None
    for c in REQUIRED_CHANNELS:  # the header was checked; a file changed since is still named
        if c not in ch or ch[c].shape != (seq.height, seq.width):
            raise SequenceError(f"{p}: channel {c} missing or not {seq.width}x{seq.height}")

    def stack(names):
        return torch.from_numpy(np.stack([ch[c] for c in names])[None].astype(np.float32)).to(device)

    cam = seq.cameras[frame][eye]
    return {"color": stack(("R", "G", "B")), "depth": stack(("Z",)), "normal": stack(("N.X", "N.Y", "N.Z")),
            "K": cam.K.to(device), "cam_from_world": cam.cam_from_world.to(device)}


# ----------------------------------------------------------------------------------------------- processing
def _temporal_step(module, state, cur):
    """One eye's accumulation: (color, history_len, valid, reason) with reason = NO_HISTORY on the first frame."""
    from .reproject import backward_reproject, temporal_blend

    if state is None:
        ones = torch.ones_like(cur["depth"])
        return (cur["color"], ones, torch.zeros_like(cur["depth"], dtype=torch.bool),
                torch.full_like(cur["depth"], NO_HISTORY, dtype=torch.uint8))
    values = torch.cat([state["color"], state["history_len"]], 1)  # Bx4xHxW: colour + n ride together
    warped, valid, reason, _ = backward_reproject(
        values, state["depth"], state["normal"], state["K"], state["cam_from_world"], cur["depth"], cur["normal"],
        cur["K"], cur["cam_from_world"], module.position_threshold, module.normal_threshold, module.sampling)
    color, n = temporal_blend(cur["color"], warped[:, :3], warped[:, 3:4], valid, module.alpha, module.warmup,
                              module.max_history)
    return color, n, valid, reason


def _stats(valid: Tensor, reason: Tensor) -> dict:
    from .reproject import Reason

    codes = reason.flatten().to(torch.int64).bincount(minlength=256).tolist()
    names = {int(r): r.name for r in Reason}
    names[NO_HISTORY] = "NO_HISTORY"
    return {"discard_pct": 100.0 * (1.0 - float(valid.float().mean())),
            "reasons": {names.get(c, str(c)): n for c, n in enumerate(codes) if n and c != 0}}


def _channels(color: Tensor, valid: Tensor, reason: Tensor, history_len: Tensor | None) -> dict:
    c = color[0].detach().float().cpu().numpy()
    out = {"R": c[0], "G": c[1], "B": c[2], "valid": valid[0, 0].float().cpu().numpy(),
           "reason": reason[0, 0].float().cpu().numpy()}
    if history_len is not None:
        out["history_len"] = history_len[0, 0].detach().float().cpu().numpy()
    return out


def _process(seq: FrameSequence, mode: str, eyes: tuple[str, ...], pos: float, nrm: float, alpha: float,
             sampling: str, device, emit, log) -> list[dict]:
    """Run the mode over the sequence; ``emit(frame, eye, channels)`` receives every output frame."""
    from .pipeline import SpatiotemporalReprojection
    from .reproject import StereoReprojection, TemporalReprojection

    per_frame = []
    if mode == "stereo":
        module = StereoReprojection(pos, nrm, sampling).to(device)
        for i in range(len(seq)):
            L, R = read_frame(seq, i, "left", device), read_frame(seq, i, "right", device)
            color, valid, reason = module(R["color"], R["depth"], R["normal"], R["K"], R["cam_from_world"],
                                          L["depth"], L["normal"], L["K"], L["cam_from_world"])
            emit(i, "left", _channels(color, valid, reason, None))
            per_frame.append({"frame": i, "left": _stats(valid, reason)})
            log(f"frame {i:4d}: left {per_frame[-1]['left']['discard_pct']:5.1f} % discarded")
    elif mode == "temporal":
        module = TemporalReprojection(pos, nrm, alpha, sampling=sampling).to(device)
        states: dict = {e: None for e in eyes}
        for i in range(len(seq)):
            rec = {"frame": i}
            for eye in eyes:
                cur = read_frame(seq, i, eye, device)
                color, n, valid, reason = _temporal_step(module, states[eye], cur)
                states[eye] = dict(cur, color=color, history_len=n)
                emit(i, eye, _channels(color, valid, reason, n))
                rec[eye] = _stats(valid, reason)
            per_frame.append(rec)
            log(f"frame {i:4d}: " + ", ".join(f"{e} {rec[e]['discard_pct']:5.1f} %" for e in eyes) + " discarded")
    else:
        driver = SpatiotemporalReprojection(pos, nrm, alpha, sampling=sampling)
        for i in range(len(seq)):
            L, R = read_frame(seq, i, "left", device), read_frame(seq, i, "right", device)
            out_r = driver.right(R["color"], R["depth"], R["normal"], R["K"], R["cam_from_world"])
            if driver.right_valid is None:  # first frame: no history
                valid_r = torch.zeros_like(R["depth"], dtype=torch.bool)
                reason_r = torch.full_like(R["depth"], NO_HISTORY, dtype=torch.uint8)
            else:
                valid_r, reason_r = driver.right_valid, driver.right_reason
            driver.left_trace_mask(L["depth"], L["normal"], L["K"], L["cam_from_world"])
            out_l = driver.left(L["color"])  # the left EXR's own colour stands in for the traced discards
            emit(i, "right", _channels(out_r, valid_r, reason_r, driver.right_state.history_len))
            emit(i, "left", _channels(out_l, driver.stereo_valid, driver.stereo_reason,
                                      driver.left_state.history_len))
            per_frame.append({"frame": i, "right": _stats(valid_r, reason_r),
                              "left": _stats(driver.stereo_valid, driver.stereo_reason)})
            log(f"frame {i:4d}: right {per_frame[-1]['right']['discard_pct']:5.1f} %, "
                f"left (stereo) {per_frame[-1]['left']['discard_pct']:5.1f} % discarded")
    return per_frame


def reproject_sequence(input_dir, out_dir, mode: str = "both", eye: str = "right",
                       position_threshold: float | None = None, normal_threshold: float | None = None,
                       alpha: float = 0.2, sampling: str = "bilinear", device="cpu", log=None) -> dict:
    """Reproject a directory of frames (see the module docstring for the format and the modes).

    Args:
        input_dir: directory with ``cameras.json`` and ``{frame:04d}_{eye}.exr``.
        out_dir: output directory (created); receives ``{frame:04d}_{eye}_reprojected.exr`` and ``summary.json``.
        mode: ``"stereo"`` | ``"temporal"`` | ``"both"``.
        eye: eyes accumulated in ``"temporal"`` mode: ``"right"`` | ``"left"`` | ``"both"``.
        position_threshold, normal_threshold: accept limits; ``None`` takes ``cameras.json``'s ``reprojection``.
        alpha: minimum EMA weight of a new frame (temporal and both).
        sampling: ``"bilinear"`` | ``"nearest"``.
        device: torch device for the reprojection (EXRs are read on the CPU).
        log: ``print``-like callable for progress, or ``None``.

    Returns:
        the summary written to ``summary.json``.

    Raises:
        SequenceError: the input is malformed or an option is invalid; nothing was written.
    """
    if mode not in MODES:
        raise SequenceError(f"mode must be one of {MODES}, got {mode!r}")
    if eye not in ("left", "right", "both"):
        raise SequenceError(f"eye must be left, right or both, got {eye!r}")
    if sampling not in ("bilinear", "nearest"):
        raise SequenceError(f"sampling must be bilinear or nearest, got {sampling!r}")
    if not (0.0 < float(alpha) <= 1.0):
        raise SequenceError(f"alpha must be in (0, 1], got {alpha}")
    eyes = (EYES if eye == "both" else (eye,)) if mode == "temporal" else EYES
    seq = load_sequence(input_dir, eyes)
    pos = position_threshold if position_threshold is not None else seq.position_threshold
    nrm = normal_threshold if normal_threshold is not None else seq.normal_threshold
    for name, v in (("position_threshold", pos), ("normal_threshold", nrm)):
        if v is None:
            raise SequenceError(f"--{name.replace('_', '-')} is required ({seq.root / 'cameras.json'} has no "
                                f"reprojection.{name})")
        if not (math.isfinite(v) and v > 0):
            raise SequenceError(f"{name} must be a positive number, got {v}")
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SequenceError("device cuda asked for but torch.cuda.is_available() is False")
    log = log or (lambda *a, **k: None)

    out = Path(out_dir)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SequenceError(f"{out}: cannot create the output directory: {e}") from None
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    written: list[str] = []
    try:
        from .render.exr import write_exr

        def emit(frame, e, chans):
            name = f"{frame:04d}_{e}_reprojected.exr"
            write_exr(staging / name, chans)
            written.append(name)

        with torch.no_grad():
            per_frame = _process(seq, mode, eyes, float(pos), float(nrm), float(alpha), sampling, device, emit, log)
        eyes_out = ("left",) if mode == "stereo" else eyes
        summary = {
            "mode": mode, "eyes": list(eyes_out), "input": str(seq.root), "frames": len(seq),
            "width": seq.width, "height": seq.height, "position_threshold": float(pos),
            "normal_threshold": float(nrm), "alpha": float(alpha) if mode != "stereo" else None,
            "sampling": sampling,
            "mean_discard_pct": {e: float(np.mean([f[e]["discard_pct"] for f in per_frame])) for e in eyes_out},
            "per_frame": per_frame,
        }
        (staging / "summary.json").write_text(json.dumps(summary, indent=1))
        for name in written + ["summary.json"]:  # summary.json last: its presence marks a complete output
            os.replace(staging / name, out / name)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    shutil.rmtree(staging, ignore_errors=True)
    return summary


# ----------------------------------------------------------------------------------------------- our tracer → DIR
def _json_matrix(t: Tensor) -> list:
    return [[float(x) for x in row] for row in t[0].double().tolist()]


def export_sequence(scene, frames, width: int, height: int, out_dir, spp: int = 1, seed: int = 0,
                    workers: int | None = None) -> Path:
    """Write an input directory for ``stereorepro reproject`` from our path tracer.

    Frame ``i`` of the directory is scene frame ``frames[i]``; both eyes are traced at ``spp`` (RNG eye keys 0 =
    left, 1 = right) and written with all the tracer's channels (``R,G,B, Z, N.*, P.*``). ``cameras.json`` gets
    the scene's thresholds with the position threshold scaled by ``180 / height`` (scene files are tuned for
    ~180 rows; a pixel's footprint grows as the resolution drops) and a ``meta`` record. ``cameras.json`` is
    written last.

    Args:
        scene: a scene name or a :class:`~stereorepro.scenes.Scene`.
        frames: number of frames (0..n-1) or an iterable of scene frame indices.
        width, height: image size.
        out_dir: directory (created).
        spp, seed, workers: tracer settings.

    Returns:
        ``out_dir`` as a Path.
    """
    from .render import PathTracer, write_exr
    from .scenes import load_scene

    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    frame_ids = list(range(int(frames))) if isinstance(frames, int) else [int(f) for f in frames]
    if not frame_ids:
        raise ValueError("export_sequence: no frames")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tracer = PathTracer(scene, seed=seed, workers=workers)
    records = []
    for i, f in enumerate(frame_ids):
        left, right = scene.stereo_cameras(f, width, height)
        rec = {}
        for eye, cam, key in (("left", left, 0), ("right", right, 1)):
            res = tracer.render(cam, f, spp, eye=key)
            write_exr(out / f"{i:04d}_{eye}.exr", res)
            rec[eye] = {"K": _json_matrix(cam.K), "cam_from_world": _json_matrix(cam.cam_from_world)}
        records.append(rec)
    doc = {"frames": records,
           "reprojection": {"position_threshold": scene.position_threshold * 180.0 / height,
                            "normal_threshold": scene.normal_threshold},
           "meta": {"scene": scene.name, "scene_frames": frame_ids, "spp": int(spp), "seed": int(seed),
                    "width": int(width), "height": int(height), "writer": "stereorepro.reproject_cli.export_sequence"}}
    fd, tmp = tempfile.mkstemp(prefix=".cameras.", suffix=".json.tmp", dir=out)
    with os.fdopen(fd, "w") as fh:
        json.dump(doc, fh, indent=1)
    os.replace(tmp, out / "cameras.json")
    return out


# ----------------------------------------------------------------------------------------------- CLI
def _cmd_reproject(args) -> int:
    from .cli import UserError

    if args.eye is not None and args.mode != "temporal":
        raise UserError(f"--eye applies to --mode temporal only (got --mode {args.mode})")
    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        summary = reproject_sequence(args.input, args.out, args.mode, args.eye or "right", args.position_threshold,
                                     args.normal_threshold, args.alpha, args.sampling, device,
                                     log=None if args.quiet else print)
    except SequenceError as e:
        raise UserError(str(e)) from None
    if not args.quiet:
        mean = ", ".join(f"{e} {v:.1f} %" for e, v in summary["mean_discard_pct"].items())
        print(f"{args.out}: {summary['frames']} frame(s), {args.mode}; mean discarded: {mean}")
    return 0


def _cmd_export(args) -> int:
    from .cli import UserError
    from .scenes import SceneError, load_scene

    w, h = args.resolution
    if args.frames < 1 or args.spp < 1 or args.stride < 1 or args.start < 0:
        raise UserError("--frames, --spp and --stride must be >= 1 and --start >= 0")
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


def _positive(s: str) -> float:
    import argparse

    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {s!r}")
    return v



def register(subparsers) -> None:
    p = subparsers.add_parser("reproject", help="stereo/temporal reprojection of a directory of EXR frames",
                              description="Reproject a directory of frames from any renderer (cameras.json + "
                                          "{frame:04d}_{left|right}.exr with R,G,B, Z, N.X/N.Y/N.Z).")
    p.add_argument("--input", required=True, help="directory with cameras.json and the frames")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--mode", choices=MODES, default="both",
                   help="stereo: right->left per frame; temporal: accumulation per eye; both: the paper's scheme")
    p.add_argument("--eye", choices=("left", "right", "both"), default=None,
                   help="eyes accumulated in temporal mode (default right)")
    p.add_argument("--position-threshold", type=_positive, default=None,
                   help="max |P_src - P_dst| in scene units (default: cameras.json reprojection.position_threshold)")
    p.add_argument("--normal-threshold", type=_positive, default=None,
                   help="max |N_src - N_dst| of unit normals (default: cameras.json reprojection.normal_threshold)")
    p.add_argument("--alpha", type=_positive, default=0.2, help="minimum EMA weight of a new frame (paper: 0.2)")
    p.add_argument("--sampling", choices=("bilinear", "nearest"), default="bilinear")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_reproject)

    p = subparsers.add_parser("export-sequence", help="trace a scene into a `stereorepro reproject` input directory")
    p.add_argument("--scene", required=True, help="built-in scene name or path to a .toml")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--frames", type=int, default=8, help="number of frames")
    p.add_argument("--start", type=int, default=0, help="first scene frame")
    p.add_argument("--stride", type=int, default=1, help="scene frames between exported frames")
    p.add_argument("--resolution", type=parse_resolution, default=(320, 180), metavar="WxH")
    p.add_argument("--spp", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_export)
