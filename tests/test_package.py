"""The package as a whole: the layer order (no import runs up the layers, no cycle), a light top-level import, the
public surface."""

from __future__ import annotations

import ast
import importlib
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import stereorepro

PACKAGE = Path(stereorepro.__file__).resolve().parent

#: The layers of the package, lowest first: a module may import from its own layer and the layers below it,
#: never from one above (lazy imports inside functions included). Entries name the top-level modules or packages
#: under ``stereorepro``; ``""`` is the package's ``__init__`` (the public names, which re-exports from every
#: layer). README's Development section shows the same order.
LAYERS = (
    ("foundation", ("errors", "_checks", "_backend", "_version", "_tensors", "camera", "_core")),
    ("io", ("io",)),  # file formats
    ("scenes", ("scenes",)),
    ("render", ("render",)),
    ("reproject", ("reproject",)),
    ("accumulate", ("accumulate",)),
    ("denoise", ("denoise",)),
    ("measure", ("measure",)),
    ("workflows", ("workflows",)),  # the application layer: sequences in and out, diagnosis, the experiment
    ("cli", ("cli", "__main__", "")),
)
#: Test inputs (:mod:`stereorepro._testing`) sit outside the layers: they may import anything, and only these
#: modules import them: ``export_onnx``'s default example inputs and ``denoiser_example_inputs``.
TESTING = "stereorepro._testing"
TESTING_USERS = {"stereorepro.io.onnx", "stereorepro.denoise"}
#: The compiled core has no .py file but is a module of the package.
NATIVE = "stereorepro._core"


