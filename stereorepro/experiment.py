"""The paper's experiment (§4) as one command: effective spp, Tables 1–2, Figures 1/3/4, and the time cost.

For every frame of a scene's camera path, both eyes are rendered by :class:`~stereorepro.PathTracer`:

* G-buffers (one unjittered primary ray per pixel),
* a **ladder** of plain path-traced images at 1..L spp — prefixes of one sample stream (sample indices 0..L-1),
* a **reference** at R spp from a disjoint stream (sample indices from :data:`REFERENCE_OFFSET`).

The 1-spp rung of each eye is the renderer's 1-spp input. The schemes then run on those inputs
(:class:`~stereorepro.SpatiotemporalReprojection`):

* ``stereo``: right eye at 1 spp reprojected into the left eye; the left eye's discarded pixels traced at 1 spp;
  evaluated on the left eye;
* ``temporal``: the right eye accumulated over time (EMA, 20 %); evaluated on the right eye;
* ``stereo_temporal``: temporal on the right eye, stereo R → L, left-eye temporal filling; evaluated on the left.

Metric: RMSE of images clamped to [0, 1] by default (``metric="ldr"``, display-referred), or of linear radiance
(``"hdr"``). Under HDR RMSE, antialiased edges of directly visible emitters (radiance ≈ 5–6 beside ≈ 0.2) dominate
the error of any resampling scheme: on the Living Room the stereo scheme fed with *noise-free* references still has
an HDR RMSE equal to 16-spp noise, so effective spp stays near 1–3 whatever the noise reduction. The paper does not
say which it used; its numbers fit display-referred images. Both are one flag apart; the README reports both.

Variants (nearest sampling, other alphas) run on the same renders, so what each step of accuracy costs shows
side by side. Quality is RMSE against the reference turned into effective spp with the eye's ladder
(:mod:`stereorepro.metrics`); matching against a ladder scored on the same reference cancels the reference's
own noise to first order.

Renders are cached by content (scene file, mesh file, frame, eye, sample range, resolution, seed, renderer source),
written atomically, so a killed run resumes and a cached run reproduces the same tables; ``force`` recomputes.

Resolution and thresholds: the position test compares a tap's surface point with the destination point, so a
tap half a pixel away on a slanted surface differs by about half a pixel footprint. Scene thresholds (in scene
units, like the paper's scene-specific limits) are chosen as 2–3 pixel footprints at a typical depth at 180 rows;
below 180 rows they are scaled by ``180 / height`` (``threshold_scale="auto"``) so the test keeps its meaning in
pixels; at 180 rows and above they are used as they are.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .camera import has_surface
from .metrics import effective_spp_many, ladder_rmse, rmse
from .pipeline import SpatiotemporalReprojection
from .reproject import reason_to_rgb

__all__ = ["ExperimentConfig", "run_experiment", "REFERENCE_OFFSET", "register", "SCHEMES"]

#: First sample index of reference renders (ladders use 0..L-1: disjoint streams).
REFERENCE_OFFSET = 1 << 24
#: Rows for which scene thresholds are ~2–3 pixel footprints; below this they are scaled up.
THRESHOLD_ROWS = 180
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
    threshold_scale: float | None = None  #: None = auto, max(1, 180 / height)
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


# ---------------------------------------------------------------------------------------------------------------
# content-addressed render cache

def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _code_version() -> str:
    """Hash of the renderer's sources (Python, and the native shading stages when their sources are present):
    renders are recomputed when the renderer changes."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256(__version__.encode())
    cpp = root.parent / "cpp_ext" / "src"
    native = sorted(cpp.glob("*tracer*")) if cpp.is_dir() else []
    for p in sorted(list((root / "render").glob("*.py")) + [root / "scenes.py"]) + native:
        h.update(p.read_bytes())
    try:
        from . import _core

        h.update(repr(sorted(_core.build_info().items())).encode())
    except ImportError:
        h.update(b"no-core")
    return h.hexdigest()[:16]


