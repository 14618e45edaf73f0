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


# -- functions a reader can hold ----------------------------------------------------------------

#: the longest function of the library (outside diagnose/ and cli/), in lines, docstring included
MAX_FUNCTION_LINES = 80

#: functions longer than that, not yet split along their jobs (issue 27): "path:name" -> what holds them
#: together.  Split one, and take it off the list (the test says so).
LONG_FUNCTIONS = {
    "detector/apply.py:map_blocks": "the block loop of apply-persistence: its closures share the threads' buffers",
    "io/frames.py:open_frame": "every frame layout (image, cube, WFC3 ramp) and its units, gain and timing",
    "measure/fit.py:_newton": "the damped Newton iteration of every fit: one loop over its shared state",
    "measure/joint.py:joint_setup": "the frames' headers read and what a joint fit fits chosen",
    "samples.py:make_sample_sequence": "the bundled sample exposures: their pixels and cards together",
    "scene/__init__.py:check_catalog": "the one check of catalogue columns, rule after rule",
    "scene/dithers.py:plan_dithers": "a dithered sequence: pattern, pointings and Roman's constraints",
    "stats/de_stats.py:theta_distribution": "the position-angle distribution, its bootstrap and its test",
    "stats/pairs.py:load_pairs": "many pairs read, matched and pooled, with their bookkeeping",
    "stats/xi.py:correlate_de": "TreeCorr's correlation and the choice of jackknife or shot-noise errors",
    "study/summary.py:variant_results": "one variant's statistics, uniformity and budget read together",
    "study/tasks.py:_final": "a study task: finals rendered, and measured or kept",
}


def _function_lengths() -> dict:
    """Lines (``end_lineno - lineno + 1``) of every function and method outside diagnose/ and cli/, by "path:name"."""
    import ast

    lengths = {}
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC)
        if rel.parts[0] in ("diagnose", "cli"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                key = f"{rel.as_posix()}:{node.name}"
                lengths[key] = max(lengths.get(key, 0), node.end_lineno - node.lineno + 1)
    return lengths


def test_no_function_is_over_80_lines_but_the_listed_ones():
    """Science in one function, its FITS layout in another: none over MAX_FUNCTION_LINES but LONG_FUNCTIONS."""
    lengths = _function_lengths()
    assert len(lengths) > 500
    long = {key: n for key, n in lengths.items() if n > MAX_FUNCTION_LINES and key not in LONG_FUNCTIONS}
    assert not long, f"split these where the science meets the FITS layout: {long}"
    gone = sorted(key for key in LONG_FUNCTIONS if lengths.get(key, 0) <= MAX_FUNCTION_LINES)
    assert not gone, f"split or gone: take them off LONG_FUNCTIONS: {gone}"
