"""CLI: ``--version``, help as plain text with every default shown, the resolution and scene-name messages,
``stereorepro scenes`` with the shared-mesh scenes, and a missing extra as one line."""

from __future__ import annotations

import argparse
import re

import pytest

from stereorepro import __version__
from stereorepro.cli import build_parser, main
from stereorepro.cli.main import _shown_default
from stereorepro.errors import MissingDependencyError

COMMANDS = ("scenes", "render", "experiment", "reproject", "export-sequence", "demo")
MARKUP = re.compile(r"`|:(func|mod|class|meth|data):")


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


class TestVersion:
    def test_version(self, capsys):
        assert main(["--version"]) == 0
        out = capsys.readouterr().out.strip()
        assert re.fullmatch(rf"stereorepro {re.escape(__version__)} \(native core: (built|not built .*)\)", out), out


class TestHelp:
    def test_top_level_help_is_plain_text(self, capsys):
        assert main(["--help"]) == 0
        out = capsys.readouterr().out
        assert not MARKUP.search(out), out
        assert "--version" in out and all(c in out for c in COMMANDS)

    @pytest.mark.parametrize("command", COMMANDS)
    def test_command_help_is_plain_text(self, capsys, command):
        assert main([command, "--help"]) == 0
        assert not MARKUP.search(capsys.readouterr().out)

    @pytest.mark.parametrize("command", COMMANDS)
    def test_every_default_is_shown(self, command):
        """Every option with a default (not a flag, not None) says it in its help."""
        parser = _subparsers(build_parser())[command]
        silent = [
            a.option_strings[0]
            for a in parser._actions
            if _shown_default(a) is not None and "default" not in (a.help or "").lower()
        ]
        assert silent == []

    def test_defaults_as_written(self, capsys):
        assert main(["demo", "--help"]) == 0
        out = " ".join(capsys.readouterr().out.split())
        assert "WxH (default: 240x135)" in out and "(default: living_room)" in out and "default: 128" in out
        assert main(["render", "--help"]) == 0
        out = " ".join(capsys.readouterr().out.split())
        assert "--resolution WxH default: 320x180" in out and "{left,right,head} default: left" in out


class TestMessages:
    @pytest.mark.parametrize("value", ["0x180", "320x0", "-4x3"])
    def test_resolution_must_be_positive(self, capsys, value):
        assert main(["render", "--scene", "atrium", "--out", "a.exr", f"--resolution={value}"]) == 2
        assert one_line(capsys).endswith(f"argument --resolution: width and height must be positive, got {value!r}")

    def test_resolution_format(self, capsys):
        assert main(["render", "--scene", "atrium", "--out", "a.exr", "--resolution", "320by180"]) == 2
        assert "expected WIDTHxHEIGHT (e.g. 320x180), got '320by180'" in one_line(capsys)

    def test_scene_did_you_mean(self, tmp_path, capsys):
        assert main(["render", "--scene", "livng_room", "--out", str(tmp_path / "a.exr"), "--quiet"]) == 2
        assert "unknown scene 'livng_room': did you mean 'living_room'?" in one_line(capsys)

    def test_missing_extra_one_line(self, monkeypatch, capsys):
        from stereorepro.cli import demo

        def missing(args):
            raise MissingDependencyError(
                "the experiment needs matplotlib, not installed: pip install 'stereorepro[experiment]'",
                name="matplotlib",
                extra="experiment",
            )

        monkeypatch.setattr(demo, "run_command", missing)
        assert main(["demo"]) == 2
        assert one_line(capsys) == (
            "stereorepro demo: error: the experiment needs matplotlib, not installed: "
            "pip install 'stereorepro[experiment]'"
        )


class TestScenes:
    def test_lists_the_shared_scenes_with_their_availability(self, tmp_path, capsys):
        """Without ``--all``; with the meshes' folder empty each shared scene says which file it misses."""
        assert main(["scenes", "--shared-scenes", str(tmp_path)]) == 0
        lines = {ln.split()[0]: ln for ln in capsys.readouterr().out.splitlines()}
        for name in ("shared_sponza", "shared_living_room", "shared_classroom"):
            assert "unavailable: mesh not found: " + str(tmp_path) in lines[name], lines[name]
        assert "frames=60" in lines["living_room"]

    def test_available_when_the_mesh_is_there(self, tmp_path, capsys):
        (tmp_path / "living_room").mkdir()
        (tmp_path / "living_room" / "living_room.ply").write_bytes(b"")
        assert main(["scenes", "--shared-scenes", str(tmp_path)]) == 0
        lines = {ln.split()[0]: ln for ln in capsys.readouterr().out.splitlines()}
        assert "frames=" in lines["shared_living_room"] and "unavailable" in lines["shared_classroom"]
