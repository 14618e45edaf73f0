"""The scene: what is on the sky, and when the telescope looks at it.

- :mod:`perscli.scene.catalog`: truth catalogs of galaxies and stars in a
  field, drawn from documented models or taken from Gaia DR2
  reference-catalog chunks;
- :mod:`perscli.scene.pointings`: the exposures that look at a field,
  selected from a real survey schedule (by boresight, or by where one SCA
  lands) or planned as a dithered sequence; SCA footprints on the sky; the
  exposures before a given one;
- :mod:`perscli.scene.regions`: footprints as convex spherical polygons,
  their union, its solid angle and a Poisson process on it.

Both read FITS binary tables (Gaia chunks, schedules) through
:func:`perscli.io.tables.read_table`.

Coordinates are checked here, once, for every command and library entry
point (:func:`check_position`, :func:`check_pa`, :func:`check_mjd`): RA in
[0, 360] degrees, Dec in [-90, 90], position angles in [-360, 360] and dates
MJD 0 to 100000 (1858-11-17 to 2132-09-01, which refuses a Julian Date or a
mistyped digit).  A value outside is refused, never wrapped: RA 370 is more
often a typo than a wish for RA 10.
"""

from __future__ import annotations

import datetime as _dt
import math

# lazy: numpy is imported inside the functions that need it: the commands' options import this package (the
# coordinate ranges; perscli.scene.settings sits below it), and ``--help`` must not wait for numpy

from .. import PerscliError
from ..instrument import ROMAN_FILTERS

#: [deg] the accepted ranges of coordinates (perscli.cli.options declares the same ones for the command line)
RA_RANGE = (0.0, 360.0)
DEC_RANGE = (-90.0, 90.0)
PA_RANGE = (-360.0, 360.0)
#: [MJD] the accepted dates: 1858-11-17 to 2132-09-01
MJD_RANGE = (0.0, 100000.0)

#: the MJD epoch
MJD_ZERO = "1858-11-17"

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


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def check_position(ra, dec, what: str = "position") -> tuple:
    """``(ra, dec)`` as floats, checked: RA in [0, 360], Dec in [-90, 90] degrees.

    Parameters
    ----------
    ra, dec
        Degrees.
    what : str
        What the position is, for the message ('field centre', 'pointing').

    Raises
    ------
    PerscliError
        A value outside its range or not a number (one line naming it).
    """
    ra, dec = _number(ra), _number(dec)
    if not RA_RANGE[0] <= ra <= RA_RANGE[1]:
        hint = f" (the same direction as RA {ra % 360.0:g})" if math.isfinite(ra) else ""
        raise PerscliError(f"{what}: RA {ra:g} is not in [0, 360] degrees{hint}")
    if not DEC_RANGE[0] <= dec <= DEC_RANGE[1]:
        raise PerscliError(f"{what}: Dec {dec:g} is not in [-90, 90] degrees")
    return ra, dec


def check_positions(label: str, ra, dec) -> None:
    """Refuse a table whose positions lie outside RA [0, 360], Dec [-90, 90] degrees (or are not numbers).

    Raises
    ------
    PerscliError
        One line naming ``label``, how many rows and the first.
    """
    import numpy as np  # lazy: see the note above the imports

    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~((ra >= RA_RANGE[0]) & (ra <= RA_RANGE[1]) & (dec >= DEC_RANGE[0]) & (dec <= DEC_RANGE[1]))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise PerscliError(f"{label}: {int(bad.sum())} row(s) with RA outside [0, 360] or Dec outside [-90, 90] "
                           f"degrees (first: row {i}, ra={ra[i]:g} dec={dec[i]:g}); fix or drop them")


