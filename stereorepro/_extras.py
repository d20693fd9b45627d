"""Optional dependencies: which extra brings each one, and the one way the package imports them.

``pip install stereorepro`` installs what the reprojection ops need (torch, numpy). The rest comes with extras,
grouped by use (pyproject.toml lists them):

======================  ==============================================  =========================================
extra                   packages                                        for
======================  ==============================================  =========================================
``render``              embreex, trimesh, tqdm                          the path tracer, meshes of the shared scenes
``exr``                 OpenEXR                                         EXR frame files (read and write)
``experiment``          render + exr + matplotlib, tqdm, kornia,        the paper's experiment, ``stereorepro demo``,
                        flip-evaluator                                  SSIM and FLIP scores
``onnx``                onnx, onnxscript, onnxruntime                   ONNX export and its parity checks
``mitsuba``             mitsuba                                         frames rendered by Mitsuba 3
``oidn``                pyoidn                                          Intel Open Image Denoise examples
``distributed``         dask[distributed]                               ``stereorepro experiment --scheduler``
``all``                 every extra above
======================  ==============================================  =========================================

Code that needs one of these imports it through :func:`require` where it is first used (never at the top of a
module the ops import), so ``import stereorepro`` works without any of them and a missing one is one
:class:`~stereorepro.errors.MissingDependencyError` naming the extra to install.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from .errors import MissingDependencyError

__all__ = ["EXTRAS", "available", "require", "require_all"]

#: Top-level module -> (the distribution pip installs, the extra that brings it).
EXTRAS: dict[str, tuple[str, str]] = {
    "embreex": ("embreex", "render"),
    "trimesh": ("trimesh", "render"),
    "tqdm": ("tqdm", "render"),
    "OpenEXR": ("OpenEXR", "exr"),
    "matplotlib": ("matplotlib", "experiment"),
    "kornia": ("kornia", "experiment"),
    "flip_evaluator": ("flip-evaluator", "experiment"),
    "onnx": ("onnx", "onnx"),
    "onnxscript": ("onnxscript", "onnx"),
    "onnxruntime": ("onnxruntime", "onnx"),
    "mitsuba": ("mitsuba", "mitsuba"),
    "pyoidn": ("pyoidn", "oidn"),
    "dask": ("dask[distributed]", "distributed"),
    "distributed": ("dask[distributed]", "distributed"),
}


def require(module: str, feature: str, extra: str | None = None) -> ModuleType:
    """Import the optional ``module`` (a dotted name; its top-level package must be in :data:`EXTRAS`).

    Args:
        module: e.g. ``"embreex.rtcore_scene"``.
        feature: what needs it, for the message (e.g. ``"the path tracer"``).
        extra: the extra to name in the message, when the feature's own extra is a larger one than the package's
            (the experiment's progress bars: ``"experiment"``); default: the package's extra in :data:`EXTRAS`.

    Raises:
        MissingDependencyError: the package is not installed (an ImportError from inside an installed package,
            a broken install, propagates unchanged).
    """
    top = module.partition(".")[0]
    dist, own_extra = EXTRAS[top]
    try:
        return importlib.import_module(module)
    except ImportError as e:
        if e.name is None or e.name.partition(".")[0] != top:
            raise
        extra = extra or own_extra
        raise MissingDependencyError(
            f"{feature} needs {dist}, which is not installed: pip install 'stereorepro[{extra}]' "
            f"(or pip install '{dist}')",
            name=module,
            extra=extra,
        ) from e


def available(module: str) -> bool:
    """True when the optional ``module``'s top-level package is installed (found without importing it)."""
    return importlib.util.find_spec(module.partition(".")[0]) is not None


def require_all(modules: list[str], feature: str, extra: str) -> None:
    """Check, before a long run starts, that every optional module of ``modules`` is installed.

    Raises:
        MissingDependencyError: one error naming every missing package and ``extra``, which brings them all.
    """
    missing = [m for m in modules if not available(m)]
    if missing:
        dists = ", ".join(EXTRAS[m.partition(".")[0]][0] for m in missing)
        raise MissingDependencyError(
            f"{feature} needs {dists}, not installed: pip install 'stereorepro[{extra}]'", name=missing[0], extra=extra
        )
