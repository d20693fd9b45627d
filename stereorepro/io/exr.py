"""EXR frames: the project's frame format, its channel names (defined here, once) and their reading and writing.

Channels (all 32-bit float, ZIP-compressed, lossless): radiance ``R, G, B``; depth ``Z`` (camera z, ``+inf``
where there is no surface); shading normal ``N.X, N.Y, N.Z``; world position ``P.X, P.Y, P.Z``; optionally the
motion to the previous frame, ``M.X, M.Y`` (pixels, ``prev_pixel = pixel + motion``) and ``MW.X, MW.Y, MW.Z``
(world units, ``P_prev = P + motion_world``), NaN where there is no surface. Other extra channels may be added
(e.g. ``albedo.R``). The same layout is read by ``stereorepro reproject``
(:mod:`stereorepro.io.frames`). The radiance group is the image a reprojection calls its ``color``.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .._extras import require
from ..errors import SequenceError, ShapeError
from .atomic import atomic_write

__all__ = [
    "write_exr",
    "read_exr",
    "exr_to_tensors",
    "result_channels",
    "CHANNELS",
    "MAX_SAMPLES",
    "exr_header",
    "exr_info",
    "ExrInfo",
    "channel_size",
]

#: Channel names of each group of the frame format (a RenderResult's field name → its EXR channels).
CHANNELS = {
    "radiance": ("R", "G", "B"),
    "depth": ("Z",),
    "normal": ("N.X", "N.Y", "N.Z"),
    "position": ("P.X", "P.Y", "P.Z"),
    "motion": ("M.X", "M.Y"),
    "motion_world": ("MW.X", "MW.Y", "MW.Z"),
}
_GROUPS = CHANNELS


def result_channels(result) -> dict[str, np.ndarray]:
    """EXR channels (name → (H, W) float32) of a :class:`~stereorepro.render.RenderResult` (B must be 1).

    Examples:
        >>> import types, torch
        >>> from stereorepro.io.exr import CHANNELS, result_channels
        >>> fields = dict.fromkeys(CHANNELS, None)  # a RenderResult's image fields: radiance and depth only here
        >>> fields.update(radiance=torch.ones(1, 3, 2, 4), depth=torch.full((1, 1, 2, 4), 2.0))
        >>> result = types.SimpleNamespace(**fields)
        >>> channels = result_channels(result)
        >>> sorted(channels), channels["Z"].shape, float(channels["Z"][0, 0])
        (['B', 'G', 'R', 'Z'], (2, 4), 2.0)
    """
    out = {}
    for field, names in _GROUPS.items():
        t = getattr(result, field)
        if t is None:
            continue
        if t.dim() != 4 or t.shape[0] != 1 or t.shape[1] != len(names):
            raise ValueError(f"write_exr: {field} must have shape (1, {len(names)}, H, W), got {tuple(t.shape)}")
        a = t[0].detach().cpu().float().numpy()
        for i, n in enumerate(names):
            out[n] = a[i]
    return out


def write_exr(path: str | os.PathLike, data) -> None:
    """Write an EXR atomically (:func:`stereorepro.io.atomic.atomic_write`): encoded in memory, then written,
    synced and renamed, so a full disk raises ``OSError(ENOSPC)`` naming ``path`` and leaves nothing behind.

    Args:
        path: output file.
        data: a :class:`~stereorepro.render.RenderResult` or a dict of channel name → (H, W) array.

    Raises:
        ShapeError: channels that are not (H, W) arrays of one size with H, W >= 1.

    Examples:
        >>> import os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import read_exr, write_exr
        >>> depth = np.arange(48, dtype=np.float32).reshape(6, 8)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_exr(os.path.join(d, "frame.exr"), {"R": np.full((6, 8), 0.5, np.float32), "depth": depth})
        ...     channels = read_exr(os.path.join(d, "frame.exr"))
        >>> sorted(channels), bool(np.array_equal(channels["depth"], depth)), float(channels["R"][0, 0])
        (['R', 'depth'], True, 0.5)
    """
    chans = result_channels(data) if not isinstance(data, dict) else data
    if not chans:
        raise ValueError("write_exr: no channels to write")
    OpenEXR = require("OpenEXR", "EXR files")

    shapes = {np.shape(v) for v in chans.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ShapeError(f"write_exr: all channels must be (H, W) arrays of one size, got {shapes}")
    if min(next(iter(shapes))) < 1:
        raise ShapeError(
            f"write_exr: {path}: channels of shape {next(iter(shapes))} are empty (an EXR needs H, W >= 1)"
        )
    # OpenEXR ignores numpy strides and rewrites the dict it is given: pass fresh, contiguous copies.
    fresh = {str(k): np.ascontiguousarray(np.asarray(v, dtype=np.float32)).copy() for k, v in chans.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buf = io.BytesIO()
    OpenEXR.File(header, fresh).write(buf)
    atomic_write(path, buf.getvalue())


#: Most samples (pixels × channels, over all parts) :func:`read_exr` decodes: a header claiming more is refused
#: before any pixel memory is allocated (2^30 samples = 4 GiB of float32).
MAX_SAMPLES = 1 << 30

#: Compressions whose ratio is bounded (deflate: at most ~1032:1; RLE: 128:1; none: 1:1), and that bound with a
#: margin: a header claiming more pixel bytes than that times the file size describes a truncated or forged file.
_BOUNDED_COMPRESSION = ("NO_COMPRESSION", "RLE_COMPRESSION", "ZIPS_COMPRESSION", "ZIP_COMPRESSION")
_MAX_RATIO = 1100


class _Capture:
    """The process's descriptors 1 and 2 (and ``sys.stdout`` / ``sys.stderr``) swapped to one temporary file while
    any thread reads an EXR. The swap is process-wide, so it is shared: the first reader swaps, later readers join,
    the last one out restores (under :data:`_CAPTURE_LOCK`); overlapping reads never restore each other's streams."""

    def __init__(self):
        self.depth = 0
        self.saved: list[int] | None = None  # dups of the real descriptors 1 and 2 while swapped
        self.tmp = None
        self.py: io.StringIO | None = None  # the bindings may also print through Python's sys.stdout
        self.streams = None

    def start(self) -> None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError, AttributeError):
                stream.flush()
        try:
            self.saved = [os.dup(1), os.dup(2)]
        except OSError:  # no standard streams to capture
            self.saved = None
            return
        self.tmp = tempfile.TemporaryFile(mode="w+b")  # noqa: SIM115 - closed by stop()
        os.dup2(self.tmp.fileno(), 1)
        os.dup2(self.tmp.fileno(), 2)
        self.py, self.streams = io.StringIO(), (sys.stdout, sys.stderr)
        sys.stdout = sys.stderr = self.py

    def mark(self) -> tuple[int, int]:
        if self.saved is None:
            return 0, 0
        return os.lseek(self.tmp.fileno(), 0, os.SEEK_END), len(self.py.getvalue())

    def since(self, mark: tuple[int, int]) -> str:
        """What was written since ``mark`` (4 KiB of each kind at most; other threads' output included)."""
        if self.saved is None:
            return ""
        return (
            os.pread(self.tmp.fileno(), 4096, mark[0]).decode(errors="replace")
            + self.py.getvalue()[mark[1] : mark[1] + 4096]
        )

    def stop(self) -> None:
        if self.saved is None:
            return
        os.dup2(self.saved[0], 1)
        os.dup2(self.saved[1], 2)
        for fd in self.saved:
            os.close(fd)
        sys.stdout, sys.stderr = self.streams
        self.tmp.close()
        self.saved = self.tmp = self.py = self.streams = None


