"""The one executor behind every ``--workers``: processes, results in input order.

Every parallel piece of perscli is a function applied to a list of items with
a read-only *context* (what every item needs: a frame's pixels, the optics of
an exposure) and goes through :func:`imap` / :func:`run`::

    results = run(func, items, context=ctx, workers=4)   # [func(ctx, item) for item in items]

- ``workers=1`` (the default) runs in this process: no pool, no pickling.
- ``workers > 1`` starts that many worker processes (fewer if there are fewer
  chunks of items).  The context is handed to each worker once, when it
  starts: on Linux the workers are forked, so the parent's arrays (including
  data it read from standard input) are shared copy-on-write and never
  pickled or reopened by name; elsewhere it is pickled once per worker.  A
  :class:`Lazy` context is instead *built* in each worker by a picklable
  factory (what a distributed scheduler such as Dask would do).  Items and
  results are pickled; results come back in input order, so an output does
  not depend on the number of workers.
- Workers hold no state outside the loop that serves them (no module
  globals).  They die with the parent: on Linux through
  ``prctl(PR_SET_PDEATHSIG)``, everywhere when the parent closes their pipe,
  and the parent terminates them on any exception (an error in an item,
  KeyboardInterrupt, or :class:`Terminated` from SIGTERM/SIGHUP).

A study's task graph goes to Dask through :func:`dask_client` (a
LocalCluster of ``workers`` processes, or a running scheduler), the one place
perscli starts a cluster or a client.

Threads are used only through :func:`thread_map`, for compiled loops that
release the GIL over parts of frames already in memory (the persistence
kernel over blocks of one frame; diagnose's forward model over its
exposures), where processes would copy the frames for nothing.  OpenMP libraries
(TreeCorr) take :func:`threads` ``(workers)``, never all cores by default.

:func:`install_signal_handlers` (called by the ``perscli`` entry point) turns
SIGTERM and SIGHUP into :class:`Terminated`, a ``SystemExit`` with status
128 + signal, so that ``finally`` blocks run: atomic outputs remove their
temporary files and worker processes are ended.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import os
import pickle
import signal
import sys
import threading
import traceback

from . import PerscliError

__all__ = ["Lazy", "Terminated", "imap", "run", "thread_map", "threads", "dask_client", "install_signal_handlers"]

log = logging.getLogger(__name__)


class Lazy:
    """A context built by ``factory(*args, **kwargs)``: once in each worker (once in-process for ``workers=1``).

    ``factory`` and its arguments must be picklable (module-level functions and
    plain data) when the workers are not forked.
    """

    def __init__(self, factory, *args, **kwargs):
        self.factory, self.args, self.kwargs = factory, args, kwargs

    def build(self):
        return self.factory(*self.args, **self.kwargs)

    def __repr__(self):
        return f"Lazy({getattr(self.factory, '__qualname__', self.factory)!r})"


def _built(context):
    return context.build() if isinstance(context, Lazy) else context


_ALLOCATOR_TUNED = False


def keep_freed_memory() -> None:
    """Have this process's allocator keep freed frames for reuse instead of handing them back (glibc).

    Called by a study's tasks and by render, apply-persistence and measure
    (not diagnose: its threads would hold more at their peak, and its
    memory is what limits it).  A study's worker makes and drops dozens of 4088^2 frames per task; glibc
    maps each frame afresh and unmaps it when freed, so every new frame
    costs a page fault per 4 kB (~0.1 s a frame, a third of a final's
    render).  Raising the mmap and trim thresholds keeps the freed memory
    in the heap.  Once per process; nothing happens elsewhere than glibc.
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return
    _ALLOCATOR_TUNED = True
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, ctypes.c_int(1 << 30))
        libc.mallopt(m_trim_threshold, ctypes.c_int((1 << 31) - 1))
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


#: the most workers any command takes (--workers): more than the cores of any machine perscli runs on, and far
#: below what breaks a library: TreeCorr's OpenMP pool crashes the process (SIGSEGV) at 100,000 threads
MAX_WORKERS = 1024


