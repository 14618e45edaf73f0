"""Reading FITS binary tables (schedules, Gaia chunks, pointings, truth catalogues, SHAPES, XI).

:func:`read_table` opens a file with :func:`perscli.io.fitsreader.open_fits` (so
that a file that is not FITS, is truncated, or whose CHECKSUM/DATASUM do not
match gives one clear line; ``-``, FIFOs, ``.fits.gz`` and ``file[EXT]`` work
as for frames) and hands out its first binary table; CFITSIO (fitsio) reads
only the columns asked for, so a million-row catalogue is never read whole.
:meth:`InputTable.column` names the file and column at fault.

Catalogues from other tools name their columns differently (SExtractor's
ALPHA_J2000/DELTA_J2000, NUMBER, MAG_AUTO): a column mapping (the commands'
``--columns ra=ALPHA_J2000,dec=DELTA_J2000``; :func:`parse_column_mapping`)
makes a file column answer to the name perscli reads, for every use of the
table, messages included.  SExtractor's FITS_LDAC files (a LDAC_IMHEAD table
holding the image header, then LDAC_OBJECTS) are read from their
LDAC_OBJECTS table.
"""

from __future__ import annotations

import contextlib
import fnmatch
import re
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from .fitsreader import open_fits


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
    header : perscli.io.cards.Header
        The table's header.
    datasum : int
        FITS DATASUM of the table's data as stored (for provenance; verified
        against the header's when it states one).
    what : str
        What the file should be ('Gaia reference catalog', 'schedule'), for messages.
    aliases : dict
        Column mapping, lower-case name perscli reads -> the file's column
        (from ``--columns``); empty when the file's own names are used.
    """

    name: str
    label: str
    index: int
    header: object
    datasum: int
    what: str
    hdu: object = field(repr=False, default=None)
    aliases: dict = field(default_factory=dict)
    mappable: bool = False
    #: the option that names the columns (pointings names a schedule's with --schedule-columns)
    option: str = "--columns"
    _cache: dict = field(repr=False, default_factory=dict)

    def __len__(self) -> int:
        return self.hdu.nrows

    @property
    def names(self) -> list:
        """Column names as perscli sees them: as written, with mapped columns under their perscli names.

        A file column that is shadowed by a mapping (the file's own 'ra' when
        ``ra=ALPHA_J2000`` is given) is left out.
        """
        targets = {real.lower(): logical for logical, real in self.aliases.items()}
        out = []
        for n in self.hdu.colnames:
            if n.lower() in targets:
                out.append(targets[n.lower()])
            elif n.lower() not in self.aliases:
                out.append(n)
        return out

    def _real(self, name: str):
        """The file's column behind a perscli name (None when absent), and how to name it in messages."""
        file_names = {n.lower(): n for n in self.hdu.colnames}
        mapped = self.aliases.get(name.lower())
        if mapped is not None:
            return file_names.get(mapped.lower()), f"'{mapped}' ({self.option} {name.lower()}={mapped})"
        return file_names.get(name.lower()), f"'{name}'"

    def _tform(self, real: str) -> str:
        k = [n.lower() for n in self.hdu.colnames].index(real.lower()) + 1
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
        real, shown = self._real(name)
        where = f"{self.label}: HDU {self.index}"
        if real is None:
            listed = ", ".join(needed) if needed else name
            fix = (f", or name its column with {self.option} {name.lower()}=COLUMN" if self.mappable and
                   name.lower() not in self.aliases else "")
            raise PerscliError(f"{where} has no column {shown}; a {self.what} needs the columns {listed}: "
                               f"check that this is a {self.what}{fix}")
        if real not in self._cache:
            self._cache[real] = self.hdu.read_column(real)
        values = self._cache[real]
        tform = self._tform(real)
        if values.ndim != 1:
            raise PerscliError(f"{where}: column {shown} has {values.shape[1:]} values per row (TFORM "
                               f"{tform}); it must be a single value per row: check that this is a {self.what}")
        ok = {"number": "iuf", "integer": "iu", "text": "SU"}[kind]
        if values.dtype.kind not in ok:
            held = "text" if values.dtype.kind in "SU" else ("floating-point numbers" if values.dtype.kind == "f"
                                                              else f"{values.dtype} values")
            wanted = {"number": "numbers", "integer": "integers", "text": "text"}[kind]
            raise PerscliError(f"{where}: column {shown} holds {held} (TFORM {tform}) but must hold "
                               f"{wanted}: check that this is a {self.what}")
        if kind == "text":
            if values.dtype.kind == "S":
                values = np.char.decode(values, "ascii", errors="replace")
            return np.char.strip(values.astype(str))
        return values.astype(values.dtype.newbyteorder("="))

    def unit(self, name: str) -> str:
        """TUNITn of a column ('' when absent)."""
        real, _ = self._real(name)
        k = [n.lower() for n in self.hdu.colnames].index(real.lower()) + 1
        return str(self.header.get(f"TUNIT{k}", "") or "").strip()


