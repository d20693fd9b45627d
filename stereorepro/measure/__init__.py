"""Measurement: image metrics and effective spp (:mod:`.metrics`), and the paper's experiment
(:mod:`.experiment`: renders, schemes, tables, figures)."""

from .metrics import (EFFECTIVE_SPP_FLAGS, EffectiveSppLadder, effective_spp, effective_spp_many, fit_ladder,
                      ladder_rmse, mse, rmse, ssim, suggest_reference_spp)

__all__ = ["EFFECTIVE_SPP_FLAGS", "EffectiveSppLadder", "effective_spp", "effective_spp_many", "fit_ladder",
           "ladder_rmse", "mse", "rmse", "ssim", "suggest_reference_spp"]
