"""EXR frame I/O."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereorepro.errors import ShapeError
from stereorepro.io.exr import exr_to_tensors, read_exr, write_exr
from stereorepro.render import RenderResult


def _result(H=5, W=7):
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(1, 1, H, W, generator=g) * 10
    depth[0, 0, 0, :3] = float("inf")
    return RenderResult(
        radiance=torch.rand(1, 3, H, W, generator=g) * 100,
        depth=depth,
        normal=torch.randn(1, 3, H, W, generator=g),
        position=torch.randn(1, 3, H, W, generator=g),
        albedo=torch.rand(1, 3, H, W, generator=g),
        material_id=torch.zeros(1, 1, H, W, dtype=torch.int32),
    )


class TestExr:
    def test_smoke(self, tmp_path):
        r = _result()
        p = tmp_path / "f.exr"
        write_exr(p, r)
        ch = read_exr(p)
        assert set(ch) == {"R", "G", "B", "Z", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"}
        t = exr_to_tensors(ch)
        for name in ("radiance", "depth", "normal", "position"):
            assert torch.equal(t[name], getattr(r, name)), name  # lossless, +inf included
        assert [q.name for q in tmp_path.iterdir()] == ["f.exr"]  # no temp file left

    def test_shapes(self, tmp_path):
        ch = read_exr(_write(tmp_path, {"A": np.ones((3, 4), np.float32)}))
        assert ch["A"].shape == (3, 4) and ch["A"].dtype == np.float32

    def test_hard_cases_strided_input(self, tmp_path):
        """OpenEXR ignores numpy strides: a transposed / sliced view must still be written correctly."""
        base = np.arange(48, dtype=np.float32).reshape(6, 8)
        big = np.arange(192, dtype=np.float32).reshape(16, 12)
        chans = {"X": base.T, "Y": big[::2, ::2]}
        keys = {k: id(v) for k, v in chans.items()}
        ch = read_exr(_write(tmp_path, chans))
        assert np.array_equal(ch["X"], base.T) and np.array_equal(ch["Y"], big[::2, ::2])
        assert {k: id(v) for k, v in chans.items()} == keys  # the caller's dict is not modified

    def test_exceptions(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="missing.exr"):
            read_exr(tmp_path / "missing.exr")
        bad = tmp_path / "bad.exr"
        bad.write_bytes(b"not an exr")
        with pytest.raises(ValueError, match="bad.exr"):
            read_exr(bad)
        with pytest.raises(ShapeError, match="same size|one size"):
            write_exr(tmp_path / "x.exr", {"A": np.zeros((2, 2)), "B": np.zeros((3, 2))})

    def test_empty_channels(self, tmp_path):
        """0x0 (and 0xW) channels: a ShapeError naming the file, nothing written (OpenEXR's raw RuntimeError)."""
        for shape in ((0, 0), (0, 4), (3, 0)):
            with pytest.raises(ShapeError, match=r"x\.exr: channels of shape .* are empty"):
                write_exr(tmp_path / "x.exr", {"R": np.zeros(shape, np.float32)})
        assert list(tmp_path.iterdir()) == []


def _write(tmp_path, chans):
    p = tmp_path / "c.exr"
    write_exr(p, chans)
    return p


def _forge_data_window(path, width: int, height: int) -> None:
    """Rewrite the header's dataWindow (box2i: xMin, yMin, xMax, yMax) of a small file to claim a huge image."""
    data = bytearray(path.read_bytes())
    key = b"dataWindow\x00box2i\x00" + (16).to_bytes(4, "little")
    at = data.index(key) + len(key)
    data[at : at + 16] = np.array([0, 0, width - 1, height - 1], "<i4").tobytes()
    path.write_bytes(bytes(data))


class TestReadExrHardCases:
    """Malformed files: forged headers, corrupt pixel data, multi-part files with grouped channel names, half
    channels."""

    def test_forged_huge_header_is_refused_before_allocating(self, tmp_path):
        import resource

        p = _write(tmp_path, {"R": np.ones((4, 4), np.float32)})
        _forge_data_window(p, 40000, 40000)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        with pytest.raises(ValueError, match=r"c\.exr.*(MAX_SAMPLES|truncated or corrupt)"):
            read_exr(p)
        grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
        assert grown_mib < 256, f"the reader allocated {grown_mib:.0f} MiB for a forged header"

    def test_header_larger_than_file_can_hold(self, tmp_path):
        p = _write(tmp_path, {"R": np.ones((4, 4), np.float32)})
        _forge_data_window(p, 4000, 4000)  # 16 M samples, fewer than MAX_SAMPLES, in a file of a few hundred bytes
        with pytest.raises(ValueError, match="truncated or corrupt"):
            read_exr(p)

    def test_corrupt_pixel_data_one_message_no_noise(self, tmp_path, capfd):
        rng = np.random.default_rng(0)
        p = _write(tmp_path, {"R": rng.random((64, 64)).astype(np.float32)})
        data = bytearray(p.read_bytes())
        data[len(data) // 2 :] = rng.integers(0, 256, len(data) - len(data) // 2, dtype=np.uint8).tobytes()
        p.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=r"cannot read .*c\.exr as EXR"):
            read_exr(p)
        out, err = capfd.readouterr()
        assert err == "" and out == ""

    def test_multipart_grouped_names_and_half(self, tmp_path):
        """Blender writes one part per pass with grouped names such as ``ViewLayer.Combined.R`` (read_exr split
        them per character and crashed)."""
        import OpenEXR

        z = np.full((3, 5), 1e10, np.float32)
        parts = [
            OpenEXR.Part(
                {"name": "ViewLayer.Combined"},
                {f"ViewLayer.Combined.{c}": np.full((3, 5), i, np.float16) for i, c in enumerate("RGBA")},
            ),
            OpenEXR.Part({"name": "ViewLayer.Depth"}, {"ViewLayer.Depth.Z": z}),
        ]
        p = tmp_path / "blender.exr"
        OpenEXR.File(parts).write(str(p))
        ch = read_exr(p)
        assert sorted(ch) == [
            "ViewLayer.Combined.A",
            "ViewLayer.Combined.B",
            "ViewLayer.Combined.G",
            "ViewLayer.Combined.R",
            "ViewLayer.Depth.Z",
        ]
        assert all(v.dtype == np.float32 and v.shape == (3, 5) for v in ch.values())
        assert np.array_equal(ch["ViewLayer.Combined.B"], np.full((3, 5), 2.0, np.float32))
        assert np.array_equal(ch["ViewLayer.Depth.Z"], z)

    def test_rgb_group_names_kept(self, tmp_path):
        ch = read_exr(_write(tmp_path, {c: np.full((2, 2), i, np.float32) for i, c in enumerate("RGBA")}))
        assert sorted(ch) == ["A", "B", "G", "R"] and float(ch["B"][0, 0]) == 2.0

    def test_write_disk_full_leaves_nothing(self, tmp_path, monkeypatch):
        import errno

        from stereorepro.io import atomic

        def full(path, directory=False):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(atomic, "_fsync_path", full)
        with pytest.raises(OSError, match="No space") as e:
            write_exr(tmp_path / "f.exr", _result())
        assert e.value.filename == str(tmp_path / "f.exr") and list(tmp_path.iterdir()) == []


READ_FROM_THREADS = """
import os, sys
from concurrent.futures import ThreadPoolExecutor
from stereorepro.io.exr import exr_header, read_exr

good, bad = sys.argv[1], sys.argv[2]

def read(i):
    if i % 4 == 3:
        try:
            read_exr(bad)
        except ValueError as e:
            return "cannot read" in str(e)
        return False
    return read_exr(good)["R"].shape == (64, 64) and exr_header(good)[1] == [(64, 64)]

with ThreadPoolExecutor(8) as ex:
    ok = list(ex.map(read, range(64)))
print("after", all(ok), flush=True)
os.write(1, b"fd1\\n")
print("err", file=sys.stderr, flush=True)
os.write(2, b"fd2\\n")
"""


class TestReadExrThreads:
    def test_threads_keep_the_process_streams(self, tmp_path):
        """Reads from 8 threads (good files, corrupt ones, headers) overlap; afterwards print and the raw
        descriptors 1 and 2 still reach the process's stdout and stderr (overlapping reads restored each
        other's swapped streams: everything printed after them was lost)."""
        import subprocess
        import sys

        rng = np.random.default_rng(0)
        good = _write(tmp_path, {"R": rng.random((64, 64)).astype(np.float32)})
        bad = tmp_path / "bad.exr"
        data = bytearray(good.read_bytes())
        data[len(data) // 2 :] = rng.integers(0, 256, len(data) - len(data) // 2, dtype=np.uint8).tobytes()
        bad.write_bytes(bytes(data))
        r = subprocess.run(
            [sys.executable, "-c", READ_FROM_THREADS, str(good), str(bad)], capture_output=True, text=True, timeout=120
        )
        assert r.returncode == 0, r.stderr[-2000:]
        assert r.stdout == "after True\nfd1\n" and r.stderr == "err\nfd2\n", (r.stdout, r.stderr)
