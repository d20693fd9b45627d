"""The numbers the reprojection implementations share have one home, stereorepro.reproject._constants: the native
kernels hold compile-time copies that must equal it, and the values must fit together."""

import math

import pytest

from stereorepro.reproject import _constants, _native
from stereorepro.reproject._constants import COORD_MARGIN, OFF_FRAME, TABLE_PAD, TAP_OK_CODE
from stereorepro.reproject.reason import Reason


@pytest.mark.skipif(not _native.available(), reason="stereorepro._core is not built")
def test_native_kernels_hold_the_python_constants():
    assert _native.core_constants() == _constants.MIRRORED_IN_CORE


@pytest.mark.parametrize("size", [1, 2, 37])
def test_table_border_holds_every_tap_of_a_clamped_coordinate(size):
    lo, hi = -COORD_MARGIN, size + COORD_MARGIN
    taps = [math.floor(lo - 0.5), math.floor(hi - 0.5) + 1, math.floor(lo), math.floor(hi)]  # bilinear, nearest
    assert all(-TABLE_PAD <= t <= size - 1 + TABLE_PAD for t in taps)


def test_off_frame_coordinate_reads_no_tap():
    assert math.floor(OFF_FRAME - 0.5) + 1 < 0 and math.floor(OFF_FRAME) < 0  # bilinear taps, nearest tap
    assert OFF_FRAME == -COORD_MARGIN  # the lower clamp: clamping keeps it


def test_tap_ok_code_is_above_every_tap_code():
    tap_codes = [Reason.OUT_OF_FRAME, Reason.NO_SURFACE_SRC, Reason.POSITION, Reason.NORMAL, Reason.NONFINITE]
    assert TAP_OK_CODE > max(tap_codes)