_CAPTURE_LOCK = threading.Lock()
_CAPTURE = _Capture()


@contextlib.contextmanager
def _captured_output():
    """Capture what C code writes to file descriptors 1 and 2 (OpenEXR prints its own errors and warnings there)
    into a list of one string, instead of the user's terminal. Thread-safe (see :class:`_Capture`)."""
    text = [""]
    with _CAPTURE_LOCK:
        if _CAPTURE.depth == 0:
            _CAPTURE.start()
        _CAPTURE.depth += 1
        mark = _CAPTURE.mark()
    try:
        yield text
    finally:
        with _CAPTURE_LOCK:
            text[0] = _CAPTURE.since(mark)
            _CAPTURE.depth -= 1
            if _CAPTURE.depth == 0:
                _CAPTURE.stop()


class ExrInfo(NamedTuple):
    """An EXR's header, as :func:`exr_info` reads it.

    Attributes:
        channels: channel names of all parts. sizes: each part's (H, W).
        data_window, display_window: ``((x_min, y_min), (x_max, y_max))`` (inclusive), one for all parts.

    Examples:
        >>> from stereorepro.io.exr import ExrInfo
        >>> info = ExrInfo(["Z"], [(2, 4)], ((0, 0), (3, 1)), ((0, 0), (3, 1)))  # what exr_info returns for a 4x2 image
        >>> info.sizes[0], info.data_window == info.display_window
        ((2, 4), True)
    """

    channels: list
    sizes: list
    data_window: tuple
    display_window: tuple


