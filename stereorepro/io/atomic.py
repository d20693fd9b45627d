"""The one atomic write of the package: nothing half-written on disk, ever.

A file is written to a temporary name in its destination folder (``.NAME.PID.XXXXXXXX.tmp``), flushed to disk
(``fsync``), then renamed over the destination (``os.replace``, atomic on POSIX) and the folder entry synced; on
any failure the temporary file is removed and the destination is untouched. Temporary files are created with mode
0666 minus the umask, as ``open()`` would create the destination itself.

A set of files that belong together (a command's outputs) is written into a staging folder beside them
(``.staging-PID-XXXXXXXX``, one per run) and renamed into place only once every file is complete
(:func:`staged_outputs`), the marker file last; runs sharing a folder move their sets in one at a time. A process
killed mid-write leaves only such temporaries; :func:`sweep` removes those of processes that are no longer running
(the commands sweep their output folders and the cache on start).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
from pathlib import Path
from typing import Iterable, Iterator

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

__all__ = ["atomic_path", "atomic_write", "staged_outputs", "sweep", "TMP_SUFFIX", "STAGING_PREFIX"]

#: Suffix of the temporary files (a crash can leave one behind; nothing else ends so in our folders).
TMP_SUFFIX = ".tmp"

#: Prefix of staging folders (:func:`staged_outputs`).
STAGING_PREFIX = ".staging-"

_TMP_RE = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{8}" + re.escape(TMP_SUFFIX) + "$")
_STAGING_RE = re.compile("^" + re.escape(STAGING_PREFIX) + r"(\d+)-[0-9a-f]{8}$")


def _fsync_path(path: Path, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to; on leaving the block without an exception, the file
    is synced and renamed to ``path``; with an exception it is removed.

    Examples:
        >>> import tempfile, pathlib
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> with atomic_path(d / "out.txt") as tmp:
        ...     _ = tmp.write_text("done")
        >>> (d / "out.txt").read_text(), sorted(p.name for p in d.iterdir())
        ('done', ['out.txt'])
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{TMP_SUFFIX}"
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            break
        except FileExistsError:  # pragma: no cover - 2^-32 per attempt
            continue
    try:
        yield tmp
        _fsync_path(tmp)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if e.filename in (None, str(tmp)):  # name the file the caller asked for, not the temporary
            raise type(e)(e.errno, e.strerror or str(e), str(path)) from e
        raise
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    with contextlib.suppress(OSError):  # not every filesystem syncs a folder
        _fsync_path(folder, directory=True)


def atomic_write(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8 encoded) to ``path`` atomically (see :func:`atomic_path`).

    Examples:
        >>> import tempfile, pathlib
        >>> from stereorepro.io.atomic import atomic_write
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     d = pathlib.Path(tmp)
        ...     atomic_write(d / "notes.txt", "hello")
        ...     print((d / "notes.txt").read_text(), sorted(p.name for p in d.iterdir()))
        hello ['notes.txt']
    """
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def sweep(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and staging folders (this module's names only) that processes no longer running
    left in ``folder`` (not recursive); returns what was removed. Temporaries of live processes are left alone,
    so concurrent runs sharing a folder (a render cache) do not disturb each other on one machine. (On a folder
    shared between machines a process id means nothing elsewhere: sweep from one machine only.)

    Examples:
        >>> import tempfile, pathlib
        >>> from stereorepro.io.atomic import sweep
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     d = pathlib.Path(tmp)
        ...     _ = (d / ".frame.exr.999999999.0123abcd.tmp").write_bytes(b"")  # left by a process that is gone
        ...     _ = (d / "frame.exr").write_bytes(b"")
        ...     print([p.name for p in sweep(d)], sorted(p.name for p in d.iterdir()))
        ['.frame.exr.999999999.0123abcd.tmp'] ['frame.exr']
    """
    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    for p in folder.iterdir():
        m = _TMP_RE.match(p.name) or _STAGING_RE.match(p.name)
        if not m or _alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
    return removed


@contextlib.contextmanager
def _publish_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on the folder ``out`` (``flock`` on its descriptor; released when the descriptor
    closes, a killed process included), so that runs move their sets into one folder one after the other. Where
    the filesystem or the platform has no such locks, the block runs unlocked."""
    if fcntl is None:  # pragma: no cover - not POSIX
        yield
        return
    try:
        fd = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        yield
        return
    try:
        with contextlib.suppress(OSError):  # no locks on this filesystem
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _own_staging(out: Path) -> tuple[bool, Path]:
    """Create ``out`` if needed and a staging folder of this run in it; whether this call created ``out``."""
    while True:
        try:
            out.mkdir(parents=True)
            created = True
        except FileExistsError:
            created = False
        sweep(out)
        staging = out / f"{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
        try:
            staging.mkdir()
            return created, staging
        except FileExistsError:  # pragma: no cover - 2^-32 per attempt
            continue
        except FileNotFoundError:  # another run removed the empty folder it had created, just now: again
            continue


@contextlib.contextmanager
def staged_outputs(
    out: str | os.PathLike, last: Iterable[str] = (), replaces: re.Pattern | None = None
) -> Iterator[Path]:
    """Yield a staging folder of this run inside ``out`` to write a set of files into (flat, by their final
    names); on leaving the block without an exception every file is synced and renamed into ``out`` (the names
    in ``last`` after the others, in that order: a marker such as ``results.json`` appears only once the set is
    complete), then the files of ``out`` whose names match ``replaces`` and are not in the set are removed (a set
    that replaces an earlier one as a whole). The temporaries that dead processes left in ``out`` are swept first
    (:func:`sweep`).

    Concurrent runs on one ``out``: each stages in its own folder, and they move their sets in one at a time
    (a lock on ``out``), so ``out`` ends with the complete set of the run that finished last. A failing run
    removes only what it created: its staging folder, and ``out`` itself if it created it and nothing else is in
    it (another run's staging folder or files keep it); ``out`` keeps what it had.

    Examples:
        >>> import tempfile, pathlib
        >>> from stereorepro.io.atomic import staged_outputs
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     out = pathlib.Path(tmp) / "run"
        ...     with staged_outputs(out, last=["results.json"]) as stage:
        ...         _ = (stage / "table.csv").write_text("a,b")
        ...         _ = (stage / "results.json").write_text("{}")
        ...     print(sorted(p.name for p in out.iterdir()))
        ['results.json', 'table.csv']
    """
    out = Path(out)
    created, staging = _own_staging(out)
    try:
        yield staging
        last = list(last)
        names = sorted(p.name for p in staging.iterdir() if p.name not in last)
        names += [n for n in last if (staging / n).exists()]
        for n in names:
            _fsync_path(staging / n)
        with _publish_lock(out):
            for n in names:
                os.replace(staging / n, out / n)
            if replaces is not None:
                for p in out.iterdir():
                    if p.name not in names and replaces.match(p.name) and not p.is_dir():
                        p.unlink()
            with contextlib.suppress(OSError):
                _fsync_path(out, directory=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created:
            with contextlib.suppress(OSError):  # only if empty
                out.rmdir()
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
