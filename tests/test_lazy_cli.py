"""The command line loads lazily, the library imports at the top of its modules.

- ``perscli --help`` lists every command from the table in perscli/cli/main.py
  (:data:`perscli.cli.main.COMMANDS`) without importing any command module,
  and neither it nor ``perscli COMMAND --help`` imports numpy, astropy, GalSim,
  SciPy, fitsio, TreeCorr, matplotlib or Dask (each checked in a fresh process);
- the table's short help is each command's own, so the two cannot drift;
- a library module (outside perscli.cli) imports at its top: an import inside a
  function is allowed only with a ``# lazy: why`` comment on its line or on the
  line just above it (an optional heavy dependency one option uses, such as
  matplotlib for the figures and Dask for a study's scheduler; a module the
  command line reads while it builds its options and help).
"""

import ast
import json
import subprocess
import sys
from pathlib import Path

import click
import pytest

from perscli.cli.main import COMMANDS, _INTERRUPTED_KEEPS, LazyGroup, cli

from fits_factory import commands

SRC = Path(__file__).resolve().parents[1] / "src" / "perscli"
HEAVY = ("numpy", "astropy", "galsim", "scipy", "fitsio", "treecorr", "matplotlib", "dask", "distributed")
#: the marker that excuses an import inside a function of a library module
MARKER = "lazy:"


