"""What the shell sees: one-line usage errors, `perscli man`, tab completion, and the modes of outputs."""

import os
import re
import shutil
import subprocess
import sys

import click
import numpy as np
import pytest
from click.shell_completion import ShellComplete

from perscli.cli import manpages
from perscli.cli.helpers import PathName
from perscli.cli.main import cli
from perscli.cli.helpers import PerscliGroup

from fits_factory import DAY, SHAPE, T0, command_named, commands, frame_file, invoke, leaf_commands, listing, usage_error

BIN = os.path.dirname(sys.executable)
SCRIPT = os.path.join(BIN, "perscli")

# -- usage errors: one line ----------------------------------------------------------------------

@pytest.mark.parametrize("args, command, message", [
    # a bad option value (a range, a choice, not a number)
    (["render", "--ra", "370"], "perscli render", "Invalid value for '--ra': 370.0 is not in the range"),
    (["apply-persistence", "a.fits", "b.fits", "-o", "x.fits", "--mode", "mul"], "perscli apply-persistence",
     "Invalid value for '--mode': 'mul' is not one of 'add', 'subtract', 'predict'"),
    (["budget", "--nbins", "many", "-o", "x.fits"], "perscli budget", "Invalid value for '--nbins'"),
    # a value refused by a parameter's callback
    (["budget", "--plot", "-", "-o", "x.fits"], "perscli budget", "Invalid value for '--plot'"),
    # missing argument, missing option
    (["apply-persistence"], "perscli apply-persistence", "Missing argument 'CURRENT'"),
    (["budget"], "perscli budget", "Missing option '-o' / '--output'"),
    # unknown option, of a command and of the group; an extra argument; an unknown command
    (["budget", "--frobnicate", "-o", "x.fits"], "perscli budget", "No such option '--frobnicate'"),
    (["--frobnicate", "budget"], "perscli", "No such option '--frobnicate'"),
    (["budget", "a.fits", "b.fits", "-o", "x.fits"], "perscli budget", "Got unexpected extra argument (b.fits)"),
    (["rendr"], "perscli", "No such command 'rendr'. Did you mean 'render'?"),
    # options that exclude each other, and a UsageError raised without a context in a command's body
    (["man", "--all", "render", "-o", "pages"], "perscli man", "--all writes every page: give no COMMAND with it"),
    (["man", "--all"], "perscli man", "--all needs -o FOLDER, e.g. -o ~/.local/share/man/man1"),
    # a choice argument
    (["completion", "tcsh"], "perscli completion", "Invalid value for 'bash|zsh|fish': 'tcsh' is not one of"),
])
def test_every_kind_of_usage_error_is_one_line(tmp_path, monkeypatch, args, command, message):
    monkeypatch.chdir(tmp_path)
    assert message in usage_error(invoke(*args), command)
    assert listing(tmp_path) == []


def test_the_usage_line_in_full():
    result = invoke("apply-persistence", "cur.fits")
    assert result.stderr == ("perscli apply-persistence: error: Missing argument 'PREVIOUS...' "
                             "(see 'perscli apply-persistence -h')\n")


def test_a_usage_error_without_context_names_its_command():
    # a command of the group raising a bare UsageError in its body: the line still names it
    group = PerscliGroup("tool", context_settings={"help_option_names": ["-h", "--help"]})

    @group.command("sub")
    def sub():
        raise click.UsageError("--a and --b exclude each other.")

    result = click.testing.CliRunner().invoke(group, ["sub"], prog_name="tool")
    assert result.exit_code == 2
    assert result.stderr == "tool sub: error: --a and --b exclude each other (see 'tool sub -h')\n"


def test_a_multi_line_message_becomes_one_line():
    group = PerscliGroup("tool")

    @group.command("sub")
    @click.pass_context
    def sub(ctx):
        raise click.UsageError("first line\n  second line", ctx)

    result = click.testing.CliRunner().invoke(group, ["sub"], prog_name="tool")
    assert result.exit_code == 2
    assert result.stderr == "tool sub: error: first line second line (see 'tool sub --help')\n"


