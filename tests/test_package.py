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
#: layer). CONTRIBUTING.md (Layout: the layers) shows the same order.
LAYERS = (
    ("foundation", ("errors", "_checks", "_backend", "_version", "_extras", "_tensors", "camera", "_core")),
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
                anchor = base[: len(base) - (node.level - 1)]
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
            "stereorepro.measure.metrics (measure) -> stereorepro (cli)",
        ]

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
            "stereorepro.reproject.functional"
        }
        assert _cycles(graph) == [["stereorepro.reproject._native", "stereorepro.reproject.functional"]]

    def test_native_wrapper_is_a_leaf(self):
        deps = _graph()["stereorepro.reproject._native"]
        assert deps <= {"stereorepro._core"}, deps

    def test_only_one_file_imports_embreex(self):
        """(An import statement or the optional-dependency helper, ``require("embreex...")``.)"""

        def imports_embreex(x) -> bool:
            if isinstance(x, (ast.Import, ast.ImportFrom)):
                return "embreex" in ast.dump(x)
            return (
                isinstance(x, ast.Call)
                and getattr(x.func, "id", None) == "require"
                and bool(x.args)
                and isinstance(x.args[0], ast.Constant)
                and str(x.args[0].value).startswith("embreex")
            )

        users = [
            n
            for n, p in _modules().items()
            if "embreex" in p.read_text() and any(imports_embreex(x) for x in ast.walk(ast.parse(p.read_text())))
        ]
        assert users == ["stereorepro.render._embree"]


class TestLightImport:
    HEAVY = ("embreex", "OpenEXR", "matplotlib", "mitsuba", "trimesh", "onnx", "onnxruntime", "kornia")

    def _loaded(self, code: str) -> list[str]:
        probe = (
            f"import sys\n{code}\nimport json\n"
            f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({list(self.HEAVY)!r}))))"
        )
        res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
        return json.loads(res.stdout.strip().splitlines()[-1])

    def test_import_stereorepro_is_light(self):
        assert self._loaded("import stereorepro") == []

    def test_renderer_loads_on_first_use(self):
        assert "embreex" in self._loaded("from stereorepro import PathTracer")
        assert "OpenEXR" in self._loaded(
            "import stereorepro, numpy as np, tempfile, os\n"
            "stereorepro.write_exr(os.path.join(tempfile.mkdtemp(), 'a.exr'), "
            "{'R': np.zeros((2, 2), np.float32)})"
        )


class TestPublicSurface:
    #: Every name ``stereorepro`` exported before the restructure (4a85799^).
    NAMES = [
        "PinholeCamera",
        "StereoRig",
        "has_surface",
        "intrinsics_from_fov",
        "invert_rigid",
        "look_at",
        "pixel_centers",
        "project",
        "unproject",
        "Reason",
        "StereoReprojection",
        "TemporalReprojection",
        "backward_reproject",
        "reason_to_rgb",
        "stereo_reproject",
        "temporal_blend",
        "temporal_reproject",
        "export_onnx",
        "EFFECTIVE_SPP_FLAGS",
        "EffectiveSppLadder",
        "effective_spp",
        "effective_spp_many",
        "fit_ladder",
        "ladder_rmse",
        "mse",
        "rmse",
        "ssim",
        "suggest_reference_spp",
        "SpatiotemporalReprojection",
        "PathTracer",
        "RenderResult",
        "read_exr",
        "write_exr",
        "list_scenes",
        "load_scene",
        "__version__",
    ]
    #: Sub-packages and the names they export.
    MODULES = {
        "stereorepro.scenes": [
            "Scene",
            "SceneError",
            "SceneGeometry",
            "list_scenes",
            "load_scene",
            "scenes_dir",
            "shared_scenes_dir",
            "KNOWN_EFFECTS",
            "expand_path",
        ],
        "stereorepro.render": ["PathTracer", "RenderResult", "ray_epsilon"],
        "stereorepro.io": [
            "atomic_path",
            "atomic_write",
            "read_exr",
            "write_exr",
            "exr_to_tensors",
            "export_onnx",
            "onnx_input_dims",
        ],
        "stereorepro.measure": ["rmse", "effective_spp_many", "ladder_rmse", "EffectiveSppLadder"],
        "stereorepro.workflows.experiment": [
            "ExperimentConfig",
            "run_experiment",
            "REFERENCE_OFFSET",
            "SCHEMES",
            "RenderCache",
            "tables_markdown",
            "THRESHOLD_ROWS",
        ],
        "stereorepro._checks": ["ShapeError", "check_shape"],
        "stereorepro.cli": ["main", "parse_resolution", "UserError", "build_parser"],
    }
    #: Module paths of an earlier layout: gone (module paths inside the package are not a contract).
    REMOVED = [
        "stereorepro.native",
        "stereorepro.pipeline",
        "stereorepro.reproject_cli",
        "stereorepro.experiment",
        "stereorepro.onnx_export",
        "stereorepro.metrics",
        "stereorepro.synthetic",
        "stereorepro.io.sequence",
        "stereorepro.io.diagnose",
        "stereorepro.measure.experiment",
    ]

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
        from stereorepro.errors import (
            SceneError,
            SequenceError,
            ShapeError,
            StereoreproError,
            UserError,
        )

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


