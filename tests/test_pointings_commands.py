"""``perscli pointings select | before | plan``: the subcommands, the deprecated flag form they replace
(same options, same bytes), their settings dataclasses and their usage errors."""

import dataclasses
import subprocess
import sys

import click
import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner

from perscli.cli.main import cli
from perscli.cli.pointings import FlagFormGroup, pointings, pointings_flags
from perscli.scene.settings import PlanOptions, SelectOptions

from fits_factory import commands, invoke, listing, raw_cards_masked
from test_scene_pointings import DEC, RA, schedule_file, was  # noqa: F401  (was: a fixture)

#: each subcommand and the flag form it stands for: (subcommand words, flag-form words), with S the schedule
PAIRS = {
    "select": (["select", "--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 0.5],
               ["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 0.5]),
    "select, filter, limit, after, columns": (
        ["select", "--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--filter", "j129", "--limit", 2,
         "--after", 60000.001, "--schedule-columns", "date=date"],
        ["--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--filter", "j129", "--limit", 2,
         "--after", 60000.001, "--schedule-columns", "date=date"]),
    "select, nothing found": (["select", "--schedule", "S", "--ra", 100, "--dec", 20, "--radius", 1],
                              ["--schedule", "S", "--ra", 100, "--dec", 20, "--radius", 1]),
    "before": (["before", "--schedule", "S", "--row", 5, "--n", 3, "--sca", 7],
               ["--schedule", "S", "--before", 5, "--n", 3, "--sca", 7]),
    "before, fewer than asked": (["before", "--schedule", "S", "--row", 2, "--n", 5],
                                 ["--schedule", "S", "--before", 2, "--n", 5]),
    "plan": (["plan", "--ra", RA, "--dec", DEC, "--n", 3, "-v"], ["--plan", "--ra", RA, "--dec", DEC, "--n", 3, "-v"]),
    "plan, every setting": (
        ["plan", "--ra", RA, "--dec", DEC, "--n", 4, "--dither", 30, "--filter", "h158", "--start", 61600.5,
         "--exptime", 60, "--gap", 10, "--pa", 240, "--sca", 3, "--seed", 5, "--footprints"],
        ["--plan", "--ra", RA, "--dec", DEC, "--n", 4, "--dither", 30, "--filter", "h158", "--start", 61600.5,
         "--exptime", 60, "--gap", 10, "--pa", 240, "--sca", 3, "--seed", 5, "--footprints"]),
}


def _run(tmp_path, words, out):
    schedule = tmp_path / "s.fits"
    if not schedule.exists():
        schedule_file(schedule)
    return invoke("pointings", *[schedule if w == "S" else w for w in words], "-o", out)


@pytest.mark.parametrize("case", sorted(PAIRS))
def test_each_subcommand_writes_the_bytes_of_its_flag_form(tmp_path, case):
    sub, flags = PAIRS[case]
    new, old = tmp_path / "new.fits", tmp_path / "old.fits"
    a, b = _run(tmp_path, sub, new), _run(tmp_path, flags, old)
    assert a.exit_code == 0 and b.exit_code == 0, (a.stderr, b.stderr)
    assert raw_cards_masked(new) == raw_cards_masked(old)
    # the same messages (the count line names the output), nothing on stdout; the flag form first says it is
    # deprecated, naming the subcommand and the release that removes it
    warning, rest = b.stderr.split("\n", 1)
    assert warning.startswith("perscli: warning: perscli pointings --") and "deprecated" in warning, b.stderr
    assert f"use perscli pointings {sub[0]} " in warning and "0.3.0" in warning, warning
    assert a.stderr.replace(str(new), "OUT") == rest.replace(str(old), "OUT")
    assert a.stdout == b.stdout == ""


def test_select_by_sca_footprint_with_counts_is_the_flag_forms(was, tmp_path):
    """The real schedule, where SCA 7 lands on the field: footprints and a catalogue's counts too."""
    catalog = tmp_path / "cat.fits"
    assert invoke("catalog", "--ra", RA, "--dec", DEC, "--size", 10, "-o", catalog).exit_code == 0
    args = ["--schedule", was, "--ra", RA, "--dec", DEC, "--radius", 0.05, "--sca", 7, "--filter", "J129",
            "--footprints", "--catalog", catalog, "--columns", "kind=kind"]
    a = invoke("pointings", "select", *args, "-o", tmp_path / "a.fits")
    b = invoke("pointings", *args, "-o", tmp_path / "b.fits")
    assert a.exit_code == b.exit_code == 0, (a.stderr, b.stderr)
    assert raw_cards_masked(tmp_path / "a.fits") == raw_cards_masked(tmp_path / "b.fits")
    assert len(fits.getdata(tmp_path / "a.fits", "POINTINGS")) == 7


def test_a_subcommand_to_standard_output_gives_the_same_table(tmp_path):
    schedule = schedule_file(tmp_path / "s.fits")
    a = invoke("pointings", "before", "--schedule", schedule, "--row", 6, "--n", 4, "-o", "-")
    b = invoke("pointings", "--schedule", schedule, "--before", 6, "--n", 4, "-o", "-")
    assert a.exit_code == b.exit_code == 0 and a.stderr == "stdout: 4 rows written (exposures)\n"
    assert b.stderr.endswith("use perscli pointings before --schedule FILE --row ROW ...\n" + a.stderr), b.stderr
    for result, name in ((a, "a.fits"), (b, "b.fits")):
        (tmp_path / name).write_bytes(result.stdout_bytes)
    assert raw_cards_masked(tmp_path / "a.fits") == raw_cards_masked(tmp_path / "b.fits")
    assert list(fits.getdata(tmp_path / "a.fits", "POINTINGS")["expid"]) == [2, 3, 4, 5]


# -- the group --------------------------------------------------------------------------------------

def test_the_group_help_lists_the_subcommands_only():
    result = invoke("pointings", "--help")
    assert result.exit_code == 0
    commands = result.stdout.split("\nCommands:\n", 1)[1]
    assert [line.split()[0] for line in commands.strip().splitlines()] == ["before", "plan", "select"]
    # the documentation names the current spellings only; the flag form's own help says it is deprecated
    assert "--plan" not in result.stdout and "--before" not in result.stdout
    text = " ".join(invoke("pointings", "--plan", "--help").stdout.split())
    assert "Deprecated" in text and "until perscli 0.3.0" in text


def test_no_arguments_show_the_help():
    result = invoke("pointings")
    assert "Commands:" in result.output and "select" in result.output


@pytest.mark.parametrize("args, command, needle", [
    (["plan", "--ra", RA, "--dec", DEC], "perscli pointings plan", "Missing option '--n'"),
    (["plan", "--dec", DEC, "--n", 2], "perscli pointings plan", "Missing option '--ra'"),
    (["plan", "--ra", RA, "--n", 2], "perscli pointings plan", "Missing option '--dec'"),
    (["plan", "--ra", RA, "--dec", DEC, "--n", 2, "--radius", 1], "perscli pointings plan",
     "No such option '--radius'"),
    (["plan", "--ra", RA, "--dec", DEC, "--n", 2, "--footprints"], "perscli pointings plan",
     "--footprints needs --sca N"),
    (["plan", "--ra", 370, "--dec", DEC, "--n", 2], "perscli pointings plan", "Invalid value for '--ra'"),
    (["select", "--schedule", "S", "--ra", RA, "--dec", DEC], "perscli pointings select", "Missing option '--radius'"),
    (["select", "--schedule", "S", "--ra", RA, "--radius", 1], "perscli pointings select",
     "Missing option '--dec'"),
    (["select", "--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--seed", 3], "perscli pointings select",
     "No such option '--seed'"),
    (["select", "--schedule", "S", "--ra", RA, "--dec", DEC, "--radius", 1, "--catalog", "S"],
     "perscli pointings select", "--catalog needs --footprints"),
    (["before", "--schedule", "S", "--n", 2], "perscli pointings before", "Missing option '--row'"),
    (["before", "--schedule", "S", "--row", 2, "--n", 2, "--ra", RA], "perscli pointings before",
     "No such option '--ra'"),
    (["before", "--schedule", "S", "--row", 2, "--n", 0], "perscli pointings before", "Invalid value for '--n'"),
    (["plna", "--ra", RA], "perscli pointings", "No such command 'plna'. Did you mean 'plan'?"),
])
def test_usage_errors_are_one_line_naming_the_subcommand(tmp_path, args, command, needle):
    schedule = schedule_file(tmp_path / "s.fits")
    files = listing(tmp_path)
    result = invoke("pointings", *[schedule if a == "S" else a for a in args], "-o", tmp_path / "out.fits")
    assert result.exit_code == 2 and result.stdout == "", result.output
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith(f"{command}: error: ") and needle in result.stderr, result.stderr
    assert result.stderr.rstrip().endswith(f"(see '{command} -h')")
    assert listing(tmp_path) == files


def test_verbosity_before_a_subcommand_or_the_flag_form(tmp_path):
    args = ["--ra", RA, "--dec", DEC, "--n", 2]
    for k, words in enumerate((["-v", "plan"], ["-v", "--plan"], ["-q", "-vv", "plan"], ["-qvv", "--plan"])):
        result = invoke("pointings", *words, *args, "-o", tmp_path / f"{k}.fits")
        assert result.exit_code == 0, (words, result.stderr)
        assert "perscli: info: plan: start MJD" in result.stderr, words
    result = invoke("pointings", "-q", "plan", *args, "-o", tmp_path / "q.fits")
    assert result.exit_code == 0 and result.stderr == ""


def test_the_flag_form_keeps_its_errors():
    # the group's name, as before: scripts that parse the line keep working
    result = invoke("pointings", "--plan", "--ra", RA, "--dec", DEC, "-o", "x.fits")
    assert result.exit_code == 2
    assert result.stderr == ("perscli pointings: error: --plan needs --n N (the number of exposures) "
                             "(see 'perscli pointings -h')\n")


def test_the_group_run_on_its_own_runs_both_forms(tmp_path):
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    args = ["--ra", str(RA), "--dec", str(DEC), "--n", "2"]
    assert CliRunner().invoke(pointings, ["plan", *args, "-o", str(a)]).exit_code == 0
    assert CliRunner().invoke(pointings, ["--plan", *args, "-o", str(b)]).exit_code == 0
    assert raw_cards_masked(a) == raw_cards_masked(b)
    result = CliRunner().invoke(pointings, ["--plan", *args])
    assert result.exit_code == 2 and result.stderr.startswith("pointings: error: Missing option '-o'")


# -- one set of options ----------------------------------------------------------------------------

def _options(command):
    return {p.opts[0]: p for p in command.params if isinstance(p, click.Option)}


@pytest.mark.parametrize("name", ["select", "before", "plan"])
def test_the_subcommands_options_are_the_flag_forms(name):
    """Built from the same decorators: the same names, types, ranges and metavars (--row is --before)."""
    legacy = _options(pointings_flags)
    for opt, param in _options(pointings.commands[name]).items():
        if opt == "--schedule":
            # the subcommands take the bundled schedule by default (roman-was); the flag form needs a file, as before
            assert param.default == "roman-was" and legacy[opt].default in (None, getattr(click.core, "UNSET", None))
            continue
        old = legacy["--before" if opt == "--row" else opt]
        assert type(param.type) is type(old.type) and repr(param.type) == repr(old.type), opt
        assert param.metavar == old.metavar and param.is_flag == old.is_flag and param.multiple == old.multiple, opt
        assert param.callback is old.callback or param.callback.__name__ == old.callback.__name__, opt


def test_the_group_parses_its_own_options_and_runs_the_flag_form_as_its_legacy():
    # the group's options are its own -v/-q and help; the flag form is a command of its own (group.legacy),
    # which tools that list every command's options reach through fits_factory.leaf_commands
    from fits_factory import leaf_commands

    group = commands()["pointings"]
    assert isinstance(group, FlagFormGroup) and group.legacy is pointings_flags
    ctx = click.Context(group, info_name="pointings")
    params = group.get_params(ctx)
    assert [p.opts for p in params[:2]] == [["-v", "--verbose"], ["-q", "--quiet"]]
    assert params[2:] == [group.get_help_option(ctx)]
    leaves = dict(leaf_commands())
    assert leaves["pointings"] is pointings_flags and {"pointings plan", "pointings select", "pointings before"} <= set(leaves)


def test_coordinates_and_files_of_the_subcommands_are_the_shared_types():
    from perscli.cli import options

    types = {"ra": options.RA_TYPE, "dec": options.DEC_TYPE, "pa": options.PA_TYPE, "start": options.MJD_TYPE,
             "after": options.MJD_TYPE}
    for command in pointings.commands.values():
        for p in command.params:
            if p.name in types:
                assert p.type is types[p.name], (command.name, p.name)
            if p.name in ("schedule", "catalog", "output"):
                assert isinstance(p.type, click.Path), (command.name, p.name)


# -- the settings: one home for each default --------------------------------------------------------

def test_the_click_defaults_are_the_dataclasses():
    plan, select = PlanOptions(), SelectOptions()
    ctx = click.Context(pointings.commands["plan"])
    for command in (pointings.commands["plan"], pointings_flags):
        opts = _options(command)
        assert opts["--dither"].get_default(ctx) == plan.dither
        assert opts["--exptime"].get_default(ctx) == plan.exptime
        assert opts["--gap"].get_default(ctx) == plan.gap
        assert opts["--seed"].get_default(ctx) == plan.seed
        assert opts["--sca"].get_default(ctx) == plan.sca == select.sca
    # and the help shows them
    text = " ".join(invoke("pointings", "plan", "--help").stdout.split())
    assert f"[default: {plan.dither}; 0<=x<=3600]" in text and f"[default: {plan.exptime}; x>0]" in text


def test_the_library_defaults_are_the_dataclasses():
    import inspect

    from perscli.scene.dithers import plan_dithers

    plan = PlanOptions()
    defaults = {k: v.default for k, v in inspect.signature(plan_dithers).parameters.items()}
    for field in ("dither", "filter", "start", "exptime", "gap", "pa", "sca", "seed"):
        assert defaults[field] == getattr(plan, field), field


def test_settings_are_frozen_and_keyword_only():
    with pytest.raises(dataclasses.FrozenInstanceError):
        PlanOptions().dither = 3.0
    with pytest.raises(TypeError):
        SelectOptions("J129")
    assert dataclasses.replace(PlanOptions(), sca=7).sca == 7


def test_library_calls_take_the_settings(tmp_path):
    from perscli.scene.pointings import plan_dithers_file, read_pointings, select_covering_file

    out = str(tmp_path / "plan.fits")
    chosen = plan_dithers_file(out, RA, DEC, 3, PlanOptions(dither=0.0, filter="y106", sca=2, seed=4))
    assert read_pointings(out) == chosen and {p.filter for p in chosen} == {"Y106"} and chosen[0].sca == 2
    assert all(p.ra == pytest.approx(RA, abs=1e-12) for p in chosen)
    with fits.open(out) as hdul:
        assert hdul["POINTINGS"].header["SEED"] == 4 and hdul["POINTINGS"].header["PTDITHER"] == 0.0
    schedule = schedule_file(tmp_path / "s.fits")
    out = str(tmp_path / "sel.fits")
    chosen = select_covering_file(out, schedule, RA, DEC, 1.0, SelectOptions(filter="J129", limit=3))
    assert [p.expid for p in chosen] == [0, 2, 3]
    # without settings: the defaults (any filter, no limit)
    assert len(select_covering_file(str(tmp_path / "all.fits"), schedule, RA, DEC, 1.0)) == 8
    assert np.all(fits.getdata(tmp_path / "all.fits", "POINTINGS")["sca"] == 0)


def test_the_command_line_does_not_import_numpy():
    """perscli --help, perscli pointings --help (and every completion) stay fast: the settings are read only
    when a subcommand needs a default."""
    code = ("import sys\n"
            "from click.testing import CliRunner\n"
            "from perscli.cli.main import cli\n"
            "for args in (['--help'], ['pointings', '--help'], ['man', '-h'], ['completion', 'bash']):\n"
            "    assert CliRunner().invoke(cli, args).exit_code == 0, args\n"
            "print('numpy' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


# -- man pages and completion ---------------------------------------------------------------------

def test_man_shows_a_subcommands_page():
    from perscli.cli.manpages import render_all

    result = invoke("man", "pointings", "plan", "--troff")
    assert result.exit_code == 0 and result.stdout == render_all(cli)["perscli-pointings-plan.1"]
    assert "\\-\\-dither" in result.stdout and "perscli\\-pointings" in result.stdout.split(".SH SEE ALSO")[1]
    result = invoke("man", "pointings", "plna")
    assert result.exit_code == 2 and "'plna' is not a subcommand of perscli pointings; did you mean 'plan'?" in \
        result.stderr


def test_completion_offers_the_subcommands():
    from click.shell_completion import ShellComplete

    def completions(args, incomplete):
        comp = ShellComplete(cli, {}, "perscli", "_PERSCLI_COMPLETE")
        return [item.value for item in comp.get_completions(args, incomplete)]

    assert completions(["pointings"], "") == ["before", "plan", "select"]
    assert completions(["pointings", "plan"], "--di") == ["--dither"]
    assert completions(["man", "pointings"], "p") == ["plan"]
    # the flag form still completes its options
    assert completions(["pointings", "--plan"], "--fo") == ["--footprints"]
