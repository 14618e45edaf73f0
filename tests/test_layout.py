"""The package's shape: modules a reader can hold (none over 800 lines)."""

from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "perscli"
MAX_LINES = 800


def test_no_module_is_over_800_lines():
    sizes = {str(p.relative_to(SRC)): len(p.read_text().splitlines()) for p in SRC.rglob("*.py")}
    assert len(sizes) > 50
    big = {name: n for name, n in sizes.items() if n > MAX_LINES}
    assert not big, f"split these along their jobs: {big}"


# -- layers: imports go one way -----------------------------------------------------------------

def _perscli_imports(path: Path) -> set:
    """The perscli modules (and names) a file imports, anywhere in it (function-level imports too)."""
    from test_imports import import_statements

    names = set()
    for base, imported in import_statements(path, ["perscli", *path.relative_to(SRC).parts[:-1]]):
        if base is None:
            names.update(imported)
        else:
            names.add(base)
            names.update(f"{base}.{alias}" for alias in imported)
    return {n for n in names if n == "perscli" or n.startswith("perscli.")}


def _reaching(paths, forbidden) -> dict:
    found = {}
    for path in paths:
        bad = sorted(n for n in _perscli_imports(path) if any(n == f or n.startswith(f + ".") for f in forbidden))
        if bad:
            found[str(path.relative_to(SRC))] = bad
    return found


def test_optics_sits_below_render_and_measure():
    """perscli.optics (Roman's WCS, PSF and stamp drawing) imports neither of the two that use it."""
    assert not _reaching([SRC / "optics.py"], ("perscli.render", "perscli.measure", "perscli.study",
                                               "perscli.cli", "perscli.diagnose", "perscli.stats"))


def test_measure_does_not_reach_into_render():
    """measure draws through perscli.optics, as render does, rather than importing render's modules."""
    assert not _reaching(sorted((SRC / "measure").rglob("*.py")), ("perscli.render", "perscli.study", "perscli.cli"))


def test_render_reaches_no_layer_above_it():
    """render draws frames; shapes, statistics, diagnose and the study's machinery sit above it."""
    assert not _reaching(sorted((SRC / "render").rglob("*.py")), ("perscli.measure", "perscli.stats",
                                                                  "perscli.diagnose", "perscli.study", "perscli.cli"))


def _third_party(path: Path) -> set:
    """The top-level names of the modules a file imports that are not perscli's (function-level too)."""
    import ast

    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
    return names


def test_the_library_knows_nothing_of_click():
    """Everything the command line does can be done from Python: only perscli.cli imports click or the cli."""
    library = [p for p in sorted(SRC.rglob("*.py")) if p.relative_to(SRC).parts[0] != "cli"
               and p.name != "__main__.py"]
    assert len(library) > 50
    assert not _reaching(library, ("perscli.cli",))
    clicking = sorted(str(p.relative_to(SRC)) for p in library if "click" in _third_party(p))
    assert not clicking, f"library modules that import click: {clicking}"
