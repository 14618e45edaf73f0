"""Small FITS files for the I/O and command-line tests, helpers to check files on disk, and the
command-line harness every test file uses: :func:`invoke`, :func:`run`, :func:`one_line_error` and
:func:`expect_error`.

Every writer takes the destination path first and returns it as a ``str``;
header keywords are given as a dict (FITS keyword names such as ``MJD-BEG``
or ``DATE-OBS`` cannot be Python identifiers).
"""

from __future__ import annotations

import gc
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner

DAY = 86400.0
T0 = 60000.0          # MJD of the first test exposure
SHAPE = (32, 32)


def _header(keywords) -> fits.Header:
    hdr = fits.Header()
    for key, value in (keywords or {}).items():
        hdr[key] = value
    return hdr


def timing(start, exptime=100.0):
    """EXPSTART/EXPEND/EXPTIME keywords of an exposure of ``exptime`` seconds starting at MJD ``start``."""
    return {"EXPSTART": start, "EXPEND": start + exptime / DAY, "EXPTIME": exptime}


def image_file(path, data, keywords=None, *, primary=False, primary_keywords=None, checksum=False):
    """An image: in a SCI extension (default) or in the primary HDU (``primary=True``).

    ``keywords`` go to the header of the HDU holding the data,
    ``primary_keywords`` to the primary header when the data are in an extension.
    """
    data = np.asarray(data)
    if primary:
        hdul = fits.HDUList([fits.PrimaryHDU(data, _header(keywords))])
    else:
        hdul = fits.HDUList([fits.PrimaryHDU(header=_header(primary_keywords)),
                             fits.ImageHDU(data, _header(keywords), name="SCI")])
    hdul.writeto(path, overwrite=True, checksum=checksum)
    return str(path)


def frame_file(path, data=None, *, start=T0, exptime=100.0, bunit="electron", extra=None, **kw):
    """An image in a SCI extension with BUNIT and EXPSTART/EXPEND/EXPTIME timing."""
    if data is None:
        data = np.full(SHAPE, 100.0)
    keywords = {}
    if bunit is not None:
        keywords["BUNIT"] = bunit
    if start is not None:
        keywords.update(timing(start, exptime))
    elif exptime is not None:
        keywords["EXPTIME"] = exptime
    keywords.update(extra or {})
    return image_file(path, data, keywords, **kw)


def cube_file(path, cube, read_times, keywords=None, *, table_name="READTIMES", column="TIME"):
    """A 3-D cube (read, y, x) in the primary HDU with a READTIMES binary table."""
    table = fits.BinTableHDU.from_columns(
        [fits.Column(column, "D", array=np.asarray(read_times, dtype=np.float64))], name=table_name)
    fits.HDUList([fits.PrimaryHDU(np.asarray(cube), _header(keywords)), table]).writeto(path, overwrite=True)
    return str(path)


def wfc3_ramp_file(path, reads, samptimes, keywords=None, *, primary_keywords=None, samptime=True,
                   file_order=None):
    """A WFC3-IR MULTIACCUM file.

    ``reads`` and ``samptimes`` are in time order (zeroth read first).  As in
    a WFC3 raw file, the last read is stored as SCI,1 and the zeroth read as
    SCI,NSAMP, each followed by its ERR and DQ extensions.  ``file_order``
    (a permutation of EXTVER values) changes the order of the SCI groups in
    the file.  ``samptime=False`` leaves out the SAMPTIME keywords.
    """
    nsamp = len(reads)
    primary = _header(primary_keywords)
    primary["NSAMP"] = nsamp
    hdus = [fits.PrimaryHDU(header=primary)]
    order = list(file_order) if file_order is not None else list(range(1, nsamp + 1))
    for ver in order:
        k = nsamp - ver                      # time index of SCI,ver
        hdr = _header(keywords)
        if samptime:
            hdr["SAMPTIME"] = float(samptimes[k])
        data = np.asarray(reads[k])
        hdus.append(fits.ImageHDU(data, hdr, name="SCI", ver=ver))
        hdus.append(fits.ImageHDU(np.ones_like(data, dtype=np.float32), name="ERR", ver=ver))
        hdus.append(fits.ImageHDU(np.zeros(data.shape, dtype=np.int16), name="DQ", ver=ver))
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return str(path)


