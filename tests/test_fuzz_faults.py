"""Faults around perscli's inputs and outputs, run as a user runs the ``perscli`` command (issue 18).

Where tests/test_fuzz.py corrupts the bytes of inputs and tests/test_fuzz_values.py their values, this
file covers what goes wrong around a run:

- write faults (item 1), for FITS outputs (``-o``), figures (``--plot``), standard output, and the
  folders of diagnose and study: a full disk (a small tmpfs, mounted in a private mount namespace with
  ``unshare``), a file-size limit (RLIMIT_FSIZE: EFBIG), a read-only file system (a read-only tmpfs),
  a folder without write permission (chmod 555, run as nobody: root bypasses permissions),
  ``> /dev/full`` and a closed standard output (``>&-``);
- header faults (item 4): a bit flipped in NAXIS1, SAMPTIME = 'soon', a BEL byte in a string value;
- headers that would give a silently wrong result or an output other readers refuse (item 5):
  EXPTIME = 0, EXPSTART = EXPEND, EXPSTART = 1E300, GAIN = 1E308 on a rate or DN frame, BZERO = 1E300,
  an unterminated string, a non-ASCII keyword;
- two writers of one output, a failing figure, SIGINT and SIGTERM (item 7);
- ``-o /dev/stdout`` and ``--exptime 0`` (item 9).

A refused run ends with exit status 1 (2 for a bad option), exactly one line on stderr naming the
fault, no traceback, nothing left in the output folder (no output, no temporary file) and every input
byte-for-byte unchanged.  Each refused case has a twin that must work, so that a check refusing too
much fails here too.  Runs are real processes of the console script; the inputs are the small seeds
of tests/fuzz_corpus.py.  The diagnose runs and study's full-disk run take longer: ``slow``.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import fuzz_corpus as fc

PERSCLI = shutil.which("perscli", path=os.path.dirname(sys.executable))
TIMEOUT = 300.0            # seconds; a deadline for a hung run, not a measure of speed
#: the arguments of correlate on the SHAPES seed (tests/test_fuzz.py)
CORRELATE_ARGS = ["--frames", "0", "1", "--npatch", "2", "--nbins", "2", "--nboot", "2", "--min-sep", "1",
                  "--max-sep", "20", "--seed", "3"]
#: a private mount namespace with a tmpfs on $1 (options $2) for the command "$@" (after $3); what is left
#: in the tmpfs is listed into $3 before the namespace (and the tmpfs) goes away
MOUNT_SCRIPT = ('mnt=$1; opts=$2; listing=$3; shift 3; mount -t tmpfs -o "$opts" perscli-test "$mnt" || exit 99; '
                '"$@"; rc=$?; (cd "$mnt" && find . -mindepth 1 | sort) > "$listing"; exit $rc')

pytestmark = pytest.mark.skipif(PERSCLI is None, reason="the perscli console script is not installed")


# =================================================================================================
# Inputs and runs
# =================================================================================================

def xi_table(path) -> str:
    """A correlate XI table (TreeCorr's GG columns) with xi+ = 0: budget's input."""
    theta = np.geomspace(0.5, 120, 12)
    n = theta.size
    columns = {"r_nom": theta, "meanr": theta, "meanlogr": np.log(theta), "xip": np.zeros(n), "xim": np.zeros(n),
               "xip_im": np.zeros(n), "xim_im": np.zeros(n), "sigma_xip": np.full(n, 1e-7),
               "sigma_xim": np.full(n, 1e-7), "weight": np.ones(n), "npairs": np.full(n, 1e4)}
    hdu = fits.BinTableHDU.from_columns([fits.Column(k, "D", array=v) for k, v in columns.items()], name="XI")
    hdu.header["SEP_UNIT"] = "arcmin"
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(path, checksum=True)
    return str(path)


def big_frame(path, start: float, value: float) -> str:
    """A 128 x 128 frame in electrons (a 66 kB output: more than the small tmpfs and file-size limits)."""
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    hdr["EXPTIME"], hdr["EXPSTART"], hdr["EXPEND"] = 100.0, start, start + 100.0 / fc.DAY
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.full((128, 128), value, np.float32), hdr, name="SCI")]
                 ).writeto(path, checksum=True)
    return str(path)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The valid inputs, in a folder of their own (never an output folder), never modified."""
    folder = tmp_path_factory.mktemp("inputs")
    seeds = fc.seeds()
    out = {}
    for name in ("frame", "ramp", "truth", "psf", "shapes", "earlier", "later"):
        path = folder / f"{name}.fits"
        path.write_bytes(seeds[name])
        out[name] = str(path)
    out["xi"] = xi_table(folder / "xi.fits")
    out["big_earlier"] = big_frame(folder / "big_earlier.fits", fc.T0, 3e4)
    out["big_current"] = big_frame(folder / "big_current.fits", fc.T0 + 3000.0 / fc.DAY, 10.0)
    out["dir"] = folder
    return out


def digests(folder) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in Path(folder).iterdir() if p.is_file()}


