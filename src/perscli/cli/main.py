"""The ``perscli`` click group: version, verbosity and the registered commands."""

from __future__ import annotations

import click

from .. import __version__
from .apply_persistence import apply_persistence
from .render import render
from .measure import measure
from .budget import budget
from .correlate import correlate
from .catalog import catalog
from .pointings import pointings
from .diagnose import diagnose
from .study import study
from .manpages import man
from .completion import completion
from .helpers import configure_logging  # noqa: F401  (re-exported: perscli.cli.main.configure_logging)
# every usage error of the group and its commands is one line on stderr: see helpers.show_usage_error
from .helpers import PerscliGroup
from .options import no_checksum_opt


@click.group("perscli", cls=PerscliGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="perscli", message="%(prog)s %(version)s")
@click.option("-v", "--verbose", count=True, help="More messages on stderr (-vv: debug, with tracebacks).")
@click.option("-q", "--quiet", count=True, help="Fewer messages on stderr (errors only; no progress bars).")
@no_checksum_opt
@click.pass_context
def cli(ctx, verbose, quiet):
    """Image persistence in near-infrared detectors, from FITS frames to shear budgets.

    Every command reads and writes FITS; '-' stands for standard input or
    output, so commands compose in shell pipelines.  Exit status: 0 success,
    1 a data or runtime error, 2 a usage error (one line on stderr, e.g.
    "perscli render: error: Missing option '--seed' (see 'perscli render -h')").

    Manual pages: perscli man COMMAND (or perscli man --all -o
    ~/.local/share/man/man1 to install them for man(1)).  Tab completion of
    commands, options and file names: eval "$(perscli completion bash)"
    (zsh, fish: see perscli completion -h).
    """
    ctx.obj = {"verbosity": verbose - quiet}
    configure_logging(verbose - quiet)


cli.add_command(apply_persistence)
cli.add_command(render)
cli.add_command(measure)
cli.add_command(budget)
cli.add_command(correlate)
cli.add_command(catalog)
cli.add_command(pointings)
cli.add_command(diagnose)
cli.add_command(study)
cli.add_command(man)
cli.add_command(completion)


def main():
    """Console-script entry point.

    SIGTERM and SIGHUP end a command cleanly: the stack unwinds (``finally``
    blocks remove temporary outputs, worker processes are ended), one line
    goes to stderr and the exit status is 128 + the signal's number.
    """
    import sys

    from ..executor import Terminated, install_signal_handlers

    install_signal_handlers()
    try:
        cli(prog_name="perscli")
    except Terminated as exc:
        try:
            sys.stderr.write(f"Error: terminated by {exc.signal_name}; no output written\n")
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        sys.exit(exc.code)
