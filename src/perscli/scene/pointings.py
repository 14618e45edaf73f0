"""Pointings: the exposures that look at a field, in time order.

Two sources:

- a real survey schedule (:func:`read_schedule`, :func:`select_covering`):
  a FITS binary table with columns ``date`` (start, MJD), ``exptime`` (s),
  ``ra``, ``dec``, ``pa`` (degrees) and ``filter``, such as the public Roman
  Wide Area Survey sequence ``Roman_WAS_obseq_11_1_23.fits`` (16,956
  exposures of 139.8 s that start ~169.8 s apart).  The exposures whose
  pointing centre lies within a radius of the field centre (great-circle
  distance) are kept, in time order, each with its row number as ``expid``.
- a planned dithered sequence (:func:`plan_dithers`): N exposures of
  ``exptime`` seconds, each starting ``gap`` seconds after the previous one
  ends (defaults 139.8 s and 30 s, the survey's cadence), pointed at the
  field centre offset by a random amount uniform in [-dither, +dither]
  arcsec along east and north on the tangent plane, all at the same PA.

A pointing is the telescope's boresight (the schedule's ra, dec, pa); ``sca``
names one detector of the focal plane when the caller chooses one, 0 when
not.  Pointings are written as a FITS table 'POINTINGS' (:func:`write_pointings`)
and read back with :func:`read_pointings`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_EXPTIME, ROMAN_WAS_GAP
from ..io.tables import read_table
from . import check_filter, deproject, separation

DAY = 86400.0

#: the schedule's columns and what they must hold
SCHEDULE_COLUMNS = {"date": "number", "exptime": "number", "ra": "number", "dec": "number", "pa": "number",
                    "filter": "text"}

#: the columns of a pointings table: name -> (FITS format, unit, description)
POINTING_COLUMNS = {
    "expid": ("K", None, "exposure number (schedule row, or sequence number)"),
    "mjd": ("D", "d", "exposure start (MJD)"),
    "exptime": ("D", "s", "exposure time"),
    "ra": ("D", "deg", "pointing centre, right ascension"),
    "dec": ("D", "deg", "pointing centre, declination"),
    "pa": ("D", "deg", "position angle of the focal plane"),
    "filter": ("4A", None, "Roman filter"),
    "sca": ("J", None, "detector (SCA 1-18), 0 if not chosen"),
}

#: Roman Wide Area Survey cadence (../shared/data/roman): exposure time and gap between exposures, s
WAS_EXPTIME = ROMAN_EXPTIME
WAS_GAP = ROMAN_WAS_GAP


@dataclass(frozen=True)
class Pointing:
    """One exposure.

    Attributes
    ----------
    expid : int
        Row of the schedule, or number in a planned sequence.
    mjd : float
        Start of the exposure (MJD).
    exptime : float
        Seconds.
    ra, dec, pa : float
        Pointing centre and position angle, degrees.
    filter : str
        Roman filter name, e.g. 'J129'.
    sca : int
        Detector 1-18, or 0 when none was chosen.
    """

    expid: int
    mjd: float
    exptime: float
    ra: float
    dec: float
    pa: float
    filter: str
    sca: int = 0

    @property
    def end(self) -> float:
        """End of the exposure (MJD)."""
        return self.mjd + self.exptime / DAY


@dataclass
class Schedule:
    """A survey schedule as columns (one entry per exposure, in file order)."""

    mjd: np.ndarray
    exptime: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    pa: np.ndarray
    filter: np.ndarray
    name: str = ""
    datasum: int = 0

    def __len__(self) -> int:
        return len(self.mjd)


def read_schedule(path: str, *, stdin=None) -> Schedule:
    """Read a survey schedule: the first binary table of a FITS file.

    Parameters
    ----------
    path : str
        FITS file, '-' for standard input.

    Raises
    ------
    PerscliError
        Unreadable file, or a column of :data:`SCHEDULE_COLUMNS` missing or
        holding the wrong type (the message names it).
    """
    table = read_table(path, what="schedule", stdin=stdin)
    cols = {name: table.column(name, kind=kind, needed=tuple(SCHEDULE_COLUMNS))
            for name, kind in SCHEDULE_COLUMNS.items()}
    return Schedule(mjd=cols["date"].astype(np.float64), exptime=cols["exptime"].astype(np.float64),
                    ra=cols["ra"].astype(np.float64), dec=cols["dec"].astype(np.float64),
                    pa=cols["pa"].astype(np.float64), filter=cols["filter"], name=path,
                    datasum=table.datasum)


def _check_centre(ra: float, dec: float):
    if not (math.isfinite(ra) and math.isfinite(dec) and -90.0 <= dec <= 90.0):
        raise PerscliError(f"field centre ({ra}, {dec}): give RA in degrees and Dec in [-90, 90] degrees")


def _check_sca(sca: int) -> int:
    if not 0 <= int(sca) <= 18:
        raise PerscliError(f"SCA {sca}: Roman has detectors 1 to 18 (0: none chosen)")
    return int(sca)


def select_covering(schedule: Schedule, ra: float, dec: float, radius: float, *, filter: str | None = None,
                    after: float | None = None, limit: int | None = None, sca: int = 0) -> list:
    """The exposures of ``schedule`` pointed within ``radius`` of (ra, dec), in time order.

    Parameters
    ----------
    schedule : Schedule
    ra, dec : float
        Field centre, degrees.
    radius : float
        Degrees, great-circle distance between the pointing centre and (ra, dec).
    filter : str, optional
        Only exposures in this Roman filter (any case).
    after : float, optional
        Only exposures that start after this MJD.
    limit : int, optional
        At most this many (the earliest).
    sca : int
        Written into every pointing (0: none chosen).

    Returns
    -------
    list of Pointing
        ``expid`` is the exposure's row in the schedule (from 0).  Rows with
        non-finite times or positions are never selected.
    """
    _check_centre(ra, dec)
    if not (radius > 0 and math.isfinite(radius)):
        raise PerscliError(f"radius {radius} degrees: must be a number > 0")
    if limit is not None and limit < 0:
        raise PerscliError(f"limit {limit}: must be >= 0")
    sca = _check_sca(sca)
    with np.errstate(invalid="ignore"):
        keep = separation(ra, dec, schedule.ra, schedule.dec) <= radius
        keep &= np.isfinite(schedule.mjd) & np.isfinite(schedule.exptime)
        if filter is not None:
            keep &= np.char.upper(schedule.filter) == check_filter(filter)
        if after is not None:
            keep &= schedule.mjd > after
    rows = np.flatnonzero(keep)
    rows = rows[np.argsort(schedule.mjd[rows], kind="stable")]
    if limit is not None:
        rows = rows[:limit]
    return [Pointing(expid=int(i), mjd=float(schedule.mjd[i]), exptime=float(schedule.exptime[i]),
                     ra=float(schedule.ra[i]), dec=float(schedule.dec[i]), pa=float(schedule.pa[i]),
                     filter=str(schedule.filter[i]), sca=sca) for i in rows]


def plan_dithers(ra: float, dec: float, n: int, *, dither: float = 10.0, filter: str = "J129",
                 start: float = 60000.0, exptime: float = WAS_EXPTIME, gap: float = WAS_GAP, pa: float = 0.0,
                 sca: int = 0, seed: int = 1) -> list:
    """A dithered sequence of ``n`` exposures on (ra, dec).

    Parameters
    ----------
    ra, dec : float
        Field centre, degrees.
    n : int
        Number of exposures.
    dither : float
        Offsets are uniform in [-dither, +dither] arcsec along east and along
        north on the tangent plane at (ra, dec), independently per exposure.
    filter : str
        Roman filter of every exposure.
    start : float
        MJD at which the first exposure starts.
    exptime, gap : float
        Seconds: each exposure lasts ``exptime`` and the next starts ``gap``
        seconds after it ends.
    pa : float
        Position angle of every exposure, degrees.
    sca : int
        Detector written into every pointing (0: none chosen).
    seed : int
        Seed of ``numpy.random.Generator(PCG64(seed))`` for the offsets.

    Returns
    -------
    list of Pointing
        ``expid`` 0 to n-1.
    """
    _check_centre(ra, dec)
    if n < 0:
        raise PerscliError(f"number of exposures {n}: must be >= 0")
    for label, value in (("dither", dither), ("exposure time", exptime), ("gap", gap)):
        if not (math.isfinite(value) and value >= 0):
            raise PerscliError(f"{label} {value}: must be a number >= 0")
    if int(seed) < 0:
        raise PerscliError(f"seed {seed}: must be an integer >= 0")
    filter = check_filter(filter)
    sca = _check_sca(sca)
    rng = np.random.Generator(np.random.PCG64(int(seed)))
    offsets = np.radians(rng.uniform(-dither, dither, (n, 2)) / 3600.0)
    ras, decs = deproject(ra, dec, offsets[:, 0], offsets[:, 1])
    step = (exptime + gap) / DAY
    return [Pointing(expid=i, mjd=start + i * step, exptime=float(exptime), ra=float(ras[i]), dec=float(decs[i]),
                     pa=float(pa) % 360.0, filter=filter, sca=sca) for i in range(n)]


def pointings_hdulist(pointings, *, step: str, params: dict | None = None, inputs=(), seed: int | None = None):
    """The FITS file of ``pointings``: an empty primary HDU and the 'POINTINGS' table with provenance.

    ``step``, ``params``, ``inputs`` and ``seed`` are those of
    :func:`perscli.io.output.add_provenance`.
    """
    from ..io.fitsfile import OutHDU, format_card, table_hdu
    from ..io.output import add_provenance

    values = {
        "expid": np.array([p.expid for p in pointings], dtype=np.int64),
        "mjd": np.array([p.mjd for p in pointings], dtype=np.float64),
        "exptime": np.array([p.exptime for p in pointings], dtype=np.float64),
        "ra": np.array([p.ra for p in pointings], dtype=np.float64),
        "dec": np.array([p.dec for p in pointings], dtype=np.float64),
        "pa": np.array([p.pa for p in pointings], dtype=np.float64),
        "filter": np.array([p.filter for p in pointings], dtype="S4"),
        "sca": np.array([p.sca for p in pointings], dtype=np.int32),
    }
    names = list(POINTING_COLUMNS)
    cards = [format_card(f"TCOMM{k}", desc) for k, (_, _, desc) in enumerate(POINTING_COLUMNS.values(), 1)]
    cards.append(format_card("NEXP", len(pointings), "exposures in this table"))
    hdu = table_hdu({name: values[name] for name in names}, "POINTINGS",
                    units={name: unit for name, (_, unit, _) in POINTING_COLUMNS.items()}, cards=cards)
    add_provenance(hdu, step=step, params=params, inputs=inputs, seed=seed)
    return [OutHDU([]), hdu]


def write_pointings(pointings, dest: str, *, overwrite: bool = False, stdout=None, **provenance) -> None:
    """Write ``pointings`` atomically (or to standard output for '-'); ``provenance`` as :func:`pointings_hdulist`."""
    from ..io.output import write_hdus

    write_hdus(pointings_hdulist(pointings, **provenance), dest, overwrite=overwrite, stdout=stdout)


def read_pointings(path: str, *, stdin=None) -> list:
    """Read a pointings table written by :func:`write_pointings`, or a survey schedule.

    A schedule (columns date, exptime, ra, dec, pa, filter, like the public
    Roman WAS sequence) gives one pointing per row, expid = row number, no SCA.

    Raises
    ------
    PerscliError
        Unreadable file, or a column of :data:`POINTING_COLUMNS` missing or of the wrong type.
    """
    table = read_table(path, what="pointings table", stdin=stdin)
    names = {n.lower() for n in table.names}
    if "mjd" not in names and "date" in names:
        cols = {name: table.column(name, kind=kind, needed=tuple(SCHEDULE_COLUMNS))
                for name, kind in SCHEDULE_COLUMNS.items()}
        return [Pointing(expid=i, mjd=float(cols["date"][i]), exptime=float(cols["exptime"][i]),
                         ra=float(cols["ra"][i]), dec=float(cols["dec"][i]), pa=float(cols["pa"][i]),
                         filter=str(cols["filter"][i]), sca=0) for i in range(len(table))]
    kinds = {"expid": "integer", "sca": "integer", "filter": "text"}
    cols = {name: table.column(name, kind=kinds.get(name, "number"), needed=tuple(POINTING_COLUMNS))
            for name in POINTING_COLUMNS}
    return [Pointing(expid=int(cols["expid"][i]), mjd=float(cols["mjd"][i]), exptime=float(cols["exptime"][i]),
                     ra=float(cols["ra"][i]), dec=float(cols["dec"][i]), pa=float(cols["pa"][i]),
                     filter=str(cols["filter"][i]), sca=int(cols["sca"][i])) for i in range(len(table))]


def select_covering_file(dest: str, schedule: str, ra: float, dec: float, radius: float, *,
                         filter: str | None = None, after: float | None = None, limit: int | None = None,
                         sca: int = 0, overwrite: bool = False, stdin=None, stdout=None) -> list:
    """Check ``dest``, select from the schedule file (:func:`select_covering`) and write the pointings."""
    from ..io.output import check_output

    check_output(dest, overwrite=overwrite, inputs=[schedule])
    if filter is not None:
        filter = check_filter(filter)
    sched = read_schedule(schedule, stdin=stdin)
    chosen = select_covering(sched, ra, dec, radius, filter=filter, after=after, limit=limit, sca=sca)
    params = {
        "PTMODE": ("schedule", "pointings: selected from a schedule"),
        "PTRA": (float(ra), "[deg] field centre, RA"),
        "PTDEC": (float(dec), "[deg] field centre, Dec"),
        "PTRADIUS": (float(radius), "[deg] pointing centres within this distance"),
        "PTFILTER": (filter or "any", "filter selected"),
        "PTLIMIT": (int(limit) if limit is not None else 0, "at most this many (0: no limit)"),
        "PTSCA": (int(sca), "detector written in every row (0: none)"),
        "PTNSCHED": (len(sched), "exposures in the schedule"),
    }
    if after is not None:
        params["PTAFTER"] = (float(after), "[MJD] only exposures starting later")
    step = (f"pointings schedule ra={ra} dec={dec} radius={radius} filter={filter or 'any'} "
            f"selected={len(chosen)} of {len(sched)}")
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params,
                    inputs=[("SCHED", schedule, sched.datasum)])
    return chosen


def plan_dithers_file(dest: str, ra: float, dec: float, n: int, *, dither: float = 10.0, filter: str = "J129",
                      start: float = 60000.0, exptime: float = WAS_EXPTIME, gap: float = WAS_GAP,
                      pa: float = 0.0, sca: int = 0, seed: int = 1, overwrite: bool = False,
                      stdout=None) -> list:
    """Check ``dest``, plan a dithered sequence (:func:`plan_dithers`) and write it."""
    from ..io.output import check_output

    check_output(dest, overwrite=overwrite)
    chosen = plan_dithers(ra, dec, n, dither=dither, filter=filter, start=start, exptime=exptime, gap=gap,
                          pa=pa, sca=sca, seed=seed)
    params = {
        "PTMODE": ("plan", "pointings: a planned dithered sequence"),
        "PTRA": (float(ra), "[deg] field centre, RA"),
        "PTDEC": (float(dec), "[deg] field centre, Dec"),
        "PTDITHER": (float(dither), "[arcsec] offsets uniform within +-this"),
        "PTFILTER": (check_filter(filter), "filter of every exposure"),
        "PTSTART": (float(start), "[MJD] start of the first exposure"),
        "PTEXPT": (float(exptime), "[s] exposure time"),
        "PTGAP": (float(gap), "[s] from the end of one exposure to the next"),
        "PTPA": (float(pa) % 360.0, "[deg] position angle"),
        "PTSCA": (int(sca), "detector written in every row (0: none)"),
    }
    step = f"pointings plan ra={ra} dec={dec} n={n} dither={dither} filter={check_filter(filter)} seed={seed}"
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params, seed=seed)
    return chosen