def _window(header, key: str) -> tuple:
    lo, hi = (np.asarray(v, dtype=np.int64) for v in header[key])
    return (int(lo[0]), int(lo[1])), (int(hi[0]), int(hi[1]))


def _check_header(path: Path, parts) -> ExrInfo:
    """The header after the checks of :func:`read_exr`: sizes against :data:`MAX_SAMPLES` and the file's size,
    and one data window for all parts (their channels are pixels of one image)."""
    size = path.stat().st_size
    samples = 0
    bounded = True
    names, sizes, windows = [], [], []
    for i, part in enumerate(parts):
        h = part.header
        (x0, y0), (x1, y1) = window = _window(h, "dataWindow")
        w, hgt = x1 - x0 + 1, y1 - y0 + 1
        if w < 1 or hgt < 1:
            raise ValueError(f"data window {w}x{hgt} is empty")
        samples += w * hgt * len(h["channels"])
        bounded &= any(name in str(h.get("compression", "")) for name in _BOUNDED_COMPRESSION)
        names += [c.name for c in h["channels"]]
        sizes.append((hgt, w))
        windows.append((str(h.get("name", i)), window))
    if samples > MAX_SAMPLES:
        raise ValueError(
            f"its header claims {samples} samples (more than MAX_SAMPLES = {MAX_SAMPLES}); "
            f"refusing to allocate {samples * 4 / 2**30:.1f} GiB"
        )
    if bounded and samples * 2 > _MAX_RATIO * size + (1 << 20):  # at least 2 bytes (half) per sample
        raise ValueError(
            f"truncated or corrupt: its header claims {samples} samples, more than a file of {size} "
            f"bytes can hold with its compression"
        )
    odd = next(((n, w) for n, w in windows if w != windows[0][1]), None)
    if odd is not None:
        raise ValueError(
            f"part {odd[0]!r} has data window {odd[1]}, part {windows[0][0]!r} {windows[0][1]} "
            "(all parts of a file must share one data window: their pixels would not line up)"
        )
    display = _window(parts[0].header, "displayWindow") if "displayWindow" in parts[0].header else windows[0][1]
    return ExrInfo(names, sizes, windows[0][1], display)


def exr_info(path: str | os.PathLike) -> ExrInfo:
    """An EXR's channel names, part sizes and windows, from the header alone (no pixels are read).

    Raises:
        ValueError: not a readable EXR, or a header :func:`read_exr` would refuse.

    Examples:
        >>> import os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import write_exr
        >>> from stereorepro.io.exr import exr_info
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_exr(os.path.join(d, "a.exr"), {"Z": np.ones((2, 4), np.float32)})
        ...     info = exr_info(os.path.join(d, "a.exr"))
        >>> info.channels, info.sizes, info.data_window
        (['Z'], [(2, 4)], ((0, 0), (3, 1)))
    """
    OpenEXR = require("OpenEXR", "EXR files")

    path = Path(path)
    with _captured_output():
        try:
            return _check_header(path, OpenEXR.File(str(path), header_only=True).parts)
        except ValueError:
            raise
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad file
            raise ValueError(str(e).strip() or type(e).__name__) from None