def check_column_scaling(label: str, header) -> None:
    """Refuse a table whose TSCALn or TZEROn cannot scale a column.

    TSCALn = 0 makes every value of column n equal to TZEROn (a catalogue
    whose RA column is all 0, say), and a TSCALn or TZEROn that is not a
    finite number makes every value NaN or infinite: CFITSIO applies them
    without complaint, so the values would be silently wrong.

    Parameters
    ----------
    label : str
        The file, for the message.
    header : mapping
        The table's header (``perscli.io.tables.InputTable.header``).

    Raises
    ------
    PerscliError
        One line naming the column and the keyword.
    """
    # this belongs with the other structure checks of the FITS layer (perscli.io), for every table;
    # until it is there, the catalogue readers of render and measure make it themselves
    try:
        nfields = int(header.get("TFIELDS", 0) or 0)
    except (TypeError, ValueError):
        return      # the FITS layer reports a bad TFIELDS
    for k in range(1, nfields + 1):
        name = str(header.get(f"TTYPE{k}", f"column {k}")).strip()
        for key in (f"TSCAL{k}", f"TZERO{k}"):
            if key not in header:
                continue
            value = _number(header[key])
            if not math.isfinite(value) or (key.startswith("TSCAL") and value == 0):
                raise PerscliError(f"{label}: {key} = {header[key]!r} (column '{name}') would make every value "
                                   "of the column the same or not a number; the file is corrupt: re-copy or "
                                   "regenerate it")


#: AB magnitudes brighter than this are no star's (the brightest in the sky are about -3 in J): a catalogue holding
#: one has another quantity in the column (a flux, a log); GalSim's Poisson draw fails past ~-25 ('lam too large')
MAG_BRIGHTEST = -5.0


