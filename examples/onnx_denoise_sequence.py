"""A recurrent denoiser and its reprojection in one ONNX graph, both eyes of a sequence run by onnxruntime alone.

1. Render a short clip of a built-in scene, both eyes, with the package's path tracer: 1-spp colour, depth,
   normal, albedo and camera per frame, and a reference (many spp).
2. The denoiser: with ``--checkpoint PATH`` the network trained by ``examples/recurrent_denoiser.py`` (its
   ``build_network`` and weights; the render size, held-out frames and thresholds of its settings); without,
   ``examples/denoiser_preprocess.py``'s U-Net trained here for a few Adam steps, unrolled through the fed-back
   output (a smoke run: parity and speed do not need a good denoiser).
3. Wrap it in :class:`~stereorepro.ReprojectionDenoiser` ``(stereo=True, recurrent=True, albedo=True)`` (temporal
   reprojection, the other eye's reprojection, the network's own previous output warped into this frame, albedo)
   and export the whole module to one ONNX file with :func:`stereorepro.export_onnx` (symbolic B, H, W). torch's
   TorchScript exporter has no symbolic for ``aten::expm1``, which the U-Nets' output uses: ``Exp(x) - 1`` is
   registered in its place during the export.
4. Write the held-out frames (the inputs only) to ``OUT/sequence.npz``.
5. In a **separate process that imports only numpy and onnxruntime** (it asserts that ``torch`` is not in
   ``sys.modules``), run the sequence frame by frame through the one graph, as the study does: the right eye
   first, with an other eye that has no surface (its stereo channels are 0), then the left eye with the right
   eye's denoised frame as the other eye; each eye's state (accumulated colour, history length, G-buffer and
   camera) and its ``denoised`` output (as ``prev_denoised``) are fed back next frame; timings per call.
6. Run the same sequence through the torch module and compare: max |difference| of the denoised frames per frame
   (and of the state), ms per call of both, and the RMSE against the references of the denoised frames, of plain
   temporal accumulation (the graph's ``color`` output: EMA 0.2 of the 1-spp frames) and of the 1-spp input.

Run::

    python examples/onnx_denoise_sequence.py --smoke --out runs/onnx_denoise                       # ~30 s
    python examples/onnx_denoise_sequence.py --checkpoint runs/recurrent_denoiser/recurrent_seed0.pt \
        --out runs/onnx_denoise                                                                 # the study's network

Writes ``OUT/onnx_denoise_sequence.json`` (and ``OUT/model.onnx``, ``OUT/sequence.npz``,
``OUT/onnxruntime_outputs.npz``), all atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

# Nothing at module level imports torch or stereorepro: the onnxruntime pass (``--ort-only``) runs without them.
sys.path.insert(0, str(Path(__file__).resolve().parent))  # denoiser_preprocess, recurrent_denoiser, _example_common

EYES = ("right", "left")  # processing order: the left eye reads the right eye's denoised frame
FRAME = ("current_color", "depth", "normal", "K", "cam_from_world")
GBUFFER = FRAME[1:]
OUTPUTS = ("denoised", "color", "history_len")
REFERENCE_OFFSET = 1 << 24  # sample index of the references' stream: disjoint from the 1-spp inputs


# ------------------------------------------------------------------------------------ onnxruntime side (no torch)
def first_state(g: dict, np) -> dict:
    """A cold start (stereorepro.empty_history(..., recurrent=True), in numpy): no history, a previous view with no
    surface, a zero previous output."""
    return {
        "history_color": np.zeros_like(g["normal"]),
        "history_len": np.zeros_like(g["depth"]),
        "prev_depth": np.zeros_like(g["depth"]),
        "prev_normal": np.zeros_like(g["normal"]),
        "prev_K": g["K"],
        "prev_cam_from_world": g["cam_from_world"],
        "prev_denoised": np.zeros_like(g["normal"]),
    }


def eye_feed(seq: dict, eye: str, i: int, state: dict, other: dict | None, np) -> dict:
    """The graph's inputs for one eye of frame ``i``: the frame, its state, albedo and the other eye (``other``:
    its denoised frame and G-buffer; None: an other eye with no surface at this eye's camera, every stereo tap
    rejected, as stereorepro.empty_state(view, stereo=True).other)."""
    feed = {k: seq[f"{eye}/{k}"][i] for k in FRAME}
    feed["albedo"] = seq[f"{eye}/albedo"][i]
    feed.update(state)
    if other is None:
        other = {
            "denoised": np.zeros_like(feed["normal"]),
            "depth": np.zeros_like(feed["depth"]),
            "normal": np.zeros_like(feed["normal"]),
            "K": feed["K"],
            "cam_from_world": feed["cam_from_world"],
        }
    feed["other_color"] = other["denoised"]
    feed.update({f"other_{k}": other[k] for k in GBUFFER})
    return feed


def next_state(feed: dict, denoised, color, n) -> dict:
    """The state of the next frame: this frame's accumulation, G-buffer, camera and denoised output."""
    state = {"history_color": color, "history_len": n, "prev_denoised": denoised}
    state.update({f"prev_{k}": feed[k] for k in GBUFFER})
    return state


