"""A recurrent learned denoiser on the reprojection layer, against the same network per frame, over several seeds.

One compact U-Net (:func:`build_network`) is trained twice on the same data, steps, batch, schedule and seeds:

* **recurrent**: every frame goes through :func:`stereorepro.reproject_denoise` with all its inputs: the temporal
  accumulation of the 1-spp colour, the network's **own previous output warped into this frame**, the other
  eye's output reprojected into this eye (the right eye runs first and gets an all-invalid other eye; the left eye
  gets the right eye's denoised frame), albedo, depth and normal;
* **per-frame**: the same call with a per-frame state (empty history, a zero previous output seen from a view
  with no surface, an all-invalid other eye), which zeroes every warped channel: the same network sees only this
  frame's 1-spp colour, albedo, depth and normal.

Training unrolls short sequences of both eyes (a few frames without gradients to fill the state, then ``unroll``
frames with backpropagation through the fed-back output); the loss, the same for both variants, is an L1 spatial
term in ``log1p`` space plus a temporal term in the manner of Chaitanya et al. 2017 (SIGGRAPH, "Interactive
reconstruction of Monte Carlo image sequences using a recurrent denoising autoencoder"): the L1 difference between
the output's change from the previous frame (the previous output warped by ``backward_reproject``) and the
reference's change, on the pixels the warp keeps.

Evaluation on held-out frames (later in the training scenes' camera paths) and a held-out scene, both eyes:
LDR RMSE, effective spp (a per-frame ladder of plain path-traced prefixes, :func:`stereorepro.effective_spp_many`),
FLIP and :func:`stereorepro.temporal_error` (flicker against the reference's own frame-to-frame change), with
the mean and spread over seeds; baselines on the same frames: the 1-spp input, plain temporal accumulation
(EMA 0.2), Intel OIDN per frame, OIDN on the accumulated input, and OIDN per frame followed by the same temporal
accumulation. This study supersedes ``examples/denoiser_preprocess.py`` (one seed, no temporal metric).

Run::

    python examples/recurrent_denoiser.py --smoke --out /tmp/rd      # CI: tiny, one seed each (< 90 s)
    python examples/recurrent_denoiser.py --out runs/recurrent_denoiser  # the study (see docs/guides/denoiser_study.md)

Writes (atomically) ``OUT/recurrent_denoiser.json`` (settings, commit, machine, timings, per-method per-seed
metrics), ``OUT/recurrent_denoiser.md`` (the table), ``OUT/<variant>_seed<k>.pt`` (checkpoints: ``state_dict``,
``network`` = ``{"name", "kwargs"}`` for :func:`build_network`, ``feature_options``, ``thresholds``,
``settings``) and, when the report builder is available, ``OUT/report.html``. Rendered data is cached under
``OUT/cache`` (one file per clip, keyed by the render settings), so a stopped run resumes without re-rendering.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from stereorepro import (
    reproject_denoise,
    temporal_error,
    PathTracer,
    TemporalReprojection,
    View,
    backward_reproject,
    effective_spp_many,
    empty_state,
    ladder_rmse,
    load_scene,
    rmse,
)
from stereorepro.accumulate import temporal_step
from stereorepro.camera import Eye
from stereorepro.io.atomic import atomic_path, atomic_write
from stereorepro.measure.metrics import flip

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _example_common import cpu_training_threads, provenance  # noqa: E402

REFERENCE_OFFSET = 1 << 24  # sample index of the references' stream: disjoint from the 1-spp inputs and ladders
CACHE_VERSION = 1
#: Eyes in processing order: the right eye first, so the left eye can read the right eye's denoised frame.
EYES = (("right", Eye.RIGHT), ("left", Eye.LEFT))
VARIANTS = ("recurrent", "per_frame")
#: Options of the features the network is trained on (stereorepro.denoise.feature_channels).
FEATURE_OPTIONS = {"stereo": True, "recurrent": True, "albedo": True}


@dataclass(frozen=True)
class Settings:
    train_scenes: tuple[str, ...]
    heldout_scenes: tuple[str, ...]  # evaluated only
    width: int
    height: int
    train_frames: tuple[int, int]  # [start, stop) of each training scene's clip
    test_frames: tuple[int, int]  # [start, stop) of every evaluated clip (a cold start at `start`)
    warmup: int  # test frames at the clip's start that are not scored (the state builds up)
    reference_spp: int  # training references
    test_reference_spp: int
    ladder: tuple[int, ...]  # rungs (spp) of the effective-spp ladder
    steps: int
    batch: int  # sequences per step (one scene per step)
    burn_in: int  # frames run without gradients before the unrolled ones (fills the state)
    unroll: int  # frames with backpropagation through time
    net_width: int
    seeds: tuple[int, ...]
    lr: float = 2e-3
    temporal_weight: float = 0.5


SMOKE = Settings(("living_room",), ("atrium",), 48, 28, (0, 8), (40, 45), 2, 16, 32, (1, 2, 4), 8, 1, 1, 2, 8, (0,))
FULL = Settings(
    ("living_room", "atrium", "living_room_glossy"),
    ("classroom",),
    96,
    54,
    (0, 36),
    (40, 54),
    4,
    256,
    512,
    (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64),
    500,
    2,
    2,
    4,
    16,
    (0, 1, 2),
)


# ------------------------------------------------------------------------------------------- network
def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    """Compact two-level U-Net: (B, C_in, H, W) features → (B, 3, H, W) radiance.

    The first three input channels are ``log1p`` of the accumulated colour (:data:`stereorepro.denoise.FEATURES`);
    the network predicts a residual in that space, ``out = expm1(max(x[:, :3] + head, 0))``, with the head
    initialised to zero, so training starts from its input colour. Any H, W (odd sizes too).
    """

    def __init__(self, in_channels: int, width: int = 16):
        super().__init__()
        self.enc1 = _block(in_channels, width)
        self.enc2 = _block(width, 2 * width)
        self.mid = _block(2 * width, 2 * width)
        self.dec2 = _block(4 * width, width)
        self.dec1 = _block(2 * width, width)
        self.head = nn.Conv2d(width, 3, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: Tensor) -> Tensor:
        e1 = self.enc1(x)  # (B, width, H, W)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        m = self.mid(F.max_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([F.interpolate(m, size=e2.shape[-2:]), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=e1.shape[-2:]), e1], 1))
        return torch.expm1((x[:, :3] + self.head(d1)).clamp_min(0.0))


def build_network(in_channels: int, width: int = 16) -> nn.Module:
    """The study's denoiser: a :class:`UNet` mapping (B, in_channels, H, W) features to (B, 3, H, W) radiance.

    Checkpoints name it as ``{"name": "recurrent_denoiser.build_network", "kwargs": {"in_channels", "width"}}``.
    """
    return UNet(in_channels, width)


def in_channels() -> int:
    """C_in of the study's features: stereo (4), recurrent (3) and albedo (3) channels after the 9 base ones."""
    from stereorepro.denoise import feature_channels

    return feature_channels(**FEATURE_OPTIONS)


