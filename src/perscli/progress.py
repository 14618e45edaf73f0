"""Progress on stderr: one callback, ``progress(done, total, name=None)``, drawn two ways.

Every long loop of perscli reports through a callback of that one signature
(the executor's :func:`~perscli.executor.run` and
:func:`~perscli.executor.thread_map`, the study's runner): ``done`` of
``total`` steps are finished, ``name`` says which one finished last.  What it
looks like is the caller's choice:

- :func:`bar`: a bar redrawn in place, for a person at a terminal (the
  commands' objects, rows, galaxies); nothing when stderr is not a terminal;
- :func:`lines`: one line per finished step, for logs and batch jobs (the
  study's tasks, whose log a cluster keeps); with ``every``, one line per
  that fraction of the work (a frame's thousands of objects in ten lines);
- :func:`reporter`: what a command uses: the bar at a terminal, else lines,
  for work of at least ``least`` steps (a cutout's few dozen objects take a
  second: a log is not told about them).

All are silent with ``quiet`` (``-q``).  This module imports nothing heavy
(click only when a bar is drawn).
"""

from __future__ import annotations

import sys
import time


def lines(label: str, stream=None, *, quiet: bool = False, every: float | None = None, least: int = 1):
    """A callback writing ``LABEL: [done/total] NAME; N s elapsed`` on ``stream`` (stderr) per step.

    Parameters
    ----------
    label : str
        The line's first word ('study', 'render: objects').
    stream : file, optional
        Where to write (default stderr, flushed at each line).
    quiet : bool
        Write nothing (``-q``).
    every : float, optional
        Write a line at the first step (the work has started), then only
        when the work done crosses another multiple of this fraction of the
        total (0.1: eleven lines in all), and at the end; None: a line per
        step.
    least : int
        Write nothing for work of fewer steps than this.
    """
    stream = stream if stream is not None else sys.stderr
    start = time.perf_counter()
    state = {"said": -1}

    def progress(done, total, name=None):
        if quiet or total < least:
            return
        if every is not None and done < total:
            step = int(done / (total * every)) if total else 0
            if step <= state["said"]:
                return
            state["said"] = step
        elapsed = time.perf_counter() - start
        print(f"{label}: [{done}/{total}] {name or ''}; {elapsed:.0f} s elapsed".replace(" ;", ";"),
              file=stream, flush=True)

    return progress
