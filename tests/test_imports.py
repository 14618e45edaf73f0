"""perscli's modules import one another without a circle, and the layers import one way.

The graph is built from the sources with ``ast``: every import, at the top of a
module or inside a function (the ones deferred to keep ``--help`` fast are real
edges too), with relative imports resolved against the importing module's
package.  ``from package import name`` is an edge to ``package.name`` when that
is a module, else to the package itself.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "perscli"


def _modules() -> dict:
    """{dotted module name: path} of every module of perscli (a package is its __init__.py)."""
    out = {}
    for path in SRC.rglob("*.py"):
        parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def import_statements(path: Path, package: list):
    """Each import of a file, anywhere in it: (resolved base, [names]) for ``from base import names``,
    (None, [modules]) for ``import modules``; relative imports resolved against ``package``."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
            yield base, [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            yield None, [alias.name for alias in node.names]


def _imports(name: str, path: Path, modules: dict) -> set:
    """The perscli modules that module ``name`` imports, anywhere in it."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for base, names in import_statements(path, package):
        for alias in names:
            if base is not None:
                if f"{base}.{alias}" in modules:
                    found.add(f"{base}.{alias}")
                elif base in modules:
                    found.add(base)
                continue
            target = alias
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target:
                found.add(target)
    found.discard(name)
    return found


def import_graph() -> dict:
    """{module: set of the perscli modules it imports}."""
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict) -> list:
    """One import circle of ``graph`` as [a, b, ..., a], or [] when there is none (depth-first search)."""
    state = {}                       # 1: on the current path, 2: finished
    path = []

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
        return []

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return []


def test_the_graph_sees_every_kind_of_import():
    graph = import_graph()
    assert len(graph) > 50
    # a relative import at the top, one inside a function, and `from package import module`
    assert "perscli.detector.settings" in graph["perscli.detector.effects"]
    assert "perscli.io.checksum" in graph["perscli.executor"]          # inside functions only (# lazy:)
    assert "perscli.cli.main" in graph["perscli.__main__"]


def test_find_cycle_reports_the_circle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


def test_no_import_circle():
    cycle = find_cycle(import_graph())
    assert not cycle, "import circle: " + " -> ".join(cycle)


def test_one_function_per_name():
    """No two library modules define a public function or class of the same name (a reader who meets
    ``roman_psf`` knows which one it is); the commands in perscli.cli bear their command's name."""
    homes = {}
    for name, path in _modules().items():
        if name.startswith("perscli.cli"):
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_"):
                homes.setdefault(node.name, []).append(name)
    shared = {key: where for key, where in homes.items() if len(where) > 1}
    assert not shared, f"one name, several functions: {shared}"


def _defined(path: Path) -> set:
    """The names a module defines at its top level (functions, classes, assignments), not those it imports."""
    names = set()

    def visit(body):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, ast.Assign):
                names.update(n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name))
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
                names.add(node.target.id)
            elif isinstance(node, (ast.If, ast.Try)):
                visit(node.body)
                visit(node.orelse)
                for handler in getattr(node, "handlers", ()):
                    visit(handler.body)
    visit(ast.parse(path.read_text()).body)
    return names


def test_every_import_names_the_module_that_defines_the_name():
    """``from perscli.X import name`` (in the package, its tests and benchmarks) finds ``name`` defined in X:
    no module passes on another's names, so each name has one import path."""
    modules = _modules()
    defined = {name: _defined(path) for name, path in modules.items()}
    root = SRC.parents[1]
    files = [*SRC.rglob("*.py"), *(root / "tests").rglob("*.py"), *(root / "benchmarks").rglob("*.py")]
    wrong = []
    for path in files:
        name = ".".join(path.relative_to(SRC.parent).with_suffix("").parts) if path.is_relative_to(SRC) else ""
        package = name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
            if base not in modules:
                continue
            for alias in node.names:
                if alias.name in defined[base] or f"{base}.{alias.name}" in modules or alias.name == "_kernels":
                    continue
                wrong.append(f"{path.relative_to(root)}:{node.lineno} from {base} import {alias.name}")
    assert not wrong, "import each name from the module that defines it: " + "; ".join(wrong)
