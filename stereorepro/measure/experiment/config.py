"""Settings of an experiment run and the schemes it measures."""

from __future__ import annotations

from dataclasses import dataclass

from ...scenes import THRESHOLD_ROWS

__all__ = ["REFERENCE_OFFSET", "THRESHOLD_ROWS", "LEFT", "RIGHT", "Scheme", "SCHEMES", "ExperimentConfig", "schemes"]

#: First sample index of reference renders (ladders use 0..L-1: disjoint streams).
REFERENCE_OFFSET = 1 << 24
LEFT, RIGHT = 0, 1


@dataclass(frozen=True)
class Scheme:
    name: str
    stereo: bool
    temporal: bool
    eye: int  # evaluated eye
    sampling: str = "bilinear"
    alpha: float = 0.2
    paper: bool = False  # one of the paper's three Table 2 columns


SCHEMES = (
    Scheme("stereo", True, False, LEFT, paper=True),
    Scheme("temporal", False, True, RIGHT, paper=True),
    Scheme("stereo_temporal", True, True, LEFT, paper=True),
    Scheme("stereo_nearest", True, False, LEFT, "nearest"),
    Scheme("temporal_nearest", False, True, RIGHT, "nearest"),
    Scheme("stereo_temporal_nearest", True, True, LEFT, "nearest"),
)


@dataclass(frozen=True)
class ExperimentConfig:
    """Settings of one experiment run (see ``stereorepro experiment --help``)."""

    scene: str
    out: str
    frames: int | None = None  #: None = the scene's own frame count
    width: int = 320
    height: int = 180
    reference_spp: int = 256
    ladder_spp: int = 16
    seed: int = 0
    alphas: tuple[float, ...] = (0.1, 0.5)  #: extra EMA weights measured beside the paper's 0.2
    threshold_scale: float | None = None  #: None = auto: stereorepro.scenes.threshold_scale(height)
    workers: int | None = None
    exr: bool = False
    force: bool = False
    progress: bool = True
    cache_dir: str | None = None  #: default: <out>/cache
    #: Renderer version used in cache keys; None = a hash of the current renderer sources. Set it to a run's
    #: recorded ``code`` to re-analyse that run's cached renders after the renderer changed (no re-rendering).
    renderer_version: str | None = None
    #: ``"hdr"``: RMSE of linear radiance; ``"ldr"``: RMSE after clamping to [0, 1] (display-referred), applied alike
    #: to the method's images, the ladder and the reference.
    metric: str = "ldr"


def schemes(cfg: ExperimentConfig) -> list[Scheme]:
    """The paper's schemes and the variants, with an alpha variant for each extra ``cfg.alphas`` weight."""
    out = list(SCHEMES)
    for a in cfg.alphas:
        if abs(a - 0.2) > 1e-12:
            out.append(Scheme(f"temporal_alpha{a:g}", False, True, RIGHT, alpha=a))
            out.append(Scheme(f"stereo_temporal_alpha{a:g}", True, True, LEFT, alpha=a))
    return out
