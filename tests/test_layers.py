"""Layers point one way: an AST scan of every module of the project's packages.

The layer table (``ALLOWED``: package -> the project packages it may import):

    streaklab        the CLI, benchmarks and report: may import everything below
    decomposition    the solver and the chunked pipeline; may read cube stores (reconstruction)
    reconstruction   run stores to cubes; may read run stores (acquisition)
    acquisition      capture sessions over the drivers
    drivers          real and simulated devices
    core             forward model, durable and staged writes, provenance, the data-layer
                     error base: imports nothing of ours

``reconstruction -> acquisition`` and ``decomposition -> reconstruction`` are the two edges
inside the middle layer: reconstruction reads the run store that acquisition writes, and the
pipeline reads the cube store that reconstruction writes.  Nothing points back, so the table
itself is acyclic; the scan fails on any import the table does not allow (function-level
imports and literal ``importlib.import_module`` calls included) and on any cycle among the
packages.

Inside ``decomposition`` a second table (``DECOMPOSITION``: unit -> the units it may import) orders
its subpackages and top-level modules the same way, bottom up::

    constants, flags, masks, options    what every layer shares
    kernels      the compiled kernels
    noise        noise estimates and deviances, the noise="auto" rule (its own compiled kernels use kernels.jit)
    model        slot states, components, refines, fidelity
    methods      ConvSCD and the GradBM baseline
    stages       the stages decompose() runs
    response     the measured-response path (reuses the stages' rules)
    api          decompose() itself; __init__ re-exports it, warmup runs it (and decompose_image) once
                 before timing
    image        decompose_image(): what the pixels of one image share (shared, spatial)
    store        the chunked store pipeline above the solver: the only unit that reads cube
                 stores (reconstruction)
    evaluation   synthetic scenes, reference fits, metrics: no unit of the solver imports it
    phasor       phasor coordinates of binned decays: NumPy alone, no unit of the solver

The module graph of ``decomposition`` (function-level imports included) must be acyclic, and
imports of ``decomposition`` modules inside functions are kept to the lazy loads of ``store``
and the package's ``__init__``: elsewhere a function-level import that only hides a cycle
would hide a wrong dependency direction.
"""
import ast
import os
import subprocess
import sys
import tomllib
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]

ALLOWED = {
    "core": set(),
    "drivers": {"core"},
    "acquisition": {"drivers", "core"},
    "reconstruction": {"acquisition", "drivers", "core"},
    "decomposition": {"reconstruction", "drivers", "core"},
    "streaklab": {"acquisition", "reconstruction", "decomposition", "drivers", "core"},
}

#: decomposition's units (a subpackage, or a top-level module; "__init__" the package itself)
#: -> the units they may import
_SHARED = {"constants", "flags", "masks", "options"}
DECOMPOSITION = {
    "constants": set(),
    "flags": set(),
    "masks": set(),
    "options": set(),
    "kernels": {"constants", "masks"},
    "noise": {"constants", "kernels", "options"},
    "model": {"constants", "masks", "kernels"},
    "methods": _SHARED | {"kernels", "model"},
    "stages": _SHARED | {"kernels", "noise", "model", "methods"},
    "response": _SHARED | {"kernels", "noise", "model", "methods", "stages"},
    "api": _SHARED | {"model", "methods", "stages", "response"},
    "__init__": {"flags", "api", "image"},
    "warmup": {"api", "image", "kernels"},
    "image": _SHARED | {"api", "stages", "model", "noise", "kernels", "methods", "response"},
    "store": _SHARED | {"__init__", "api", "image", "methods", "noise", "response", "warmup"},
    "evaluation": {"constants", "noise", "model"},
    "phasor": set(),
}
#: the project packages (besides core) a unit of decomposition may import
DECOMPOSITION_OUTSIDE = {"store": {"reconstruction"}}
#: units whose functions may import decomposition modules (lazy loads: the API on first use,
#: the pipeline's parts when a run needs them)
LAZY_UNITS = {"__init__", "store"}