def check_catalog(label: str, cols: dict, *, header=None, names=None) -> None:
    """Refuse a catalogue whose values cannot describe objects: the one check of catalogue columns.

    Used by every reader of a truth catalogue that draws or measures its
    objects (``perscli render``, ``perscli measure``), on the columns it
    read, so that a bad value is one line naming the file and the first bad
    row instead of a GalSim or WCS traceback, a crash, or a silently wrong
    output.  Checked, for each column present:

    - ``id``: unique (each row is one object; ``perscli correlate`` matches
      the measurements of an object by id and refuses repeated ones);
    - ``ra``, ``dec``: RA in [0, 360], Dec in [-90, 90] degrees
      (:func:`check_positions`); ``x``, ``y``: finite;
    - ``hlr`` (half-light radius, arcsec): never negative or infinite, and
      > 0 for every galaxy (a profile of zero size cannot be drawn);
    - ``e1``, ``e2``: |e| = sqrt(e1^2 + e2^2) < 1 wherever given (an
      ellipticity of 1 is a line), and finite for every galaxy;
    - ``mag`` and ``mag_*`` (AB): a number for every row, and not brighter
      than :data:`MAG_BRIGHTEST` (a magnitude of -30 is no star's: the
      column holds something else).

    Galaxies are the rows whose ``kind`` is 'galaxy'; without a kind column
    no row is known to be one, and only the checks that hold for any row
    apply.  Non-finite values the caller allows (a star's NaN hlr, a
    position off every frame) are left to it.

    Parameters
    ----------
    label : str
        The file, for the messages.
    cols : dict of str -> ndarray
        The columns read, by perscli name (``kind`` lower-case).
    header : mapping, optional
        The table's header: its column scaling is checked too
        (:func:`check_column_scaling`).
    names : dict, optional
        The file's name of a column read under another key (render reads
        ``mag_J129`` as ``mag``), for the messages.

    Raises
    ------
    PerscliError
        One line naming the file, the column, how many rows and the first.
    """
    import numpy as np  # lazy: see the note above the imports

    if header is not None:
        check_column_scaling(label, header)
    ids = np.asarray(cols["id"]) if "id" in cols else None

    def first(bad: np.ndarray) -> str:
        i = int(np.flatnonzero(bad)[0])
        return f"id {int(ids[i])}" if ids is not None else f"row {i}"

    if ids is not None and len(ids):
        s = np.sort(ids)
        dup = s[1:][s[1:] == s[:-1]]
        if len(dup):
            raise PerscliError(f"{label}: id {int(dup[0])} appears more than once ({len(np.unique(dup))} repeated "
                               "id(s)): each row is one object with its own id; renumber or drop the duplicates")
    if "ra" in cols and "dec" in cols:
        check_positions(label, cols["ra"], cols["dec"])
    for key in ("x", "y"):
        if key in cols:
            bad = ~np.isfinite(np.asarray(cols[key], dtype=np.float64))
            if np.any(bad):
                raise PerscliError(f"{label}: column {key} has {int(bad.sum())} non-finite value(s) (first at "
                                   f"{first(bad)}); fix or drop those rows")
    galaxy = (np.asarray(cols["kind"]) == "galaxy") if "kind" in cols else None
    if "hlr" in cols:
        hlr = np.asarray(cols["hlr"], dtype=np.float64)
        with np.errstate(invalid="ignore"):
            bad = (hlr < 0) | np.isinf(hlr)
            if galaxy is not None:
                bad |= galaxy & ~(hlr > 0)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise PerscliError(f"{label}: column hlr has {int(bad.sum())} value(s) that cannot be a half-light "
                               f"radius (first at {first(bad)}: hlr = {hlr[i]:g}): hlr is in arcsec, >= 0, and > 0 "
                               "for a galaxy; fix or drop those rows")
    for key in [k for k in cols if k == "mag" or k.startswith("mag_")]:
        mag = np.asarray(cols[key], dtype=np.float64)
        shown = (names or {}).get(key, key)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(mag)
            bright = np.isfinite(mag) & (mag < MAG_BRIGHTEST)
        if np.any(bad):
            raise PerscliError(f"{label}: column {shown} has {int(bad.sum())} value(s) that are not a magnitude "
                               f"(first at {first(bad)}: {mag[np.flatnonzero(bad)[0]]:g}); give every row one, or "
                               "drop those rows")
        if np.any(bright):
            i = int(np.flatnonzero(bright)[0])
            raise PerscliError(f"{label}: column {shown} has {int(bright.sum())} value(s) brighter than any star "
                               f"(first at {first(bright)}: {mag[i]:g}; the brightest stars are about -3): AB "
                               "magnitudes expected; check what the column holds (a flux? a log?)")
    if "e1" in cols and "e2" in cols:
        e1 = np.asarray(cols["e1"], dtype=np.float64)
        e2 = np.asarray(cols["e2"], dtype=np.float64)
        with np.errstate(invalid="ignore"):
            # hypot: no overflow for huge components, inf for an infinite one, NaN left to the caller
            bad = np.hypot(e1, e2) >= 1.0
            if galaxy is not None:
                bad |= galaxy & ~(np.isfinite(e1) & np.isfinite(e2))
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise PerscliError(f"{label}: {int(bad.sum())} row(s) with an ellipticity |e| = sqrt(e1^2 + e2^2) "
                               f">= 1 or not a number (first at {first(bad)}: e1 = {e1[i]:g}, e2 = {e2[i]:g}): "
                               "|e| < 1 (|e| = 1 is a line); fix or drop those rows")


def check_pa(pa, what: str = "position angle") -> float:
    """A position angle in degrees, checked to lie in [-360, 360].

    Raises
    ------
    PerscliError
        Outside that range or not a number.
    """
    pa = _number(pa)
    if not PA_RANGE[0] <= pa <= PA_RANGE[1]:
        raise PerscliError(f"{what} {pa:g}: give degrees in [-360, 360]")
    return pa


def check_mjd(mjd, what: str = "date") -> float:
    """A date (MJD), checked to lie in :data:`MJD_RANGE`.

    Raises
    ------
    PerscliError
        Outside it (a Julian Date gets a hint: MJD = JD - 2400000.5) or not a number.
    """
    mjd = _number(mjd)
    if not MJD_RANGE[0] <= mjd <= MJD_RANGE[1]:
        hint = f" (a Julian Date? MJD = JD - 2400000.5 = {mjd - 2400000.5:.5f})" if mjd > 2400000.5 else ""
        raise PerscliError(f"{what} MJD {mjd:g} is not in [{MJD_RANGE[0]:g}, {MJD_RANGE[1]:g}] "
                           f"(1858-11-17 to 2132-09-01){hint}")
    return mjd


