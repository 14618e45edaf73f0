"""Detectors on the sky: the WCS of one Roman SCA for a pointing, its footprint, and what lands on it.

- :func:`sca_wcs`: GalSim's Roman WCS of one SCA for a pointing (refused,
  in one line, when Roman cannot observe there then);
- :func:`sca_footprint`: the four corners on the sky of one SCA (its outer
  pixel edges, or those of a cutout), through that WCS, optionally grown by
  a margin;
- :func:`sky_to_pixels` and :func:`objects_on_sca`: where catalogue objects
  land on an SCA, and which of them land on it (or on a cutout of it,
  :func:`frame_bounds`); :func:`count_on_sca` counts them, by kind, for
  every row of a table.
"""

from __future__ import annotations

import math

import galsim
import galsim.roman as roman
import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_N_SCA, ROMAN_PIXEL_SCALE, ROMAN_SCA_SIZE
from . import check_mjd, check_pa, check_position, within
from .observability import _date, _when, unobservable_message

#: [deg] objects farther than this from an SCA's centre are taken to be off it without asking the WCS:
#: the SCA's half-diagonal is 0.09 deg and the largest stamp 0.06 deg wide, while GalSim's TAN-SIP WCS maps
#: the far side of the sky back onto the frame (the antipode of the centre lands on the centre) and fails to
#: converge for distant points
NEAR_SCA_DEG = 0.5


# -- detectors on the sky -------------------------------------------------------------------------

def sca_wcs(pointing, sca: int):
    """GalSim's Roman WCS of one SCA for a pointing.

    Parameters
    ----------
    pointing
        Anything with ``ra``, ``dec`` (centre of the focal plane, degrees),
        ``pa`` (observatory position angle, degrees) and ``mjd`` (start):
        a :class:`Pointing` or a :class:`perscli.render.exposure.Exposure`.
    sca : int
        1-18.

    Returns
    -------
    galsim.GSFitsWCS
        ``galsim.roman.getWCS(world_pos, PA=pa, date=...)[sca]``.

    Raises
    ------
    PerscliError
        Not an SCA, a coordinate out of range, or a position Roman cannot
        observe at that date (GalSim allows positions 54 to 126 degrees from
        the Sun): one line with the first date after it when Roman can.
    """
    if not 1 <= int(sca) <= ROMAN_N_SCA:
        raise PerscliError(f"SCA {sca}: Roman has detectors 1 to {ROMAN_N_SCA}")
    ra, dec = check_position(getattr(pointing, "ra"), getattr(pointing, "dec"), "pointing")
    pa = check_pa(getattr(pointing, "pa"), "pointing: position angle")
    mjd = check_mjd(getattr(pointing, "mjd"), "pointing: date")
    date = _date(mjd)
    world = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    if not roman.allowedPos(world, date):
        raise PerscliError(unobservable_message(ra, dec, mjd) + " (perscli pointings plan chooses an "
                           "observable date; render --mjd, pointings plan --start)")
    try:
        return roman.getWCS(world_pos=world, PA=pa * galsim.degrees, date=date, SCAs=int(sca))[int(sca)]
    except galsim.GalSimError as exc:
        raise PerscliError(f"GalSim's Roman WCS for ra={ra:g} dec={dec:g} pa={pa:g} on {_when(mjd)}: "
                           f"{str(exc).splitlines()[0]}") from None


