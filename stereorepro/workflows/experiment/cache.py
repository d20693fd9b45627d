"""The content-addressed render cache of the experiment: npz files keyed by a hash of what determines a render
(scene file, mesh files, frame, eye, sample range, resolution, seed, renderer source), written atomically, so a
killed run resumes and a cached run reproduces the same tables."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ..._version import __version__
from ...io.atomic import atomic_path, sweep

__all__ = ["RenderCache", "code_version", "scene_fingerprint"]


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def code_version() -> str:
    """Hash of the renderer's sources (Python, and the native shading stages when their sources are present):
    renders are recomputed when the renderer changes.

    Examples:
        >>> from stereorepro.workflows.experiment.cache import code_version
        >>> v = code_version()
        >>> len(v), v == code_version()
        (16, True)
    """
    root = Path(__file__).resolve().parents[2]  # the package
    h = hashlib.sha256(__version__.encode())
    cpp = root.parent / "cpp_ext" / "src"
    native = sorted(cpp.glob("*tracer*")) if cpp.is_dir() else []
    for p in sorted(list((root / "render").glob("*.py")) + list((root / "scenes").glob("*.py"))) + native:
        h.update(p.read_bytes())
    try:
        from ... import _core

        # what the build is, not how many threads this process may use (Dask workers run with OMP_NUM_THREADS=1;
        # renders do not depend on the thread count)
        h.update(repr(sorted((k, v) for k, v in _core.build_info().items() if k != "max_threads")).encode())
    except ImportError:
        h.update(b"no-core")
    return h.hexdigest()[:16]


def scene_fingerprint(scene) -> str:
    """Hash of the scene's resolved description and of every file it references (path, size, mtime).

    Examples:
        >>> from types import SimpleNamespace
        >>> from stereorepro.workflows.experiment.cache import scene_fingerprint
        >>> a = SimpleNamespace(name="box", spec={"camera": {"fov": 60}}, source=None)
        >>> b = SimpleNamespace(name="box", spec={"camera": {"fov": 45}}, source=None)
        >>> fa, fb = scene_fingerprint(a), scene_fingerprint(b)
        >>> len(fa), fa == scene_fingerprint(a), fa == fb
        (16, True, False)
    """
    h = hashlib.sha256(str(getattr(scene, "name", "")).encode())
    data = getattr(scene, "spec", None)
    h.update(json.dumps(data, sort_keys=True, default=str).encode())
    src = getattr(scene, "source", None)
    if src and Path(src).is_file():
        h.update(Path(src).read_bytes())

    from ...scenes import expand_path

    base = Path(src).parent if src else Path.cwd()

    def files(x):
        if isinstance(x, dict):
            for v in x.values():
                yield from files(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                yield from files(v)
        elif isinstance(x, (str, Path)) and str(x).lower().endswith((".ply", ".obj", ".glb", ".gltf", ".json")):
            f = expand_path(str(x), base)
            yield f
            if f.suffix.lower() == ".ply":
                yield f.with_suffix(".json")  # the default material sidecar

    for f in files(data):
        if f.is_file():
            st = f.stat()
            h.update(f"{f}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


class RenderCache:
    """npz files keyed by a hash of what determines a render; atomic writes.

    On start the temporaries that killed runs left behind are swept (:func:`~stereorepro.io.atomic.sweep`; Dask
    workers open the cache with ``sweep_on_start=False``: only the client sweeps, as process ids mean nothing on
    another machine). Two processes making one entry at once both write a complete temporary and rename it over
    the same name: one valid entry remains (atomic rename). An
    entry that cannot be read back (zero bytes, truncated, corrupt, missing its metadata) is recomputed and
    rewritten; ``corrupt`` lists those entries' file names and ``log`` (when given) reports each one.

    Examples:
        >>> import tempfile
        >>> import numpy as np
        >>> from stereorepro.workflows.experiment.cache import RenderCache
        >>> with tempfile.TemporaryDirectory() as d:
        ...     cache = RenderCache(d)
        ...     make = lambda: ({"rgb": np.ones((2, 3), np.float32)}, {"spp": 1})
        ...     data, meta = cache.get_or_make({"frame": 0, "eye": "left"}, make)
        ...     data, meta = cache.get_or_make({"frame": 0, "eye": "left"}, make)
        ...     print(data["rgb"].shape, meta["spp"], cache.hits, cache.misses)
        (2, 3) 1 1 1
    """

    def __init__(self, root: Path, force: bool = False, log=None, sweep_on_start: bool = True):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.swept = sweep(self.root) if sweep_on_start else []
        self.force = force
        self.log = log
        self.hits = 0
        self.misses = 0
        self.corrupt: list[str] = []
        self._made: set[Path] = set()

    def path(self, key: dict) -> Path:
        """The entry's file (it may not exist yet)."""
        return self._path(key)

    def _path(self, key: dict) -> Path:
        return self.root / (_sha(json.dumps(key, sort_keys=True).encode())[:32] + ".npz")

    @staticmethod
    def _read(path: Path):
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(str(data.pop("__meta__")))
        if not isinstance(meta, dict):
            raise ValueError("metadata is not an object")
        return data, meta

    def get_or_make(self, key: dict, make):
        path = self._path(key)
        if path.exists() and not (self.force and path not in self._made):  # force: each entry once per cache
            try:
                data, meta = self._read(path)
                self.hits += 1
                return data, meta
            except Exception as e:  # noqa: BLE001 - any unreadable entry (EOFError, BadZipFile, ...) is recomputed
                self.corrupt.append(path.name)
                if self.log:
                    self.log(f"cache: {path} is unreadable ({type(e).__name__}: {e}); recomputing it")
        data, meta = make()
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, __meta__=np.array(json.dumps(meta)), **data)
        self.misses += 1
        self._made.add(path)
        return data, meta