@pytest.fixture
def untouched(inputs):
    """Checks, after the test, that no input changed and nothing appeared beside them."""
    before = digests(inputs["dir"])
    yield
    assert digests(inputs["dir"]) == before


def clean_env() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def file_size_limit(nbytes: int):
    """A preexec_fn: RLIMIT_FSIZE of ``nbytes`` (a write past it fails with EFBIG; SIGXFSZ ignored)."""

    def apply():
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    return apply


def close_stdout():
    """A preexec_fn: the command starts with file descriptor 1 closed (``>&-``)."""
    os.close(1)


def perscli(args, *, cwd, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, preexec_fn=None,
            wrap=()) -> subprocess.CompletedProcess:
    """Run ``perscli ARGS`` in ``cwd`` (``wrap``: a command to run it under, such as unshare)."""
    return subprocess.run([*wrap, PERSCLI, *[str(a) for a in args]], cwd=cwd, stdin=stdin, stdout=stdout,
                          stderr=subprocess.PIPE, preexec_fn=preexec_fn, env=clean_env(), timeout=TIMEOUT,
                          text=False)


def error_lines(run) -> list:
    return run.stderr.decode("utf-8", "backslashreplace").splitlines()


def refused(run, *needles, code: int = 1) -> str:
    """Assert the run ended with ``code`` and exactly one stderr line, an error holding every needle."""
    lines = error_lines(run)
    assert run.returncode == code, (run.returncode, lines)
    assert len(lines) == 1, lines
    line = lines[0]
    assert line.startswith("Error: ") if code == 1 else "error:" in line, line
    for needle in needles:
        assert needle in line, (needle, line)
    return line


def listing(folder) -> list:
    """Everything under ``folder`` (hidden files included), as relative paths."""
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def temporaries(folder) -> list:
    """Temporary files perscli makes (``.perscli-*``, ``*.part*``, ``.NAME.*.png``) under ``folder``."""
    return [p for p in listing(folder) if any(part.startswith(".perscli") or ".part" in part
                                              or (part.startswith(".") and part.endswith(".png"))
                                              for part in Path(p).parts)]


# -- a tmpfs of its own ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def can_mount(tmp_path_factory):
    """Whether a tmpfs can be mounted in a private mount namespace (root, or user namespaces)."""
    if shutil.which("unshare") is None:
        return False
    folder = tmp_path_factory.mktemp("probe")
    (folder / "mnt").mkdir()
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", MOUNT_SCRIPT, "sh", str(folder / "mnt"), "size=64k",
                            str(folder / "listing"), "true"], capture_output=True, timeout=60)
    return probe.returncode == 0


def on_tmpfs(can_mount, args, *, cwd: Path, options: str, **kw):
    """Run perscli with ``cwd/mnt`` a tmpfs mounted with ``options``; (run, what was left in it)."""
    if not can_mount:
        pytest.skip("cannot mount a tmpfs here (needs root or user namespaces)")
    (cwd / "mnt").mkdir(exist_ok=True)
    left = cwd / "left-in-tmpfs.txt"
    run = perscli(args, cwd=cwd, wrap=("unshare", "-rm", "sh", "-c", MOUNT_SCRIPT, "sh", str(cwd / "mnt"), options,
                                       str(left)), **kw)
    assert run.returncode != 99, "the tmpfs could not be mounted"
    return run, [line for line in left.read_text().splitlines() if line]


# =================================================================================================
# Item 1: write faults
# =================================================================================================

#: commands whose output is standard output: FITS (budget, apply-persistence) and text
STDOUT_COMMANDS = {
    "budget": lambda i: ["budget", i["xi"], "-o", "-"],
    "apply-persistence": lambda i: ["apply-persistence", i["later"], i["earlier"], "-o", "-"],
    "version": lambda i: ["--version"],
    "help": lambda i: ["budget", "-h"],
    "man": lambda i: ["man", "render"],
    "study-dry-run": lambda i: ["study", "--preset", "ci", "-o", "never", "--dry-run"],
}


