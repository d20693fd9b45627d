"""Numbers the reprojection implementations share: the torch general path (:mod:`._general`), its fast path
(:mod:`._fast`), the export formulation (:mod:`._lean`) and the native kernels (``cpp_ext/src/reproject.cpp``).

The C++ kernels mirror :data:`MIRRORED_IN_CORE` as compile-time constants and export them as
``stereorepro._core.reproject_constants``; a test checks that the two agree (``tests/reproject/test_constants.py``).
"""

from __future__ import annotations

import struct

from .reason import Reason

#: How far outside the source image (in pixels) a projected coordinate is clamped: ``u`` to
#: ``[-COORD_MARGIN, Ws + COORD_MARGIN]``, ``v`` likewise. Keeps coordinates finite and small; a clamped coordinate
#: is off the frame for every tap, so the clamp changes no decision.
COORD_MARGIN = 4.0

#: The source coordinate a destination pixel that may read no tap is sent to (no surface, behind the source
#: camera, non-finite motion): the lower clamp, where every tap lies off the frame.
OFF_FRAME = -COORD_MARGIN

#: Border (pixels) of the padded source tables of the fast path and the export formulation: the taps of a
#: coordinate clamped to ``[-COORD_MARGIN, W + COORD_MARGIN]`` read pixels ``-TABLE_PAD .. W + COORD_MARGIN``.
TABLE_PAD = int(COORD_MARGIN) + 1

#: Integers up to this are exact in float32: larger tables index in float64 (torch) or leave the vector path (C++).
F32_EXACT_INT = 2**24

#: Code of a source tap that passes every destination-independent test in the export formulation: above every
#: code a tap can report (they run up to ``NONFINITE``).
TAP_OK_CODE = float(Reason.NONFINITE) + 1.0

#: Most value channels the native kernels carry per pixel (the temporal kernel's history colour plus its length):
#: inputs with more run on torch (``backend="auto"``).
NATIVE_MAX_CHANNELS = 16

#: The plane test (``Thresholds(position_test="plane")``) widens its threshold at grazing angles by
#: ``1 / (PLANE_BASE + PLANE_SLOPE·|n·v|)`` (NVIDIA NRD's ``lerp(0.05, 1, NoV)``): 20× edge-on, 1× head-on.
PLANE_BASE = 0.05
PLANE_SLOPE = 0.95

#: A destination normal defines a plane only where it is finite and ``|n|² >= PLANE_MIN_NORMAL2`` (elsewhere its
#: taps fail the plane test).
PLANE_MIN_NORMAL2 = 0.25


def _f32(x: float) -> float:
    """``x`` rounded to float32 (what a C++ ``float`` literal holds)."""
    return struct.unpack("f", struct.pack("f", x))[0]


#: What the native kernels hold as their own compile-time copies (``_core.reproject_constants`` must equal it).
MIRRORED_IN_CORE = {
    "COORD_MARGIN": COORD_MARGIN,
    "F32_EXACT_INT": F32_EXACT_INT,
    "MAX_CHANNELS": NATIVE_MAX_CHANNELS,
    "PLANE_BASE": _f32(PLANE_BASE),
    "PLANE_SLOPE": _f32(PLANE_SLOPE),
    "PLANE_MIN_NORMAL2": _f32(PLANE_MIN_NORMAL2),
    **{f"REASON_{r.name}": int(r) for r in Reason if r <= Reason.NONFINITE},
}