def _modules() -> dict[str, Path]:
    """Every Python module of the package: dotted name -> file."""
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(name: str, path: Path, modules) -> set[str]:
    """Package modules that ``name`` imports anywhere in its source (lazy imports inside functions included).
    ``from pkg import x`` is an import of ``pkg.x`` where that is a module (``modules`` or :data:`NATIVE`), else of
    ``pkg`` (a name its ``__init__`` defines)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                anchor = base[:len(base) - (node.level - 1)]
                mod = ".".join(anchor + ([mod] if mod else []))
            targets = [f"{mod}.{a.name}" for a in node.names]
        for t in targets:
            while t and t not in modules and t != NATIVE:  # the module, or the nearest package defining the name
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), each a list of names."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _graph() -> dict[str, set[str]]:
    """Import edges between modules; a package's ``__init__`` imports of its own submodules are not edges into the
    package (importing ``pkg.sub`` runs ``pkg/__init__`` first, which is not a cycle of the code's layers)."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        deps = _imports(name, path, modules)
        # a submodule naming its package (``from . import x``, ``from ..pkg import y``) depends on what it names,
        # which _imports already resolved to the submodule where there is one
        graph[name] = {d for d in deps if not name.startswith(d + ".")}
    return graph


def _layer(module: str) -> int | None:
    """Index in :data:`LAYERS` of a package module (None: not in any layer)."""
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else ""
    return next((i for i, (_, tops) in enumerate(LAYERS) if top in tops), None)


def _edges() -> dict[str, set[str]]:
    """Every import of every package module (lazy ones included), the package ``__init__`` as ``stereorepro``."""
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _upward(edges: dict[str, set[str]]) -> list[str]:
    """The imports that break the layer order, as ``"importer (layer) -> imported (layer)"``."""
    bad = []
    for name, deps in sorted(edges.items()):
        for dep in sorted(deps):
            if TESTING in (name, dep):
                if dep == TESTING and name not in TESTING_USERS:
                    bad.append(f"{name} -> {dep} (only {sorted(TESTING_USERS)} import the test inputs)")
                continue
            lo, hi = _layer(name), _layer(dep)
            if hi is not None and lo is not None and hi > lo:
                bad.append(f"{name} ({LAYERS[lo][0]}) -> {dep} ({LAYERS[hi][0]})")
    return bad


class TestLayers:
    def test_every_module_has_a_layer(self):
        names = set(_modules()) - {TESTING}
        assert sorted(n for n in names if _layer(n) is None) == []

    def test_no_import_runs_up_the_layers(self):
        assert _upward(_edges()) == []

    def test_detects_an_upward_import(self):
        """The check itself fails on an upward import (here: a file format importing the tracer, as the sequence
        export did when it lived in io/), on an import of the package ``__init__`` from inside (what reading
        ``__version__`` from it was) and on a new importer of the test inputs."""
        edges = _edges()
        edges["stereorepro.io.frames"] = edges["stereorepro.io.frames"] | {"stereorepro.render.tracer"}
        edges["stereorepro.measure.metrics"] = edges["stereorepro.measure.metrics"] | {"stereorepro"}
        edges["stereorepro.accumulate"] = edges["stereorepro.accumulate"] | {TESTING}
        assert _upward(edges) == [
            "stereorepro.accumulate -> stereorepro._testing (only ['stereorepro.denoise', 'stereorepro.io.onnx'] "
            "import the test inputs)",
            "stereorepro.io.frames (io) -> stereorepro.render.tracer (render)",
            "stereorepro.measure.metrics (measure) -> stereorepro (cli)"]

    def test_relative_imports_resolve(self):
        """``from .. import _backend`` is an import of the module, ``from .. import _core`` of the compiled core."""
        edges = _edges()
        assert "stereorepro._backend" in edges["stereorepro.reproject.functional"]
        assert NATIVE in edges["stereorepro.reproject._native"]
        assert "stereorepro" not in edges["stereorepro.reproject._native"]

    def test_version_without_the_package(self):
        """The version has one home, which imports nothing; the installed metadata agrees with it."""
        from importlib.metadata import version

        from stereorepro._version import __version__

        assert _edges()["stereorepro._version"] == set()
        assert stereorepro.__version__ == __version__ == version("stereorepro")


class TestImportGraph:
    def test_no_cycles(self):
        assert _cycles(_graph()) == []

    def test_detects_a_cycle(self):
        """The check itself fails on a graph with a cycle (here: the one the native wrapper used to close)."""
        graph = _graph()
        graph["stereorepro.reproject._native"] = graph["stereorepro.reproject._native"] | {
            "stereorepro.reproject.functional"}
        assert _cycles(graph) == [["stereorepro.reproject._native", "stereorepro.reproject.functional"]]

    def test_native_wrapper_is_a_leaf(self):
        deps = _graph()["stereorepro.reproject._native"]
        assert deps <= {"stereorepro._core"}, deps

    def test_only_one_file_imports_embreex(self):
        users = [n for n, p in _modules().items() if "embreex" in p.read_text() and "import" in p.read_text()
                 and any(isinstance(x, (ast.Import, ast.ImportFrom)) and "embreex" in ast.dump(x)
                         for x in ast.walk(ast.parse(p.read_text())))]
        assert users == ["stereorepro.render._embree"]


class TestLightImport:
    HEAVY = ("embreex", "OpenEXR", "matplotlib", "mitsuba", "trimesh", "onnx", "onnxruntime", "kornia")

    def _loaded(self, code: str) -> list[str]:
        probe = (f"import sys\n{code}\nimport json\n"
                 f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({list(self.HEAVY)!r}))))")
        res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
        return json.loads(res.stdout.strip().splitlines()[-1])

    def test_import_stereorepro_is_light(self):
        assert self._loaded("import stereorepro") == []

    def test_renderer_loads_on_first_use(self):
        assert "embreex" in self._loaded("from stereorepro import PathTracer")
        assert "OpenEXR" in self._loaded("import stereorepro, numpy as np, tempfile, os\n"
                                         "stereorepro.write_exr(os.path.join(tempfile.mkdtemp(), 'a.exr'), "
                                         "{'R': np.zeros((2, 2), np.float32)})")