@pytest.mark.parametrize("command", sorted(STDOUT_COMMANDS))
def test_a_full_standard_output_is_one_line(command, inputs, tmp_path, untouched):
    with open("/dev/full", "wb") as full:
        run = perscli(STDOUT_COMMANDS[command](inputs), cwd=tmp_path, stdout=full)
    refused(run, "standard output: cannot write: no space left")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("command", sorted(set(STDOUT_COMMANDS) - {"study-dry-run"}))
def test_a_closed_standard_output_is_one_line(command, inputs, tmp_path, untouched):
    run = perscli(STDOUT_COMMANDS[command](inputs), cwd=tmp_path, stdout=None, preexec_fn=close_stdout)
    refused(run, "standard output is closed")
    assert listing(tmp_path) == []


def test_a_traceback_only_with_vv(inputs, tmp_path):
    with open("/dev/full", "wb") as full:
        quiet = perscli(["budget", inputs["xi"], "-o", "-"], cwd=tmp_path, stdout=full)
        loud = perscli(["-vv", "budget", inputs["xi"], "-o", "-"], cwd=tmp_path, stdout=full)
    assert b"Traceback" not in quiet.stderr
    assert loud.returncode == 1 and b"Traceback" in loud.stderr
    assert error_lines(loud)[-1] == refused(quiet)


#: (errno name, tmpfs options or None for RLIMIT_FSIZE, what the message says)
FAULTS = [("ENOSPC", "size=32k", "no space left on the device of"),
          ("EFBIG", None, "would exceed the file-size limit"),
          ("EROFS", "ro,size=64k", "is on a read-only file system")]


def faulty_run(can_mount, fault, args, *, cwd: Path, limit: int = 24 << 10):
    """Run ``args`` (outputs under mnt/) with ``fault``: (run, what is left in mnt/)."""
    name, options, _ = fault
    if options is None:
        (cwd / "mnt").mkdir(exist_ok=True)
        run = perscli(args, cwd=cwd, preexec_fn=file_size_limit(limit))
        return run, listing(cwd / "mnt")
    return on_tmpfs(can_mount, args, cwd=cwd, options=options)


@pytest.mark.parametrize("fault", FAULTS, ids=[f[0] for f in FAULTS])
def test_a_fits_output_that_cannot_be_written(fault, can_mount, inputs, tmp_path, untouched):
    run, left = faulty_run(can_mount, fault, ["apply-persistence", inputs["big_current"], inputs["big_earlier"],
                                              "-o", "mnt/out.fits"], cwd=tmp_path)
    refused(run, "mnt/out.fits: cannot write", fault[2])
    assert left == []


@pytest.mark.parametrize("fault", FAULTS, ids=[f[0] for f in FAULTS])
def test_a_figure_that_cannot_be_written_leaves_no_table(fault, can_mount, inputs, tmp_path, untouched):
    # the table (11.5 kB) fits in the tmpfs and under the size limit, the figure (~31 kB) does not; read-only:
    # refused before any work
    run, left = faulty_run(can_mount, fault, ["budget", inputs["xi"], "-o", "mnt/b.fits", "--plot", "mnt/b.png"],
                           cwd=tmp_path)
    refused(run, "cannot write", fault[2], "mnt/b." + ("fits" if fault[0] == "EROFS" else "png"))
    assert left == []


@pytest.mark.parametrize("fault", [FAULTS[0], FAULTS[2], pytest.param(FAULTS[1], marks=pytest.mark.slow)],
                         ids=["ENOSPC", "EROFS", "EFBIG"])
def test_correlate_outputs_that_cannot_be_written(fault, can_mount, inputs, tmp_path, untouched):
    run, left = faulty_run(can_mount, fault, ["correlate", inputs["shapes"], *CORRELATE_ARGS, "-o", "mnt/c.fits",
                                              "--plot", "mnt/c.png"], cwd=tmp_path)
    refused(run, "mnt/c.", "cannot write", fault[2])
    assert left == []


def test_the_twin_of_the_write_faults_works(can_mount, inputs, tmp_path, untouched):
    run, left = on_tmpfs(can_mount, ["budget", inputs["xi"], "-o", "mnt/b.fits", "--plot", "mnt/b.png", "-q"],
                         cwd=tmp_path, options="size=1m")
    assert run.returncode == 0 and run.stderr == b"", run.stderr
    assert left == ["./b.fits", "./b.png"]