def _scene_fingerprint(scene) -> str:
    """Hash of the scene's resolved description and of every file it references (path, size, mtime)."""
    h = hashlib.sha256(str(getattr(scene, "name", "")).encode())
    data = getattr(scene, "_data", None)
    h.update(json.dumps(data, sort_keys=True, default=str).encode())
    src = getattr(scene, "source", None)
    if src and Path(src).is_file():
        h.update(Path(src).read_bytes())

    from .scenes import _expand_path

    base = Path(src).parent if src else Path.cwd()

    def files(x):
        if isinstance(x, dict):
            for v in x.values():
                yield from files(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                yield from files(v)
        elif isinstance(x, (str, Path)) and str(x).lower().endswith((".ply", ".obj", ".glb", ".gltf", ".json")):
            f = _expand_path(str(x), base)
            yield f
            if f.suffix.lower() == ".ply":
                yield f.with_suffix(".json")  # the default material sidecar

    for f in files(data):
        if f.is_file():
            st = f.stat()
            h.update(f"{f}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


class RenderCache:
    """npz files keyed by a hash of what determines a render; atomic writes."""

    def __init__(self, root: Path, force: bool = False):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.force = force
        self.hits = 0
        self.misses = 0

    def _path(self, key: dict) -> Path:
        return self.root / (_sha(json.dumps(key, sort_keys=True).encode())[:32] + ".npz")

    def get_or_make(self, key: dict, make):
        path = self._path(key)
        if path.exists() and not self.force:
            try:
                with np.load(path, allow_pickle=False) as z:
                    data = {k: z[k] for k in z.files}
                meta = json.loads(str(data.pop("__meta__")))
                self.hits += 1
                return data, meta
            except (OSError, ValueError, KeyError):
                pass  # corrupt or partial file: recompute
        data, meta = make()
        fd, tmp = tempfile.mkstemp(dir=self.root, suffix=".npz.tmp")
        os.close(fd)
        try:
            with open(tmp, "wb") as f:
                np.savez(f, __meta__=np.array(json.dumps(meta)), **data)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        self.misses += 1
        return data, meta


# ---------------------------------------------------------------------------------------------------------------
# rendering of one frame's inputs

@dataclass
class EyeData:
    depth: torch.Tensor  # (1, 1, H, W)
    normal: torch.Tensor  # (1, 3, H, W)
    K: torch.Tensor  # (1, 3, 3)
    cam_from_world: torch.Tensor  # (1, 4, 4)
    ladder: list[torch.Tensor]  # prefix means at 1..L spp, each (1, 3, H, W)
    reference: torch.Tensor  # (1, 3, H, W)
    ms_gbuffer: float
    ms_per_spp: float  # mean wall time of one 1-spp full-frame render
    ms_reference: float
    camera: object = None


def _render_eye(tracer, cache: RenderCache, base_key: dict, camera, frame: int, eye: int, cfg: ExperimentConfig
                ) -> EyeData:
    key = dict(base_key, frame=frame, eye=eye)

    def gbuf():
        r = tracer.gbuffer(camera, frame)
        return ({"depth": r.depth.numpy(), "normal": r.normal.numpy()},
                {"ms": r.time_s * 1e3, "rays": r.ray_counts})

    g, gmeta = cache.get_or_make(dict(key, kind="gbuffer"), gbuf)
    rungs, times = [], []
    total = None
    for s in range(cfg.ladder_spp):
        def one(s=s):
            r = tracer.render(camera, frame, 1, sample_offset=s, eye=eye, gbuffers=False)
            return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

        d, meta = cache.get_or_make(dict(key, kind="spp", spp=1, offset=s), one)
        x = torch.from_numpy(d["radiance"]).double()
        total = x if total is None else total + x
        rungs.append((total / (s + 1)).float())
        times.append(meta["ms"])

    def ref():
        r = tracer.render(camera, frame, cfg.reference_spp, sample_offset=REFERENCE_OFFSET, eye=eye, gbuffers=False,
                          progress=False)
        return {"radiance": r.radiance.numpy()}, {"ms": r.time_s * 1e3, "rays": r.ray_counts}

    rd, rmeta = cache.get_or_make(dict(key, kind="spp", spp=cfg.reference_spp, offset=REFERENCE_OFFSET), ref)
    return EyeData(torch.from_numpy(g["depth"]), torch.from_numpy(g["normal"]), camera.K.float(),
                   camera.cam_from_world.double(), rungs, torch.from_numpy(rd["radiance"]), gmeta["ms"],
                   float(np.mean(times)), rmeta["ms"], camera)


# ---------------------------------------------------------------------------------------------------------------
# the experiment

def _stats(xs) -> dict:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    if not xs:
        return {"avg": None, "min": None, "max": None, "n": 0}
    return {"avg": float(np.mean(xs)), "min": float(np.min(xs)), "max": float(np.max(xs)), "n": len(xs)}


def _schemes(cfg: ExperimentConfig) -> list[Scheme]:
    out = list(SCHEMES)
    for a in cfg.alphas:
        if abs(a - 0.2) > 1e-12:
            out.append(Scheme(f"temporal_alpha{a:g}", False, True, RIGHT, alpha=a))
            out.append(Scheme(f"stereo_temporal_alpha{a:g}", True, True, LEFT, alpha=a))
    return out


def _metric_image(x: torch.Tensor, metric: str) -> torch.Tensor:
    return x.clamp(0.0, 1.0) if metric == "ldr" else x


def run_experiment(cfg: ExperimentConfig, log=print) -> dict:
    """Run the experiment and write its outputs into ``cfg.out``. Returns the ``results.json`` content."""
    from tqdm.auto import tqdm

    from .render import PathTracer
    from .scenes import load_scene

    if cfg.metric not in ("hdr", "ldr"):
        raise ValueError(f"metric must be 'hdr' or 'ldr', got {cfg.metric!r}")
    if cfg.ladder_spp < 2:
        raise ValueError("ladder_spp must be >= 2")
    if cfg.reference_spp < cfg.ladder_spp:
        raise ValueError("reference_spp must be >= ladder_spp")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(cfg.scene)
    frames = scene.num_frames if cfg.frames is None else int(cfg.frames)
    if not 1 <= frames <= scene.num_frames:
        raise ValueError(f"frames must be in 1..{scene.num_frames} for scene {scene.name!r}, got {frames}")
    W, H = cfg.width, cfg.height
    scale = cfg.threshold_scale if cfg.threshold_scale is not None else max(1.0, THRESHOLD_ROWS / H)
    pos_thr = float(scene.position_threshold) * scale
    nrm_thr = float(scene.normal_threshold)
    tracer = PathTracer(scene, seed=cfg.seed, workers=cfg.workers)
    cache = RenderCache(Path(cfg.cache_dir) if cfg.cache_dir else out / "cache", force=cfg.force)
    code = cfg.renderer_version or _code_version()
    base_key = {"scene": _scene_fingerprint(scene), "code": code, "seed": cfg.seed, "w": W, "h": H}
    schemes = _schemes(cfg)
    drivers = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                  stereo=s.stereo, temporal=s.temporal) for s in schemes}
    # The same schemes fed with the noise-free references: their error is the resampling bias alone (bilinear blur
    # compounded over frames, edges), the part of the error that more samples cannot remove.
    clean = {s.name: SpatiotemporalReprojection(pos_thr, nrm_thr, alpha=s.alpha, sampling=s.sampling,
                                                stereo=s.stereo, temporal=s.temporal) for s in schemes if s.paper}
    per_frame = []
    timing = {k: [] for k in ("trace_1spp_ms", "gbuffer_ms", "trace_left_discards_ms", "reference_ms")}
    timing.update({f"reproject_{s.name}_ms": [] for s in schemes})
    keep = {}  # frames kept for figures
    fig1_frame = frames // 2
    t_start = time.perf_counter()
    bar = tqdm(range(frames), desc=f"{scene.name} {W}x{H}", unit="frame", disable=not cfg.progress)
    for f in bar:
        left_cam, right_cam = scene.stereo_cameras(f, W, H)
        eyes = {LEFT: _render_eye(tracer, cache, base_key, left_cam, f, LEFT, cfg),
                RIGHT: _render_eye(tracer, cache, base_key, right_cam, f, RIGHT, cfg)}
        L, R = eyes[LEFT], eyes[RIGHT]
        timing["trace_1spp_ms"] += [L.ms_per_spp, R.ms_per_spp]
        timing["gbuffer_ms"] += [L.ms_gbuffer, R.ms_gbuffer]
        timing["reference_ms"] += [L.ms_reference, R.ms_reference]
        surface = {e: has_surface(d.depth) for e, d in eyes.items()}
        row = {"frame": f, "discard_pct": {}, "rmse": {}, "effective_spp": {}, "flags": {},
               "ladder_rmse": {}, "no_surface_pct": {}, "rmse_noise_free": {}}
        ladder_spp = list(range(1, cfg.ladder_spp + 1))
        ladder_err = {}
        for e, d in eyes.items():
            errs = ladder_rmse([_metric_image(x, cfg.metric) for x in d.ladder],
                               _metric_image(d.reference, cfg.metric))[0].tolist()
            ladder_err[e] = errs
            row["ladder_rmse"]["left" if e == LEFT else "right"] = errs
            row["no_surface_pct"]["left" if e == LEFT else "right"] = 100.0 * float((~surface[e]).float().mean())
        for s in schemes:
            drv = drivers[s.name]
            t0 = time.perf_counter()
            right_out = drv.right(R.ladder[0], R.depth, R.normal, R.K, R.cam_from_world)
            t1 = time.perf_counter()
            mask = drv.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world)
            left_out = drv.left(L.ladder[0])  # the left 1-spp samples; only masked pixels are read
            t2 = time.perf_counter()
            # per-eye accounting: a stereo scheme's left eye pays for its own steps, the right eye for its own
            timing[f"reproject_{s.name}_ms"].append((t2 - t1) * 1e3 if s.stereo else (t1 - t0) * 1e3)
            img = left_out if s.eye == LEFT else right_out
            d = eyes[s.eye]
            err = float(rmse(_metric_image(img, cfg.metric), _metric_image(d.reference, cfg.metric))[0])
            spp, flags = effective_spp_many(torch.tensor([err]), torch.tensor(ladder_spp, dtype=torch.float64),
                                            torch.tensor(ladder_err[s.eye], dtype=torch.float64))
            row["rmse"][s.name] = err
            if s.name in clean:
                c = clean[s.name]
                c_right = c.right(R.reference, R.depth, R.normal, R.K, R.cam_from_world)
                c.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world)
                c_left = c.left(L.reference)
                row["rmse_noise_free"][s.name] = float(rmse(_metric_image(c_left if s.eye == LEFT else c_right,
                                                                          cfg.metric),
                                                            _metric_image(d.reference, cfg.metric))[0])
            row["effective_spp"][s.name] = float(spp[0])
            row["flags"][s.name] = flags[0]
            if s.name == "stereo":
                surf = surface[LEFT]
                row["discard_pct"]["stereo"] = 100.0 * float((mask & surf).sum() / surf.sum().clamp_min(1))
                if f == fig1_frame:
                    keep["fig1_stereo"] = drv.stereo_reason.clone()
                    # the masked trace the paper counts, timed for real (same samples as the full 1-spp render)
                    r = tracer.render(L.camera, f, 1, sample_offset=0, eye=LEFT, gbuffers=False,
                                      pixel_mask=mask[0, 0])
                    timing["trace_left_discards_ms"].append(r.time_s * 1e3)
                    row["masked_trace_matches"] = bool(torch.equal(torch.where(mask, r.radiance, 0.0),
                                                                   torch.where(mask, L.ladder[0], 0.0)))
            if s.name == "temporal" and drv.right_valid is not None:
                surf = surface[RIGHT]
                row["discard_pct"]["temporal"] = 100.0 * float((~drv.right_valid & surf).sum()
                                                               / surf.sum().clamp_min(1))
                if f == fig1_frame:
                    keep["fig1_temporal"] = drv.right_reason.clone()
            if s.name == "stereo_temporal" and f == frames - 1:
                keep["fig4"] = {"method": left_out.clone(), "one": L.ladder[0].clone(), "ref": L.reference.clone(),
                                "top": L.ladder[-1].clone(), "spp": row["effective_spp"][s.name]}
        if cfg.exr:
            _write_frame_exr(out / "exr", f, eyes, drivers)
        per_frame.append(row)
        bar.set_postfix(st=f"{row['effective_spp']['stereo_temporal']:.1f}spp", cache=f"{cache.hits}/{cache.misses}")
    wall = time.perf_counter() - t_start

    table1 = {"stereo": _stats([r["discard_pct"].get("stereo") for r in per_frame]),
              "temporal": _stats([r["discard_pct"].get("temporal") for r in per_frame])}
    table2 = {s.name: _stats([r["effective_spp"][s.name] for r in per_frame]) for s in schemes}
    timing_ms = {k: float(np.median(v)) if v else None for k, v in timing.items()}
    cost = _cost_table(schemes, table2, timing_ms, cfg)
    bias = {k: {"rmse_noise_free": _stats([r["rmse_noise_free"][k] for r in per_frame]),
                "bias_share_of_mse": _stats([(r["rmse_noise_free"][k] / r["rmse"][k]) ** 2 for r in per_frame
                                             if r["rmse"][k] > 0])} for k in clean}
    bias["ladder_top_rmse"] = _stats([r["ladder_rmse"]["left"][-1] for r in per_frame])
    results = {
        "scene": scene.name, "effects": sorted(scene.effects), "frames": frames, "resolution": f"{W}x{H}",
        "reference_spp": cfg.reference_spp, "ladder_spp": cfg.ladder_spp, "seed": cfg.seed, "metric": cfg.metric,
        "thresholds": {"position": pos_thr, "normal": nrm_thr, "position_scene": float(scene.position_threshold),
                       "scale": scale},
        "table1": table1,
        "table2": {k: table2[k] for k in ("stereo", "temporal", "stereo_temporal")},
        "table2_variants": {k: v for k, v in table2.items() if k not in ("stereo", "temporal", "stereo_temporal")},
        "timing_ms": timing_ms, "cost": cost, "bias": bias, "per_frame": per_frame,
        "flags": _flag_counts(per_frame), "cache": {"hits": cache.hits, "misses": cache.misses},
        "wall_s": wall, "version": __version__, "code": code,
    }
    _write_outputs(out, results, per_frame, keep, cfg)
    return results