class TestPublicSurface:
    #: Every name ``stereorepro`` exported before the restructure (4a85799^).
    NAMES = ["PinholeCamera", "StereoRig", "has_surface", "intrinsics_from_fov", "invert_rigid", "look_at",
             "pixel_centers", "project", "unproject", "Reason", "StereoReprojection", "TemporalReprojection",
             "backward_reproject", "reason_to_rgb", "stereo_reproject", "temporal_blend", "temporal_reproject",
             "export_onnx", "EFFECTIVE_SPP_FLAGS", "EffectiveSppLadder", "effective_spp", "effective_spp_many",
             "fit_ladder", "ladder_rmse", "mse", "rmse", "ssim", "suggest_reference_spp",
             "SpatiotemporalReprojection", "PathTracer", "RenderResult", "read_exr", "write_exr", "list_scenes",
             "load_scene", "__version__"]
    #: Sub-packages and the names they export.
    MODULES = {
        "stereorepro.scenes": ["Scene", "SceneError", "SceneGeometry", "list_scenes", "load_scene", "scenes_dir",
                               "shared_scenes_dir", "KNOWN_EFFECTS", "expand_path"],
        "stereorepro.render": ["PathTracer", "RenderResult", "ray_epsilon"],
        "stereorepro.io": ["atomic_path", "atomic_write", "read_exr", "write_exr", "exr_to_tensors", "export_onnx",
                           "onnx_input_dims"],
        "stereorepro.measure": ["rmse", "effective_spp_many", "ladder_rmse", "EffectiveSppLadder"],
        "stereorepro.workflows.experiment": ["ExperimentConfig", "run_experiment", "REFERENCE_OFFSET", "SCHEMES",
                                             "RenderCache", "tables_markdown", "THRESHOLD_ROWS"],
        "stereorepro._checks": ["ShapeError", "check_shape"],
        "stereorepro.cli": ["main", "parse_resolution", "UserError", "build_parser"],
    }
    #: Module paths of an earlier layout: gone (module paths inside the package are not a contract).
    REMOVED = ["stereorepro.native", "stereorepro.pipeline", "stereorepro.reproject_cli", "stereorepro.experiment",
               "stereorepro.onnx_export", "stereorepro.metrics", "stereorepro.synthetic", "stereorepro.io.sequence",
               "stereorepro.io.diagnose", "stereorepro.measure.experiment"]

    def test_old_names_importable(self):
        for name in self.NAMES:
            assert getattr(stereorepro, name) is not None, name

    @pytest.mark.parametrize("module", sorted(MODULES))
    def test_modules_export(self, module):
        mod = importlib.import_module(module)
        missing = [n for n in self.MODULES[module] if not hasattr(mod, n)]
        assert missing == []

    def test_removed_modules(self):
        """(By file: an editable install's import map can still list a removed module.)"""
        assert sorted(set(self.REMOVED) & set(_modules())) == []

    def test_all_is_complete_and_resolves(self):
        public = {n for n in dir(stereorepro) if not n.startswith("_")}
        modules = {n for n in public if type(getattr(stereorepro, n)).__name__ == "module"}
        assert set(stereorepro.__all__) == public - modules
        for n in stereorepro.__all__:
            getattr(stereorepro, n)

    def test_one_error_base(self):
        from stereorepro.errors import SceneError, SequenceError, ShapeError, StereoreproError, UserError

        for e in (SceneError, SequenceError, ShapeError, UserError):
            assert issubclass(e, StereoreproError)
        for e in (SceneError, SequenceError, ShapeError):
            assert issubclass(e, ValueError)  # code written against ValueError keeps working
        assert stereorepro.scenes.SceneError is SceneError
        from stereorepro.io import frames

        assert frames.SequenceError is SequenceError


def test_every_module_imports():
    for info in pkgutil.walk_packages(stereorepro.__path__, "stereorepro."):
        if info.name != "stereorepro.__main__":
            importlib.import_module(info.name)


def _modules_with_examples() -> list[str]:
    return [n for n, p in _modules().items() if ">>>" in p.read_text()]


def test_examples_exist():
    assert "stereorepro.reproject.functional" in _modules_with_examples()


@pytest.mark.parametrize("module", _modules_with_examples())
def test_doctests(module):
    """Every ``Example:`` block (``>>>``) of the package runs and prints what it shows."""
    import doctest

    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0, result


def test_test_module_basenames_are_unique():
    """pytest imports test modules by basename (no __init__.py): two test_x.py in different folders collide."""
    from collections import Counter
    from pathlib import Path

    names = Counter(p.name for p in Path(__file__).resolve().parent.rglob("test_*.py"))
    assert not [n for n, c in names.items() if c > 1]
