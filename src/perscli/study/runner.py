"""Run a study's task graph: serially, on a LocalCluster, or on an existing Dask cluster.

Tasks pass file names, never arrays; each one skips itself when its product
is already made from the same settings (:func:`perscli.study.tasks.is_done`),
so a killed run resumes where it stopped, and a worker that dies loses only
its own task (Dask runs it again elsewhere).  Every product depends only on
the settings and seeds, so serial and parallel runs write the same bytes.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import sys

from .. import PerscliError
from ..executor import dask_client
from ..io.checksum import carrying_read_options
from ..progress import lines
from .config import fingerprint
from .settings import StudyOptions
from .tasks import is_done, read_record, run_task

log = logging.getLogger(__name__)


def task_dicts(tasks) -> list:
    """Tasks as dicts with their fingerprints: a task's settings and those of everything it reads."""
    fps, out = {}, []
    for t in tasks:
        d = dataclasses.asdict(t)
        d["fingerprint"] = fingerprint([t.kind, t.output, t.params, [fps[k] for k in t.deps]])
        fps[t.key] = d["fingerprint"]
        out.append(d)
    return out


def run_serial(tasks: list, study_dir: str, progress) -> list:
    """Every task in graph order, in this process."""
    recs = []
    for t in tasks:
        rec = run_task(t, study_dir)
        progress(rec)
        recs.append(rec)
    return recs


def run_dask(tasks: list, study_dir: str, progress, *, scheduler: str = "local", workers: int = 2,
             quiet: bool = False) -> list:
    """The graph on dask.distributed: a LocalCluster of ``workers`` processes, or ``scheduler``'s address.

    Tasks already made are not even submitted.  Each task is one Dask task
    whose arguments are its dependencies' futures, so Dask runs it after
    them; ``retries`` covers a worker lost mid-task.
    """
    todo = [t for t in tasks if not is_done(study_dir, t)]
    for t in tasks:
        if t not in todo:
            rec = read_record(study_dir, t["key"])
            rec["skipped"] = True
            progress(rec)
    if not todo:
        return []
    with dask_client(scheduler, workers) as client:
        from distributed import as_completed  # lazy: Dask only for --scheduler local or an address

        if not quiet:
            link = getattr(client, "dashboard_link", None)
            print(f"study: {len(todo)} tasks on Dask ({scheduler}, "
                  f"{len(client.scheduler_info().get('workers', {}))} workers)"
                  + (f"; dashboard {link}" if link else ""), file=sys.stderr, flush=True)

        # a worker (maybe on another machine) knows nothing of this command line: each task carries
        # the read options (--no-checksum) with it
        task = carrying_read_options(run_task)
        futures = {}
        for t in todo:
            deps = [futures[k] for k in t["deps"] if k in futures]
            futures[t["key"]] = client.submit(task, t, study_dir, *deps, key=_dask_key(t),
                                              pure=False, retries=2)
        recs = []
        for fut in as_completed(list(futures.values())):
            try:
                rec = fut.result()
            except PerscliError:
                raise
            except Exception as exc:  # noqa: BLE001 - a task's own error, reported in one line
                raise PerscliError(f"study task {fut.key} failed: {exc}") from exc
            progress(rec)
            recs.append(rec)
        return recs


def _dask_key(t: dict) -> str:
    return f"perscli-{t['key']}-{t['fingerprint'][:8]}"


def remove_stale_parts(study_dir: str) -> int:
    """Remove what a killed run left half-written, before a run starts.

    Records are written to ``NAME.PID.part`` and products through the output
    writer's ``.perscli-*.part*`` temporaries, each renamed into place when
    whole, so a SIGKILL can leave one behind.  ``.part`` files of a process
    still alive are left alone.  Returns how many were removed.
    """
    removed = 0
    for folder, dirs, files in os.walk(study_dir):
        for name in list(dirs):
            # a temporary output folder (diagnose-style ``.perscli-...``) of a killed run
            if name.startswith(".perscli-"):
                shutil.rmtree(os.path.join(folder, name), ignore_errors=True)
                dirs.remove(name)
                removed += 1
        for name in files:
            if name.startswith(".perscli-") and ".part" in name:
                # the output writer's temporary file (mkstemp: no process id); none is open before a run starts
                try:
                    os.remove(os.path.join(folder, name))
                    removed += 1
                except OSError:
                    pass
                continue
            if not name.endswith(".part"):
                continue
            pid = name[:-5].rsplit(".", 1)[-1]
            if pid.isdigit() and int(pid) != os.getpid():
                try:
                    os.kill(int(pid), 0)
                    continue                  # its writer is still running
                except ProcessLookupError:
                    pass
                except PermissionError:
                    continue
            try:
                os.remove(os.path.join(folder, name))
                removed += 1
            except OSError:
                pass
    return removed


def run_study(tasks: list, study_dir: str, options: StudyOptions = StudyOptions()) -> list:
    """Run the graph as ``options`` say (:class:`~perscli.study.settings.StudyOptions`: the scheduler, 'serial',
    'local' or a Dask scheduler's address, its workers, and whether to say each finished task)."""
    scheduler, workers, quiet = options.scheduler, options.workers, options.quiet
    os.makedirs(study_dir, exist_ok=True)
    if remove_stale_parts(study_dir):
        log.info("removed the half-written files of an earlier run")

    step, done = lines("study", quiet=quiet), [0]

    def progress(rec: dict) -> None:
        # one line per finished task (a cluster's log keeps them), through the one progress callback
        done[0] += 1
        what = "already made" if rec.get("skipped") else f"{rec['wall_s']:.1f} s"
        step(done[0], len(tasks), f"{rec['key']} ({what})")

    if scheduler == "serial":
        return run_serial(tasks, study_dir, progress)
    return run_dask(tasks, study_dir, progress, scheduler=scheduler, workers=workers, quiet=quiet)