@pytest.fixture(scope="module")
def as_nobody():
    """(wrapper, folder) to run perscli as the user nobody when the tests run as root (who may write
    anywhere): setpriv; skips when that is not possible here."""
    if os.geteuid() != 0:
        yield (), None
        return
    wrap = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups")
    folder = Path(tempfile.mkdtemp(prefix="perscli-nobody-"))
    os.chmod(folder, 0o777)
    try:
        probe = subprocess.run([*wrap, PERSCLI, "--version"], capture_output=True, cwd=folder, timeout=60)
        ok = probe.returncode == 0
    except OSError:
        ok = False
    if not ok:
        shutil.rmtree(folder)
        pytest.skip("running as root and perscli cannot be run as nobody: permissions are not testable")
    yield wrap, folder
    shutil.rmtree(folder)


@pytest.mark.parametrize("which", ["output", "plot"])
def test_a_folder_without_write_permission(which, as_nobody, inputs, tmp_path, untouched):
    wrap, base = as_nobody
    work = (base if base is not None else tmp_path) / which
    work.mkdir()
    shutil.copy(inputs["xi"], work / "xi.fits")
    (work / "ro").mkdir()
    os.chmod(work, 0o777)
    os.chmod(work / "ro", 0o555)
    if which == "output":
        args, bad = ["budget", "xi.fits", "-o", "ro/b.fits"], "ro/b.fits"
    else:
        args, bad = ["budget", "xi.fits", "-o", "b.fits", "--plot", "ro/b.png"], "ro/b.png"
    run = perscli(args, cwd=work, wrap=wrap)
    refused(run, f"{bad}: cannot write in", "(permission denied)")
    assert listing(work) == ["ro", "xi.fits"]


@pytest.mark.parametrize("fault", [f for f in FAULTS if f[0] != "ENOSPC"] + [
    pytest.param(FAULTS[0], marks=pytest.mark.slow)], ids=["EFBIG", "EROFS", "ENOSPC"])
def test_study_folder_that_cannot_be_written(fault, can_mount, tmp_path):
    # the finished products stay (a study resumes), but never a partial file or a temporary one
    name, options, message = fault
    args = ["study", "--preset", "ci", "-o", "mnt/s", "--scheduler", "serial", "-q"]
    if options is not None and name == "ENOSPC":
        options = "size=200k"
    run, left = faulty_run(can_mount, (name, options, message), args, cwd=tmp_path, limit=20 << 10)
    lines = error_lines(run)
    assert run.returncode == 1 and b"Traceback" not in run.stderr, lines
    assert [line for line in lines if line.startswith("Error: ")] == lines[-1:], lines
    assert "cannot write" in lines[-1] and message in lines[-1], lines
    assert not [p for p in left if ".perscli" in p or ".part" in p], left


@pytest.fixture(scope="module")
def diagnose_inputs(tmp_path_factory):
    """Two measured frames (a dark current) and their simulation: a 64 x 64 cutout, 8 objects."""
    from diagnose_scene import make_truth, render_sequence

    folder = tmp_path_factory.mktemp("diagnose")
    bounds = (1001, 1064, 2001, 2064)
    truth = make_truth(folder / "truth.fits", bounds=bounds, nstars=4, ngalaxies=4)
    sim = render_sequence(truth, folder / "sim", bounds=bounds, n=2, seed=200)
    meas = render_sequence(truth, folder / "meas", bounds=bounds, n=2, seed=300, settings=["dark.current=0.4"])
    return [*meas, "--simulated", sim[0], "--simulated", sim[1]]


@pytest.mark.slow
@pytest.mark.parametrize("fault", FAULTS, ids=[f[0] for f in FAULTS])
def test_diagnose_folder_that_cannot_be_written(fault, can_mount, diagnose_inputs, tmp_path):
    name, options, message = fault
    run, left = faulty_run(can_mount, (name, "size=100k" if name == "ENOSPC" else options, message),
                           ["diagnose", *diagnose_inputs, "-o", "mnt/d", "-q"], cwd=tmp_path, limit=30 << 10)
    refused(run, "mnt/d: cannot write", message)
    assert left == []


# =================================================================================================
# Items 4 and 5: headers that are corrupt, or would give a silently wrong result
# =================================================================================================

def frame_with(*, hdu: int = 1, sign: bool = True, replace=None, insert=None, seed: str = "frame") -> bytes:
    """The frame seed with cards of HDU ``hdu`` replaced ({KEY: (value token, comment)}) or inserted."""
    cards = {key: fc.card(key, value) for key, value in (replace or {}).items()}
    return fc.edit(fc.seeds()[seed], hdu, replace=cards, insert=[fc.card(k, v) for k, v in (insert or {}).items()],
                   sign=sign)


