"""The settings of ``perscli study``'s run (not of the study itself), with their defaults written once.

What a study computes is its description, checked against one schema with
every default (:data:`perscli.study.config.SCHEMA`, which takes the commands'
own defaults from their settings: :class:`~perscli.scene.settings.CatalogOptions`,
:class:`~perscli.measure.settings.MeasureOptions`,
:class:`~perscli.stats.settings.CorrelateOptions`,
:class:`~perscli.stats.settings.BudgetOptions`).  How it runs, which changes no
product, is :class:`StudyOptions`: the runner
(:func:`perscli.study.runner.run_study`) takes one and the command's options
show its defaults.  This module imports nothing heavy, so that ``--help``
stays fast.
"""

from __future__ import annotations

import dataclasses
import re

from .. import PerscliError
from ..settings import setting

#: where a study's tasks run: in this process, on a Dask LocalCluster, or on a running Dask scheduler
SCHEDULERS = ("serial", "local")


def check_scheduler(value: str) -> str:
    """'serial', 'local' or a Dask scheduler's address (tcp://host:port, tls://, ucx://, inproc://, or host:port)."""
    if value in SCHEDULERS or re.fullmatch(r"(tcp|tls|ucx|inproc|ws|wss)://\S+|[\w.\-]+:\d{1,5}", value):
        return value
    raise PerscliError(f"{value!r} is not serial, local or a Dask scheduler address (tcp://HOST:8786)")


@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """How a study's task graph runs (the products are the same bytes whatever these are).

    Attributes
    ----------
    scheduler : str
        'serial' (this process), 'local' (a Dask LocalCluster of ``workers``
        processes) or the address of a running Dask scheduler
        (tcp://host:8786).
    workers : int
        Worker processes of the LocalCluster, one task each at a time.
    quiet : bool
        No progress lines on stderr.
    """

    scheduler: str = setting("local", "text", "serial: in this process; local: a Dask LocalCluster of --workers "
                             "processes; ADDRESS: an existing Dask scheduler (tcp://host:8786), e.g. one "
                             "dask-jobqueue started.", metavar="serial|local|ADDRESS", check=check_scheduler)
    workers: int = 1
    quiet: bool = False
