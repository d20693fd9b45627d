"""Reprojection as a denoiser's preprocessing: does a small learned denoiser gain from our temporal reprojection?

Two identical compact U-Nets are trained with the same budget, data and seed on frames of the built-in scenes
(right eye, 1 spp, against higher-spp references):

* **(a) plain**: input = 1-spp colour + albedo + shading normal (9 channels);
* **(b) reprojected**: the same, plus the outputs of :class:`~stereorepro.TemporalReprojection` run as the
  network's fixed first layer: accumulated colour, valid mask and history length (14 channels). The first layer
  has no trained parameters (hard accept tests, the scene's thresholds), so its outputs are computed once per
  clip and cached.

Held-out frames (later in each scene's camera path) are evaluated by RMSE against the references and converted
to effective spp (:func:`stereorepro.effective_spp_many`) with a per-frame ladder of plain path-traced prefixes at
1..L spp from the same renderer. The un-learned accumulation and the raw 1-spp input are reported alongside.

Run::

    python examples/denoiser_preprocess.py --smoke --out runs/denoiser     # < 60 s on 2 cores
    python examples/denoiser_preprocess.py --out runs/denoiser             # 3 scenes at 96x54, 1500 steps (~18 min)

Writes ``OUT/denoiser_preprocess.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
import sys
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from stereorepro import (
    PathTracer,
    TemporalReprojection,
    effective_spp_many,
    ladder_rmse,
    load_scene,
    rmse,
    temporal_step,
)
from stereorepro.camera import Eye

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _example_common import cpu_training_threads  # noqa: E402

REFERENCE_OFFSET = 1 << 24  # sample index of the references' stream: disjoint from the 1-spp inputs and ladders


@dataclass(frozen=True)
class Settings:
    scenes: tuple[str, ...]
    width: int
    height: int
    train_frames: tuple[int, int]  # [start, stop) of each scene's training clip
    test_frames: tuple[int, int]  # [start, stop) of each scene's held-out clip (accumulation starts at `start`)
    warmup: int  # held-out frames at the clip's start that are not evaluated (history builds up)
    reference_spp: int
    ladder_spp: int
    steps: int
    batch: int
    lr: float = 2e-3


SMOKE = Settings(("living_room", "atrium"), 64, 36, (0, 8), (40, 46), 2, 64, 8, 200, 4)
FULL = Settings(("living_room", "atrium", "classroom"), 96, 54, (0, 24), (36, 48), 4, 256, 16, 1500, 4)


# ------------------------------------------------------------------------------------------- data
def render_clip(scene_name: str, frames: range, s: Settings, ladder: bool, seed: int = 0) -> dict[str, Tensor]:
    """Right-eye frames of a clip: 1-spp colour, G-buffers, reference, (ladder) — stacked over frames (F, ...)."""
    scene = load_scene(scene_name)
    tracer = PathTracer(scene, seed=seed, workers=2)
    out: dict[str, list] = {k: [] for k in ("color", "depth", "normal", "albedo", "K", "T", "reference", "ladder")}
    for f in frames:
        _, cam = scene.stereo_cameras(f, s.width, s.height)
        r = tracer.render(cam, f, 1, sample_offset=0, eye=Eye.RIGHT)
        out["color"].append(r.radiance)
        out["depth"].append(r.depth)
        out["normal"].append(r.normal)
        out["albedo"].append(r.albedo)
        out["K"].append(cam.K)
        out["T"].append(cam.cam_from_world)
        out["reference"].append(
            tracer.render(
                cam, f, s.reference_spp, sample_offset=REFERENCE_OFFSET, eye=Eye.RIGHT, gbuffers=False
            ).radiance
        )
        if ladder:  # prefixes of the input's own sample stream: rung n = mean of samples 0..n-1
            total, rungs = r.radiance.double(), [r.radiance]
            for k in range(1, s.ladder_spp):
                sample = tracer.render(cam, f, 1, sample_offset=k, eye=Eye.RIGHT, gbuffers=False).radiance
                total = total + sample.double()
                rungs.append((total / (k + 1)).float())
            out["ladder"].append(torch.stack(rungs))  # Nx1x3xHxW
    res = {k: torch.cat(v) for k, v in out.items() if v and k != "ladder"}
    if ladder:
        res["ladder"] = torch.cat(out["ladder"], 1)  # NxFx3xHxW
    position_threshold, normal_threshold = scene.thresholds(s.height)
    res["position_threshold"] = torch.tensor(position_threshold)
    res["normal_threshold"] = torch.tensor(normal_threshold)
    return res


def accumulate(clip: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """Run :class:`TemporalReprojection` over a clip (first frame: no history). Returns colour, valid, history
    length, each (F, C, H, W)."""
    m = TemporalReprojection(float(clip["position_threshold"]), float(clip["normal_threshold"]), alpha=0.2)
    colors, valids, lens = [], [], []
    state = None
    with torch.no_grad():
        for i in range(clip["color"].shape[0]):
            cur = [clip[k][i : i + 1] for k in ("color", "depth", "normal", "K", "T")]
            state, valid, _ = temporal_step(m, state, *cur)
            colors.append(state.color)
            valids.append(valid.float())
            lens.append(state.history_len)
    return torch.cat(colors), torch.cat(valids), torch.cat(lens)


def features(clip: dict[str, Tensor], reprojected: bool) -> Tensor:
    """(F, 9 or 14, H, W) network input; colours in log1p space."""
    base = [torch.log1p(clip["color"].clamp_min(0)), clip["albedo"], clip["normal"]]
    if reprojected:
        acc, valid, n = clip["accumulated"], clip["valid"], clip["history_len"]
        base += [torch.log1p(acc.clamp_min(0)), valid, torch.log1p(n) / math.log(256.0)]
    return torch.cat(base, 1)


# ------------------------------------------------------------------------------------------- model
def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    """Compact two-level U-Net: (B, C_in, H, W) features → (B, 3, H, W) radiance.

    The first three input channels are ``log1p`` of the 1-spp colour (both variants); the network predicts a
    residual in that space, ``out = expm1(x[:, :3] + head)``, with the head initialised to zero, so training
    starts from the identity (the 1-spp input) for both variants.
    """

    def __init__(self, in_channels: int, width: int = 24):
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
        e1 = self.enc1(x)  # BxWxHxW
        e2 = self.enc2(F.max_pool2d(e1, 2))
        m = self.mid(F.max_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([F.interpolate(m, size=e2.shape[-2:]), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=e1.shape[-2:]), e1], 1))
        return torch.expm1((x[:, :3] + self.head(d1)).clamp_min(0.0))


def train(x: Tensor, target: Tensor, s: Settings, seed: int) -> tuple[UNet, float, float]:
    """Adam on MSE in log1p space (HDR-robust) over random batches of whole frames; same seed → same init and
    batch order for both variants."""
    torch.manual_seed(seed)
    model = UNet(x.shape[1])
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, s.steps)
    g = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    loss = torch.zeros(())
    for _ in range(s.steps):
        idx = torch.randint(0, x.shape[0], (s.batch,), generator=g)
        xb, tb = x[idx], target[idx]
        if torch.rand((), generator=g) < 0.5:  # horizontal flip (normals' x flips sign too; kept simple)
            xb, tb = xb.flip(-1), tb.flip(-1)
        loss = (torch.log1p(model(xb)) - torch.log1p(tb.clamp_min(0))).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return model.eval(), float(loss.detach()), time.perf_counter() - t0


# ------------------------------------------------------------------------------------------- main
def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny run for CI (< 60 s)")
    p.add_argument("--out", default="runs/denoiser", help="output directory")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    s = SMOKE if args.smoke else FULL
    with cpu_training_threads():
        return _run(s, args)


def _run(s: Settings, args) -> dict:
    t_start = time.perf_counter()

    train_clips, test_clips = [], []
    for name in s.scenes:
        for frames, ladder, bucket in (
            (range(*s.train_frames), False, train_clips),
            (range(*s.test_frames), True, test_clips),
        ):
            clip = render_clip(name, frames, s, ladder, seed=args.seed)
            clip["accumulated"], clip["valid"], clip["history_len"] = accumulate(clip)
            clip["scene"] = name
            bucket.append(clip)
    t_render = time.perf_counter() - t_start

    def cat(clips, key, lo=0):
        return torch.cat([c[key][lo:] for c in clips])

    target = cat(train_clips, "reference")
    results: dict = {
        "example": "denoiser_preprocess",
        "smoke": bool(args.smoke),
        "scenes": list(s.scenes),
        "width": s.width,
        "height": s.height,
        "train_frames": list(s.train_frames),
        "test_frames": list(s.test_frames),
        "warmup": s.warmup,
        "reference_spp": s.reference_spp,
        "ladder_spp": s.ladder_spp,
        "steps": s.steps,
        "batch": s.batch,
        "seed": args.seed,
        "methods": {},
    }
    models = {}
    for label, reproj in (("unet_plain", False), ("unet_reprojected", True)):
        x = torch.cat([features(c, reproj) for c in train_clips])
        model, last_loss, secs = train(x, target, s, args.seed)
        models[label] = (model, reproj)
        results["methods"][label] = {
            "input_channels": x.shape[1],
            "final_train_loss": last_loss,
            "train_seconds": secs,
            "parameters": sum(p.numel() for p in model.parameters()),
        }

    # held-out evaluation: per-frame RMSE and effective spp against each frame's own ladder
    ladder_spp = torch.arange(1, s.ladder_spp + 1, dtype=torch.float64)
    ref = cat(test_clips, "reference", s.warmup)
    ladders = torch.cat([c["ladder"][:, s.warmup :] for c in test_clips], 1)  # NxFx3xHxW
    ladder = ladder_rmse(ladders, ref)  # FxN
    outputs = {
        "input_1spp": cat(test_clips, "color", s.warmup),
        "accumulated": cat(test_clips, "accumulated", s.warmup),
    }
    with torch.no_grad():
        for label, (model, reproj) in models.items():
            outputs[label] = torch.cat([model(features(c, reproj)[s.warmup :]) for c in test_clips])
    for label, img in outputs.items():
        r = rmse(img, ref)
        spp, flags = effective_spp_many(r, ladder_spp, ladder)
        finite = spp[torch.isfinite(spp)]
        rec = results["methods"].setdefault(label, {})
        rec.update(
            rmse_mean=float(r.mean()),
            rmse_per_frame=r.tolist(),
            effective_spp_median=float(spp.median()),
            effective_spp_mean_finite=float(finite.mean()) if finite.numel() else None,
            effective_spp_per_frame=[x if math.isfinite(x) else None for x in spp.tolist()],
            flags={f: flags.count(f) for f in sorted(set(flags))},
        )
    results["held_out_frames"] = int(ref.shape[0])
    results["discard_pct_held_out"] = float(100 * (1 - cat(test_clips, "valid", s.warmup).mean()))
    results["seconds"] = {"render": t_render, "total": time.perf_counter() - t_start}

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "denoiser_preprocess.json").write_text(json.dumps(results, indent=1))
    print(
        f"denoiser_preprocess: {', '.join(s.scenes)} at {s.width}x{s.height}; {results['held_out_frames']} "
        f"held-out frames; {s.steps} steps per model; ladder 1..{s.ladder_spp} spp, reference {s.reference_spp} spp"
    )
    print(f"  {'method':18s} {'RMSE':>9s} {'eff. spp (median)':>18s}  flags")
    for label, rec in results["methods"].items():
        print(f"  {label:18s} {rec['rmse_mean']:9.4f} {rec['effective_spp_median']:18.2f}  {rec['flags']}")
    print(f"  ({results['seconds']['total']:.0f} s) -> {out / 'denoiser_preprocess.json'}")
    return results


if __name__ == "__main__":
    main()
