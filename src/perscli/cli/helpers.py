"""Glue between click and the library: errors, logging, progress and path parameters."""

from __future__ import annotations

import errno
import functools
import logging
import os
import signal

import click

from .. import PerscliError, deprecation
from ..executor import Terminated
from ..io.output import STDOUT_LABEL, WRITE_ERRNOS, OutputGroup, check_output, declare_output, is_stdout, write_error
from .progress import reporter


class _StderrFormatter(logging.Formatter):
    def format(self, record):
        return f"perscli: {record.levelname.lower()}: {record.getMessage()}" + (
            "\n" + self.formatException(record.exc_info) if record.exc_info else "")


def configure_logging(verbosity: int) -> None:
    """WARNING by default; -v INFO, -vv DEBUG (with tracebacks); -q ERROR."""
    deprecation._said.clear()           # a new command line: its deprecated spellings are said again
    level = max(10, logging.WARNING - 10 * verbosity)
    logger = logging.getLogger("perscli")
    logger.handlers[:] = []
    handler = logging.StreamHandler()
    handler.setFormatter(_StderrFormatter())
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False


class DataError(click.ClickException):
    """A runtime or data error: one line on stderr, exit status 1."""

    exit_code = 1


#: suffixes of formats other than FITS, and their names: an output named so is refused (its bytes would be FITS)
FOREIGN_SUFFIXES = {
    ".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".gif": "GIF", ".tif": "TIFF", ".tiff": "TIFF", ".bmp": "BMP",
    ".pdf": "PDF", ".svg": "SVG", ".eps": "EPS", ".ps": "PostScript", ".txt": "text", ".csv": "CSV",
    ".tsv": "TSV", ".ecsv": "ECSV", ".json": "JSON", ".yaml": "YAML", ".yml": "YAML", ".md": "Markdown",
    ".html": "HTML", ".xml": "XML", ".votable": "VOTable", ".vot": "VOTable", ".h5": "HDF5", ".hdf5": "HDF5",
    ".npy": "NumPy", ".npz": "NumPy", ".parquet": "Parquet", ".asdf": "ASDF", ".reg": "ds9 region",
}


def check_fits_name(output: str, option: str = "-o") -> None:
    """Refuse an output name whose suffix says another format (``-o shapes.png``): the command writes FITS.

    A usage error (exit status 2) in one line; '-' and names without such a suffix (.fits, .fits.gz, .fz,
    none at all) pass.
    """
    if output is None or output == "-":
        return
    suffix = os.path.splitext(str(output).lower().removesuffix(".gz"))[1]
    if suffix in FOREIGN_SUFFIXES:
        ctx = click.get_current_context(silent=True)
        what = ctx.command_path if ctx is not None else "this command"
        raise click.BadParameter(f"{output}: {what} writes FITS, not {FOREIGN_SUFFIXES[suffix]}: name it "
                                 f"{os.path.splitext(os.path.basename(str(output)))[0]}.fits (or .fits.gz)",
                                 ctx, param_hint=f"'{option}'")


def check_outputs(output: str, *, inputs=(), plot: str | None = None, overwrite: bool = False,
                  fits: bool = True) -> None:
    """Refuse, before any work, an output (-o, --plot) that would replace any input or each other.

    ``inputs`` are every file the command reads (None, '-' and names that
    are not files, such as a model's name, are skipped).  The outputs become
    the command's output group (:class:`perscli.io.output.OutputGroup`):
    published together when the command succeeds, none of them when it
    fails.  Raises PerscliError: one line, exit status 1.  ``fits``: the
    output is a FITS file, and a name saying another format is a usage
    error (:func:`check_fits_name`).
    """
    if fits:
        check_fits_name(output)
    inputs = [str(name) for name in inputs if name is not None]
    check_output(output, overwrite=overwrite, inputs=inputs)
    declare_output(output)
    if plot is not None:
        check_output(plot, overwrite=overwrite, inputs=inputs)
        if is_stdout(output) and is_stdout(plot):
            raise PerscliError(f"{plot}: --plot and -o both name standard output: give the figure a file name")
        if not is_stdout(output) and os.path.abspath(plot) == os.path.abspath(output):
            raise PerscliError(f"{plot}: --plot and -o name the same file: choose another name for the figure")
        declare_output(plot)


