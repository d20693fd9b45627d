"""stereorepro: spatiotemporal sample reprojection for real-time stereoscopic path tracing.

Conventions (camera axes, pixel centres, depth, "no surface") are documented once in
:mod:`stereorepro.camera`.
"""

__version__ = "0.1.0"

from .camera import (  # noqa: F401
    PinholeCamera,
    StereoRig,
    has_surface,
    intrinsics_from_fov,
    invert_rigid,
    look_at,
    pixel_centers,
    project,
    unproject,
)
from .reproject import (  # noqa: F401
    Reason,
    StereoReprojection,
    TemporalReprojection,
    backward_reproject,
    reason_to_rgb,
    stereo_reproject,
    temporal_blend,
    temporal_reproject,
)
from .onnx_export import export_onnx  # noqa: F401

# --- metrics (stereorepro/metrics.py): image errors and effective spp ---
from .metrics import (  # noqa: F401
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
# --- end metrics ---
from .pipeline import SpatiotemporalReprojection  # noqa: F401
# --- render (path tracer, scenes, EXR frames) ---
from .render import PathTracer, RenderResult, read_exr, write_exr  # noqa: F401,E402
from .scenes import list_scenes, load_scene  # noqa: F401,E402
# --- end render ---
