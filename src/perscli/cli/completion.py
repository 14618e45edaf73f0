"""``perscli completion``: the shell script that completes perscli's commands, options and file names."""

from __future__ import annotations

import os

import click
from click.shell_completion import get_completion_class

from ..io.output import atomic_output, check_output, send_to_stdout
from .helpers import FILE, PerscliCommand, report_errors
from .options import overwrite_opt, verbosity_opts

SHELLS = ("bash", "zsh", "fish")
#: the variable through which the shell asks the perscli script for completions (click's convention)
COMPLETE_VAR = "_PERSCLI_COMPLETE"


def completion_script(group: click.Group, shell: str) -> str:
    """The completion script of the ``perscli`` console script for ``shell`` (bash, zsh or fish).

    Parameters
    ----------
    group : click.Group
        The ``perscli`` group (:data:`perscli.cli.main.cli`); the command
        finds it as the root of its context, so that this module need not
        import the group that imports it.
    shell : {'bash', 'zsh', 'fish'}
    """
    return get_completion_class(shell)(group, {}, "perscli", COMPLETE_VAR).source()


@click.command("completion", cls=PerscliCommand,
               short_help="Print the script that makes the shell complete perscli's words.")
@click.argument("shell", type=click.Choice(SHELLS), metavar="bash|zsh|fish")
@click.option("-o", "--output", "dest", type=FILE, metavar="PATH", default="-", show_default=True,
              help="Write the script to PATH (its folder is created if missing), or '-' for standard output.")
@overwrite_opt
@verbosity_opts
@report_errors
def completion(shell, dest, overwrite):
    """The completion script for bash, zsh or fish.

    With it, TAB completes commands, options, their choices (--mode a<TAB>)
    and file names (inputs, outputs, -o FOLDER).  The script asks perscli
    itself (it runs perscli with _PERSCLI_COMPLETE set), so it follows the
    installed version; bash needs version 4.4 or newer.

    bash: eval the script in ~/.bashrc, or write it where bash-completion
    looks (first example, then the second).  zsh: write it as _perscli into
    a folder of $fpath (e.g. ~/.zfunc, with fpath+=~/.zfunc before compinit
    in ~/.zshrc).  fish: write it into ~/.config/fish/completions.

    \b
    Examples:
      eval "$(perscli completion bash)"
      perscli completion bash -o ~/.local/share/bash-completion/completions/perscli
      perscli completion zsh -o ~/.zfunc/_perscli
      perscli completion fish -o ~/.config/fish/completions/perscli.fish
    """
    script = completion_script(click.get_current_context().find_root().command, shell)
    if not script.endswith("\n"):
        script += "\n"
    if dest == "-":
        # text, not FITS: a terminal is a fine place for it
        send_to_stdout(script.encode())
        return
    # the places shells read these from (~/.zfunc, bash-completion's folder) often do not exist yet
    os.makedirs(os.path.dirname(os.path.abspath(dest)), exist_ok=True)
    check_output(dest, overwrite=overwrite)
    with atomic_output(dest, overwrite=overwrite) as fh:
        fh.write(script.encode())
