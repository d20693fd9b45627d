"""Diagnosis of convention mistakes in a frame sequence (:mod:`stereorepro.io.frames`), before it is reprojected.

The usual mistakes when frames come from another renderer do not fail: they give many discards and a result
that still looks plausible. Each leaves a signature: the position test fails on a large share of the surface
pixels, and *undoing the mistake* makes it pass. So for a few frame pairs (stereo: right → left of one frame;
temporal: one eye's previous → current frame) the share of surface pixels failing the position test is measured
as given and under each hypothesis:

* ``swapped`` (stereo): the left and right images exchanged against their cameras;
* ``inverted``: ``world_from_cam`` given as ``cam_from_world``;
* ``axes``: camera axes x left / y up (Mitsuba's camera frame, an OpenGL view matrix with z negated) instead of
  OpenCV's x right, y down, z forward: ``diag(-1, -1, 1) · cam_from_world`` (a mirror, det −1, is rejected
  outright when the cameras are read);
* ``ray_length``: ``Z`` holding the distance along the ray instead of the camera-space z (nearly invisible to the
  same-instant stereo test at a small baseline; visible to the temporal one when the camera turns).

A warning is raised when the share as given exceeds :data:`POSITION_SHARE_WARN` and a hypothesis at least halves
it (the message names that mistake), or when it exceeds :data:`POSITION_SHARE_ALARM` whatever the hypotheses give.
Calibration (our tracer's frames, built-in scenes, 32×18 to 96×54): correct sequences fail the position test on
≤ 4.2 % of the pixels in stereo (Classroom's chairs and blinds) and ≤ 4.0 % in temporal, and no hypothesis
improves on them; the mistakes above give 4–9.5 % (stereo) and 7.5–28 % (temporal), and undoing them gives
≤ 0.8 % / ≤ 3 %.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from ..camera import has_surface
from ..io.frames import Frame, FrameSequence, read_frame
from ..reproject import Reason, Thresholds, View
from ..reproject.functional import warp_values

__all__ = ["diagnose_conventions", "HYPOTHESES", "POSITION_SHARE_WARN", "POSITION_SHARE_ALARM"]

#: Share of surface pixels failing the position test above which the hypotheses are tried.
POSITION_SHARE_WARN = 0.02
#: Share above which a warning is given even when no hypothesis explains it.
POSITION_SHARE_ALARM = 0.15

HYPOTHESES = {
    "swapped": "the left and right images look swapped against their cameras (left.exr holds the right eye)",
    "inverted": "cam_from_world looks inverted (world_from_cam given: the camera-to-world pose instead of the "
    "world-to-camera transform)",
    "axes": "the camera axes look flipped (x left / y up, as Mitsuba's camera frame or an OpenGL view matrix; "
    "ours are OpenCV's: x right, y down, z forward)",
    "ray_length": "Z looks like the distance along the ray, not the camera-space z",
}


def _variant(frame: Frame, hypothesis: str | None) -> Frame:
    if hypothesis == "inverted":
        return replace(frame, cam_from_world=torch.linalg.inv(frame.cam_from_world.double()))
    if hypothesis == "axes":
        flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64))
        return replace(frame, cam_from_world=flip @ frame.cam_from_world.double())
    if hypothesis == "ray_length":
        K = frame.K[0].double()
        H, W = frame.depth.shape[-2:]
        v, u = torch.meshgrid(
            torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij"
        )
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
        return replace(frame, depth=(frame.depth.double() / torch.sqrt(1 + x * x + y * y)).to(frame.depth.dtype))
    return frame


def _position_share(src: Frame, dst: Frame, pos: float, nrm: float, sampling: str) -> float:
    def view(f: Frame) -> View:
        return View.unchecked(f.depth, f.normal, f.K, f.cam_from_world)

    reason = warp_values(src.color, view(src), view(dst), Thresholds(pos, nrm), sampling, confidence=False).reason
    surf = has_surface(dst.depth)
    n = int(surf.sum())
    return float(((reason == int(Reason.POSITION)) & surf).sum()) / n if n else 0.0


def diagnose_conventions(
    seq: FrameSequence,
    mode: str,
    eyes: tuple[str, ...],
    pos: float,
    nrm: float,
    sampling: str = "bilinear",
    device=None,
) -> list[dict]:
    """Warnings for likely convention mistakes (see the module docstring), from up to two frame pairs per test.

    Returns:
        a list of ``{"test": "stereo" | "temporal", "position_pct": given, "suspect": the best hypothesis or None,
        "suspects": those that explain it about as well, "position_pct_if_fixed": float or None, "message": str}``;
        empty when nothing looks wrong.

    Examples:
        >>> import os, tempfile
        >>> from stereorepro.workflows.export import export_sequence
        >>> tmp = tempfile.TemporaryDirectory()
        >>> src = export_sequence("living_room", 2, 8, 6, os.path.join(tmp.name, "in"))  # 2 frames of 8x6, 1 spp
        >>> from stereorepro.io.frames import load_sequence
        >>> from stereorepro.workflows.diagnose import diagnose_conventions
        >>> seq = load_sequence(src)
        >>> diagnose_conventions(seq, "both", ("right",), seq.position_threshold, seq.normal_threshold)
        []
        >>> tmp.cleanup()
    """
    n = len(seq)
    frames = sorted({min(1, n - 1), n // 2})
    tests = []
    if mode in ("stereo", "both"):
        tests.append(("stereo", [(("right", i), ("left", i)) for i in frames], ("swapped", "inverted", "axes")))
    if mode in ("temporal", "both") and n > 1:
        pairs = [((e, i - 1), (e, i)) for e in eyes for i in frames if i >= 1]
        tests.append(("temporal", pairs, ("inverted", "axes", "ray_length")))
    cache: dict = {}

    def load(eye: str, i: int) -> Frame:
        if (eye, i) not in cache:
            cache[(eye, i)] = read_frame(seq, i, eye, device)
        return cache[(eye, i)]

    out = []
    with torch.no_grad():
        for test, pairs, hypotheses in tests:

            def share(h):
                vals = []
                for (se, si), (de, di) in pairs:
                    src, dst = load(se, si), load(de, di)
                    if h == "swapped":  # exchange the images, keep each eye's camera
                        src = replace(load(de, di), K=src.K, cam_from_world=src.cam_from_world)
                        dst = replace(load(se, si), K=dst.K, cam_from_world=dst.cam_from_world)
                    vals.append(_position_share(_variant(src, h), _variant(dst, h), pos, nrm, sampling))
                return float(np.mean(vals))

            given = share(None)
            if given <= POSITION_SHARE_WARN:
                continue
            tried = {h: share(h) for h in hypotheses}
            best = min(tried, key=tried.get)
            pct = 100.0 * given
            if tried[best] <= given / 2:
                # hypotheses that explain it about as well (in stereo, a translated rig with inverted cameras is
                # the same as swapped eyes; the temporal test tells them apart)
                alike = [h for h in hypotheses if tried[h] <= given / 2 and tried[h] <= 1.5 * tried[best] + 0.002]
                alike.sort(key=tried.get)
                out.append(
                    {
                        "test": test,
                        "position_pct": pct,
                        "suspect": best,
                        "suspects": alike,
                        "position_pct_if_fixed": 100.0 * tried[best],
                        "position_pct_by_hypothesis": {h: 100.0 * v for h, v in tried.items()},
                        "message": f"{test}: {pct:.1f} % of the surface pixels fail the position test; "
                        + "; or ".join(HYPOTHESES[h] for h in alike)
                        + f": undoing that gives {100.0 * tried[best]:.1f} %",
                    }
                )
            elif given > POSITION_SHARE_ALARM:
                out.append(
                    {
                        "test": test,
                        "position_pct": pct,
                        "suspect": None,
                        "suspects": [],
                        "position_pct_if_fixed": None,
                        "position_pct_by_hypothesis": {h: 100.0 * v for h, v in tried.items()},
                        "message": f"{test}: {pct:.1f} % of the surface pixels fail the position test: check "
                        "the conventions (cam_from_world, OpenCV axes, Z = camera z, eye order; "
                        "docs/conventions.md) and the thresholds",
                    }
                )
    stereo = [w for w in out if w["test"] == "stereo" and w["suspects"]]
    if stereo and mode == "both" and not any(w["test"] == "temporal" for w in out) and n > 1:
        # the cameras are consistent over time, so the stereo failure is between the eyes: their order
        w = stereo[0]
        w["suspects"], w["suspect"] = ["swapped"], "swapped"
        w["position_pct_if_fixed"] = w["position_pct_by_hypothesis"]["swapped"]
        w["message"] = (
            f"stereo: {w['position_pct']:.1f} % of the surface pixels fail the position test while the "
            f"temporal test passes; {HYPOTHESES['swapped']}: swapping them gives "
            f"{w['position_pct_if_fixed']:.1f} %"
        )
    return out