def project_packages() -> list[str]:
    """The top-level packages pyproject.toml installs."""
    with open(ROOT / "pyproject.toml", "rb") as f:
        include = tomllib.load(f)["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted({pattern.rstrip("*").rstrip(".") for pattern in include})


def imported_modules(source: str, module: str, *, is_package: bool = False) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, at any depth of the tree."""
    package = module if is_package else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1])
                name = f"{base}.{node.module}" if node.module else base
            else:
                name = node.module
            found.append((node.lineno, name))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == "import_module" and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append((node.lineno, node.args[0].value))
    return found


def package_imports(root: Path, packages) -> dict[str, dict[str, list[str]]]:
    """package -> {imported project package -> ["path:line", ...]} over every module under ``root``."""
    packages = set(packages)
    edges: dict[str, dict[str, list[str]]] = {p: {} for p in packages}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            is_package = path.name == "__init__.py"
            parts = rel.with_suffix("").parts
            module = ".".join(parts[:-1] if is_package else parts)
            for line, name in imported_modules(path.read_text(encoding="utf-8"), module, is_package=is_package):
                top = name.split(".")[0]
                if top in packages and top != pkg:
                    edges[pkg].setdefault(top, []).append(f"{rel}:{line}")
    return edges


def violations(edges, allowed) -> list[str]:
    """Imports the layer table does not allow, one line each."""
    out = []
    for pkg, targets in sorted(edges.items()):
        for target, where in sorted(targets.items()):
            if target not in allowed.get(pkg, set()):
                out.append(f"{pkg} -> {target} (not allowed by the layer table): {', '.join(where)}")
    return out


def find_cycle(graph) -> list[str] | None:
    """A cycle in ``graph`` (node -> iterable of nodes) as [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1 = on the current path, 2 = finished
    path: list[str] = []

    def visit(node):
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def module_imports(root: Path, package: str):
    """{module: [(line, imported module or package, inside a function)]} for every module of
    ``package`` under ``root``; ``from pkg import name`` counts as an import of ``pkg.name`` where
    that is a module of the package."""
    files = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        is_package = path.name == "__init__.py"
        files[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    out = {}
    for module, (path, is_package) in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        in_function = {id(n) for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
                       for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))}
        found = []
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = imported_modules(ast.unparse(node), module, is_package=is_package)[0][1]
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            found += [(node.lineno, name, id(node) in in_function) for name in names]
        out[module] = found
    return out


def unit_of(module: str) -> str:
    """The unit of a decomposition module: its subpackage, or itself at the top level."""
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def module_graph(imports, package: str):
    """module -> the modules of ``package`` it imports (function-level imports included)."""
    return {m: {name for _, name, _ in found if name in imports and name != m} for m, found in imports.items()}


# ---------------------------------------------------------------------------------------------
# the project
# ---------------------------------------------------------------------------------------------
def test_every_package_has_a_layer():
    packages = project_packages()
    assert set(packages) == set(ALLOWED), "add the package to the layer table (and the module docstring)"
    for pkg in packages:
        assert (ROOT / pkg / "__init__.py").is_file(), pkg


def test_the_layer_table_is_acyclic():
    assert find_cycle(ALLOWED) is None


def test_no_import_points_up_a_layer():
    edges = package_imports(ROOT, project_packages())
    assert violations(edges, ALLOWED) == []


def test_no_cycle_among_packages():
    edges = package_imports(ROOT, project_packages())
    assert find_cycle({pkg: set(targets) for pkg, targets in edges.items()}) is None


def test_the_scan_sees_the_known_edges():
    """The scan finds real imports (module-level, function-level, relative), so an empty list
    of violations means something."""
    edges = package_imports(ROOT, project_packages())
    assert "core" in edges["drivers"]            # drivers/sim/scene.py renders the forward model
    assert "acquisition" in edges["reconstruction"]  # reconstruction/build.py reads run stores
    assert "reconstruction" in edges["decomposition"]  # the pipeline opens cube stores (function level)
    assert "decomposition" in edges["streaklab"]
    assert edges["core"] == {}


#: the optional extras: the folder that alone may import them -> the third-party packages only
#: that extra installs (the core install needs none of them)
EXTRAS = {
    ("streaklab", "napari"): {"napari", "npe2", "qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6", "magicgui", "pint",
                              "phasorpy", "superqt", "vispy"},
    ("streaklab", "bluesky"): {"bluesky", "ophyd_async", "event_model"},
}


def extra_imports(root: Path, packages) -> list[str]:
    """"path:line imports name" for every import of an extra's package outside the extra's folder."""
    bad = []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            is_package = path.name == "__init__.py"
            parts = rel.with_suffix("").parts
            module = ".".join(parts[:-1] if is_package else parts)
            for line, name in imported_modules(path.read_text(encoding="utf-8"), module, is_package=is_package):
                top = (name or "").split(".")[0]
                if any(top in names and rel.parts[:len(home)] != home for home, names in EXTRAS.items()):
                    bad.append(f"{rel}:{line} imports {name}")
    return bad


def test_only_each_extra_imports_its_packages(tmp_path):
    assert extra_imports(ROOT, project_packages()) == []
    root = _tree(tmp_path, {"decomposition/__init__.py": "", "decomposition/p.py": "def f():\n    import phasorpy.phasor\n",
                            "streaklab/napari/w.py": "import napari\nfrom qtpy import QtWidgets\nimport bluesky\n",
                            "streaklab/bluesky/d.py": "from ophyd_async.core import Device\nimport npe2\n",
                            "streaklab/commands/x.py": "import event_model\n"})
    assert extra_imports(root, ["decomposition", "streaklab"]) == [
        "decomposition/p.py:2 imports phasorpy.phasor", "streaklab/bluesky/d.py:2 imports npe2",
        "streaklab/commands/x.py:1 imports event_model", "streaklab/napari/w.py:3 imports bluesky"]


def test_every_decomposition_module_has_a_unit():
    units = {unit_of(m) for m in module_imports(ROOT, "decomposition")}
    assert units == set(DECOMPOSITION), "add the unit to DECOMPOSITION (and the module docstring)"


def test_the_decomposition_table_is_acyclic():
    assert find_cycle(DECOMPOSITION) is None


#: the longest module without a comment that says why it is one module
MODULE_LINES = 600
#: the most modules one folder of decomposition holds (its __init__ not counted)
FOLDER_MODULES = 15
LONG_MODULE_NOTE = "# One module over 600 lines on purpose:"


def test_decomposition_folders_stay_small_and_long_modules_say_why():
    """A newcomer finds a thing by the folder names: no folder of ``decomposition`` holds more than
    FOLDER_MODULES modules, and a module over MODULE_LINES lines carries a comment that says why
    it is one module."""
    folders, long_modules = {}, []
    for path in sorted((ROOT / "decomposition").rglob("*.py")):
        if path.name != "__init__.py":
            folders.setdefault(path.parent.relative_to(ROOT), []).append(path.name)
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MODULE_LINES and LONG_MODULE_NOTE not in text:
            long_modules.append(str(path.relative_to(ROOT)))
    crowded = {str(k): len(v) for k, v in folders.items() if len(v) > FOLDER_MODULES}
    assert not crowded, f"folders over {FOLDER_MODULES} modules: {crowded}"
    assert not long_modules, f"modules over {MODULE_LINES} lines without {LONG_MODULE_NOTE!r}: {long_modules}"


def test_no_decomposition_import_outside_its_table():
    bad = []
    for module, found in module_imports(ROOT, "decomposition").items():
        unit = unit_of(module)
        for line, name, _ in found:
            top = name.split(".")[0]
            if top == "decomposition":
                target = unit_of(name)
                if target != unit and target not in DECOMPOSITION[unit]:
                    bad.append(f"{module}:{line} imports {name} ({unit} -> {target})")
            elif top in ALLOWED and top != "core" and top not in DECOMPOSITION_OUTSIDE.get(unit, set()):
                bad.append(f"{module}:{line} imports {name} ({unit} -> {top})")
    assert bad == []


def test_no_cycle_among_decomposition_modules():
    """Function-level imports count: one that closes a cycle hides a wrong dependency direction."""
    assert find_cycle(module_graph(module_imports(ROOT, "decomposition"), "decomposition")) is None


def test_function_level_imports_of_decomposition_are_lazy_loads_only():
    found = [(module, line, name) for module, imports in module_imports(ROOT, "decomposition").items()
             for line, name, inside in imports if inside and name.split(".")[0] == "decomposition"]
    assert found  # the scan sees them (the store's lazy loads)
    assert [f for f in found if unit_of(f[0]) not in LAZY_UNITS] == []


def test_the_scan_sees_the_known_decomposition_edges():
    imports = module_imports(ROOT, "decomposition")
    graph = module_graph(imports, "decomposition")
    assert "decomposition.stages.grow" in graph["decomposition.stages.search"]
    assert "decomposition.methods.convscd" in graph["decomposition.stages.detect"]  # from ..methods import convscd
    assert "decomposition.kernels.jit" in graph["decomposition.noise"]
    assert any(name.startswith("reconstruction") and inside
               for _, name, inside in imports["decomposition.store.pipeline"])


def test_the_kernels_load_and_run_without_the_solver_above_them():
    """The compiled kernels import nothing above them: a process that imports every kernel module
    and runs a kernel holds no stage, API or evaluation module."""
    code = ("import sys\n"
            "import decomposition.kernels.atomlm, decomposition.kernels.derivatives, decomposition.kernels.onsets\n"
            "import decomposition.kernels.pick, decomposition.kernels.pickcorr\n"
            "from decomposition.kernels import jit\n"
            "assert abs(jit.erfcx(0.5) - 0.6156903441929259) < 1e-14\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('decomposition'))))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    loaded = set(out.stdout.split())
    assert "decomposition.kernels.atomlm" in loaded
    assert {unit_of(m) for m in loaded} <= {"__init__", "kernels", "constants", "flags", "masks"}, loaded


# ---------------------------------------------------------------------------------------------
# the checker itself, on a synthetic tree
# ---------------------------------------------------------------------------------------------
def _tree(tmp_path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_checker_fails_on_an_upward_import(tmp_path):
    root = _tree(tmp_path, {
        "core/__init__.py": "",
        "core/model.py": "import numpy\n",
        "drivers/__init__.py": "",
        "drivers/sim/__init__.py": "",
        "drivers/sim/scene.py": "from core.model import x\n\ndef f():\n    from decomposition.api import decompose\n",
        "decomposition/__init__.py": "from .api import decompose\n",
        "decomposition/api.py": "from core import model\n",
    })
    edges = package_imports(root, ["core", "drivers", "decomposition"])
    bad = violations(edges, ALLOWED)
    assert len(bad) == 1
    assert bad[0].startswith("drivers -> decomposition")
    assert "drivers/sim/scene.py:4" in bad[0]  # found inside a function, with its line


def test_checker_resolves_relative_and_dynamic_imports():
    assert imported_modules("from ..x import y\n", "a.b.c") == [(1, "a.x")]
    assert imported_modules("from . import y\n", "a.b", is_package=True) == [(1, "a.b")]
    assert imported_modules("from .m import y\n", "a.b", is_package=True) == [(1, "a.b.m")]
    assert imported_modules("import importlib\nimportlib.import_module('streaklab.cli')\n", "a.b") == [
        (1, "importlib"), (2, "streaklab.cli")]


def test_checker_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    bad = dict(ALLOWED, core={"decomposition"})
    assert find_cycle(bad) is not None


def test_checker_finds_a_cycle_closed_inside_a_function(tmp_path):
    root = _tree(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/grow.py": "from .search import objective\n",
        "pkg/search.py": "def block():\n    from .grow import grow_block\n",
        "pkg/stages/__init__.py": "",
        "pkg/stages/label.py": "from .. import grow as g\n",
    })
    imports = module_imports(root, "pkg")
    assert (2, "pkg.grow", True) in imports["pkg.search"]
    assert (1, "pkg.grow", False) in imports["pkg.stages.label"]  # from .. import module
    graph = module_graph(imports, "pkg")
    assert find_cycle(graph) in (["pkg.grow", "pkg.search", "pkg.grow"], ["pkg.search", "pkg.grow", "pkg.search"])
    (root / "pkg/search.py").write_text("def block():\n    return 0\n")
    assert find_cycle(module_graph(module_imports(root, "pkg"), "pkg")) is None