def snapshot(*paths):
    """{path: (bytes, mtime_ns)} of existing files, to show that inputs are left unchanged."""
    state = {}
    for p in paths:
        p = str(p)
        if os.path.isfile(p):
            state[p] = (Path(p).read_bytes(), os.stat(p).st_mtime_ns)
    return state


def listing(folder):
    """Sorted names in ``folder`` (hidden files included)."""
    return sorted(os.listdir(folder))


def cards_except(path, skip=("DATE", "CHECKSUM")):
    """Every header card of every HDU as (hdu, keyword, value, comment), without the ``skip`` keywords."""
    out = []
    with fits.open(path) as hdul:
        for i, hdu in enumerate(hdul):
            for card in hdu.header.cards:
                if card.keyword not in skip:
                    out.append((i, card.keyword, card.value, card.comment))
    return out


def raw_cards_masked(path, skip=("DATE", "CHECKSUM")):
    """The file's bytes, with the 80-character card images of the ``skip`` keywords blanked."""
    raw = bytearray(Path(path).read_bytes())
    with fits.open(path) as hdul:
        for hdu in hdul:
            info = hdu.fileinfo()
            loc, end = info["hdrLoc"], info["datLoc"]
            for pos in range(loc, end, 80):
                key = raw[pos:pos + 8].decode("ascii").rstrip()
                if key in skip:
                    raw[pos:pos + 80] = b" " * 80
    return bytes(raw)


@pytest.fixture
def collect_leaked_files():
    """Collect file handles a test leaked, at its own teardown (import this name to use it).

    For the tests of broken files: if a reader leaks the handle of a truncated
    input, its ResourceWarning is raised here rather than at a random moment of a
    later test (perscli 61e1e4a leaked it and mistook such warnings for truncation).
    """
    yield
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        gc.collect()


# -- running commands -----------------------------------------------------------------------------
# One home for the command-line harness: every test runs perscli through these (issue "one home per concept").

def invoke(*args, **kw):
    """Run the perscli group with CliRunner; stdout and stderr are separate (click >= 8.2)."""
    from perscli.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], **kw)


def commands(group=None) -> dict:
    """{name: command} of the perscli group (or of ``group``, e.g. pointings), each command loaded: the group
    imports a command's module only when asked for it (perscli.cli.main.LazyGroup), so its ``commands`` dict,
    click's store of commands added eagerly, holds none of them."""
    import click

    from perscli.cli.main import cli

    group = cli if group is None else group
    ctx = click.Context(group, info_name=group.name)
    return {name: group.get_command(ctx, name) for name in group.list_commands(ctx)}


def leaf_commands():
    """[(name, command)] of every command that runs: 'render', the subcommands of a group ('pointings plan'),
    and the flag form a group still runs as a deprecated alias (perscli.cli.pointings.FlagFormGroup.legacy,
    as 'pointings')."""
    import click

    out = []

    def walk(name, cmd):
        if isinstance(cmd, click.Group):
            if getattr(cmd, "legacy", None) is not None:
                out.append((name, cmd.legacy))
            for sub, child in sorted(commands(cmd).items()):
                walk(f"{name} {sub}", child)
        else:
            out.append((name, cmd))

    for name, cmd in sorted(commands().items()):
        walk(name, cmd)
    return out


def command_named(name: str):
    """The command 'render', 'pointings plan' or (a group's flag form) 'pointings' of :func:`leaf_commands`."""
    return dict(leaf_commands())[name]


def run(*args, code=0, **kw):
    """``perscli ARGS`` (:func:`invoke`), asserting its exit status ``code``; returns click's result.

    ``code=None`` asserts nothing (the caller looks at the result).  A wrong
    status shows stdout, stderr and the exception (with its traceback).
    """
    result = invoke(*args, **kw)
    if code is not None:
        assert result.exit_code == code, _failure(result)
    return result


def _failure(result):
    """What a command said (and raised, other than SystemExit), for an assertion's message."""
    import traceback

    said = f"exit status {result.exit_code}\n--- stdout:\n{result.stdout}\n--- stderr:\n{result.stderr}"
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        said += "\n--- exception:\n" + "".join(traceback.format_exception(*result.exc_info))
    return said