@pytest.mark.parametrize("module, command, args, message", [
    ("correlate", "correlate", ["--frobnicate"], "No such option '--frobnicate'"),
    ("correlate", "correlate", [], "Missing option '-o' / '--output'"),
    ("budget", "budget", ["--nbins", "many", "-o", "x.fits"], "Invalid value for '--nbins'"),
    ("render", "render", ["t.fits", "--ra", "370"], "Invalid value for '--ra': 370.0 is not in the range"),
    ("manpages", "man", ["--all"], "--all needs -o FOLDER"),
])
def test_a_command_run_on_its_own_has_one_line_usage_errors(tmp_path, monkeypatch, module, command, args, message):
    # as tests of single commands run them: no perscli group around the command
    import importlib

    monkeypatch.chdir(tmp_path)
    cmd = getattr(importlib.import_module(f"perscli.cli.{module}"), command)
    result = click.testing.CliRunner().invoke(cmd, args)
    assert result.exit_code == 2 and result.stdout == "", (result.exit_code, result.output)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"{command}: error: ") and message in lines[0], lines[0]
    assert lines[0].endswith(f" (see '{command} --help')"), lines[0]
    assert listing(tmp_path) == []


def test_other_click_programs_keep_clicks_display():
    # nothing is patched at import: click's class keeps its own display, and a program of someone else's in
    # the same process shows click's four lines
    from perscli.cli import helpers

    assert click.UsageError.show.__module__ == "click.exceptions"
    assert helpers.PerscliGroup.__mro__[1] is helpers.OneLineUsage

    @click.command("other")
    @click.option("--n", type=int)
    def other(n):
        pass

    result = click.testing.CliRunner().invoke(other, ["--n", "x"])
    assert result.exit_code == 2
    assert result.stderr.startswith("Usage: other [OPTIONS]\nTry 'other --help' for help.\n\nError: ")
    # a perscli command taken into another program's group is that program's too
    group = click.Group("theirs", commands={"budget": command_named("budget")})
    result = click.testing.CliRunner().invoke(group, ["budget", "--frobnicate"])
    assert result.exit_code == 2 and result.stderr.startswith("Usage: theirs budget ")
    # a perscli command on its own (as a Python caller runs it) speaks perscli
    result = click.testing.CliRunner().invoke(command_named("budget"), ["--frobnicate"])
    assert result.exit_code == 2 and result.stderr.startswith("budget: error: No such option '--frobnicate'")
    assert len(result.stderr.splitlines()) == 1


def test_usage_errors_keep_their_type_and_message_for_python_callers():
    with pytest.raises(click.UsageError) as err:
        cli.main(["rendr"], prog_name="perscli", standalone_mode=False)
    assert "No such command 'rendr'" in err.value.format_message()
    with pytest.raises(click.BadParameter) as err:
        cli.main(["render", "--ra", "370"], prog_name="perscli", standalone_mode=False)
    assert err.value.param.name == "ra"


def test_help_and_no_arguments_still_show_the_help():
    for args in ([], ["-h"], ["render", "-h"]):
        result = invoke(*args)
        assert result.exit_code in (0, 2)
        assert result.output.startswith("Usage: perscli") and len(result.output.splitlines()) > 10, args


def test_data_errors_stay_as_they_were(tmp_path):
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=T0)
    missing = tmp_path / "missing.fits"
    result = invoke("apply-persistence", missing, prev, "-o", tmp_path / "out.fits")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {missing}: no such file\n"