def flipped(seed: str, key: str, column: int, mask: int, *, signed: bool = True) -> bytes:
    """``seed`` with one bit of card ``key`` of HDU 1 flipped (column 0-79); unsigned: CHECKSUM removed first."""
    raw = fc.seeds()[seed] if signed else fc.edit(fc.seeds()[seed], 1, delete=["CHECKSUM", "DATASUM"], sign=False)
    offset, _ = fc.flip_in_card(fc.split(raw), 1, key, column)
    return fc.flip(raw, offset, mask)


RATE = {"BUNIT": "'electron/s'"}
#: (id, the current frame's bytes, the command ('cur': apply-persistence CASE earlier; 'measure'), needles)
HEADER_CASES = [
    # item 4: a bit flipped in NAXIS1 under a CHECKSUM (the keyword, the value), and without one
    ("naxis1-name-signed", lambda: flipped("frame", "NAXIS1", 5, 0x02), "cur", ["CHECKSUM"]),
    ("naxis1-value-signed", lambda: flipped("frame", "NAXIS1", 29, 0x01), "cur", ["CHECKSUM"]),
    ("naxis1-equals-unsigned", lambda: flipped("frame", "NAXIS1", 8, 0x01, signed=False), "cur", ["NAXIS1 missing"]),
    ("naxis1-value-unsigned", lambda: flipped("frame", "NAXIS1", 28, 0x10, signed=False), "cur",
     ["NAXIS1", "not a FITS value"]),
    ("naxis1-name-unsigned", lambda: flipped("frame", "NAXIS1", 5, 0x02, signed=False), "cur", ["HDU 1", "corrupt"]),
    # item 4: a string where seconds are needed, a BEL in a string value (the reader and measure)
    ("samptime-soon", lambda: fc.edit(fc.seeds()["ramp"], 1, replace={"SAMPTIME": fc.card("SAMPTIME", "'soon'")}),
     "cur", ["SAMPTIME='soon'", "not a number"]),
    ("bel-in-value", lambda: frame_with(insert={"OBJECT": "'ab\x07d'"}), "cur", ["OBJECT", "0x07", r"\x07"]),
    ("bel-in-value-measure", lambda: frame_with(insert={"OBJECT": "'ab\x07d'"}), "measure", ["0x07"]),
    ("bel-in-primary-measure", lambda: frame_with(hdu=0, insert={"OBJECT": "'ab\x07d'"}), "measure", ["HDU 0", "0x07"]),
    # item 5: cards astropy would call corrupt are never copied into an output
    ("unterminated-quote", lambda: frame_with(insert={"TARGNAME": "'abcd "}), "cur",
     ["TARGNAME", "not a FITS value"]),
    ("non-ascii-keyword", lambda: fc.edit(fc.seeds()["frame"], 1, insert=[fc.card("TARG\xc9", "1")]), "cur",
     ["0xc9", "not printable ASCII"]),
    # item 5: values that would silently give the input back, or an all-inf output
    ("rate-exptime-0", lambda: frame_with(replace={**RATE, "EXPTIME": "0.0"}), "cur", ["exposure time is 0 s"]),
    ("rate-expstart-expend", lambda: frame_with(replace={**RATE, "EXPEND": "60000.01157407407"}), "cur",
     ["lasts 0 s", "EXPSTART/EXPEND"]),
    ("rate-expstart-1e300", lambda: frame_with(replace={**RATE, "EXPSTART": "1E300", "EXPEND": "1E300"}), "cur",
     ["MJD 1e+300", "EXPSTART/EXPEND", "corrupt"]),
    ("dn-gain-1e308", lambda: frame_with(replace={"BUNIT": "'DN'", "GAIN": "1E308"}), "cur", ["gain 1e+308", "GAIN"]),
    ("bzero-1e300", lambda: bzero_frame("1E300"), "cur", ["BZERO = 1e+300", "corrupt"]),
]

#: twins that must work: the same edits with values a detector has
TWINS = [
    ("rate-exptime-100", lambda: frame_with(replace={**RATE, "EXPTIME": "100.0"})),
    ("dn-gain-2", lambda: frame_with(replace={"BUNIT": "'DN'", "GAIN": "2.0"})),
    ("bzero-32768", lambda: bzero_frame("32768.0")),
    ("quoted-ascii", lambda: frame_with(insert={"TARGNAME": "'abcd'"})),
]


