"""Backward reprojection with discard masks (paper §4.1), stereo and temporal: pure tensor functions first
(:mod:`.functional`), nn.Modules that store their configuration and call them (:mod:`.modules`).

Implementations behind one backend rule (:func:`select_backend`): the torch reference (``_general``: the
differentiable, exportable definition; ``_fast``: its inference fast path with identical outputs) and the native
kernels (``_native``, a leaf over ``stereorepro._core``).
"""

from .functional import (
    BACKENDS,
    backward_reproject,
    native_unsupported,
    select_backend,
    stereo_reproject,
    temporal_blend,
    temporal_reproject,
)
from ._general import SOFT_DEN_FLOOR
from .modules import StereoReprojection, TemporalReprojection
from .clamp import fast_history_clamp
from .modules import FastHistoryClamp
from .reason import REASON_COLORS, Reason, reason_to_rgb
from .._checks import SAMPLINGS
from .view import (
    HISTORY_ROUNDINGS,
    POSITION_TESTS,
    Blend,
    FastClamp,
    History,
    ReprojectionResult,
    TemporalResult,
    Thresholds,
    View,
)

__all__ = [
    "View",
    "Thresholds",
    "Blend",
    "FastClamp",
    "History",
    "ReprojectionResult",
    "TemporalResult",
    "SAMPLINGS",
    "POSITION_TESTS",
    "HISTORY_ROUNDINGS",
    "Reason",
    "REASON_COLORS",
    "SOFT_DEN_FLOOR",
    "BACKENDS",
    "backward_reproject",
    "stereo_reproject",
    "temporal_blend",
    "temporal_reproject",
    "reason_to_rgb",
    "select_backend",
    "native_unsupported",
    "StereoReprojection",
    "TemporalReprojection",
    "fast_history_clamp",
    "FastHistoryClamp",
]
