"""Manual pages from the click help: the ``perscli man`` command (``make man`` runs ``perscli man --all``).

One page for the group (perscli.1), one per command (perscli-NAME.1) and one
per subcommand of a command that has them (perscli-NAME-SUB.1, e.g.
perscli-pointings-plan.1).
The text is click's own help, so the pages cannot drift from ``--help``:
``perscli man`` builds them from the commands it runs with, and
tests/test_manpages.py checks that the pages committed in man/ (installed
into share/man/man1 of the environment) are current.

A page is built once (:func:`page_parts`) and written two ways: troff
(:func:`to_troff`, what man(1) reads) and plain text (:func:`to_text`, what
a pipeline or a system without man(1) gets).
"""

from __future__ import annotations

import difflib
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap

import click
from click.shell_completion import CompletionItem

from .. import PerscliError, __version__
from ..io.output import atomic_output, check_output, send_to_stdout
from .helpers import FILE, PerscliCommand, report_errors
from .options import overwrite_opt, verbosity_opts


# -- pages ---------------------------------------------------------------------------------------

def page_parts(command: click.Command, name: str, parent: click.Context | None = None) -> dict:
    """What a page says, before it is typeset.

    Returns
    -------
    dict
        name ('perscli render'), short (one-line summary), usage, description
        (list of ('para' | 'verbatim', text)), options (list of (flags,
        text)), commands (list of (name, summary); a group's only).
    """
    ctx = click.Context(command, info_name=name, parent=parent, **command.context_settings)
    description = []
    for block in (command.help or "").strip().split("\n\n"):
        lines = block.splitlines()
        if lines and lines[0].strip() == "\b":
            description.append(("verbatim", "\n".join(lines[1:])))
        else:
            description.append(("para", " ".join(line.strip() for line in lines)))
    # command.params, not get_params(): click caches the help option on the command with the
    # names of whichever context asked first (a test invoking the command alone, say)
    params = command.params
    options = [p.get_help_record(ctx) for p in params if isinstance(p, click.Option)]
    options = [rec for rec in options if rec]
    options.append((", ".join(ctx.help_option_names), "Show this message and exit."))
    commands = None
    if isinstance(command, click.Group):
        commands = [(sub, command.get_command(ctx, sub).get_short_help_str(limit=200))
                    for sub in command.list_commands(ctx)]
    return {"name": name, "short": command.get_short_help_str(limit=200),
            "usage": " ".join(command.collect_usage_pieces(ctx)), "description": description,
            "options": options, "commands": commands}


def _escape(text: str) -> str:
    text = text.replace("\\", "\\e")
    lines = []
    for line in text.splitlines():
        # a leading dot or quote would be read as a troff request
        if line.startswith((".", "'")):
            line = "\\&" + line
        lines.append(line.replace("-", "\\-"))
    return "\n".join(lines)


def _page_name(name: str) -> str:
    """The page of a command line: 'perscli pointings plan' -> 'perscli-pointings-plan'."""
    return name.replace(" ", "-")


def _parent_page(name: str) -> str:
    """The page a command's page refers to: its group's ('perscli' for a command, 'perscli-pointings' for a
    subcommand of pointings)."""
    return _page_name(name.rsplit(" ", 1)[0])


def to_troff(parts: dict) -> str:
    """A page as troff (the man(7) macros)."""
    name = parts["name"]
    out = [
        f'.TH "{name.replace(" ", "-").upper()}" "1" "" "perscli {__version__}" "perscli manual"',
        ".SH NAME",
        f"{_escape(name.replace(' ', '-'))} \\- {_escape(parts['short'])}",
        ".SH SYNOPSIS",
        f".B {_escape(name)}\n{_escape(parts['usage'])}",
        ".SH DESCRIPTION",
    ]
    for kind, text in parts["description"]:
        out.append(".PP\n.nf\n" + _escape(text) + "\n.fi" if kind == "verbatim" else ".PP\n" + _escape(text))
    out.append(".SH OPTIONS")
    for flags, text in parts["options"]:
        out.append(f".TP\n\\fB{_escape(flags)}\\fR\n{_escape(text)}")
    if parts["commands"] is not None:
        out.append(".SH COMMANDS")
        for sub, short in parts["commands"]:
            page = _escape(f"{_page_name(name)}-{sub}")
            out.append(f".TP\n\\fB{_escape(sub)}\\fR\n{_escape(short)}\nSee \\fB{page}\\fR(1).")
    else:
        out.append(f".SH SEE ALSO\n\\fB{_escape(_parent_page(name))}\\fR(1)")
    return "\n".join(out) + "\n"


