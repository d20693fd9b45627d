"""Measurement: image metrics and effective spp (:mod:`.metrics`), temporal stability (:mod:`.temporal`), where an
image's error lives (:mod:`.anatomy`).
The paper's experiment, which drives them, is in the application layer (:mod:`stereorepro.workflows.experiment`)."""

from .metrics import (
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
from .temporal import TEMPORAL_TONEMAPS, temporal_error

__all__ = [
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
    "TEMPORAL_TONEMAPS",
    "temporal_error",
]
