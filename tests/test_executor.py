"""perscli.executor, the one executor behind every --workers: same results for any number of workers,
contexts handed over once, errors and dead workers reported, stdin through a real pipe, and workers
that end when the command is signalled (SIGTERM, SIGHUP) or killed, leaving no temporary file."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from perscli import PerscliError, executor

from fits_factory import invoke

SCRIPT = os.path.join(os.path.dirname(sys.executable), "perscli")


# -- the library -----------------------------------------------------------------------------------

def _scaled(context, item):
    return context["scale"] * item, os.getpid()


def _pid_context():
    return {"pid": os.getpid(), "scale": 3}


def _fails_on_seven(context, item):
    if item == 7:
        raise ValueError(f"item {item} is bad")
    return item


def _dies_on_three(context, item):
    if item == 3:
        os._exit(3)
    return item


def _sleeps(context, item):
    time.sleep(30)


@pytest.mark.parametrize("workers", [1, 2, 3])
@pytest.mark.parametrize("chunksize", [None, 1, 4])
def test_results_in_input_order_whatever_the_workers(workers, chunksize):
    out = executor.run(_scaled, range(23), context={"scale": 2}, workers=workers, chunksize=chunksize)
    assert [v for v, _ in out] == [2 * i for i in range(23)]


def test_one_worker_runs_in_this_process_and_more_in_others():
    assert {pid for _, pid in executor.run(_scaled, range(8), context={"scale": 1})} == {os.getpid()}
    pids = {pid for _, pid in executor.run(_scaled, range(8), context={"scale": 1}, workers=2, chunksize=1)}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2


def test_lazy_context_is_built_in_each_worker():
    def check(context, item):
        return context["pid"] == os.getpid(), context["scale"] * item

    # a closure is fine with forked workers; the factory itself is a module-level function
    out = executor.run(check, range(10), context=executor.Lazy(_pid_context), workers=2, chunksize=2)
    assert out == [(True, 3 * i) for i in range(10)]
    assert executor.run(check, range(3), context=executor.Lazy(_pid_context)) == [(True, 0), (True, 3), (True, 6)]


def test_progress_is_reported_in_order():
    seen = []
    executor.run(_scaled, range(9), context={"scale": 1}, workers=2, chunksize=2,
                 progress=lambda done, total: seen.append((done, total)))
    assert seen == [(i, 9) for i in range(1, 10)]


def _children(pid):
    """Live (not zombie) child processes of ``pid``, from /proc."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(entry))
    return out


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc (Linux)")


@needs_proc
def test_an_error_in_an_item_is_raised_and_the_workers_end():
    with pytest.raises(ValueError, match="item 7 is bad"):
        executor.run(_fails_on_seven, range(40), workers=2, chunksize=1)
    assert _children(os.getpid()) == []


@needs_proc
def test_a_worker_that_dies_is_reported_and_the_others_end():
    with pytest.raises(PerscliError, match="worker process ended unexpectedly"):
        executor.run(_dies_on_three, range(20), workers=2, chunksize=1)
    assert _children(os.getpid()) == []


@needs_proc
def test_stopping_early_ends_the_workers():
    import contextlib

    with contextlib.closing(executor.imap(_scaled, range(100), context={"scale": 1}, workers=2, chunksize=1)) as it:
        next(it)
        assert len(_children(os.getpid())) == 2
    assert _children(os.getpid()) == []


def test_thread_map_keeps_order_and_threads_default_to_one():
    assert executor.thread_map(lambda x: x * x, range(50), workers=3) == [x * x for x in range(50)]
    assert executor.thread_map(lambda x: -x, [1, 2]) == [-1, -2]
    assert executor.threads(None) == 1 and executor.threads(1) == 1 and executor.threads(4) == 4