def check_workers(workers) -> int:
    """``workers`` as an int from 1 to :data:`MAX_WORKERS`, else a one-line error.

    Raises
    ------
    PerscliError
        Fewer than 1 or more than :data:`MAX_WORKERS`.
    """
    n = int(workers or 1)
    if not 1 <= n <= MAX_WORKERS:
        raise PerscliError(f"{workers} workers: give 1 to {MAX_WORKERS} (this machine has {os.cpu_count()} cores)")
    return n


def threads(workers) -> int:
    """Threads for a library with its own thread pool (OpenMP): ``workers`` (checked), 1 when not given."""
    return check_workers(workers)


def run(func, items, *, context=None, workers: int = 1, chunksize: int | None = None, progress=None) -> list:
    """``[func(context, item) for item in items]``, on ``workers`` processes.

    Parameters
    ----------
    func : callable
        ``func(context, item)``; a module-level function (picklable) when the
        work may leave this machine.
    items : iterable
        Picklable items (made a list first).
    context : object or Lazy
        Read-only data every item needs, handed to each worker once.
    workers : int
        1: in this process.  More: worker processes.
    chunksize : int, optional
        Items sent to a worker at a time [default: about four chunks per worker].
    progress : callable, optional
        ``progress(done, total)`` after each item, in input order.

    Returns
    -------
    list
        The results in the order of ``items``, whatever ``workers``.

    Raises
    ------
    Exception
        The first error raised by ``func`` (the workers are ended first).
    PerscliError
        A worker process died (killed, out of memory).
    """
    gen = imap(func, items, context=context, workers=workers, chunksize=chunksize, progress=progress)
    try:
        return list(gen)
    finally:
        gen.close()


def imap(func, items, *, context=None, workers: int = 1, chunksize: int | None = None, progress=None):
    """Like :func:`run`, as an iterator: results are yielded in input order as they are ready.

    Close it (``contextlib.closing``) when you may stop early, so that the
    workers are ended at once rather than when the iterator is collected.
    """
    items = list(items)
    total = len(items)
    workers = max(1, int(workers or 1))
    if chunksize is None:
        chunksize = max(1, math.ceil(total / (4 * workers)))
    chunks = [items[i:i + chunksize] for i in range(0, total, max(1, int(chunksize)))]
    if workers == 1 or len(chunks) < 2:
        return _serial(func, items, context, progress)
    return _parallel(func, chunks, context, min(workers, len(chunks)), total, progress)


def _serial(func, items, context, progress):
    context = _built(context)
    for done, item in enumerate(items, 1):
        yield func(context, item)
        if progress is not None:
            progress(done, len(items))


# -- worker processes ------------------------------------------------------------------------------

PR_SET_PDEATHSIG = 1


def _die_with_parent(parent_pid: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux), and check it has not already."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no libc prctl
            pass
    if os.getppid() != parent_pid:
        os._exit(1)


def _error_payload(exc: BaseException) -> bytes:
    """The exception, pickled; a RuntimeError with its text when it cannot be."""
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:
        exc.remote_traceback = text
    except (AttributeError, TypeError):
        pass
    try:
        payload = pickle.dumps(exc)
        pickle.loads(payload)
        return payload
    except Exception:
        return pickle.dumps(RuntimeError(f"{type(exc).__name__}: {exc}\n(in a worker process)\n{text}"))


def _worker(conn, func, context, parent_pid: int, read: dict) -> None:
    """Serve chunks from ``conn`` until told to stop or the parent goes away, with the parent's read options."""
    # lazy: every command imports this module (--workers, the signal handlers); io.checksum imports numpy
    from .io.checksum import read_options

    with read_options(**read):
        _serve(conn, func, context, parent_pid)


def _serve(conn, func, context, parent_pid: int) -> None:
    _die_with_parent(parent_pid)
    # the parent's handlers (Terminated, KeyboardInterrupt) are not for workers: the parent ends them
    for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    built, failure = False, None
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return  # the parent closed the pipe or died
        if task is None:
            return
        index, chunk = task
        try:
            if not built:
                built = True
                try:
                    context = _built(context)
                except BaseException as exc:  # reported with every chunk
                    failure = exc
            if failure is not None:
                raise failure
            message = (index, True, [func(context, item) for item in chunk])
            data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException as exc:
            data = pickle.dumps((index, False, _error_payload(exc)))
        try:
            conn.send_bytes(data)
        except (BrokenPipeError, OSError):
            return


