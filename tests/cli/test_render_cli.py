"""CLI: ``stereorepro scenes`` and ``stereorepro render``."""

from __future__ import annotations

import torch

from stereorepro.cli import main
from stereorepro.io.exr import exr_to_tensors, read_exr


class TestRenderCli:
    def test_smoke(self, tmp_path, capsys):
        assert main(["scenes"]) == 0
        out = capsys.readouterr().out
        assert "atrium_glossy" in out and "classroom" in out
        p = tmp_path / "f.exr"
        assert (
            main(
                [
                    "render",
                    "--scene",
                    "living_room",
                    "--frame",
                    "3",
                    "--spp",
                    "1",
                    "--resolution",
                    "16x9",
                    "--out",
                    str(p),
                    "--quiet",
                ]
            )
            == 0
        )
        t = exr_to_tensors(read_exr(p))
        assert t["radiance"].shape == (1, 3, 9, 16) and torch.isfinite(t["depth"]).all()

    def test_exceptions(self, tmp_path, capsys):
        assert main(["render", "--scene", "nope", "--out", str(tmp_path / "a.exr")]) == 2
        assert "unknown scene" in capsys.readouterr().err
        assert main(["render", "--scene", "atrium", "--frame", "60", "--out", str(tmp_path / "a.exr")]) == 2
        assert main(["render", "--scene", "atrium", "--spp", "0", "--out", str(tmp_path / "a.exr")]) == 2
        assert main(["render", "--scene", "atrium", "--out", str(tmp_path / "a.png")]) == 2