def mjd_datetime(mjd: float):
    """The UTC ``datetime.datetime`` of an MJD (what GalSim's Roman module takes as a date)."""
    return _dt.datetime(1858, 11, 17) + _dt.timedelta(days=float(mjd))


def sky_extent(ra, dec) -> tuple:
    """Where a set of positions is: their centre and the radius that holds them all.

    Parameters
    ----------
    ra, dec : array_like
        Degrees.

    Returns
    -------
    (ra, dec, radius) : tuple of float
        The direction of the mean unit vector (degrees; RA in [0, 360)) and the
        largest great-circle distance from it (degrees); NaNs for no positions.
    """
    import numpy as np  # lazy: see the note above the imports

    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    if ra.size == 0:
        return math.nan, math.nan, math.nan
    v = unit_vector(ra, dec).reshape(-1, 3).sum(axis=0)
    norm = np.linalg.norm(v)
    if norm == 0:
        # balanced over the whole sphere: any centre holds them within 180 degrees
        return 0.0, 0.0, 180.0
    v = v / norm
    ra0 = float(np.degrees(np.arctan2(v[1], v[0])) % 360.0)
    dec0 = float(np.degrees(np.arcsin(np.clip(v[2], -1.0, 1.0))))
    return ra0, dec0, float(np.max(separation(ra0, dec0, ra, dec)))


# -- sky geometry -------------------------------------------------------------------------------
#
# Unit vectors rather than spherical-trigonometry formulas: they hold everywhere, the poles and
# RA = 0/360 included.

def unit_vector(ra, dec) -> np.ndarray:
    """Unit vectors (..., 3) of positions in degrees."""
    import numpy as np  # lazy: see the note above the imports

    ra, dec = np.radians(ra), np.radians(dec)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)


def tangent_basis(ra: float, dec: float) -> tuple:
    """The centre, east and north unit vectors of the tangent plane at (ra, dec) in degrees."""
    import numpy as np  # lazy: see the note above the imports

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
    import numpy as np  # lazy: see the note above the imports

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
    import numpy as np  # lazy: see the note above the imports

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
    import numpy as np  # lazy: see the note above the imports

    a1, d1, a2, d2 = (np.radians(np.asarray(x, dtype=np.float64)) for x in (ra1, dec1, ra2, dec2))
    da = a2 - a1
    num = np.hypot(np.cos(d2) * np.sin(da), np.cos(d1) * np.sin(d2) - np.sin(d1) * np.cos(d2) * np.cos(da))
    den = np.sin(d1) * np.sin(d2) + np.cos(d1) * np.cos(d2) * np.cos(da)
    return np.degrees(np.arctan2(num, den))


def within(ra0, dec0, ra, dec, radius: float) -> np.ndarray:
    """Which positions lie within ``radius`` degrees of (ra0, dec0): ``separation(...) <= radius``, the same
    booleans, with the great circle computed only in the band of declinations that can be that near.

    A great-circle distance is at least the difference of declinations, so a position further than ``radius``
    (plus a margin far above rounding) in declination is out; the rest get :func:`separation`.  (Placing a
    1 deg^2 catalogue on each of a study's 4,783 SCA-exposures spent most of a final task in Vincenty's formula.)
    """
    import numpy as np  # lazy: see the note above the imports

    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    shape = np.broadcast(ra, dec).shape
    out = np.zeros(shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        band = np.abs(np.broadcast_to(dec, shape) - float(dec0)) <= float(radius) + 1e-6
    if np.any(band):
        with np.errstate(invalid="ignore"):
            out[band] = separation(ra0, dec0, np.broadcast_to(ra, shape)[band],
                                   np.broadcast_to(dec, shape)[band]) <= radius
    return out
