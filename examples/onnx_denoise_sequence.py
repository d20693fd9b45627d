"""The denoiser and its reprojection in one ONNX graph, run over a frame sequence by onnxruntime alone.

1. Render a short clip of a built-in scene (right eye) with the package's path tracer: 1-spp colour, depth,
   normal and camera per frame, and a reference (many spp) for training and for the RMSE column.
2. Train ``examples/denoiser_preprocess.py``'s U-Net (imported from there) as the denoiser of a
   :class:`~stereorepro.ReprojectionDenoiser`: a few hundred Adam steps on random crops of the training frames'
   features (the reprojection has no trained parameters, so the features of a clip are computed once). With
   ``--steps 0`` the network stays untrained (fixed seed; its zero-initialised head makes it the identity of the
   accumulation). Parity and speed do not need a good denoiser; the RMSE column shows what training gave.
3. Export the whole module (temporal reprojection + features + U-Net) to one ONNX file with
   :func:`stereorepro.export_onnx` (symbolic B, H, W). torch's TorchScript exporter has no symbolic for
   ``aten::expm1``, which the U-Net's output uses: ``Exp(x) - 1`` is registered in its place during the export.
4. Write the held-out frames (the inputs only) to ``OUT/sequence.npz``.
5. In a **separate process that imports only numpy and onnxruntime** (it asserts that ``torch`` is not in
   ``sys.modules``), run the sequence frame by frame, feeding the state (accumulated colour, history length) and
   the frame's G-buffer and camera back as the next frame's history; timings per frame.
6. Run the same sequence through the torch module and compare: max |difference| of the denoised frames (and of
   the state), ms per frame of both.

Run::

    python examples/onnx_denoise_sequence.py --smoke --out runs/onnx_denoise     # ~15 s
    python examples/onnx_denoise_sequence.py --out runs/onnx_denoise             # 128x72, 300 steps (~1 min)

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
sys.path.insert(0, str(Path(__file__).resolve().parent))  # denoiser_preprocess, _example_common (imported where used)

STATE = ("history_color", "history_len", "prev_depth", "prev_normal", "prev_K", "prev_cam_from_world")
FRAME = ("current_color", "depth", "normal", "K", "cam_from_world")
REFERENCE_OFFSET = 1 << 24  # sample index of the references' stream: disjoint from the 1-spp inputs


# ------------------------------------------------------------------------------------ onnxruntime side (no torch)
def run_onnxruntime(model_path, seq_npz, out_path, threads: int = 2) -> dict:
    """The sequence through the one-graph model with numpy and onnxruntime only; writes the denoised frames and
    the state per frame to ``out_path`` (an .npz, opened as given: the caller's atomic temporary name)."""
    import numpy as np
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    # spin-waiting between the graph's nodes (onnxruntime's default), stopped when a run ends: the cores are free
    # between frames
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1")
    opts.add_session_config_entry("session.force_spinning_stop", "1")
    sess = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
    with np.load(seq_npz) as z:
        seq = {k: z[k] for k in FRAME}
    frames = seq["current_color"].shape[0]

    def first_state(depth, normal, K, T):  # stereorepro.empty_history, in numpy
        return (np.zeros_like(normal), np.zeros_like(depth), np.zeros_like(depth), np.zeros_like(normal), K, T)

    def step(i, state):
        feed = {k: seq[k][i] for k in FRAME}
        feed.update(zip(STATE, state))
        denoised, color, n = sess.run(["denoised", "color", "history_len_out"], feed)
        return (denoised, color, n), (color, n, feed["depth"], feed["normal"], feed["K"], feed["cam_from_world"])

    step(0, first_state(*(seq[k][0] for k in ("depth", "normal", "K", "cam_from_world"))))  # warm-up, discarded
    state = first_state(*(seq[k][0] for k in ("depth", "normal", "K", "cam_from_world")))
    outs, ms = {"denoised": [], "color": [], "history_len": []}, []
    for i in range(frames):
        t0 = time.perf_counter()
        (denoised, color, n), state = step(i, state)
        ms.append((time.perf_counter() - t0) * 1e3)
        for k, v in zip(outs, (denoised, color, n)):
            outs[k].append(v)
    with open(out_path, "wb") as f:  # a file object: np.savez would append ".npz" to a name
        np.savez(f, **{k: np.stack(v) for k, v in outs.items()}, ms_per_frame=np.asarray(ms))
    torch_loaded = "torch" in sys.modules
    assert not torch_loaded, "the onnxruntime process imported torch"
    return {
        "ms_per_frame": ms,
        "torch_in_process": torch_loaded,
        "stereorepro_in_process": "stereorepro" in sys.modules,
        "onnxruntime": ort.__version__,
        "threads": threads,
    }


# ------------------------------------------------------------------------------------ torch side
def render_clip(scene, frames, width: int, height: int, reference_spp: int, seed: int = 0) -> dict:
    """Right-eye frames of ``frames``: 1-spp colour, G-buffer, float32 cameras and references, stacked (F, 1, ...)."""
    import torch

    from stereorepro import PathTracer
    from stereorepro.camera import Eye

    tracer = PathTracer(scene, seed=seed, workers=2)
    out: dict = {k: [] for k in (*FRAME, "reference")}
    for f in frames:
        _, cam = scene.stereo_cameras(f, width, height)
        r = tracer.render(cam, f, 1, eye=Eye.RIGHT)
        ref = tracer.render(cam, f, reference_spp, sample_offset=REFERENCE_OFFSET, eye=Eye.RIGHT, gbuffers=False)
        for k, v in zip(out, (r.radiance, r.depth, r.normal, cam.K, cam.cam_from_world, ref.radiance)):
            out[k].append(v.float())
    return {k: torch.stack(v) for k, v in out.items()}


def run_torch(model, clip: dict, features: bool = False) -> tuple[dict, list]:
    """The clip through ``model`` with the state fed back (first frame: :func:`stereorepro.empty_history`), with
    timings per frame (after one warm-up call). ``features``: return the denoiser's inputs instead of timing."""
    import torch

    from stereorepro import empty_history

    n_frames = clip["current_color"].shape[0]
    call = model.features if features else model
    outs: dict = {"out": [], "color": [], "history_len": []}
    ms = []
    with torch.inference_mode():
        first = empty_history(*(clip[k][0] for k in ("depth", "normal", "K", "cam_from_world")))
        call(*(clip[k][0] for k in FRAME), *first)  # warm-up, discarded
        state = first
        for i in range(n_frames):
            frame = [clip[k][i] for k in FRAME]
            t0 = time.perf_counter()
            out, color, n = call(*frame, *state)
            ms.append((time.perf_counter() - t0) * 1e3)
            state = (color, n, *frame[1:])
            for k, v in zip(outs, (out, color, n)):
                outs[k].append(v)
    return {k: torch.stack(v) for k, v in outs.items()}, ms


def train_denoiser(model, clip: dict, steps: int, batch: int, crop: int, lr: float, seed: int) -> dict:
    """Adam on MSE in log1p space over random crops of the clip's features (computed once) against the
    references; ``model.denoiser`` is trained in place."""
    import torch

    from _example_common import cpu_training_threads

    feats, _ = run_torch(model, clip, features=True)
    x, target = feats["out"][:, 0], clip["reference"][:, 0]  # (F, C, H, W)
    H, W = x.shape[-2:]
    ch, cw = min(crop, H), min(crop, W)
    net = model.denoiser
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
    loss = torch.zeros(())
    t0 = time.perf_counter()
    with cpu_training_threads():
        net.train()
        for _ in range(steps):
            idx = torch.randint(0, x.shape[0], (batch,), generator=g).tolist()
            ys = torch.randint(0, H - ch + 1, (batch,), generator=g).tolist()
            xs = torch.randint(0, W - cw + 1, (batch,), generator=g).tolist()
            xb = torch.stack([x[i, :, y : y + ch, u : u + cw] for i, y, u in zip(idx, ys, xs)])
            tb = torch.stack([target[i, :, y : y + ch, u : u + cw] for i, y, u in zip(idx, ys, xs)])
            loss = (torch.log1p(net(xb)) - torch.log1p(tb.clamp_min(0))).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        net.eval()
    return {
        "steps": steps,
        "batch": batch,
        "crop": [ch, cw],
        "lr": lr,
        "final_loss": float(loss.detach()),
        "seconds": time.perf_counter() - t0,
    }


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
    p.add_argument("--scene", default="living_room")
    p.add_argument("--steps", type=int, default=None, help="training steps (0: untrained U-Net; default 300, smoke 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ort-only", nargs=4, metavar=("MODEL", "SEQ", "OUT", "THREADS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.ort_only:  # the deployment process: numpy and onnxruntime only
        model, seq, out, threads = args.ort_only
        info = run_onnxruntime(model, seq, out, int(threads))
        print(json.dumps(info))
        return info
    return _run(args)


def _run(args) -> dict:
    import subprocess

    import numpy as np
    import torch

    from stereorepro import ReprojectionDenoiser, load_scene, rmse
    from stereorepro.denoise import FEATURES, feature_channels
    from stereorepro.io.atomic import atomic_path, atomic_write

    from denoiser_preprocess import UNet  # the example U-Net (this folder is on sys.path)

    if args.smoke:
        (W, H), train_frames, test_frames, ref_spp, steps, crop = (64, 36), range(0, 4), range(20, 24), 8, 10, 32
    else:
        (W, H), train_frames, test_frames, ref_spp, steps, crop = (128, 72), range(0, 16), range(24, 36), 64, 300, 48
    steps = steps if args.steps is None else args.steps
    if steps < 0:
        raise SystemExit("--steps must be >= 0")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.scene)
    pos, nrm = scene.thresholds(H)
    t_start = time.perf_counter()
    train_clip = render_clip(scene, train_frames, W, H, ref_spp, args.seed) if steps else None
    seq = render_clip(scene, test_frames, W, H, ref_spp, args.seed)
    t_render = time.perf_counter() - t_start

    torch.manual_seed(args.seed)
    model = ReprojectionDenoiser(UNet(feature_channels()), pos, nrm, alpha=0.2).eval()
    training = train_denoiser(model, train_clip, steps, 4, crop, 2e-3, args.seed) if steps else {"steps": 0}

    t0 = time.perf_counter()
    model_path = export_model(model, out / "model.onnx")
    t_export = time.perf_counter() - t0
    seq_path = out / "sequence.npz"
    with atomic_path(seq_path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **{k: seq[k].numpy() for k in FRAME})

    threads = torch.get_num_threads()
    ort_path = out / "onnxruntime_outputs.npz"
    with atomic_path(ort_path) as tmp:
        proc = subprocess.run(
            [
                sys.executable,
                str(Path(__file__).resolve()),
                "--ort-only",
                str(model_path),
                str(seq_path),
                str(tmp),
                str(threads),
            ],
            capture_output=True,
            text=True,
            timeout=600,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"onnxruntime process failed:\n{proc.stderr[-3000:]}")
    ort_info = json.loads(proc.stdout.strip().splitlines()[-1])
    with np.load(ort_path) as z:
        ort_out = {k: z[k] for k in ("denoised", "color", "history_len")}

    ref, torch_ms = run_torch(model, seq)
    ref = {"denoised": ref["out"], "color": ref["color"], "history_len": ref["history_len"]}

    def max_diff(k):
        return float(np.abs(ort_out[k].astype(np.float64) - ref[k].double().numpy()).max())

    def rmse_of(img):  # mean over the sequence of the per-frame RMSE against the references
        return float(rmse(img[:, 0].double(), seq["reference"][:, 0].double()).mean())

    res = {
        "example": "onnx_denoise_sequence",
        "smoke": bool(args.smoke),
        "scene": scene.name,
        "frames": len(test_frames),
        "width": W,
        "height": H,
        "position_threshold": pos,
        "normal_threshold": nrm,
        "features": list(FEATURES),
        "denoiser": f"examples/denoiser_preprocess.py UNet(in_channels="
        f"{feature_channels()}), {sum(p.numel() for p in model.denoiser.parameters())} parameters",
        "trained": bool(steps),
        "training": training,
        "reference_spp": ref_spp,
        "max_abs_diff": {k: max_diff(k) for k in ref},
        "max_abs_value_denoised": float(ref["denoised"].abs().max()),
        "onnxruntime_torch_in_process": ort_info["torch_in_process"],
        "onnxruntime_stereorepro_in_process": ort_info["stereorepro_in_process"],
        "ms_per_frame": {
            "onnxruntime": float(np.median(ort_info["ms_per_frame"])),
            "torch": float(np.median(torch_ms)),
        },
        "ms_per_frame_all": {"onnxruntime": ort_info["ms_per_frame"], "torch": torch_ms},
        "threads": threads,
        "onnxruntime": ort_info["onnxruntime"],
        "torch": torch.__version__,
        "torch_reprojection_backend": model.temporal.backend,
        "rmse_vs_reference": {
            "input_1spp": rmse_of(seq["current_color"]),
            "accumulated": rmse_of(ref["color"]),
            "denoised": rmse_of(ref["denoised"]),
        },
        "seconds": {"render": t_render, "export": t_export, "total": time.perf_counter() - t_start},
    }
    res["max_abs_diff_denoised"] = res["max_abs_diff"]["denoised"]
    atomic_write(out / "onnx_denoise_sequence.json", json.dumps(res, indent=1) + "\n")
    ms = res["ms_per_frame"]
    print(
        f"onnx_denoise_sequence: {res['frames']} frames of {scene.name} at {W}x{H}, U-Net "
        f"{'trained ' + str(steps) + ' steps' if steps else 'untrained'}; one graph (reprojection + U-Net)"
    )
    print(
        "  max |onnxruntime - torch|: "
        + ", ".join(f"{k} {v:.2e}" for k, v in res["max_abs_diff"].items())
        + f"  (onnxruntime process without torch: {not res['onnxruntime_torch_in_process']})"
    )
    print(f"  ms/frame (median, {threads} threads): onnxruntime {ms['onnxruntime']:.1f}, torch {ms['torch']:.1f}")
    print(
        "  RMSE vs reference: "
        + ", ".join(f"{k} {v:.4f}" for k, v in res["rmse_vs_reference"].items())
        + f"  -> {out / 'onnx_denoise_sequence.json'}"
    )
    return res


if __name__ == "__main__":
    main()
