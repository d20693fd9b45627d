"""Blender (Cycles) frames in our conventions, converted here and nowhere else.

:func:`write_cameras` runs inside Blender's Python (or ``bpy``, ``pip install bpy``) and writes our
``cameras.json`` for both eyes of a multiview (stereo 3D) camera; :func:`frame_from_channels` converts the channels
of Blender's own multilayer EXRs (one part per pass) when ``stereorepro reproject --from blender`` reads them.

Blender's conventions, and what we do with them:

* **Camera frame**: x right, y up, z backward (the camera looks along −z). Ours is OpenCV's (x right, y down, z
  forward): ``cam_from_world = diag(1, −1, −1, 1) · inv(matrix_world_eye)``.
* **Stereo eyes**: offset along the camera's x axis by the interocular distance, from the camera as the stereo
  ``pivot`` says (``LEFT``: the camera is the left eye, Blender's default; ``CENTER``: ±IOD/2; ``RIGHT``).
  ``PARALLEL`` and ``OFFAXIS`` convergence are supported; ``OFFAXIS`` shifts each eye's principal point so that a
  point at the convergence distance straight ahead of the *camera* (the pivot, not the rig's centre) is at the
  image centre of both eyes, ``cx = W/2 + f · x_eye / convergence_distance`` (measured against Cycles' Position
  pass for pivots LEFT and CENTER);
  ``TOE`` (toe-in) is refused.
* **Intrinsics**: ``fx = fy = lens / sensor · W`` (horizontal fit; the vertical fit uses ``H``; ``AUTO`` fits the
  larger image side to ``sensor_width``), principal point at the image centre; lens shift is refused.
* **Passes**: ``Depth`` is the camera-space z, ``1e10`` where nothing is hit; ``Normal`` is world space, averaged
  over the pixel's samples (not unit at edges: the reader renormalises it), ``0`` where nothing is hit; ``Vector``
  XY is previous − current in pixels with **y up**: our ``motion = (X, −Y)``. Blender has no world-space motion, so
  moving objects still fail the position test (static geometry is warped as exactly as with the cameras).
* **Inside Blender**, whose Python has no torch, load this file by path (it then needs only numpy)::

      import importlib.util
      spec = importlib.util.spec_from_file_location("stereorepro_blender", "/path/to/stereorepro/io/blender.py")
      blender = importlib.util.module_from_spec(spec); spec.loader.exec_module(blender)
      blender.write_cameras("/path/to/frames/cameras.json")

* **Files**: Blender 5 needs ``image_settings.media_type = 'MULTI_LAYER_IMAGE'`` before ``file_format =
  'OPEN_EXR_MULTILAYER'``; with ``render.filepath = "DIR/"`` stereo frames are ``DIR/{frame:04d}_L.exr`` and
  ``_R.exr``. Turn the denoiser off (``cycles.use_denoising = False``) to keep 1-spp samples unbiased.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
from pathlib import Path

import numpy as np

__all__ = [
    "FLIP",
    "BLENDER_CHANNELS",
    "BACKGROUND_DEPTH",
    "FILE_RE",
    "eye_camera",
    "write_cameras",
    "frame_from_channels",
    "layer_prefix",
    "file_name",
]

#: Blender's camera axes (y up, z backward) to OpenCV's (y down, z forward).
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
#: Channels of a Blender view layer the conversion reads (layer name first, as Blender writes them).
BLENDER_CHANNELS = ("Combined.R", "Combined.G", "Combined.B", "Depth.Z", "Normal.X", "Normal.Y", "Normal.Z")
#: Depths at or beyond this are Blender's background (it writes 1e10).
BACKGROUND_DEPTH = 1e9
#: Blender's stereo frame file names (:func:`file_name`): frame number and eye letter.
FILE_RE = re.compile(r"^(\d{4,})_([LR])\.exr$")


def _atomic_write(path, text: str) -> None:
    """The package's one atomic write; loaded by path when this file was (inside Blender, without the package)."""
    try:
        from .atomic import atomic_write
    except ImportError:
        spec = importlib.util.spec_from_file_location("_stereorepro_atomic", Path(__file__).with_name("atomic.py"))
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        atomic_write = mod.atomic_write
    atomic_write(path, text)


def file_name(frame_number: int, eye: str) -> str:
    """Blender's stereo output name for ``render.filepath = "DIR/"``: ``0001_L.exr``.

    Examples:
        >>> from stereorepro.io.blender import file_name
        >>> file_name(1, "left"), file_name(12, "right")
        ('0001_L.exr', '0012_R.exr')
    """
    return f"{int(frame_number):04d}_{'L' if eye == 'left' else 'R'}.exr"