def _flag_counts(per_frame) -> dict:
    counts: dict = {}
    for r in per_frame:
        for k, fl in r["flags"].items():
            counts.setdefault(k, {}).setdefault(fl, 0)
            counts[k][fl] += 1
    return counts


def _cost_table(schemes, table2, t, cfg) -> list[dict]:
    """ms per frame of the evaluated eye for each scheme and for plain path tracing at n spp.

    Per-eye cost accounting: the stereo schemes' left eye costs its G-buffer, the reprojection and the traced
    discards (the right eye is paid for once, by itself); temporal's right eye costs its 1-spp trace, its G-buffer
    and the reprojection. G-buffers are counted although a real renderer gets them with the primary ray.
    """
    spp_ms = t["trace_1spp_ms"]
    gb = t["gbuffer_ms"]
    masked = t["trace_left_discards_ms"] or 0.0
    rows = [{"scheme": f"path tracing {n} spp", "ms": n * spp_ms, "effective_spp": float(n),
             "ms_per_effective_spp": spp_ms} for n in (1, 2, 4, 8, 16) if n <= cfg.ladder_spp]
    for s in schemes:
        rep = t[f"reproject_{s.name}_ms"]
        if s.stereo:
            ms = gb + rep + masked
        else:
            ms = spp_ms + gb + rep
        e = table2[s.name]["avg"]
        rows.append({"scheme": s.name, "ms": ms, "effective_spp": e,
                     "ms_per_effective_spp": (ms / e) if e else None, "reprojection_ms": rep})
    return rows


