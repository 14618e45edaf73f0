"""Writing FITS outputs: provenance, checksums, atomic replacement, stdout.

Every output carries ``CREATOR = 'perscli X.Y.Z'``, ``DATE``, a HISTORY card
per processing step, one keyword per parameter, the inputs with their
DATASUM, and CHECKSUM/DATASUM on every HDU.  Files are written to a temporary
file in the destination folder and renamed into place, so a Makefile never
sees a half-written target and an error leaves nothing behind.

Two kinds of output are written the same way: a list of
:class:`perscli.io.fitsfile.OutHDU` (images streamed by perscli's own writer)
and an ``astropy.io.fits.HDUList`` (tables and anything else).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import os
import sys
import tempfile

from .. import PerscliError, __version__

CREATOR = f"perscli {__version__}"


def check_output(dest: str, *, overwrite: bool = False, inputs=()) -> None:
    """Refuse an output before any work is done.

    Parameters
    ----------
    dest : str
        Output path, or '-' for standard output.
    overwrite : bool
        Allow replacing an existing file.
    inputs : iterable of str
        Input paths: an output may never replace one of them.
    """
    if dest == "-":
        if sys.stdout.isatty():
            raise PerscliError("refusing to write FITS to a terminal: give -o FILE or redirect standard output")
        return
    folder = os.path.dirname(os.path.abspath(dest))
    if not os.path.isdir(folder):
        raise PerscliError(f"{dest}: folder {folder} does not exist; create it or choose another output")
    if os.path.isdir(dest):
        raise PerscliError(f"{dest}: is a directory; give a file name for the output")
    for name in inputs:
        if name != "-" and os.path.exists(name) and os.path.exists(dest) and os.path.samefile(name, dest):
            raise PerscliError(f"{dest}: is also an input; inputs are never modified: choose another output")
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")


def add_provenance(header, *, step: str, params: dict | None = None, inputs=(), seed: int | None = None):
    """Record who made an output, from what and how.

    Parameters
    ----------
    header : astropy.io.fits.Header or perscli.io.fitsfile.OutHDU
        Updated in place (and returned): anything with item assignment of
        ``(value, comment)`` and ``add_history``.
    step : str
        One line for the HISTORY card, e.g. 'apply-persistence mode=add'.
    params : dict
        KEYWORD -> value or (value, comment); keywords of at most 8 characters.
    inputs : iterable of (str, str, int)
        (keyword stem of at most 5 characters, file name, DATASUM).  Writes
        ``<stem>`` = name and ``<stem>DS`` = DATASUM.
    seed : int, optional
        Random seed, written as SEED.
    """
    header["CREATOR"] = (CREATOR, "software that made this file")
    header["DATE"] = (_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S"),
                      "UTC date this file was written")
    for key, value in (params or {}).items():
        header[key] = value
    for stem, name, datasum in inputs:
        header[stem] = (os.path.basename(name) if name != "-" else "stdin", "input file")
        header[f"{stem}DS"] = (str(datasum), f"DATASUM of {stem}'s data as read")
    if seed is not None:
        header["SEED"] = (int(seed), "random seed")
    header.add_history(f"{CREATOR}: {step}")
    return header


@contextlib.contextmanager
def atomic_output(dest: str, *, overwrite: bool = False, stdout=None):
    """A binary stream for ``dest`` that becomes the file only if the block succeeds.

    Parameters
    ----------
    dest : str
        Path, or '-' for standard output (buffered, written at the end).
    overwrite : bool
        Replace an existing file.
    stdout : binary file, optional
        Stream for '-' (default ``sys.stdout.buffer``).
    """
    if dest == "-":
        buffer = io.BytesIO()
        yield buffer
        stream = stdout if stdout is not None else sys.stdout.buffer
        try:
            stream.write(buffer.getbuffer())
            stream.flush()
        except BrokenPipeError:
            # the reader went away (e.g. `| head`): not our error
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")
    folder = os.path.dirname(os.path.abspath(dest))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(dest)}.", suffix=".part", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, dest)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_hdus(hdus, dest: str, *, overwrite: bool = False, stdout=None) -> None:
    """Write :class:`~perscli.io.fitsfile.OutHDU` s with checksums, atomically or to stdout."""
    from .fitsfile import Writer

    with atomic_output(dest, overwrite=overwrite, stdout=stdout) as stream:
        writer = Writer(stream)
        for hdu in hdus:
            writer.write(hdu)


def write_fits(hdul, dest: str, *, overwrite: bool = False, stdout=None) -> None:
    """Write an ``astropy.io.fits.HDUList`` with checksums, atomically or to stdout."""
    with atomic_output(dest, overwrite=overwrite, stdout=stdout) as stream:
        hdul.writeto(stream, checksum=True, output_verify="fix+warn")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
