"""Moving objects in the tracer: one BVH of the whole scene rebuilt every frame, against a BVH of the static faces
built once plus a BVH of the moving faces rebuilt every frame, both queried and the nearer hit kept
(:class:`stereorepro.render._embree.SplitBVH`, what the tracer does).

    .venv/bin/python bench/bvh.py                 # writes bench/results/bvh.{json,md}
    .venv/bin/python bench/bvh.py --repeats 3     # quicker

Per frame is what a sequence pays for each new frame: the frame's geometry (objects placed, face normals, the BVH
builds) and one render of one eye with G-buffers (the cases of :data:`CASES`: scene, size, spp). Both ways render the
same frames, timed in alternation (medians after warm-up, one process); their radiance, G-buffers and ray counts
are compared byte for byte. The whole-scene build costs about the same per triangle in every frame, the second BVH
about the same per ray, so the ratio moves with rays per frame: the last case has 16 times the rays of the first
shared one. Scenes: the built-in ``living_room_moving_objects``, and ``shared_living_room`` (needs the shared meshes) with
a moving object added by a scene file written to a temporary folder: a box (12 triangles) sliding across the room,
or the sofa cushion ``Cushion1`` (3360 triangles) sliding and turning.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import header, save, time_rounds  # noqa: E402

from stereorepro import load_scene  # noqa: E402
from stereorepro.render import PathTracer  # noqa: E402
from stereorepro.render._embree import TriangleBVH  # noqa: E402
from stereorepro.render.tracer import _face_normals, _Geometry  # noqa: E402
from stereorepro.scenes import scenes_dir  # noqa: E402

#: moving objects added to shared_living_room: name -> scene-file text after ``extends``
SHARED_MOVERS = {
    "box": """
[geometry]
boxes = [{min = [-0.3, 0.03, 3.6], max = [0.3, 0.63, 4.2], material = "mover"}]
[materials.mover]
albedo = [0.7, 0.45, 0.15]
[[animations]]
materials = ["mover"]
frames = [0, 30, 59]
translate = [[-1.0, 0.0, 0.0], [1.5, 0.0, 0.0], [-1.0, 0.0, 0.0]]
rotate = [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 90.0], [0.0, 1.0, 0.0, 0.0]]
""",
    "Cushion1": """
