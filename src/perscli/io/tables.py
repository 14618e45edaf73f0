"""Reading FITS binary tables (schedules, Gaia chunks, pointings, truth catalogues).

:func:`read_table` checks a file with perscli's own FITS scanner first (so that
a file that is not FITS, is truncated, or whose data do not match their
stated DATASUM gives one clear line), then parses the table with astropy,
and :meth:`InputTable.column` names the file and column at fault.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from dataclasses import dataclass

import numpy as np

from .. import PerscliError


@dataclass
class InputTable:
    """A FITS binary table read for a scene step.

    Attributes
    ----------
    name : str
        The path as given ('-' for standard input).
    label : str
        The name used in messages ('stdin' for '-').
    index : int
        HDU number of the table in the file.
    header : astropy.io.fits.Header
        The table's header.
    data : astropy.io.fits.FITS_rec
        The rows.
    datasum : int
        FITS DATASUM of the table's data as stored (for provenance).
    what : str
        What the file should be ('Gaia reference catalog', 'schedule'), for messages.
    """

    name: str
    label: str
    index: int
    header: object
    data: object
    datasum: int
    what: str

    def __len__(self) -> int:
        return len(self.data)

    def column(self, name: str, *, kind: str = "number", needed=()) -> np.ndarray:
        """One scalar column as a native-order array, checked.

        Parameters
        ----------
        name : str
            Column name (matched without regard to case, as FITS does).
        kind : {'number', 'integer', 'text'}
            What the column must hold.  Integers are accepted for 'number'.
        needed : iterable of str
            Every column this kind of file needs, listed in the message when
            ``name`` is missing.

        Raises
        ------
        PerscliError
            The column is missing, holds the wrong type, or is not scalar.
        """
        names = {n.lower(): n for n in self.data.columns.names}
        real = names.get(name.lower())
        where = f"{self.label}: HDU {self.index}"
        if real is None:
            listed = ", ".join(needed) if needed else name
            raise PerscliError(f"{where} has no column '{name}'; a {self.what} needs the columns {listed}: "
                               f"check that this is a {self.what}")
        col = self.data.columns[real]
        values = np.asarray(self.data[real])
        if values.ndim != 1:
            raise PerscliError(f"{where}: column '{real}' has {values.shape[1:]} values per row (TFORM "
                               f"{col.format}); it must be a single value per row: check that this is a {self.what}")
        ok = {"number": "iuf", "integer": "iu", "text": "SU"}[kind]
        if values.dtype.kind not in ok:
            held = "text" if values.dtype.kind in "SU" else ("floating-point numbers" if values.dtype.kind == "f"
                                                              else f"{values.dtype} values")
            wanted = {"number": "numbers", "integer": "integers", "text": "text"}[kind]
            raise PerscliError(f"{where}: column '{real}' holds {held} (TFORM {col.format}) but must hold "
                               f"{wanted}: check that this is a {self.what}")
        if kind == "text":
            if values.dtype.kind == "S":
                values = np.char.decode(values, "ascii", errors="replace")
            return np.char.strip(values.astype(str))
        return values.astype(values.dtype.newbyteorder("="))

    def unit(self, name: str) -> str:
        """TUNITn of a column ('' when absent)."""
        names = [n.lower() for n in self.data.columns.names]
        k = names.index(name.lower()) + 1
        return str(self.header.get(f"TUNIT{k}", "")).strip()


def read_bytes(name: str, stdin=None) -> tuple:
    """The bytes of a file, or of standard input for '-'; (label, bytes)."""
    if name == "-":
        stream = stdin if stdin is not None else sys.stdin.buffer
        data = stream.read()
        if not data:
            raise PerscliError("stdin: standard input is empty; pipe a FITS file into it")
        return "stdin", data
    if not os.path.exists(name):
        raise PerscliError(f"{name}: no such file")
    if os.path.isdir(name):
        raise PerscliError(f"{name}: is a directory, not a FITS file; give the path of a file inside it")
    try:
        with open(name, "rb") as fh:
            return name, fh.read()
    except OSError as exc:
        raise PerscliError(f"{name}: cannot be read ({exc.strerror})") from None


def read_table(name: str, *, what: str, stdin=None) -> InputTable:
    """Read the first binary table of a FITS file.

    The file is checked by perscli's own FITS scanner first (so that a file
    that is not FITS, is truncated, or whose data do not match their stated
    DATASUM gives one clear line), then parsed with astropy.

    Parameters
    ----------
    name : str
        Path, or '-' for standard input.
    what : str
        What the file should be, for messages ('schedule', 'Gaia reference catalog').
    stdin : binary file, optional
        Stream to read for '-' (default ``sys.stdin.buffer``).

    Raises
    ------
    PerscliError
        Unreadable, not FITS, truncated, corrupt, or without a binary table.
    """
    from ..io.fitsfile import Source, scan

    label, raw = read_bytes(name, stdin)
    hdus = scan(Source(label, data=raw))
    hdu = _first_table(label, hdus, what)
    datasum = _checked_datasum(label, hdu, hdu.datasum())
    from astropy.io import fits

    try:
        with fits.open(io.BytesIO(raw), memmap=False) as hdul:
            table = hdul[hdu.index]
            header = table.header.copy()
            data = table.data
            if data is None:
                data = fits.FITS_rec.from_columns(table.columns, nrows=0)
            else:
                data = data.copy()
    except (ValueError, KeyError, TypeError, IndexError, OSError) as exc:
        raise PerscliError(f"{label}: HDU {hdu.index} is not a readable FITS binary table ({exc}); "
                           f"check that this is a {what}") from None
    return InputTable(name=name, label=label, index=hdu.index, header=header, data=data,
                      datasum=datasum, what=what)


# -- Roman filters ------------------------------------------------------------------------------

#: Roman WFI imaging filters, bluest first (W146 is the wide filter spanning J to H).


def _first_table(label: str, hdus, what: str):
    """The first binary-table HDU of a scanned file, or one clear error."""
    tables = [h for h in hdus if str(h.header.get("XTENSION", "")).strip() == "BINTABLE"]
    if not tables:
        raise PerscliError(f"{label}: has no binary table HDU; a {what} is a FITS binary table: "
                           f"check that this is a {what}")
    return tables[0]


def _checked_datasum(label: str, hdu, datasum: int) -> int:
    """``datasum``, after checking it against the DATASUM the header states, if any."""
    stated = str(hdu.header.get("DATASUM", "")).strip()
    if stated.isdigit() and int(stated) != datasum:
        raise PerscliError(f"{label}: HDU {hdu.index} data do not match its DATASUM ({stated}, computed "
                           f"{datasum}): the file is corrupt; re-copy it "
                           "(or delete DATASUM if the data were edited on purpose)")
    return datasum


@contextlib.contextmanager
def open_table(name: str, *, what: str, stdin=None):
    """The first binary table of a FITS file, memory-mapped rather than read and copied.

    The same checks and messages as :func:`read_table` and the same
    :class:`InputTable`, but the rows stay in the page cache and only the
    columns asked for are copied, which for a catalogue of a million objects
    saves a copy of the whole table and most of the time.  Standard input
    ('-') is read by :func:`read_table`.  Use as a context manager; take
    columns inside it.
    """
    if name == "-" or not os.path.isfile(name):
        yield read_table(name, what=what, stdin=stdin)
        return
    import mmap

    from astropy.io import fits

    from .. import _kernels
    from .fitsfile import Source, scan

    source = Source(name, path=name)
    try:
        hdus = scan(source)
    finally:
        source.close()
    hdu = _first_table(name, hdus, what)
    with open(name, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
        with memoryview(mapped) as view:
            datasum = _kernels.datasum(view[hdu.data_offset:hdu.data_offset + hdu.data_size]) if hdu.data_size else 0
    datasum = _checked_datasum(name, hdu, datasum)
    try:
        hdul = fits.open(name, memmap=True)
        table = hdul[hdu.index]
        header = table.header.copy()
        data = table.data
        if data is None:
            data = fits.FITS_rec.from_columns(table.columns, nrows=0)
    except (ValueError, KeyError, TypeError, IndexError, OSError) as exc:
        raise PerscliError(f"{name}: HDU {hdu.index} is not a readable FITS binary table ({exc}); "
                           f"check that this is a {what}") from None
    try:
        yield InputTable(name=name, label=name, index=hdu.index, header=header, data=data, datasum=datasum,
                         what=what)
    finally:
        del data, table
        hdul.close()