def run_onnxruntime(model_path, seq_npz, out_path, threads: int = 2) -> dict:
    """The sequence (both eyes) through the one-graph model with numpy and onnxruntime only; writes the outputs
    per eye and frame to ``out_path`` (an .npz, opened as given: the caller's atomic temporary name)."""
    import numpy as np
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    # spin-waiting between the graph's nodes (onnxruntime's default), stopped when a run ends: the cores are free
    # between frames
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1")
    opts.add_session_config_entry("session.force_spinning_stop", "1")
    sess = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    with np.load(seq_npz) as z:
        seq = {k: z[k] for k in z.files}
    frames = seq["right/current_color"].shape[0]

    def run(feed):
        return sess.run(["denoised", "color", "history_len_out"], {k: feed[k] for k in names})

    def cold(eye):
        return first_state({k: seq[f"{eye}/{k}"][0] for k in GBUFFER}, np)

    run(eye_feed(seq, "right", 0, cold("right"), None, np))  # warm-up, discarded
    states = {eye: cold(eye) for eye in EYES}
    outs = {f"{eye}/{k}": [] for eye in EYES for k in OUTPUTS}
    ms = []
    for i in range(frames):
        other = None
        for eye in EYES:
            feed = eye_feed(seq, eye, i, states[eye], other, np)
            t0 = time.perf_counter()
            denoised, color, n = run(feed)
            ms.append((time.perf_counter() - t0) * 1e3)
            states[eye] = next_state(feed, denoised, color, n)
            other = {"denoised": denoised, **{k: feed[k] for k in GBUFFER}}
            for k, v in zip(OUTPUTS, (denoised, color, n)):
                outs[f"{eye}/{k}"].append(v)
    with open(out_path, "wb") as f:  # a file object: np.savez would append ".npz" to a name
        np.savez(f, **{k: np.stack(v) for k, v in outs.items()}, ms_per_call=np.asarray(ms))
    torch_loaded = "torch" in sys.modules
    assert not torch_loaded, "the onnxruntime process imported torch"
    return {
        "ms_per_call": ms,
        "torch_in_process": torch_loaded,
        "stereorepro_in_process": "stereorepro" in sys.modules,
        "onnxruntime": ort.__version__,
        "threads": threads,
        "input_names": names,
    }


# ------------------------------------------------------------------------------------ torch side
def render_clip(scene, frames, width: int, height: int, reference_spp: int, seed: int = 0) -> dict:
    """Both eyes of ``frames``: ``clip[eye][key]`` with 1-spp colour, G-buffer, albedo, float32 cameras and
    references, stacked (F, 1, ...)."""
    import torch

    from stereorepro import PathTracer
    from stereorepro.camera import Eye

    tracer = PathTracer(scene, seed=seed, workers=2)
    clip: dict = {}
    for eye, which in (("right", Eye.RIGHT), ("left", Eye.LEFT)):
        out: dict = {k: [] for k in (*FRAME, "albedo", "reference")}
        for f in frames:
            cam = scene.stereo_cameras(f, width, height)[int(which)]
            r = tracer.render(cam, f, 1, eye=which)
            ref = tracer.render(cam, f, reference_spp, sample_offset=REFERENCE_OFFSET, eye=which, gbuffers=False)
            values = (r.radiance, r.depth, r.normal, cam.K, cam.cam_from_world, r.albedo, ref.radiance)
            for k, v in zip(out, values):
                out[k].append(v.float())
        clip[eye] = {k: torch.stack(v) for k, v in out.items()}
    return clip


