"""Reading FITS binary tables (schedules, Gaia chunks, pointings, truth catalogues, SHAPES, XI).

:func:`read_table` opens a file with :func:`perscli.io.fitsfile.open_fits` (so
that a file that is not FITS, is truncated, or whose CHECKSUM/DATASUM do not
match gives one clear line; ``-``, FIFOs, ``.fits.gz`` and ``file[EXT]`` work
as for frames) and hands out its first binary table; CFITSIO (fitsio) reads
only the columns asked for, so a million-row catalogue is never read whole.
:meth:`InputTable.column` names the file and column at fault.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError


@dataclass
class InputTable:
    """A FITS binary table opened for reading.

    Attributes
    ----------
    name : str
        The path as given ('-' for standard input).
    label : str
        The name used in messages ('stdin' for '-').
    index : int
        HDU number of the table in the file.
    header : perscli.io.fitsfile.Header
        The table's header.
    datasum : int
        FITS DATASUM of the table's data as stored (for provenance; verified
        against the header's when it states one).
    what : str
        What the file should be ('Gaia reference catalog', 'schedule'), for messages.
    """

    name: str
    label: str
    index: int
    header: object
    datasum: int
    what: str
    hdu: object = field(repr=False, default=None)
    _cache: dict = field(repr=False, default_factory=dict)

    def __len__(self) -> int:
        return self.hdu.nrows

    @property
    def names(self) -> list:
        """Column names as written."""
        return self.hdu.colnames

    def _tform(self, real: str) -> str:
        k = [n.lower() for n in self.names].index(real.lower()) + 1
        return str(self.header.get(f"TFORM{k}", "")).strip()

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
        names = {n.lower(): n for n in self.names}
        real = names.get(name.lower())
        where = f"{self.label}: HDU {self.index}"
        if real is None:
            listed = ", ".join(needed) if needed else name
            raise PerscliError(f"{where} has no column '{name}'; a {self.what} needs the columns {listed}: "
                               f"check that this is a {self.what}")
        if real not in self._cache:
            self._cache[real] = self.hdu.read_column(real)
        values = self._cache[real]
        tform = self._tform(real)
        if values.ndim != 1:
            raise PerscliError(f"{where}: column '{real}' has {values.shape[1:]} values per row (TFORM "
                               f"{tform}); it must be a single value per row: check that this is a {self.what}")
        ok = {"number": "iuf", "integer": "iu", "text": "SU"}[kind]
        if values.dtype.kind not in ok:
            held = "text" if values.dtype.kind in "SU" else ("floating-point numbers" if values.dtype.kind == "f"
                                                              else f"{values.dtype} values")
            wanted = {"number": "numbers", "integer": "integers", "text": "text"}[kind]
            raise PerscliError(f"{where}: column '{real}' holds {held} (TFORM {tform}) but must hold "
                               f"{wanted}: check that this is a {self.what}")
        if kind == "text":
            if values.dtype.kind == "S":
                values = np.char.decode(values, "ascii", errors="replace")
            return np.char.strip(values.astype(str))
        return values.astype(values.dtype.newbyteorder("="))

    def unit(self, name: str) -> str:
        """TUNITn of a column ('' when absent)."""
        names = [n.lower() for n in self.names]
        k = names.index(name.lower()) + 1
        return str(self.header.get(f"TUNIT{k}", "") or "").strip()


def read_table(name: str, *, what: str, stdin=None) -> InputTable:
    """Open the first binary table of a FITS file (``file[EXT]`` chooses another).

    The file stays open until the process ends or the table is garbage
    collected; :func:`open_table` closes it at the end of a ``with`` block.

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
        Unreadable, not FITS, truncated, corrupt (CHECKSUM/DATASUM), or without a binary table.
    """
    from .fitsfile import open_fits

    fits = open_fits(name, stdin=stdin)
    try:
        if fits.selected is not None:
            hdu = fits.hdus[fits.selected]
            if hdu.kind != "table":
                raise PerscliError(f"{fits.label}: the selected {hdu.label} is not a binary table; "
                                   f"a {what} is a FITS binary table")
        else:
            hdu = _first_table(fits.label, fits.hdus, what)
        if str(hdu.header.get("XTENSION", "BINTABLE")).strip() not in ("BINTABLE", "A3DTABLE"):
            raise PerscliError(f"{fits.label}: {hdu.label} is an ASCII table; a {what} is a FITS binary table")
        datasum = hdu.verify()
        hdu.colnames  # noqa: B018  (a table CFITSIO cannot describe fails here, as one line)
    except (OSError, ValueError) as exc:
        fits.close()
        raise PerscliError(f"{fits.label}: not a readable FITS binary table ({exc}); check that this is a {what}") from None
    except BaseException:
        fits.close()
        raise
    return InputTable(name=name, label=fits.label, index=hdu.index, header=hdu.header, datasum=datasum,
                      what=what, hdu=hdu)


def _first_table(label: str, hdus, what: str):
    """The first binary-table HDU of a file, or one clear error."""
    tables = [h for h in hdus if h.kind == "table"]
    if not tables:
        raise PerscliError(f"{label}: has no binary table HDU; a {what} is a FITS binary table: "
                           f"check that this is a {what}")
    return tables[0]


@contextlib.contextmanager
def open_table(name: str, *, what: str, stdin=None):
    """:func:`read_table` as a context manager that closes the file at the end.

    Only the columns asked for are read (by CFITSIO), which for a catalogue
    of a million objects saves reading the whole table.
    """
    table = read_table(name, what=what, stdin=stdin)
    try:
        yield table
    finally:
        table.hdu.file.close()
