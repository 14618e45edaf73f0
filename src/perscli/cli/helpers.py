"""Glue between click and the library: errors, logging and progress."""

from __future__ import annotations

import functools
import logging
import sys

import click

from .. import PerscliError


class _StderrFormatter(logging.Formatter):
    def format(self, record):
        return f"perscli: {record.levelname.lower()}: {record.getMessage()}" + (
            "\n" + self.formatException(record.exc_info) if record.exc_info else "")


def configure_logging(verbosity: int) -> None:
    """WARNING by default; -v INFO, -vv DEBUG (with tracebacks); -q ERROR."""
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


def check_outputs(output: str, *, inputs=(), plot: str | None = None, overwrite: bool = False) -> None:
    """Refuse, before any work, an output (-o, --plot) that would replace any input or each other.

    ``inputs`` are every file the command reads (None, '-' and names that
    are not files, such as a model's name, are skipped).  Raises PerscliError:
    one line, exit status 1.
    """
    import os

    from .. import PerscliError
    from ..io.output import check_output

    inputs = [str(name) for name in inputs if name is not None]
    check_output(output, overwrite=overwrite, inputs=inputs)
    if plot is not None:
        check_output(plot, overwrite=overwrite, inputs=inputs)
        if output != "-" and os.path.abspath(plot) == os.path.abspath(output):
            raise PerscliError(f"{plot}: --plot and -o name the same file: choose another name for the figure")


def report_errors(func):
    """Turn library errors into one clear line and exit 1 (a traceback with -vv)."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except PerscliError as exc:
            if logging.getLogger("perscli").isEnabledFor(logging.DEBUG):
                logging.getLogger("perscli").exception("traceback")
            raise DataError(str(exc)) from None
        except MemoryError:
            raise DataError("out of memory: use smaller inputs or fewer --workers") from None
        except KeyboardInterrupt:
            raise click.Abort() from None

    return wrapper


def progress_reporter(label: str, stream=None):
    """A ``progress(done, total, name=None)`` callback drawing a bar on stderr.

    Silent (None) when stderr is not a terminal or with -q, so logs and pipes
    stay clean.
    """
    stream = stream if stream is not None else sys.stderr
    ctx = click.get_current_context(silent=True)
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0) if ctx else 0
    if verbosity < 0 or not stream.isatty():
        return None
    state = {"done": 0}

    def progress(done, total, name=None):
        bar = state.get("bar")
        if bar is None:
            bar = click.progressbar(length=total, label=label, file=stream)
            bar.__enter__()
            state["bar"] = bar
        bar.update(done - state["done"], current_item=name)
        state["done"] = done
        if done >= total:
            bar.__exit__(None, None, None)

    return progress
