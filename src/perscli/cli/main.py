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
from .helpers import configure_logging
# every usage error of the group and its commands is one line on stderr: see helpers.OneLineUsage
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
    import sys

    from .. import PerscliError
    from ..executor import Terminated, install_signal_handlers

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
            from ..io.output import WRITE_ERRNOS, write_error

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
    import sys

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
    import os
    import sys

    from ..io.output import ClosedStdout, GuardedStdout

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
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return
    signal.signal(signal.SIGINT, _interrupted)


def _interrupted(signum, frame):
    import signal

    from ..executor import Terminated

    # later signals are ignored while the stack unwinds, so that the clean-up itself is not cut short
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)
    raise Terminated(signum)


def _flush_stdout() -> None:
    """Deliver what is still buffered for standard output; if it cannot be, say so in one line, exit 1."""
    import sys

    from .. import PerscliError
    from ..io.output import write_error

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
    import sys

    try:
        sys.stdout.flush()
    except Exception:  # noqa: BLE001 - whatever it was, it was said or is moot: drop the rest
        _drop_stdout()


def _drop_stdout() -> None:
    """Point standard output at /dev/null: the interpreter's own flush at exit then has nowhere to fail."""
    import os
    import sys

    from .. import PerscliError

    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError, AttributeError, PerscliError):
        pass
