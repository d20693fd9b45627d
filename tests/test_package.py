"""The package as a whole: no import cycles, a light top-level import, the public surface and its old names."""

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


def _modules() -> dict[str, Path]:
    """Every module of the package: dotted name -> file."""
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """Package modules that ``name`` imports anywhere in its source (lazy imports inside functions included)."""
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
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        for t in targets:
            while t and t not in modules:  # ``from pkg import name``: the module or its nearest package
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
    #: Module paths of the previous layout and names they held.
    OLD_MODULES = {
        "stereorepro.native": ["available", "select_backend", "native_unsupported", "native_backward_reproject",
                               "native_temporal_reproject", "ENV_VAR", "BACKENDS", "check_backend"],
        "stereorepro.pipeline": ["SpatiotemporalReprojection", "EyeState"],
        "stereorepro.reproject_cli": ["REQUIRED_CHANNELS", "NO_HISTORY", "SequenceError", "EyeCamera",
                                      "FrameSequence", "load_sequence", "read_frame", "reproject_sequence",
                                      "export_sequence", "register"],
        "stereorepro.experiment": ["ExperimentConfig", "run_experiment", "REFERENCE_OFFSET", "register", "SCHEMES",
                                   "RenderCache", "tables_markdown", "THRESHOLD_ROWS"],
        "stereorepro.onnx_export": ["export_onnx", "example_inputs", "onnx_input_dims"],
        "stereorepro.metrics": ["rmse", "effective_spp_many", "ladder_rmse", "EffectiveSppLadder"],
        "stereorepro.scenes": ["Scene", "SceneError", "SceneGeometry", "list_scenes", "load_scene", "scenes_dir",
                               "shared_scenes_dir", "KNOWN_EFFECTS"],
        "stereorepro.render": ["PathTracer", "RenderResult", "ray_epsilon", "read_exr", "write_exr",
                               "exr_to_tensors"],
        "stereorepro._checks": ["ShapeError", "check_shape"],
        "stereorepro.cli": ["main", "parse_resolution", "UserError", "build_parser"],
    }

    def test_old_names_importable(self):
        for name in self.NAMES:
            assert getattr(stereorepro, name) is not None, name

    @pytest.mark.parametrize("module", sorted(OLD_MODULES))
    def test_old_modules_importable(self, module):
        mod = importlib.import_module(module)
        missing = [n for n in self.OLD_MODULES[module] if not hasattr(mod, n)]
        assert missing == []

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
        assert stereorepro.reproject_cli.SequenceError is SequenceError


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