def sky_to_pixels(wcs, ra, dec) -> tuple:
    """Pixel positions on an SCA of sky positions, through its WCS (GalSim convention: pixel centres at integers).

    Parameters
    ----------
    wcs : galsim.GSFitsWCS
        The SCA's WCS (:func:`sca_wcs`).
    ra, dec : array_like
        Degrees.

    Returns
    -------
    x, y : ndarray
        Pixels; NaN for positions more than :data:`NEAR_SCA_DEG` from the
        SCA's centre, which cannot land on it (and which a TAN-SIP WCS
        would fold onto it or fail to invert).
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    x, y = np.full(ra.shape, np.nan), np.full(ra.shape, np.nan)
    if ra.size == 0:
        return x, y
    centre = wcs.toWorld(galsim.PositionD(ROMAN_SCA_SIZE / 2 + 0.5, ROMAN_SCA_SIZE / 2 + 0.5))
    with np.errstate(invalid="ignore"):
        near = within(centre.ra / galsim.degrees, centre.dec / galsim.degrees, ra, dec, NEAR_SCA_DEG)
    if np.any(near):
        try:
            px, py = wcs.radecToxy(np.radians(ra[near]), np.radians(dec[near]), units="radians")
        except galsim.GalSimError as exc:
            raise PerscliError(f"GalSim's Roman WCS cannot place objects near the SCA: {str(exc).splitlines()[0]}")\
                from None
        x[near], y[near] = px, py
    return x, y


def frame_bounds(bounds=None) -> tuple:
    """``(xmin, xmax, ymin, ymax)`` of a cutout (1-indexed inclusive SCA pixels), checked; default the whole SCA."""
    if bounds is None:
        return 1, ROMAN_SCA_SIZE, 1, ROMAN_SCA_SIZE
    try:
        xmin, xmax, ymin, ymax = (int(v) for v in bounds)
    except (TypeError, ValueError):
        raise PerscliError(f"bounds {bounds!r}: give (xmin, xmax, ymin, ymax) in SCA pixels") from None
    if not (1 <= xmin <= xmax <= ROMAN_SCA_SIZE and 1 <= ymin <= ymax <= ROMAN_SCA_SIZE):
        raise PerscliError(f"bounds {tuple(bounds)} must lie within 1..{ROMAN_SCA_SIZE} with min <= max")
    return xmin, xmax, ymin, ymax


def objects_on_sca(x, y, bounds=None) -> np.ndarray:
    """Which pixel positions (:func:`sky_to_pixels`) land on the frame: inside its outer pixel edges.

    Parameters
    ----------
    x, y : array_like
        Pixels, GalSim convention; NaN is off the frame.
    bounds : (xmin, xmax, ymin, ymax), optional
        A cutout (1-indexed inclusive SCA pixels); default the whole SCA.

    Returns
    -------
    ndarray of bool
        ``xmin - 0.5 <= x < xmax + 0.5`` and the same in y.
    """
    xmin, xmax, ymin, ymax = frame_bounds(bounds)
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return (x >= xmin - 0.5) & (x < xmax + 0.5) & (y >= ymin - 0.5) & (y < ymax + 0.5)


def count_on_sca(pointings, ra, dec, kind, *, sca: int = 0, bounds=None) -> dict:
    """How many catalogue objects of each kind land on each pointing's SCA.

    Parameters
    ----------
    pointings : sequence of Pointing
    ra, dec : array_like
        The catalogue's positions, degrees.
    kind : array_like of str
        'star' or 'galaxy' for each object.
    sca : int
        The detector; 0: each pointing's own.
    bounds : optional
        A cutout, as :func:`objects_on_sca`.

    Returns
    -------
    dict
        ``{'star': ndarray, 'galaxy': ndarray}``: counts per pointing, in order.
    """
    kind = np.char.lower(np.char.strip(np.asarray(kind).astype(str)))
    counts = {"star": np.zeros(len(pointings), dtype=np.int64), "galaxy": np.zeros(len(pointings), dtype=np.int64)}
    for i, p in enumerate(pointings):
        which = sca or p.sca
        if not which:
            raise PerscliError("counting objects on an SCA needs one: give --sca N (1-18)")
        on = objects_on_sca(*sky_to_pixels(sca_wcs(p, which), ra, dec), bounds)
        for name in counts:
            counts[name][i] = int(np.count_nonzero(on & (kind == name)))
    return counts


def sca_footprint(pointing, sca: int | None = None, *, margin_arcsec: float = 0.0, bounds=None) -> tuple:
    """The corners on the sky of one SCA (or a cutout of it) for a pointing.

    Parameters
    ----------
    pointing
        A :class:`Pointing` (or anything with ra, dec, pa, mjd: an Exposure).
    sca : int, optional
        1-18; default the pointing's own ``sca``.
    margin_arcsec : float
        Grow the footprint outwards by this much: the pixel box is widened
        by margin / 0.11" pixels on each side before the corners go through
        the WCS (the plate scale varies by a few per cent over the focal
        plane, so the margin on the sky is that much approximate).
    bounds : (xmin, xmax, ymin, ymax), optional
        A cutout (1-indexed inclusive SCA pixels, as ``perscli render
        --bounds``); default the whole 4088 x 4088 SCA.

    Returns
    -------
    ra, dec : ndarray of 4
        Degrees: the outer pixel edges (xmin - 0.5, ymin - 0.5),
        (xmax + 0.5, ymin - 0.5), (xmax + 0.5, ymax + 0.5),
        (xmin - 0.5, ymax + 0.5) in GalSim's convention (pixel centres at
        integers), through ``galsim.roman.getWCS`` for the pointing's
        position, position angle and date.  The sides between them are
        great-circle arcs to within 0.001 arcsec.

    Raises
    ------
    PerscliError
        No SCA, bad bounds or margin, or a pointing Roman cannot observe.
    """
    if sca is None or sca == 0:
        sca = getattr(pointing, "sca", 0)
    if not sca:
        raise PerscliError("footprint: give an SCA (1-18): the pointing does not name one")
    if not (math.isfinite(margin_arcsec) and margin_arcsec >= 0):
        raise PerscliError(f"margin {margin_arcsec} arcsec: must be a number >= 0")
    xmin, xmax, ymin, ymax = frame_bounds(bounds)
    wcs = sca_wcs(pointing, int(sca))
    grow = 0.5 + margin_arcsec / ROMAN_PIXEL_SCALE
    x = np.array([xmin - grow, xmax + grow, xmax + grow, xmin - grow])
    y = np.array([ymin - grow, ymin - grow, ymax + grow, ymax + grow])
    ra, dec = wcs.xyToradec(x, y, units="deg")
    return np.asarray(ra, dtype=np.float64) % 360.0, np.asarray(dec, dtype=np.float64)
