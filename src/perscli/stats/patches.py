"""Patch centres for the jackknife of xi: the file given with ``--patch-centers``, checked and read.

:func:`read_patch_centers` (or :func:`read_patch_center_columns` then
:func:`patch_center_vectors`, so that the file is read before any table)
accepts TreeCorr's ``write_patch_centers`` file, a table of ra/dec, or an
earlier ``perscli correlate`` output (its PATCHES table);
:func:`check_patch_centers_file` refuses a name that is not a regular file
before anything is read.
"""

from __future__ import annotations

import io
import os
import stat
import warnings

import numpy as np

from .. import PerscliError
from ..io.fitsreader import open_fits
from ..io.sources import stat_input
from ..scene import DEC_RANGE, RA_RANGE

#: the largest text file of patch centres read (bytes): TreeCorr's text file of 10,000 centres is ~0.7 MB
MAX_PATCH_TEXT = 16 << 20

#: what --patch-centers takes, for messages
_PATCH_FILE = ("TreeCorr's write_patch_centers file, a table of ra/dec or an earlier perscli correlate output "
               "(--patch-centers)")


def check_patch_centers_file(path: str) -> None:
    """Refuse, before anything is read, a --patch-centers name that is not a regular file.

    The checks every input of perscli makes before reading it
    (:func:`perscli.io.sources.open_source`), in one line each: missing, a
    broken or looping symbolic link, a directory, a device (/dev/null,
    /dev/zero: read for ever), a socket, an empty file.  A named pipe is
    refused too, without waiting for a writer: a patch-centre file may be
    FITS or text, which is told from its first bytes and then read again
    from the start, and a pipe cannot be read twice (give the file, or
    ``<(...)`` into a temporary file).

    Raises
    ------
    PerscliError
        One line naming the file and what to give instead.
    """
    st = stat_input(path, kind=_PATCH_FILE, hint=f"; give {_PATCH_FILE}")
    if stat.S_ISDIR(st.st_mode):
        raise PerscliError(f"{path}: is a directory, not a file of patch centres; give {_PATCH_FILE}")
    if stat.S_ISFIFO(st.st_mode):
        raise PerscliError(f"{path}: is a named pipe (FIFO), which cannot be read twice as a patch-centre file "
                           f"is; write it to a file first and give {_PATCH_FILE}")
    if not stat.S_ISREG(st.st_mode):
        raise PerscliError(f"{path}: is not a regular file (a device or socket); give {_PATCH_FILE}")
    if st.st_size == 0:
        raise PerscliError(f"{path}: the file is empty; give {_PATCH_FILE}")
    if not os.access(path, os.R_OK):
        raise PerscliError(f"{path}: cannot be read (permission denied); give {_PATCH_FILE}")


