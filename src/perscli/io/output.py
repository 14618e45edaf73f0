"""Writing FITS outputs: provenance, checksums, atomic replacement, stdout.

Every output carries ``CREATOR = 'perscli X.Y.Z'``, ``DATE``, a HISTORY card
per processing step, one keyword per parameter, the inputs with their
DATASUM, and CHECKSUM/DATASUM on every HDU.  Files are written to a temporary
file in the destination folder and renamed into place, so a Makefile never
sees a half-written target and an error leaves nothing behind.
"""

from __future__ import annotations

import datetime as _dt
import io
import os
import sys
import tempfile

from astropy.io import fits

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
        raise PerscliError(f"{dest}: folder {folder} does not exist")
    for name in inputs:
        if name != "-" and os.path.exists(name) and os.path.exists(dest) and os.path.samefile(name, dest):
            raise PerscliError(f"{dest}: is also an input; inputs are never modified: choose another output")
    if os.path.exists(dest) and not overwrite:
        raise PerscliError(f"{dest}: already exists; use --overwrite to replace it")


def add_provenance(header: fits.Header, *, step: str, params: dict | None = None,
                   inputs=(), seed: int | None = None) -> fits.Header:
    """Record who made an output, from what and how.

    Parameters
    ----------
    header : astropy.io.fits.Header
        Updated in place (and returned).
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


def write_fits(hdul: fits.HDUList, dest: str, *, overwrite: bool = False, stdout=None) -> None:
    """Write ``hdul`` with checksums, atomically, or to standard output.

    Parameters
    ----------
    hdul : astropy.io.fits.HDUList
    dest : str
        Path, or '-' for standard output.
    overwrite : bool
        Replace an existing file.
    stdout : binary file, optional
        Stream for '-' (default ``sys.stdout.buffer``).
    """
    if dest == "-":
        buffer = io.BytesIO()
        hdul.writeto(buffer, checksum=True, output_verify="fix+warn")
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
            hdul.writeto(fh, checksum=True, output_verify="fix+warn")
        os.chmod(tmp, 0o644 & ~_umask())
        os.replace(tmp, dest)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
