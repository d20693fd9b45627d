"""The frame-sequence format that ``stereorepro reproject`` reads: a directory of EXR frames and their cameras.

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
tracer's EXR output (:func:`stereorepro.io.exr.write_exr`) is valid input. All files share one size. Cameras follow
:mod:`stereorepro.camera`: OpenCV axes (x right, y down, z forward), ``K`` maps camera space to pixel coordinates
whose pixel centres are at +0.5, ``cam_from_world`` is rigid. Unknown keys are errors (a typo is not silence).

:func:`stereorepro.workflows.export.export_sequence` (and ``stereorepro export-sequence``) writes such a
directory from our path tracer.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._checks import intrinsics_problem, rigid_problem
from ..camera import Eye
from ..errors import SequenceError
from .exr import CHANNELS, exr_info

__all__ = [
    "REQUIRED_CHANNELS",
    "SequenceError",
    "EyeCamera",
    "FrameSequence",
    "Frame",
    "load_sequence",
    "read_frame",
    "EYES",
    "FRAME_FILE_RE",
]

#: Channels every input EXR must have (others are ignored): the radiance, depth and normal groups.
REQUIRED_CHANNELS = CHANNELS["radiance"] + CHANNELS["depth"] + CHANNELS["normal"]
#: The eyes of a frame, in file-name form (``left``, ``right``).
EYES = tuple(Eye)
#: Our frame files' names (``{frame:04d}_{eye}.exr``): frame number and eye.
FRAME_FILE_RE = re.compile(r"^(\d{4,})_(left|right)\.exr$")


@dataclass(frozen=True)
class EyeCamera:
    """One eye's camera of one frame.

    Attributes:
        K: (1, 3, 3) float64 intrinsics (pixel centres at +0.5).
        cam_from_world: (1, 4, 4) float64 rigid extrinsics (OpenCV axes).

    Examples:
        >>> import torch
        >>> from stereorepro import intrinsics_from_fov
        >>> from stereorepro.io.frames import EyeCamera
        >>> cam = EyeCamera(intrinsics_from_fov(90.0, 4, 2).double(), torch.eye(4, dtype=torch.float64)[None])
        >>> tuple(cam.K.shape), tuple(cam.cam_from_world.shape)
        ((1, 3, 3), (1, 4, 4))
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

    Examples:
        >>> import torch
        >>> from pathlib import Path
        >>> from stereorepro.io.frames import EyeCamera, FrameSequence
        >>> cam = EyeCamera(torch.eye(3, dtype=torch.float64)[None], torch.eye(4, dtype=torch.float64)[None])
        >>> seq = FrameSequence(Path("clip"), cameras=({"left": cam, "right": cam},), height=2, width=4)
        >>> len(seq), seq.path(0, "right").as_posix()  # the file of frame 0, right eye
        (1, 'clip/0000_right.exr')
    """

    root: Path
    cameras: tuple
    height: int
    width: int
    position_threshold: float | None = None
    normal_threshold: float | None = None
    source: str = "stereorepro"  #: the renderer whose EXRs these are (:data:`SOURCES`)
    frame_numbers: tuple | None = None  #: Blender's file frame numbers (``meta.frame_numbers``)

    def __len__(self) -> int:
        return len(self.cameras)

    def path(self, frame: int, eye: str) -> Path:
        if self.source == "blender":
            from .blender import file_name

            return self.root / file_name(self.frame_numbers[frame], eye)
        return self.root / f"{frame:04d}_{eye}.exr"


@dataclass(frozen=True, eq=False)
class Frame:
    """One eye of one frame, as :func:`read_frame` returns it (on one device).

    Attributes:
        color: (1, 3, H, W) float32 linear radiance.
        depth: (1, 1, H, W) float32 camera z (no surface: NaN, ±inf or <= 0, as the file has it).
        normal: (1, 3, H, W) float32 world-space unit normals (non-unit ones renormalised, see ``normal_stats``).
        K: (1, 3, 3) float64 intrinsics. cam_from_world: (1, 4, 4) float64 rigid extrinsics.
        motion: (1, 2, H, W) float32 pixels to the previous frame, or ``None`` (the file has no ``M.*``).
        motion_world: (1, 3, H, W) float32 world motion to the previous frame, or ``None`` (no ``MW.*``).
        normal_stats: the normal policy's counts over the surface pixels: ``surface``, ``renormalised``,
            ``invalid`` (zero or non-finite normals, which fail the normal test).

    Dict-style access (``frame["color"]``, ``"motion" in frame``, ``frame.get("motion")``), the former return
    type's, still works for one release with a DeprecationWarning; a ``None`` motion reads as an absent key.

    Examples:
        >>> import torch
        >>> from stereorepro.io.frames import Frame
        >>> frame = Frame(torch.zeros(1, 3, 2, 4), torch.full((1, 1, 2, 4), 2.0), torch.zeros(1, 3, 2, 4),
        ...               torch.eye(3, dtype=torch.float64)[None], torch.eye(4, dtype=torch.float64)[None])
        >>> tuple(frame.color.shape), frame.motion is None, frame.normal_stats
        ((1, 3, 2, 4), True, {})
    """

    color: Tensor
    depth: Tensor
    normal: Tensor
    K: Tensor
    cam_from_world: Tensor
    motion: Tensor | None = None
    motion_world: Tensor | None = None
    normal_stats: dict = field(default_factory=dict)

    def _keys(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]

    @staticmethod
    def _deprecated(how: str) -> None:
        warnings.warn(
            f"Frame {how} (dict-style access) is deprecated: use attribute access (frame.color, frame.motion is None)",
            DeprecationWarning,
            stacklevel=3,
        )

    def __getitem__(self, key: str):
        self._deprecated(f"[{key!r}]")
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def __contains__(self, key) -> bool:
        self._deprecated("'in'")
        return key in self._keys()

    def get(self, key: str, default=None):
        self._deprecated(f".get({key!r})")
        return getattr(self, key) if key in self._keys() else default

    def keys(self) -> list[str]:
        self._deprecated(".keys()")
        return self._keys()

    def __iter__(self):
        self._deprecated("iteration")
        return iter(self._keys())


def _matrix(value, rows: int, where: str) -> np.ndarray:
    ok = (
        isinstance(value, list)
        and len(value) == rows
        and all(isinstance(r, list) and len(r) == rows for r in value)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for r in value for x in r)
    )
    if not ok:
        raise SequenceError(f"{where}: expected a {rows}x{rows} list of numbers, got {json.dumps(value)[:80]}")
    a = np.asarray(value, np.float64)
    if not np.isfinite(a).all():
        raise SequenceError(f"{where}: values must be finite, got {a.tolist()}")
    return a


def _check_K(K: np.ndarray, where: str) -> None:
    problem = intrinsics_problem(K)
    if problem:
        raise SequenceError(f"{where}: {problem}")


def _check_rigid(T: np.ndarray, where: str, tol: float = 1e-4) -> None:
    problem = rigid_problem(T, tol)
    if problem:
        raise SequenceError(f"{where}: {problem}")


def _threshold(table, key: str, where: str) -> float | None:
    if key not in table:
        return None
    v = table[key]
    if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
        raise SequenceError(f"{where}.{key}: expected a positive number, got {v!r}")
    return float(v)


def _parse_cameras(path: Path, eyes: tuple[str, ...]) -> tuple[list[dict], dict, dict]:
    """Per-frame cameras of ``eyes``, the default thresholds and the ``meta`` object of a ``cameras.json``."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SequenceError(f"{path}: not a UTF-8 text (JSON) file: {e.reason} at byte {e.start}") from None
    except FileNotFoundError:
        raise SequenceError(f"{path}: not found (the input directory needs cameras.json)") from None
    except OSError as e:
        raise SequenceError(f"{path}: cannot read: {e}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise SequenceError(f"{path}: malformed JSON: {e}") from None
    except RecursionError:
        raise SequenceError(f"{path}: malformed: nested too deeply to be a cameras.json") from None
    if not isinstance(data, dict):
        raise SequenceError(f'{path}: expected an object {{"frames": [...]}}, got {type(data).__name__}')
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
        raise SequenceError(
            f"{path}: 'reprojection' must be an object with position_threshold and/or "
            f"normal_threshold, got {json.dumps(rep)[:80]}"
        )
    thr = {k: _threshold(rep, k, f"{path}: reprojection") for k in ("position_threshold", "normal_threshold")}
    meta = data.get("meta", {})
    return out, thr, meta if isinstance(meta, dict) else {}


def _exr_header(path: Path) -> tuple[list[str], int, int]:
    """Channel names (all parts) and the common size (H, W) from the headers alone; the header must pass
    :func:`stereorepro.io.exr.read_exr`'s checks (one data window for all parts), and the data window must be the
    display window (the cameras' pixel grid: a shifted or cropped image would not line up with them)."""
    try:
        info = exr_info(path)
    except ValueError as e:
        raise SequenceError(f"{path}: not a readable EXR: {e}") from None
    if info.data_window != info.display_window:
        raise SequenceError(
            f"{path}: data window {info.data_window} differs from the display window "
            f"{info.display_window} (a shifted or cropped image; frames must cover the whole image)"
        )
    return info.channels, info.sizes[0][0], info.sizes[0][1]


#: Renderers whose frame files the reader converts: ours (this module's format), Mitsuba 3's films written with
#: the ``aov`` integrator (:mod:`stereorepro.io.mitsuba`) and Blender's multilayer EXRs named as its stereo output
#: names them (:mod:`stereorepro.io.blender`). ``cameras.json`` is ours (OpenCV) for all.
SOURCES = ("stereorepro", "mitsuba", "blender")


def _required_channels(source: str) -> tuple[str, ...]:
    if source == "mitsuba":
        from .mitsuba import MITSUBA_CHANNELS

        return MITSUBA_CHANNELS
    if source == "blender":  # the view layer's name prefixes them: checked by suffix
        from .blender import BLENDER_CHANNELS

        return BLENDER_CHANNELS
    return REQUIRED_CHANNELS


def _has(names, channel: str, source: str) -> bool:
    return any(n.endswith("." + channel) for n in names) if source == "blender" else channel in names


def _frame_numbers(meta: dict, path: Path, n: int) -> tuple:
    """Blender's file frame numbers from ``cameras.json`` ``meta.frame_numbers`` (default 1 .. n, Blender's
    default frame_start = 1)."""
    nums = meta.get("frame_numbers")
    if nums is None:
        return tuple(range(1, n + 1))
    if not (
        isinstance(nums, list)
        and len(nums) == n
        and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in nums)
    ):
        raise SequenceError(f"{path}: meta.frame_numbers must list {n} frame numbers >= 0, got {json.dumps(nums)[:80]}")
    twice = sorted({x for x in nums if nums.count(x) > 1})
    if twice:
        raise SequenceError(
            f"{path}: meta.frame_numbers lists frame(s) {twice} more than once (each frame number "
            "names one pair of files)"
        )
    return tuple(nums)


