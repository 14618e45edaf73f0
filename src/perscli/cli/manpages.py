"""Generate man pages (troff) from the click help: ``python -m perscli.cli.manpages man``.

One page for the group (perscli.1) and one per command (perscli-NAME.1).
The text is click's own help, so the pages cannot drift from ``--help``;
tests/test_manpages.py checks that the committed pages are current.
"""

from __future__ import annotations

import os
import sys

import click

from .. import __version__


def _escape(text: str) -> str:
    text = text.replace("\\", "\\e")
    lines = []
    for line in text.splitlines():
        # a leading dot or quote would be read as a troff request
        if line.startswith((".", "'")):
            line = "\\&" + line
        lines.append(line.replace("-", "\\-"))
    return "\n".join(lines)


def _paragraphs(help_text: str) -> str:
    """click help text to troff: paragraphs, with \\b blocks kept verbatim."""
    out = []
    blocks = help_text.strip().split("\n\n")
    for block in blocks:
        lines = block.splitlines()
        if lines and lines[0].strip() == "\b":
            out.append(".PP\n.nf\n" + _escape("\n".join(lines[1:])) + "\n.fi")
        else:
            out.append(".PP\n" + _escape(" ".join(line.strip() for line in lines)))
    return "\n".join(out)


def render_page(command: click.Command, name: str, parent: click.Context | None = None) -> str:
    """The man page of ``command`` as troff text."""
    ctx = click.Context(command, info_name=name, parent=parent, **command.context_settings)
    usage = " ".join(command.collect_usage_pieces(ctx))
    title = name.replace(" ", "-").upper()
    short = command.get_short_help_str(limit=200)
    parts = [
        f'.TH "{title}" "1" "" "perscli {__version__}" "perscli manual"',
        ".SH NAME",
        f"{_escape(name.replace(' ', '-'))} \\- {_escape(short)}",
        ".SH SYNOPSIS",
        f".B {_escape(name)}\n{_escape(usage)}",
        ".SH DESCRIPTION",
        _paragraphs(command.help or ""),
    ]
    # command.params, not get_params(): click caches the help option on the command with the
    # names of whichever context asked first (a test invoking the command alone, say)
    options = [p.get_help_record(ctx) for p in command.params if isinstance(p, click.Option)]
    options = [rec for rec in options if rec]
    options.append((", ".join(ctx.help_option_names), "Show this message and exit."))
    if options:
        parts.append(".SH OPTIONS")
        for flags, text in options:
            parts.append(f".TP\n\\fB{_escape(flags)}\\fR\n{_escape(text)}")
    if isinstance(command, click.Group):
        parts.append(".SH COMMANDS")
        for sub in command.list_commands(ctx):
            cmd = command.get_command(ctx, sub)
            parts.append(f".TP\n\\fB{_escape(sub)}\\fR\n{_escape(cmd.get_short_help_str(limit=200))}\n"
                         f"See \\fBperscli\\-{_escape(sub)}\\fR(1).")
    else:
        parts.append(".SH SEE ALSO\n\\fBperscli\\fR(1)")
    return "\n".join(parts) + "\n"


def render_all() -> dict:
    """{file name: troff text} for the group and every command."""
    from .main import cli

    pages = {"perscli.1": render_page(cli, "perscli")}
    root = click.Context(cli, info_name="perscli", **cli.context_settings)
    for sub in cli.list_commands(root):
        pages[f"perscli-{sub}.1"] = render_page(cli.get_command(root, sub), f"perscli {sub}", parent=root)
    return pages


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    folder = argv[0] if argv else "man"
    os.makedirs(folder, exist_ok=True)
    for fname, text in render_all().items():
        with open(os.path.join(folder, fname), "w") as fh:
            fh.write(text)
        print(os.path.join(folder, fname))


if __name__ == "__main__":
    main()
