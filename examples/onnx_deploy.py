"""Deploy the reprojection modules with ONNX and run a whole EXR sequence through onnxruntime alone.

1. Trace a short stereo sequence of a built-in scene to an EXR directory (``stereorepro export-sequence``'s
   format: ``cameras.json`` + ``{frame:04d}_{left|right}.exr``).
2. Export :class:`~stereorepro.StereoReprojection` and :class:`~stereorepro.TemporalReprojection` to ONNX
   (symbolic batch and image sizes).
3. In a **separate process where ``import torch`` is blocked**, read the EXRs with OpenEXR + numpy and run the
   paper's combined scheme per frame with onnxruntime: temporal accumulation of the right eye, then stereo
   right → left, the left eye's discards filled from its own 1-spp colour. Outputs go to an ``.npz``.
4. Back in torch, run the same frames through the torch modules and report the largest differences.

Run::

    python examples/onnx_deploy.py --smoke --out runs/onnx_deploy     # ~10 s
    python examples/onnx_deploy.py --out runs/onnx_deploy             # 24 frames at 320x180

Writes ``OUT/onnx_deploy.json`` (max abs differences, mismatching mask pixels, per-frame timings).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

# Nothing at module level imports torch: the onnxruntime pass (``--ort-only``) runs without it.

EYES = ("left", "right")


# ------------------------------------------------------------------------------------ onnxruntime side (no torch)
def _read_eye(seq_dir: Path, frame: int, eye: str, cams: dict):
    """(color (1,3,H,W), depth (1,1,H,W), normal (1,3,H,W)) float32 and (K (1,3,3), T (1,4,4)) float32."""
    import numpy as np
    import OpenEXR

    f = OpenEXR.File(str(seq_dir / f"{frame:04d}_{eye}.exr"), separate_channels=True)
    ch = {name: np.asarray(c.pixels, np.float32) for name, c in f.channels().items()}

    def stack(names):
        return np.ascontiguousarray(np.stack([ch[n] for n in names])[None])

    cam = cams["frames"][frame][eye]
    K = np.asarray(cam["K"], np.float32)[None]
    T = np.asarray(cam["cam_from_world"], np.float32)[None]
    return stack(("R", "G", "B")), stack(("Z",)), stack(("N.X", "N.Y", "N.Z")), K, T


def run_onnxruntime(seq_dir, model_dir, out_npz) -> dict:
    """The combined scheme over the sequence with onnxruntime and numpy only. Returns per-frame timings (ms)."""
    import numpy as np
    import onnxruntime as ort

    seq_dir, model_dir = Path(seq_dir), Path(model_dir)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    stereo = ort.InferenceSession(str(model_dir / "stereo.onnx"), opts, providers=["CPUExecutionProvider"])
    temporal = ort.InferenceSession(str(model_dir / "temporal.onnx"), opts, providers=["CPUExecutionProvider"])
    cams = json.loads((seq_dir / "cameras.json").read_text())
    hist = {}  # eye -> (color, history_len, depth, normal, K, T) of the previous frame
    outs, ms = {}, []
    for i in range(len(cams["frames"])):
        t0 = time.perf_counter()
        frame_out = {}
        # right eye: temporal accumulation (first frame: its own G-buffer as "previous", history length 0)
        cr, dr, nr, Kr, Tr = _read_eye(seq_dir, i, "right", cams)
        h = hist.get("right") or (cr, np.zeros_like(dr), dr, nr, Kr, Tr)
        acc_r, n_r, valid_r = temporal.run(
            None,
            dict(
                current_color=cr,
                depth=dr,
                normal=nr,
                K=Kr,
                cam_from_world=Tr,
                history_color=h[0],
                history_len=h[1],
                prev_depth=h[2],
                prev_normal=h[3],
                prev_K=h[4],
                prev_cam_from_world=h[5],
            ),
        )
        hist["right"] = (acc_r, n_r, dr, nr, Kr, Tr)
        # stereo right -> left (the accumulated colour)
        cl, dl, nl, Kl, Tl = _read_eye(seq_dir, i, "left", cams)
        s_color, s_valid, s_reason = stereo.run(
            None,
            dict(
                src_color=acc_r,
                src_depth=dr,
                src_normal=nr,
                src_K=Kr,
                src_cam_from_world=Tr,
                dst_depth=dl,
                dst_normal=nl,
                dst_K=Kl,
                dst_cam_from_world=Tl,
            ),
        )
        # left eye: traced discards (its own 1-spp colour) accumulated with the left history; kept pixels = stereo.
        # (Unlike SpatiotemporalReprojection, the left history length is the fill's everywhere: the exported stereo
        # module carries colour only.)
        traced = np.where(s_valid, 0.0, cl).astype(np.float32)
        h = hist.get("left") or (traced, np.zeros_like(dl), dl, nl, Kl, Tl)
        fill, n_l, _ = temporal.run(
            None,
            dict(
                current_color=traced,
                depth=dl,
                normal=nl,
                K=Kl,
                cam_from_world=Tl,
                history_color=h[0],
                history_len=h[1],
                prev_depth=h[2],
                prev_normal=h[3],
                prev_K=h[4],
                prev_cam_from_world=h[5],
            ),
        )
        left = np.where(s_valid, s_color, fill).astype(np.float32)
        hist["left"] = (left, n_l, dl, nl, Kl, Tl)
        ms.append((time.perf_counter() - t0) * 1e3)
        frame_out.update(
            right=acc_r,
            right_len=n_r,
            right_valid=valid_r,
            stereo=s_color,
            stereo_valid=s_valid,
            stereo_reason=s_reason,
            left=left,
        )
        for k, v in frame_out.items():
            outs[f"{i:04d}_{k}"] = v
    np.savez(out_npz, **outs)
    return {"ms_per_frame": ms, "torch_imported": "torch" in sys.modules and sys.modules["torch"] is not None}


# ------------------------------------------------------------------------------------ torch side
def run_torch(seq_dir, pos: float, nrm: float, alpha: float) -> tuple[dict, list]:
    """The same per-frame computation with the torch modules (float32 cameras, as fed to onnxruntime)."""
    from dataclasses import replace

    import numpy as np
    import torch

    from stereorepro import StereoReprojection, TemporalReprojection
    from stereorepro.io.frames import load_sequence, read_frame

    seq = load_sequence(seq_dir)
    stereo = StereoReprojection(pos, nrm, backend="torch")
    temporal = TemporalReprojection(pos, nrm, alpha, backend="torch")
    hist, outs, ms = {}, {}, []
    with torch.no_grad():
        for i in range(len(seq)):
            t0 = time.perf_counter()
            R, L = (
                replace(f, K=f.K.float(), cam_from_world=f.cam_from_world.float())
                for f in (read_frame(seq, i, "right"), read_frame(seq, i, "left"))
            )
            h = hist.get("right") or (R.color, torch.zeros_like(R.depth), R)
            acc_r, n_r, valid_r = temporal(
                R.color,
                R.depth,
                R.normal,
                R.K,
                R.cam_from_world,
                h[0],
                h[1],
                h[2].depth,
                h[2].normal,
                h[2].K,
                h[2].cam_from_world,
            )
            hist["right"] = (acc_r, n_r, R)
            s_color, s_valid, s_reason = stereo(
                acc_r, R.depth, R.normal, R.K, R.cam_from_world, L.depth, L.normal, L.K, L.cam_from_world
            )
            traced = torch.where(s_valid, torch.zeros(()), L.color)
            h = hist.get("left") or (traced, torch.zeros_like(L.depth), L)
            fill, n_l, _ = temporal(
                traced,
                L.depth,
                L.normal,
                L.K,
                L.cam_from_world,
                h[0],
                h[1],
                h[2].depth,
                h[2].normal,
                h[2].K,
                h[2].cam_from_world,
            )
            left = torch.where(s_valid, s_color, fill)
            hist["left"] = (left, n_l, L)
            ms.append((time.perf_counter() - t0) * 1e3)
            for k, v in dict(
                right=acc_r,
                right_len=n_r,
                right_valid=valid_r,
                stereo=s_color,
                stereo_valid=s_valid,
                stereo_reason=s_reason,
                left=left,
            ).items():
                outs[f"{i:04d}_{k}"] = v.numpy()
    return {k: np.asarray(v) for k, v in outs.items()}, ms


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="6 frames at 64x36 (CI)")
    p.add_argument("--out", default="runs/onnx_deploy", help="output directory")
    p.add_argument("--scene", default="living_room")
    p.add_argument("--ort-only", nargs=3, metavar=("SEQ", "MODELS", "NPZ"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.ort_only:  # the deployment process: torch must not be importable
        sys.modules["torch"] = None  # type: ignore[assignment]  (makes `import torch` raise ImportError)
        info = run_onnxruntime(*args.ort_only)
        print(json.dumps(info))
        return info

    import numpy as np

    from stereorepro import StereoReprojection, TemporalReprojection, export_onnx, load_scene
    from stereorepro.camera import DEFAULT_RESOLUTION
    from stereorepro.workflows.export import export_sequence

    frames, (W, H) = (6, (64, 36)) if args.smoke else (24, DEFAULT_RESOLUTION)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    seq_dir = export_sequence(scene, frames, W, H, out / "sequence", spp=1, seed=0)
    t_trace = time.perf_counter() - t0
    (pos, nrm), alpha = scene.thresholds(H), 0.2

    t0 = time.perf_counter()
    models = out / "models"
    export_onnx(StereoReprojection(pos, nrm, backend="torch"), models / "stereo.onnx")
    export_onnx(TemporalReprojection(pos, nrm, alpha, backend="torch"), models / "temporal.onnx")
    t_export = time.perf_counter() - t0

    npz = out / "onnxruntime_outputs.npz"
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--ort-only", str(seq_dir), str(models), str(npz)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"onnxruntime process failed:\n{proc.stderr[-2000:]}")
    ort_info = json.loads(proc.stdout.strip().splitlines()[-1])
    with np.load(npz) as z:
        ort_out = {k: z[k] for k in z.files}
    ref, torch_ms = run_torch(seq_dir, pos, nrm, alpha)

    def max_diff(kind):
        return max(
            float(np.abs(ort_out[k].astype(np.float64) - ref[k].astype(np.float64)).max())
            for k in ref
            if k.endswith("_" + kind)
        )

    def mismatches(kind):
        return int(sum(int((ort_out[k] != ref[k]).sum()) for k in ref if k.endswith("_" + kind)))

    res = {
        "example": "onnx_deploy",
        "smoke": bool(args.smoke),
        "scene": scene.name,
        "frames": frames,
        "width": W,
        "height": H,
        "position_threshold": pos,
        "normal_threshold": nrm,
        "alpha": alpha,
        "max_abs_diff": {k: max_diff(k) for k in ("right", "right_len", "stereo", "left")},
        "mask_mismatch_pixels": {k: mismatches(k) for k in ("right_valid", "stereo_valid", "stereo_reason")},
        "onnxruntime_imported_torch": ort_info["torch_imported"],
        "ms_per_frame_onnxruntime": float(np.median(ort_info["ms_per_frame"])),
        "ms_per_frame_torch": float(np.median(torch_ms)),
        "seconds": {"trace": t_trace, "export": t_export},
    }
    res["max_abs_diff_all"] = max(res["max_abs_diff"].values())
    (out / "onnx_deploy.json").write_text(json.dumps(res, indent=1))
    print(f"onnx_deploy: {frames} frames of {scene.name} at {W}x{H}; onnxruntime (no torch in process) vs torch:")
    print("  max |diff|: " + ", ".join(f"{k} {v:.2e}" for k, v in res["max_abs_diff"].items()))
    print(f"  mask/reason mismatches (pixels): {res['mask_mismatch_pixels']}")
    print(
        f"  per frame (median): onnxruntime {res['ms_per_frame_onnxruntime']:.1f} ms, "
        f"torch {res['ms_per_frame_torch']:.1f} ms  -> {out / 'onnx_deploy.json'}"
    )
    return res


if __name__ == "__main__":
    main()
