"""The commands' progress: a bar at a terminal, else :func:`perscli.progress.lines`.

- :func:`bar`: a bar redrawn in place (click's progress bar), for a person at
  a terminal (the commands' objects, rows, galaxies); nothing when stderr is
  not a terminal;
- :func:`reporter`: what a command uses: the bar at a terminal, else lines,
  for work of at least ``least`` steps (a cutout's few dozen objects take a
  second: a log is not told about them).

Both are silent with ``quiet`` (``-q``), and both make a callback of the one
signature every long loop of perscli reports through,
``progress(done, total, name=None)``.
"""

from __future__ import annotations

import sys

import click

from ..progress import lines


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
        if state["bar"] is None:
            state["bar"] = click.progressbar(length=total, label=label, file=stream)
            state["bar"].__enter__()
        state["bar"].update(done - state["done"], current_item=name)
        state["done"] = done
        if done >= total:
            state["bar"].__exit__(None, None, None)

    return progress


def reporter(label: str, stream=None, *, quiet: bool = False, least: int = 1, command: str = "perscli"):
    """The progress of a command: a bar at a terminal, else a line per tenth of the work; None when quiet.

    Parameters
    ----------
    label : str
        What is counted ('objects', 'galaxies', 'rows').
    stream : file, optional
        Where to report (default stderr).
    quiet : bool
        Nothing (``-q``).
    least : int
        Work of fewer steps says nothing when stderr is not a terminal (a
        cutout's objects take a second; a full frame's, minutes).
    command : str
        The lines' first word ('render'), so that a log says whose they are.
    """
    stream = stream if stream is not None else sys.stderr
    if quiet:
        return None
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return bar(label, stream)
    return lines(f"{command}: {label}", stream, every=0.1, least=least)
