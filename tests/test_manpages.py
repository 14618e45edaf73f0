"""The committed man pages are the current click help (regenerate with `make man`)."""

from pathlib import Path

from perscli.cli.main import cli
from perscli.cli.manpages import render_all

MAN = Path(__file__).resolve().parents[1] / "man"


def test_one_page_per_command_and_all_current():
    pages = render_all()
    assert set(pages) == {"perscli.1"} | {f"perscli-{name}.1" for name in cli.commands}
    for name, text in pages.items():
        path = MAN / name
        assert path.exists(), f"man/{name} missing: run `make man`"
        assert path.read_text() == text, f"man/{name} is out of date: run `make man`"
    stale = {p.name for p in MAN.glob("*.1")} - set(pages)
    assert not stale, f"pages for commands that no longer exist: {stale}"


def test_pages_carry_the_options_and_examples():
    page = render_all()["perscli-apply-persistence.1"]
    for text in ("\\-\\-time\\-model", "\\-\\-max\\-previous", "\\-\\-combine", "Examples:", ".SH SYNOPSIS"):
        assert text in page
