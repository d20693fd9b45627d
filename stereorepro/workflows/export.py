"""Export a frame sequence from our path tracer: the input directory of ``stereorepro reproject``
(:mod:`stereorepro.io.frames` describes the format)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from torch import Tensor

from ..io.atomic import atomic_write, staged_outputs
from ..io.frames import FRAME_FILE_RE

__all__ = ["export_sequence"]


def _json_matrix(t: Tensor) -> list:
    return [[float(x) for x in row] for row in t[0].double().tolist()]


def export_sequence(
    scene, frames, width: int, height: int, out_dir, spp: int = 1, seed: int = 0, workers: int | None = None
) -> Path:
    """Write an input directory for ``stereorepro reproject`` from our path tracer.

    Frame ``i`` of the directory is scene frame ``frames[i]``; both eyes are traced at ``spp`` (RNG eye keys 0 =
    left, 1 = right) and written with all the tracer's channels (``R,G,B, Z, N.*, P.*``; for scenes with moving
    objects, from the second frame on, also the motion to the previous exported frame, ``M.*`` and ``MW.*``).
    ``cameras.json`` gets the scene's thresholds at that height (:meth:`~stereorepro.scenes.Scene.thresholds`: the
    position threshold scaled by ``max(1, 180 / height)``; scene files are tuned for ~180 rows) and a ``meta``
    record. The files appear together once all are written (:func:`~stereorepro.io.atomic.staged_outputs`),
    ``cameras.json`` last, and replace an earlier sequence in ``out`` as a whole (its other frame files are
    removed); on any failure none do and ``out`` keeps what it had.

    Args:
        scene: a scene name or a :class:`~stereorepro.scenes.Scene`.
        frames: number of frames (0..n-1) or an iterable of scene frame indices.
        width, height: image size.
        out_dir: directory (created).
        spp, seed, workers: tracer settings.

    Returns:
        ``out_dir`` as a Path.

    Examples:
        >>> import os, tempfile
        >>> from stereorepro.workflows.export import export_sequence
        >>> tmp = tempfile.TemporaryDirectory()
        >>> src = export_sequence("living_room", 2, 8, 6, os.path.join(tmp.name, "in"))  # 2 frames of 8x6, 1 spp
        >>> sorted(os.listdir(src))
        ['0000_left.exr', '0000_right.exr', '0001_left.exr', '0001_right.exr', 'cameras.json']
        >>> tmp.cleanup()
    """
    from ..io.exr import write_exr
    from ..render import PathTracer
    from ..scenes import load_scene

    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    frame_ids = list(range(int(frames))) if isinstance(frames, int) else [int(f) for f in frames]
    if not frame_ids:
        raise ValueError("export_sequence: no frames")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"export_sequence: {out} exists and is not a directory")
    tracer = PathTracer(scene, seed=seed, workers=workers)
    # all frames or none, cameras.json last; the frame files of an earlier export into ``out`` are removed
    with staged_outputs(out, last=["cameras.json"], replaces=FRAME_FILE_RE) as stage:
        records = []
        moving = "moving_objects" in scene.effects  # static scenes: the cameras give the motion exactly
        for i, f in enumerate(frame_ids):
            left, right = scene.stereo_cameras(f, width, height)
            rec = {}
            prev = scene.stereo_cameras(frame_ids[i - 1], width, height) if i and moving else None
            for eye, cam, key in (("left", left, 0), ("right", right, 1)):
                res = tracer.render(
                    cam,
                    f,
                    spp,
                    eye=key,
                    prev_camera=None if prev is None else prev[key],
                    prev_frame=frame_ids[i - 1] if prev is not None else None,
                )
                write_exr(stage / f"{i:04d}_{eye}.exr", res)
                rec[eye] = {"K": _json_matrix(cam.K), "cam_from_world": _json_matrix(cam.cam_from_world)}
            records.append(rec)
        position_threshold, normal_threshold = scene.thresholds(height)
        doc = {
            "frames": records,
            "reprojection": {"position_threshold": position_threshold, "normal_threshold": normal_threshold},
            "meta": {
                "scene": scene.name,
                "scene_frames": frame_ids,
                "spp": int(spp),
                "seed": int(seed),
                "width": int(width),
                "height": int(height),
                "writer": "stereorepro.workflows.export.export_sequence",
            },
        }
        atomic_write(stage / "cameras.json", json.dumps(doc, indent=1))
    return out
