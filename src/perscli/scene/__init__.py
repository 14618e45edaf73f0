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
"""

from __future__ import annotations


import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_FILTERS

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