[[animations]]
materials = ["Cushion1"]
frames = [0, 30, 59]
translate = [[0.0, 0.0, 0.0], [0.8, 0.1, 0.6], [0.0, 0.0, 0.0]]
rotate = [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 45.0], [0.0, 1.0, 0.0, 0.0]]
""",
}


class WholeSceneBVH(PathTracer):
    """The tracer with one BVH of every face, built for each frame (its geometry stage before the split)."""

    def geometry(self, frame: int) -> _Geometry:
        frame = int(frame)
        if self._geom_cache is not None and self._geom_cache.frame == frame:
            return self._geom_cache
        v = self.object_vertices(frame)
        self._geom_cache = _Geometry(frame, v, _face_normals(v, self.faces), TriangleBVH(v, self.faces))
        return self._geom_cache


def shared_moving_scene(folder: Path, mover: str):
    path = folder / f"shared_living_room_{mover}.toml"
    base = (scenes_dir() / "shared_living_room.toml").resolve()
    path.write_text(
        f'extends = "{base}"\nname = "shared_living_room + moving {mover}"\n'
        f'effects = ["moving_objects"]\n{SHARED_MOVERS[mover]}'
    )
    return load_scene(path)


#: (scene: built-in name or a key of SHARED_MOVERS, size, spp)
CASES = [
    ("living_room_moving_objects", "320x180", 1),
    ("box", "320x180", 1),
    ("Cushion1", "320x180", 1),
    ("box", "1280x720", 1),
]
WAYS = ("one BVH, rebuilt per frame", "static BVH + moving-faces BVH")
FIELDS = ("radiance", "depth", "normal", "position", "albedo", "material_id", "object_id")


def measure(scene, W: int, H: int, spp: int, repeats: int, warmup: int) -> dict:
    """Per-frame and per-part times of both ways on the same frames, and whether their renders are identical."""
    tracers = dict(zip(WAYS, (WholeSceneBVH(scene), PathTracer(scene))))
    frames = list(range(1, scene.num_frames))
    cams = {f: scene.camera(f, W, H) for f in frames}
    state = {"i": 0, "out": {}}

    def frame_fn(name, tr):
        def fn():
            f = frames[state["i"] % len(frames)]
            r = tr.render(cams[f], f, spp)
            state["out"][name] = r

        return fn

    def advance():
        a, b = (state["out"][n] for n in tracers)
        same = all(np.asarray(getattr(a, k)).tobytes() == np.asarray(getattr(b, k)).tobytes() for k in FIELDS)
        state.setdefault("identical", []).append(bool(same and a.ray_counts == b.ray_counts))
        state["i"] += 1

    fns = {n: frame_fn(n, tr) for n, tr in tracers.items()}
    fns["(compare, next frame)"] = advance
    ts = time_rounds(fns, repeats=repeats, warmup=warmup)
    del ts["(compare, next frame)"]
    geo = time_rounds({n: geometry_fn(tr, frames[0]) for n, tr in tracers.items()}, repeats=repeats, warmup=1)
    split = tracers[WAYS[1]]
    moving = int((split.face_object >= 0).sum())
    return {
        "scene": scene.name,
        "triangles": int(len(split.faces)),
        "moving_triangles": moving,
        "resolution": f"{W}x{H}",
        "spp": spp,
        "rays": int(sum(state["out"][WAYS[1]].ray_counts.values())),
        "frames_compared": len(state["identical"]),
        "frames_identical": int(sum(state["identical"])),
        "per_frame_ms": {n: _stats(v) for n, v in ts.items()},
        "geometry_ms": {n: _stats(v) for n, v in geo.items()},
    }


def geometry_fn(tr: PathTracer, frame: int):
    """The geometry stage of ``frame`` alone, built anew at every call."""

    def fn():
        tr._geom_cache = None
        tr.geometry(frame)

    return fn


def _stats(v: list) -> dict:
    return {"median_ms": float(np.median(v)), "min_ms": float(min(v)), "max_ms": float(max(v)), "repeats": len(v)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    args = ap.parse_args()
    rec = header()
    rec["command"] = " ".join([".venv/bin/python bench/bvh.py"] + sys.argv[1:])
    rec["load_average_before"] = os.getloadavg()[0]
    rows, scenes = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, size, spp in CASES:
            if name not in scenes:
                try:
                    scenes[name] = shared_moving_scene(Path(tmp), name) if name in SHARED_MOVERS else load_scene(name)
                    scenes[name].geometry()
                except Exception as e:  # noqa: BLE001 - the shared meshes are optional
                    scenes[name] = f"skipped: {e}"
            if isinstance(scenes[name], str):
                rows.append({"scene": name, "skipped": scenes[name]})
                continue
            W, H = (int(x) for x in size.split("x"))
            rows.append(measure(scenes[name], W, H, spp, args.repeats, args.warmup))
            print(rows[-1], flush=True)
    rec["rows"] = rows
    rec["load_average_after"] = os.getloadavg()[0]
    save("bvh", rec, markdown(rec))
    print(markdown(rec))


def markdown(rec: dict) -> str:
    md = [
        f"`{rec['command']}`",
        "",
        "Per frame: the frame's geometry (BVH builds included) + one render of one eye with G-buffers. "
        "Medians (min-max) in ms after warm-up, both ways in alternation on the same frames; identical: radiance, "
        "G-buffers and ray counts equal byte for byte. Ratio: one BVH / static + moving (> 1: the split is faster). "
        f"Load average before / after: {rec['load_average_before']:.1f} / {rec['load_average_after']:.1f} on "
        f"{rec['machine']['cores']} cores (other jobs running: absolute times are inflated, the ratios come from "
        "alternating rounds).",
        "",
        "| scene | triangles (moving) | size, spp | rays | "
        + " | ".join(WAYS)
        + " | ratio | geometry only: "
        + " / ".join(WAYS)
        + " | identical frames |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rec["rows"]:
        if "skipped" in r:
            md.append(f"| {r['scene']} | {r['skipped']} ||||||||")
            continue
        p, g = r["per_frame_ms"], r["geometry_ms"]
        cell = [f"{p[w]['median_ms']:.1f} ({p[w]['min_ms']:.1f}-{p[w]['max_ms']:.1f})" for w in WAYS]
        md.append(
            f"| `{r['scene']}` | {r['triangles']} ({r['moving_triangles']}) | {r['resolution']}, {r['spp']} | "
            f"{r['rays']} | "
            + " | ".join(cell)
            + f" | {p[WAYS[0]]['median_ms'] / p[WAYS[1]]['median_ms']:.2f} | "
            + " / ".join(f"{g[w]['median_ms']:.1f}" for w in WAYS)
            + f" | {r['frames_identical']} of {r['frames_compared']} |"
        )
    return "\n".join(md) + "\n"


if __name__ == "__main__":
    main()