def test_console_script_usage_error_in_a_real_process(tmp_path):
    if not os.path.exists(SCRIPT):
        pytest.skip("the perscli console script is not installed next to this Python")
    proc = subprocess.run([SCRIPT, "render", "--ra", "370"], capture_output=True, text=True, timeout=60,
                          cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("perscli render: error: Invalid value for '--ra': 370.0 is not in the range")
    assert proc.stderr.endswith(" (see 'perscli render -h')\n")


# -- perscli man ---------------------------------------------------------------------------------

def test_man_in_a_pipe_is_plain_text_with_every_option():
    result = invoke("man", "render")
    assert result.exit_code == 0, result.stderr
    text = result.stdout
    assert text.startswith("PERSCLI-RENDER(1)")
    for heading in ("NAME", "SYNOPSIS", "DESCRIPTION", "OPTIONS", "SEE ALSO"):
        assert f"\n{heading}\n" in text, heading
    assert "\n       perscli-render - " in text
    assert "\\f" not in text and "\\-" not in text and ".TP" not in text          # no troff left
    for param in command_named("render").params:
        if isinstance(param, click.Option):
            assert f"       {param.opts[0]}" in text or f", {param.opts[-1]}" in text, param.opts
    assert text.rstrip().endswith("PERSCLI-RENDER(1)")


def test_man_of_the_group_lists_every_command():
    result = invoke("man")
    assert result.exit_code == 0
    section = "\n" + result.stdout.split("\nCOMMANDS\n", 1)[1]
    for name in commands():
        assert f"\n       {name}\n" in section and f"See perscli-{name}(1)." in " ".join(section.split()), name


def test_plain_text_wraps_at_the_width():
    parts = manpages.page_parts(command_named("budget"), "perscli budget")
    text = manpages.to_text(parts, width=50)
    verbatim = {line for kind, block in parts["description"] if kind == "verbatim" for line in block.splitlines()}
    for line in text.splitlines():
        if line.strip() not in {v.strip() for v in verbatim} and " " in line.strip():
            assert len(line) <= 50, line


def test_man_troff_is_the_installed_page():
    pages = manpages.render_all(cli)
    for name in ("render", "man", "completion"):
        result = invoke("man", name, "--troff")
        assert result.exit_code == 0
        assert result.stdout == pages[f"perscli-{name}.1"]
    assert invoke("man", "--troff").stdout == pages["perscli.1"]


def test_man_output_writes_the_troff_and_refuses_to_replace_it(tmp_path):
    out = tmp_path / "perscli-render.1"
    assert invoke("man", "render", "-o", out).exit_code == 0
    assert out.read_text() == manpages.render_all(cli)["perscli-render.1"]
    out.write_text("old")
    result = invoke("man", "render", "-o", out)
    assert result.exit_code == 1 and result.stderr == f"Error: {out}: already exists; use --overwrite to replace it\n"
    assert out.read_text() == "old"
    assert invoke("man", "render", "-o", out, "--overwrite").exit_code == 0
    assert out.read_text().startswith('.TH "PERSCLI-RENDER"')


def test_man_all_installs_every_page_in_a_new_folder(tmp_path):
    folder = tmp_path / "share" / "man" / "man1"
    result = invoke("man", "--all", "-o", folder)
    assert result.exit_code == 0, result.stderr
    pages = manpages.render_all(cli)
    assert sorted(p.name for p in folder.iterdir()) == sorted(pages)
    for name, text in pages.items():
        assert (folder / name).read_text() == text
    # again: nothing replaced without --overwrite, and the error names a page
    (folder / "perscli.1").write_text("old")
    result = invoke("man", "--all", "-o", folder)
    assert result.exit_code == 1 and "already exists; use --overwrite" in result.stderr
    assert (folder / "perscli.1").read_text() == "old"
    assert invoke("man", "--all", "-o", folder, "--overwrite").exit_code == 0
    assert (folder / "perscli.1").read_text() == pages["perscli.1"]


def test_man_all_into_a_file_is_refused(tmp_path):
    target = tmp_path / "file"
    target.write_text("x")
    result = invoke("man", "--all", "-o", target)
    assert result.exit_code == 1 and "is not a folder" in result.stderr
    assert target.read_text() == "x"


def test_man_of_an_unknown_command():
    message = usage_error(invoke("man", "rendr"), "perscli man")
    assert message == "Invalid value for COMMAND: 'rendr' is not a perscli command; did you mean 'render'?"


def test_man_on_a_terminal_goes_through_man(monkeypatch):
    seen = {}

    def run(argv, *args, **kwargs):
        seen["argv"] = argv
        with open(argv[-1]) as fh:
            seen["page"] = fh.read()
        return subprocess.CompletedProcess(argv, 0)

    monkeypatch.setattr(manpages, "_stdout_is_terminal", lambda: True)
    monkeypatch.setattr(shutil, "which", lambda name: "/usr/bin/man" if name == "man" else None)
    monkeypatch.setattr(subprocess, "run", run)
    result = invoke("man", "study")
    assert result.exit_code == 0 and result.stdout == ""
    assert seen["argv"][:2] == ["/usr/bin/man", "-l"]
    assert seen["page"] == manpages.render_all(cli)["perscli-study.1"]
    assert not os.path.exists(seen["argv"][-1])                       # the temporary page is gone


@pytest.mark.parametrize("man_program", [None, "/usr/bin/man"])
def test_man_on_a_terminal_without_a_working_man_uses_the_pager(monkeypatch, man_program):
    shown = []
    monkeypatch.setattr(manpages, "_stdout_is_terminal", lambda: True)
    monkeypatch.setattr(shutil, "which", lambda name: man_program)
    monkeypatch.setattr(subprocess, "run", lambda argv, *a, **k: subprocess.CompletedProcess(argv, 16))
    monkeypatch.setattr(click, "echo_via_pager", lambda text, *a, **k: shown.append(text))
    result = invoke("man", "study")
    assert result.exit_code == 0
    assert len(shown) == 1 and shown[0].startswith("PERSCLI-STUDY(1)")


@pytest.mark.skipif(shutil.which("man") is None, reason="man(1) is not installed")
def test_real_man_reads_the_pages(tmp_path):
    page = tmp_path / "perscli-render.1"
    page.write_text(manpages.render_all(cli)["perscli-render.1"])
    env = dict(os.environ, MANPAGER="cat", PAGER="cat", MANWIDTH="80", LANG="C.UTF-8")
    proc = subprocess.run(["man", "-l", str(page)], capture_output=True, text=True, env=env, timeout=60)
    if proc.returncode != 0 and "not found" in proc.stderr:       # man without its formatter (groff)
        pytest.skip(proc.stderr.strip())
    assert proc.returncode == 0, proc.stderr
    plain = re.sub(r".\x08", "", proc.stdout)                    # overstrike bold, if any
    assert "perscli-render - " in plain and "--previous" in plain


def test_man_in_a_real_pipeline_that_stops_reading(tmp_path):
    if not os.path.exists(SCRIPT):
        pytest.skip("the perscli console script is not installed next to this Python")
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", "perscli man correlate | head -n 1"], cwd=tmp_path,
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    head = proc.stdout.rstrip("\n")
    assert proc.stdout.count("\n") == 1 and len(head) == 80
    assert head.startswith("PERSCLI-CORRELATE(1) ") and head.endswith(" PERSCLI-CORRELATE(1)")
    assert head.split() == ["PERSCLI-CORRELATE(1)", "perscli", "manual", "PERSCLI-CORRELATE(1)"]
    assert proc.stderr == ""


# -- completion ----------------------------------------------------------------------------------

#: every parameter that names a file or a folder: (command, parameter) -> completion type (and names)
PATH_PARAMS = {
    ("measure", "write_psf"): "file",
    ("apply-persistence", "current"): "file",
    ("apply-persistence", "previous"): "file",
    ("apply-persistence", "law"): ("file", "typical", "pessimistic", "wfc3", "galsim-linear"),
    ("apply-persistence", "model_spec"): ("file", "typical", "pessimistic", "wfc3", "galsim-linear"),
    ("apply-persistence", "output"): "file",
    ("budget", "xi"): "file",
    ("budget", "plot"): "file",
    ("budget", "output"): "file",
    ("catalog", "pointings_table"): "file",
    ("catalog", "footprints"): "file",
    ("catalog", "gaia"): "file",
    ("catalog", "output"): "file",
    ("correlate", "shapes"): "file",
    ("correlate", "pair_list"): "file",
    ("correlate", "pairs_file"): "file",
    ("correlate", "patch_centers"): "file",
    ("correlate", "plot"): "file",
    ("correlate", "plots_dir"): "dir",
    ("correlate", "output"): "file",
    ("diagnose", "measured"): "file",
    ("diagnose", "simulated"): "file",
    ("diagnose", "model_spec"): "file",
    ("diagnose", "outdir"): "dir",
    ("measure", "frames"): "file",
    ("measure", "catalog"): "file",
    ("measure", "psf"): ("file", "roman"),
    ("measure", "output"): "file",
    ("pointings", "schedule"): "file",
    ("pointings", "catalog"): "file",
    ("pointings", "output"): "file",
    ("pointings select", "schedule"): ("file", "roman-was"),
    ("pointings select", "catalog"): "file",
    ("pointings select", "output"): "file",
    ("pointings before", "schedule"): ("file", "roman-was"),
    ("pointings before", "catalog"): "file",
    ("pointings before", "output"): "file",
    ("pointings plan", "catalog"): "file",
    ("pointings plan", "output"): "file",
    ("render", "truth"): "file",
    ("render", "pointings_file"): "file",
    ("render", "model_spec"): ("file", "roman"),
    ("render", "previous"): "file",
    ("render", "regions"): "file",
    ("render", "plot"): "file",
    ("render", "output"): "file",
    ("study", "description"): "file",
    ("study", "outdir"): "dir",
    ("study", "cost_from"): "file",
    ("man", "dest"): "file",
    ("completion", "dest"): "file",
}

#: metavars that say "a file or a folder": a new parameter with one of them belongs in PATH_PARAMS
_PATHLIKE = re.compile(r"\.(fits|yaml|reg|json|png)\b|FILE|PATH|DIR|PNG|FRAME", re.I)


def _param(command, name):
    return next(p for p in command_named(command).params if p.name == name)


def completions(args, incomplete):
    comp = ShellComplete(cli, {}, "perscli", "_PERSCLI_COMPLETE")
    return [(item.type, item.value) for item in comp.get_completions(args, incomplete)]


def test_every_file_parameter_is_known_here():
    for command, cmd in leaf_commands():
        for p in cmd.params:
            if p.metavar and _PATHLIKE.search(p.metavar) and (command, p.name) not in PATH_PARAMS:
                pytest.fail(f"{command} {p.name} ({p.metavar}) takes a path: add it to PATH_PARAMS")
    assert all(any(p.name == name for p in command_named(cmd).params) for cmd, name in PATH_PARAMS), \
        "PATH_PARAMS names a parameter that no longer exists"


@pytest.mark.parametrize("command, name", sorted(PATH_PARAMS))
def test_every_path_parameter_completes_file_names(command, name):
    want = PATH_PARAMS[(command, name)]
    kind, names = (want, ()) if isinstance(want, str) else (want[0], want[1:])
    param = _param(command, name)
    assert isinstance(param.type, click.Path), f"{command} {name}: type=click.Path (perscli.cli.helpers.FILE)"
    ctx = click.Context(command_named(command), info_name=command)
    items = param.shell_complete(ctx, "")
    assert (items[0].type, items[0].value) == (kind, "")
    assert sorted(item.value for item in items[1:]) == sorted(names)


def test_path_types_check_nothing():
    # the library, not click, reports a missing or unreadable file (one line naming it, exit 1)
    for type_ in (PathName(), PathName(folder=True), PathName(names=("roman",))):
        for value in ("-", "/no/such/file.fits", "roman", "/"):
            assert type_.convert(value, None, None) == value


def test_completion_offers_files_commands_options_and_choices():
    assert completions(["man", "render", "-o"], "pers") == [("file", "pers")]
    assert completions(["completion", "bash", "--output"], "") == [("file", "")]
    assert completions(["man"], "re") == [("plain", "render")]
    assert completions(["completion"], "") == [("plain", "bash"), ("plain", "zsh"), ("plain", "fish")]
    assert ("plain", "apply-persistence") in completions([], "app")
    assert ("plain", "--overwrite") in completions(["man"], "--ov")


@pytest.mark.parametrize("shell, needles", [
    ("bash", ["_PERSCLI_COMPLETE=bash_complete", "complete -o nosort -F _perscli_completion perscli"]),
    ("zsh", ["#compdef perscli", "_PERSCLI_COMPLETE=zsh_complete", "_path_files -f"]),
    ("fish", ["complete --no-files --command perscli", "_PERSCLI_COMPLETE=fish_complete", "__fish_complete_path"]),
])
def test_completion_prints_the_script(shell, needles):
    result = invoke("completion", shell)
    assert result.exit_code == 0 and result.stderr == ""
    for needle in needles:
        assert needle in result.stdout, needle


def test_completion_output_creates_its_folder_and_refuses_to_replace(tmp_path):
    out = tmp_path / ".local" / "share" / "bash-completion" / "completions" / "perscli"
    assert invoke("completion", "bash", "-o", out).exit_code == 0
    assert out.read_text() == invoke("completion", "bash").stdout
    result = invoke("completion", "zsh", "-o", out)
    assert result.exit_code == 1 and "already exists; use --overwrite" in result.stderr
    assert invoke("completion", "zsh", "-o", out, "--overwrite").exit_code == 0
    assert out.read_text().startswith("#compdef perscli")


def _bash_complete(tmp_path, words):
    """Run the generated bash script's completion function on ``words`` (the last one incomplete)."""
    if not os.path.exists(SCRIPT) or shutil.which("bash") is None:
        pytest.skip("needs bash and the installed perscli script")
    # compopt acts on readline, which a script has not: a function in its place records what the script asked
    script = ('eval "$(perscli completion bash)"\n'
              'compopt() { echo compopt "$@"; }\n'
              f'COMP_WORDS=({" ".join(words)}); COMP_CWORD={len(words) - 1}\n'
              '_perscli_completion perscli\n'
              'printf "reply %s\\n" "${COMPREPLY[@]}"\n')
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    proc = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_bash_completes_a_file_name_through_the_real_script(tmp_path):
    (tmp_path / "perscli-render.1").write_text("")
    lines = _bash_complete(tmp_path, ["perscli", "man", "render", "-o", "pers"])
    # no words of its own: bash's default completion, file names, takes over
    assert lines == ["compopt -o default", "reply "]
    lines = _bash_complete(tmp_path, ["perscli", "man", "ren"])
    assert lines == ["reply render"]


# -- outputs get the mode of any new file ----------------------------------------------------------

# the umask fixture (022, 077, 027 and the mode a new file gets under each) and mode_of are test_io_output's
from test_io_output import mode_of, umask  # noqa: E402,F401  (umask: a fixture)


def test_fits_and_png_outputs_follow_the_umask(tmp_path, umask):
    result = invoke("budget", "-o", tmp_path / "budget.fits", "--plot", tmp_path / "budget.png")
    assert result.exit_code == 0, result.stderr
    assert {name: mode_of(tmp_path / name) for name in listing(tmp_path)} == {"budget.fits": umask,
                                                                               "budget.png": umask}


def test_fits_outputs_of_apply_persistence_follow_the_umask(tmp_path, umask):
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=T0)
    cur = frame_file(tmp_path / "cur.fits", np.full(SHAPE, 50.0), start=T0 + 300.0 / DAY)
    for out in ("out.fits", "out.fits.gz"):
        result = invoke("apply-persistence", cur, prev, "-o", tmp_path / out)
        assert result.exit_code == 0, result.stderr
        assert mode_of(tmp_path / out) == umask, out


def test_region_files_follow_the_umask(tmp_path, umask):
    truth = tmp_path / "truth.fits"
    result = invoke("catalog", "--ra", "9.5", "--dec", "-44", "--size", "1", "--seed", "1", "-o", truth)
    assert result.exit_code == 0, result.stderr
    regions = tmp_path / "frame.reg"
    result = invoke("-q", "render", truth, "--ra", "9.5", "--dec", "-44", "--pa", "30", "--mjd", "61541.97",
                    "--filter", "J129", "--sca", "7", "--dry-run", "--regions", regions)
    assert result.exit_code == 0, result.stderr
    assert mode_of(truth) == umask and mode_of(regions) == umask


def test_man_pages_and_completion_scripts_follow_the_umask(tmp_path, umask):
    assert invoke("man", "render", "-o", tmp_path / "perscli-render.1").exit_code == 0
    assert invoke("man", "--all", "-o", tmp_path / "man1").exit_code == 0
    assert invoke("completion", "fish", "-o", tmp_path / "perscli.fish").exit_code == 0
    assert mode_of(tmp_path / "perscli-render.1") == umask
    assert {mode_of(p) for p in (tmp_path / "man1").iterdir()} == {umask}
    assert mode_of(tmp_path / "perscli.fish") == umask