def _in_a_fresh_process(code: str) -> dict:
    """Run ``code`` in a new interpreter; it ends by printing a JSON line, returned parsed."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


_REPORT = ("import json, sys\n"
           f"print(json.dumps({{'heavy': [m for m in {HEAVY!r} if m in sys.modules], "
           "'perscli': sorted(m for m in sys.modules if m.startswith('perscli'))}))\n")


# -- the group ------------------------------------------------------------------------------------

def test_the_group_help_imports_no_command_and_nothing_heavy():
    code = ("import click\n"
            "from perscli.cli.main import cli\n"
            "ctx = click.Context(cli, info_name='perscli', **cli.context_settings)\n"
            "help_text = cli.get_help(ctx)\n"
            "assert 'apply-persistence' in help_text and 'study' in help_text\n" + _REPORT)
    seen = _in_a_fresh_process(code)
    assert seen["heavy"] == []
    command_modules = {target.partition(":")[0] for target, _ in COMMANDS.values()}
    loaded = sorted(command_modules & set(seen["perscli"]))
    assert not loaded, f"perscli --help imported command modules: {loaded}"


def test_no_commands_help_imports_anything_heavy():
    """Every ``perscli COMMAND --help`` in turn, in one process, through the console script's own path (main:
    signal handlers, standard streams); modules only accumulate, so the first help to import one is named."""
    helps = [[name, "--help"] for name in sorted(COMMANDS)] + [["pointings", sub, "--help"]
                                                             for sub in ("select", "before", "plan")]
    code = ("import json, sys\n"
            "from perscli.cli.main import main\n"
            "seen = {}\n"
            f"for args in {helps!r}:\n"
            "    sys.argv = ['perscli', *args]\n"
            "    try:\n"
            "        main()\n"
            "    except SystemExit as exc:\n"
            "        assert exc.code in (0, None), (args, exc.code)\n"
            f"    seen[' '.join(args)] = [m for m in {HEAVY!r} if m in sys.modules]\n"
            "print(json.dumps(seen))\n")
    seen = _in_a_fresh_process(code)
    assert list(seen) == [" ".join(args) for args in helps]
    first = next(((args, heavy) for args, heavy in seen.items() if heavy), None)
    assert first is None, f"perscli {first[0]} imported {first[1]}"


# -- the table ------------------------------------------------------------------------------------

def test_every_row_of_the_table_is_its_command_with_its_short_help():
    loaded = commands()
    assert set(loaded) == set(COMMANDS)
    for name, (target, short) in COMMANDS.items():
        command = loaded[name]
        assert isinstance(command, click.Command) and command.name == name, target
        # the command says its short help itself (not cut from its help text at a width): the table's is it
        assert command.short_help == short, f"{name}: the table's short help differs from the command's"
        assert command.get_short_help_str(limit=200) == short
        assert not command.hidden


def test_the_help_lists_what_click_would_list_with_every_command_loaded():
    ctx = click.Context(cli, info_name="perscli", **cli.context_settings)
    ours, clicks = click.HelpFormatter(), click.HelpFormatter()
    cli.format_commands(ctx, ours)
    click.Group.format_commands(cli, ctx, clicks)          # click's own: loads each command, asks its short help
    assert ours.getvalue() == clicks.getvalue()
    assert cli.commands == {}                              # nothing loaded ahead of use


def test_an_unknown_command_is_suggested_from_the_whole_table():
    group = LazyGroup("g", lazy_subcommands={"budget": COMMANDS["budget"]})
    with pytest.raises(click.UsageError) as err:
        group.main(["budgte"], prog_name="g", standalone_mode=False)
    assert "No such command 'budgte'" in err.value.format_message()
    if hasattr(click.exceptions, "NoSuchCommand"):      # click 8.4+ suggests a close name
        assert "Did you mean 'budget'?" in err.value.format_message()


def test_a_row_that_is_not_a_command_is_refused():
    group = LazyGroup("g", lazy_subcommands={"x": ("perscli.cli.main:COMMANDS", "Not a command.")})
    with pytest.raises(TypeError, match="is not a click command"):
        group.get_command(None, "x")


def test_the_interrupted_lines_name_commands_of_the_table():
    assert set(_INTERRUPTED_KEEPS) <= set(COMMANDS)


# -- the library imports at the top ------------------------------------------------------------

def function_level_imports(path: Path):
    """(line, statement) of each import inside a function of ``path``, with whether a ``# lazy:`` comment excuses
    it (on its line or on the line just above)."""
    text = path.read_text()
    lines = text.splitlines()
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                if in_function:
                    above = lines[child.lineno - 2].strip() if child.lineno > 1 else ""
                    excused = MARKER in lines[child.lineno - 1] or (above.startswith("#") and MARKER in above)
                    found.append((child.lineno, ast.unparse(child), excused))
            else:
                visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    visit(ast.parse(text), False)
    return found


def _library():
    return [p for p in sorted(SRC.rglob("*.py")) if p.relative_to(SRC).parts[0] != "cli" and p.name != "__main__.py"]


def test_the_marker_rule_sees_functions_and_comments(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("import os\n\ndef f():\n    import json\n    import re  # lazy: why\n"
                      "    # lazy: why, for the next line\n    import sys\n\n"
                      "class C:\n    def g(self):\n        if True:\n            import csv\n")
    assert [(line, excused) for line, _, excused in function_level_imports(module)] == [
        (4, False), (5, True), (7, True), (12, False)]


def test_library_modules_import_at_the_top():
    """Imports inside functions of the library hide the real dependency graph: each needs a reason, written."""
    unexcused = [f"{path.relative_to(SRC)}:{line}: {statement}" for path in _library()
                 for line, statement, excused in function_level_imports(path) if not excused]
    assert len(_library()) > 50
    assert not unexcused, ("move these imports to the top of their module, or say on the line (or the line "
                           f"above) why not, with '# {MARKER} ...': " + "; ".join(unexcused))


def test_no_command_rewrites_its_own_parameters_at_import():
    """A command's options say what they are where they are declared: no module of cli/ changes a click
    parameter after the fact (no loop over ``command.params``, no ``param.required = ...`` at module level)."""
    import ast
    from pathlib import Path

    cli_dir = Path(__file__).resolve().parents[1] / "src" / "perscli" / "cli"
    found = []
    for path in sorted(cli_dir.glob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, (ast.For, ast.While)):
                found.append(f"{path.name}:{node.lineno}: a loop at module level")
            targets = node.targets if isinstance(node, ast.Assign) else (
                [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])
            for t in targets:
                if isinstance(t, (ast.Attribute, ast.Subscript)):
                    found.append(f"{path.name}:{node.lineno}: {ast.unparse(t)} changed at module level")
    assert not found, found