def run_torch(model, clip: dict, start: int = 0, count: int | None = None, grad_from: int | None = None):
    """Frames ``start .. start + count`` of both eyes through ``model`` from a cold start, as the onnxruntime
    process runs them. Returns ``({eye/key: (F, 1, ...)}, ms per call)``; frames from ``grad_from`` on keep
    gradients (training), none do when it is None (then one warm-up call is run first and each call timed)."""
    import torch

    from stereorepro import empty_history

    count = clip["right"]["current_color"].shape[0] - start if count is None else count
    outs: dict = {f"{eye}/{k}": [] for eye in EYES for k in OUTPUTS}
    ms: list = []

    def frame(eye, i):
        return [clip[eye][k][i] for k in FRAME]

    def cold(eye):
        return empty_history(*frame(eye, start)[1:], recurrent=True)

    def call(eye, i, state, other):
        f = frame(eye, i)
        if other is None:  # no surface: every stereo tap rejected
            other = (torch.zeros_like(f[2]), torch.zeros_like(f[1]), torch.zeros_like(f[2]), f[3], f[4])
        return model(*f, *state[:6], *other, state[6], clip[eye]["albedo"][i])

    if grad_from is None:
        with torch.inference_mode():
            call("right", start, cold("right"), None)  # warm-up, discarded
    states = {eye: cold(eye) for eye in EYES}
    for i in range(start, start + count):
        other = None
        with torch.set_grad_enabled(grad_from is not None and i - start >= grad_from):
            for eye in EYES:
                t0 = time.perf_counter()
                denoised, color, n = call(eye, i, states[eye], other)
                ms.append((time.perf_counter() - t0) * 1e3)
                states[eye] = (color, n, *frame(eye, i)[1:], denoised)
                other = (denoised, *frame(eye, i)[1:])
                for k, v in zip(OUTPUTS, (denoised, color, n)):
                    outs[f"{eye}/{k}"].append(v)
    return {k: torch.stack(v) for k, v in outs.items()}, ms


def train_denoiser(model, clip: dict, steps: int, lr: float, seed: int, burn_in: int = 1, unroll: int = 2) -> dict:
    """Adam on L1 in log1p space against the references, over random windows of the clip (``burn_in`` frames
    without gradients, then ``unroll`` frames backpropagated through the fed-back output); ``model.denoiser`` is
    trained in place."""
    import torch

    from _example_common import cpu_training_threads

    frames = clip["right"]["current_color"].shape[0]
    span = min(burn_in + unroll, frames)
    g = torch.Generator().manual_seed(seed)
    net = model.denoiser
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
    loss = torch.zeros(())
    t0 = time.perf_counter()
    with cpu_training_threads():
        net.train()
        for _ in range(steps):
            start = int(torch.randint(0, frames - span + 1, (1,), generator=g))
            outs, _ = run_torch(model, clip, start, span, grad_from=min(burn_in, span - 1))
            loss = torch.zeros(())
            for eye in EYES:
                out = outs[f"{eye}/denoised"][-(span - min(burn_in, span - 1)) :]
                ref = clip[eye]["reference"][start + span - out.shape[0] : start + span]
                loss = loss + (torch.log1p(out.clamp_min(0)) - torch.log1p(ref.clamp_min(0))).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        net.eval()
    return {
        "steps": steps,
        "burn_in": burn_in,
        "unroll": unroll,
        "lr": lr,
        "final_loss": float(loss.detach()),
        "seconds": time.perf_counter() - t0,
    }


def load_checkpoint(path) -> tuple:
    """``(network, checkpoint dict)`` of a checkpoint written by ``examples/recurrent_denoiser.py``."""
    import torch

    from recurrent_denoiser import build_network

    ckpt = torch.load(path, weights_only=False, map_location="cpu")
    net = build_network(**ckpt["network"]["kwargs"])
    net.load_state_dict(ckpt["state_dict"])
    return net.eval(), ckpt


def _expm1_symbolic(g, x):
    import torch

    one = g.op("CastLike", g.op("Constant", value_t=torch.tensor(1.0)), x)
    return g.op("Sub", g.op("Exp", x), one)


