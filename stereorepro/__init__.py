"""stereorepro: spatiotemporal sample reprojection for real-time stereoscopic path tracing.

The package is layered along the pipeline, lowest first (a module imports only from its own layer and the ones
below; ``tests/test_package.py`` holds the order and enforces it): the foundation (:mod:`~stereorepro.errors`,
:mod:`~stereorepro.camera`, checks) → :mod:`~stereorepro.io` (file formats) → :mod:`~stereorepro.scenes` →
:mod:`~stereorepro.render` → :mod:`~stereorepro.reproject` → :mod:`~stereorepro.accumulate` →
:mod:`~stereorepro.denoise` → :mod:`~stereorepro.measure` → :mod:`~stereorepro.workflows` (the application layer:
frame sequences, the experiment) → :mod:`~stereorepro.cli`. Conventions (camera axes, pixel centres, depth,
"no surface", motion) are documented once in :mod:`stereorepro.camera`.

``import stereorepro`` loads the reprojection layer only (torch and numpy); the renderer, the scenes and the EXR
frame I/O are imported on first use of their names (``stereorepro.PathTracer``, ``load_scene``, ``read_exr``).
"""

import importlib as _importlib

from ._version import __version__  # noqa: F401 (the package version, read without importing the package)

from .accumulate import EyeState, SpatiotemporalReprojection, temporal_step
from .camera import (
    DEFAULT_BASELINE,
    DEFAULT_RESOLUTION,
    Eye,
    PinholeCamera,
    StereoRig,
    Warp,
    camera_motion,
    compose_warp,
    has_surface,
    intrinsics_from_fov,
    invert_rigid,
    look_at,
    pixel_centers,
    project,
    unproject,
    world_motion_from_view_z,
)
from .denoise import (
    ReprojectionDenoiser,
    denoise_features,
    empty_history,
    empty_state,
    reproject_denoise,
    reprojection_features,
)
from .errors import (
    CameraError,
    MissingDependencyError,
    ParameterError,
    ParameterTypeError,
    SceneError,
    SequenceError,
    ShapeError,
    StereoreproError,
    UserError,
)
from .io.onnx import export_onnx
from .measure.metrics import (
    EFFECTIVE_SPP_FLAGS,
    EffectiveSppLadder,
    effective_spp,
    effective_spp_many,
    fit_ladder,
    ladder_rmse,
    mse,
    rmse,
    ssim,
    suggest_reference_spp,
)
from .measure.temporal import temporal_error
from .reproject import (
    HISTORY_ROUNDINGS,
    POSITION_TESTS,
    SAMPLINGS,
    Blend,
    FastClamp,
    FastHistoryClamp,
    fast_history_clamp,
    History,
    ReprojectionResult,
    TemporalResult,
    Thresholds,
    View,
    Reason,
    StereoReprojection,
    TemporalReprojection,
    backward_reproject,
    reason_to_rgb,
    stereo_reproject,
    temporal_blend,
    temporal_reproject,
)

#: Names loaded on first use: (module, attribute). The renderer pulls in embreex and trimesh; EXR I/O OpenEXR.
_LAZY = {
    "PathTracer": ("stereorepro.render", "PathTracer"),
    "RenderResult": ("stereorepro.render", "RenderResult"),
    "read_exr": ("stereorepro.io.exr", "read_exr"),
    "write_exr": ("stereorepro.io.exr", "write_exr"),
    "list_scenes": ("stereorepro.scenes", "list_scenes"),
    "load_scene": ("stereorepro.scenes", "load_scene"),
}

__all__ = [
    # cameras and conventions
    "DEFAULT_BASELINE",
    "DEFAULT_RESOLUTION",
    "Eye",
    "PinholeCamera",
    "StereoRig",
    "Warp",
    "camera_motion",
    "world_motion_from_view_z",
    "compose_warp",
    "has_surface",
    "intrinsics_from_fov",
    "invert_rigid",
    "look_at",
    "pixel_centers",
    "project",
    "unproject",
    # the data model of the ops: G-buffer views, settings, named results
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
    # reprojection ops and modules
    "Reason",
    "StereoReprojection",
    "TemporalReprojection",
    "backward_reproject",
    "reason_to_rgb",
    "stereo_reproject",
    "temporal_blend",
    "temporal_reproject",
    "fast_history_clamp",
    "FastHistoryClamp",
    "export_onnx",
    # accumulation over a sequence
    "SpatiotemporalReprojection",
    "EyeState",
    "temporal_step",
    # a learned denoiser and its reprojection in one graph
    "ReprojectionDenoiser",
    "reproject_denoise",
    "reprojection_features",
    "denoise_features",
    "empty_history",
    "empty_state",
    # metrics
    "EFFECTIVE_SPP_FLAGS",
    "EffectiveSppLadder",
    "effective_spp",
    "effective_spp_many",
    "fit_ladder",
    "ladder_rmse",
    "mse",
    "rmse",
    "ssim",
    "suggest_reference_spp",
    "temporal_error",
    # errors
    "StereoreproError",
    "ParameterError",
    "ParameterTypeError",
    "ShapeError",
    "CameraError",
    "SceneError",
    "SequenceError",
    "UserError",
    "MissingDependencyError",
    # loaded on first use
    *_LAZY,
]


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(_importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'stereorepro' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
