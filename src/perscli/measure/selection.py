"""Which catalogue objects ``perscli measure`` fits, and where they fall on a frame.

The catalogue (:func:`read_positions`: id, ra/dec or x/y, and the columns
it adds), the rows of the kinds asked for (:func:`select_kinds`: galaxies
by default), their FITS pixel positions on a frame through its WCS
(:func:`frame_wcs`, :func:`frame_xy`), whether they fall on it
(:func:`on_frame`), and which have a neighbour close enough to spoil their
shapes (:func:`blended`, :func:`blended_on_sky`).  The cut on the predicted
S/N is in :mod:`perscli.measure.noise`.
"""

from __future__ import annotations

import warnings

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS
from astropy.wcs.utils import proj_plane_pixel_scales
from scipy.spatial import cKDTree

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from ..io.tables import read_table
from ..scene import check_catalog, separation, within

#: the catalogue's kinds fitted by default (perscli catalog writes 'galaxy' and 'star')
DEFAULT_KINDS = ("galaxy",)

#: the columns read_positions reads from a catalogue (all optional but id and ra/dec or x/y): what
#: ``--columns`` may map
CATALOG_READS = ("id", "ra", "dec", "x", "y", "hlr", "e1", "e2", "kind", "mag_*")


def read_positions(path: str, *, columns=None):
    """The objects of a catalogue: id, ra/dec (degrees) or x/y (pixels, FITS convention), and what it adds.

    Optional columns read when present: hlr (arcsec), e1 and e2 (only
    checked: the fit starts round), kind (lower-cased) and every mag_*.
    Every value is checked by :func:`perscli.scene.check_catalog`, the check
    ``perscli render`` makes of the same catalogue.

    Parameters
    ----------
    path : str
        The catalogue (``perscli catalog``'s TRUTH table, or any table with
        id and ra/dec or x/y).
    columns : dict, optional
        Column mapping {perscli name: file column} (``--columns``; names of
        :data:`CATALOG_READS`).  Given (even empty), a missing column's
        message suggests the option.

    Returns
    -------
    dict
        The columns by perscli name (mag columns lower-cased), plus ``label``
        and ``datasum`` (for provenance).

    Raises
    ------
    PerscliError
        Unreadable, without id or positions, a mapping of a column perscli
        does not read, or values no object can have (repeated ids, positions
        off the sky, hlr < 0, |e| >= 1, ...).
    """
    table = read_table(path, what="catalogue (id and ra/dec or x/y)", columns=columns, known=CATALOG_READS)
    names = {n.lower() for n in table.names}
    out = {"id": table.column("id", kind="integer", needed=("id", "ra", "dec"))}
    if {"ra", "dec"} <= names:
        out["ra"] = table.column("ra").astype(np.float64)
        out["dec"] = table.column("dec").astype(np.float64)
    elif {"x", "y"} <= names:
        out["x"] = table.column("x").astype(np.float64)
        out["y"] = table.column("y").astype(np.float64)
    else:
        fix = (": name them with --columns ra=COLUMN,dec=COLUMN (or x=COLUMN,y=COLUMN)" if table.mappable else "")
        raise PerscliError(f"{table.label}: HDU {table.index} has no ra/dec (degrees) or x/y (pixels) columns; a "
                           f"catalogue needs one pair{fix}")
    for optional in ("hlr", "kind", "e1", "e2"):
        if optional in names:
            out[optional] = table.column(optional, kind="text" if optional == "kind" else "number")
    if "kind" in out:
        out["kind"] = np.char.lower(out["kind"])
    mags = [n for n in table.names if n.lower().startswith("mag_")]
    for name in mags:
        out[name.lower()] = table.column(name).astype(np.float64)
    out["label"], out["datasum"] = table.label, table.datasum
    for key in ("ra", "dec", "x", "y"):
        if key in out and not np.all(np.isfinite(out[key])):
            bad = int((~np.isfinite(out[key])).sum())
            raise PerscliError(f"{table.label}: column {key} has {bad} non-finite value(s); drop those rows")
    # the values render would refuse are refused here too (one check for both): repeated ids (whose SHAPES
    # rows correlate refuses), RA/Dec off the sky (WCS tracebacks), negative or zero sizes, |e| >= 1
    check_catalog(table.label, out, header=table.header, names={name.lower(): name for name in mags})
    return out


def select_kinds(cat, kinds=None):
    """Indices of the catalogue rows to measure, and a description for the header.

    Parameters
    ----------
    cat : dict
        From :func:`read_positions`.
    kinds : None, 'all', or sequence of str
        None: the galaxies (``kind == 'galaxy'``) when the catalogue has a
        kind column, every row when it has none.  'all': every row.  A
        list (or a comma-separated string): the rows of those kinds; the
        catalogue must have a kind column.

    Raises
    ------
    PerscliError
        Kinds asked for of a catalogue without a kind column, or a kind that
        is neither in the catalogue nor one perscli writes.
    """
    n = len(cat["id"])
    if isinstance(kinds, str):
        kinds = [k for k in (part.strip().lower() for part in kinds.split(",")) if k]
        if kinds == ["all"]:
            kinds = "all"
    elif kinds is not None:
        kinds = [str(k).strip().lower() for k in kinds]
    if kinds == "all" or (kinds is not None and "all" in kinds):
        if kinds != "all" and len(kinds) > 1:
            raise PerscliError(f"--kinds {','.join(kinds)}: 'all' goes alone")
        return np.arange(n), "all"
    if kinds is None:
        if "kind" not in cat:
            return np.arange(n), "all (no kind column)"
        kinds = list(DEFAULT_KINDS)
    elif not kinds:
        raise PerscliError("--kinds is empty: give galaxy, star, a comma-separated list, or all")
    elif "kind" not in cat:
        raise PerscliError(f"{cat.get('label', 'catalogue')}: no kind column to select --kinds "
                           f"{','.join(kinds)} from; give --kinds all (every row) or a catalogue with kind")
    present = sorted(set(np.unique(cat["kind"]).tolist()))
    unknown = [k for k in kinds if k not in present and k not in ("galaxy", "star")]
    if unknown:
        raise PerscliError(f"--kinds {','.join(kinds)}: the catalogue has no kind {', '.join(unknown)} "
                           f"(its kinds: {', '.join(present) or 'none'})")
    return np.flatnonzero(np.isin(cat["kind"], kinds)), ",".join(kinds)


