"""The ``perscli`` click group: version, verbosity and the registered commands.

The commands are loaded lazily (click's LazyGroup pattern): :data:`COMMANDS`
names each command's module and short help, and :class:`LazyGroup` imports a
command's module only when that command is used (run, or its help shown);
``perscli --help`` lists every command from the table without importing any
of them.  A new command is a row of :data:`COMMANDS` (tests/test_lazy_cli.py
checks each row's short help against the command's own).

The import rule of ``perscli.cli``: a command module imports at its top only
click, the cli helpers and options (``cli/helpers.py``, ``cli/options.py``) and
the light modules the options are built from (the ``settings.py`` modules,
``perscli.instrument``, ``perscli.io.config``); the library a command calls is
imported inside its body, in one place.  So ``perscli COMMAND --help`` never
waits for numpy, astropy or GalSim (tests/test_lazy_cli.py), while the library
itself imports at the top of its modules (CONTRIBUTING.md).
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
import threading

import click

from .. import PerscliError, __version__
from ..executor import Terminated, install_signal_handlers
from ..io.output import WRITE_ERRNOS, ClosedStdout, GuardedStdout, write_error
from .helpers import configure_logging
# every usage error of the group and its commands is one line on stderr: see helpers.OneLineUsage
from .helpers import PerscliGroup
from .options import no_checksum_opt

#: every command: {name: ("module:attribute" of the command, its short help)}.  The short help is what
#: ``perscli --help`` lists without importing the module: the command's own ``short_help`` (a test holds them equal)
COMMANDS = {
    "apply-persistence": ("perscli.cli.apply_persistence:apply_persistence",
                          "Add, subtract or predict the persistence of earlier exposures."),
    "budget": ("perscli.cli.budget:budget", "Compare a measured xi+ with the Roman additive shear budget."),
    "catalog": ("perscli.cli.catalog:catalog", "Draw a truth catalog of galaxies and stars for a field."),
    "completion": ("perscli.cli.completion:completion",
                   "Print the script that makes the shell complete perscli's words."),
    "correlate": ("perscli.cli.correlate:correlate", "Correlation function xi+/- and statistics of shape changes De."),
    "diagnose": ("perscli.cli.diagnose:diagnose",
                 "Find the detector effect a simulation lacks, fit it, show the gap shrink."),
    "man": ("perscli.cli.manpages:man", "Show the manual page of perscli or of one of its commands."),
    "measure": ("perscli.cli.measure:measure", "Measure galaxy shapes on frames by exponential-profile fits."),
    "pointings": ("perscli.cli.pointings:pointings",
                  "Select exposures of a field from a schedule, or plan dithered ones."),
    "render": ("perscli.cli.render:render", "Draw a Roman SCA exposure of a truth catalogue through a detector model."),
    "study": ("perscli.cli.study:study", "Run a whole persistence study from one YAML description (Dask or serial)."),
}

#: click (8.4+) raises this for an unknown command, with a close name as a suggestion
_NO_SUCH_COMMAND = getattr(click.exceptions, "NoSuchCommand", ())


class LazyGroup(PerscliGroup):
    """A :class:`~perscli.cli.helpers.PerscliGroup` whose commands are imported when first used.

    click's documented LazyGroup: :meth:`list_commands` and
    :meth:`get_command` answer from ``lazy_subcommands``, importing a
    command's module only in :meth:`get_command`; the group's help lists
    the table's short help (:meth:`format_commands`), so that ``--help``
    imports no command.  Commands added with ``add_command`` work as in any
    group.

    Parameters
    ----------
    lazy_subcommands : dict
        {name: ("module:attribute", short help)}, as :data:`COMMANDS`.
    """

    def __init__(self, *args, lazy_subcommands=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy_subcommands = dict(lazy_subcommands or {})

    def list_commands(self, ctx):
        return sorted({*super().list_commands(ctx), *self.lazy_subcommands})

    def get_command(self, ctx, cmd_name):
        if cmd_name not in self.lazy_subcommands:
            return super().get_command(ctx, cmd_name)
        target = self.lazy_subcommands[cmd_name][0]
        module, _, attribute = target.partition(":")
        command = getattr(importlib.import_module(module), attribute)
        if not isinstance(command, click.Command):
            raise TypeError(f"{target} (perscli command {cmd_name!r}) is not a click command")
        return command

    def format_commands(self, ctx, formatter):
        """The Commands section of the help: the table's short help, each command's module left unimported."""
        names = self.list_commands(ctx)
        limit = formatter.width - 6 - max((len(name) for name in names), default=0)   # as click's
        rows = []
        for name in names:
            if name in self.lazy_subcommands:
                rows.append((name, self.lazy_subcommands[name][1]))
                continue
            command = super().get_command(ctx, name)
            if command is not None and not command.hidden:
                rows.append((name, command.get_short_help_str(limit)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def resolve_command(self, ctx, args):
        try:
            return super().resolve_command(ctx, args)
        except _NO_SUCH_COMMAND as exc:
            # click suggests a close name from self.commands, which holds none of the lazy commands
            raise type(exc)(exc.command_name, possibilities=self.list_commands(ctx), ctx=exc.ctx) from None


@click.group("perscli", cls=LazyGroup, lazy_subcommands=COMMANDS,
             context_settings={"help_option_names": ["-h", "--help"]})
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


#: what an interrupted command leaves behind, said in its one line: by default nothing (outputs are
#: published only when complete); a study keeps every product it finished, so that it resumes
_INTERRUPTED_KEEPS = {
    "study": "finished parts are kept; run the same command again to resume",
    "man": "pages already written are kept",
}
_INTERRUPTED_DEFAULT = "no output written"


def interrupted_message(exc) -> str:
    """The line said when a signal ends a command (:class:`perscli.executor.Terminated`).

    Parameters
    ----------
    exc : perscli.executor.Terminated
        The signal; its ``command`` (set by :func:`perscli.cli.helpers.report_errors`)
        names the command it cut short, None before one started.

    Returns
    -------
    str
        e.g. "interrupted (Ctrl-C) by SIGINT; no output written".
    """
    how = "interrupted (Ctrl-C)" if exc.signal_name == "SIGINT" else "terminated"
    outcome = _INTERRUPTED_KEEPS.get(getattr(exc, "command", None), _INTERRUPTED_DEFAULT)
    return f"{how} by {exc.signal_name}; {outcome}"


def main():
    """Console-script entry point.

    SIGTERM, SIGHUP and SIGINT (Ctrl-C) end a command cleanly: the stack
    unwinds (``finally`` blocks remove temporary outputs, worker processes
    are ended), one line goes to stderr saying what is left
    (:func:`interrupted_message`) and the exit status is 128 + the signal's
    number (130 for SIGINT, as shells report it).  Standard streams closed
    by the caller (``>&-``) are held open on /dev/null, so that no file
    perscli opens takes their place; a closed standard output is then an
    error for whatever writes to it (:class:`perscli.io.output.ClosedStdout`).
    Text written to standard output that cannot be delivered
    (``> /dev/full``) is one line on stderr and exit status 1, not a
    traceback at exit.
    """
    _hold_closed_std_streams()
    install_signal_handlers()
    _install_sigint_handler()
    try:
        try:
            cli(prog_name="perscli")
        except Terminated as exc:
            _say(interrupted_message(exc))
            sys.exit(exc.code)
        except PerscliError as exc:
            # outside a command, where report_errors does not reach: --version or --help to a closed or
            # full standard output
            _say(str(exc))
            sys.exit(1)
        except OSError as exc:
            # click's own output outside a command (its EPIPE handling aside): standard output's fault
            if exc.errno not in WRITE_ERRNOS:
                raise
            _drop_stdout()
            _say(str(write_error("-", exc)))
            sys.exit(1)
        except SystemExit:
            _flush_stdout()
            raise
    finally:
        _quiet_exit_flush()


def _say(message: str) -> None:
    """``Error: message`` on stderr, if stderr can take it."""
    try:
        sys.stderr.write(f"Error: {message}\n")
        sys.stderr.flush()
    except (OSError, ValueError, AttributeError):
        pass


def _hold_closed_std_streams() -> None:
    """Open /dev/null on any of file descriptors 0, 1 and 2 that the caller closed.

    Otherwise the next file opened (an input, a temporary output) would get
    that number and whatever a library prints to it would land in the file.
    Python has already set ``sys.stdout`` (or stdin, stderr) to None for a
    stream that was closed; standard output becomes a
    :class:`perscli.io.output.ClosedStdout`, which refuses to be written to.
    """
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                null = os.open(os.devnull, os.O_RDWR)
                if null != fd:
                    os.dup2(null, fd)
                    os.close(null)
            except OSError:
                pass
    if sys.stdout is None:
        # click would drop what is echoed without a word (--version, a report): make it an error
        sys.stdout = ClosedStdout()
    elif not isinstance(sys.stdout, (ClosedStdout, GuardedStdout)):
        # text that cannot be delivered (> /dev/full) is said as standard output's fault, in one line
        sys.stdout = GuardedStdout(sys.stdout)


def _install_sigint_handler() -> None:
    """Make SIGINT end a command as SIGTERM does (one line, exit 130), instead of click's "Aborted!" and 1.

    Kept as it is when the caller made it ignored (a background job of a
    non-interactive shell) or installed its own.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return
    signal.signal(signal.SIGINT, _interrupted)