# ------------------------------------------------------------------------------------------- data
def _cache_key(scene: str, frames: tuple[int, int], s: Settings, test: bool) -> str:
    spec = {
        "v": CACHE_VERSION,
        "scene": scene,
        "frames": list(frames),
        "size": [s.width, s.height],
        "reference_spp": s.test_reference_spp if test else s.reference_spp,
        "ladder": list(s.ladder) if test else None,
    }
    digest = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:12]
    return f"{scene}_{frames[0]}-{frames[1]}_{s.width}x{s.height}_{'test' if test else 'train'}_{digest}"


def _ldr(x: Tensor) -> Tensor:
    return x.clamp(0.0, 1.0)


def _render_eye(tracer, scene, eye: Eye, frames: range, s: Settings, ref_spp: int, ladder: tuple) -> dict:
    """One eye of a clip, stacked over frames (F, ...): 1-spp colour, G-buffers, cameras, reference and (ladder)
    the LDR RMSE of each rung (F, N) against the reference."""
    out: dict[str, list] = {k: [] for k in ("color", "depth", "normal", "albedo", "K", "T", "reference", "ladder")}
    for f in frames:
        cam = scene.stereo_cameras(f, s.width, s.height)[int(eye)]
        r = tracer.render(cam, f, 1, sample_offset=0, eye=eye)
        ref = tracer.render(cam, f, ref_spp, sample_offset=REFERENCE_OFFSET, eye=eye, gbuffers=False).radiance
        for k, v in (("color", r.radiance), ("depth", r.depth), ("normal", r.normal), ("albedo", r.albedo)):
            out[k].append(v)
        out["K"].append(cam.K)
        out["T"].append(cam.cam_from_world)
        out["reference"].append(ref)
        if ladder:  # prefixes of the input's own sample stream: rung n = mean of samples 0..n-1
            total, rungs = r.radiance.double(), []
            for k in range(1, ladder[-1] + 1):
                if k > 1:
                    total = total + tracer.render(cam, f, 1, sample_offset=k - 1, eye=eye, gbuffers=False).radiance
                if k in ladder:
                    rungs.append(_ldr((total / k).float()))
            out["ladder"].append(ladder_rmse(rungs, _ldr(ref)))  # (1, N)
    return {k: torch.cat(v) for k, v in out.items() if v}