def require_inputs(*names) -> None:
    """Refuse, before anything else is said, an input file that is not there (one line naming it, exit 1).

    For commands whose usage checks depend on what is given (one table or two): a missing file is the first
    thing to fix, not the options that would go with it.  '-' (standard input) and None are skipped.
    """
    from ..io.sources import split_selector     # io.sources imports numpy: only when a command runs

    for name in names:
        if name is None or name == "-":
            continue
        path = split_selector(str(name))[0]
        if not os.path.lexists(path):
            raise PerscliError(f"{path}: no such file")


def describe_os_error(exc: OSError, outputs=()) -> str:
    """An OSError that reached the command line (no library call said it better) as one line.

    Parameters
    ----------
    exc : OSError
        The error.
    outputs : sequence of str
        The command's outputs (``-o``, ``--plot``), named for a write fault
        whose error names no file (``write()`` and ``close()`` do not) or
        a temporary file perscli made beside an output (``.perscli-*``),
        which the user never sees.

    Returns
    -------
    str
        A write fault names the output(s) and what to do
        (:func:`perscli.io.output.write_error`); anything else names the
        file and the system's reason.
    """
    name = exc.filename
    ours = name is None or any(part.startswith(".perscli-") for part in str(name).split(os.sep))
    # permission denied on a file the user named may be an input being read: said as it is, below
    writing = exc.errno in WRITE_ERRNOS and exc.errno not in (errno.EBADF, errno.ENXIO) and (
        ours or exc.errno not in (errno.EACCES, errno.EPERM))
    if writing:
        if not ours:
            return str(write_error(str(name), exc))
        outputs = [str(o) for o in outputs if o is not None]
        if outputs:
            files = [o for o in outputs if not is_stdout(o)]
            label = " or ".join(STDOUT_LABEL if is_stdout(o) else o for o in outputs)
            return str(write_error(files[0] if files else "-", exc, name=label))
        reason = exc.strerror or str(exc)
        return f"cannot write an output ({reason}); check the device and the folder, or write elsewhere"
    reason = exc.strerror or str(exc) or type(exc).__name__
    return f"{name}: {reason}" if name else f"{reason} (an operating-system error; -vv shows where)"


def _outputs_of(kwargs) -> list:
    """The outputs a command's arguments name: ``-o`` (``output``, ``outdir`` or ``dest``), ``--plot``."""
    return [kwargs[key] for key in ("output", "outdir", "dest", "plot") if isinstance(kwargs.get(key), str)]


def report_errors(func):
    """Turn library errors into one clear line and exit 1 (a traceback with -vv).

    The command runs inside an output group (:class:`perscli.io.output.OutputGroup`):
    the outputs it declared (:func:`check_outputs`) are published together
    when it returns, or ends with a deliberate exit status (``ctx.exit``),
    and none of them when it fails or is interrupted.  Errors from the
    operating system (a full disk, a file-size limit, a read-only folder)
    are one line too; SIGINT (Ctrl-C) ends the command like SIGTERM, with
    exit status 130 (:class:`perscli.executor.Terminated`), which carries
    the command's name for the line :func:`perscli.cli.main.main` prints.
    """

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        group = OutputGroup()
        try:
            try:
                with group.active():
                    result = func(*args, **kwargs)
            except click.exceptions.Exit:
                group.commit()          # a chosen exit status (budget --check): the outputs stand
                raise
            except BaseException:
                group.discard()
                raise
            group.commit()
            return result
        except PerscliError as exc:
            _debug_traceback()
            raise DataError(str(exc)) from None
        except MemoryError:
            raise DataError("out of memory: use smaller inputs or fewer --workers") from None
        except KeyboardInterrupt:
            # SIGINT where perscli's handler is not installed (a library, a test runner): as SIGTERM
            exc = Terminated(signal.SIGINT)
            exc.command = _command_name()
            raise exc from None
        except Terminated as exc:
            # which command was cut short: what it leaves behind differs (a study keeps what it finished)
            if getattr(exc, "command", None) is None:
                exc.command = _command_name()
            raise
        except OSError as exc:
            if isinstance(exc, BrokenPipeError):
                raise                   # click's own handling: a reader that went away is no error
            _debug_traceback()
            raise DataError(describe_os_error(exc, _outputs_of(kwargs))) from None

    return wrapper


