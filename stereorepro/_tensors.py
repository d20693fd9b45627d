"""Small tensor helpers every layer uses: the compute dtype rule, scalars as 0-d tensors, non-finite to zero."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["compute_dtype", "as_scalar", "finite_or_zero"]


def compute_dtype(*tensors: Tensor) -> torch.dtype:
    """The dtype the ops compute in: float64 if any input is float64, else float32 (float16 / bfloat16 widen)."""
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def as_scalar(x, like: Tensor) -> Tensor:
    """A number or one-element tensor as a 0-d tensor of ``like``'s dtype and device (tensors keep their graph)."""
    if isinstance(x, Tensor):
        return x.to(device=like.device, dtype=like.dtype).reshape(())
    return torch.full((), float(x), device=like.device, dtype=like.dtype)


def finite_or_zero(x: Tensor) -> Tensor:
    """``x`` with NaN and ±inf replaced by 0."""
    return torch.where(torch.isfinite(x), x, torch.zeros((), dtype=x.dtype, device=x.device))