def load_clip(scene_name: str, frames: tuple[int, int], s: Settings, test: bool, cache: Path) -> dict:
    """Both eyes of a clip (``clip[eye][key]``, (F, ...) tensors), from the cache or rendered and cached
    (``torch.save``, atomic), plus the scene's thresholds."""
    path = cache / f"{_cache_key(scene_name, frames, s, test)}.pt"
    if path.exists():
        return torch.load(path, weights_only=True)
    scene = load_scene(scene_name)
    tracer = PathTracer(scene, seed=0, workers=2)
    ref_spp = s.test_reference_spp if test else s.reference_spp
    clip = {
        name: _render_eye(tracer, scene, eye, range(*frames), s, ref_spp, s.ladder if test else ())
        for name, eye in EYES
    }
    clip["thresholds"] = torch.tensor(scene.thresholds(s.height), dtype=torch.float64)
    with atomic_path(path) as tmp:
        torch.save(clip, tmp)
    return clip


# ------------------------------------------------------------------------------------------- the unrolled sequence
def _view(eye_data: dict, idx: Tensor) -> View:
    """The views of frames ``idx`` (B,) of one eye's cached data (checked when the clip was rendered)."""
    return View.unchecked(eye_data["depth"][idx], eye_data["normal"][idx], eye_data["K"][idx], eye_data["T"][idx])


def sequence(net: nn.Module, clip: dict, starts: Tensor, count: int, recurrent: bool, grad_from: int = 0):
    """Run the denoiser over frames ``starts + k`` (k < count) of both eyes (a cold start at ``starts``).

    Yields ``(k, outputs, views)`` per frame, both dicts keyed by eye name; frames before ``grad_from`` run without
    gradients (their outputs only fill the state). The per-frame variant (``recurrent=False``) sees the cold state
    and an all-invalid other eye at every frame.
    """
    thr = tuple(float(t) for t in clip["thresholds"])
    states: dict = {}
    for k in range(count):
        idx = starts + k
        outputs, views = {}, {}
        with torch.set_grad_enabled(torch.is_grad_enabled() and k >= grad_from):
            for name, _ in EYES:
                d = clip[name]
                view = _view(d, idx)
                cold = empty_state(view, recurrent=True, stereo=True)
                history, prev_view, prev_out = states[name] if recurrent and name in states else cold[:3]
                if recurrent and name == "left":
                    other = (outputs["right"], views["right"])  # the right eye's denoised frame
                else:
                    other = cold.other  # an other eye with no surface: the stereo channels are 0
                res = reproject_denoise(
                    d["color"][idx],
                    view,
                    history,
                    prev_view,
                    net,
                    thr,
                    other=other,
                    previous_output=prev_out,
                    albedo=d["albedo"][idx],
                )
                states[name] = (res.history, view, res.denoised)
                outputs[name], views[name] = res.denoised, view
        yield k, outputs, views


def sequence_loss(net: nn.Module, clip: dict, starts: Tensor, s: Settings, recurrent: bool) -> Tensor:
    """The training loss of one unrolled batch: per unrolled frame and eye, L1 in ``log1p`` space plus
    ``temporal_weight`` times the L1 of (output change − reference change) after warping the previous frame,
    on the warp's valid pixels."""
    thr = tuple(float(t) for t in clip["thresholds"])
    total, terms, prev = torch.zeros(()), 0, {}
    for k, outputs, views in sequence(net, clip, starts, s.burn_in + s.unroll, recurrent, grad_from=s.burn_in):
        idx = starts + k
        for name, _ in EYES:
            out = torch.log1p(outputs[name].clamp_min(0.0))
            ref = torch.log1p(clip[name]["reference"][idx].clamp_min(0.0))
            if k >= s.burn_in:
                loss = (out - ref).abs().mean()
                if name in prev:
                    p_out, p_ref, p_view = prev[name]
                    warped = backward_reproject(torch.cat([p_out, p_ref], 1), p_view, views[name], thr)
                    change = (out - warped.values[:, :3]) - (ref - warped.values[:, 3:])
                    w = warped.valid.to(change.dtype)
                    loss = loss + s.temporal_weight * (change.abs() * w).sum() / (3 * w.sum()).clamp_min(1.0)
                total, terms = total + loss, terms + 1
            prev[name] = (out, ref, views[name])
    return total / terms