def _mp_context():
    import multiprocessing as mp  # lazy: ~30 ms that --help and workers=1 need not pay

    # fork hands the parent's data to the workers without pickling it (and stdin was read by the parent)
    if "fork" in mp.get_all_start_methods():
        return mp.get_context("fork")
    return mp.get_context()


def _describe_death(code) -> str:
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"killed by {name}"
    return f"exit status {code}"


def _died(proc) -> PerscliError:
    proc.join(1.0)
    return PerscliError(f"a worker process ended unexpectedly ({_describe_death(proc.exitcode)}): "
                        "out of memory? use fewer --workers")


def _parallel(func, chunks, context, nworkers: int, total: int, progress):
    from multiprocessing.connection import wait  # lazy: as in _mp_context

    from .io.checksum import current_read_options  # lazy: as in _worker

    ctx = _mp_context()
    procs, conns = [], []
    finished = False
    try:
        for _ in range(nworkers):
            parent_end, child_end = ctx.Pipe(duplex=True)
            proc = ctx.Process(target=_worker, args=(child_end, func, context, os.getpid(), current_read_options()),
                               daemon=True, name="perscli-worker")
            proc.start()
            child_end.close()
            procs.append(proc)
            conns.append(parent_end)
        busy = {}                  # worker number -> chunk index
        ready = {}                 # chunk index -> results
        next_chunk = next_out = done = 0
        # at most this many chunks beyond the next one to yield: bounds the results held in memory
        ahead = 4 * nworkers
        while next_out < len(chunks):
            for w in range(nworkers):
                if w not in busy and next_chunk < len(chunks) and next_chunk < next_out + ahead:
                    try:
                        conns[w].send((next_chunk, chunks[next_chunk]))
                    except OSError:
                        raise _died(procs[w]) from None
                    busy[w] = next_chunk
                    next_chunk += 1
            waiting = {conns[w]: w for w in busy}
            sentinels = {procs[w].sentinel: w for w in busy}
            for obj in wait(list(waiting) + list(sentinels)):
                if obj in waiting:
                    w = waiting[obj]
                    try:
                        index, ok, payload = pickle.loads(obj.recv_bytes())
                    except (EOFError, OSError):
                        raise _died(procs[w]) from None
                    if not ok:
                        raise pickle.loads(payload)
                    ready[index] = payload
                    del busy[w]
                elif sentinels[obj] in busy and not conns[sentinels[obj]].poll():
                    raise _died(procs[sentinels[obj]])
            while next_out in ready:
                for result in ready.pop(next_out):
                    yield result
                    done += 1
                    if progress is not None:
                        progress(done, total)
                next_out += 1
        finished = True
    finally:
        _shutdown(procs, conns, graceful=finished)


def _shutdown(procs, conns, *, graceful: bool) -> None:
    """Stop the workers: politely after success, at once (SIGTERM, then SIGKILL) otherwise."""
    for conn in conns:
        try:
            if graceful:
                conn.send(None)
        except (OSError, ValueError):
            pass
    if not graceful:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
    for proc in procs:
        proc.join(5.0 if graceful else 2.0)
        if proc.is_alive():
            proc.kill()
            proc.join()
    for conn in conns:
        conn.close()


# -- threads ---------------------------------------------------------------------------------------

