"""EXR frames: the project's frame format, its channel names (defined here, once) and their reading and writing.

Channels (all 32-bit float, ZIP-compressed, lossless): radiance ``R, G, B``; depth ``Z`` (camera z, ``+inf``
where there is no surface); shading normal ``N.X, N.Y, N.Z``; world position ``P.X, P.Y, P.Z``. Optional extra
channels may be added (e.g. ``albedo.R``). The same layout is read by ``stereorepro reproject``
(:mod:`stereorepro.io.frames`). The radiance group is the image a reprojection calls its ``color``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from .atomic import atomic_path

__all__ = ["write_exr", "read_exr", "exr_to_tensors", "result_channels", "CHANNELS"]

#: Channel names of each group of the frame format (a RenderResult's field name → its EXR channels).
CHANNELS = {"radiance": ("R", "G", "B"), "depth": ("Z",), "normal": ("N.X", "N.Y", "N.Z"),
            "position": ("P.X", "P.Y", "P.Z")}
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
    """Write an EXR atomically (:func:`stereorepro.io.atomic.atomic_path`).

    Args:
        path: output file.
        data: a :class:`~stereorepro.render.RenderResult` or a dict of channel name → (H, W) array.
    """
    chans = result_channels(data) if not isinstance(data, dict) else data
    if not chans:
        raise ValueError("write_exr: no channels to write")
    import OpenEXR

    shapes = {np.shape(v) for v in chans.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"write_exr: all channels must be (H, W) arrays of one size, got {shapes}")
    # OpenEXR ignores numpy strides and rewrites the dict it is given: pass fresh, contiguous copies.
    fresh = {str(k): np.ascontiguousarray(np.asarray(v, dtype=np.float32)).copy() for k, v in chans.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, fresh).write(str(tmp))


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read all channels of an EXR: name → (H, W) float32 array.

    Raises:
        FileNotFoundError: the file does not exist. ValueError: it is not a readable EXR.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"read_exr: no such file: {path}")
    try:
        f = OpenEXR.File(str(path))
        chans = f.channels()
        out = {}
        for name, ch in chans.items():
            px = np.asarray(ch.pixels)
            if px.ndim == 3:  # an RGB(A) group read as one channel
                for i, sub in enumerate(name):
                    out[sub] = np.ascontiguousarray(px[..., i], dtype=np.float32)
            else:
                out[name] = np.ascontiguousarray(px, dtype=np.float32)
    except Exception as e:
        raise ValueError(f"read_exr: cannot read {path} as EXR: {e}") from None
    return out


def exr_to_tensors(channels: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Group channels into (1, C, H, W) float32 tensors: ``radiance``, ``depth``, ``normal``, ``position`` (those
    present with all their channels)."""
    out = {}
    for field, names in _GROUPS.items():
        if all(n in channels for n in names):
            out[field] = torch.from_numpy(np.stack([channels[n] for n in names])[None].copy())
    return out
