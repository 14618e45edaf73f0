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


import math

import numpy as np

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
    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~((ra >= RA_RANGE[0]) & (ra <= RA_RANGE[1]) & (dec >= DEC_RANGE[0]) & (dec <= DEC_RANGE[1]))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise PerscliError(f"{label}: {int(bad.sum())} row(s) with RA outside [0, 360] or Dec outside [-90, 90] "
                           f"degrees (first: row {i}, ra={ra[i]:g} dec={dec[i]:g}); fix or drop them")


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
    import datetime as _dt

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
