"""``stereorepro reproject`` and ``export-sequence``: external G-buffer directories, end to end from our tracer."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from stereorepro import SpatiotemporalReprojection, StereoReprojection, has_surface
from stereorepro.cli import main
from stereorepro.errors import SequenceError
from stereorepro.io.exr import read_exr, write_exr
from stereorepro.io.frames import REQUIRED_CHANNELS, load_sequence, read_frame
from stereorepro.workflows.export import export_sequence
from stereorepro.workflows.sequence import NO_HISTORY, reproject_sequence

W, H, N = 32, 18, 3


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    """Three stereo frames of living_room at 32x18, 1 spp, written by our tracer (full channel set)."""
    return export_sequence("living_room", [0, 2, 4], W, H, tmp_path_factory.mktemp("seq"), spp=1, seed=3, workers=2)


@pytest.fixture
def work_dir(seq_dir, tmp_path):
    """A private, mutable copy of the sequence."""
    d = tmp_path / "in"
    shutil.copytree(seq_dir, d)
    return d


def _frames(d):
    return sorted(p.name for p in d.iterdir())


class TestReprojectCli:
    def test_smoke(self, seq_dir, tmp_path, capsys):
        out = tmp_path / "out"
        assert main(["reproject", "--input", str(seq_dir), "--out", str(out)]) == 0
        assert "mean discarded" in capsys.readouterr().out
        names = _frames(out)
        assert names == sorted(
            [f"{i:04d}_{e}_reprojected.exr" for i in range(N) for e in ("left", "right")] + ["summary.json"]
        )
        ch = read_exr(out / "0001_left_reprojected.exr")
        assert set(ch) == {"R", "G", "B", "valid", "reason", "history_len"}
        assert ch["R"].shape == (H, W)
        assert set(np.unique(ch["valid"])) <= {0.0, 1.0}
        summary = json.loads((out / "summary.json").read_text())
        assert summary["mode"] == "both" and summary["frames"] == N and len(summary["per_frame"]) == N
        # thresholds come from cameras.json: scene values, position scaled by 180 / height
        assert summary["position_threshold"] == pytest.approx(0.05 * 180 / H)

    def test_cardinality(self, seq_dir, tmp_path):
        for mode, eye, want in (
            ("stereo", None, {"left"}),
            ("temporal", "both", {"left", "right"}),
            ("temporal", None, {"right"}),
        ):
            out = tmp_path / f"{mode}{eye}"
            args = ["reproject", "--input", str(seq_dir), "--out", str(out), "--mode", mode, "--quiet"]
            assert main(args + (["--eye", eye] if eye else [])) == 0
            eyes = {n.split("_")[1] for n in _frames(out) if n.endswith(".exr")}
            assert eyes == want and len(_frames(out)) == N * len(want) + 1
            ch = read_exr(out / f"0000_{sorted(want)[0]}_reprojected.exr")
            assert ("history_len" in ch) == (mode == "temporal")

    def test_stereo_matches_module(self, seq_dir, tmp_path):
        out = tmp_path / "o"
        reproject_sequence(seq_dir, out, "stereo", position_threshold=0.4, normal_threshold=0.3)
        seq = load_sequence(seq_dir)
        L, R = read_frame(seq, 1, "left"), read_frame(seq, 1, "right")
        color, valid, reason = StereoReprojection(0.4, 0.3)(
            R.color, R.depth, R.normal, R.K, R.cam_from_world, L.depth, L.normal, L.K, L.cam_from_world
        )
        ch = read_exr(out / "0001_left_reprojected.exr")
        np.testing.assert_array_equal(np.stack([ch["R"], ch["G"], ch["B"]]), color[0].numpy())
        np.testing.assert_array_equal(ch["valid"], valid[0, 0].float().numpy())
        np.testing.assert_array_equal(ch["reason"], reason[0, 0].float().numpy())
        assert 0.5 < valid.float().mean() < 1.0  # a real stereo pair: most pixels kept, some discarded

    def test_catmull_rom_through_the_cli(self, seq_dir, tmp_path):
        """``--sampling catmull_rom`` reaches the module: the same pixels kept as bilinear, other colours (a loose
        position test: at 32x18 few 4x4 footprints pass the scene's own)."""
        outs = {}
        for sampling in ("bilinear", "catmull_rom"):
            outs[sampling] = tmp_path / sampling
            argv = ["reproject", "--input", str(seq_dir), "--out", str(outs[sampling]), "--mode", "stereo"]
            assert main(argv + ["--position-threshold", "2", "--normal-threshold", "0.3", "--sampling", sampling]) == 0
        seq = load_sequence(seq_dir)
        L, R = read_frame(seq, 1, "left"), read_frame(seq, 1, "right")
        color, _, _ = StereoReprojection(2.0, 0.3, "catmull_rom")(
            R.color, R.depth, R.normal, R.K, R.cam_from_world, L.depth, L.normal, L.K, L.cam_from_world
        )
        cubic, linear = (read_exr(outs[s] / "0001_left_reprojected.exr") for s in ("catmull_rom", "bilinear"))
        np.testing.assert_array_equal(np.stack([cubic["R"], cubic["G"], cubic["B"]]), color[0].numpy())
        np.testing.assert_array_equal(cubic["valid"], linear["valid"])
        assert not np.array_equal(cubic["R"], linear["R"])

    def test_both_matches_driver(self, seq_dir, tmp_path):
        out = tmp_path / "o"
        summary = reproject_sequence(seq_dir, out, "both")
        seq = load_sequence(seq_dir)
        st = SpatiotemporalReprojection(seq.position_threshold, seq.normal_threshold)
        for i in range(N):
            L, R = read_frame(seq, i, "left"), read_frame(seq, i, "right")
            right = st.right(R.color, R.depth, R.normal, R.K, R.cam_from_world)
            mask = st.left_trace_mask(L.depth, L.normal, L.K, L.cam_from_world)
            left = st.left(L.color)
        for eye, img in (("left", left), ("right", right)):
            ch = read_exr(out / f"{N - 1:04d}_{eye}_reprojected.exr")
            np.testing.assert_array_equal(np.stack([ch["R"], ch["G"], ch["B"]]), img[0].numpy())
        assert summary["per_frame"][-1]["left"]["discard_pct"] == pytest.approx(100 * mask.float().mean().item())
        surface = has_surface(L.depth)  # the share over surface pixels, the one the paper reports
        want = 100 * float((mask & surface).sum()) / float(surface.sum())
        assert summary["per_frame"][-1]["left"]["surface_discard_pct"] == pytest.approx(want)
        assert summary["mean_surface_discard_pct"]["left"] is not None

    def test_temporal_first_frame(self, seq_dir, tmp_path):
        out = tmp_path / "o"
        reproject_sequence(seq_dir, out, "temporal", eye="left")
        first, second = read_exr(out / "0000_left_reprojected.exr"), read_exr(out / "0001_left_reprojected.exr")
        seq = load_sequence(seq_dir)
        np.testing.assert_array_equal(first["R"], read_frame(seq, 0, "left").color[0, 0].numpy())
        assert (first["valid"] == 0).all() and (first["reason"] == NO_HISTORY).all()
        assert (first["history_len"] == 1).all()
        assert second["history_len"].max() == 2 and second["valid"].mean() > 0.5

    def test_extra_channels_ignored(self, work_dir, tmp_path):
        ch = read_exr(work_dir / "0000_left.exr")
        assert {"P.X", "P.Y", "P.Z"} <= set(ch)  # our tracer writes positions: ignored by the reader
        ch["albedo.R"] = np.zeros((H, W), np.float32)
        write_exr(work_dir / "0000_left.exr", ch)
        assert main(["reproject", "--input", str(work_dir), "--out", str(tmp_path / "o"), "--quiet"]) == 0

    def test_device(self, seq_dir, tmp_path):
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device")
        cpu, gpu = tmp_path / "cpu", tmp_path / "gpu"
        reproject_sequence(seq_dir, cpu, "both")
        reproject_sequence(seq_dir, gpu, "both", device="cuda")
        for name in _frames(cpu):
            if name.endswith(".exr"):
                a, b = read_exr(cpu / name), read_exr(gpu / name)
                np.testing.assert_allclose(a["R"], b["R"], rtol=1e-4, atol=1e-5)
                assert (a["valid"] != b["valid"]).mean() < 1e-2  # threshold ties may flip a few pixels


class TestReprojectCliExceptions:
    """Every user error: exit code 2, one line naming the file (and frame/key), nothing written."""

    def _fails(self, capsys, inp, out, *extra) -> str:
        assert main(["reproject", "--input", str(inp), "--out", str(out), "--quiet", *extra]) == 2
        assert not out.exists()  # nothing partial: the output directory is not even created
        return capsys.readouterr().err

    def test_missing_channel(self, work_dir, tmp_path, capsys):
        ch = read_exr(work_dir / "0002_right.exr")
        del ch["N.Z"]
        write_exr(work_dir / "0002_right.exr", ch)
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "0002_right.exr" in err and "N.Z" in err and "missing channel" in err

    def test_size_mismatch(self, work_dir, tmp_path, capsys):
        ch = {k: v[:-2] for k, v in read_exr(work_dir / "0001_left.exr").items()}
        write_exr(work_dir / "0001_left.exr", ch)
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "0001_left.exr" in err and f"{W}x{H - 2}" in err and f"{W}x{H}" in err

    def test_malformed_json(self, work_dir, tmp_path, capsys):
        cams = work_dir / "cameras.json"
        good = json.loads(cams.read_text())
        cams.write_text(cams.read_text()[:-5])
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "cameras.json" in err and "malformed JSON" in err

        bad = json.loads(json.dumps(good))
        bad["frames"][1]["right"]["K"] = [[1, 0, 0], [0, 1, 0]]
        cams.write_text(json.dumps(bad))
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "frames[1].right.K" in err and "3x3" in err

        bad = json.loads(json.dumps(good))
        bad["frames"][2]["left"]["cam_from_world"][0][0] = "x"
        cams.write_text(json.dumps(bad))
        assert "frames[2].left.cam_from_world" in self._fails(capsys, work_dir, tmp_path / "o")

        bad = json.loads(json.dumps(good))
        bad["frames"][0]["left"]["cam_from_world"][0][0] = 2.0  # scaled: not rigid
        cams.write_text(json.dumps(bad))
        assert "rigid" in self._fails(capsys, work_dir, tmp_path / "o")

        bad = json.loads(json.dumps(good))
        del bad["frames"][0]["right"]
        cams.write_text(json.dumps(bad))
        assert "frames[0]: missing key 'right'" in self._fails(capsys, work_dir, tmp_path / "o")

        bad = json.loads(json.dumps(good))
        bad["frames"][0]["left"]["k"] = bad["frames"][0]["left"]["K"]  # a typo is an error, not silence
        cams.write_text(json.dumps(bad))
        assert "unknown key" in self._fails(capsys, work_dir, tmp_path / "o")

    def test_frame_count(self, work_dir, tmp_path, capsys):
        cams = work_dir / "cameras.json"
        good = json.loads(cams.read_text())
        fewer = dict(good, frames=good["frames"][:2])
        cams.write_text(json.dumps(fewer))
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "lists 2 frame(s)" in err and "0002_left.exr" in err
        cams.write_text(json.dumps(good))
        (work_dir / "0001_left.exr").unlink()
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "0001_left.exr" in err and "missing" in err
        # temporal on the right eye alone does not need the left files
        assert (
            main(["reproject", "--input", str(work_dir), "--out", str(tmp_path / "r"), "--mode", "temporal", "--quiet"])
            == 0
        )

    def test_options(self, work_dir, tmp_path, capsys):
        cams = work_dir / "cameras.json"
        doc = json.loads(cams.read_text())
        del doc["reprojection"]
        cams.write_text(json.dumps(doc))
        err = self._fails(capsys, work_dir, tmp_path / "o")
        assert "--position-threshold is required" in err
        err = self._fails(capsys, work_dir, tmp_path / "o", "--position-threshold", "0.1", "--eye", "left")
        assert "--eye applies to --mode temporal" in err
        assert (
            main(
                [
                    "reproject",
                    "--input",
                    str(work_dir),
                    "--out",
                    str(tmp_path / "o"),
                    "--quiet",
                    "--position-threshold",
                    "0.1",
                    "--normal-threshold",
                    "0.2",
                ]
            )
            == 0
        )
        # 0.1 is too tight for 18 rows (the scene's 0.05 scaled to this height is 0.28): warned, not silent
        assert "and the thresholds" in capsys.readouterr().err
        assert main(["reproject", "--input", str(work_dir), "--out", str(tmp_path / "x"), "--alpha", "-1"]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [
            "stereorepro reproject: error: argument --alpha: expected a positive number, got '-1'"
        ]
        with pytest.raises(SequenceError, match="not a directory"):
            load_sequence(tmp_path / "nope")

    def test_existing_output_untouched_on_error(self, work_dir, tmp_path, capsys):
        out = tmp_path / "o"
        out.mkdir()
        (out / "keep.txt").write_text("x")
        (work_dir / "0000_right.exr").write_bytes(b"not an exr")
        assert main(["reproject", "--input", str(work_dir), "--out", str(out), "--quiet"]) == 2
        assert "0000_right.exr" in capsys.readouterr().err
        assert _frames(out) == ["keep.txt"]

    def test_failure_mid_sequence_leaves_nothing(self, work_dir, tmp_path, monkeypatch):
        import stereorepro.workflows.sequence as rc

        real = rc.read_frame

        def flaky(seq, frame, eye, device=None):
            if frame == 2:
                raise SequenceError(f"{seq.path(frame, eye)}: simulated read failure")
            return real(seq, frame, eye, device)

        monkeypatch.setattr(rc, "read_frame", flaky)
        out = tmp_path / "o"
        out.mkdir()
        with pytest.raises(SequenceError, match="0002_"):
            reproject_sequence(work_dir, out, "both")
        assert _frames(out) == []  # frames 0 and 1 were staged, never moved in


class TestExportSequence:
    def test_smoke(self, tmp_path, capsys):
        out = tmp_path / "seq"
        assert (
            main(
                [
                    "export-sequence",
                    "--scene",
                    "atrium",
                    "--frames",
                    "2",
                    "--stride",
                    "5",
                    "--resolution",
                    "16x9",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        doc = json.loads((out / "cameras.json").read_text())
        assert doc["meta"]["scene_frames"] == [0, 5] and len(doc["frames"]) == 2
        ch = read_exr(out / "0001_right.exr")
        assert set(REQUIRED_CHANNELS) <= set(ch) and ch["R"].shape == (9, 16)
        seq = load_sequence(out)
        assert (seq.height, seq.width) == (9, 16)
        # cameras round-trip exactly (float64 in JSON)
        from stereorepro import load_scene

        left, _ = load_scene("atrium").stereo_cameras(5, 16, 9)
        assert torch.equal(seq.cameras[1]["left"].cam_from_world, left.cam_from_world)

    def test_exceptions(self, tmp_path, capsys):
        assert main(["export-sequence", "--scene", "nope", "--out", str(tmp_path / "a")]) == 2
        assert (
            main(
                [
                    "export-sequence",
                    "--scene",
                    "atrium",
                    "--frames",
                    "7",
                    "--stride",
                    "10",
                    "--out",
                    str(tmp_path / "a"),
                ]
            )
            == 2
        )
        assert "exceed" in capsys.readouterr().err


class TestMotionChannels:
    """Frames with motion channels (``M.*``, ``MW.*``): our tracer writes them for scenes with moving objects and
    ``reproject`` reads them for its temporal steps."""

    @pytest.fixture(scope="class")
    def moving_dir(self, tmp_path_factory):
        return export_sequence(
            "living_room_moving_objects", [20, 21, 22, 23], 64, 36, tmp_path_factory.mktemp("mseq"), spp=1, seed=1
        )

    def test_export_writes_motion_from_the_second_frame(self, moving_dir, seq_dir):
        assert "M.X" not in read_exr(moving_dir / "0000_left.exr")
        ch = read_exr(moving_dir / "0001_right.exr")
        assert {"M.X", "M.Y", "MW.X", "MW.Y", "MW.Z"} <= set(ch)
        assert "M.X" not in read_exr(seq_dir / "0001_left.exr")  # static scenes: the cameras say it all
        seq = load_sequence(moving_dir)
        fr = read_frame(seq, 1, "right")
        assert fr.motion.shape == (1, 2, 36, 64) and fr.motion_world.shape == (1, 3, 36, 64)
        assert float(fr.motion_world.nan_to_num().abs().max()) > 0

    @pytest.mark.parametrize("mode", ["temporal", "both"])
    def test_reproject_uses_motion(self, moving_dir, tmp_path, mode):
        with_mv = reproject_sequence(moving_dir, tmp_path / "mv", mode, eye="right")
        stripped = tmp_path / "in"
        shutil.copytree(moving_dir, stripped)
        for p in stripped.glob("*.exr"):
            write_exr(p, {k: v for k, v in read_exr(p).items() if not k.startswith("M")})
        without = reproject_sequence(stripped, tmp_path / "cam", mode, eye="right")
        assert [f["right"]["motion"] for f in with_mv["per_frame"]] == [False, True, True, True]
        assert not any(f["right"]["motion"] for f in without["per_frame"])
        later = slice(1, None)
        d_mv = np.mean([f["right"]["discard_pct"] for f in with_mv["per_frame"][later]])
        d_cam = np.mean([f["right"]["discard_pct"] for f in without["per_frame"][later]])
        assert d_mv < 0.85 * d_cam, (d_mv, d_cam)  # the moving objects keep their history


#: A ``reproject`` run whose frame reads or writes wait at a point for a file to appear (two runs interleaved).
GATED_RUN = """
import pathlib, sys, time
import stereorepro.workflows.sequence as rs
from stereorepro.cli import main

inp, out, role, signal, wait_for = sys.argv[1:6]

def wait():
    t = time.time()
    while not pathlib.Path(wait_for).exists():
        if time.time() - t > 120:
            sys.exit(f"gated run: {wait_for} never appeared")
        time.sleep(0.02)

if role == "fail":  # read the last (corrupt) frame only once the other run is staging
    real_read = rs.read_frame
    def read_frame(seq, frame, eye, device=None):
        if frame == len(seq) - 1:
            wait()
        return real_read(seq, frame, eye, device)
    rs.read_frame = read_frame
else:  # after the first staged file: tell, and go on once the failing run is over
    real_write, count = rs.write_exr, [0]
    def write_exr(path, chans):
        real_write(path, chans)
        count[0] += 1
        if count[0] == 1:
            pathlib.Path(signal).touch()
            wait()
    rs.write_exr = write_exr
sys.exit(main(["reproject", "--input", inp, "--out", out, "--quiet"]))
"""


class TestConcurrentRuns:
    def test_failing_run_keeps_a_concurrent_runs_output(self, seq_dir, work_dir, tmp_path):
        """Run A (last frame's pixel data corrupt) creates --out; run B (valid input) starts staging into it; A
        fails. A removes only its own staging (the folder it created still holds B's): B ends with exit 0 and its
        complete set. (A removed the whole folder it had created, B's staged frame with it: 6 of 7 files.)"""
        import subprocess
        import sys
        import time

        bad = work_dir / f"{N - 1:04d}_right.exr"
        data = bytearray(bad.read_bytes())
        data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)
        bad.write_bytes(bytes(data))
        out, b_staged, a_done = tmp_path / "out", tmp_path / "b_staged", tmp_path / "a_done"

        def run(inp, role, signal, wait_for):
            return subprocess.Popen(
                [sys.executable, "-c", GATED_RUN, str(inp), str(out), role, str(signal), str(wait_for)],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )

        a = run(work_dir, "fail", tmp_path / "unused", b_staged)
        t = time.time()
        while not (out.is_dir() and any(p.name.startswith(".staging-") for p in out.iterdir())):
            assert a.poll() is None and time.time() - t < 120, a.communicate()
            time.sleep(0.02)
        b = run(seq_dir, "ok", b_staged, a_done)
        _, a_err = a.communicate(timeout=180)
        a_done.touch()
        _, b_err = b.communicate(timeout=180)
        assert a.returncode == 2 and len(a_err.strip().splitlines()) == 1 and bad.name in a_err, a_err
        assert b.returncode == 0, b_err
        names = sorted([f"{i:04d}_{e}_reprojected.exr" for i in range(N) for e in ("left", "right")] + ["summary.json"])
        assert _frames(out) == names
        reference = tmp_path / "reference"
        reproject_sequence(seq_dir, reference, "both")
        for name in names[:-1]:
            got, want = read_exr(out / name), read_exr(reference / name)
            assert all(np.array_equal(got[k], want[k]) for k in want), name


class TestExportReplaces:
    def test_shorter_export_replaces_the_sequence(self, tmp_path, capsys):
        """export-sequence --frames 3 then --frames 2 into one folder: a valid reproject input of 2 frames (frame 2
        of the first export was left behind, and reproject refused the folder: 'frame files beyond them')."""
        out = tmp_path / "S"
        common = ["export-sequence", "--scene", "atrium", "--resolution", "16x9", "--out", str(out)]
        assert main(common + ["--frames", "3"]) == 0
        (out / "notes.txt").write_text("the user's")
        assert main(common + ["--frames", "2"]) == 0
        assert _frames(out) == [
            "0000_left.exr",
            "0000_right.exr",
            "0001_left.exr",
            "0001_right.exr",
            "cameras.json",
            "notes.txt",
        ]
        assert main(["reproject", "--input", str(out), "--out", str(tmp_path / "o"), "--quiet"]) == 0, (
            capsys.readouterr().err
        )
