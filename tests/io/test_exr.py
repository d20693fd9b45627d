"""EXR frame I/O."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereorepro.render import RenderResult, exr_to_tensors, read_exr, write_exr


def _result(H=5, W=7):
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(1, 1, H, W, generator=g) * 10
    depth[0, 0, 0, :3] = float("inf")
    return RenderResult(radiance=torch.rand(1, 3, H, W, generator=g) * 100, depth=depth,
                        normal=torch.randn(1, 3, H, W, generator=g), position=torch.randn(1, 3, H, W, generator=g),
                        albedo=torch.rand(1, 3, H, W, generator=g),
                        material_id=torch.zeros(1, 1, H, W, dtype=torch.int32))


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
        with pytest.raises(ValueError, match="same size|one size"):
            write_exr(tmp_path / "x.exr", {"A": np.zeros((2, 2)), "B": np.zeros((3, 2))})


def _write(tmp_path, chans):
    p = tmp_path / "c.exr"
    write_exr(p, chans)
    return p