def test_terminated_is_a_system_exit_with_128_plus_the_signal():
    exc = executor.Terminated(signal.SIGTERM)
    assert isinstance(exc, SystemExit) and exc.code == 143 and exc.signal_name == "SIGTERM"
    assert executor.Terminated(signal.SIGHUP).code == 129


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_inside_an_atomic_output_removes_its_temporary_file(tmp_path, sig):
    dest = tmp_path / "out.fits"
    code = f"""
import os, signal, time
from perscli.executor import install_signal_handlers
from perscli.io.output import atomic_path
install_signal_handlers()
with atomic_path({str(dest)!r}) as tmp:
    open(tmp, "wb").write(b"half")
    os.kill(os.getpid(), {int(sig)})
    time.sleep(30)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert proc.returncode == 128 + sig, proc.stderr
    assert b"Traceback" not in proc.stderr
    assert os.listdir(tmp_path) == []


# -- commands: same bytes for any --workers, stdin through a real pipe ---------------------------

MJD = 61541.97
POINTING = ["--ra", "10", "--dec", "-44", "--pa", "30", "--filter", "J129", "--sca", "7", "--mjd", MJD]


def _run(*args):
    result = invoke(*args)
    assert result.exit_code == 0, (result.output, result.exception)
    return result


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A 160x160 rendered cutout and its truth catalogue: a few galaxies and a bright star."""
    from astropy.table import Table

    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    tmp = tmp_path_factory.mktemp("small")
    optics = Optics(Exposure(ra=10, dec=-44, pa=30, sca=7, filter="J129", mjd=MJD))
    xs = np.array([40.0, 100.0, 120.0, 45.0, 150.0, 80.0, 3000.0])
    ys = np.array([40.0, 50.0, 110.0, 120.0, 150.0, 80.0, 3000.0])
    ra, dec = optics.wcs.xyToradec(xs, ys, units="deg")
    n = len(xs)
    Table(dict(id=np.arange(1, n + 1, dtype=np.int64), ra=ra, dec=dec,
               kind=np.array(["galaxy"] * 4 + ["star", "galaxy", "galaxy"]),
               mag_J129=np.array([20.0, 20.3, 20.2, 20.4, 16.0, 21.0, 21.0]),
               mag_H158=np.array([19.7, 20.0, 19.9, 20.1, 15.8, 20.7, 20.7]),
               hlr=np.array([0.3, 0.25, 0.35, 0.3, 0.0, 0.3, 0.3]),
               e1=np.array([0.2, -0.1, 0.0, 0.3, 0.0, 0.1, 0.0]),
               e2=np.array([0.0, 0.2, -0.3, 0.1, 0.0, 0.0, 0.0]))).write(tmp / "truth.fits")
    return tmp, tmp / "truth.fits"


def _data(path, names):
    with fits.open(path, checksum=True) as hdul:
        return {name: hdul[name].data.tobytes() for name in names}


def test_render_same_bytes_with_one_or_two_workers(small):
    tmp, truth = small
    for w in (1, 2):
        _run("render", truth, *POINTING, "--bounds", 1, 160, 1, 160, "--seed", 4, "--workers", w,
             "-o", tmp / f"r{w}.fits")
    names = ("SCI", "IDEAL", "FLUENCE")
    assert _data(tmp / "r1.fits", names) == _data(tmp / "r2.fits", names)


def test_measure_same_bytes_with_one_or_two_workers(small):
    tmp, truth = small
    frame = tmp / "m.fits"
    _run("render", truth, *POINTING, "--bounds", 1, 160, 1, 160, "--seed", 5, "-o", frame)
    for w in (1, 2, 3):
        _run("measure", frame, frame, "--catalog", truth, "--workers", w, "-o", tmp / f"s{w}.fits")
    one = _data(tmp / "s1.fits", ("SHAPES", "COMBINED"))
    assert _data(tmp / "s2.fits", ("SHAPES", "COMBINED")) == one
    assert _data(tmp / "s3.fits", ("SHAPES", "COMBINED")) == one
    shapes = fits.getdata(tmp / "s1.fits", "SHAPES")
    assert np.sum(shapes["flags"] == 0) >= 6     # real fits, not a table of flags


def _script_or_skip():
    if not os.path.exists(SCRIPT):
        pytest.skip("the perscli console script is not installed next to this Python")
    return SCRIPT