# ---------------------------------------------------------------------------------------------------------------
# outputs

def _atomic_write(path: Path, data: bytes | str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def _fmt(x, nd=2):
    return "–" if x is None else f"{x:.{nd}f}"


def tables_markdown(results: dict) -> str:
    t1, t2 = results["table1"], results["table2"]
    lines = [f"**Table 1** — discarded pixels (%), {results['scene']}, {results['frames']} frames, "
             f"{results['resolution']}", "", "| | Avg | Min | Max |", "|---|---:|---:|---:|"]
    for k in ("stereo", "temporal"):
        lines.append(f"| {k} | {_fmt(t1[k]['avg'])} | {_fmt(t1[k]['min'])} | {_fmt(t1[k]['max'])} |")
    lines += ["", f"**Table 2** — effective spp ({results.get('metric', 'hdr').upper()} RMSE, reference "
              f"{results['reference_spp']} spp, ladder 1..."
              f"{results['ladder_spp']} spp)", "",
              "| | Stereo Avg | Min | Max | Temporal Avg | Min | Max | Stereo+temporal Avg | Min | Max |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    cells = []
    for k in ("stereo", "temporal", "stereo_temporal"):
        cells += [_fmt(t2[k]["avg"]), _fmt(t2[k]["min"]), _fmt(t2[k]["max"])]
    lines.append(f"| {results['scene']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def cost_markdown(results: dict) -> str:
    lines = ["| scheme | ms / frame (evaluated eye) | effective spp (avg) | ms per effective spp |",
             "|---|---:|---:|---:|"]
    for r in results["cost"]:
        lines.append(f"| {r['scheme']} | {_fmt(r['ms'], 1)} | {_fmt(r['effective_spp'])} | "
                     f"{_fmt(r['ms_per_effective_spp'], 1)} |")
    return "\n".join(lines) + "\n"


def _tonemap(x: torch.Tensor) -> np.ndarray:
    """(1, 3, H, W) linear → (H, W, 3) sRGB-ish in [0, 1] (clamp, gamma 2.2)."""
    return np.clip(x[0].permute(1, 2, 0).numpy(), 0, 1) ** (1 / 2.2)


def _write_outputs(out: Path, results: dict, per_frame, keep, cfg) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def save(fig, name):
        fd, tmp = tempfile.mkstemp(dir=out, suffix=".png")
        os.close(fd)
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
        plt.close(fig)
        os.replace(tmp, out / name)

    # Figure 1: discard reasons
    if "fig1_stereo" in keep:
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
        for ax, key, title in ((axes[0], "fig1_stereo", "(a) Stereo"), (axes[1], "fig1_temporal", "(b) Temporal")):
            if key in keep:
                ax.imshow(reason_to_rgb(keep[key])[0].permute(1, 2, 0).numpy())
            ax.set_title(title)
            ax.axis("off")
        fig.suptitle("Discarded pixels: green position, cyan normal, red out of frame")
        save(fig, "fig1_discards.png")
    # Figure 3: framewise RMSE against ladder rungs
    fig, ax = plt.subplots(figsize=(7, 4))
    fr = [r["frame"] for r in per_frame]
    for n in (1, 2, 8, 16):
        if n <= cfg.ladder_spp:
            ax.plot(fr, [r["ladder_rmse"]["left"][n - 1] for r in per_frame], "--", lw=1, label=f"{n} spp")
    for k in ("stereo", "stereo_temporal"):
        ax.plot(fr, [r["rmse"][k] for r in per_frame], lw=2, label=k.replace("_", " + "))
    ax.set_xlabel("frame")
    ax.set_ylabel("RMSE (left eye)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title(f"{results['scene']}: framewise RMSE")
    save(fig, "fig3_rmse.png")
    # Figure 4: 1 spp, reference, top ladder rung, reprojected
    if "fig4" in keep:
        k = keep["fig4"]
        fig, axes = plt.subplots(1, 4, figsize=(14, 2.6))
        panels = [("1 spp", k["one"]), (f"{cfg.reference_spp} spp reference", k["ref"]),
                  (f"{cfg.ladder_spp} spp", k["top"]), (f"reprojected: {k['spp']:.2f} effective spp", k["method"])]
        for ax, (t, img) in zip(axes, panels):
            ax.imshow(_tonemap(img))
            ax.set_title(t, fontsize=9)
            ax.axis("off")
        save(fig, "fig4_comparison.png")
    # What accuracy costs in time
    fig, ax = plt.subplots(figsize=(7, 4.5))
    pt = [r for r in results["cost"] if r["scheme"].startswith("path tracing")]
    ax.plot([r["ms"] for r in pt], [r["effective_spp"] for r in pt], "k.-", label="plain path tracing (n spp)")
    for r in results["cost"]:
        if not r["scheme"].startswith("path tracing") and r["effective_spp"]:
            ax.plot(r["ms"], r["effective_spp"], "o")
            ax.annotate(r["scheme"], (r["ms"], r["effective_spp"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("ms per frame (evaluated eye)")
    ax.set_ylabel("effective spp")
    ax.set_title("What accuracy costs in time")
    save(fig, "fig_cost.png")

    _atomic_write(out / "results.json", json.dumps(results, indent=1))
    tables = tables_markdown(results)
    _atomic_write(out / "tables.md", tables)
    flags = ", ".join(f"{k}: {v}" for k, v in results["flags"].get("stereo_temporal", {}).items())
    t = results["timing_ms"]
    report = [f"# Experiment report: {results['scene']}", "",
              f"{results['frames']} frames at {results['resolution']}, reference {results['reference_spp']} spp, "
              f"ladder 1..{results['ladder_spp']} spp, seed {results['seed']}; thresholds: position "
              f"{results['thresholds']['position']:.4g} (scene {results['thresholds']['position_scene']:.4g} × "
              f"{results['thresholds']['scale']:.3g} for the resolution), normal {results['thresholds']['normal']:.3g}. "
              f"stereorepro {results['version']} (renderer {results['code']}); wall time {results['wall_s']:.0f} s "
              f"(cache hits/misses {results['cache']['hits']}/{results['cache']['misses']}).", "",
              tables, "", "Variants (same renders):", "",
              "| scheme | Avg | Min | Max |", "|---|---:|---:|---:|"]
    for kk, v in results["table2_variants"].items():
        report.append(f"| {kk} | {_fmt(v['avg'])} | {_fmt(v['min'])} | {_fmt(v['max'])} |")
    b = results["bias"]
    report += ["", "## Resampling bias", "",
               "Each scheme fed with the noise-free references instead of 1-spp images: its RMSE is pure bias "
               "(bilinear blur compounded over frames, edges), the part more samples cannot remove.", "",
               "| scheme | noise-free RMSE (avg) | share of the scheme's MSE (avg) |", "|---|---:|---:|"]
    for kk in ("stereo", "temporal", "stereo_temporal"):
        if kk in b:
            report.append(f"| {kk} | {_fmt(b[kk]['rmse_noise_free']['avg'], 4)} | "
                          f"{_fmt(100 * b[kk]['bias_share_of_mse']['avg'], 1)} % |")
    report += ["", f"For scale: the left eye's {results['ladder_spp']}-spp RMSE averages "
               f"{_fmt(b['ladder_top_rmse']['avg'], 4)}.", ""]
    report += ["", "## What accuracy costs in time", "",
               f"Median per frame: 1-spp trace of one eye {_fmt(t['trace_1spp_ms'], 1)} ms, G-buffer "
               f"{_fmt(t['gbuffer_ms'], 1)} ms, tracing only the left eye's discarded pixels "
               f"{_fmt(t['trace_left_discards_ms'], 1)} ms.", "", cost_markdown(results), "",
               "![cost](fig_cost.png)", "", "## Figures", "", "![fig1](fig1_discards.png)", "",
               "![fig3](fig3_rmse.png)", "", "![fig4](fig4_comparison.png)", "",
               f"Effective-spp flags (stereo+temporal): {flags}. `extrapolated_high` means the value lies beyond "
               f"the ladder's top rung and was extrapolated on a fit of the ladder (see stereorepro.metrics).", ""]
    _atomic_write(out / "report.md", "\n".join(report))


def _write_frame_exr(root: Path, f: int, eyes: dict, drivers: dict) -> None:
    from .render import write_exr

    root.mkdir(parents=True, exist_ok=True)
    for e, d in eyes.items():
        name = "left" if e == LEFT else "right"
        drv = drivers["stereo_temporal"]
        state = drv.left_state if e == LEFT else drv.right_state
        chans = {c: state.color[0, i].numpy() for i, c in enumerate("RGB")}
        chans["Z"] = d.depth[0, 0].numpy()
        chans.update({f"N.{c}": d.normal[0, i].numpy() for i, c in enumerate("XYZ")})
        write_exr(root / f"{f:04d}_{name}.exr", chans)


# ---------------------------------------------------------------------------------------------------------------
# CLI

def add_arguments(p: argparse.ArgumentParser, defaults: dict | None = None) -> None:
    from .cli import parse_resolution

    d = defaults or {}
    p.add_argument("--scene", default=d.get("scene"), required="scene" not in d, help="built-in name or .toml path")
    p.add_argument("--frames", type=int, default=d.get("frames"), help="frames (default: the scene's)")
    p.add_argument("--resolution", type=parse_resolution, default=d.get("resolution", (320, 180)), help="WxH")
    p.add_argument("--reference-spp", type=int, default=d.get("reference_spp", 256))
    p.add_argument("--ladder-spp", type=int, default=d.get("ladder_spp", 16))
    p.add_argument("--out", default=d.get("out"), required="out" not in d)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--alphas", default="0.1,0.5", help="extra EMA weights measured beside 0.2")
    p.add_argument("--threshold-scale", default="auto", help="'auto' = max(1, 180/height), or a number")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--exr", action="store_true", help="also write EXR frames of both eyes")
    p.add_argument("--force", action="store_true", help="recompute cached renders")
    p.add_argument("--cache-dir", default=None, help="render cache (default: OUT/cache); runs may share one")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--metric", choices=("hdr", "ldr"), default="ldr",
                   help="RMSE on linear radiance (hdr) or on values clamped to [0, 1] (ldr, display-referred)")
    p.add_argument("--renderer-version", default=None,
                   help="cache key of a previous run's renderer (results.json 'code'): re-analyse its cached renders")


def config_from_args(args) -> ExperimentConfig:
    from .cli import UserError

    try:
        alphas = tuple(float(a) for a in args.alphas.split(",") if a.strip())
        scale = None if args.threshold_scale == "auto" else float(args.threshold_scale)
    except ValueError as e:
        raise UserError(f"bad --alphas/--threshold-scale: {e}") from None
    w, h = args.resolution
    return ExperimentConfig(scene=args.scene, out=args.out, frames=args.frames, width=w, height=h,
                            reference_spp=args.reference_spp, ladder_spp=args.ladder_spp, seed=args.seed,
                            alphas=alphas, threshold_scale=scale, workers=args.workers, exr=args.exr,
                            force=args.force, progress=not args.no_progress, renderer_version=args.renderer_version, cache_dir=args.cache_dir,
                            metric=args.metric)


def _cmd(args) -> int:
    from .cli import UserError

    cfg = config_from_args(args)
    try:
        results = run_experiment(cfg)
    except (ValueError, FileNotFoundError) as e:
        raise UserError(str(e)) from None
    print(tables_markdown(results))
    print(f"report: {Path(cfg.out) / 'report.md'} (figures and results.json beside it); "
          f"wall {results['wall_s']:.0f} s")
    return 0


def register(sub) -> None:
    p = sub.add_parser("experiment", help="the paper's experiment: effective spp, Tables 1-2, figures, time cost")
    add_arguments(p)
    p.set_defaults(func=_cmd)