def frame_wcs(frame):
    """astropy WCS of the frame's science header (with SIP), or None (made once per frame)."""
    cached = getattr(frame, "_measure_wcs", False)
    if cached is not False:
        return cached

    header = fits.Header.fromstring("".join(frame.header.cards))
    wcs = None
    if "CTYPE1" in header:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wcs = WCS(header)
    try:
        frame._measure_wcs = wcs
    except AttributeError:
        pass
    return wcs


#: degrees beyond a frame's half-diagonal: catalogue rows farther from its centre are not placed on it (NaN),
#: as none of them can fall on it, and a catalogue of a study holds a million rows around it
NEAR_FRAME_DEG = 0.5


def frame_xy(wcs, shape, ra, dec):
    """FITS pixel positions (first pixel centre at 1) on a frame of ``shape`` of sky positions (degrees).

    NaN for positions more than :data:`NEAR_FRAME_DEG` beyond the frame's
    half-diagonal from its centre.
    """
    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    x, y = np.full(ra.shape, np.nan), np.full(ra.shape, np.nan)
    ny, nx = shape
    corners = np.array([[(nx + 1) / 2.0, (ny + 1) / 2.0], [0.5, 0.5], [nx + 0.5, ny + 0.5], [0.5, ny + 0.5],
                        [nx + 0.5, 0.5]])
    (ra0, dec0), *edges = wcs.all_pix2world(corners, 1)
    half = max(float(separation(ra0, dec0, e[0], e[1])) for e in edges)
    near = within(ra0, dec0, ra, dec, half + NEAR_FRAME_DEG)
    if near.any():
        x[near], y[near] = wcs.all_world2pix(ra[near], dec[near], 1)
    return x, y


def _frame_positions(frame, cat, wcs):
    """x, y (FITS pixels) and ra, dec of every catalogue row on a frame (x, y NaN far from it)."""
    if "ra" in cat:
        if wcs is None:
            raise PerscliError(f"{frame.label}: no WCS in the header to place ra/dec; give a catalogue with x/y")
        x, y = frame_xy(wcs, frame.shape, cat["ra"], cat["dec"])
        return x, y, cat["ra"], cat["dec"]
    x, y = cat["x"], cat["y"]
    if wcs is not None:
        ra, dec = wcs.all_pix2world(x, y, 1)
    else:
        ra = dec = np.full(len(x), np.nan)
    return np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), ra, dec


def _pixel_scale(wcs) -> float:
    if wcs is None:
        return ROMAN_PIXEL_SCALE

    return float(np.mean(proj_plane_pixel_scales(wcs.celestial)) * 3600.0)


def on_frame(x, y, shape) -> np.ndarray:
    """True where FITS pixel position (x, y) falls on a frame of ``shape``: its nearest pixel exists."""
    ny, nx = shape
    ix = np.floor(np.asarray(x, dtype=np.float64) - 0.5)
    iy = np.floor(np.asarray(y, dtype=np.float64) - 0.5)
    with np.errstate(invalid="ignore"):
        return (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)


def blended(x, y, radius: float, shape=None) -> np.ndarray:
    """True for catalogue objects with another object within ``radius`` pixels.

    ``shape`` (ny, nx): only objects on a frame of that shape or within
    ``radius`` of it are looked at (the others are False): a catalogue of a
    million objects around a frame costs seconds otherwise, and only the
    objects on the frame are fitted.
    """
    pts = np.column_stack([x, y])
    ok = np.all(np.isfinite(pts), axis=1)
    if shape is not None:
        reach = radius + 1.0
        with np.errstate(invalid="ignore"):
            ok &= (pts[:, 0] >= 0.5 - reach) & (pts[:, 0] <= shape[1] + 0.5 + reach) \
                & (pts[:, 1] >= 0.5 - reach) & (pts[:, 1] <= shape[0] + 0.5 + reach)
    out = np.zeros(len(x), dtype=bool)
    if ok.sum() > 1 and radius > 0:
        tree = cKDTree(pts[ok])
        counts = np.array([len(n) for n in tree.query_ball_point(pts[ok], radius)])
        out[np.flatnonzero(ok)] = counts > 1
    return out


def blended_on_sky(ra, dec, radius_arcsec: float) -> np.ndarray:
    """True for objects with another within ``radius_arcsec`` (chord distance on the unit sphere)."""
    ra_r, dec_r = np.radians(ra), np.radians(dec)
    xyz = np.column_stack([np.cos(dec_r) * np.cos(ra_r), np.cos(dec_r) * np.sin(ra_r), np.sin(dec_r)])

    out = np.zeros(len(ra), dtype=bool)
    if len(ra) > 1 and radius_arcsec > 0:
        chord = 2.0 * np.sin(np.radians(radius_arcsec / 3600.0) / 2.0)
        counts = np.array([len(n) for n in cKDTree(xyz).query_ball_point(xyz, chord)])
        out = counts > 1
    return out