#: Runs in a subprocess with the optional packages in ``BLOCK`` made unimportable (as if not installed).
_BLOCKED = """
import sys
for name in {block!r}:
    sys.modules[name] = None  # import raises ModuleNotFoundError, as for a package that is not installed
{code}
"""


def _run_blocked(block, code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _BLOCKED.format(block=list(block), code=code)],
        capture_output=True,
        text=True,
        check=False,
    )


class TestExtras:
    """Optional dependencies: the core needs torch and numpy only; a missing extra is one error naming it."""

    def test_core_without_optional_packages(self):
        """``import stereorepro``, the ops on torch and the CLI's help and scene list, with every package of
        every extra unimportable; the demo then exits 2 with one line naming ``[experiment]``."""
        from stereorepro._extras import EXTRAS

        code = """
import torch, stereorepro as sr
from stereorepro.cli import main
d = torch.full((1, 1, 6, 8), 2.0); n = torch.zeros(1, 3, 6, 8); n[:, 2] = -1
K = sr.intrinsics_from_fov(60.0, 8, 6); right = torch.eye(4)[None].clone(); right[:, 0, 3] = -0.065
values, valid, reason = sr.StereoReprojection(0.5, 0.1)(torch.rand(1, 3, 6, 8), d, n, K, torch.eye(4)[None],
                                                        d, n, K, right)
assert valid.all(), reason
assert main(["--help"]) == 0 and main(["scenes"]) == 0
sys.exit(10 + main(["demo", "--frames", "1", "--out", "/nonexistent/demo"]))
"""
        res = _run_blocked(EXTRAS, code)
        assert res.returncode == 12, res.stderr
        err = res.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("stereorepro demo: error"), err
        assert "pip install 'stereorepro[experiment]'" in err[0], err

    #: A scene file with a mesh: loading its geometry needs trimesh.
    MESH_SCENE = (
        "import tempfile, os; from stereorepro import load_scene\n"
        "p = os.path.join(tempfile.mkdtemp(), 's.toml')\n"
        "open(p, 'w').write(open(load_scene('living_room').source).read()"
        ".replace('generator = \"living_room\"', 'mesh = \"x.ply\"'))\n"
        "load_scene(p).geometry()"
    )

    @pytest.mark.parametrize(
        "block, code, extra",
        [
            ("embreex", "from stereorepro import PathTracer", "render"),
            ("trimesh", MESH_SCENE, "render"),
            (
                "OpenEXR",
                (
                    "import stereorepro, numpy as np\n"
                    "stereorepro.write_exr('/nonexistent/a.exr', {'R': np.zeros((2, 2), np.float32)})"
                ),
                "exr",
            ),
            (
                "kornia",
                "import torch, stereorepro\nstereorepro.ssim(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16))",
                "experiment",
            ),
            (
                "flip_evaluator",
                (
                    "import torch\nfrom stereorepro.measure.metrics import flip\n"
                    "flip(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16))"
                ),
                "experiment",
            ),
        ],
    )
    def test_missing_extra_is_named(self, block, code, extra):
        res = _run_blocked([block], code)
        last = res.stderr.strip().splitlines()[-1]
        assert last.startswith("stereorepro.errors.MissingDependencyError:"), res.stderr
        assert f"pip install 'stereorepro[{extra}]'" in last, last

    def test_require(self, monkeypatch):
        """The error is an ImportError and a StereoreproError naming the extra; an ImportError from inside an
        installed package (here: its own dependency missing) is not mistaken for the package's absence."""
        from stereorepro import _extras
        from stereorepro.errors import MissingDependencyError, StereoreproError

        monkeypatch.setitem(sys.modules, "kornia", None)
        with pytest.raises(MissingDependencyError) as info:
            _extras.require("kornia", "ssim")
        assert isinstance(info.value, ImportError) and isinstance(info.value, StereoreproError)
        assert info.value.extra == "experiment" and info.value.name == "kornia"
        assert str(info.value).startswith(
            "ssim needs kornia, which is not installed: pip install 'stereorepro[experiment]'"
        )

        def broken(name):
            raise ImportError("libfoo.so: cannot open shared object file", name="libfoo")

        monkeypatch.setattr(_extras.importlib, "import_module", broken)
        with pytest.raises(ImportError) as info:
            _extras.require("embreex", "the path tracer")
        assert not isinstance(info.value, MissingDependencyError)

    def test_extras_match_pyproject(self):
        """Every package of :data:`~stereorepro._extras.EXTRAS` is in the extra it names (directly or through the
        extras that extra includes); the core dependencies are torch and numpy."""
        import re

        import tomllib

        from stereorepro._extras import EXTRAS

        pyproject = PACKAGE.parent / "pyproject.toml"
        if not pyproject.is_file():
            pytest.skip("an installed package without its pyproject.toml")
        project = tomllib.loads(pyproject.read_text())["project"]
        extras = project["optional-dependencies"]

        def names(extra: str) -> set[str]:
            out = set()
            for req in extras[extra]:
                name = re.match(r"[A-Za-z0-9_.-]+(\[[^]]*\])?", req).group(0)
                if name.startswith("stereorepro["):
                    for sub in name[len("stereorepro[") : -1].split(","):
                        out |= names(sub)
                else:
                    out.add(name.lower())
            return out

        wrong = {m: (dist, extra) for m, (dist, extra) in EXTRAS.items() if dist.lower() not in names(extra)}
        assert wrong == {}
        assert sorted(re.match(r"[a-z]+", d).group(0) for d in project["dependencies"]) == ["numpy", "torch"]
        for extra in ("render", "exr", "experiment", "onnx", "mitsuba", "oidn", "distributed", "all", "test", "dev"):
            assert extra in extras, extra
        assert names("experiment") >= names("render") | names("exr")