def _interrupted(signum, frame):
    # later signals are ignored while the stack unwinds, so that the clean-up itself is not cut short
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)
    raise Terminated(signum)


def _flush_stdout() -> None:
    """Deliver what is still buffered for standard output; if it cannot be, say so in one line, exit 1."""
    stream = sys.stdout
    if stream is None:
        return
    try:
        stream.flush()
    except BrokenPipeError:
        _drop_stdout()
    except PerscliError as exc:     # GuardedStdout: already said as standard output's fault
        _drop_stdout()
        _say(str(exc))
        sys.exit(1)
    except OSError as exc:
        _drop_stdout()
        _say(str(write_error("-", exc)))
        sys.exit(1)


def _quiet_exit_flush() -> None:
    """Make sure the interpreter's own flush of standard output at exit cannot fail (exit status 120
    and an 'Exception ignored' message): what cannot be delivered now is dropped, the error having
    been said (or the exit status being a signal's)."""
    try:
        sys.stdout.flush()
    except Exception:  # noqa: BLE001 - whatever it was, it was said or is moot: drop the rest
        _drop_stdout()


def _drop_stdout() -> None:
    """Point standard output at /dev/null: the interpreter's own flush at exit then has nowhere to fail."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError, AttributeError, PerscliError):
        pass