def thread_map(func, items, *, workers: int = 1, progress=None) -> list:
    """``[func(item) for item in items]`` on ``workers`` threads, in input order.

    For compiled loops that release the GIL over pieces of one array (the
    persistence kernel over blocks of rows): threads share the array, which
    processes would have to copy.  Queued items are cancelled on any error.
    """
    items = list(items)
    results = []
    workers = max(1, int(workers or 1))
    if workers == 1 or len(items) < 2:
        for done, item in enumerate(items, 1):
            results.append(func(item))
            if progress is not None:
                progress(done, len(items))
        return results
    from concurrent.futures import ThreadPoolExecutor  # lazy: ~25 ms that --help and workers=1 need not pay

    from .io.checksum import carrying_read_options  # lazy: as in _worker

    func = carrying_read_options(func)     # a new thread starts from an empty context
    pool = ThreadPoolExecutor(min(workers, len(items)), thread_name_prefix="perscli")
    futures = []
    try:
        futures = [pool.submit(func, item) for item in items]
        for done, future in enumerate(futures, 1):
            results.append(future.result())
            if progress is not None:
                progress(done, len(items))
        return results
    finally:
        for future in futures:
            future.cancel()
        pool.shutdown(wait=True)


# -- Dask ---------------------------------------------------------------------------------------------

@contextlib.contextmanager
def dask_client(scheduler: str, workers: int):
    """A dask.distributed Client: on a LocalCluster of ``workers`` processes ('local'), or on the scheduler at
    address ``scheduler``; closed (with its local cluster) on the way out, however it is left.

    The study's runner submits its task graph to it; this is the one place
    perscli starts a Dask cluster or client.
    """
    try:
        from distributed import Client, LocalCluster  # lazy: Dask only for a study's --scheduler
    except ImportError:  # pragma: no cover - a dependency
        raise PerscliError("dask.distributed is not installed: pip install distributed, "
                           "or run with --scheduler serial") from None
    cluster = None
    if scheduler == "local":
        cluster = _local_cluster(LocalCluster, workers)
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise PerscliError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({exc}); "
                               "start one (dask scheduler) or use --scheduler local") from None
    try:
        yield client
    finally:
        _shut_down(client, cluster)


def _shut_down(client, cluster) -> None:
    """Close the client and any local cluster without hiding the error that got us here.

    A worker busy in compiled code may not die within Dask's close timeout;
    the resulting TimeoutError would replace a failed task's message, so
    shutdown problems are logged, never raised.
    """
    for closer in (client.close, getattr(cluster, "close", None)):
        if closer is None:
            continue
        try:
            closer(timeout=30)
        except Exception as exc:  # noqa: BLE001 - shutdown is best effort
            log.debug("dask shutdown: %r", exc)


def _local_cluster(LocalCluster, workers: int):
    """A LocalCluster of ``workers`` one-thread processes that leave Ctrl-C to this process.

    Ctrl-C goes to the terminal's whole process group: worker processes that
    took it would each print a traceback before this process says its one
    line and shuts them down.  They start with SIGINT ignored (an ignored
    signal is inherited through exec) and this process's handler is put
    back at once.
    """
    # one thread per worker process: GalSim, fitsio and perscli's kernels are not all thread-safe, and each
    # task is a whole frame's work
    # the workers' own log lines stay quiet: a task's failure reaches perscli through the client and is said in
    # one line, and after Ctrl-C workers outliving the scheduler for a moment would log heartbeat tracebacks
    kwargs = dict(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                  silence_logs=logging.CRITICAL)
    if threading.current_thread() is not threading.main_thread():
        return LocalCluster(**kwargs)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        return LocalCluster(**kwargs)
    finally:
        signal.signal(signal.SIGINT, previous)


# -- signals ---------------------------------------------------------------------------------------

class Terminated(SystemExit):
    """SIGTERM or SIGHUP received: unwinds the stack (running ``finally`` blocks) and exits 128 + signal."""

    def __init__(self, signum: int):
        super().__init__(128 + signum)
        self.signum = signum

    @property
    def signal_name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"


def _raise_terminated(signum, frame):
    # later signals are ignored while the stack unwinds, so that the clean-up itself is not cut short
    for sig in _HANDLED:
        signal.signal(sig, signal.SIG_IGN)
    raise Terminated(signum)


_HANDLED = tuple(s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None)


def install_signal_handlers() -> None:
    """Turn SIGTERM and SIGHUP into :class:`Terminated` (main thread only; a no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in _HANDLED:
        if signal.getsignal(sig) is signal.SIG_IGN and sig == getattr(signal, "SIGHUP", None):
            continue  # started under nohup: keep ignoring hangups
        signal.signal(sig, _raise_terminated)
