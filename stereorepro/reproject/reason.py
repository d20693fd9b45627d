"""Discard reasons of the reprojection (the uint8 ``reason`` map) and the paper's Figure 1 colours."""

from __future__ import annotations

import enum

import torch
from torch import Tensor

from .._checks import check_shape

__all__ = ["Reason", "REASON_COLORS", "reason_to_rgb"]


class Reason(enum.IntEnum):
    """Why a destination pixel was discarded (values of the uint8 ``reason`` map).

    Examples:
        >>> from stereorepro.reproject import Reason
        >>> Reason(5), int(Reason.NORMAL), Reason.OUT_OF_FRAME.name
        (<Reason.POSITION: 5>, 6, 'OUT_OF_FRAME')
    """

    KEPT = 0
    NO_SURFACE_DST = 1  #: the destination pixel has no surface: nothing to reproject
    BEHIND_CAMERA = 2  #: the destination point is not in front of the source camera
    OUT_OF_FRAME = 3  #: the tap lies outside the source image
    NO_SURFACE_SRC = 4  #: the source tap has no surface
    POSITION = 5  #: |P_src − P_dst| > position_threshold (occlusion / disocclusion)
    NORMAL = 6  #: |N_src − N_dst| > normal_threshold
    NONFINITE = 7  #: the source tap's values are NaN or Inf
    NO_HISTORY = 8  #: no previous frame to reproject from (first frame of an accumulation)


#: Figure 1 colours (RGB in [0, 1]) by reason: green = position, cyan = normal, red = out of frame.
REASON_COLORS = {
    Reason.KEPT: (0.0, 0.0, 0.0),
    Reason.NO_SURFACE_DST: (0.25, 0.25, 0.25),
    Reason.BEHIND_CAMERA: (1.0, 0.0, 1.0),
    Reason.OUT_OF_FRAME: (1.0, 0.0, 0.0),
    Reason.NO_SURFACE_SRC: (0.0, 0.0, 1.0),
    Reason.POSITION: (0.0, 1.0, 0.0),
    Reason.NORMAL: (0.0, 1.0, 1.0),
    Reason.NONFINITE: (1.0, 1.0, 0.0),
    Reason.NO_HISTORY: (1.0, 1.0, 1.0),
}


def reason_to_rgb(reason: Tensor) -> Tensor:
    """Colour a reason map like the paper's Figure 1 (green position, cyan normal, red out of frame).

    Args:
        reason: (B, 1, H, W) uint8 :class:`Reason` codes.

    Returns:
        (B, 3, H, W) float32 RGB in [0, 1].

    Examples:
        >>> import torch
        >>> from stereorepro.reproject import Reason, reason_to_rgb
        >>> codes = [Reason.KEPT, Reason.OUT_OF_FRAME, Reason.POSITION, Reason.NORMAL]
        >>> rgb = reason_to_rgb(torch.tensor(codes, dtype=torch.uint8).reshape(1, 1, 1, 4))
        >>> tuple(rgb.shape), rgb[0, :, 0].T.tolist()  # black, red, green, cyan
        ((1, 3, 1, 4), [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 1.0]])
    """
    check_shape(reason, ["B", "1", "H", "W"], "reason")
    lut = torch.tensor(
        [REASON_COLORS[Reason(i)] for i in range(len(Reason))], dtype=torch.float32, device=reason.device
    )  # Rx3
    rgb = lut[reason[:, 0].long().clamp(0, len(Reason) - 1)]  # BxHxWx3
    return rgb.permute(0, 3, 1, 2).contiguous()
