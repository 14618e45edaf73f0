"""The scene: what is on the sky, and when the telescope looks at it.

- :mod:`perscli.scene.catalog`: truth catalogs of galaxies and stars in a
  field, drawn from documented models or taken from Gaia DR2
  reference-catalog chunks;
- :mod:`perscli.scene.pointings`: the exposures that look at a field,
  selected from a real survey schedule or planned as a dithered sequence.

Both read FITS binary tables (Gaia chunks, schedules) through
:func:`read_table`, which checks them as the frame reader checks images
(not FITS, truncated, DATASUM that does not match) and names the file and
column at fault.
"""

from __future__ import annotations

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
    tables = [h for h in hdus if str(h.header.get("XTENSION", "")).strip() == "BINTABLE"]
    if not tables:
        raise PerscliError(f"{label}: has no binary table HDU; a {what} is a FITS binary table: "
                           f"check that this is a {what}")
    hdu = tables[0]
    datasum = hdu.datasum()
    stated = str(hdu.header.get("DATASUM", "")).strip()
    if stated.isdigit() and int(stated) != datasum:
        raise PerscliError(f"{label}: HDU {hdu.index} data do not match its DATASUM ({stated}, computed "
                           f"{datasum}): the file is corrupt; re-copy it "
                           "(or delete DATASUM if the data were edited on purpose)")
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
ROMAN_FILTERS = ("R062", "Z087", "Y106", "J129", "H158", "F184", "K213", "W146")

#: Effective wavelengths in microns, used only by the simple colour model of
#: :func:`perscli.scene.catalog.filter_magnitudes`.
EFFECTIVE_WAVELENGTH_UM = {"R062": 0.620, "Z087": 0.869, "Y106": 1.060, "J129": 1.293,
                           "H158": 1.577, "F184": 1.842, "K213": 2.125, "W146": 1.464}


def check_filter(name: str) -> str:
    """The canonical name of a Roman filter ('j129' -> 'J129').

    Raises
    ------
    PerscliError
        Not a Roman filter.
    """
    canonical = str(name).strip().upper()
    if canonical not in ROMAN_FILTERS:
        raise PerscliError(f"unknown filter '{name}': valid are {', '.join(ROMAN_FILTERS)}")
    return canonical


# -- sky geometry -------------------------------------------------------------------------------
#
# Unit vectors rather than spherical-trigonometry formulas: they hold everywhere, the poles and
# RA = 0/360 included.

def unit_vector(ra, dec) -> np.ndarray:
    """Unit vectors (..., 3) of positions in degrees."""
    ra, dec = np.radians(ra), np.radians(dec)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)


def tangent_basis(ra: float, dec: float) -> tuple:
    """The centre, east and north unit vectors of the tangent plane at (ra, dec) in degrees."""
    a, d = np.radians(ra), np.radians(dec)
    centre = np.array([np.cos(d) * np.cos(a), np.cos(d) * np.sin(a), np.sin(d)])
    east = np.array([-np.sin(a), np.cos(a), 0.0])
    north = np.array([-np.sin(d) * np.cos(a), -np.sin(d) * np.sin(a), np.cos(d)])
    return centre, east, north


def deproject(ra0: float, dec0: float, xi, eta) -> tuple:
    """Gnomonic (TAN) standard coordinates about (ra0, dec0) to (ra, dec).

    Parameters
    ----------
    ra0, dec0 : float
        Tangent point in degrees.
    xi, eta : array_like
        Standard coordinates in radians: xi towards east (increasing RA),
        eta towards north.

    Returns
    -------
    ra, dec : ndarray
        Degrees, RA in [0, 360).
    """
    centre, east, north = tangent_basis(ra0, dec0)
    xi, eta = np.asarray(xi, dtype=np.float64), np.asarray(eta, dtype=np.float64)
    v = centre + xi[..., None] * east + eta[..., None] * north
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    ra = np.degrees(np.arctan2(v[..., 1], v[..., 0])) % 360.0
    dec = np.degrees(np.arcsin(np.clip(v[..., 2], -1.0, 1.0)))
    return ra, dec


def project(ra0: float, dec0: float, ra, dec) -> tuple:
    """(ra, dec) in degrees to gnomonic standard coordinates (radians) about (ra0, dec0).

    Returns
    -------
    xi, eta : ndarray
        Radians; NaN for points 90 degrees or more from the tangent point,
        which have no gnomonic projection.
    """
    centre, east, north = tangent_basis(ra0, dec0)
    v = unit_vector(ra, dec)
    cos_c = v @ centre
    with np.errstate(divide="ignore", invalid="ignore"):
        front = cos_c > 0
        xi = np.where(front, (v @ east) / cos_c, np.nan)
        eta = np.where(front, (v @ north) / cos_c, np.nan)
    return xi, eta


def separation(ra1, dec1, ra2, dec2) -> np.ndarray:
    """Great-circle distance in degrees (Vincenty's formula: accurate at all distances)."""
    a1, d1, a2, d2 = (np.radians(np.asarray(x, dtype=np.float64)) for x in (ra1, dec1, ra2, dec2))
    da = a2 - a1
    num = np.hypot(np.cos(d2) * np.sin(da), np.cos(d1) * np.sin(d2) - np.sin(d1) * np.cos(d2) * np.cos(da))
    den = np.sin(d1) * np.sin(d2) + np.cos(d1) * np.cos(d2) * np.cos(da)
    return np.degrees(np.arctan2(num, den))
