"""The one atomic write: temporaries named by process, swept once their process is gone, staged sets of files,
errors naming the destination."""

from __future__ import annotations

import errno
import os
import stat
import subprocess
import sys

import pytest

from stereorepro.io import atomic
from stereorepro.io.atomic import atomic_path, atomic_write, staged_outputs, sweep


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


class TestAtomicWrite:
    def test_smoke(self, tmp_path):
        atomic_write(tmp_path / "a.txt", "x")
        assert (tmp_path / "a.txt").read_text() == "x" and os.listdir(tmp_path) == ["a.txt"]

    def test_umask(self, tmp_path):
        old = os.umask(0o022)
        try:
            atomic_write(tmp_path / "a.txt", "x")
        finally:
            os.umask(old)
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644

    def test_failure_leaves_nothing(self, tmp_path):
        (tmp_path / "a.txt").write_text("old")
        with pytest.raises(RuntimeError):
            with atomic_path(tmp_path / "a.txt") as tmp:
                tmp.write_text("half")
                raise RuntimeError("killed")
        assert os.listdir(tmp_path) == ["a.txt"] and (tmp_path / "a.txt").read_text() == "old"

    def test_disk_full_names_destination(self, tmp_path, monkeypatch):
        def full(path, directory=False):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

        monkeypatch.setattr(atomic, "_fsync_path", full)
        with pytest.raises(OSError) as e:
            atomic_write(tmp_path / "a.txt", "x")
        assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / "a.txt")
        assert os.listdir(tmp_path) == []

    def test_temp_names_carry_the_pid(self, tmp_path):
        with atomic_path(tmp_path / "a.txt") as tmp:
            assert f".{os.getpid()}." in tmp.name and tmp.name.endswith(".tmp")
            tmp.write_text("x")


class TestSweep:
    def test_removes_dead_processes_temporaries(self, tmp_path):
        pid = dead_pid()
        (tmp_path / f".a.npz.{pid}.0123abcd.tmp").write_bytes(b"half")
        (tmp_path / f".staging-{pid}-0123abcd").mkdir()
        (tmp_path / f".staging-{pid}-0123abcd" / "x.png").write_bytes(b"half")
        mine = tmp_path / f".b.npz.{os.getpid()}.0123abcd.tmp"
        mine.write_bytes(b"in progress")
        (tmp_path / "keep.tmp").write_text("not ours")
        (tmp_path / "result.npz").write_text("done")
        removed = sweep(tmp_path)
        assert len(removed) == 2
        assert sorted(os.listdir(tmp_path)) == sorted([mine.name, "keep.tmp", "result.npz"])

    def test_missing_folder(self, tmp_path):
        assert sweep(tmp_path / "nope") == []


class TestStagedOutputs:
    def test_all_or_nothing(self, tmp_path):
        (tmp_path / "results.json").write_text("old")
        with pytest.raises(OSError):
            with staged_outputs(tmp_path, last=["results.json"]) as stage:
                atomic_write(stage / "fig.png", b"png")
                raise OSError(errno.ENOSPC, "No space left on device")
        assert os.listdir(tmp_path) == ["results.json"] and (tmp_path / "results.json").read_text() == "old"

    def test_marker_last(self, tmp_path, monkeypatch):
        order = []
        real = os.replace
        monkeypatch.setattr(atomic.os, "replace", lambda a, b: (order.append(os.path.basename(b)), real(a, b)))
        with staged_outputs(tmp_path, last=["results.json"]) as stage:
            for name in ("results.json", "a.png", "z.md"):
                (stage / name).write_text(name)
        assert order == ["a.png", "z.md", "results.json"]
        assert sorted(os.listdir(tmp_path)) == ["a.png", "results.json", "z.md"]

    def test_failing_run_removes_only_its_own(self, tmp_path):
        """A failing run that created the folder leaves it when another run stages there (it removed the folder
        it had created, the other run's staging with it); an empty folder it created goes."""
        out = tmp_path / "o"
        other = out / f".staging-{os.getpid()}-0123abcd"
        with pytest.raises(RuntimeError):
            with staged_outputs(out) as stage:
                (stage / "mine.txt").write_text("x")
                other.mkdir()
                (other / "theirs.txt").write_text("x")
                raise RuntimeError("killed")
        assert os.listdir(out) == [other.name] and os.listdir(other) == ["theirs.txt"]
        with pytest.raises(RuntimeError):
            with staged_outputs(tmp_path / "p"):
                raise RuntimeError("killed")
        assert not (tmp_path / "p").exists()

    def test_runs_publish_one_at_a_time(self, tmp_path, monkeypatch):
        """Two runs on one folder: the second moves its set in only once the first has moved all of its own, so
        the folder ends with one complete set (the last one's)."""
        import threading

        order, first, release = [], threading.Event(), threading.Event()
        real = os.replace

        def replace(a, b):
            order.append(threading.current_thread().name)
            if not first.is_set():
                first.set()
                release.wait(10)
            real(a, b)

        monkeypatch.setattr(atomic.os, "replace", replace)

        def run():
            with staged_outputs(tmp_path, last=["done.json"]) as stage:
                for n in ("a.txt", "b.txt", "done.json"):
                    (stage / n).write_text(threading.current_thread().name)

        a, b = threading.Thread(target=run, name="A"), threading.Thread(target=run, name="B")
        a.start()
        assert first.wait(10)
        b.start()
        b.join(0.5)
        assert b.is_alive() and order == ["A"]  # B has staged its set and waits to move it in
        release.set()
        a.join(10)
        b.join(10)
        assert order == ["A"] * 3 + ["B"] * 3
        assert {(tmp_path / n).read_text() for n in ("a.txt", "b.txt", "done.json")} == {"B"}

    def test_replaces(self, tmp_path):
        import re

        for n in ("0000_left.exr", "0002_left.exr", "cameras.json", "notes.txt"):
            (tmp_path / n).write_text("old")
        with staged_outputs(tmp_path, last=["cameras.json"], replaces=re.compile(r"^\d{4}_left\.exr$")) as stage:
            for n in ("0000_left.exr", "cameras.json"):
                (stage / n).write_text("new")
        assert sorted(os.listdir(tmp_path)) == ["0000_left.exr", "cameras.json", "notes.txt"]
        assert (tmp_path / "notes.txt").read_text() == "old" and (tmp_path / "0000_left.exr").read_text() == "new"
