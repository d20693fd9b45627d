"""Learn the reprojection's accept thresholds and EMA weight end to end, and compare them with the hand-set ones.

The paper sets the position and normal limits per scene by hand and blends with a fixed 20 % EMA. Here
:class:`~stereorepro.TemporalReprojection` runs with ``soft=True``: the accept tests become sigmoids, so the
position threshold, the normal threshold and ``alpha`` are ``nn.Parameter``s. Adam minimises the RMSE of the
accumulated right eye against higher-spp references over short windows of training frames (backpropagating
through the recurrence). The learned values are then evaluated with **hard** tests on held-out frames, next to
the scene's hand-set values (``Scene.thresholds(height)``: the position threshold scaled by ``max(1, 180 / height)``),
as RMSE and effective spp (per-frame ladders of 1..L spp prefixes from the same renderer).

Run::

    python examples/train_thresholds.py --smoke --out runs/thresholds      # < 60 s on 2 cores
    python examples/train_thresholds.py --out runs/thresholds              # 96x54, more frames and steps

Writes ``OUT/train_thresholds.json``.
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
from torch import Tensor

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

REFERENCE_OFFSET = 1 << 24  # sample index of the references' stream: disjoint from the inputs and ladders


@dataclass(frozen=True)
class Settings:
    width: int
    height: int
    train_frames: tuple[int, int]  # [start, stop)
    test_frames: tuple[int, int]  # [start, stop); accumulation starts at `start`
    warmup: int  # held-out frames not evaluated while the history builds up
    window: int  # frames per training window (truncated backpropagation through time)
    reference_spp: int
    ladder_spp: int
    steps: int
    lr: float = 0.01


SMOKE = Settings(64, 36, (0, 16), (40, 50), 3, 8, 64, 8, 40)
FULL = Settings(96, 54, (0, 30), (36, 60), 4, 10, 256, 16, 200)


def render_clip(scene, frames: range, s: Settings, ladder: bool, seed: int = 0) -> dict[str, Tensor]:
    """Right-eye frames of a clip (F, ...): 1-spp colour, depth, normal, cameras, reference, (ladder N×F×3×H×W)."""
    tracer = PathTracer(scene, seed=seed, workers=2)
    out: dict[str, list] = {k: [] for k in ("color", "depth", "normal", "K", "T", "reference", "ladder")}
    for f in frames:
        _, cam = scene.stereo_cameras(f, s.width, s.height)
        r = tracer.render(cam, f, 1, sample_offset=0, eye=Eye.RIGHT)
        for k, v in (
            ("color", r.radiance),
            ("depth", r.depth),
            ("normal", r.normal),
            ("K", cam.K),
            ("T", cam.cam_from_world),
        ):
            out[k].append(v)
        out["reference"].append(
            tracer.render(
                cam, f, s.reference_spp, sample_offset=REFERENCE_OFFSET, eye=Eye.RIGHT, gbuffers=False
            ).radiance
        )
        if ladder:
            total, rungs = r.radiance.double(), [r.radiance]
            for k in range(1, s.ladder_spp):
                sample = tracer.render(cam, f, 1, sample_offset=k, eye=Eye.RIGHT, gbuffers=False).radiance
                total = total + sample.double()
                rungs.append((total / (k + 1)).float())
            out["ladder"].append(torch.stack(rungs))
    res = {k: torch.cat(v) for k, v in out.items() if v and k != "ladder"}
    if ladder:
        res["ladder"] = torch.cat(out["ladder"], 1)
    return res


def accumulate(module: TemporalReprojection, clip: dict[str, Tensor], lo: int, hi: int) -> tuple[Tensor, Tensor]:
    """Accumulate frames [lo, hi) of a clip from no history. Returns colour (F, 3, H, W) and valid (F, 1, H, W)."""
    colors, valids = [], []
    state = None
    for i in range(lo, hi):
        state, valid, _ = temporal_step(
            module, state, *[clip[k][i : i + 1] for k in ("color", "depth", "normal", "K", "T")]
        )
        colors.append(state.color)
        valids.append(valid)
    return torch.cat(colors), torch.cat(valids)


def values(m: TemporalReprojection) -> dict[str, float]:
    return {k: float(getattr(m, k).detach()) for k in ("position_threshold", "normal_threshold", "alpha")}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny run for CI (< 60 s)")
    p.add_argument("--out", default="runs/thresholds", help="output directory")
    p.add_argument(
        "--scene",
        default="living_room_moving_light",
        help="built-in scene (a moving light makes alpha a real trade-off: lag vs noise)",
    )
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    s = SMOKE if args.smoke else FULL
    with cpu_training_threads():
        return _run(s, args)


def _run(s: Settings, args) -> dict:
    t_start = time.perf_counter()
    scene = load_scene(args.scene)
    train = render_clip(scene, range(*s.train_frames), s, False, args.seed)
    test = render_clip(scene, range(*s.test_frames), s, True, args.seed)
    t_render = time.perf_counter() - t_start

    position_threshold, normal_threshold = scene.thresholds(s.height)
    hand = {"position_threshold": position_threshold, "normal_threshold": normal_threshold, "alpha": 0.2}
    model = TemporalReprojection(hand["position_threshold"], hand["normal_threshold"], hand["alpha"], soft=True)
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    floor = {"position_threshold": 1e-3 * hand["position_threshold"], "normal_threshold": 1e-3}
    g = torch.Generator().manual_seed(args.seed)
    n_train = train["color"].shape[0]
    history, nonfinite = [], []
    t0 = time.perf_counter()
    for step in range(s.steps):
        lo = int(torch.randint(0, n_train - s.window + 1, (), generator=g))
        color, _ = accumulate(model, train, lo, lo + s.window)
        loss = rmse(color[1:], train["reference"][lo + 1 : lo + s.window]).mean()  # frame 0 has no history
        opt.zero_grad()
        loss.backward()
        grads_ok = all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
        if not (torch.isfinite(loss) and grads_ok):  # reported, not hidden: see "nonfinite_steps" in the JSON
            nonfinite.append(step)
            continue
        opt.step()
        with torch.no_grad():  # keep the parameters in their domains
            model.position_threshold.clamp_(min=floor["position_threshold"])
            model.normal_threshold.clamp_(min=floor["normal_threshold"])
            model.alpha.clamp_(0.02, 1.0)
        history.append(dict(step=step, loss=float(loss.detach()), **values(model)))
    t_train = time.perf_counter() - t0
    learned = values(model)

    # held-out: hard tests at both settings
    ladder_spp = torch.arange(1, s.ladder_spp + 1, dtype=torch.float64)
    F = test["color"].shape[0]
    ref = test["reference"][s.warmup :]
    ladder = ladder_rmse(test["ladder"][:, s.warmup :], ref)
    results: dict = {
        "example": "train_thresholds",
        "smoke": bool(args.smoke),
        "scene": scene.name,
        "width": s.width,
        "height": s.height,
        "train_frames": list(s.train_frames),
        "test_frames": list(s.test_frames),
        "warmup": s.warmup,
        "window": s.window,
        "steps": s.steps,
        "lr": s.lr,
        "reference_spp": s.reference_spp,
        "ladder_spp": s.ladder_spp,
        "seed": args.seed,
        "hand_set": hand,
        "learned": learned,
        "history": history[:: max(1, s.steps // 20)],
        "nonfinite_steps": nonfinite,
        "held_out": {},
    }
    with torch.no_grad():
        for label, v in (("hand_set", hand), ("learned", learned)):
            hard = TemporalReprojection(v["position_threshold"], v["normal_threshold"], v["alpha"], soft=False)
            color, valid = accumulate(hard, test, 0, F)
            r = rmse(color[s.warmup :], ref)
            spp, flags = effective_spp_many(r, ladder_spp, ladder)
            results["held_out"][label] = {
                "rmse_mean": float(r.mean()),
                "effective_spp_median": float(spp.median()),
                "effective_spp_mean": float(spp[torch.isfinite(spp)].mean()) if torch.isfinite(spp).any() else None,
                "effective_spp_per_frame": [x if math.isfinite(x) else None for x in spp.tolist()],
                "discard_pct": float(100 * (1 - valid[s.warmup :].float().mean())),
                "flags": {f: flags.count(f) for f in sorted(set(flags))},
            }
        r1 = rmse(test["color"][s.warmup :], ref)
        results["held_out"]["input_1spp"] = {"rmse_mean": float(r1.mean()), "effective_spp_median": 1.0}
    results["seconds"] = {"render": t_render, "train": t_train, "total": time.perf_counter() - t_start}

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "train_thresholds.json").write_text(json.dumps(results, indent=1))
    print(
        f"train_thresholds: {scene.name} at {s.width}x{s.height}; {s.steps} Adam steps on frames "
        f"{s.train_frames[0]}..{s.train_frames[1] - 1}; held-out frames {s.test_frames[0] + s.warmup}.."
        f"{s.test_frames[1] - 1} (hard tests)"
    )
    head = ("pos. thr", "normal thr", "alpha", "RMSE", "eff. spp", "discard")
    print(f"  {'':10s} " + " ".join(f"{h:>{w}s}" for h, w in zip(head, (9, 10, 7, 8, 9, 8))))
    for label in ("hand_set", "learned"):
        v, h = results[label], results["held_out"][label]
        print(
            f"  {label:10s} {v['position_threshold']:9.4f} {v['normal_threshold']:10.4f} {v['alpha']:7.3f} "
            f"{h['rmse_mean']:8.4f} {h['effective_spp_median']:9.2f} {h['discard_pct']:7.1f}%"
        )
    print(f"  ({results['seconds']['total']:.0f} s) -> {out / 'train_thresholds.json'}")
    return results


if __name__ == "__main__":
    main()