def eye_camera(camera_object, scene, eye: str) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), cam_from_world (4, 4)) float64, ours (OpenCV), of one eye of a Blender camera at the scene's
    current frame. Works for a mono camera too (``eye`` then only matters with multiview on).

    Examples:
        >>> import types
        >>> import numpy as np
        >>> from stereorepro.io.blender import eye_camera
        >>> data = types.SimpleNamespace(type="PERSP", shift_x=0, shift_y=0, sensor_fit="HORIZONTAL", sensor_width=36.0,
        ...                              lens=18.0)  # stand-ins for Blender's camera object and scene
        >>> camera = types.SimpleNamespace(name="Camera", data=data, matrix_world=np.eye(4))
        >>> render = types.SimpleNamespace(pixel_aspect_x=1, pixel_aspect_y=1, resolution_x=4, resolution_y=2,
        ...                                resolution_percentage=100, use_multiview=False)
        >>> K, cam_from_world = eye_camera(camera, types.SimpleNamespace(render=render), "left")
        >>> K.tolist(), np.diag(cam_from_world).tolist()  # f = 18 / 36 * 4 pixels; y and z flipped
        ([[2.0, 0.0, 2.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]], [1.0, -1.0, -1.0, 1.0])
    """
    cam = camera_object.data
    if cam.type != "PERSP":
        raise ValueError(f"write_cameras: camera {camera_object.name!r} is {cam.type}, expected PERSP")
    if cam.shift_x != 0 or cam.shift_y != 0:
        raise ValueError(f"write_cameras: camera {camera_object.name!r} has a lens shift; not supported")
    r = scene.render
    if r.pixel_aspect_x != r.pixel_aspect_y:
        raise ValueError("write_cameras: non-square pixels (pixel_aspect_x != pixel_aspect_y) are not supported")
    W = int(round(r.resolution_x * r.resolution_percentage / 100))
    H = int(round(r.resolution_y * r.resolution_percentage / 100))
    fit = cam.sensor_fit
    if fit == "AUTO":
        fit, sensor = ("HORIZONTAL", cam.sensor_width) if W >= H else ("VERTICAL", cam.sensor_width)
    else:
        sensor = cam.sensor_width if fit == "HORIZONTAL" else cam.sensor_height
    f = cam.lens / sensor * (W if fit == "HORIZONTAL" else H)
    cx = W / 2.0
    world = np.array(camera_object.matrix_world, dtype=np.float64)
    stereo = r.use_multiview and r.views_format == "STEREO_3D"
    if stereo:
        st = cam.stereo
        iod = float(st.interocular_distance)
        x = {
            "LEFT": {"left": 0.0, "right": iod},
            "RIGHT": {"left": -iod, "right": 0.0},
            "CENTER": {"left": -iod / 2, "right": iod / 2},
        }[st.pivot][eye]
        if st.convergence_mode == "TOE":
            raise ValueError("write_cameras: toe-in stereo is not supported (use PARALLEL or OFFAXIS)")
        if st.convergence_mode == "OFFAXIS":  # a point at the convergence distance ahead of the camera -> centre
            cx = W / 2.0 + f * x / float(st.convergence_distance)
        offset = np.eye(4)
        offset[0, 3] = x
        world = world @ offset
    K = np.array([[f, 0.0, cx], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    return K, FLIP @ np.linalg.inv(world)


def write_cameras(
    path, scene=None, frames=None, position_threshold: float | None = None, normal_threshold: float | None = None
) -> Path:
    """Write our ``cameras.json`` for both eyes of the scene's camera at ``frames`` (default: frame_start ..
    frame_end), with ``meta.frame_numbers`` so that ``stereorepro reproject --from blender`` finds Blender's
    ``{frame:04d}_L.exr`` / ``_R.exr``. Runs where ``bpy`` imports (Blender's Python, or ``pip install bpy``).

    Returns:
        the path written (atomically).

    Examples:
        >>> import json, sys, tempfile, types
        >>> from unittest import mock
        >>> import numpy as np
        >>> from stereorepro.io.blender import write_cameras
        >>> data = types.SimpleNamespace(type="PERSP", shift_x=0, shift_y=0, sensor_fit="HORIZONTAL", sensor_width=36.0,
        ...                              lens=18.0)  # stand-ins for Blender's camera and scene
        >>> render = types.SimpleNamespace(pixel_aspect_x=1, pixel_aspect_y=1, resolution_x=4, resolution_y=2,
        ...                                resolution_percentage=100, use_multiview=False)
        >>> camera = types.SimpleNamespace(name="Camera", data=data, matrix_world=np.eye(4))
        >>> scene = types.SimpleNamespace(camera=camera, render=render, frame_start=1, frame_end=2, frame_current=1,
        ...                               frame_set=lambda frame: None)
        >>> with tempfile.TemporaryDirectory() as d, mock.patch.dict(sys.modules, bpy=types.ModuleType("bpy")):
        ...     path = write_cameras(f"{d}/cameras.json", scene)  # bpy imports; the scene is the one given
        ...     doc = json.loads(path.read_text())
        >>> len(doc["frames"]), sorted(doc["frames"][0]), doc["meta"]["frame_numbers"]
        (2, ['left', 'right'], [1, 2])
    """
    import bpy

    scene = bpy.context.scene if scene is None else scene
    if scene.camera is None:
        raise ValueError("write_cameras: the scene has no camera")
    frames = list(range(scene.frame_start, scene.frame_end + 1)) if frames is None else [int(f) for f in frames]
    current = scene.frame_current
    records = []
    try:
        for fr in frames:
            scene.frame_set(fr)
            rec = {}
            for eye in ("left", "right"):
                K, T = eye_camera(scene.camera, scene, eye)
                rec[eye] = {"K": K.tolist(), "cam_from_world": T.tolist()}
            records.append(rec)
    finally:
        scene.frame_set(current)
    doc = {"frames": records, "meta": {"writer": "stereorepro.io.blender.write_cameras", "frame_numbers": frames}}
    rep = {
        k: v
        for k, v in (("position_threshold", position_threshold), ("normal_threshold", normal_threshold))
        if v is not None
    }
    if rep:
        doc["reprojection"] = rep
    _atomic_write(path, json.dumps(doc, indent=1))
    return Path(path)


def layer_prefix(names, where: str = "") -> str:
    """The view-layer prefix (``"ViewLayer."``) of a Blender multilayer EXR's channel names, checked: one view
    layer with a Depth pass and every channel of :data:`BLENDER_CHANNELS`.

    Raises:
        SequenceError: no view-layer prefix (not a multilayer EXR), none or several view layers, or a missing pass.

    Examples:
        >>> from stereorepro.io.blender import BLENDER_CHANNELS, layer_prefix
        >>> layer_prefix(["ViewLayer." + c for c in BLENDER_CHANNELS] + ["ViewLayer.Vector.X"])
        'ViewLayer.'
    """
    from ..errors import SequenceError

    names = set(names)
    prefixes = sorted({k[: -len("Depth.Z")] for k in names if k.endswith(".Depth.Z")})
    if not prefixes and any(c in names for c in BLENDER_CHANNELS):
        raise SequenceError(
            f"{where}: channels without a view-layer prefix (found: {', '.join(sorted(names))}); "
            "Blender's multilayer EXRs name them <view layer>.<pass>.<channel>, e.g. "
            "ViewLayer.Combined.R: save as OpenEXR MultiLayer"
        )
    if len(prefixes) != 1:
        raise SequenceError(
            f"{where}: expected one view layer with a Depth pass, found {prefixes or 'none'} "
            "(enable the Z, Normal (and Vector) passes)"
        )
    pre = prefixes[0]
    missing = [pre + c for c in BLENDER_CHANNELS if pre + c not in names]
    if missing:
        raise SequenceError(
            f"{where}: missing Blender pass channel(s) {', '.join(missing)} (enable the Combined, Z "
            f"and Normal passes of the view layer; found: {', '.join(sorted(names))})"
        )
    return pre


def frame_from_channels(channels: dict, where: str = "") -> dict:
    """Our frame from the channels of a Blender multilayer EXR (as :func:`~stereorepro.io.exr.read_exr` returns
    them): ``color`` (1, 3, H, W), ``depth`` (camera z, ``+inf`` at the background), ``normal`` (world; zero at
    the background), and ``motion`` (1, 2, H, W) when the Vector pass is present.

    Raises:
        SequenceError: no single view layer with the needed passes (:func:`layer_prefix`), or channels of
            different sizes (naming the channel).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.io.blender import BLENDER_CHANNELS, frame_from_channels
        >>> channels = {"ViewLayer." + c: np.zeros((2, 4), np.float32) for c in BLENDER_CHANNELS}
        >>> channels["ViewLayer.Depth.Z"][:] = 2.0; channels["ViewLayer.Depth.Z"][0, 0] = 1e10  # one background pixel
        >>> channels["ViewLayer.Normal.Z"][:] = 1.0
        >>> channels.update({"ViewLayer.Vector.X": np.ones((2, 4)), "ViewLayer.Vector.Y": np.ones((2, 4))})
        >>> frame = frame_from_channels(channels, "0001_L.exr")
        >>> frame["depth"][0, 0, 0].tolist(), frame["motion"][0, :, 1, 1].tolist()  # y up -> y down
        ([inf, 2.0, 2.0, 2.0], [1.0, -1.0])
    """
    import torch

    from .exr import channel_size

    pre = layer_prefix(channels, where)
    vector = [pre + c for c in ("Vector.X", "Vector.Y")]
    used = [pre + c for c in BLENDER_CHANNELS] + [c for c in vector if c in channels]
    channel_size(channels, used, where)

    def stack(names):
        return torch.from_numpy(np.stack([np.asarray(channels[pre + c], np.float32) for c in names])[None].copy())

    depth = stack(("Depth.Z",))
    normal = stack(("Normal.X", "Normal.Y", "Normal.Z"))
    background = ~(depth < BACKGROUND_DEPTH) | (normal.abs().sum(1, keepdim=True) == 0)
    out = {
        "color": stack(("Combined.R", "Combined.G", "Combined.B")),
        "depth": torch.where(background, torch.full((), math.inf), depth),
        "normal": normal,
    }
    if all(c in channels for c in vector):
        v = stack(("Vector.X", "Vector.Y"))
        motion = torch.cat([v[:, :1], -v[:, 1:2]], 1)  # y up -> our y down
        out["motion"] = torch.where(background, torch.full((), math.nan), motion)
    return out
