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
from pathlib import Path

import numpy as np
import torch

from .._extras import require
from .atomic import atomic_write

__all__ = ["write_exr", "read_exr", "exr_to_tensors", "result_channels", "CHANNELS", "MAX_SAMPLES", "exr_header"]

#: Channel names of each group of the frame format (a RenderResult's field name → its EXR channels).
CHANNELS = {"radiance": ("R", "G", "B"), "depth": ("Z",), "normal": ("N.X", "N.Y", "N.Z"),
            "position": ("P.X", "P.Y", "P.Z"), "motion": ("M.X", "M.Y"), "motion_world": ("MW.X", "MW.Y", "MW.Z")}
_GROUPS = CHANNELS


def result_channels(result) -> dict[str, np.ndarray]:
    """EXR channels (name → (H, W) float32) of a :class:`~stereorepro.render.RenderResult` (B must be 1)."""
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
    """
    chans = result_channels(data) if not isinstance(data, dict) else data
    if not chans:
        raise ValueError("write_exr: no channels to write")
    OpenEXR = require("OpenEXR", "EXR files")

    shapes = {np.shape(v) for v in chans.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"write_exr: all channels must be (H, W) arrays of one size, got {shapes}")
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


@contextlib.contextmanager
def _captured_output():
    """Capture what C code writes to file descriptors 1 and 2 (OpenEXR prints its own errors and warnings there)
    into a list of one string, instead of the user's terminal."""
    text = [""]
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:  # no standard streams to capture
        yield text
        return
    py_text = io.StringIO()  # the bindings may also print through Python's sys.stdout
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        try:
            with contextlib.redirect_stdout(py_text), contextlib.redirect_stderr(py_text):
                yield text
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            tmp.seek(0)
            text[0] = tmp.read(4096).decode(errors="replace") + py_text.getvalue()[:4096]


def _check_header(path: Path, parts) -> tuple[list[str], list[tuple[int, int]]]:
    """Channel names and (H, W) of each part, after the size checks of :func:`read_exr`."""
    size = path.stat().st_size
    samples = 0
    bounded = True
    names, sizes = [], []
    for part in parts:
        h = part.header
        lo, hi = (np.asarray(v, dtype=np.int64) for v in h["dataWindow"])
        w, hgt = int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
        if w < 1 or hgt < 1:
            raise ValueError(f"data window {w}x{hgt} is empty")
        samples += w * hgt * len(h["channels"])
        bounded &= any(name in str(h.get("compression", "")) for name in _BOUNDED_COMPRESSION)
        names += [c.name for c in h["channels"]]
        sizes.append((hgt, w))
    if samples > MAX_SAMPLES:
        raise ValueError(f"its header claims {samples} samples (more than MAX_SAMPLES = {MAX_SAMPLES}); "
                         f"refusing to allocate {samples * 4 / 2 ** 30:.1f} GiB")
    if bounded and samples * 2 > _MAX_RATIO * size + (1 << 20):  # at least 2 bytes (half) per sample
        raise ValueError(f"truncated or corrupt: its header claims {samples} samples, more than a file of {size} "
                         f"bytes can hold with its compression")
    return names, sizes


def exr_header(path: str | os.PathLike) -> tuple[list[str], list[tuple[int, int]]]:
    """Channel names (all parts) and each part's (H, W), from the header alone (no pixels are read).

    Raises:
        ValueError: not a readable EXR, or a header :func:`read_exr` would refuse.
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


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read all channels of all parts of an EXR: name → (H, W) float32 array (half and float channels alike).

    Channel names are returned as written, grouped or dotted (``R``, ``N.X``, ``ViewLayer.Combined.R``); a
    multi-part file (one part per pass, as Blender writes) gives the union of its parts' channels. The header is
    checked before pixels are read: more than :data:`MAX_SAMPLES` samples, or more than the file's size can
    hold, is refused without allocating them.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: it is not a readable EXR (the message says why; OpenEXR's own messages are folded into it
            instead of being printed).
    """
    OpenEXR = require("OpenEXR", "EXR files")

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"read_exr: no such file: {path}")
    out: dict[str, np.ndarray] = {}
    with _captured_output() as noise:
        try:
            names, _ = _check_header(path, OpenEXR.File(str(path), header_only=True).parts)
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


def exr_to_tensors(channels: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Group channels into (1, C, H, W) float32 tensors: ``radiance``, ``depth``, ``normal``, ``position``,
    ``motion``, ``motion_world`` (those present with all their channels)."""
    out = {}
    for field, names in _GROUPS.items():
        if all(n in channels for n in names):
            out[field] = torch.from_numpy(np.stack([channels[n] for n in names])[None].copy())
    return out
