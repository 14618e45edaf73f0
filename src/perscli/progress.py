"""Progress on stderr: one callback, ``progress(done, total, name=None)``, drawn two ways.

Every long loop of perscli reports through a callback of that one signature
(the executor's :func:`~perscli.executor.run` and
:func:`~perscli.executor.thread_map`, the study's runner): ``done`` of
``total`` steps are finished, ``name`` says which one finished last.  What it
looks like is the caller's choice:

- :func:`bar`: a bar redrawn in place, for a person at a terminal (the
  commands' objects, rows, galaxies); nothing when stderr is not a terminal;
- :func:`lines`: one line per finished step, for logs and batch jobs (the
  study's tasks, whose log a cluster keeps).

Both are silent with ``quiet`` (``-q``).  This module imports nothing heavy
(click only when a bar is drawn).
"""

from __future__ import annotations

import sys
import time


def bar(label: str, stream=None, *, quiet: bool = False):
    """A callback drawing a bar on ``stream`` (stderr), or None when quiet or not a terminal.

    Parameters
    ----------
    label : str
        What is counted ('rows', 'objects').
    stream : file, optional
        Where to draw (default stderr).
    quiet : bool
        Draw nothing (``-q``).
    """
    stream = stream if stream is not None else sys.stderr
    if quiet or not stream.isatty():
        return None        # logs and pipes stay clean
    state = {"done": 0, "bar": None}

    def progress(done, total, name=None):
        import click

        if state["bar"] is None:
            state["bar"] = click.progressbar(length=total, label=label, file=stream)
            state["bar"].__enter__()
        state["bar"].update(done - state["done"], current_item=name)
        state["done"] = done
        if done >= total:
            state["bar"].__exit__(None, None, None)

    return progress


def lines(label: str, stream=None, *, quiet: bool = False):
    """A callback writing ``LABEL: [done/total] NAME; N s elapsed`` on ``stream`` (stderr) per step.

    Parameters
    ----------
    label : str
        The line's first word ('study').
    stream : file, optional
        Where to write (default stderr, flushed at each line).
    quiet : bool
        Write nothing (``-q``).
    """
    stream = stream if stream is not None else sys.stderr
    start = time.perf_counter()

    def progress(done, total, name=None):
        if quiet:
            return
        elapsed = time.perf_counter() - start
        print(f"{label}: [{done}/{total}] {name or ''}; {elapsed:.0f} s elapsed".replace(" ;", ";"),
              file=stream, flush=True)

    return progress
