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
