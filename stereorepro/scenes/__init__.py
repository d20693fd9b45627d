"""Scenes: declarative scene files (the built-in ones ship in ``stereorepro/scenes/builtin``), their loader, the
built-in procedural geometry, and the one rule for reprojection thresholds against image resolution
(:func:`threshold_scale`, :meth:`Scene.thresholds`).
"""

from .loader import (
    BUILTIN_SCENES,
    EXTERNAL_SCENES,
    KNOWN_EFFECTS,
    SCENES_ENV,
    SHARED_ENV,
    THRESHOLD_ROWS,
    Scene,
    SceneError,
    SceneGeometry,
    catmull_rom,
    expand_path,
    list_scenes,
    load_scene,
    scenes_dir,
    shared_scenes_dir,
    threshold_scale,
)

__all__ = [
    "Scene",
    "SceneError",
    "SceneGeometry",
    "list_scenes",
    "load_scene",
    "scenes_dir",
    "shared_scenes_dir",
    "KNOWN_EFFECTS",
    "BUILTIN_SCENES",
    "EXTERNAL_SCENES",
    "SCENES_ENV",
    "SHARED_ENV",
    "THRESHOLD_ROWS",
    "threshold_scale",
    "catmull_rom",
    "expand_path",
]
