"""Mitsuba 3 frames in our conventions, converted here and nowhere else (``pip install mitsuba``; the
``scalar_rgb`` variant: the llvm variants abort on some machines).

Mitsuba's conventions, and what we do with them:

* **Camera frame**: x left, y up, z forward (``to_world`` maps it to the world). Ours is OpenCV's (x right, y down,
  z forward): ``cam_from_world = diag(-1, -1, 1, 1) · inv(to_world)``.
* **Intrinsics**: a ``perspective`` sensor's ``x_fov`` (degrees, whatever ``fov_axis`` was given) with square
  pixels: ``fx = fy = (W / 2) / tan(x_fov / 2)``, principal point at the film centre (``principal_point_offset``
  other than 0 is refused).
* **G-buffer**: the ``aov`` integrator with :data:`AOVS` (``"dd:depth,nn:sh_normal,pp:position"``): ``dd`` is a
  distance along the ray (0 where nothing is hit), ``nn`` the world-space shading normal, ``pp`` the world
  position. Our depth is the camera-space **z**, taken from the position: ``z = (cam_from_world · pp).z`` where
  ``dd > 0``, ``+inf`` elsewhere. AOVs are averages over a pixel's samples; :func:`render_gbuffer` renders them in
  a separate pass with one unjittered ``stratified`` sample and a ``box`` filter, at the pixel centres.
* **Films**: ``mi.render`` returns unnamed channels; the named ones are on ``sensor.film().bitmap()``. Written
  with ``bitmap.write(path)`` an EXR has ``R, G, B`` (the image), ``dd.T``, ``nn.X/Y/Z``, ``pp.X/Y/Z`` (and the
  ``img.*`` copy); :func:`frame_from_channels` converts those. Use ``component_format = "float32"`` (``hdrfilm``
  defaults to float16).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .._extras import require
from ..camera import PinholeCamera
from ..errors import SequenceError
from .exr import channel_size

__all__ = ["AOVS", "MITSUBA_CHANNELS", "FLIP", "sensor_to_camera", "render_gbuffer", "frame_from_channels"]

#: The ``aov`` integrator's ``aovs`` string our conversion expects.
AOVS = "dd:depth,nn:sh_normal,pp:position"
#: Channels of a Mitsuba film written with :data:`AOVS` that the conversion reads.
MITSUBA_CHANNELS = ("R", "G", "B", "dd.T", "nn.X", "nn.Y", "nn.Z", "pp.X", "pp.Y", "pp.Z")
#: Mitsuba's camera axes (x left, y up) to OpenCV's (x right, y down).
FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])


def _mi():
    mi = require("mitsuba", "Mitsuba frames")

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi


def sensor_to_camera(sensor) -> PinholeCamera:
    """Our :class:`~stereorepro.camera.PinholeCamera` (float64, B = 1) of a Mitsuba ``perspective`` sensor.

    Examples:
        >>> import mitsuba as mi
        >>> from stereorepro.io.mitsuba import sensor_to_camera
        >>> mi.set_variant("scalar_rgb")
        >>> sensor = mi.load_dict({"type": "perspective", "fov_axis": "x", "fov": 90.0,
        ...                        "film": {"type": "hdrfilm", "width": 4, "height": 2}})
        >>> cam = sensor_to_camera(sensor)
        >>> [[round(v, 9) for v in row] for row in cam.K[0].tolist()], (cam.height, cam.width)
        ([[2.0, 0.0, 2.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]], (2, 4))
        >>> cam.cam_from_world[0].diagonal().tolist()  # Mitsuba's x-left, y-up camera -> OpenCV's x-right, y-down
        [-1.0, -1.0, 1.0, 1.0]
    """
    mi = _mi()
    params = mi.traverse(sensor)
    for k in ("principal_point_offset_x", "principal_point_offset_y"):
        if k in params and float(params[k]) != 0.0:
            raise ValueError(
                f"sensor_to_camera: {k} = {float(params[k])} is not supported (only a centred principal point)"
            )
    if "x_fov" not in params:
        raise ValueError(f"sensor_to_camera: expected a perspective sensor, got {sensor.class_name()}")
    W, H = (int(v) for v in sensor.film().crop_size())
    fx = (W / 2.0) / math.tan(math.radians(float(params["x_fov"])) / 2.0)
    K = torch.tensor([[[fx, 0.0, W / 2.0], [0.0, fx, H / 2.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    to_world = np.array(sensor.world_transform().matrix, dtype=np.float64)
    T = torch.from_numpy(FLIP @ np.linalg.inv(to_world))[None]
    return PinholeCamera(K, T, H, W)


def frame_from_channels(channels: dict, camera: PinholeCamera, where: str = "") -> dict:
    """Our frame (``color`` (1, 3, H, W), ``depth`` camera z with ``+inf`` where nothing is hit, world ``normal``,
    ``position``) from the channels of a Mitsuba film written with :data:`AOVS` (as :func:`read_exr` returns
    them), seen by ``camera`` (ours).

    Raises:
        SequenceError: a channel is missing, or one is not of the camera's size (naming it).

    Examples:
        >>> import numpy as np, torch
        >>> from stereorepro.camera import PinholeCamera
        >>> from stereorepro.io.mitsuba import MITSUBA_CHANNELS, frame_from_channels
        >>> K = torch.tensor([[[2.0, 0, 2], [0, 2.0, 1], [0, 0, 1]]], dtype=torch.float64)
        >>> camera = PinholeCamera(K, torch.eye(4, dtype=torch.float64)[None], 2, 4)
        >>> channels = {c: np.zeros((2, 4), np.float32) for c in MITSUBA_CHANNELS}  # a film written with AOVS
        >>> channels["pp.Z"][:] = 3.0; channels["dd.T"][:] = 3.0; channels["dd.T"][0, 0] = 0.0  # one pixel hits nothing
        >>> frame = frame_from_channels(channels, camera, "frame.exr")
        >>> sorted(frame), frame["depth"][0, 0, 0].tolist()
        (['color', 'depth', 'normal', 'position'], [inf, 3.0, 3.0, 3.0])
    """
    missing = [c for c in MITSUBA_CHANNELS if c not in channels]
    if missing:
        raise SequenceError(
            f"{where}: missing Mitsuba channel(s) {', '.join(missing)} (render with the aov "
            f'integrator, aovs = "{AOVS}"; found: {", ".join(sorted(channels))})'
        )
    channel_size(channels, MITSUBA_CHANNELS, where, (camera.height, camera.width))

    def stack(names):
        return torch.from_numpy(np.stack([np.asarray(channels[c], np.float32) for c in names])[None].copy())

    P = stack(("pp.X", "pp.Y", "pp.Z")).double()
    T = camera.cam_from_world[0].double()
    z = (T[2, :3].view(1, 3, 1, 1) * P).sum(1, keepdim=True) + T[2, 3]
    hit = torch.from_numpy(np.asarray(channels["dd.T"], np.float32))[None, None] > 0
    depth = torch.where(hit & (z > 0), z, torch.full((), math.inf, dtype=torch.float64)).float()
    return {
        "color": stack(("R", "G", "B")),
        "depth": depth,
        "normal": stack(("nn.X", "nn.Y", "nn.Z")),
        "position": P.float(),
    }


def render_gbuffer(scene, sensor=None, spp: int = 16, seed: int = 0) -> dict:
    """Render ``scene`` with Mitsuba and return our frame: ``color`` (1, 3, H, W) at ``spp`` with the scene's
    integrator, ``depth`` (camera z), ``normal``, ``position`` from an AOV pass at the pixel centres, and the
    camera as ``K`` (1, 3, 3) and ``cam_from_world`` (1, 4, 4) float64 (see the module docstring).

    Args:
        scene: a loaded Mitsuba scene. sensor: one of its sensors or another (default: its first).
        spp: samples per pixel of the colour. seed: the sampler seed.

    Examples:
        >>> import mitsuba as mi
        >>> from stereorepro.io.mitsuba import render_gbuffer
        >>> mi.set_variant("scalar_rgb")
        >>> scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"},
        ...     "sensor": {"type": "perspective", "fov_axis": "x", "fov": 60.0,
        ...                "to_world": mi.ScalarTransform4f().look_at([0, 0, -3], [0, 0, 0], [0, 1, 0]),
        ...                "film": {"type": "hdrfilm", "width": 4, "height": 2}},
        ...     "wall": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(4.0)}, "sky": {"type": "constant"}})
        >>> frame = render_gbuffer(scene, spp=1)
        >>> tuple(frame["color"].shape), tuple(frame["depth"].shape)
        ((1, 3, 2, 4), (1, 1, 2, 4))
        >>> [round(float(d), 4) for d in frame["depth"][0, 0, 0]]  # camera z of the wall, 3 units ahead
        [3.0, 3.0, 3.0, 3.0]
    """
    mi = _mi()
    sensor = scene.sensors()[0] if sensor is None else sensor
    cam = sensor_to_camera(sensor)
    color = np.array(mi.render(scene, sensor=sensor, spp=int(spp), seed=int(seed)), dtype=np.float32)[..., :3]
    params = mi.traverse(sensor)
    aov_sensor = mi.load_dict(
        {
            "type": "perspective",
            "fov_axis": "x",
            "fov": float(params["x_fov"]),
            "near_clip": float(params["near_clip"]),
            "far_clip": float(params["far_clip"]),
            "to_world": mi.ScalarTransform4f(np.array(sensor.world_transform().matrix)),
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
            "film": {
                "type": "hdrfilm",
                "width": cam.width,
                "height": cam.height,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
                "component_format": "float32",
            },
        }
    )
    aov = mi.load_dict({"type": "aov", "aovs": AOVS})
    mi.render(scene, sensor=aov_sensor, integrator=aov, spp=1, seed=int(seed))
    bmp = aov_sensor.film().bitmap()
    names = [f.name for f in bmp.struct_()] if hasattr(bmp, "struct_") else None
    arr = np.array(bmp, dtype=np.float32)
    if names is None or len(names) != arr.shape[-1]:
        raise RuntimeError("render_gbuffer: cannot read the AOV film's channel names")
    channels = {n: arr[..., i] for i, n in enumerate(names)}
    channels.update({"R": color[..., 0], "G": color[..., 1], "B": color[..., 2]})
    frame = frame_from_channels(channels, cam, "render_gbuffer")
    frame.update(K=cam.K, cam_from_world=cam.cam_from_world)
    return frame
