"""A command option is one field of its settings dataclass (perscli.settings.setting): the click option is made
from it (perscli.cli.options.settings_options), with its default, type, range and help."""

import dataclasses
import pathlib
import re

import click
import pytest

from perscli import PerscliError

from fits_factory import command_named, run, usage_error
from perscli.detector.settings import ApplyOptions
from perscli.diagnose.settings import DiagnoseOptions
from perscli.measure.settings import MeasureOptions
from perscli.render.settings import RenderOptions
from perscli.scene.settings import CatalogOptions, PlanOptions, SelectOptions
from perscli.settings import OptionSpec, default_text, option_fields, setting
from perscli.stats.settings import BudgetOptions, CorrelateOptions
from perscli.study.settings import StudyOptions

#: each settings dataclass and the commands whose options it makes
OWNERS = {CorrelateOptions: ["correlate"], BudgetOptions: ["budget"], MeasureOptions: ["measure"],
          ApplyOptions: ["apply-persistence"], CatalogOptions: ["catalog"], DiagnoseOptions: ["diagnose"],
          RenderOptions: ["render"], PlanOptions: ["pointings plan"], SelectOptions: ["pointings select"],
          StudyOptions: ["study"]}

#: options that show a settings default without being made from the field, and why
DERIVED = {
    "correlate.py": {"D.flagged": "--keep-flagged is a flag for flagged='keep', not the field's own values"},
    "render.py": {"D.persistence_source": "its values are checked against the persistence parameters' table"},
}


@pytest.mark.parametrize("cls", list(OWNERS), ids=lambda c: c.__name__)
def test_every_option_field_is_its_commands_option_with_the_fields_default(cls):
    fields = option_fields(cls)
    assert fields, f"{cls.__name__} declares no option"
    for command in OWNERS[cls]:
        params = {p.name: p for p in command_named(command).params}
        for name, (default, spec) in fields.items():
            if command == "pointings plan" and name == "sca":
                continue        # plan's --sca is SelectOptions' (the same detector field)
            assert name in params, f"{command}: no option for {cls.__name__}.{name}"
            param = params[name]
            assert (spec.flag or "--" + name.replace("_", "-")) in param.opts
            want = default_text(default) if spec.kind == "numbers" else default
            assert param.default == want, f"{command} {param.opts}: default {param.default!r}, field {want!r}"


def test_an_options_range_and_choices_come_from_its_field():
    # budget --sigma: lo=0 in BudgetOptions.n_sigma; correlate --sep-units: the field's choices
    assert "--sigma" in usage_error(run("budget", "--sigma", "-1", "-o", "x.fits", code=2), "perscli budget")
    assert "--sep-units" in usage_error(run("correlate", "a.fits", "--sep-units", "parsec", "-o", "x.fits", code=2),
                                        "perscli correlate")
    param = {p.name: p for p in command_named("measure").params}["blend_radius"]
    assert isinstance(param.type, click.FloatRange) and param.type.min == 0
    assert run("correlate", "--help").stdout.count("--theta-bins E0,E1,...") == 1


def test_no_command_restates_a_settings_default():
    """A click option never writes ``default=D.x`` itself: it is made from the field, or listed in DERIVED."""
    cli = pathlib.Path(__file__).resolve().parents[1] / "src" / "perscli" / "cli"
    found = []
    for path in sorted(cli.glob("*.py")):
        for m in re.finditer(r"default=([A-Z]\.[a-z_]+)", path.read_text()):
            if m.group(1) not in DERIVED.get(path.name, {}):
                found.append(f"{path.name}: default={m.group(1)}")
    assert not found, "options restating a settings default (declare the field with perscli.settings.setting): " \
                      + "; ".join(found)


def test_a_setting_declares_a_known_kind_of_value():
    with pytest.raises(ValueError, match="option kind"):
        setting(1, "colour", "no such kind")
    with pytest.raises(ValueError, match="choices"):
        OptionSpec("choice", "a choice of nothing")
    field = setting(2.0, "float", "help", lo=0)
    # the range is an effect parameter's (one description of a range): Param checks a value against it
    assert field.default == 2.0 and field.metadata["option"].values.lo == 0
    with pytest.raises(PerscliError, match="must not be negative"):
        field.metadata["option"].values.check("budget", -1.0, "--sigma")
    assert dataclasses.make_dataclass("X", [("a", float, field)])().a == 2.0


def test_a_text_setting_is_checked_by_the_library_once(tmp_path):
    """--scheduler takes serial, local or an address: the library's check (study.settings.check_scheduler)
    runs as the option's callback, and its message is the usage error's."""
    from perscli.study.settings import check_scheduler
    for good in ("serial", "local", "tcp://10.0.0.1:8786", "node17:8786"):
        assert check_scheduler(good) == good
    with pytest.raises(PerscliError, match="Dask scheduler address"):
        check_scheduler("tcp:/nowhere")
    out = tmp_path / "never_made"
    err = usage_error(run("study", "--preset", "ci", "-o", str(out), "--scheduler", "tcp:/nowhere", code=2),
                      "perscli study")
    assert "--scheduler" in err and "is not serial, local or a Dask scheduler address" in err
    assert not out.exists()