def _unlisted_files(root: Path, n: int, source: str, numbers: tuple | None) -> list[str]:
    """Frame files in ``root`` that ``cameras.json`` does not list: ours beyond its ``n`` frames, Blender's whose
    number is not in ``meta.frame_numbers``."""
    if source == "blender":
        from .blender import FILE_RE

        listed = set(numbers)
        return sorted(p.name for p in root.iterdir() if (m := FILE_RE.match(p.name)) and int(m.group(1)) not in listed)
    return sorted(p.name for p in root.iterdir() if (m := FRAME_FILE_RE.match(p.name)) and int(m.group(1)) >= n)


def load_sequence(input_dir, eyes: tuple[str, ...] = EYES, source: str = "stereorepro") -> FrameSequence:
    """Validate an input directory without reading pixels: ``cameras.json`` (shapes, rigidity, keys), the frame
    files present against the frames listed, and every needed EXR's channels and size (from its header).

    Args:
        input_dir: the directory.
        eyes: the eyes whose cameras and files are needed.
        source: the renderer that wrote the EXRs (:data:`SOURCES`); converted to our conventions on reading.

    Raises:
        SequenceError: naming the file, and the frame and key for ``cameras.json``.

    Examples:
        >>> import json, os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import write_exr
        >>> from stereorepro.io.frames import load_sequence
        >>> camera = {"K": [[2.0, 0, 2], [0, 2.0, 1], [0, 0, 1]], "cam_from_world": np.eye(4).tolist()}
        >>> exr = {c: np.zeros((2, 4), np.float32) for c in ("R", "G", "B", "N.X", "N.Y")}
        >>> exr.update({"Z": np.full((2, 4), 2.0, np.float32), "N.Z": np.full((2, 4), -1.0, np.float32)})
        >>> with tempfile.TemporaryDirectory() as d:
        ...     with open(os.path.join(d, "cameras.json"), "w") as f:
        ...         json.dump({"frames": [{"left": camera, "right": camera}]}, f)
        ...     for eye in ("left", "right"):
        ...         write_exr(os.path.join(d, f"0000_{eye}.exr"), exr)
        ...     seq = load_sequence(d)
        >>> len(seq), (seq.height, seq.width), sorted(str(eye) for eye in seq.cameras[0]), seq.position_threshold
        (1, (2, 4), ['left', 'right'], None)
    """
    if source not in SOURCES:
        raise SequenceError(f"source must be one of {SOURCES}, got {source!r}")
    required = _required_channels(source)
    root = Path(input_dir)
    if not root.is_dir():
        raise SequenceError(f"{root}: not a directory")
    cams, thr, meta = _parse_cameras(root / "cameras.json", tuple(eyes))
    n = len(cams)
    numbers = _frame_numbers(meta, root / "cameras.json", n) if source == "blender" else None
    probe = FrameSequence(root, tuple(cams), 0, 0, source=source, frame_numbers=numbers)
    beyond = _unlisted_files(root, n, source, numbers)
    if beyond:
        which = "not in its meta.frame_numbers" if source == "blender" else "beyond them"
        raise SequenceError(
            f"{root / 'cameras.json'}: lists {n} frame(s) but {root} has frame files {which}: "
            f"{', '.join(beyond[:4])}{' ...' if len(beyond) > 4 else ''}"
        )
    size = None
    first = None
    for i in range(n):
        for eye in eyes:
            p = probe.path(i, eye)
            if not p.is_file():
                raise SequenceError(f"{p}: missing (cameras.json lists {n} frame(s); frame {i} needs {eye} eye)")
            names, H, W = _exr_header(p)
            if source == "blender":
                from .blender import layer_prefix

                layer_prefix(names, str(p))
            missing = [c for c in required if not _has(names, c, source)]
            if missing:
                raise SequenceError(
                    f"{p}: missing channel(s) {', '.join(missing)} (required for --from {source}: "
                    f"{', '.join(required)}; found: {', '.join(sorted(names))})"
                )
            if size is None:
                size, first = (H, W), p
            elif (H, W) != size:
                raise SequenceError(
                    f"{p}: size {W}x{H} differs from {first.name}: {size[1]}x{size[0]} "
                    "(all frames and eyes must have one size)"
                )
    return FrameSequence(
        root, tuple(cams), size[0], size[1], thr["position_threshold"], thr["normal_threshold"], source, numbers
    )


