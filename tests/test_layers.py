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
"""
import ast
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