def to_text(parts: dict, width: int = 80) -> str:
    """A page as plain text, laid out as man(1) shows it (headings, then text indented by 7).

    Parameters
    ----------
    parts : dict
        From :func:`page_parts`.
    width : int
        Columns to fill (at least 40); verbatim blocks (Examples) are kept
        as they are, even when longer.
    """
    width = max(width, 40)
    body, item = " " * 7, " " * 14

    def fill(text, indent=body, first=None):
        return textwrap.fill(text, width, initial_indent=first if first is not None else indent,
                             subsequent_indent=indent, break_long_words=False, break_on_hyphens=False)

    name = parts["name"]
    title = f"{name.replace(' ', '-').upper()}(1)"
    middle = "perscli manual"
    gap = max(1, width - 2 * len(title) - len(middle))
    out = [title + " " * (gap // 2) + middle + " " * (gap - gap // 2) + title, ""]
    out += ["NAME", fill(f"{name.replace(' ', '-')} - {parts['short']}"), ""]
    out += ["SYNOPSIS", fill(f"{name} {parts['usage']}", body + " " * (len(name) + 1), first=body), ""]
    out.append("DESCRIPTION")
    for kind, text in parts["description"]:
        if kind == "verbatim":
            out += [body + line if line.strip() else "" for line in textwrap.dedent(text).splitlines()]
        elif text:
            out.append(fill(text))
        out.append("")
    out.append("OPTIONS")
    for flags, text in parts["options"]:
        out += [fill(flags), fill(text, item), ""]
    if parts["commands"] is not None:
        out.append("COMMANDS")
        for sub, short in parts["commands"]:
            out += [fill(sub), fill(f"{short} See {_page_name(name)}-{sub}(1).", item), ""]
    else:
        out += ["SEE ALSO", body + f"{_parent_page(name)}(1)", ""]
    footer = f"perscli {__version__}"
    out.append(footer + " " * max(1, width - len(footer) - len(title)) + title)
    return "\n".join(out) + "\n"


def render_page(command: click.Command, name: str, parent: click.Context | None = None) -> str:
    """The man page of ``command`` as troff text."""
    return to_troff(page_parts(command, name, parent))


def _pages(cli: click.Group):
    """{file name: (command, name, parent context)} for the group, every command and every subcommand."""
    root = click.Context(cli, info_name="perscli", **cli.context_settings)
    pages = {"perscli.1": (cli, "perscli", None)}
    for sub in cli.list_commands(root):
        command = cli.get_command(root, sub)
        pages[f"perscli-{sub}.1"] = (command, f"perscli {sub}", root)
        if isinstance(command, click.Group):
            ctx = click.Context(command, info_name=sub, parent=root)
            for subsub in command.list_commands(ctx):
                pages[f"perscli-{sub}-{subsub}.1"] = (command.get_command(ctx, subsub), f"perscli {sub} {subsub}",
                                                      ctx)
    return pages


def render_all(cli: click.Group) -> dict:
    """{file name: troff text} for the group ``cli`` (:data:`perscli.cli.main.cli`), every command and every
    subcommand."""
    return {fname: render_page(*spec) for fname, spec in _pages(cli).items()}


def write_pages(folder: str, cli: click.Group, *, overwrite: bool = False) -> list:
    """Write every page (troff) into ``folder``, created if missing.

    Each page is written atomically; an existing page is an error without
    ``overwrite``, found before any page is written.

    Parameters
    ----------
    folder : str
        e.g. ``man`` (the repository's copy) or ``~/.local/share/man/man1``.
    cli : click.Group
        The ``perscli`` group (:data:`perscli.cli.main.cli`).
    overwrite : bool
        Replace pages already there.

    Returns
    -------
    list of str
        The paths written.

    Raises
    ------
    perscli.PerscliError
        ``folder`` is a file, or a page exists and ``overwrite`` is false.
    """
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise PerscliError(f"{folder}: is not a folder; give the folder that receives the pages")
    pages = render_all(cli)
    paths = [os.path.join(folder, fname) for fname in pages]
    existing = [path for path in paths if os.path.exists(path)]
    if existing and not overwrite:
        raise PerscliError(f"{existing[0]}: already exists; use --overwrite to replace the pages")
    os.makedirs(folder, exist_ok=True)
    for path, text in zip(paths, pages.values()):
        with atomic_output(path, overwrite=True) as fh:
            fh.write(text.encode())
    return paths


# -- perscli man ---------------------------------------------------------------------------------

def _command_names(ctx, param, incomplete):
    """Complete COMMAND, then SUBCOMMAND when COMMAND has them (perscli man pointings <TAB>)."""
    group = ctx.find_root().command
    for word in ctx.params.get("command_name") or ():
        group = group.get_command(ctx, word) if isinstance(group, click.Group) else None
    if not isinstance(group, click.Group):
        return []
    return [CompletionItem(name) for name in group.list_commands(ctx) if name.startswith(incomplete)]


def _known_command(ctx, param, value):
    """COMMAND [SUBCOMMAND]: a perscli command, and one of its subcommands when it has them."""
    cli = ctx.find_root().command
    group, path = cli, "perscli"
    for word in value or ():
        if not isinstance(group, click.Group):
            raise click.BadParameter(f"'{path}' has no subcommands: give only '{path.split(' ', 1)[1]}'", ctx,
                                     param, param_hint="COMMAND")
        names = group.list_commands(ctx)
        if word not in names:
            close = difflib.get_close_matches(word, names, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else f": one of {', '.join(sorted(names))}"
            what = "a perscli command" if group is cli else f"a subcommand of {path}"
            raise click.BadParameter(f"'{word}' is not {what}{hint}", ctx, param, param_hint="COMMAND")
        group, path = group.get_command(ctx, word), f"{path} {word}"
    return tuple(value or ())


def _stdout_is_terminal() -> bool:
    return sys.stdout.isatty()


def _man_width() -> int:
    # man(1)'s own variable; a fixed 80 otherwise, so that the text in a pipe does not depend on the window
    try:
        return int(os.environ.get("MANWIDTH", "80"))
    except ValueError:
        return 80


def show_with_man(troff: str) -> bool:
    """Show a page through ``man -l`` (its pager, its formatting); False when man(1) could not."""
    program = shutil.which("man")
    if program is None:
        return False
    fd, path = tempfile.mkstemp(prefix="perscli-", suffix=".1")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(troff)
        try:
            return subprocess.run([program, "-l", path]).returncode == 0
        except OSError:
            return False
    finally:
        os.unlink(path)


@click.command("man", cls=PerscliCommand,
               short_help="Show the manual page of perscli or of one of its commands.")
@click.argument("command_name", metavar="[COMMAND [SUBCOMMAND]]", nargs=-1, callback=_known_command,
                shell_complete=_command_names)
@click.option("--troff", is_flag=True, default=False,
              help="Print the troff source (what man(1) reads) instead of showing the page.")
@click.option("--all", "all_pages", is_flag=True, default=False,
              help="Every page: perscli.1 and perscli-COMMAND.1 for each command (with -o FOLDER).")
@click.option("-o", "--output", "dest", type=FILE, metavar="PATH", default=None,
              help="Write the troff source to PATH instead of showing the page; with --all, PATH is a folder "
                   "(created if missing) that receives every page, e.g. ~/.local/share/man/man1, where man(1) "
                   "finds them.")
@overwrite_opt
@verbosity_opts
@report_errors
def man(command_name, troff, all_pages, dest, overwrite):
    """The manual page of perscli, or of COMMAND (e.g. render), or of its SUBCOMMAND (pointings plan).

    The pages are made from the help of the commands installed, so they
    always describe the perscli that runs.  On a terminal the page is shown
    through man(1) and its pager; in a pipe, or without man(1), it is
    printed as plain text (80 columns, or MANWIDTH).  --troff prints the
    troff source instead, and -o writes it to a file.

    The pages are also installed with perscli into share/man/man1 of its
    environment, where man(1) finds them when the environment's bin is on
    PATH (man perscli-render); --all -o FOLDER writes them anywhere else.

    \b
    Examples:
      perscli man render
      perscli man render | grep -A2 -e --previous
      perscli man pointings plan | grep -A1 -e --dither
      perscli man apply-persistence -o perscli-apply-persistence.1
      perscli man --all -o ~/.local/share/man/man1
    """
    # the group this command runs under: manpages is one of its commands, and does not import it
    cli = click.get_current_context().find_root().command

    if all_pages:
        if command_name:
            raise click.UsageError("--all writes every page: give no COMMAND with it")
        if dest is None or dest == "-":
            raise click.UsageError("--all needs -o FOLDER, e.g. -o ~/.local/share/man/man1")
        write_pages(dest, cli, overwrite=overwrite)
        return
    if not command_name:
        parts = page_parts(cli, "perscli")
    else:
        # the page as installed (the same contexts as render_all's)
        parts = page_parts(*_pages(cli)[f"perscli-{'-'.join(command_name)}.1"])
    if dest is not None and dest != "-":
        check_output(dest, overwrite=overwrite)
        with atomic_output(dest, overwrite=overwrite) as fh:
            fh.write(to_troff(parts).encode())
    elif troff or dest == "-":
        send_to_stdout(to_troff(parts).encode())
    elif _stdout_is_terminal():
        if not show_with_man(to_troff(parts)):
            click.echo_via_pager(to_text(parts, _man_width()))
    else:
        send_to_stdout(to_text(parts, _man_width()).encode())