def _command_name() -> str | None:
    ctx = click.get_current_context(silent=True)
    return ctx.info_name if ctx is not None else None


def _debug_traceback() -> None:
    if logging.getLogger("perscli").isEnabledFor(logging.DEBUG):
        logging.getLogger("perscli").exception("traceback")


def verbosity() -> int:
    """The command line's -v/-q count (-v: 1, -q: -1; 0 without either or outside a command)."""
    ctx = click.get_current_context(silent=True)
    return (ctx.find_root().obj or {}).get("verbosity", 0) if ctx else 0


def progress_reporter(label: str, stream=None, *, least: int = 1):
    """A ``progress(done, total, name=None)`` callback for the current command (:func:`.progress.reporter`).

    A bar at a terminal; elsewhere (a log, a pipe, a batch job) one line per
    tenth of the work, for work of at least ``least`` steps; nothing with -q.
    """
    ctx = click.get_current_context(silent=True)
    command = ctx.command_path.replace("perscli ", "", 1) if ctx is not None else "perscli"
    return reporter(label, stream, quiet=verbosity() < 0, least=least, command=command)


def deprecated_option(old: str, new: str, *, check=None):
    """A click callback for an option kept under an older name: one warning line when it is given
    (:func:`perscli.deprecation.deprecated`), then its value as it is.  The option should be ``hidden``:
    the help documents the current spelling only.  ``check(ctx, value)``, if given, runs first (a usage
    error when the new spelling is given too)."""

    def callback(ctx, param, value):
        if value not in (None, (), False) and not ctx.resilient_parsing:
            if check is not None:
                check(ctx, value)
            deprecation.deprecated(old, new)
        return value

    return callback


# -- usage errors: one line ----------------------------------------------------------------------

def usage_error_line(exc: click.UsageError) -> str:
    """A usage error as one line: ``perscli render: error: MESSAGE (see 'perscli render -h')``.

    The message is click's own (``Invalid value for '--ra': ...``,
    ``Missing option '-o' / '--output'``, ``No such command 'rendr'``),
    joined into one line; the line starts with the command it concerns, as
    argparse's do, so that in ``perscli A | perscli B`` one knows which of
    them complained.  The command is ``exc.ctx``'s ('perscli' without one).
    """
    command_path, help_names = "perscli", ("-h", "--help")
    ctx = exc.ctx
    if ctx is not None:
        command_path = ctx.command_path
        help_names = ctx.help_option_names if ctx.command.get_help_option(ctx) is not None else ()
    message = " ".join(line.strip() for line in exc.format_message().splitlines() if line.strip())
    if message.endswith(".") and not message.endswith(".."):
        message = message[:-1]
    hint = f" (see '{command_path} {min(help_names, key=len)}')" if help_names else ""
    return f"{command_path}: error: {message}{hint}"


def speaks_perscli(ctx: click.Context) -> bool:
    """True when ``ctx`` belongs to a perscli command line: one started at a PerscliGroup or a perscli command.

    The second case is a command run on its own, as tests do
    (``CliRunner().invoke(correlate, ...)``): its callback is perscli code.
    """
    root = ctx.find_root().command
    module = getattr(root.callback, "__module__", None) or ""
    return isinstance(root, PerscliGroup) or module == "perscli" or module.startswith("perscli.")