#: the start of the one line of a usage error (exit status 2): "perscli render: error: ..."
USAGE_PREFIX = re.compile(r"perscli( [\w-]+)*: error: ")
#: ...and its end: where the command's help is
USAGE_HINT = re.compile(r" \(see 'perscli( [\w-]+)* -h'\)$")


#: one usage error: which command, what, and where its help is
USAGE_LINE = re.compile(r"^(perscli(?: [a-z-]+)*): error: (.+) \(see '\1 -h'\)$")


def usage_error(result, command="perscli"):
    """The message of a one-line usage error of ``command`` (exit 2, nothing on stdout)."""
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    match = USAGE_LINE.match(lines[0])
    assert match, lines[0]
    assert match.group(1) == command, lines[0]
    return match.group(2)


def one_line_error(result, *needles, code=1, out=None, allow_warnings=False):
    """Assert that a command failed in one line; returns that line.

    Exit status ``code``; nothing on stdout; exactly one line on stderr (with
    ``allow_warnings``, lines starting 'perscli: warning' aside) and no traceback.
    The line starts 'Error: ' (status 1) or 'perscli COMMAND: error: '
    (status 2, a usage error), and holds every needle (``str(needle)``,
    case-sensitive).  ``out``: an output that must not exist.
    """
    assert result.exit_code == code, _failure(result)
    assert result.stdout == "", _failure(result)
    assert "Traceback" not in result.stderr, _failure(result)
    lines = result.stderr.splitlines()
    if allow_warnings:
        lines = [line for line in lines if not line.startswith("perscli: warning")]
    assert len(lines) == 1, _failure(result)
    if code == 1:
        assert lines[0].startswith("Error: "), lines[0]
    elif code == 2:
        assert USAGE_PREFIX.match(lines[0]), lines[0]
        assert "Usage:" not in result.stderr and USAGE_HINT.search(lines[0]), lines[0]
    for needle in map(str, needles):
        assert needle in lines[0], (needle, lines[0])
    if out is not None:
        assert not os.path.lexists(out), f"{out} written"
    return lines[0]


def expect_error(tmp_path, args, *needles, command=(), code=1, out="out.fits", inputs=None, any_of=(),
                 fix_words=(), words_outside_paths=False, allow_warnings=False):
    """Run ``perscli COMMAND ARGS -o OUT`` expecting a one-line error (:func:`one_line_error`); returns the line.

    Besides the one line (exit status ``code``, nothing on stdout, every
    needle): no file appears in or leaves ``tmp_path`` (no output, no
    temporary file) and the inputs, and an existing OUT, are unchanged.

    ``command``: words put before ``args`` (a string or a sequence), for a
    module's ``functools.partial``.  ``out``: the output, relative to
    ``tmp_path`` (None: no ``-o``, for the error of a missing one).  ``inputs``: the files that must be left unchanged (by
    default every argument naming a file).  ``any_of``: the line holds at
    least one of these; ``fix_words``: at least one of these (words that say
    what to do).  ``words_outside_paths``: the needles (other than paths in
    ``tmp_path``), ``any_of`` and ``fix_words`` are looked for outside the
    paths in ``tmp_path`` (pytest names it after the test: 'truncated', ...).
    """
    argv = [*((command,) if isinstance(command, str) else command), *args]
    out = None if out is None else Path(tmp_path, out)
    inputs = [str(a) for a in argv if os.path.isfile(str(a))] if inputs is None else inputs
    outs = () if out is None else (out,)
    before, files = snapshot(*inputs, *outs), listing(tmp_path)
    result = invoke(*argv, *(("-o", out) if out is not None else ()))
    line = one_line_error(result, code=code, allow_warnings=allow_warnings)
    if code == 2:
        assert line.startswith(f"perscli {argv[0]}: error: "), line
    tmp = str(tmp_path)
    words = line.replace(tmp, "<tmp>") if words_outside_paths else line
    for needle in map(str, needles):
        assert needle in (line if needle.startswith(tmp) else words), (needle, line)
    if any_of:
        assert any(alt in words for alt in any_of), (any_of, line)
    if fix_words:
        assert any(w in words for w in fix_words), ("no fix suggested", line)
    assert listing(tmp_path) == files          # no output, no temporary file
    assert snapshot(*inputs, *outs) == before  # inputs (and an existing output) unchanged
    return line