def bzero_frame(bzero: str) -> bytes:
    """The frame seed's pixels as 16-bit integers with ``BZERO`` (signed)."""
    seed = fc.seeds()["frame"]
    with fits.open(__import__("io").BytesIO(seed)) as hdul:
        hdr = hdul[1].header.copy()
        data = np.clip(np.round(hdul[1].data), 0, 30000).astype(np.int16)
    for key in ("CHECKSUM", "DATASUM"):
        hdr.remove(key, ignore_missing=True)
    buf = __import__("io").BytesIO()
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data, hdr, name="SCI")]).writeto(buf)
    return fc.edit(buf.getvalue(), 1, insert=[fc.card("BZERO", bzero)])


def run_case(raw: bytes, command: str, inputs, folder: Path):
    case = folder / "case.fits"
    case.write_bytes(raw)
    out = folder / "out"
    out.mkdir()
    if command == "cur":
        args = ["apply-persistence", case, inputs["earlier"], "--mode", "add", "-o", out / "o.fits"]
    else:
        args = ["measure", case, "--catalog", inputs["truth"], "--psf", inputs["psf"], "--stamp", "16",
                "-o", out / "o.fits"]
    run = perscli(args, cwd=folder)
    assert case.read_bytes() == raw, "the input was modified"
    return run, listing(out), case


@pytest.mark.parametrize("make, command, needles", [c[1:] for c in HEADER_CASES], ids=[c[0] for c in HEADER_CASES])
def test_a_header_fault_is_one_line(make, command, needles, inputs, tmp_path, untouched):
    run, left, case = run_case(make(), command, inputs, tmp_path)
    refused(run, str(case), *needles)
    assert left == []


@pytest.mark.parametrize("make", [t[1] for t in TWINS], ids=[t[0] for t in TWINS])
def test_the_twins_of_the_header_faults_work(make, inputs, tmp_path, untouched):
    run, left, case = run_case(make(), "cur", inputs, tmp_path)
    assert run.returncode == 0, error_lines(run)
    assert left == ["o.fits"]
    with fits.open(tmp_path / "out" / "o.fits", checksum=True) as out, fits.open(case) as cur:
        # not the input given back: the earlier exposure's persistence is in it, every value finite
        assert np.isfinite(out["SCI"].data).all()
        assert not np.array_equal(out["SCI"].data, cur["SCI"].data)


# =================================================================================================
# Item 7: two writers, a failing figure, interrupts
# =================================================================================================

