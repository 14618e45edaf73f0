"""The committed man pages are the current click help (regenerate with `make man`), installed with the package."""

from pathlib import Path

import click
import pytest

from perscli.cli.main import cli
from perscli.cli.manpages import render_all

from fits_factory import commands

MAN = Path(__file__).resolve().parents[1] / "man"


def _commands():
    """(name, command) of every command and subcommand: ('render', ...), ('pointings plan', ...)."""
    for name, command in commands().items():
        yield name, command
        for sub, subcommand in (commands(command) if isinstance(command, click.Group) else {}).items():
            yield f"{name} {sub}", subcommand


def test_one_page_per_command_and_all_current():
    pages = render_all(cli)
    assert set(pages) == {"perscli.1"} | {f"perscli-{name.replace(' ', '-')}.1" for name, _ in _commands()}
    assert {"perscli-pointings-plan.1", "perscli-pointings-select.1", "perscli-pointings-before.1"} <= set(pages)
    for name, text in pages.items():
        path = MAN / name
        assert path.exists(), f"man/{name} missing: run `make man`"
        assert path.read_text() == text, f"man/{name} is out of date: run `make man`"
    stale = {p.name for p in MAN.glob("*.1")} - set(pages)
    assert not stale, f"pages for commands that no longer exist: {stale}"


def test_pages_carry_the_options_and_examples():
    page = render_all(cli)["perscli-apply-persistence.1"]
    for text in ("\\-\\-time\\-model", "\\-\\-max\\-previous", "\\-\\-combine", "Examples:", ".SH SYNOPSIS"):
        assert text in page


def test_a_subcommands_page_and_its_groups():
    pages = render_all(cli)
    plan = pages["perscli-pointings-plan.1"]
    assert plan.startswith('.TH "PERSCLI-POINTINGS-PLAN" "1"')
    for text in ("\\-\\-dither", "\\-\\-exptime", "\\-\\-footprints", "Examples:",
                 ".SH SEE ALSO\n\\fBperscli\\-pointings\\fR(1)"):
        assert text in plan, text
    # the group's page: its commands, each naming its page; not the deprecated flag form's options
    group = pages["perscli-pointings.1"]
    assert "See \\fBperscli\\-pointings\\-plan\\fR(1)." in group and ".SH COMMANDS" in group
    assert "\\-\\-dither" not in group.split(".SH OPTIONS")[1]


def test_the_generator_writes_every_page(tmp_path):
    from perscli.cli.manpages import write_pages

    paths = write_pages(str(tmp_path / "man"), cli, overwrite=True)
    pages = render_all(cli)
    assert sorted(p.name for p in (tmp_path / "man").iterdir()) == sorted(pages)
    assert all((tmp_path / "man" / name).read_text() == text for name, text in pages.items())
    assert paths == [str(tmp_path / "man" / name) for name in pages]
    write_pages(str(tmp_path / "man"), cli, overwrite=True)      # regenerating replaces them


def test_plain_text_and_troff_are_the_same_page():
    from perscli.cli.manpages import page_parts, to_text

    root = click.Context(cli, info_name="perscli", **cli.context_settings)
    for name, command in _commands():
        parts = page_parts(command, f"perscli {name}", root)
        text = " ".join(to_text(parts).split())
        for flags, help_text in parts["options"]:
            assert flags in text and " ".join(help_text.split()) in text, (name, flags)
        for kind, block in parts["description"]:
            assert " ".join(block.split()) in text, (name, block[:40])


def test_the_pages_are_installed_with_the_package():
    tomllib = pytest.importorskip("tomllib")           # Python 3.11+

    with open(MAN.parent / "pyproject.toml", "rb") as fh:
        project = tomllib.load(fh)
    patterns = project["tool"]["setuptools"]["data-files"]["share/man/man1"]
    installed = {p.name for pattern in patterns for p in MAN.parent.glob(pattern)}
    assert installed == set(render_all(cli))