def export_model(model, path, opset: int = 18):
    """:func:`stereorepro.export_onnx` of the one-graph model, with ``aten::expm1`` exported as ``Exp(x) - 1``
    (the TorchScript exporter has no symbolic for it); the registration is removed afterwards."""
    import torch

    from stereorepro import export_onnx
    from stereorepro.denoise import denoiser_example_inputs

    torch.onnx.register_custom_op_symbolic("aten::expm1", _expm1_symbolic, 17)
    try:
        return export_onnx(model, path, opset=opset, inputs=denoiser_example_inputs(model))
    finally:
        torch.onnx.unregister_custom_op_symbolic("aten::expm1", 17)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny run for CI: 64x36, 4 frames, 10 steps")
    p.add_argument("--out", default="runs/onnx_denoise", help="output directory")
    p.add_argument("--checkpoint", default=None, help="a network trained by examples/recurrent_denoiser.py (.pt)")
    p.add_argument("--scene", default=None, help="default: the checkpoint's first held-out scene, else living_room")
    p.add_argument("--reference-spp", type=int, default=None, help="default: the checkpoint's test references")
    p.add_argument(
        "--cache", default=None, help="with --checkpoint: the study's render cache; its clip of the frames is used"
    )
    p.add_argument(
        "--steps", type=int, default=None, help="training steps without a checkpoint (default 300, smoke 10)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ort-only", nargs=4, metavar=("MODEL", "SEQ", "OUT", "THREADS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.ort_only:  # the deployment process: numpy and onnxruntime only
        model, seq, out, threads = args.ort_only
        info = run_onnxruntime(model, seq, out, int(threads))
        print(json.dumps(info))
        return info
    return _run(args)


#: Options of the one-graph model (stereorepro.ReprojectionDenoiser); a checkpoint must have been trained on them.
OPTIONS = {"stereo": True, "recurrent": True, "albedo": True}


def _setup(args) -> dict:
    """The network and the clip's settings: from the checkpoint, or the smoke / default settings of a network
    trained here."""
    if args.checkpoint:
        net, ckpt = load_checkpoint(args.checkpoint)
        if {k: bool(ckpt["feature_options"].get(k)) for k in OPTIONS} != OPTIONS:
            raise SystemExit(f"--checkpoint: trained on {ckpt['feature_options']}, this graph needs {OPTIONS}")
        st = ckpt["settings"]
        scene = args.scene or st["heldout_scenes"][0]
        return dict(
            net=net,
            size=(st["width"], st["height"]),
            scene=scene,
            train_frames=None,
            test_frames=range(*st["test_frames"]),
            reference_spp=args.reference_spp or st["test_reference_spp"],
            warmup=st["warmup"],
            steps=0,
            thresholds=_scene_thresholds(ckpt.get("thresholds", {}), scene),
            denoiser=f"examples/recurrent_denoiser.py build_network({ckpt['network']['kwargs']}) from {args.checkpoint}",
            checkpoint={"path": str(args.checkpoint), "variant": ckpt.get("variant"), "training": ckpt.get("training")},
            clip=_study_clip(args.cache, scene, st) if args.cache and not args.reference_spp else None,
        )
    from stereorepro.denoise import feature_channels

    from denoiser_preprocess import UNet  # the example U-Net (this folder is on sys.path)

    import torch

    if args.smoke:
        size, train_frames, test_frames, ref_spp, steps = (64, 36), range(0, 4), range(20, 24), 8, 10
    else:
        size, train_frames, test_frames, ref_spp, steps = (128, 72), range(0, 16), range(24, 36), 64, 300
    steps = steps if args.steps is None else args.steps
    if steps < 0:
        raise SystemExit("--steps must be >= 0")
    torch.manual_seed(args.seed)
    c_in = feature_channels(**OPTIONS)
    return dict(
        net=UNet(c_in),
        size=size,
        scene=args.scene or "living_room",
        train_frames=train_frames if steps else None,
        test_frames=test_frames,
        reference_spp=args.reference_spp or ref_spp,
        warmup=2,
        steps=steps,
        thresholds=None,
        denoiser=f"examples/denoiser_preprocess.py UNet(in_channels={c_in}), trained here",
        checkpoint=None,
    )


def _study_clip(cache, scene: str, settings: dict) -> dict | None:
    """The study's cached clip of ``scene`` at its test frames (``examples/recurrent_denoiser.py``: same frames,
    inputs and references), in this example's layout, or None when the cache does not have it."""
    from recurrent_denoiser import Settings, _cache_key, load_clip

    s = Settings(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})
    if not (Path(cache) / f"{_cache_key(scene, s.test_frames, s, True)}.pt").exists():
        return None
    clip = load_clip(scene, s.test_frames, s, True, Path(cache))
    names = {"current_color": "color", "cam_from_world": "T"}
    return {
        eye: {k: clip[eye][names.get(k, k)].float().unsqueeze(1) for k in (*FRAME, "albedo", "reference")}
        for eye in EYES
    }


def _scene_thresholds(thresholds: dict, scene: str):
    """The checkpoint's thresholds of ``scene`` (keyed by the scene's name or its clips' labels, "name (frames
    a-b)"), or None (then the scene's own at this height, which is what the study uses)."""
    for label, thr in thresholds.items():
        if label == scene or label.startswith(f"{scene} ("):
            return tuple(thr)
    return None


def _run(args) -> dict:
    import subprocess

    import numpy as np
    import torch
    from _example_common import provenance

    from stereorepro import ReprojectionDenoiser, load_scene
    from stereorepro.io.atomic import atomic_path, atomic_write

    cfg = _setup(args)
    (W, H), net = cfg["size"], cfg["net"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(cfg["scene"])
    pos, nrm = cfg["thresholds"] or scene.thresholds(H)
    t_start = time.perf_counter()
    frames = cfg["train_frames"]
    train_clip = render_clip(scene, frames, W, H, cfg["reference_spp"], args.seed) if frames else None
    seq = cfg.get("clip") or render_clip(scene, cfg["test_frames"], W, H, cfg["reference_spp"], args.seed)
    t_render = time.perf_counter() - t_start

    model = ReprojectionDenoiser(net, pos, nrm, alpha=0.2, **OPTIONS).eval()
    steps = cfg["steps"]
    training = train_denoiser(model, train_clip, steps, 2e-3, args.seed) if steps else {"steps": 0}
    model.eval()

    t0 = time.perf_counter()
    model_path = export_model(model, out / "model.onnx")
    t_export = time.perf_counter() - t0
    seq_path = out / "sequence.npz"
    with atomic_path(seq_path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **{f"{eye}/{k}": seq[eye][k].numpy() for eye in EYES for k in (*FRAME, "albedo")})

    threads = torch.get_num_threads()
    ort_path = out / "onnxruntime_outputs.npz"
    with atomic_path(ort_path) as tmp:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--ort-only", str(model_path), str(seq_path)]
        proc = subprocess.run([*cmd, str(tmp), str(threads)], capture_output=True, text=True, timeout=1200)
        if proc.returncode != 0:
            raise RuntimeError(f"onnxruntime process failed:\n{proc.stderr[-3000:]}")
    ort_info = json.loads(proc.stdout.strip().splitlines()[-1])
    with np.load(ort_path) as z:
        ort_out = {k: z[k] for k in z.files if k != "ms_per_call"}
    ref, torch_ms = run_torch(model, seq)
    res = _results(cfg, seq, ref, ort_out, warmup=cfg["warmup"])
    res.update(
        scene=scene.name,
        width=W,
        height=H,
        position_threshold=pos,
        normal_threshold=nrm,
        options=OPTIONS,
        input_names=model.input_names,
        features=list(model.feature_names),
        parameters=sum(p.numel() for p in model.denoiser.parameters()),
        trained=bool(steps) or cfg["checkpoint"] is not None,
        training=training,
        onnxruntime_torch_in_process=ort_info["torch_in_process"],
        onnxruntime_stereorepro_in_process=ort_info["stereorepro_in_process"],
        ms_per_frame={  # one eye: one call of the graph
            "onnxruntime": float(np.median(ort_info["ms_per_call"])),
            "torch": float(np.median(torch_ms)),
        },
        ms_per_frame_all={"onnxruntime": ort_info["ms_per_call"], "torch": torch_ms},
        threads=threads,
        onnxruntime=ort_info["onnxruntime"],
        torch=torch.__version__,
        torch_reprojection_backend=model.temporal.backend,
        seconds={"render": t_render, "export": t_export, "total": time.perf_counter() - t_start},
        provenance=provenance("examples", "stereorepro"),
    )
    atomic_write(out / "onnx_denoise_sequence.json", json.dumps(res, indent=1) + "\n")
    _print(res, out)
    return res


def _results(cfg: dict, seq: dict, ref: dict, ort_out: dict, warmup: int) -> dict:
    """Parity (max |onnxruntime - torch| per output, and of the denoised frame per eye and frame) and RMSE against
    the references of the 1-spp input, plain temporal accumulation and the denoised frames."""
    import numpy as np

    from stereorepro import rmse

    def diff(k):
        return np.abs(ort_out[k].astype(np.float64) - ref[k].detach().double().numpy())

    per_frame = {eye: diff(f"{eye}/denoised").reshape(len(cfg["test_frames"]), -1).max(1).tolist() for eye in EYES}
    max_abs = {k: max(float(diff(f"{eye}/{k}").max()) for eye in EYES) for k in OUTPUTS}

    def rmse_of(img, eye: str, first: int, ldr: bool) -> float:  # mean over frames of the per-frame RMSE
        a, b = img[first:, 0].double(), seq[eye]["reference"][first:, 0].double()
        if ldr:
            a, b = a.clamp(0, 1), b.clamp(0, 1)
        return float(rmse(a, b).mean())

    table: dict = {}
    for metric, ldr in (("hdr", False), ("ldr", True)):
        for frames, first in (("all_frames", 0), ("after_warmup", warmup)):
            per_eye = {
                eye: {
                    "input_1spp": rmse_of(seq[eye]["current_color"], eye, first, ldr),
                    "accumulated": rmse_of(ref[f"{eye}/color"], eye, first, ldr),
                    "denoised": rmse_of(ref[f"{eye}/denoised"], eye, first, ldr),
                }
                for eye in EYES
            }
            mean = {m: float(np.mean([per_eye[e][m] for e in EYES])) for m in per_eye["right"]}
            table[f"{metric}/{frames}"] = {"both_eyes": mean, **per_eye}
    beats = {k: v["both_eyes"]["denoised"] < v["both_eyes"]["accumulated"] for k, v in table.items()}
    return {
        "example": "onnx_denoise_sequence",
        "denoiser": cfg["denoiser"],
        "checkpoint": cfg["checkpoint"],
        "frames": len(cfg["test_frames"]),
        "test_frames": [cfg["test_frames"][0], cfg["test_frames"][-1] + 1],
        "eyes": list(EYES),
        "reference_spp": cfg["reference_spp"],
        "clip_from_study_cache": cfg.get("clip") is not None,
        "warmup": warmup,
        "max_abs_diff": max_abs,
        "max_abs_diff_denoised": max_abs["denoised"],
        "max_abs_diff_denoised_per_frame": per_frame,
        "max_abs_value_denoised": max(float(ref[f"{eye}/denoised"].abs().max()) for eye in EYES),
        "rmse_vs_reference": table["hdr/all_frames"]["both_eyes"],
        "rmse": table,
        "beats_accumulation": beats,
        "denoised_beats_accumulation": all(beats.values()),
    }


def _print(res: dict, out: Path) -> None:
    ms = res["ms_per_frame"]
    print(
        f"onnx_denoise_sequence: {res['frames']} frames x 2 eyes of {res['scene']} at {res['width']}x{res['height']}; "
        f"one graph ({len(res['input_names'])} inputs: reprojection, stereo, own warped output, albedo + network); "
        f"{res['denoiser']}"
    )
    print(
        "  max |onnxruntime - torch|: "
        + ", ".join(f"{k} {v:.2e}" for k, v in res["max_abs_diff"].items())
        + f"  (onnxruntime process without torch: {not res['onnxruntime_torch_in_process']})"
    )
    print(
        f"  ms per eye-frame (median, {res['threads']} threads): onnxruntime {ms['onnxruntime']:.1f}, torch {ms['torch']:.1f}"
    )
    for key, v in res["rmse"].items():
        print(f"  RMSE {key}: " + ", ".join(f"{k} {x:.4f}" for k, x in v["both_eyes"].items()))
    print(f"  denoised beats plain accumulation: {res['beats_accumulation']}  -> {out / 'onnx_denoise_sequence.json'}")


if __name__ == "__main__":
    main()
