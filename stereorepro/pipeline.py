"""Former home of the combined scheme (kept importable): see :mod:`stereorepro.accumulate`."""

from .accumulate import EyeState, SpatiotemporalReprojection, temporal_step  # noqa: F401

__all__ = ["SpatiotemporalReprojection", "EyeState", "temporal_step"]
