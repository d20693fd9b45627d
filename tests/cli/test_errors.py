"""The command line's error policy (README "Errors and guarantees"): user mistakes and a refusing disk → exit 2
with one line naming the file / argument; nothing partial in ``--out`` or the cache, after a failure or a kill."""

from __future__ import annotations

import errno
import json
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stereorepro.cli import main
from stereorepro.io import atomic

TINY_EXPERIMENT = [
    "--scene",
    "living_room",
    "--frames",
    "3",
    "--resolution",
    "32x18",
    "--reference-spp",
    "8",
    "--ladder-spp",
    "2",
    "--alphas",
    "",
    "--no-progress",
]


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def leftovers(folder: Path) -> list[str]:
    """Temporaries or staging folders of ours anywhere under ``folder``."""
    return [
        str(p)
        for p in folder.rglob("*")
        if p.name.endswith(atomic.TMP_SUFFIX) or p.name.startswith(atomic.STAGING_PREFIX)
    ]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("seq") / "in"
    assert (
        main(
            [
                "export-sequence",
                "--scene",
                "living_room",
                "--frames",
                "2",
                "--resolution",
                "32x18",
                "--out",
                str(d),
                "--quiet",
            ]
        )
        == 0
    )
    return d


class TestOptions:
    """Options that gave tracebacks or were silently accepted."""

    @pytest.mark.parametrize(
        "argv, needle",
        [
            (["render", "--scene", "living_room", "--workers", "0"], "argument --workers: expected an integer >= 1"),
            (
                ["render", "--scene", "living_room", "--sample-offset", "-5"],
                "argument --sample-offset: expected an integer >= 0",
            ),
            (["render", "--scene", "living_room", "--spp", "many"], "argument --spp"),
            (["experiment", *TINY_EXPERIMENT, "--alphas", "nan"], "argument --alphas: expected numbers in (0, 1]"),
            (["experiment", *TINY_EXPERIMENT, "--alphas", "0.1,x"], "argument --alphas"),
            (["experiment", *TINY_EXPERIMENT, "--workers", "0"], "argument --workers"),
            (["experiment", *TINY_EXPERIMENT, "--threshold-scale", "-1"], "argument --threshold-scale"),
            (["experiment", *TINY_EXPERIMENT, "--frames", "0"], "argument --frames"),
        ],
    )
    def test_bad_option_one_line(self, tmp_path, capsys, argv, needle):
        out = tmp_path / "out"
        argv = argv + ["--out", str(out / "a.exr" if argv[0] == "render" else out)]
        assert main(argv) == 2
        assert needle in one_line(capsys)
        assert not out.exists()

    def test_experiment_out_is_a_file(self, tmp_path, capsys):
        f = tmp_path / "results"
        f.write_text("x")
        assert main(["experiment", *TINY_EXPERIMENT, "--out", str(f)]) == 2
        assert f"{f} exists and is not a directory" in one_line(capsys)
        assert f.read_text() == "x"

    def test_experiment_validation_creates_nothing(self, tmp_path, capsys):
        out = tmp_path / "out"
        assert main(["experiment", *TINY_EXPERIMENT[:-1], "--frames", "999", "--out", str(out)]) == 2
        assert "frames must be in" in one_line(capsys)
        assert main(["experiment", "--scene", str(tmp_path / "nope.toml"), "--out", str(out)]) == 2
        assert "nope.toml" in one_line(capsys)
        assert not out.exists()

    def test_reproject_out_equals_input(self, sequence, tmp_path, capsys):
        before = sorted(p.name for p in sequence.iterdir())
        assert main(["reproject", "--input", str(sequence), "--out", str(sequence), "--quiet"]) == 2
        assert "is the input directory" in one_line(capsys)
        assert sorted(p.name for p in sequence.iterdir()) == before

    def test_reproject_out_is_a_file(self, sequence, tmp_path, capsys):
        f = tmp_path / "f"
        f.write_text("x")
        assert main(["reproject", "--input", str(sequence), "--out", str(f), "--quiet"]) == 2
        assert "exists and is not a directory" in one_line(capsys)

    def test_render_binary_scene_file(self, tmp_path, capsys):
        p = tmp_path / "scene.toml"
        p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
        assert main(["render", "--scene", str(p), "--out", str(tmp_path / "a.exr")]) == 2
        assert f"{p}: not a text (UTF-8) TOML file" in one_line(capsys)

    def test_nested_cameras_json(self, sequence, tmp_path, capsys):
        d = tmp_path / "in"
        shutil.copytree(sequence, d)
        (d / "cameras.json").write_text("[" * 100_000 + "]" * 100_000)
        assert main(["reproject", "--input", str(d), "--out", str(tmp_path / "o"), "--quiet"]) == 2
        assert "nested too deeply" in one_line(capsys)
        assert not (tmp_path / "o").exists()