#: Normals whose length differs from 1 by more than this (beyond float16 rounding) are renormalised on reading.
NORMAL_LENGTH_TOLERANCE = 2e-3


def _unit_normals(normal: Tensor, depth: Tensor) -> tuple[Tensor, dict]:
    """The policy for normals read from files: a finite, non-zero normal whose length is off by more than
    :data:`NORMAL_LENGTH_TOLERANCE` is renormalised (renderers average normals over a pixel's samples); a zero or
    non-finite one is left as it is (it fails the normal test). Returns the normals and counts over the surface
    pixels: ``surface``, ``renormalised``, ``invalid``."""
    length = normal.double().norm(dim=1, keepdim=True)
    surf = torch.isfinite(depth) & (depth > 0)
    ok = torch.isfinite(length) & (length > 0)
    fix = ok & ((length - 1.0).abs() > NORMAL_LENGTH_TOLERANCE)
    if bool(fix.any()):
        normal = torch.where(fix, (normal.double() / torch.where(ok, length, 1.0)).to(normal.dtype), normal)
    return normal, {
        "surface": int(surf.sum()),
        "renormalised": int((fix & surf).sum()),
        "invalid": int((~ok & surf).sum()),
    }


def read_frame(seq: FrameSequence, frame: int, eye: str, device=None) -> Frame:
    """Read one eye of one frame, on ``device``.

    Returns:
        a :class:`Frame`: colour, depth, normal (non-unit normals renormalised, see :func:`_unit_normals`), the
        eye's camera, and ``motion`` / ``motion_world`` when the file has those channels (``M.*``, ``MW.*``).

    Examples:
        >>> import json, os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import write_exr
        >>> from stereorepro.io.frames import load_sequence, read_frame
        >>> camera = {"K": [[2.0, 0, 2], [0, 2.0, 1], [0, 0, 1]], "cam_from_world": np.eye(4).tolist()}
        >>> exr = {c: np.zeros((2, 4), np.float32) for c in ("R", "G", "B", "N.X", "N.Y")}
        >>> exr.update({"Z": np.full((2, 4), 2.0, np.float32), "N.Z": np.full((2, 4), -1.0, np.float32)})
        >>> with tempfile.TemporaryDirectory() as d:
        ...     with open(os.path.join(d, "cameras.json"), "w") as f:
        ...         json.dump({"frames": [{"left": camera}]}, f)
        ...     write_exr(os.path.join(d, "0000_left.exr"), exr)
        ...     frame = read_frame(load_sequence(d, eyes=("left",)), 0, "left")
        >>> tuple(frame.color.shape), float(frame.depth.max()), frame.motion is None, frame.normal_stats["surface"]
        ((1, 3, 2, 4), 2.0, True, 8)
    """
    from .exr import read_exr

    p = seq.path(frame, eye)
    try:
        ch = read_exr(p)
    except (FileNotFoundError, ValueError) as e:
        raise SequenceError(str(e)) from None
    for c in _required_channels(seq.source):  # the header was checked; a file changed since is still named
        got = [k for k in ch if k == c or (seq.source == "blender" and k.endswith("." + c))]
        if not got or ch[got[0]].shape != (seq.height, seq.width):
            raise SequenceError(f"{p}: channel {c} missing or not {seq.width}x{seq.height}")

    def stack(names):
        return torch.from_numpy(np.stack([ch[c] for c in names])[None].astype(np.float32)).to(device)

    cam = seq.cameras[frame][eye]
    if seq.source == "mitsuba":  # converted at the edge, here, once
        from ..camera import PinholeCamera
        from .mitsuba import frame_from_channels

        conv = frame_from_channels(ch, PinholeCamera(cam.K, cam.cam_from_world, seq.height, seq.width), str(p))
        color, depth, normal = (conv[k].to(device) for k in ("color", "depth", "normal"))
    elif seq.source == "blender":
        from .blender import frame_from_channels as blender_frame

        conv = blender_frame(ch, str(p))
        color, depth, normal = (conv[k].to(device) for k in ("color", "depth", "normal"))
    else:
        color, depth, normal = stack(CHANNELS["radiance"]), stack(CHANNELS["depth"]), stack(CHANNELS["normal"])
    normal, normal_stats = _unit_normals(normal, depth)
    motion = {}
    if seq.source == "blender":
        if "motion" in conv:  # Blender's Vector pass; it has no world-space motion
            motion["motion"] = conv["motion"].to(device)
    else:
        for key in ("motion", "motion_world"):
            names = CHANNELS[key]
            if all(c in ch and ch[c].shape == (seq.height, seq.width) for c in names):
                motion[key] = stack(names)
    return Frame(
        color, depth, normal, cam.K.to(device), cam.cam_from_world.to(device), normal_stats=normal_stats, **motion
    )