def exr_header(path: str | os.PathLike) -> tuple[list[str], list[tuple[int, int]]]:
    """Channel names (all parts) and each part's (H, W), from the header alone (:func:`exr_info`).

    Examples:
        >>> import os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import write_exr
        >>> from stereorepro.io.exr import exr_header
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_exr(os.path.join(d, "a.exr"), {"Z": np.ones((2, 4), np.float32), "R": np.zeros((2, 4))})
        ...     names, sizes = exr_header(os.path.join(d, "a.exr"))
        >>> sorted(names), sizes
        (['R', 'Z'], [(2, 4)])
    """
    info = exr_info(path)
    return info.channels, info.sizes


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read all channels of all parts of an EXR: name → (H, W) float32 array (half and float channels alike).

    Channel names are returned as written, grouped or dotted (``R``, ``N.X``, ``ViewLayer.Combined.R``); a
    multi-part file (one part per pass, as Blender writes) gives the union of its parts' channels. The header is
    checked before pixels are read: more than :data:`MAX_SAMPLES` samples, or more than the file's size can
    hold, is refused without allocating them; so are parts with different data windows.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: it is not a readable EXR (the message says why; OpenEXR's own messages are folded into it
            instead of being printed).

    Examples:
        >>> import os, tempfile
        >>> import numpy as np
        >>> from stereorepro.io import read_exr, write_exr
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_exr(os.path.join(d, "a.exr"), {"Z": np.ones((6, 8), np.float32)})
        ...     channels = read_exr(os.path.join(d, "a.exr"))
        >>> {name: (a.shape, str(a.dtype)) for name, a in channels.items()}
        {'Z': ((6, 8), 'float32')}
    """
    OpenEXR = require("OpenEXR", "EXR files")

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"read_exr: no such file: {path}")
    out: dict[str, np.ndarray] = {}
    with _captured_output() as noise:
        try:
            names = _check_header(path, OpenEXR.File(str(path), header_only=True).parts).channels
            f = OpenEXR.File(str(path), separate_channels=True)
            for part in f.parts:
                for name, ch in part.channels.items():
                    px = np.asarray(ch.pixels)
                    if px.ndim != 2:
                        raise ValueError(f"channel {name!r} has shape {px.shape}, expected (H, W)")
                    if name in out:
                        raise ValueError(f"channel {name!r} appears in more than one part")
                    out[name] = np.ascontiguousarray(px, dtype=np.float32)
            missing = sorted(set(names) - set(out))
            if missing:  # OpenEXR drops a part whose pixel data it cannot decode, with a warning on stdout
                raise ValueError(f"corrupt pixel data: channel(s) {', '.join(missing)} could not be decoded")
            error = None
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad file
            error = e
    if error is not None:
        detail = str(error).strip() or type(error).__name__
        c_line = next((ln.strip() for ln in noise[0].splitlines() if ln.strip()), "")
        if c_line and c_line not in detail:
            detail += f" ({c_line})"
        raise ValueError(f"read_exr: cannot read {path} as EXR: {detail}") from None
    return out


def channel_size(channels: dict, names, where: str, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """The common (H, W) of ``channels[name]`` for ``names`` (all present): every one must be a 2-D array of that
    size (``size`` when given, else the first one's).

    Raises:
        SequenceError: naming ``where``, the channel and both sizes.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.errors import SequenceError
        >>> from stereorepro.io.exr import channel_size
        >>> channels = {"R": np.zeros((2, 4)), "Z": np.zeros((2, 4)), "small": np.zeros((1, 4))}
        >>> channel_size(channels, ["R", "Z"], "frame.exr")
        (2, 4)
        >>> try:
        ...     channel_size(channels, ["R", "small"], "frame.exr")
        ... except SequenceError:
        ...     print("refused")
        refused
    """
    reference = "the camera"
    for name in names:
        shape = np.shape(channels[name])
        if len(shape) != 2:
            raise SequenceError(f"{where}: channel {name} has shape {shape}, expected (H, W)")
        if size is None:
            size, reference = shape, f"channel {name}"
        elif shape != tuple(size):
            raise SequenceError(
                f"{where}: channel {name} is {shape[1]}x{shape[0]}, {reference} {size[1]}x{size[0]} "
                "(all channels of a frame must have one size)"
            )
    return tuple(size)


def exr_to_tensors(channels: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Group channels into (1, C, H, W) float32 tensors: ``radiance``, ``depth``, ``normal``, ``position``,
    ``motion``, ``motion_world`` (those present with all their channels).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.io.exr import exr_to_tensors
        >>> channels = {c: np.ones((2, 4), np.float32) for c in ("R", "G", "B", "Z", "N.X")}  # N.Y, N.Z missing
        >>> {name: tuple(t.shape) for name, t in exr_to_tensors(channels).items()}
        {'radiance': (1, 3, 2, 4), 'depth': (1, 1, 2, 4)}
    """
    out = {}
    for field, names in _GROUPS.items():
        if all(n in channels for n in names):
            out[field] = torch.from_numpy(np.stack([channels[n] for n in names])[None].copy())
    return out