def wait_reading_stdin(proc, deadline: float = 120.0) -> None:
    """Wait until ``proc`` is blocked reading its standard input (a pipe nobody writes yet)."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        assert proc.poll() is None, proc.stderr.read()
        try:
            wchan = Path(f"/proc/{proc.pid}/wchan").read_text()
            syscall = Path(f"/proc/{proc.pid}/syscall").read_text().split()
        except OSError:
            wchan, syscall = "", []
        # x86-64's read(2) is 0, arm64's 63; its first argument, the descriptor, is 0
        if "pipe" in wchan or (syscall[:2] in (["0", "0x0"], ["63", "0x0"])):
            return
        time.sleep(0.05)
    pytest.fail("perscli never read its standard input")


def held_writer(args, cwd):
    """``perscli ARGS`` reading '-' from a pipe: started, and waiting for its input."""
    proc = subprocess.Popen([PERSCLI, *[str(a) for a in args]], cwd=cwd, stdin=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=clean_env())
    wait_reading_stdin(proc)
    return proc


def test_of_two_writers_of_one_output_only_the_first_to_finish_publishes(inputs, tmp_path, untouched):
    # A passes the "exists" check and waits for its input; B writes the output meanwhile; A then finds it
    a = held_writer(["budget", "-", "-o", "same.fits", "-q"], tmp_path)
    try:
        b = perscli(["budget", inputs["xi"], "-o", "same.fits", "-q"], cwd=tmp_path)
        assert b.returncode == 0, error_lines(b)
        written = (tmp_path / "same.fits").read_bytes()
        _, err = a.communicate(Path(inputs["xi"]).read_bytes(), timeout=TIMEOUT)
    finally:
        a.kill()
        a.wait()
    lines = err.decode().splitlines()
    # said when A comes to write (its check before the work passed), or when it publishes (link(2) fails)
    assert a.returncode == 1 and len(lines) == 1, lines
    assert re.fullmatch(r"Error: same\.fits: already exists( \(another program wrote it meanwhile\))?; use "
                        r"--overwrite to replace it", lines[0]), lines
    assert (tmp_path / "same.fits").read_bytes() == written
    assert listing(tmp_path) == ["same.fits"]


def test_two_writers_started_together(inputs, tmp_path, untouched):
    procs = [subprocess.Popen([PERSCLI, "budget", inputs["xi"], "-o", "same.fits", "-q"], cwd=tmp_path,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=clean_env()) for _ in range(2)]
    results = [(p.wait(timeout=TIMEOUT), p.stderr.read().decode()) for p in procs]
    for p in procs:
        p.stderr.close()
    assert sorted(code for code, _ in results) == [0, 1], results
    loser = next(err for code, err in results if code == 1)
    assert loser.count("\n") == 1 and "same.fits: already exists" in loser, loser
    assert listing(tmp_path) == ["same.fits"]


def test_a_file_written_meanwhile_is_never_replaced(tmp_path):
    from perscli import PerscliError
    from perscli.io.output import atomic_path

    dest = tmp_path / "o.fits"
    with pytest.raises(PerscliError, match="already exists \\(another program wrote it meanwhile\\)"):
        with atomic_path(str(dest)) as tmp:
            Path(tmp).write_bytes(b"mine")
            dest.write_bytes(b"theirs")
    assert dest.read_bytes() == b"theirs" and listing(tmp_path) == ["o.fits"]


def test_an_output_group_publishes_all_or_nothing(tmp_path):
    from perscli import PerscliError
    from perscli.io.output import OutputGroup, atomic_path, declare_output

    first, second = tmp_path / "a.fits", tmp_path / "b.png"
    with OutputGroup().active():
        declare_output(str(first))
        declare_output(str(second))
        with atomic_path(str(first)) as tmp:
            Path(tmp).write_bytes(b"table")
        assert not first.exists()                          # staged until the figure is finished too
        with pytest.raises(PerscliError, match="b.png: already exists"):
            with atomic_path(str(second)) as tmp:
                Path(tmp).write_bytes(b"figure")
                second.write_bytes(b"theirs")              # another program takes the figure's name
    assert listing(tmp_path) == ["b.png"] and second.read_bytes() == b"theirs"
    # finished together, published together: as soon as the last one is ready, before the command ends
    second.unlink()
    with OutputGroup().active():
        declare_output(str(first))
        declare_output(str(second))
        for dest in (first, second):
            with atomic_path(str(dest)) as tmp:
                Path(tmp).write_bytes(dest.name.encode())
        assert listing(tmp_path) == ["a.fits", "b.png"] and first.read_bytes() == b"a.fits"


@pytest.mark.parametrize("sig, code, line", [
    (signal.SIGINT, 130, "Error: interrupted (Ctrl-C) by SIGINT; no output written"),
    (signal.SIGTERM, 143, "Error: terminated by SIGTERM; no output written"),
], ids=["SIGINT", "SIGTERM"])
def test_an_interrupt_is_one_line_and_leaves_nothing(sig, code, line, tmp_path):
    proc = held_writer(["budget", "-", "-o", "o.fits", "--plot", "o.png"], tmp_path)
    try:
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=TIMEOUT)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == code and err.decode().splitlines() == [line], (proc.returncode, err)
    assert listing(tmp_path) == []


@pytest.mark.parametrize("scheduler", ["serial", pytest.param("local", marks=pytest.mark.slow)])
def test_an_interrupted_study_keeps_what_it_finished(tmp_path, scheduler):
    # Ctrl-C reaches the whole process group (Dask's worker processes too, which must leave it to perscli: no
    # traceback of theirs); the products finished stay for the resumed run
    proc = subprocess.Popen([PERSCLI, "study", "--preset", "ci", "-o", "s", "--scheduler", scheduler, "-q"],
                            cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env=clean_env(), start_new_session=True)
    try:
        end = time.monotonic() + TIMEOUT
        while not (tmp_path / "s" / ".state" / "catalog.json").exists():
            assert proc.poll() is None and time.monotonic() < end, proc.stderr.read()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=TIMEOUT)
    finally:
        proc.kill()
        proc.wait()
    lines = err.decode().splitlines()
    assert proc.returncode == 130, lines
    assert lines == ["Error: interrupted (Ctrl-C) by SIGINT; finished parts are kept; run the same command again "
                     "to resume"], lines
    assert (tmp_path / "s" / "truth.fits").exists() and temporaries(tmp_path) == []


@pytest.mark.parametrize("command, outcome", [("study", "finished parts are kept; run the same command again to "
                                                          "resume"),
                                              ("render", "no output written"), (None, "no output written")])
def test_the_interrupt_line_says_what_is_left(command, outcome):
    from perscli.cli.main import interrupted_message
    from perscli.executor import Terminated

    exc = Terminated(signal.SIGTERM)
    exc.command = command
    assert interrupted_message(exc) == f"terminated by SIGTERM; {outcome}"


# =================================================================================================
# Item 9: -o /dev/stdout, --exptime
# =================================================================================================

@pytest.mark.parametrize("name", ["/dev/stdout", "/dev/fd/1"])
def test_dev_stdout_is_standard_output(name, inputs, tmp_path, untouched):
    target = tmp_path / "existing.fits"
    target.write_bytes(b"")                      # the shell's '>' made it: it exists
    with open(target, "wb") as fh:
        run = perscli(["budget", inputs["xi"], "-o", name, "-q"], cwd=tmp_path, stdout=fh)
    assert run.returncode == 0 and run.stderr == b"", run.stderr
    with fits.open(target, checksum=True) as hdul:
        assert hdul[1].name == "BUDGET"
    piped = perscli(["budget", inputs["xi"], "-o", name, "-q"], cwd=tmp_path)
    assert piped.returncode == 0 and piped.stdout.startswith(b"SIMPLE  =")
    assert listing(tmp_path) == ["existing.fits"]


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e300"])
def test_exptime_must_be_a_positive_finite_time(value, inputs, tmp_path, untouched):
    run = perscli(["apply-persistence", inputs["later"], inputs["earlier"], "--exptime", value, "-o", "o.fits"],
                  cwd=tmp_path)
    refused(run, "Invalid value for '--exptime'", code=2)
    assert listing(tmp_path) == []


# =================================================================================================
# The library pieces the command line relies on
# =================================================================================================

@pytest.mark.parametrize("code, words", [
    (errno.ENOSPC, "no space left on the device of"), (errno.EFBIG, "file-size limit"),
    (errno.EROFS, "read-only file system"), (errno.EACCES, "permission denied"),
    (getattr(errno, "EDQUOT", errno.ENOSPC), "quota" if hasattr(errno, "EDQUOT") else "no space"),
])
def test_write_error_names_the_output_and_the_fix(code, words, tmp_path):
    from perscli.io.output import write_error

    message = str(write_error(str(tmp_path / "o.fits"), OSError(code, os.strerror(code))))
    assert message.startswith(f"{tmp_path / 'o.fits'}: cannot write") and words in message
    assert "\n" not in message and ";" in message            # the fault, then what to do


def test_an_os_error_without_a_file_names_the_outputs(tmp_path):
    from perscli.cli.helpers import describe_os_error

    fault = OSError(errno.ENOSPC, "No space left on device")
    assert describe_os_error(fault, ["o.fits", "o.png"]).startswith("o.fits or o.png: cannot write: no space")
    temp = OSError(errno.EFBIG, "File too large", str(tmp_path / ".perscli-diagnose-x" / "report.json"))
    assert describe_os_error(temp, ["d"]).startswith("d: cannot write: the file would exceed")
    # permission denied on a file the user named is not taken for a write fault (it may be an input)
    read = PermissionError(errno.EACCES, "Permission denied", "in.fits")
    assert describe_os_error(read, ["o.fits"]) == "in.fits: Permission denied"


def test_standard_output_wrappers(monkeypatch):
    from perscli import PerscliError
    from perscli.io.output import ClosedStdout, GuardedStdout

    closed = ClosedStdout()
    for use in (lambda: closed.write("x"), closed.isatty, lambda: closed.buffer):
        with pytest.raises(PerscliError, match="standard output is closed"):
            use()
    closed.flush()                                  # the interpreter's flush at exit is quiet

    class Full:
        encoding, errors = "utf-8", "strict"

        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self):
            raise OSError(errno.ENOSPC, "No space left on device")

    silenced = []
    monkeypatch.setattr("perscli.io.output._silence_stdout", lambda: silenced.append(True))
    guarded = GuardedStdout(Full())
    with pytest.raises(PerscliError, match="standard output: cannot write: no space left"):
        guarded.write("")                           # click's probe: the fault is then remembered
    with pytest.raises(PerscliError, match="standard output: cannot write"):
        guarded.write("text")
    guarded.flush()                                 # said once to the writer; the exit flush is quiet
    assert guarded.encoding == "utf-8" and silenced