_MAPPING_ITEM = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*=\s*([^=,\s][^=,]*?)\s*$")


def parse_column_mapping(specs) -> dict:
    """``--columns`` values ('ra=ALPHA_J2000,dec=DELTA_J2000', repeatable) as {perscli name: file column}.

    Parameters
    ----------
    specs : str or iterable of str
        Comma-separated NAME=COLUMN items; perscli names are matched without
        regard to case (as FITS column names are).

    Raises
    ------
    ValueError
        An item is not NAME=COLUMN, or one name is mapped twice.
    """
    if isinstance(specs, str):
        specs = [specs]
    mapping: dict = {}
    for spec in specs or ():
        for item in str(spec).split(","):
            if not item.strip():
                continue
            m = _MAPPING_ITEM.match(item)
            if m is None:
                raise ValueError(f"{item.strip()!r} is not NAME=COLUMN (e.g. ra=ALPHA_J2000)")
            logical, real = m.group(1).lower(), m.group(2)
            if logical in mapping and mapping[logical] != real:
                raise ValueError(f"{logical} is mapped twice ({mapping[logical]} and {real})")
            mapping[logical] = real
    return mapping


def _check_mapping(label: str, colnames, aliases: dict, what: str, known, option: str = "--columns") -> None:
    """Every mapped file column exists, and (when ``known`` is given) every perscli name is one perscli reads."""
    file_names = {n.lower() for n in colnames}
    for logical, real in aliases.items():
        if real.lower() not in file_names:
            shown = ", ".join(colnames[:30]) + (", ..." if len(colnames) > 30 else "")
            raise PerscliError(f"{label}: {option} {logical}={real}: the file has no column '{real}'; "
                               f"its columns are {shown}")
        if known is not None and not any(fnmatch.fnmatch(logical, k.lower()) for k in known):
            raise PerscliError(f"{label}: {option} {logical}={real}: a {what} has no column '{logical}' for "
                               f"perscli to read; it reads {', '.join(known)}")


def read_table(name: str, *, what: str, stdin=None, columns=None, known=None, option: str = "--columns") -> InputTable:
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
    columns : dict, optional
        Column mapping {perscli name: file column} (:func:`parse_column_mapping`);
        given (even empty) by commands that offer ``--columns``, whose
        messages about a missing column then suggest it.
    known : iterable of str, optional
        The names perscli reads from this kind of table (glob patterns such
        as 'mag_*' allowed): a mapping of any other name is refused, since it
        would be silently ignored.
    option : str
        The command's option that maps the columns, named in messages
        (``--columns``; pointings' schedule: ``--schedule-columns``).

    Raises
    ------
    PerscliError
        Unreadable, not FITS, truncated, corrupt (CHECKSUM/DATASUM), without a
        binary table, or a mapping naming a column the file lacks.
    """
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
        colnames = list(hdu.colnames)  # a table CFITSIO cannot describe fails here, as one line
        aliases = {k.lower(): v for k, v in (columns or {}).items()}
        _check_mapping(fits.label, colnames, aliases, what, known, option)
    except (OSError, ValueError) as exc:
        fits.close()
        raise PerscliError(f"{fits.label}: not a readable FITS binary table ({exc}); check that this is a {what}") from None
    except BaseException:
        fits.close()
        raise
    return InputTable(name=name, label=fits.label, index=hdu.index, header=hdu.header, datasum=datasum,
                      what=what, hdu=hdu, aliases=aliases, mappable=columns is not None, option=option)


def _first_table(label: str, hdus, what: str):
    """The first binary-table HDU of a file, or one clear error."""
    tables = [h for h in hdus if h.kind == "table"]
    if len(tables) > 1 and str(tables[0].header.get("EXTNAME", "")).strip().upper() == "LDAC_IMHEAD":
        # SExtractor FITS_LDAC: the first table holds the image's header as text; the objects follow
        objects = [h for h in tables if str(h.header.get("EXTNAME", "")).strip().upper() == "LDAC_OBJECTS"]
        return objects[0] if objects else tables[1]
    if not tables:
        raise PerscliError(f"{label}: has no binary table HDU; a {what} is a FITS binary table: "
                           f"check that this is a {what}")
    return tables[0]


@contextlib.contextmanager
def open_table(name: str, *, what: str, stdin=None, columns=None, known=None):
    """:func:`read_table` as a context manager that closes the file at the end.

    Only the columns asked for are read (by CFITSIO), which for a catalogue
    of a million objects saves reading the whole table.
    """
    table = read_table(name, what=what, stdin=stdin, columns=columns, known=known)
    try:
        yield table
    finally:
        table.hdu.file.close()
