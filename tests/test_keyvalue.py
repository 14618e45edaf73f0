"""One reading of KEY=VALUE items (perscli.io.config), and one click callback for every --set."""

import click
import pytest

from perscli import PerscliError
from perscli.cli.options import key_values
from perscli.io.config import DETECTOR_ITEM, STUDY_ITEM, parse_value, split_key_value

from fits_factory import commands


def test_split_at_the_first_equals_sign_both_sides_stripped():
    assert split_key_value(" persistence.gamma = 1.1 ") == ("persistence.gamma", "1.1")
    assert split_key_value("render.set=[persistence.floor=1e4]") == ("render.set", "[persistence.floor=1e4]")
    assert split_key_value("name=") == ("name", "")


@pytest.mark.parametrize("text, form, line", [
    ("ipc", DETECTOR_ITEM, "--set 'ipc' is not EFFECT.KEY=VALUE or EFFECT=on|off"),
    ("foo", STUDY_ITEM, "override 'foo' is not KEY=VALUE (e.g. exposures.count=5)"),
    (3, STUDY_ITEM, "override 3 is not KEY=VALUE (e.g. exposures.count=5)"),
])
def test_an_item_without_equals_sign_is_one_line_naming_it(text, form, line):
    with pytest.raises(PerscliError) as err:
        split_key_value(text, **form)
    assert str(err.value) == line


def test_values_are_typed_as_yaml():
    assert parse_value("5") == 5 and parse_value("1.5") == 1.5 and parse_value("true") is True
    assert parse_value("[stars, all]") == ["stars", "all"] and parse_value("well") == "well"
    assert parse_value("") is None and parse_value("", blank="") == ""
    assert parse_value("[") == "["                   # not YAML: the text, for the schema to refuse
    with pytest.raises(PerscliError, match=r"^override 'name=\[': not a YAML value: "):
        parse_value("[", strict="name=[")


def test_the_callback_passes_items_on_or_refuses_them():
    cmd = click.Command("x", params=[click.Option(["--set", "settings"], multiple=True)])
    ctx = click.Context(cmd)
    param = cmd.params[0]
    assert key_values(STUDY_ITEM)(ctx, param, ("a.b=1",)) == ("a.b=1",)
    with pytest.raises(click.ClickException) as err:
        key_values(STUDY_ITEM)(ctx, param, ("a.b",))
    assert err.value.exit_code == 1 and err.value.message == "override 'a.b' is not KEY=VALUE (e.g. exposures.count=5)"
    one = key_values(effect="persistence")
    assert one(ctx, param, ("persistence.gamma=1.1", "persistence.A = 0.05")) == ("gamma=1.1", "A=0.05")
    for text, needle in (("gamma=1.1", "give persistence.KEY=VALUE"), ("ipc.alpha=0.02", "persistence only"),
                         ("persistence.gamma", "give persistence.KEY=VALUE")):
        with pytest.raises(click.BadParameter, match=needle):
            one(ctx, param, (text,))


def test_every_set_option_reads_its_items_with_the_one_callback():
    setting = [c for c in commands().values() if any("--set" in p.opts for p in c.params)]
    assert {c.name for c in setting} == {"render", "study", "apply-persistence"}
    for command in setting:
        option = next(p for p in command.params if "--set" in p.opts)
        assert option.callback.__qualname__ == "key_values.<locals>.callback", command.name