def test_measure_reads_a_frame_from_a_real_pipe_with_two_workers(small):
    tmp, truth = small
    frame = tmp / "pipe_frame.fits"
    _run("render", truth, *POINTING, "--bounds", 1, 160, 1, 160, "--seed", 6, "-o", frame)
    ref = tmp / "pipe_ref.fits"
    _run("measure", frame, "--catalog", truth, "-o", ref)
    out = tmp / "pipe_out.fits"
    proc = subprocess.Popen([_script_or_skip(), "measure", "-", "--catalog", str(truth), "--workers", "2",
                             "-o", str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    stdout, stderr = proc.communicate(Path(frame).read_bytes(), timeout=300)
    assert proc.returncode == 0, stderr.decode()
    assert stdout == b"" and stderr == b""
    assert _data(out, ("SHAPES",)) == _data(ref, ("SHAPES",))
    assert fits.getval(out, "FRM01") == "stdin"


# -- commands: signals ---------------------------------------------------------------------------

#: a 1024 x 1024 cutout at the centre of SCA 7, and its centre on the sky (for the catalogue)
BIG_BOUNDS = ["--bounds", 1533, 2556, 1533, 2556]


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    """~10,000 galaxies on a 1024 x 1024 cutout: a few seconds of work for render and measure."""
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    tmp = tmp_path_factory.mktemp("crowded")
    centre = Optics(Exposure(ra=10, dec=-44, pa=30, sca=7, filter="J129", mjd=MJD)).world_centre
    truth = tmp / "dense.fits"
    _run("catalog", "--ra", centre.ra.deg, "--dec", centre.dec.deg, "--size", 2, "--galaxy-density", 2500,
         "--seed", 3, "-o", truth)
    frame = tmp / "frame.fits"
    _run("render", truth, *POINTING, *BIG_BOUNDS, "--seed", 1, "--workers", 2, "-o", frame)
    return tmp, truth, frame


def _start_and_wait_for_workers(args, cwd, nworkers=2, timeout=120.0):
    proc = subprocess.Popen([_script_or_skip(), *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        workers = _children(proc.pid)
        if len(workers) >= nworkers:
            return proc, workers
        if proc.poll() is not None:
            break
        time.sleep(0.01)
    proc.kill()
    out, err = proc.communicate()
    pytest.fail(f"no {nworkers} worker processes seen (exit {proc.returncode}): {err.decode()}")


def _all_gone(pids, timeout=120.0):
    # a deadline for workers that never go, not a measure of how fast they go (a loaded machine is slow)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not any(_alive(pid) for pid in pids):
            return True
        time.sleep(0.05)
    return False


def _temporary_files(folder):
    return [name for name in os.listdir(folder) if name.startswith(".") and ".part" in name]


@needs_proc
@pytest.mark.parametrize("command, sig", [("render", signal.SIGTERM), ("measure", signal.SIGTERM),
                                          ("measure", signal.SIGHUP)])
def test_signal_ends_the_workers_and_leaves_no_temporary_file(crowded, tmp_path, command, sig):
    _, truth, frame = crowded
    out = tmp_path / "out.fits"
    if command == "render":
        args = ["render", truth, *POINTING, *BIG_BOUNDS, "--seed", 2, "--workers", 2, "-o", out]
    else:
        args = ["measure", frame, "--catalog", truth, "--workers", 2, "-o", out]
    proc, workers = _start_and_wait_for_workers(args, tmp_path)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, stderr.decode()
    lines = stderr.decode().splitlines()
    assert lines == [f"Error: terminated by {signal.Signals(sig).name}; no output written"], lines
    assert _all_gone(workers), [pid for pid in workers if _alive(pid)]
    assert not out.exists()
    assert _temporary_files(tmp_path) == []


@needs_proc
def test_workers_die_with_a_killed_parent(crowded, tmp_path):
    _, truth, frame = crowded
    proc, workers = _start_and_wait_for_workers(["measure", frame, "--catalog", truth, "--workers", 2,
                                                 "-o", tmp_path / "out.fits"], tmp_path)
    proc.kill()
    proc.communicate(timeout=60)
    assert _all_gone(workers), "workers outlived a parent killed with SIGKILL"


# -- read options (--no-checksum) are passed down to every worker -------------------------------------

def _verifying(context, item):
    from perscli.io.checksum import checksums_enabled

    return checksums_enabled()


def test_read_options_reach_worker_processes_threads_and_pickled_tasks():
    """--no-checksum is a read option passed down (perscli.io.checksum.read_options), not a global: the
    executor's processes and threads and the study's Dask tasks get the caller's, and it ends with its block."""
    import pickle

    from perscli.executor import run, thread_map
    from perscli.io.checksum import carrying_read_options, checksums_enabled, read_options

    with read_options(verify_checksums=False):
        assert not checksums_enabled()
        assert run(_verifying, range(6), workers=2) == [False] * 6
        assert thread_map(lambda i: checksums_enabled(), range(6), workers=2) == [False] * 6
        task = pickle.dumps(carrying_read_options(_verifying))   # as Dask ships a study task
    assert checksums_enabled()
    assert run(_verifying, range(4), workers=2) == [True] * 4
    assert pickle.loads(task)(None, 0) is False and checksums_enabled()


def test_one_progress_callback_drawn_as_lines_or_a_bar():
    """progress(done, total, name): lines for logs (the study's), a bar only at a terminal, nothing with -q."""
    import io

    from perscli.cli.progress import bar
    from perscli.progress import lines

    out = io.StringIO()
    step = lines("study", out)
    step(1, 2, "render-e1 (3.0 s)")
    step(2, 2)
    said = out.getvalue().splitlines()
    assert said[0].startswith("study: [1/2] render-e1 (3.0 s); ") and said[0].endswith(" s elapsed")
    assert said[1].startswith("study: [2/2]; ")
    quiet = io.StringIO()
    lines("study", quiet, quiet=True)(1, 1, "x")
    assert quiet.getvalue() == ""
    assert bar("rows", io.StringIO()) is None            # not a terminal: logs and pipes stay clean

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    draw = bar("rows", term)
    assert bar("rows", term, quiet=True) is None
    for k in (1, 2, 3):
        draw(k, 3)
    assert "rows" in term.getvalue() and "100%" in term.getvalue()