def train(clips: list[dict], s: Settings, recurrent: bool, seed: int) -> tuple[nn.Module, dict]:
    """Adam with a cosine schedule over ``s.steps`` unrolled batches; the seed fixes the initial weights and the
    order of scenes and start frames (identical for both variants)."""
    torch.manual_seed(seed)
    net = build_network(in_channels(), s.net_width)
    opt = torch.optim.Adam(net.parameters(), lr=s.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, s.steps)
    g = torch.Generator().manual_seed(seed)
    span = s.burn_in + s.unroll
    t0, losses = time.perf_counter(), []
    for _ in range(s.steps):
        clip = clips[int(torch.randint(0, len(clips), (1,), generator=g))]
        frames = clip["right"]["color"].shape[0]
        starts = torch.randint(0, frames - span + 1, (s.batch,), generator=g)
        loss = sequence_loss(net, clip, starts, s, recurrent)
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    tail = losses[-max(1, len(losses) // 10) :]
    return net.eval(), {"train_seconds": time.perf_counter() - t0, "final_train_loss": statistics.mean(tail)}


# ------------------------------------------------------------------------------------------- methods
def oidn(color: Tensor, albedo: Tensor, normal: Tensor) -> Tensor:
    """Intel OIDN (RT filter, HDR, albedo and normal auxiliary images) on every frame of (F, 3, H, W)."""
    import pyoidn

    def hwc(x: Tensor, lo=None, hi=None) -> np.ndarray:
        return np.ascontiguousarray(x.permute(1, 2, 0).numpy().astype(np.float32).clip(lo, hi))

    frames = [
        torch.from_numpy(np.asarray(pyoidn.denoise(hwc(c, 0, None), albedo=hwc(a, 0, 1), normal=hwc(n), hdr=True)))
        for c, a, n in zip(color, albedo, normal)
    ]
    return torch.stack(frames).permute(0, 3, 1, 2).contiguous()


def accumulate(eye_data: dict, images: Tensor, thresholds: Tensor) -> Tensor:
    """Plain temporal accumulation (:func:`~stereorepro.accumulate.temporal_step`, EMA 0.2 after warm-up) of
    ``images`` (F, 3, H, W) over one eye's clip, from a cold start."""
    module = TemporalReprojection(float(thresholds[0]), float(thresholds[1]), alpha=0.2)
    state, out = None, []
    for i in range(images.shape[0]):
        g = [eye_data[k][i : i + 1] for k in ("depth", "normal", "K", "T")]
        state, _, _ = temporal_step(module, state, images[i : i + 1], *g)
        out.append(state.color)
    return torch.cat(out)


#: The baselines, in table order.
BASELINES = ("1 spp", "accumulation", "OIDN per frame", "OIDN(accumulation)", "OIDN, then accumulation")


def baseline_outputs(clip: dict) -> dict[str, dict[str, Tensor]]:
    """``{method: {eye: (F, 3, H, W)}}`` of the baselines on one clip."""
    out: dict[str, dict[str, Tensor]] = {m: {} for m in BASELINES}
    for name, _ in EYES:
        d = clip[name]
        acc = accumulate(d, d["color"], clip["thresholds"])
        per_frame = oidn(d["color"], d["albedo"], d["normal"])
        out["1 spp"][name] = d["color"]
        out["accumulation"][name] = acc
        out["OIDN per frame"][name] = per_frame
        out["OIDN(accumulation)"][name] = oidn(acc, d["albedo"], d["normal"])
        out["OIDN, then accumulation"][name] = accumulate(d, per_frame, clip["thresholds"])
    return out


def network_outputs(net: nn.Module, clip: dict, recurrent: bool) -> dict[str, Tensor]:
    """``{eye: (F, 3, H, W)}``: the network over the whole clip from a cold start (both eyes, no gradients)."""
    frames = clip["right"]["color"].shape[0]
    out: dict[str, list] = {name: [] for name, _ in EYES}
    with torch.no_grad():
        for _, outputs, _ in sequence(net, clip, torch.zeros(1, dtype=torch.long), frames, recurrent):
            for name in out:
                out[name].append(outputs[name])
    return {name: torch.cat(v) for name, v in out.items()}


# ------------------------------------------------------------------------------------------- metrics
def score(images: Tensor, eye_data: dict, thresholds: Tensor, s: Settings) -> dict[str, list]:
    """Per scored frame (``warmup`` onwards) of one eye: LDR RMSE, effective spp on the frame's ladder, FLIP and
    :func:`~stereorepro.temporal_error` against the previous frame."""
    w = s.warmup
    img, ref = images[w:], eye_data["reference"][w:]
    r = rmse(_ldr(img), _ldr(ref))
    spp, flags = effective_spp_many(r, torch.tensor(s.ladder, dtype=torch.float64), eye_data["ladder"][w:])
    idx = torch.arange(w, images.shape[0])
    thr = tuple(float(t) for t in thresholds)
    te = temporal_error(
        img,
        ref,
        images[w - 1 : -1],
        eye_data["reference"][w - 1 : -1],
        _view(eye_data, idx),
        _view(eye_data, idx - 1),
        thr,
    )
    # where the temporal reprojection keeps a history (the other pixels are disoccluded or new in the frame)
    kept = backward_reproject(torch.ones_like(img[:, :1]), _view(eye_data, idx - 1), _view(eye_data, idx), thr).valid
    sq = (_ldr(img) - _ldr(ref)).double().pow(2).mean(1, keepdim=True)
    return {
        "rmse": r.tolist(),
        "effective_spp": [x if math.isfinite(x) else None for x in spp.tolist()],
        "spp_flags": flags,
        "flip": flip(img, ref).tolist(),
        "temporal_error": te.tolist(),
        "sq_history": (sq * kept).sum((1, 2, 3)).tolist(),
        "n_history": kept.sum((1, 2, 3)).tolist(),
        "sq_no_history": (sq * ~kept).sum((1, 2, 3)).tolist(),
        "n_no_history": (~kept).sum((1, 2, 3)).tolist(),
    }


def _pooled(scores: list[dict]) -> dict:
    """Means over frames and eyes of a list of :func:`score` results (effective spp: the median, frames beyond
    the ladder's floor counted as above it); RMSE over the pixels with and without a reprojected history (pixel
    RMSE pooled over the frames)."""
    cat = {k: [v for sc in scores for v in sc[k]] for k in scores[0] if k != "spp_flags"}
    spp = [math.inf if v is None else v for v in cat["effective_spp"]]
    n_new, n_old = sum(cat["n_no_history"]), sum(cat["n_history"])
    return {
        "rmse_history": math.sqrt(sum(cat["sq_history"]) / n_old) if n_old else math.nan,
        "rmse_no_history": math.sqrt(sum(cat["sq_no_history"]) / n_new) if n_new else math.nan,
        "no_history_share": n_new / (n_new + n_old),
        "rmse": statistics.mean(cat["rmse"]),
        "effective_spp_median": statistics.median(spp),
        "beyond_ladder_share": sum(1 for v in spp if math.isinf(v)) / len(spp),
        "flip": statistics.mean(cat["flip"]),
        "temporal_error": statistics.mean(v for v in cat["temporal_error"] if math.isfinite(v)),
        "frames": len(spp),
    }


def summarise(per_clip: dict[str, dict[str, dict]], groups: dict[str, list[str]]) -> dict:
    """``per_clip[clip][eye]`` scores → pooled metrics over all clips and eyes, per group of clips and per eye."""
    everything = [sc for eyes in per_clip.values() for sc in eyes.values()]
    out = {"all": _pooled(everything)}
    for group, names in groups.items():
        out[group] = _pooled([per_clip[n][e] for n in names for e in per_clip[n]])
    for name, _ in EYES:
        out[f"{name} eye"] = _pooled([eyes[name] for eyes in per_clip.values()])
    return out


def spread(values: list[float]) -> dict:
    """Mean, standard deviation (n − 1), min and max over seeds."""
    return {
        "mean": statistics.mean(values),
        "std": statistics.stdev(values) if len(values) > 1 else 0.0,
        "min": min(values),
        "max": max(values),
        "n": len(values),
    }


# ------------------------------------------------------------------------------------------- the run
TRAIN_VERSION = 1  # bump when training changes: a checkpoint of another version is retrained, not reused


def _variant_seed(variant: str, seed: int) -> str:
    return f"{variant}_seed{seed}"


def train_or_load(clips: list[dict], s: Settings, variant: str, seed: int, out: Path, thresholds: dict):
    """Train one network, or load its checkpoint when one of the same settings and training version exists (a
    stopped run resumes); the checkpoint is written atomically."""
    path = out / f"{_variant_seed(variant, seed)}.pt"
    settings = dataclasses.asdict(s)
    if path.exists():
        ckpt = torch.load(path, weights_only=False)
        if ckpt.get("settings") == settings and ckpt.get("train_version") == TRAIN_VERSION:
            net = build_network(**ckpt["network"]["kwargs"])
            net.load_state_dict(ckpt["state_dict"])
            return net.eval(), {**ckpt["training"], "loaded_from_checkpoint": True}
    net, info = train(clips, s, variant == "recurrent", seed)
    info["parameters"] = sum(p.numel() for p in net.parameters())
    ckpt = {
        "state_dict": net.state_dict(),
        "network": {
            "name": "recurrent_denoiser.build_network",
            "kwargs": {"in_channels": in_channels(), "width": s.net_width},
        },
        "feature_options": dict(FEATURE_OPTIONS),
        "variant": variant,
        "per_frame_state": variant != "recurrent",
        "thresholds": thresholds,
        "settings": settings,
        "train_version": TRAIN_VERSION,
        "training": info,
    }
    with atomic_path(path) as tmp:
        torch.save(ckpt, tmp)
    return net, info


def _provenance() -> dict:
    return provenance("examples/recurrent_denoiser.py", "stereorepro")


def _load_all(s: Settings, cache: Path) -> tuple[list[dict], dict[str, dict], dict[str, list[str]]]:
    train_clips = [load_clip(n, s.train_frames, s, False, cache) for n in s.train_scenes]
    test = {f"{n} (frames {s.test_frames[0]}-{s.test_frames[1] - 1})": n for n in s.train_scenes + s.heldout_scenes}
    test_clips = {label: load_clip(n, s.test_frames, s, True, cache) for label, n in test.items()}
    groups = {
        "held-out frames": [lbl for lbl, n in test.items() if n in s.train_scenes],
        "held-out scene": [lbl for lbl, n in test.items() if n in s.heldout_scenes],
    }
    return train_clips, test_clips, groups


def evaluate(nets: dict, test_clips: dict, groups: dict, s: Settings) -> tuple[dict, dict]:
    """Scores of every method (networks: per seed) and the left-eye frames the report shows
    (``shown[clip][method]``, networks at their first seed)."""
    methods: dict = {}
    shown: dict = {label: {} for label in test_clips}
    per_clip: dict = {m: {} for m in BASELINES}
    for label, clip in test_clips.items():
        for m, eyes in baseline_outputs(clip).items():
            per_clip[m][label] = {e: score(img, clip[e], clip["thresholds"], s) for e, img in eyes.items()}
            shown[label][m] = eyes["left"]
        shown[label]["reference"] = clip["left"]["reference"]
    for m in BASELINES:
        methods[m] = {"kind": "baseline", "metrics": summarise(per_clip[m], groups)}
    for variant in VARIANTS:
        rec = methods[f"U-Net {variant}"] = {"kind": "network", "seeds": {}}
        for seed, net in nets[variant].items():
            scores, seconds, frames = {}, 0.0, 0
            for label, clip in test_clips.items():
                t0 = time.perf_counter()
                eyes = network_outputs(net, clip, variant == "recurrent")
                seconds += time.perf_counter() - t0
                frames += clip["right"]["color"].shape[0]
                scores[label] = {e: score(img, clip[e], clip["thresholds"], s) for e, img in eyes.items()}
                if seed == min(nets[variant]):
                    shown[label][f"U-Net {variant}"] = eyes["left"]
            rec["seeds"][str(seed)] = summarise(scores, groups)
            rec.setdefault("ms_per_stereo_frame", {})[str(seed)] = 1e3 * seconds / frames  # both eyes, 1 thread
        rec["spread"] = {
            group: {k: spread([m[group][k] for m in rec["seeds"].values()]) for k in METRIC_KEYS}
            for group in next(iter(rec["seeds"].values()))
        }
    return methods, shown


#: The pooled metrics that get a spread over seeds.
METRIC_KEYS = ("rmse", "effective_spp_median", "flip", "temporal_error", "rmse_history", "rmse_no_history")


def _cell(rec: dict, group: str, key: str, digits: int) -> str:
    if rec["kind"] == "baseline":
        v = rec["metrics"][group][key]
        return "> ladder" if math.isinf(v) else f"{v:.{digits}f}"
    sp = rec["spread"][group][key]
    if not math.isfinite(sp["mean"]):
        return "> ladder"
    return f"{sp['mean']:.{digits}f} ± {sp['std']:.{digits}f} ({sp['min']:.{digits}f}–{sp['max']:.{digits}f})"


#: The table's columns: (metric key, header, digits).
COLUMNS = (
    ("rmse", "LDR RMSE ↓", 4),
    ("effective_spp_median", "eff. spp ↑", 1),
    ("flip", "FLIP ↓", 4),
    ("temporal_error", "temporal error ↓", 4),
)


#: The columns of the table of where the error is: pixels with and without a reprojected history.
WHERE_COLUMNS = (
    ("rmse_history", "LDR RMSE, pixels with history ↓", 4),
    ("rmse_no_history", "LDR RMSE, disoccluded pixels ↓", 4),
)


def table_rows(methods: dict, group: str, columns=COLUMNS) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of one group's table."""
    header = ["method"] + [c[1] for c in columns]
    return header, [[m] + [_cell(rec, group, k, d) for k, _, d in columns] for m, rec in methods.items()]


def table(methods: dict, groups: list[str]) -> str:
    """The study's Markdown tables: all scored frames, then per group (held-out frames / held-out scene)."""
    lines = []
    for group in ("all", *groups):
        header, rows = table_rows(methods, group)
        lines += [f"**{group}**", "", "| " + " | ".join(header) + " |", "|---|" + "---:|" * len(COLUMNS)]
        lines += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    share = methods["1 spp"]["metrics"]["all"]["no_history_share"]  # the same pixels for every method
    header, rows = table_rows(methods, "all", WHERE_COLUMNS)
    lines += [f"**where (all; {100 * share:.1f} % of the scored pixels are disoccluded)**", ""]
    lines += ["| " + " | ".join(header) + " |", "|---|" + "---:|" * len(WHERE_COLUMNS)]
    lines += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    return "\n".join(lines)


def _flicker_map(images: Tensor, reference: Tensor, eye_data: dict, thresholds: Tensor, f: int) -> Tensor:
    """(H, W) per-pixel |change − reference change| (LDR, mean over channels) from frame f − 1 to f, 0 where the
    warp rejects the pixel: what :func:`~stereorepro.temporal_error` averages."""
    idx = torch.tensor([f])
    prev = torch.cat([_ldr(images[f - 1 : f]), _ldr(reference[f - 1 : f])], 1)
    thr = tuple(float(t) for t in thresholds)
    w = backward_reproject(prev, _view(eye_data, idx - 1), _view(eye_data, idx), thr)
    d = (_ldr(images[f : f + 1]) - w.values[:, :3]) - (_ldr(reference[f : f + 1]) - w.values[:, 3:])
    return (d.abs().mean(1, keepdim=True) * w.valid)[0, 0]


def write_report(path: Path, results: dict, shown: dict, test_clips: dict) -> None:
    """``report.html``: the tables, and per held-out clip (left eye, last frame) a slider comparison of every
    method against the reference, error maps and flicker maps (:func:`_flicker_map`)."""
    from stereorepro.workflows.html_report import Page, abs_error, colorize, full_frame, worst_crop

    s = results["settings"]
    page = Page("Recurrent denoiser study")
    page.text(
        f"Left eye, {s['width']}x{s['height']}, 1 spp input; networks shown at seed {s['seeds'][0]}. "
        "Tables: mean ± std (min–max) over seeds. Temporal error: `stereorepro.temporal_error` (0 = as steady as "
        "the reference)."
    )
    page.section("Tables")
    for group in ("all", *results["groups"]):
        header, rows = table_rows(results["methods"], group)
        page.table(rows, header=header, caption=group)
    header, rows = table_rows(results["methods"], "all", WHERE_COLUMNS)
    page.table(rows, header=header, caption="where the error is (all scored frames)")
    for label, images in shown.items():
        clip, f = test_clips[label], images["reference"].shape[0] - 1
        ref = images["reference"][f]
        methods = {m: v[f] for m, v in images.items() if m != "reference"}
        page.section(f"{label}, left eye, frame {s['test_frames'][0] + f}")
        focus = abs_error(methods["U-Net per_frame"], ref)
        page.compare(methods, ref, crops=[full_frame(ref), worst_crop(focus, min(32, ref.shape[-2]))])
        errors = {m: abs_error(v, ref) for m, v in methods.items()}
        vmax = float(np.percentile(errors["accumulation"], 99)) or 1.0
        page.text(f"Absolute error against the reference (black 0, light yellow ≥ {vmax:.3f}).")
        page.gallery({m: colorize(e, vmax) for m, e in errors.items()}, scale=2)
        flicker = {
            m: _flicker_map(images[m], images["reference"], clip["left"], clip["thresholds"], f) for m in methods
        }
        fmax = float(np.percentile(flicker["accumulation"].numpy(), 99)) or 1.0
        page.text(
            f"Flicker from frame {s['test_frames'][0] + f - 1} to this one: |change − reference change| after "
            f"warping (black 0, light yellow ≥ {fmax:.3f}; pixels the warp rejects are black)."
        )
        page.gallery({m: colorize(v, fmax) for m, v in flicker.items()}, scale=2)
    page.write(path)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny run for CI (< 90 s on 2 cores)")
    p.add_argument("--out", default="runs/recurrent_denoiser", help="output directory")
    p.add_argument("--cache", default=None, help="render cache directory (default: OUT/cache)")
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    args = p.parse_args(argv)
    s = SMOKE if args.smoke else FULL
    with cpu_training_threads():
        return _run(s, args)


def _run(s: Settings, args) -> dict:
    t_start = time.perf_counter()
    out = Path(args.out)
    cache = Path(args.cache) if args.cache else out / "cache"
    train_clips, test_clips, groups = _load_all(s, cache)
    seconds: dict = {"data": time.perf_counter() - t_start}
    thresholds = {
        label: [float(t) for t in c["thresholds"]]
        for label, c in (*zip(s.train_scenes, train_clips), *test_clips.items())
    }
    nets: dict = {v: {} for v in VARIANTS}
    training: dict = {v: {} for v in VARIANTS}
    t0 = time.perf_counter()
    for seed in s.seeds:
        for variant in VARIANTS:
            nets[variant][seed], training[variant][str(seed)] = train_or_load(
                train_clips, s, variant, seed, out, thresholds
            )
            print(f"  trained {_variant_seed(variant, seed)}: {training[variant][str(seed)]}", flush=True)
    seconds["training"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    methods, shown = evaluate(nets, test_clips, groups, s)
    seconds["evaluation"] = time.perf_counter() - t0
    results = {
        "example": "recurrent_denoiser",
        "smoke": bool(args.smoke),
        "settings": dataclasses.asdict(s),
        "feature_options": dict(FEATURE_OPTIONS),
        "in_channels": in_channels(),
        **_provenance(),
        "test_clips": {label: groups_of(label, groups) for label in test_clips},
        "groups": list(groups),
        "thresholds": thresholds,
        "training": training,
        "methods": methods,
        "seconds": seconds,
        "checkpoints": {f"{v}": [f"{_variant_seed(v, k)}.pt" for k in s.seeds] for v in VARIANTS},
    }
    results["table"] = table(methods, list(groups))
    seconds["total_before_report"] = time.perf_counter() - t_start
    if not args.no_report:
        t0 = time.perf_counter()
        write_report(out / "report.html", results, shown, test_clips)
        seconds["report"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_start
    atomic_write(out / "recurrent_denoiser.json", json.dumps(_json_safe(results), indent=1, allow_nan=False))
    atomic_write(out / "recurrent_denoiser.md", _markdown(results))
    print(results["table"])
    print(f"  ({seconds['total']:.0f} s) -> {out / 'recurrent_denoiser.json'}")
    return results


def _json_safe(x):
    """``x`` with every non-finite float as None (an effective spp beyond the ladder is +inf in memory)."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return None if isinstance(x, float) and not math.isfinite(x) else x


def groups_of(label: str, groups: dict) -> list[str]:
    return [g for g, names in groups.items() if label in names]


def _markdown(results: dict) -> str:
    s = results["settings"]
    records = [r for seeds in results["training"].values() for r in seeds.values()]
    train = sum(r["train_seconds"] for r in records)
    loaded = sum(1 for r in records if r.get("loaded_from_checkpoint"))
    head = (
        f"# Recurrent denoiser study\n\nTrained on {', '.join(s['train_scenes'])} frames "
        f"{s['train_frames'][0]}-{s['train_frames'][1] - 1}; scored on frames {s['test_frames'][0] + s['warmup']}-"
        f"{s['test_frames'][1] - 1} of those scenes (held-out frames) and of {', '.join(s['heldout_scenes'])} "
        f"(held-out scene), both eyes, {s['width']}x{s['height']}, 1 spp input, references "
        f"{s['test_reference_spp']} spp. Networks: mean ± std (min–max) over seeds {list(s['seeds'])}.\n\n"
        f"Commit {results['commit']}, {results['machine']['cpu']} ({results['machine']['cpu_count']} cores): "
        f"{results['seconds']['total']:.0f} s for this run; the networks' training {train:.0f} s in all"
        f"{f' ({loaded} of them loaded from checkpoints here)' if loaded else ''}.\n\n"
    )
    return head + results["table"]


if __name__ == "__main__":
    main()
