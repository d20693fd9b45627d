"""Convention mistakes in external frame sequences are caught (warning on stderr and in summary.json), correct
sequences are not flagged; normals policy; NO_HISTORY frames kept out of the discard means."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from stereorepro.cli import main
from stereorepro.io.exr import read_exr, write_exr
from stereorepro.io.frames import load_sequence
from stereorepro.workflows.diagnose import diagnose_conventions
from stereorepro.workflows.export import export_sequence
from stereorepro.workflows.sequence import reproject_sequence

W, H = 96, 54


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return export_sequence("living_room", [0, 3, 6, 9], W, H, tmp_path_factory.mktemp("good") / "in", spp=1, seed=1)


def _copy(src, dst, cam=None, files=None):
    shutil.copytree(src, dst)
    doc = json.loads((dst / "cameras.json").read_text())
    if cam is not None:
        for fr in doc["frames"]:
            for e in ("left", "right"):
                fr[e]["cam_from_world"] = cam(np.array(fr[e]["cam_from_world"])).tolist()
        (dst / "cameras.json").write_text(json.dumps(doc))
    if files is not None:
        files(dst, doc)
    return dst


def _swap_eyes(d, doc):
    for i in range(len(doc["frames"])):
        a, b = d / f"{i:04d}_left.exr", d / f"{i:04d}_right.exr"
        a.rename(d / "t.exr")
        b.rename(a)
        (d / "t.exr").rename(b)


def _ray_length(d, doc):
    for i in range(len(doc["frames"])):
        for e in ("left", "right"):
            p = d / f"{i:04d}_{e}.exr"
            ch = read_exr(p)
            K = np.array(doc["frames"][i][e]["K"])
            ys, xs = np.mgrid[0:H, 0:W]
            x, y = (xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1]
            ch["Z"] = (ch["Z"] * np.sqrt(1 + x * x + y * y)).astype(np.float32)
            write_exr(p, ch)


MISTAKES = {
    "inverted": dict(cam=np.linalg.inv),
    "axes": dict(cam=lambda T: np.diag([-1.0, -1.0, 1.0, 1.0]) @ T),  # Mitsuba's x-left, y-up camera frame
    "swapped": dict(files=_swap_eyes),
    "ray_length": dict(files=_ray_length),
}


class TestDiagnoseConventions:
    @pytest.mark.parametrize("mode", ["stereo", "temporal", "both"])
    def test_correct_sequence_not_flagged(self, good, mode):
        seq = load_sequence(good)
        assert diagnose_conventions(seq, mode, ("left", "right"), seq.position_threshold, seq.normal_threshold) == []

    @pytest.mark.parametrize("scene", ["classroom", "atrium", "living_room_moving_objects"])
    def test_other_correct_scenes_not_flagged(self, tmp_path, scene):
        d = export_sequence(scene, [10, 13, 16], 64, 36, tmp_path / "in", spp=1, seed=2)
        seq = load_sequence(d)
        assert diagnose_conventions(seq, "both", ("left", "right"), seq.position_threshold, seq.normal_threshold) == []

    @pytest.mark.parametrize("mistake", sorted(MISTAKES))
    def test_each_mistake_named(self, good, tmp_path, capsys, mistake):
        d = _copy(good, tmp_path / "in", **MISTAKES[mistake])
        out = tmp_path / "out"
        assert main(["reproject", "--input", str(d), "--out", str(out), "--mode", "both", "--quiet"]) == 0
        err = capsys.readouterr().err
        summary = json.loads((out / "summary.json").read_text())
        named = [w for w in summary["warnings"] if mistake in w.get("suspects", [])]
        assert named, summary["warnings"]
        assert "stereorepro reproject: warning:" in err
        w = named[0]
        assert w["position_pct_if_fixed"] < w["position_pct"] / 2

    def test_swap_and_inversion_told_apart(self, good, tmp_path):
        """In stereo alone a translated rig with inverted cameras looks like swapped eyes; with the temporal test
        (mode both) each is named alone."""
        for mistake, expected in (("swapped", ["swapped"]), ("inverted", ["inverted"])):
            d = _copy(good, tmp_path / mistake, **MISTAKES[mistake])
            s = reproject_sequence(d, tmp_path / f"o_{mistake}", "both")
            suspects = {w["test"]: w["suspects"] for w in s["warnings"]}
            last = suspects.get("temporal", suspects.get("stereo"))
            assert last == expected, s["warnings"]


class TestNormalsPolicy:
    def test_non_unit_normals_renormalised(self, good, tmp_path):
        d = _copy(good, tmp_path / "in")
        ref = reproject_sequence(good, tmp_path / "ref", "stereo")
        for p in d.glob("*_right.exr"):
            ch = read_exr(p)
            for c in ("N.X", "N.Y", "N.Z"):
                ch[c] = ch[c] * np.float32(0.7)  # averaged over samples: shorter than 1
            write_exr(p, ch)
        got = reproject_sequence(d, tmp_path / "out", "stereo")
        assert got["mean_discard_pct"] == pytest.approx(ref["mean_discard_pct"], abs=0.05)
        assert got["warnings"] == []

    def test_zero_normals_warned(self, good, tmp_path):
        d = _copy(good, tmp_path / "in")
        p = d / "0002_left.exr"
        ch = read_exr(p)
        for c in ("N.X", "N.Y", "N.Z"):
            ch[c][:] = 0.0
        write_exr(p, ch)
        s = reproject_sequence(d, tmp_path / "out", "stereo")
        w = [w for w in s["warnings"] if w["test"] == "normals"]
        assert len(w) == 1 and w[0]["frame"] == 2 and w[0]["eye"] == "left" and "normals are zero" in w[0]["message"]
        assert s["per_frame"][2]["left"]["normals"]["invalid"] == s["per_frame"][2]["left"]["normals"]["surface"]


class TestNoHistoryFrames:
    def test_means_exclude_no_history_frames(self, good, tmp_path):
        """summary.json in both mode averaged frame 0 (NO_HISTORY, 100 %) into the right eye's mean discard."""
        s = reproject_sequence(good, tmp_path / "o", "both")
        right = [f["right"]["discard_pct"] for f in s["per_frame"]]
        assert s["no_history_frames"]["right"] == [0] and right[0] == 100.0
        assert s["mean_discard_pct"]["right"] == pytest.approx(np.mean(right[1:]))
        assert s["no_history_frames"]["left"] == []  # the stereo test of the left eye has no history to lack