def _out_arg(cmd: str, out: Path) -> list[str]:
    return ["--out", str(out / "a.exr" if cmd == "render" else out)]


#: Each command with the options it needs to start (``--out`` follows).
COMMANDS = {
    "render": ["render", "--scene", "living_room", "--resolution", "16x9", "--quiet"],
    "export-sequence": [
        "export-sequence",
        "--scene",
        "living_room",
        "--frames",
        "1",
        "--resolution",
        "16x9",
        "--quiet",
    ],
    "experiment": ["experiment", *TINY_EXPERIMENT],
}


class TestEnvironment:
    """The machine and the environment as the user set them: a bad STEREOREPRO_BACKEND, a resolution beyond the
    memory, numbers beyond the renderer's or float32's range, an unusable scheduler, experiments too small to
    measure. Each is refused before anything is created, in one line, exit 2 (render and reproject gave a
    ValueError traceback for the backend, the resolutions a 37-line MemoryError after creating --out)."""

    @pytest.mark.parametrize("cmd", ["render", "export-sequence", "experiment", "reproject"])
    def test_bad_backend_variable(self, sequence, tmp_path, capsys, monkeypatch, cmd):
        monkeypatch.setenv("STEREOREPRO_BACKEND", "bogus")
        out = tmp_path / "out"
        argv = ["reproject", "--input", str(sequence), "--quiet"] if cmd == "reproject" else COMMANDS[cmd]
        assert main(argv + _out_arg(cmd, out)) == 2
        assert one_line(capsys) == (
            f"stereorepro {cmd}: error: STEREOREPRO_BACKEND must be one of ('auto', "
            "'native', 'reference', 'torch', 'numpy'), got 'bogus'"
        )
        assert not out.exists()

    @pytest.mark.parametrize("cmd", ["render", "export-sequence", "experiment"])
    def test_resolution_beyond_memory(self, tmp_path, capsys, cmd):
        out = tmp_path / "out"
        assert main(COMMANDS[cmd] + ["--resolution", "100000x100000"] + _out_arg(cmd, out)) == 2
        line = one_line(capsys)
        assert f"stereorepro {cmd}: error: " in line and "at 100000x100000 needs about " in line, line
        assert "TiB of memory" in line and "use a smaller resolution" in line, line
        assert not out.exists()

    def test_sample_offset_beyond_the_sample_index(self, tmp_path, capsys):
        out = tmp_path / "a.exr"
        assert main(COMMANDS["render"] + ["--sample-offset", str(2**63), "--out", str(out)]) == 2
        assert "--sample-offset + --spp must be at most 2**63" in one_line(capsys)
        assert main(COMMANDS["render"] + ["--sample-offset", str(2**63 - 2), "--spp", "2", "--out", str(out)]) == 0
        assert out.is_file()

    @pytest.mark.parametrize("option", ["--position-threshold", "--normal-threshold"])
    def test_threshold_beyond_float32(self, sequence, tmp_path, capsys, option):
        out = tmp_path / "o"
        assert main(["reproject", "--input", str(sequence), "--out", str(out), option, "1e300", "--quiet"]) == 2
        assert one_line(capsys) == (
            f"stereorepro reproject: error: {option}: 1e+300 is beyond float32's range (|x| <= 3.402823e+38)"
        )
        assert not out.exists()

    @pytest.mark.parametrize("scheduler", ["tcp://127.0.0.1:99999", "tcp://127.0.0.1:0", "tcp://:8786", "local:0"])
    def test_scheduler_address(self, tmp_path, capsys, scheduler):
        out = tmp_path / "out"
        assert main(["experiment", *TINY_EXPERIMENT, "--scheduler", scheduler, "--out", str(out)]) == 2
        assert "scheduler must be 'local:N' (N >= 1) or 'tcp://HOST:PORT' (PORT in 1..65535)" in one_line(capsys)
        assert not out.exists()

    @pytest.mark.parametrize(
        "options, option",
        [
            (["--reference-spp", "2", "--ladder-spp", "2"], "reference_spp (--reference-spp) must be >= 4, got 2"),
            (
                ["--reference-spp", "16", "--ladder-spp", "4", "--reference-chunk-spp", "1"],
                "reference_chunk_spp (--reference-chunk-spp) must be >= 4, got 1",
            ),
            (
                ["--reference-spp", "8", "--ladder-spp", "2", "--reference-chunk-spp", "2"],
                "reference_chunk_spp (--reference-chunk-spp) must be >= 4, got 2",
            ),
        ],
    )
    def test_experiment_too_small_to_measure(self, tmp_path, capsys, options, option):
        """Ladders scored against references of 1 or 2 spp exited 2 only after rendering everything
        ("effective_spp: ladder error does not decrease"): refused first, naming the option."""
        out = tmp_path / "out"
        t0 = time.perf_counter()
        assert main(["experiment", *TINY_EXPERIMENT, *options, "--out", str(out)]) == 2
        assert option in one_line(capsys)
        assert not out.exists() and time.perf_counter() - t0 < 10

    def test_native_backend_runs_moving_objects(self, tmp_path, capsys, monkeypatch):
        """STEREOREPRO_BACKEND=native on the scene with moving objects (motion vectors): the native kernels read
        them, so the run completes (it was a RuntimeError traceback when native refused motion)."""
        pytest.importorskip("stereorepro._core")
        monkeypatch.setenv("STEREOREPRO_BACKEND", "native")
        out = tmp_path / "out"
        assert (
            main(
                [
                    "experiment",
                    *TINY_EXPERIMENT,
                    "--scene",
                    "living_room_moving_objects",
                    "--frames",
                    "2",
                    "--no-flip",
                    "--no-ssim",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        assert (out / "results.json").is_file()

    def test_shared_scenes_missing_are_unavailable(self, capsys, monkeypatch, tmp_path):
        """With STEREOREPRO_SHARED_SCENES naming no folder, ``scenes --all`` lists the shared_* scenes as
        unavailable (they were listed as available, and ``render`` then failed)."""
        monkeypatch.setenv("STEREOREPRO_SHARED_SCENES", str(tmp_path / "nonexistent"))
        assert main(["scenes", "--all"]) == 0
        shared = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("shared_")]
        assert shared and all("unavailable: mesh not found" in ln for ln in shared), shared


def _disk_full_at_fsync(monkeypatch):
    """Every file write fails as on a full disk (at the sync before the atomic rename)."""

    def full(path, directory=False):
        if directory:
            return
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(atomic, "_fsync_path", full)


class TestDiskFull:
    """Disk full: ``render`` and ``reproject`` exited 1 with a traceback; ``experiment`` crashed leaving a
    half-written figure and figures without results.json. Injected at the writer (every write of the package
    goes through stereorepro.io.atomic) for each command, then on a real 200 KiB filesystem where one can be
    mounted."""

    def test_render(self, tmp_path, capsys, monkeypatch):
        _disk_full_at_fsync(monkeypatch)
        out = tmp_path / "a.exr"
        assert main(["render", "--scene", "living_room", "--resolution", "16x9", "--out", str(out), "--quiet"]) == 2
        assert one_line(capsys) == f"stereorepro render: error: {out}: no space left on the device"
        assert list(tmp_path.iterdir()) == []

    def test_export_sequence(self, tmp_path, capsys, monkeypatch):
        _disk_full_at_fsync(monkeypatch)
        out = tmp_path / "seq"
        assert (
            main(
                [
                    "export-sequence",
                    "--scene",
                    "living_room",
                    "--frames",
                    "2",
                    "--resolution",
                    "16x9",
                    "--out",
                    str(out),
                    "--quiet",
                ]
            )
            == 2
        )
        assert "no space left on the device" in one_line(capsys)
        assert not out.exists()

    def test_reproject(self, sequence, tmp_path, capsys, monkeypatch):
        _disk_full_at_fsync(monkeypatch)
        out = tmp_path / "o"
        out.mkdir()
        (out / "keep.txt").write_text("x")
        assert main(["reproject", "--input", str(sequence), "--out", str(out), "--quiet"]) == 2
        assert "no space left on the device" in one_line(capsys)
        assert [p.name for p in out.iterdir()] == ["keep.txt"]

    def test_experiment(self, tmp_path, capsys, monkeypatch):
        _disk_full_at_fsync(monkeypatch)
        out = tmp_path / "exp"
        assert main(["experiment", *TINY_EXPERIMENT, "--out", str(out)]) == 2
        assert "no space left on the device" in one_line(capsys)
        assert leftovers(out) == [] and not (out / "results.json").exists()
        assert [p.name for p in out.iterdir()] == ["cache"] and list((out / "cache").iterdir()) == []

    def test_experiment_figures_all_or_none(self, tmp_path, capsys, monkeypatch):
        """A disk that fills while the figures are written: no figure without results.json."""
        real = atomic._fsync_path

        def full_for_figures(path, directory=False):
            if not directory and str(path).endswith(".png"):
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            return real(path, directory)

        monkeypatch.setattr(atomic, "_fsync_path", full_for_figures)
        out = tmp_path / "exp"
        assert main(["experiment", *TINY_EXPERIMENT, "--out", str(out)]) == 2
        assert "no space left on the device" in one_line(capsys)
        assert sorted(p.name for p in out.iterdir()) == ["cache"] and leftovers(out) == []

    @pytest.mark.parametrize("cmd", ["render", "export-sequence", "reproject", "experiment"])
    def test_real_small_filesystem(self, sequence, tmp_path, cmd):
        """The same on a real 200 KiB tmpfs (a user + mount namespace; skipped where that is not allowed)."""
        if not shutil.which("unshare"):
            pytest.skip("unshare(1) is not installed")
        probe = subprocess.run(
            [
                "unshare",
                "--user",
                "--map-root-user",
                "--mount",
                "sh",
                "-c",
                f"mount -t tmpfs -o size=8k tmpfs {tmp_path}",
            ],
            capture_output=True,
        )
        if probe.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs in a user namespace here: {probe.stderr.decode().strip()}")
        mnt = tmp_path / "full"
        mnt.mkdir()
        argv = {
            "render": [
                "render",
                "--scene",
                "living_room",
                "--resolution",
                "160x90",
                "--out",
                f"{mnt}/a.exr",
                "--quiet",
            ],
            "export-sequence": [
                "export-sequence",
                "--scene",
                "living_room",
                "--frames",
                "2",
                "--resolution",
                "64x36",
                "--out",
                f"{mnt}/seq",
                "--quiet",
            ],
            "reproject": ["reproject", "--input", str(sequence), "--out", f"{mnt}/rep", "--quiet"],
            "experiment": ["experiment", *TINY_EXPERIMENT, "--resolution", "64x36", "--out", f"{mnt}/exp"],
        }[cmd]
        size = "12k" if cmd == "reproject" else "200k"  # the reprojected 32x18 frames are small
        script = (
            f"mount -t tmpfs -o size={size} tmpfs {mnt} && "
            f"{shlex.join([sys.executable, '-m', 'stereorepro', *argv])}; rc=$?; "
            f"find {mnt} -name '*.tmp' -o -name '.staging-*' | sed 's/^/LEFT: /'; "
            f"ls {mnt} | sed 's/^/TOP: /'; exit $rc"
        )
        r = subprocess.run(
            ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script],
            capture_output=True,
            text=True,
            timeout=300,
        )
        err = r.stderr.strip().splitlines()
        assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
        assert len(err) == 1 and "no space left on the device" in err[0], err
        assert "LEFT: " not in r.stdout, r.stdout
        top = [ln[5:] for ln in r.stdout.splitlines() if ln.startswith("TOP: ")]
        assert top == (["exp"] if cmd == "experiment" else []), top


def _experiment_proc(out: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "stereorepro", "experiment", *TINY_EXPERIMENT, "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def _tables(out: Path) -> dict:
    r = json.loads((out / "results.json").read_text())
    return {k: r[k] for k in ("table1", "table2", "table2_variants")} | {
        "per_frame": [{k: f[k] for k in ("discard_pct", "rmse", "effective_spp")} for f in r["per_frame"]]
    }


class TestCrash:
    """``experiment`` killed with SIGKILL during renders and during figure writing, then rerun: the tables equal
    an uninterrupted run's and no temporary file is left (a kill during a cache write left ``*.tmp`` files in
    the cache forever; during figure writing, ``tmp*.png`` in ``--out``)."""

    @pytest.fixture(scope="class")
    def reference(self, tmp_path_factory) -> dict:
        out = tmp_path_factory.mktemp("uninterrupted")
        assert main(["experiment", *TINY_EXPERIMENT, "--out", str(out)]) == 0
        return _tables(out)

    @staticmethod
    def _kill_when(out: Path, ready, timeout: float = 120.0) -> None:
        p = _experiment_proc(out)
        t0 = time.monotonic()
        try:
            while not ready(out):
                assert p.poll() is None, "the run ended before the moment to kill it came"
                assert time.monotonic() - t0 < timeout
                time.sleep(0.002)
            p.send_signal(signal.SIGKILL)
        finally:
            p.wait()
        assert p.returncode == -signal.SIGKILL

    @pytest.mark.parametrize("moment", ["renders", "figures"])
    def test_kill_then_resume(self, reference, tmp_path, moment, capsys):
        out = tmp_path / "exp"
        if moment == "renders":  # a few cache entries in: the renders are under way
            ready = lambda o: len(list((o / "cache").glob("*.npz"))) >= 5  # noqa: E731
        else:  # the staging folder of the figures exists: they are being written
            ready = lambda o: (  # noqa: E731
                o.is_dir() and any(p.name.startswith(atomic.STAGING_PREFIX) for p in o.iterdir())
            )
        self._kill_when(out, ready)
        assert not (out / "results.json").exists()
        assert main(["experiment", *TINY_EXPERIMENT, "--out", str(out)]) == 0
        capsys.readouterr()
        assert _tables(out) == reference
        assert leftovers(out) == []
