"""The frame-sequence reader (:mod:`stereorepro.io.frames`): its named result, and the files it refuses."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch

from stereorepro.camera import Eye
from stereorepro.errors import SequenceError
from stereorepro.io.exr import write_exr
from stereorepro.io.frames import EYES, Frame, load_sequence, read_frame

W, H = 8, 6


def _channels(value: float = 1.0, motion: bool = False) -> dict:
    ch = {c: np.full((H, W), value, np.float32) for c in ("R", "G", "B")}
    ch["Z"] = np.full((H, W), 2.0, np.float32)
    ch.update(
        {
            "N.X": np.zeros((H, W), np.float32),
            "N.Y": np.zeros((H, W), np.float32),
            "N.Z": np.full((H, W), -1.0, np.float32),
        }
    )
    if motion:
        ch.update({"M.X": np.full((H, W), 0.5, np.float32), "M.Y": np.zeros((H, W), np.float32)})
    # Mitsuba's AOVs too (extra channels for our format): the same directory reads --from mitsuba
    ch.update(
        {
            "dd.T": ch["Z"],
            "nn.X": ch["N.X"],
            "nn.Y": ch["N.Y"],
            "nn.Z": ch["N.Z"],
            "pp.X": ch["N.X"],
            "pp.Y": ch["N.Y"],
            "pp.Z": ch["Z"],
        }
    )
    return ch


def _camera() -> dict:
    return {"K": [[8.0, 0.0, W / 2], [0.0, 8.0, H / 2], [0.0, 0.0, 1.0]], "cam_from_world": np.eye(4).tolist()}


def write_sequence(d, n: int = 2, motion: bool = False):
    """A tiny valid input directory of ``n`` frames (our format)."""
    d.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        for e in EYES:
            write_exr(d / f"{i:04d}_{e}.exr", _channels(i + 1.0, motion and i > 0))
    (d / "cameras.json").write_text(
        json.dumps(
            {
                "frames": [{"left": _camera(), "right": _camera()}] * n,
                "reprojection": {"position_threshold": 0.1, "normal_threshold": 0.25},
            }
        )
    )
    return d


class TestFrame:
    def test_smoke(self, tmp_path):
        seq = load_sequence(write_sequence(tmp_path / "in", motion=True))
        f = read_frame(seq, 0, "left")
        assert isinstance(f, Frame)
        assert f.color.shape == (1, 3, H, W) and f.depth.shape == (1, 1, H, W) and f.normal.shape == (1, 3, H, W)
        assert f.K.dtype == torch.float64 and f.cam_from_world.shape == (1, 4, 4)
        assert f.motion is None and f.motion_world is None  # frame 0 has no motion channels
        assert f.normal_stats == {"surface": H * W, "renormalised": 0, "invalid": 0}
        g = read_frame(seq, 1, Eye.RIGHT)
        assert g.motion.shape == (1, 2, H, W) and g.motion_world is None and float(g.color[0, 0, 0, 0]) == 2.0

    def test_eyes(self):
        assert EYES == ("left", "right") and EYES == (Eye.LEFT, Eye.RIGHT)

    def test_dict_access_is_deprecated_but_works(self, tmp_path):
        seq = load_sequence(write_sequence(tmp_path / "in", motion=True))
        f, g = read_frame(seq, 0, "left"), read_frame(seq, 1, "left")
        with pytest.warns(DeprecationWarning, match=r"Frame \['color'\].*attribute access"):
            assert f["color"] is f.color
        with pytest.warns(DeprecationWarning):
            assert "motion" not in f and "motion" in g and "normal_stats" in f
        with pytest.warns(DeprecationWarning):
            assert f.get("motion") is None and g.get("motion") is g.motion and f.get("motion", 3) == 3
        with pytest.warns(DeprecationWarning), pytest.raises(KeyError, match="motion"):
            f["motion"]
        with pytest.warns(DeprecationWarning):
            d = dict(g)
        assert sorted(d) == sorted(["color", "depth", "normal", "K", "cam_from_world", "motion", "normal_stats"])
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            _ = f.color, f.motion, g.motion_world  # attribute access: no warning


class TestFramesRefused:
    def test_shifted_data_window(self, tmp_path):
        """Our format and Mitsuba's: a file whose pixels are shifted against the display window (the cameras'
        pixel grid) is refused, naming the file and both windows."""
        import OpenEXR

        d = write_sequence(tmp_path / "in")
        shifted = {
            "dataWindow": (np.array([5, 3], np.int32), np.array([W + 4, H + 2], np.int32)),
            "displayWindow": (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32)),
        }
        OpenEXR.File(shifted, _channels()).write(str(d / "0001_left.exr"))
        for source in ("stereorepro", "mitsuba"):
            with pytest.raises(
                SequenceError,
                match=r"0001_left\.exr: data window \(\(5, 3\), .* differs from the "
                r"display window \(\(0, 0\)",
            ):
                load_sequence(d, source=source)

    def test_mitsuba_channel_shapes(self):
        """The Mitsuba converter's Python API with a channel of another size: one SequenceError naming it (numpy's
        'all input arrays must have the same shape' before)."""
        from stereorepro.camera import PinholeCamera
        from stereorepro.io.mitsuba import MITSUBA_CHANNELS, frame_from_channels

        cam = PinholeCamera(
            torch.tensor([[[8.0, 0, W / 2], [0, 8.0, H / 2], [0, 0, 1]]], dtype=torch.float64),
            torch.eye(4, dtype=torch.float64)[None],
            H,
            W,
        )
        ch = {c: np.ones((H, W), np.float32) for c in MITSUBA_CHANNELS}
        assert frame_from_channels(ch, cam, "f.exr")["depth"].shape == (1, 1, H, W)
        ch["nn.Y"] = np.ones((H, W + 1), np.float32)
        with pytest.raises(SequenceError, match=rf"f\.exr: channel nn\.Y is {W + 1}x{H}, the camera {W}x{H}"):
            frame_from_channels(ch, cam, "f.exr")
        ch = {c: np.ones((H - 1, W), np.float32) for c in MITSUBA_CHANNELS}  # all alike, but not the camera's
        with pytest.raises(SequenceError, match=r"channel R is"):
            frame_from_channels(ch, cam, "f.exr")