def read_patch_center_columns(path: str) -> dict:
    """The columns of a patch-centre file, by lower-case name (see :func:`read_patch_centers`).

    Checked as every input is (:func:`check_patch_centers_file`), then read
    as FITS (through :func:`perscli.io.fitsreader.open_fits`: structure and
    checksums verified) when it starts with a SIMPLE card (or is gzip
    compressed), else as a whitespace-separated text table with a header
    line of column names (at most :data:`MAX_PATCH_TEXT` bytes).

    Parameters
    ----------
    path : str
        The file (``--patch-centers``).

    Returns
    -------
    dict of str -> ndarray
        Every column of the table, as float64.

    Raises
    ------
    PerscliError
        Not a regular file, unreadable, no table, a text file too large to
        be one, or columns that are not numbers.
    """
    check_patch_centers_file(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(9)
        # FITS, plain or gzip-compressed (open_fits decompresses it): a text file starts otherwise
        is_fits = head == b"SIMPLE  =" or head[:2] == b"\x1f\x8b"
    except OSError as exc:
        raise PerscliError(f"{path}: cannot be read ({exc.strerror}); give {_PATCH_FILE}") from None
    if is_fits:
        with open_fits(path) as fitsin:
            tables = [h for h in fitsin.hdus if h.kind == "table"]
            named = [h for h in tables if h.name == "PATCHES"]
            if not tables:
                raise PerscliError(f"{path}: has no binary table of patch centres (--patch-centers)")
            hdu = (named or tables)[0]
            try:
                return {n.lower(): np.asarray(hdu.read_column(n), dtype=np.float64) for n in hdu.colnames}
            except (TypeError, ValueError) as exc:
                raise PerscliError(f"{path}: not a readable FITS table of patch centres ({exc})") from None

    try:
        with open(path, "rb") as fh:
            # a text table of a few thousand centres is well under a megabyte: a file larger than the cap
            # (a disk image given by mistake, say) is refused instead of being read into memory
            raw = fh.read(MAX_PATCH_TEXT + 1)
        if len(raw) > MAX_PATCH_TEXT:
            raise PerscliError(f"{path}: over {MAX_PATCH_TEXT >> 20} MiB of text: not a file of patch centres; "
                               f"give {_PATCH_FILE}")
        text = raw.decode("utf-8")
    except OSError as exc:
        raise PerscliError(f"{path}: cannot be read ({exc.strerror}); give {_PATCH_FILE}") from None
    except UnicodeDecodeError:
        raise PerscliError(f"{path}: neither FITS nor text: not a file of patch centres; give {_PATCH_FILE}") \
            from None

    try:
        with warnings.catch_warnings():
            # numpy warns (and returns nothing) for a file without data lines: the check below says it
            warnings.simplefilter("ignore")
            arr = np.genfromtxt(io.StringIO(text), names=True, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise PerscliError(f"{path}: not a readable table of patch centres ({exc})") from None
    if arr.dtype.names is None:
        raise PerscliError(f"{path}: no column names: a patch-centre file has columns x y [z] or ra dec")
    return {n.lower(): np.atleast_1d(arr[n]) for n in arr.dtype.names}


def patch_center_vectors(data: dict, coords: str, path: str) -> np.ndarray:
    """Patch centres in TreeCorr's units from the columns of a patch-centre file (see :func:`read_patch_centers`).

    Parameters
    ----------
    data : dict of str -> ndarray
        The file's columns (:func:`read_patch_center_columns`).
    coords : {'radec', 'xy'}
        The positions the centres are for.
    path : str
        The file, for the messages.

    Returns
    -------
    ndarray
        (npatch, 3) unit vectors for 'radec', (npatch, 2) for 'xy'.

    Raises
    ------
    PerscliError
        Columns that do not fit ``coords``, fewer than 2 centres, values
        that are not finite, or ra/dec off the sky.
    """
    if coords == "radec":
        if {"x", "y", "z"} <= set(data):
            centers = np.column_stack([data["x"], data["y"], data["z"]])
        elif {"ra", "dec"} <= set(data):
            # the ranges of every position perscli reads: refused, never wrapped (Dec 100 would fold over the
            # pole into another centre without a word)
            with np.errstate(invalid="ignore"):
                off = (np.abs(data["dec"]) > DEC_RANGE[1]) | (data["ra"] < RA_RANGE[0]) | (data["ra"] > RA_RANGE[1])
            if np.any(off):
                raise PerscliError(f"{path}: {int(off.sum())} patch centre(s) with RA outside [0, 360] or Dec "
                                   "outside [-90, 90] degrees: not positions on the sky")
            ra, dec = np.radians(data["ra"]), np.radians(data["dec"])
            centers = np.column_stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
        else:
            raise PerscliError(f"{path}: patch centres for ra/dec positions need columns x, y, z (TreeCorr's unit "
                               "vectors) or ra, dec (degrees)")
    else:
        if not {"x", "y"} <= set(data) or "z" in data:
            raise PerscliError(f"{path}: patch centres for x/y positions need columns x, y (and no z)")
        centers = np.column_stack([data["x"], data["y"]])
    if len(centers) < 2:
        raise PerscliError(f"{path}: {len(centers)} patch centre(s); the jackknife needs at least 2")
    if not np.all(np.isfinite(centers)):
        raise PerscliError(f"{path}: patch centres that are not finite")
    return centers


def read_patch_centers(path: str, coords: str) -> np.ndarray:
    """Patch centres from a file: TreeCorr's (x, y[, z]) columns or ra/dec in degrees.

    Accepts the file TreeCorr's ``Catalog.write_patch_centers`` writes (FITS
    or ASCII), a FITS table with ra/dec columns (degrees), or a
    ``perscli correlate`` output (its PATCHES table).  The name must be a
    regular file (:func:`check_patch_centers_file`).

    Returns
    -------
    ndarray
        (npatch, 3) unit vectors for coords 'radec'; (npatch, 2) for 'xy'
        (in TreeCorr's internal units, as TreeCorr writes them).

    Raises
    ------
    PerscliError
        See :func:`read_patch_center_columns` and :func:`patch_center_vectors`.
    """
    return patch_center_vectors(read_patch_center_columns(path), coords, path)
