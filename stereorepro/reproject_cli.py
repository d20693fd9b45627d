"""Former home of the frame-sequence format and ``reproject`` (kept importable): see :mod:`stereorepro.io.frames`,
:mod:`stereorepro.io.sequence` and :mod:`stereorepro.cli.reproject`."""

from .cli.reproject import register  # noqa: F401
from .errors import SequenceError  # noqa: F401
from .io.frames import (EYES, REQUIRED_CHANNELS, EyeCamera, FrameSequence, export_sequence,  # noqa: F401
                        load_sequence, read_frame)
from .io.sequence import MODES, NO_HISTORY, reproject_sequence  # noqa: F401

__all__ = ["REQUIRED_CHANNELS", "NO_HISTORY", "SequenceError", "EyeCamera", "FrameSequence", "load_sequence",
           "read_frame", "reproject_sequence", "export_sequence", "register"]
