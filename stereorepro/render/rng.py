"""Counter-based random numbers: every number is a pure function of its key.

Key layout
----------
A random number is ``hash(seed, frame, eye, pixel, sample, dimension)`` where

* ``seed``  - the tracer's seed (``PathTracer(seed=...)``),
* ``frame`` - the frame index of the sequence,
* ``eye``   - 0 = left, 1 = right (any small int),
* ``pixel`` - the flat pixel index ``y * W + x``,
* ``sample``- the absolute sample index ``sample_offset + s`` (``s`` in ``[0, spp)``),
* ``dimension`` - which number of the path (see :data:`DIM`).

The key is folded left to right with a 64-bit combine (``h = fmix(h ^ fmix(v + c))``, ``fmix`` = the splitmix64
finaliser); the first three fields are folded once per render in Python integers, ``pixel`` and ``sample`` per
path in vectorised numpy ``uint64``, and ``dimension`` per number. The top 24 bits give a float32 in [0, 1).

Consequences: an n-spp image is a prefix of the (n+m)-spp image's sample stream; results do not depend on batch
size, chunking or number of workers; ``sample_offset`` selects streams disjoint from those of another render
(e.g. a reference rendered with samples ``[0, N)`` and a ladder rendered from ``sample_offset = N``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["DIM", "stream_key", "path_keys", "uniform", "uniform2"]

_M64 = (1 << 64) - 1
_C0 = 0x9E3779B97F4A7C15
_C1 = 0xBF58476D1CE4E5B9
_C2 = 0x94D049BB133111EB

#: Dimensions of one path sample (one primary ray, one bounce, two shadow rays).
DIM = {
    "jitter_x": 0,
    "jitter_y": 1,  # sub-pixel position
    "light1": 2,
    "light1_u": 3,
    "light1_v": 4,  # next-event estimation at the first hit
    "lobe": 5,
    "bsdf_u": 6,
    "bsdf_v": 7,  # BSDF-sampled secondary ray
    "light2": 8,
    "light2_u": 9,
    "light2_v": 10,  # next-event estimation at the second hit
}


def _fmix_int(z: int) -> int:
    z &= _M64
    z = ((z ^ (z >> 30)) * _C1) & _M64
    z = ((z ^ (z >> 27)) * _C2) & _M64
    return z ^ (z >> 31)


def _combine_int(h: int, v: int) -> int:
    return _fmix_int(h ^ _fmix_int((v + _C0) & _M64))


def _fmix(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * np.uint64(_C1)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(_C2)
    return z ^ (z >> np.uint64(31))


def stream_key(seed: int, frame: int, eye: int) -> int:
    """Fold (seed, frame, eye) into one 64-bit key (a Python int).

    Examples:
        >>> from stereorepro.render.rng import stream_key
        >>> stream_key(0, 0, 0) == stream_key(0, 0, 0), stream_key(0, 0, 0) == stream_key(0, 0, 1)
        (True, False)
        >>> 0 <= stream_key(7, 3, 1) < 2 ** 64
        True
    """
    h = _fmix_int(0x5EED ^ (int(seed) & _M64))
    h = _combine_int(h, int(frame) & _M64)
    return _combine_int(h, int(eye) & _M64)


def path_keys(key: int, pixel: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """Per-path keys.

    Args:
        key: from :func:`stream_key`.
        pixel: (N,) flat pixel indices (any integer dtype).
        sample: (N,) absolute sample indices, broadcastable with ``pixel``.

    Returns:
        (N,) uint64.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.rng import path_keys, stream_key
        >>> keys = path_keys(stream_key(0, 0, 0), np.arange(4), np.zeros(4, np.int64))
        >>> keys.shape, keys.dtype, len(set(keys.tolist()))
        ((4,), dtype('uint64'), 4)
    """
    with np.errstate(over="ignore"):
        p = pixel.astype(np.uint64) + np.uint64(_C0)
        h = _fmix(np.uint64(key) ^ _fmix(p))
        s = np.asarray(sample).astype(np.uint64) + np.uint64(_C0)
        return _fmix(h ^ _fmix(s))


def uniform(keys: np.ndarray, dim: int) -> np.ndarray:
    """Uniform float32 numbers in [0, 1) for dimension ``dim`` of each path key (N,) → (N,).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.rng import DIM, path_keys, stream_key, uniform
        >>> keys = path_keys(stream_key(0, 0, 0), np.arange(1000), np.zeros(1000, np.int64))
        >>> u = uniform(keys, DIM["jitter_x"])
        >>> u.dtype, bool((u >= 0).all() and (u < 1).all()), round(float(u.mean()), 1)
        (dtype('float32'), True, 0.5)
    """
    d = np.uint64(_fmix_int((int(dim) + _C0) & _M64))
    with np.errstate(over="ignore"):
        bits = _fmix(keys ^ d) >> np.uint64(40)
    return bits.astype(np.float32) * np.float32(1.0 / (1 << 24))


def uniform2(keys: np.ndarray, dim0: int, dim1: int) -> tuple[np.ndarray, np.ndarray]:
    """Two uniform dimensions at once, each (N,) float32 in [0, 1).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.rng import DIM, path_keys, stream_key, uniform, uniform2
        >>> keys = path_keys(stream_key(0, 0, 0), np.arange(3), np.zeros(3, np.int64))
        >>> ux, uy = uniform2(keys, DIM["jitter_x"], DIM["jitter_y"])
        >>> ux.shape, bool(np.array_equal(ux, uniform(keys, DIM["jitter_x"]))), bool(np.array_equal(ux, uy))
        ((3,), True, False)
    """
    return uniform(keys, dim0), uniform(keys, dim1)
