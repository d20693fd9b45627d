"""What a user gets from ``pip install`` of the repository, checked in the fresh virtual environment that
``.ci/test-install`` made (run with that environment's python, outside the checkout).

``core``: ``pip install .`` with the compiler disabled: the ops run on torch without the native core and without any
optional dependency; each missing extra is one error naming it. ``experiment``: then ``pip install '.[experiment]'``
with the compiler: the native core, the tracer, EXR files and ``stereorepro demo`` (a small run).
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

OPTIONAL = ("embreex", "OpenEXR", "trimesh", "matplotlib", "kornia", "tqdm", "flip_evaluator", "onnx", "mitsuba")


def _stereorepro(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("stereorepro")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, check=False)


def _installed_outside_the_checkout(checkout: Path) -> None:
    import stereorepro
    from stereorepro.scenes import scenes_dir

    where = Path(stereorepro.__file__).resolve()
    assert checkout not in where.parents, f"imported from the checkout, not the installed package: {where}"
    assert where.parent in scenes_dir().parents, f"built-in scenes outside the package: {scenes_dir()}"


def _stereo_pair():
    """A plane at z = 2 seen by a rectified stereo pair 0.5 apart (2.6 pixels of disparity): the right eye
    reprojected from the left; its two rightmost columns see what the left eye does not."""
    import torch

    import stereorepro as sr

    H, W = 12, 16
    K = sr.intrinsics_from_fov(60.0, W, H)
    depth = torch.full((1, 1, H, W), 2.0)
    normal = torch.zeros(1, 3, H, W)
    normal[:, 2] = -1
    left = torch.eye(4)[None]
    right = left.clone()
    right[:, 0, 3] = -0.5  # cam_from_world: the right camera sits at x = +0.5
    color = torch.rand(1, 3, H, W)
    module = sr.StereoReprojection(0.2, 0.1)
    values, valid, reason = module(color, depth, normal, K, left, depth, normal, K, right)
    assert values.shape == color.shape and valid.dtype == torch.bool, (values.shape, valid.dtype)
    frac = float(valid.float().mean())
    assert frac == 14 / 16 and bool(valid[..., :14].all()), f"expected columns 0-13 reprojected, got {valid}"
    assert bool((reason[..., 14:] == int(sr.Reason.OUT_OF_FRAME)).all()), reason
    out = sr.stereo_reproject(color, sr.View(depth, normal, K, left), sr.View(depth, normal, K, right), (0.2, 0.1))
    assert torch.equal(out.valid, valid) and torch.equal(out.values, values)
    return frac


def core(checkout: Path) -> None:
    present = [m for m in OPTIONAL if importlib.util.find_spec(m) is not None]
    assert present == [], f"the core install pulled optional packages: {present}"
    assert importlib.util.find_spec("stereorepro._core") is None, "the native core was built (compiler disabled)"
    import stereorepro as sr

    _installed_outside_the_checkout(checkout)
    assert sr.StereoReprojection is not None
    frac = _stereo_pair()
    assert sr.load_scene("living_room").num_frames > 0  # the scene files ship with the package
    for what, call, extra in (("PathTracer", lambda: sr.PathTracer, "render"),
                              ("ssim", lambda: sr.ssim(*[__import__("torch").rand(1, 3, 16, 16)] * 2), "experiment"),
                              ("write_exr", lambda: sr.write_exr("/nonexistent/a.exr", {"R": [[0.0]]}), "exr")):
        try:
            call()
        except sr.errors.MissingDependencyError as e:
            assert f"stereorepro[{extra}]" in str(e) and e.extra == extra, (what, str(e))
        else:
            raise AssertionError(f"{what} ran without its extra")
    version = _stereorepro("--version")
    assert version.returncode == 0 and sr.__version__ in version.stdout, version
    demo = _stereorepro("demo", "--frames", "1")
    assert demo.returncode == 2 and "stereorepro[experiment]" in demo.stderr and "Traceback" not in demo.stderr, demo
    print(f"core install: ops on torch without the native core ({frac:.0%} of the right eye reprojected); "
          f"{version.stdout.strip()}; missing extras named: render, experiment, exr; demo without "
          f"[experiment]: {demo.stderr.strip()}")


def experiment(checkout: Path, out: Path) -> None:
    _installed_outside_the_checkout(checkout)
    assert importlib.util.find_spec("stereorepro._core") is not None, "the native core was not built"
    for m in ("embreex", "OpenEXR", "trimesh", "matplotlib", "kornia", "tqdm", "flip_evaluator"):
        assert importlib.util.find_spec(m) is not None, f"[experiment] did not install {m}"
    _stereo_pair()
    demo = _stereorepro("demo", "--frames", "4", "--resolution", "64x36", "--reference-spp", "16",
                        "--ladder-spp", "4", "--no-progress", "--out", str(out))
    assert demo.returncode == 0, demo.stdout + demo.stderr
    for name in ("report.md", "results.json", "tables.md", "fig1_discards.png"):
        assert (out / name).is_file(), f"demo wrote no {name}"
    print(f"experiment install: {_stereorepro('--version').stdout.strip()}; stereorepro demo (4 frames, 64x36) "
          f"wrote {out / 'report.md'}")


if __name__ == "__main__":
    mode, checkout = sys.argv[1], Path(sys.argv[2]).resolve()
    if mode == "core":
        core(checkout)
    elif mode == "experiment":
        experiment(checkout, Path(sys.argv[3]))
    else:
        raise SystemExit(f"usage: {sys.argv[0]} core|experiment CHECKOUT [DEMO_OUT]")