def _show_one_line(exc: click.UsageError, file=None) -> None:
    click.echo(usage_error_line(exc), file=file, err=True)


def _one_line(exc: click.UsageError) -> click.UsageError:
    """Give ``exc`` perscli's display (:func:`usage_error_line`) when it arose on a perscli command line.

    Only this exception's ``show`` is replaced (an attribute of the instance;
    click's class is untouched), so it keeps its type, message and context
    for Python callers (``standalone_mode=False``), and errors of other
    click programs in the same process, a perscli command taken into
    another program's group among them, keep click's display.  Help shown
    for a group called without a command (NoArgsIsHelpError) is still the
    help.
    """
    if (not isinstance(exc, click.exceptions.NoArgsIsHelpError) and exc.ctx is not None
            and speaks_perscli(exc.ctx)):
        exc.show = functools.partial(_show_one_line, exc)
    return exc


class OneLineUsage:
    """Mixin of perscli's click commands and group: a usage error is one line on stderr.

    click's own display is four lines (usage, a hint, a blank line, the
    error), which in a pipeline or a log is mostly noise.  Usage errors come
    from parsing (``make_context``) and from running (``invoke``: an unknown
    subcommand, a check inside a command); both pass through here.
    """

    def make_context(self, *args, **kwargs):
        try:
            return super().make_context(*args, **kwargs)
        except click.UsageError as exc:
            raise _one_line(exc)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:
            raise _one_line(exc)


class PerscliCommand(OneLineUsage, click.Command):
    """A perscli command: usage errors in one line (:class:`OneLineUsage`), also when run on its own."""


class PerscliGroup(OneLineUsage, click.Group):
    """The perscli group: its usage errors and its commands' are one line on stderr (:class:`OneLineUsage`)."""


# -- path parameters ----------------------------------------------------------------------------

class PathName(click.Path):
    """A file (or folder) name on the command line: completed by the shell as one, passed on as given.

    click completes file names only for parameters of type click.Path; this
    is one that checks nothing, so that the library still reports a
    missing, unreadable or wrong file in one line naming it, with exit
    status 1 (click.Path's own checks would make those usage errors), and
    '-' still means standard input or output.

    Parameters
    ----------
    folder : bool
        Complete folder names only (an output folder).
    names : iterable of str
        Words the parameter takes besides a file name (``--model typical``):
        completed too.
    """

    def __init__(self, *, folder: bool = False, names=()):
        super().__init__(file_okay=not folder, dir_okay=True, readable=False)
        self.names = tuple(names)

    def convert(self, value, param, ctx):
        return value

    def shell_complete(self, ctx, param, incomplete):
        from click.shell_completion import CompletionItem

        # the file item first: bash's script empties its list when it meets one
        return super().shell_complete(ctx, param, incomplete) + [
            CompletionItem(name) for name in self.names if name.startswith(incomplete)]


class OutputName(PathName):
    """An output file name: ``/dev/stdout`` (and /dev/fd/1, /proc/self/fd/1) is taken as '-'.

    Commands treat '-' as standard output; the other names of it would
    otherwise be files that exist ("already exists") or that a temporary
    file cannot be made beside (/dev).
    """

    def convert(self, value, param, ctx):
        return "-" if value is not None and is_stdout(value) else value


#: a file name: an input or an output ('-' for standard input or output)
FILE = PathName()
#: an output file name ('-' or /dev/stdout for standard output)
OUTPUT = OutputName()
#: a folder name (an output folder)
FOLDER = PathName(folder=True)


def file_or(*names: str) -> PathName:
    """A parameter that takes one of ``names`` or a file name (``--model typical|MODEL.yaml``)."""
    return PathName(names=names)