class TestSceneFiles:
    """The built-in scene files are package data; ``STEREOREPRO_SCENES_DIR`` replaces their folder."""

    def test_builtin_scenes_ship_in_the_package(self, monkeypatch):
        from stereorepro.scenes import list_scenes, scenes_dir

        monkeypatch.delenv("STEREOREPRO_SCENES_DIR", raising=False)
        folder = scenes_dir()
        assert folder == PACKAGE / "scenes" / "builtin"
        assert sorted(p.stem for p in folder.glob("*.toml")) == sorted(list_scenes(True, True))

    def test_scenes_dir_from_the_environment(self, tmp_path, monkeypatch):
        from stereorepro.scenes import SceneError, load_scene, scenes_dir

        monkeypatch.delenv("STEREOREPRO_SCENES_DIR", raising=False)
        (tmp_path / "living_room.toml").write_bytes((scenes_dir() / "living_room.toml").read_bytes())
        monkeypatch.setenv("STEREOREPRO_SCENES_DIR", str(tmp_path))
        assert load_scene("living_room").source == tmp_path.resolve() / "living_room.toml"
        with pytest.raises(SceneError, match="scene file not found"):
            load_scene("atrium")
        monkeypatch.setenv("STEREOREPRO_SCENES_DIR", str(tmp_path / "missing"))
        with pytest.raises(SceneError, match=r"\$STEREOREPRO_SCENES_DIR is .*which is not a folder"):
            load_scene("living_room")

    def test_did_you_mean(self):
        from stereorepro.scenes import SceneError, load_scene

        with pytest.raises(SceneError, match="unknown scene 'livingroom': did you mean 'living_room'\\?"):
            load_scene("livingroom")
        with pytest.raises(SceneError) as info:
            load_scene("qqq")
        assert "did you mean" not in str(info.value)
