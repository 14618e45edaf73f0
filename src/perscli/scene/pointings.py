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
  Every exposure of a plan is one Roman can take (GalSim's Sun-angle
  limits, :func:`observable`): without a start, the plan starts at the
  first observable date on or after :data:`PLAN_REFERENCE_MJD` (the first
  exposure of the public survey schedule), searched in steps of one day
  (:func:`first_observable_start`); without a PA, at GalSim's best PA
  (:func:`best_pa`) at that start.  A start given is checked, and refused
  with the first observable date after it.

A pointing is the telescope's boresight (the schedule's ra, dec, pa: the
centre of the focal plane and the observatory's position angle, as
``galsim.roman.getWCS`` takes them); ``sca`` names one detector of the focal
plane when the caller chooses one, 0 when not.

Detectors on the sky:

- :func:`sca_footprint`: the four corners on the sky of one SCA (its outer
  pixel edges, or those of a cutout), through GalSim's Roman WCS for the
  pointing, optionally grown by a margin;
- :func:`select_covering` with ``sca=N`` keeps the exposures whose SCA N
  footprint overlaps the field circle (not only those whose boresight is in
  it): the SCAs lie up to :data:`FPA_REACH_DEG` from the boresight;
- :func:`previous_exposures`: the exposures of a schedule that start before
  a given row, whatever their filter and pointing: on the same detector they
  are what leaves persistence in it;
- :func:`sky_to_pixels` and :func:`objects_on_sca`: where catalogue objects
  land on an SCA, and which of them land on it (or on a cutout of it);
  :func:`count_on_sca` counts them, by kind, for every row of a table.

Observability (GalSim's Roman module, ``galsim.roman.allowedPos`` and
``bestPA``): Roman looks at positions 54 to 126 degrees from the Sun
(90 +- ``galsim.roman.max_sun_angle``); GalSim does not limit the roll
about the boresight (``getWCS`` takes any PA), and neither does perscli: the
public schedule's PAs lie far from ``bestPA`` (another convention), so a roll
limit would refuse the real survey.

Pointings are written as a FITS table 'POINTINGS' (:func:`write_pointings`,
with each row's SCA corners when asked) and read back with
:func:`read_pointings`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_EXPTIME, ROMAN_N_SCA, ROMAN_PIXEL_SCALE, ROMAN_SCA_SIZE, ROMAN_WAS_GAP
from ..io.tables import read_table
from . import (check_filter, check_mjd, check_pa, check_position, check_positions, deproject, mjd_datetime,
               separation)

log = logging.getLogger(__name__)

DAY = 86400.0

#: farthest any SCA corner lies from the boresight (the centre of the focal plane), degrees: GalSim's
#: Roman focal plane reaches 0.450 deg; 0.5 bounds it for the pre-selection of :func:`select_covering`
FPA_REACH_DEG = 0.5

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

#: the optional columns of :func:`pointings_hdulist` with ``footprints=True``
FOOTPRINT_COLUMNS = {
    "corner_ra": ("4D", "deg", "SCA corners (pixel edges) (0.5,0.5) (4088.5,0.5) (4088.5,4088.5) (0.5,4088.5): RA"),
    "corner_dec": ("4D", "deg", "SCA corners, same order: Dec"),
}

#: the optional columns of :func:`pointings_hdulist` with ``counts``: catalogue objects on each row's SCA
COUNT_COLUMNS = {
    "n_star": ("K", None, "catalogue stars whose centre lands on the SCA"),
    "n_galaxy": ("K", None, "catalogue galaxies whose centre lands on the SCA"),
}

#: Roman Wide Area Survey cadence (the public WAS schedule, Roman_WAS_obseq_11_1_23.fits): exposure time and gap between exposures, s
WAS_EXPTIME = ROMAN_EXPTIME
WAS_GAP = ROMAN_WAS_GAP

#: [MJD] where a plan without a start looks for its first observable date: the start of the first exposure
#: of the public Roman Wide Area Survey schedule (Roman_WAS_obseq_11_1_23.fits), 2027-05-16 23:20:18 UTC.
#: A fixed date, not today's, so that the same inputs give the same plan
PLAN_REFERENCE_MJD = 61541.972429

#: [days] how far after its earliest date a start is searched for (every position is observable at some
#: time of a year), and in what steps
OBSERVABLE_SEARCH_DAYS = 366
OBSERVABLE_SEARCH_STEP = 1.0

#: [deg] objects farther than this from an SCA's centre are taken to be off it without asking the WCS:
#: the SCA's half-diagonal is 0.09 deg and the largest stamp 0.06 deg wide, while GalSim's TAN-SIP WCS maps
#: the far side of the sky back onto the frame (the antipode of the centre lands on the centre) and fails to
#: converge for distant points
NEAR_SCA_DEG = 0.5


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


def schedule_pointing(schedule: Schedule, row: int, *, sca: int = 0) -> Pointing:
    """Row ``row`` (from 0) of a schedule as a :class:`Pointing` (``expid`` = row, ``sca`` written in).

    Raises
    ------
    PerscliError
        A row outside the schedule.
    """
    row = _check_row(schedule, row)
    return Pointing(expid=row, mjd=float(schedule.mjd[row]), exptime=float(schedule.exptime[row]),
                    ra=float(schedule.ra[row]), dec=float(schedule.dec[row]), pa=float(schedule.pa[row]),
                    filter=str(schedule.filter[row]).strip(), sca=_check_sca(sca))


def _check_row(schedule: Schedule, row) -> int:
    if isinstance(row, bool) or int(row) != row or not 0 <= int(row) < len(schedule):
        where = f"{schedule.name}: " if schedule.name else ""
        raise PerscliError(f"{where}schedule row {row} does not exist: the rows are 0 to {len(schedule) - 1}")
    return int(row)


def read_schedule(path: str, *, stdin=None, columns=None) -> Schedule:
    """Read a survey schedule: the first binary table of a FITS file.

    Parameters
    ----------
    path : str
        FITS file, '-' for standard input.
    columns : dict, optional
        Column mapping {perscli name: file column} for another survey's
        schedule (names of :data:`SCHEDULE_COLUMNS`).

    Raises
    ------
    PerscliError
        Unreadable file, a column of :data:`SCHEDULE_COLUMNS` missing or
        holding the wrong type (the message names it), or an exposure time
        <= 0 (:func:`check_exptimes`).
    """
    table = read_table(path, what="schedule", stdin=stdin, columns=columns or {}, known=tuple(SCHEDULE_COLUMNS))
    cols = {name: table.column(name, kind=kind, needed=tuple(SCHEDULE_COLUMNS))
            for name, kind in SCHEDULE_COLUMNS.items()}
    check_exptimes(table.label, cols["exptime"], what="schedule")
    return Schedule(mjd=cols["date"].astype(np.float64), exptime=cols["exptime"].astype(np.float64),
                    ra=cols["ra"].astype(np.float64), dec=cols["dec"].astype(np.float64),
                    pa=cols["pa"].astype(np.float64), filter=cols["filter"], name=path,
                    datasum=table.datasum)


def check_exptimes(label: str, exptime, *, what: str = "pointings table") -> None:
    """Refuse exposure times that no exposure can have: <= 0 seconds (or, in a pointings table, not finite).

    A schedule may hold rows without a time (NaN), which are never selected
    (:func:`select_covering`, :func:`previous_exposures`); a pointings table
    is what render takes one exposure from, so every row must have one.  A
    negative time would otherwise pass into the output and into render's
    exposure (an end before its start).

    Parameters
    ----------
    label : str
        The file, for the message.
    exptime : array_like
        Seconds.
    what : {'schedule', 'pointings table'}
        What the file is: a schedule allows non-finite times.

    Raises
    ------
    PerscliError
        One line naming the file, how many rows and the first.
    """
    exptime = np.asarray(exptime, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = exptime <= 0
        if what != "schedule":
            bad |= ~np.isfinite(exptime)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise PerscliError(f"{label}: column exptime has {int(bad.sum())} value(s) that cannot be an exposure time "
                           f"(first: row {i}, exptime = {exptime[i]:g} s): an exposure lasts > 0 seconds; "
                           f"fix or drop those rows of the {what}")


def _check_centre(ra: float, dec: float):
    return check_position(ra, dec, "field centre")


def _check_sca(sca: int) -> int:
    if not 0 <= int(sca) <= 18:
        raise PerscliError(f"SCA {sca}: Roman has detectors 1 to 18 (0: none chosen)")
    return int(sca)


def select_covering(schedule: Schedule, ra: float, dec: float, radius: float, *, filter: str | None = None,
                    after: float | None = None, limit: int | None = None, sca: int = 0) -> list:
    """The exposures of ``schedule`` that look at the field (ra, dec, radius), in time order.

    Parameters
    ----------
    schedule : Schedule
    ra, dec : float
        Field centre, degrees.
    radius : float
        Degrees: the field is the circle (cap) of this great-circle radius.
    filter : str, optional
        Only exposures in this Roman filter (any case).
    after : float, optional
        Only exposures that start after this MJD.
    limit : int, optional
        At most this many (the earliest).
    sca : int
        0: the exposures whose pointing centre (boresight) lies within
        ``radius`` of (ra, dec).  1-18: the exposures that put that SCA on
        the field, i.e. whose SCA footprint (:func:`sca_footprint`, GalSim's
        WCS) overlaps the field circle; ``sca`` is written into every
        pointing.  (A boresight up to :data:`FPA_REACH_DEG` beyond the
        radius can qualify; a boresight inside it need not, since the SCA
        may point elsewhere.)

    Returns
    -------
    list of Pointing
        ``expid`` is the exposure's row in the schedule (from 0).  Rows with
        non-finite times or positions are never selected.

    Raises
    ------
    PerscliError
        A bad centre, radius, limit or SCA; with ``sca``, a row that Roman
        cannot observe at its date (GalSim's Sun-angle limits).
    """
    _check_centre(ra, dec)
    if not (radius > 0 and math.isfinite(radius)):
        raise PerscliError(f"radius {radius} degrees: must be a number > 0")
    if limit is not None and limit < 0:
        raise PerscliError(f"limit {limit}: must be >= 0")
    sca = _check_sca(sca)
    reach = radius + (FPA_REACH_DEG if sca else 0.0)
    with np.errstate(invalid="ignore"):
        keep = separation(ra, dec, schedule.ra, schedule.dec) <= reach
        keep &= np.isfinite(schedule.mjd) & np.isfinite(schedule.exptime)
        if sca:
            keep &= np.isfinite(schedule.pa)
        if filter is not None:
            keep &= np.char.upper(np.char.strip(schedule.filter.astype(str))) == check_filter(filter)
        if after is not None:
            keep &= schedule.mjd > after
    rows = np.flatnonzero(keep)
    rows = rows[np.argsort(schedule.mjd[rows], kind="stable")]
    if not sca:
        if limit is not None:
            rows = rows[:limit]
        return [schedule_pointing(schedule, i) for i in rows]
    from .regions import polygon_meets_circle

    chosen = []
    for i in rows:
        if limit is not None and len(chosen) >= limit:
            break
        p = schedule_pointing(schedule, i, sca=sca)
        if polygon_meets_circle(*sca_footprint(p, sca), ra, dec, radius):
            chosen.append(p)
    return chosen


def previous_exposures(schedule: Schedule, row: int, n: int, *, sca: int = 0) -> list:
    """The ``n`` exposures of ``schedule`` that start last before row ``row`` starts, in time order.

    Whatever their filter and wherever they point: on one detector, every
    earlier exposure leaves persistence, so a frame's history is the rows
    just before it in time.

    Parameters
    ----------
    schedule : Schedule
    row : int
        The exposure (schedule row, from 0).
    n : int
        How many earlier exposures (>= 0).
    sca : int
        Written into every pointing (0: none chosen).

    Returns
    -------
    list of Pointing
        At most ``n`` (fewer when the schedule starts sooner), earliest
        first, the most recent last; ``expid`` is the schedule row.  Rows
        that start at the same time as ``row`` or later, and rows with
        non-finite times, are not earlier exposures.

    Raises
    ------
    PerscliError
        A row outside the schedule, a row without a finite start, or n < 0.
    """
    row = _check_row(schedule, row)
    if isinstance(n, bool) or int(n) != n or n < 0:
        raise PerscliError(f"number of earlier exposures {n}: must be a whole number >= 0")
    sca = _check_sca(sca)
    start = schedule.mjd[row]
    if not math.isfinite(start):
        raise PerscliError(f"schedule row {row} has no finite start time (date {start})")
    with np.errstate(invalid="ignore"):
        earlier = np.flatnonzero((schedule.mjd < start) & np.isfinite(schedule.exptime))
    # time order, ties by row; the last n are the most recent
    earlier = earlier[np.lexsort((earlier, schedule.mjd[earlier]))]
    picked = earlier[len(earlier) - int(n):] if n else earlier[:0]
    return [schedule_pointing(schedule, i, sca=sca) for i in picked]


# -- detectors on the sky -------------------------------------------------------------------------

def _date(mjd: float):
    return mjd_datetime(mjd)


def _when(mjd: float) -> str:
    return f"MJD {mjd:.5f} ({mjd_datetime(mjd):%Y-%m-%d %H:%M} UTC)"


def sun_limits() -> tuple:
    """GalSim's limits on the angle between a Roman pointing and the Sun, degrees: (54, 126)."""
    import galsim.roman as roman

    return 90.0 - roman.max_sun_angle, 90.0 + roman.max_sun_angle


def sun_angle(ra: float, dec: float, mjd: float) -> float:
    """Degrees between (ra, dec) and the Sun at ``mjd``, computed as ``galsim.roman.allowedPos`` does."""
    import coord
    import galsim

    date = mjd_datetime(mjd)
    lam = coord.util.sun_position_ecliptic(date)
    sun = coord.CelestialCoord.from_ecliptic(lam, 0 * coord.radians, date.year)
    world = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    return float(world.distanceTo(sun) / galsim.degrees)


def observable(ra: float, dec: float, mjd: float) -> bool:
    """Whether Roman can point at (ra, dec) (degrees) at ``mjd``: ``galsim.roman.allowedPos``.

    Raises
    ------
    PerscliError
        A position or date out of range.
    """
    import galsim
    import galsim.roman as roman

    ra, dec = check_position(ra, dec, "pointing")
    mjd = check_mjd(mjd)
    return bool(roman.allowedPos(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees),
                                 mjd_datetime(mjd)))


def best_pa(ra: float, dec: float, mjd: float) -> float | None:
    """GalSim's best observatory position angle at (ra, dec) on ``mjd``, degrees in [0, 360).

    ``galsim.roman.bestPA``: the solar panels face the Sun as directly as
    possible.  None when Roman cannot point there then.
    """
    import galsim
    import galsim.roman as roman

    ra, dec = check_position(ra, dec, "pointing")
    pa = roman.bestPA(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees), mjd_datetime(check_mjd(mjd)))
    return None if pa is None else float(pa / galsim.degrees) % 360.0


def _first_unobservable(ras, decs, starts, ends):
    """Index of the first exposure (ra, dec, start, end in MJD) Roman cannot take, or None.

    Observing windows and the gaps between them last days (the Sun moves by a degree a day), so an
    exposure is checked at its start, its end and every half day between (none for a survey exposure).
    """
    for i in range(len(starts)):
        times = [starts[i], *np.arange(starts[i] + 0.5, ends[i], 0.5), ends[i]]
        if not all(observable(ras[i], decs[i], t) for t in times):
            return i
    return None


def first_observable_start(ras, decs, offsets, durations, earliest: float, *,
                           days: float = OBSERVABLE_SEARCH_DAYS, step: float = OBSERVABLE_SEARCH_STEP):
    """The first start at which Roman can take every exposure of a sequence.

    Parameters
    ----------
    ras, decs : sequence of float
        Each exposure's pointing, degrees.
    offsets : sequence of float
        Each exposure's start after the sequence's start, days.
    durations : sequence of float
        Each exposure's length, days.
    earliest : float
        MJD: the starts tried are ``earliest + k * step`` for k = 0, 1, ...
    days, step : float
        Search ``days`` days after ``earliest``, in steps of ``step`` days.

    Returns
    -------
    float or None
        The first such start (MJD), or None when there is none within ``days``.
    """
    ras, decs = list(ras), list(decs)
    offsets, durations = np.asarray(offsets, dtype=np.float64), np.asarray(durations, dtype=np.float64)
    if not ras:
        return float(earliest)
    # cheap filters first, the first and the last exposure, then about two exposures a day; a start is
    # accepted only once every exposure has been checked
    n = len(ras)
    stride = max(1, int(0.5 / max(float(offsets[-1]) / max(n - 1, 1), 1e-9)))
    coarse = sorted({0, n - 1, *range(0, n, stride)})
    for k in range(int(math.floor(days / step)) + 1):
        start = earliest + k * step
        for subset in ([0, n - 1], coarse, range(n)):
            idx = list(subset)
            if _first_unobservable([ras[i] for i in idx], [decs[i] for i in idx], start + offsets[idx],
                                   start + offsets[idx] + durations[idx]) is not None:
                break
        else:
            return float(start)
    return None


def _never_observable(ra: float, dec: float, mjd: float, days: float) -> bool:
    return first_observable_start([ra], [dec], [0.0], [0.0], mjd, days=days) is None


def unobservable_message(ra: float, dec: float, mjd: float, what: str = "") -> str:
    """One line: Roman cannot point at (ra, dec) at ``mjd``, why, and the first date on or after it when it can."""
    low, high = sun_limits()
    angle = sun_angle(ra, dec, mjd)
    later = first_observable_start([ra], [dec], [0.0], [0.0], mjd)
    where = f"ra={ra:g} dec={dec:g}"
    head = f"{what}: " if what else ""
    text = (f"{head}Roman cannot point at {where} on {_when(mjd)}: the Sun is {angle:.1f} degrees from it and "
            f"GalSim's Roman module allows {low:g} to {high:g} degrees")
    if later is None:
        return text + ", which it never is in the year after; choose another field"
    pa = best_pa(ra, dec, later)
    return text + f"; the first date after it when Roman can is {_when(later)}, best PA {pa:.2f} degrees"


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
    import galsim
    import galsim.roman as roman

    if not 1 <= int(sca) <= ROMAN_N_SCA:
        raise PerscliError(f"SCA {sca}: Roman has detectors 1 to {ROMAN_N_SCA}")
    ra, dec = check_position(getattr(pointing, "ra"), getattr(pointing, "dec"), "pointing")
    pa = check_pa(getattr(pointing, "pa"), "pointing: position angle")
    mjd = check_mjd(getattr(pointing, "mjd"), "pointing: date")
    date = _date(mjd)
    world = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    if not roman.allowedPos(world, date):
        raise PerscliError(unobservable_message(ra, dec, mjd) + " (perscli pointings --plan chooses an "
                           "observable date; render --mjd, pointings --start)")
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
    import galsim

    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    x, y = np.full(ra.shape, np.nan), np.full(ra.shape, np.nan)
    if ra.size == 0:
        return x, y
    centre = wcs.toWorld(galsim.PositionD(ROMAN_SCA_SIZE / 2 + 0.5, ROMAN_SCA_SIZE / 2 + 0.5))
    with np.errstate(invalid="ignore"):
        near = separation(centre.ra / galsim.degrees, centre.dec / galsim.degrees, ra, dec) <= NEAR_SCA_DEG
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


def plan_dithers(ra: float, dec: float, n: int, *, dither: float = 10.0, filter: str = "J129",
                 start: float | None = None, exptime: float = WAS_EXPTIME, gap: float = WAS_GAP,
                 pa: float | None = None, sca: int = 0, seed: int = 1,
                 reference: float = PLAN_REFERENCE_MJD) -> list:
    """A dithered sequence of ``n`` exposures on (ra, dec), every one of which Roman can take.

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
    start : float, optional
        MJD at which the first exposure starts.  Default: the first of
        ``reference + k`` days (k = 0 ... 366) at which Roman can take every
        exposure (:func:`first_observable_start`).
    exptime, gap : float
        Seconds: each exposure lasts ``exptime`` and the next starts ``gap``
        seconds after it ends.
    pa : float, optional
        Observatory position angle of every exposure, degrees (GalSim's
        convention; not checked against the Sun, as GalSim does not).
        Default: GalSim's best PA (:func:`best_pa`) for the first exposure at
        its start.
    sca : int
        Detector written into every pointing (0: none chosen).
    seed : int
        Seed of ``numpy.random.Generator(PCG64(seed))`` for the offsets.
    reference : float
        MJD where the search for a start begins (:data:`PLAN_REFERENCE_MJD`).

    Returns
    -------
    list of Pointing
        ``expid`` 0 to n-1; PA in [0, 360).

    Raises
    ------
    PerscliError
        Bad parameters; a ``start`` at which Roman cannot take every
        exposure (the message names the first start after it when it can,
        and the best PA then); no such start within a year (the sequence is
        longer than the field's observing windows).
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
    if pa is not None:
        pa = check_pa(pa)
    rng = np.random.Generator(np.random.PCG64(int(seed)))
    offsets = np.radians(rng.uniform(-dither, dither, (n, 2)) / 3600.0)
    ras, decs = deproject(ra, dec, offsets[:, 0], offsets[:, 1])
    step = (exptime + gap) / DAY
    after = np.arange(n) * step
    lengths = np.full(n, exptime / DAY)
    hours = float(after[-1] + lengths[-1]) * 24 if n else 0.0
    span = f"{n} exposure{'s' if n != 1 else ''} over " + (f"{hours:.2f} h" if hours < 48 else f"{hours / 24:.1f} days")
    if start is None:
        start = first_observable_start(ras, decs, after, lengths, check_mjd(reference, "reference date"))
        if start is None:
            raise PerscliError(_never_message(ra, dec, reference, span, "from"))
    else:
        start = check_mjd(start, "start")
        bad = _first_unobservable(ras, decs, start + after, start + after + lengths)
        if bad is not None:
            later = first_observable_start(ras, decs, after, lengths, start)
            t = start + after[bad]
            low, high = sun_limits()
            which = "the first exposure" if bad == 0 else f"exposure {bad} of {n}"
            text = (f"start {_when(start)}: Roman cannot take {which} of the plan (ra={ras[bad]:.5f} "
                    f"dec={decs[bad]:.5f} on {_when(t)}): the Sun is {sun_angle(ras[bad], decs[bad], t):.1f} "
                    f"degrees from it and GalSim's Roman module allows {low:g} to {high:g}")
            if later is None:
                raise PerscliError(text + "; " + _never_message(ra, dec, start, span, "after"))
            raise PerscliError(text + f"; the first start after it when Roman can is --start {later:.5f} "
                               f"({mjd_datetime(later):%Y-%m-%d}), best --pa {best_pa(ras[0], decs[0], later):.2f} "
                               "(or leave --start out: perscli chooses)")
    if pa is None:
        pa = best_pa(ras[0], decs[0], start) if n else 0.0
    return [Pointing(expid=i, mjd=start + i * step, exptime=float(exptime), ra=float(ras[i]), dec=float(decs[i]),
                     pa=float(pa) % 360.0, filter=filter, sca=sca) for i in range(n)]


def _never_message(ra, dec, mjd, span, word) -> str:
    if _never_observable(ra, dec, mjd, OBSERVABLE_SEARCH_DAYS):
        low, high = sun_limits()
        return (f"Roman can never point at ra={ra:g} dec={dec:g} in the year {word} MJD {mjd:.5f}: the Sun is "
                f"never {low:g} to {high:g} degrees from it")
    return (f"no start {word} MJD {mjd:.5f} within {OBSERVABLE_SEARCH_DAYS} days lets Roman take all {span} at "
            f"ra={ra:g} dec={dec:g}: the plan is longer than the field's observing windows; shorten it "
            "(--n, --exptime, --gap)")


def pointings_hdulist(pointings, *, step: str, params: dict | None = None, inputs=(), seed: int | None = None,
                      footprints: bool = False, counts: dict | None = None):
    """The FITS file of ``pointings``: an empty primary HDU and the 'POINTINGS' table with provenance.

    ``step``, ``params``, ``inputs`` and ``seed`` are those of
    :func:`perscli.io.output.add_provenance`.  With ``footprints`` the table
    also has the columns of :data:`FOOTPRINT_COLUMNS`: each row's SCA
    corners (:func:`sca_footprint` of its ``sca``, which must be 1-18);
    with ``counts`` (:func:`count_on_sca`) those of :data:`COUNT_COLUMNS`.
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
    columns = dict(POINTING_COLUMNS)
    if footprints:
        if any(not p.sca for p in pointings):
            raise PerscliError("footprints need an SCA: give --sca N (1-18)")
        corners = [sca_footprint(p, p.sca) for p in pointings]
        values["corner_ra"] = np.array([c[0] for c in corners], dtype=np.float64).reshape(-1, 4)
        values["corner_dec"] = np.array([c[1] for c in corners], dtype=np.float64).reshape(-1, 4)
        columns.update(FOOTPRINT_COLUMNS)
    if counts is not None:
        values["n_star"] = np.asarray(counts["star"], dtype=np.int64)
        values["n_galaxy"] = np.asarray(counts["galaxy"], dtype=np.int64)
        columns.update(COUNT_COLUMNS)
    cards = [format_card(f"TCOMM{k}", desc) for k, (_, _, desc) in enumerate(columns.values(), 1)]
    cards.append(format_card("NEXP", len(pointings), "exposures in this table"))
    hdu = table_hdu({name: values[name] for name in columns}, "POINTINGS",
                    units={name: unit for name, (_, unit, _) in columns.items()}, cards=cards)
    add_provenance(hdu, step=step, params=params, inputs=inputs, seed=seed)
    return [OutHDU([]), hdu]


def write_pointings(pointings, dest: str, *, overwrite: bool = False, stdout=None, **provenance) -> None:
    """Write ``pointings`` atomically (or to standard output for '-'); ``provenance`` (and ``footprints``,
    ``counts``) as :func:`pointings_hdulist`."""
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
    return _read_pointings(path, stdin=stdin)[0]


def pointings_footprints(path: str, *, sca: int = 0, margin_arcsec: float = 0.0, bounds=None,
                         stdin=None) -> tuple:
    """The SCA footprints (:func:`sca_footprint`) of every row of a pointings table.

    Parameters
    ----------
    path : str
        A pointings table (:func:`write_pointings`) or a schedule.
    sca : int
        The detector; 0: each row's own ``sca`` (every row must name one).
    margin_arcsec, bounds
        As :func:`sca_footprint`.

    Returns
    -------
    (list of (ra, dec), int)
        The corners of each row's footprint, and the table's DATASUM (for provenance).

    Raises
    ------
    PerscliError
        An unreadable table, an empty one, or a row without an SCA when ``sca`` is 0.
    """
    pointings, datasum = _read_pointings(path, stdin=stdin)
    label = "stdin" if path == "-" else path
    if not pointings:
        raise PerscliError(f"{label}: the pointings table is empty: no footprint to cover")
    sca = _check_sca(sca)
    if not sca and any(not p.sca for p in pointings):
        raise PerscliError(f"{label}: rows without an SCA (sca 0): give the detector (--sca N)")
    return [sca_footprint(p, sca or p.sca, margin_arcsec=margin_arcsec, bounds=bounds) for p in pointings], datasum


def _read_pointings(path: str, *, stdin=None) -> tuple:
    table = read_table(path, what="pointings table", stdin=stdin)
    return _pointings_of(table), table.datasum


def _pointings_of(table) -> list:
    names = {n.lower() for n in table.names}
    if "mjd" not in names and "date" in names:
        cols = {name: table.column(name, kind=kind, needed=tuple(SCHEDULE_COLUMNS))
                for name, kind in SCHEDULE_COLUMNS.items()}
        check_exptimes(table.label, cols["exptime"], what="schedule")
        return [Pointing(expid=i, mjd=float(cols["date"][i]), exptime=float(cols["exptime"][i]),
                         ra=float(cols["ra"][i]), dec=float(cols["dec"][i]), pa=float(cols["pa"][i]),
                         filter=str(cols["filter"][i]), sca=0) for i in range(len(table))]
    kinds = {"expid": "integer", "sca": "integer", "filter": "text"}
    cols = {name: table.column(name, kind=kinds.get(name, "number"), needed=tuple(POINTING_COLUMNS))
            for name in POINTING_COLUMNS}
    check_exptimes(table.label, cols["exptime"])
    return [Pointing(expid=int(cols["expid"][i]), mjd=float(cols["mjd"][i]), exptime=float(cols["exptime"][i]),
                     ra=float(cols["ra"][i]), dec=float(cols["dec"][i]), pa=float(cols["pa"][i]),
                     filter=str(cols["filter"][i]), sca=int(cols["sca"][i])) for i in range(len(table))]


def read_catalog_positions(path: str, *, stdin=None, columns=None) -> tuple:
    """The positions and kinds of a truth catalogue (``perscli catalog``): ra, dec, kind arrays and its DATASUM.

    ``columns`` maps perscli's names (ra, dec, kind) to another tool's (``--columns``).

    Raises
    ------
    PerscliError
        Unreadable, a column missing, or a position out of range.
    """
    needed = ("ra", "dec", "kind")
    table = read_table(path, what="truth catalogue (perscli catalog)", stdin=stdin, columns=columns or {},
                       known=needed)
    ra = table.column("ra", needed=needed).astype(np.float64)
    dec = table.column("dec", needed=needed).astype(np.float64)
    kind = np.char.lower(np.char.strip(table.column("kind", kind="text", needed=needed).astype(str)))
    check_positions(table.label, ra, dec)
    return ra, dec, kind, table.datasum


def _with_counts(chosen, catalog, sca, params, inputs, *, stdin=None, columns=None):
    """Count the catalogue's objects on each row's SCA: (counts, params, inputs) for the output."""
    if catalog is None:
        return None, params, inputs
    ra, dec, kind, datasum = read_catalog_positions(catalog, stdin=stdin, columns=columns)
    counts = count_on_sca(chosen, ra, dec, kind, sca=sca)
    covered = int(np.count_nonzero(counts["star"] + counts["galaxy"]))
    if chosen and not covered:
        log.warning("no object of %s lands on SCA %s in any of the %d rows: the catalogue lies elsewhere (draw one "
                    "where the SCA lands: perscli catalog --footprints POINTINGS.fits --sca N)", catalog,
                    sca or "of each row", len(chosen))
    elif chosen:
        log.info("%s: objects on the SCA in %d of %d rows (at most %d stars, %d galaxies in one)", catalog, covered,
                 len(chosen), int(counts["star"].max()), int(counts["galaxy"].max()))
    params = dict(params)
    params["PTNCAT"] = (len(ra), "objects in the catalogue counted")
    params["PTNSTAR"] = (int(counts["star"].sum()), "stars on the SCA, summed over rows")
    params["PTNGAL"] = (int(counts["galaxy"].sum()), "galaxies on the SCA, summed over rows")
    return counts, params, [*inputs, ("TRUTH", catalog, datasum)]


def select_covering_file(dest: str, schedule: str, ra: float, dec: float, radius: float, *,
                         filter: str | None = None, after: float | None = None, limit: int | None = None,
                         sca: int = 0, footprints: bool = False, catalog: str | None = None,
                         overwrite: bool = False, stdin=None, stdout=None, columns=None,
                         schedule_columns=None) -> list:
    """Check ``dest``, select from the schedule file (:func:`select_covering`) and write the pointings
    (with each row's SCA corners when ``footprints``, and how many objects of the truth catalogue
    ``catalog`` land on each row's SCA, :func:`count_on_sca`).  ``columns`` and ``schedule_columns``
    map perscli's column names to those of the catalogue and of the schedule (``--columns``,
    ``--schedule-columns``)."""
    from ..io.output import check_output

    check_output(dest, overwrite=overwrite, inputs=[schedule, catalog])
    if filter is not None:
        filter = check_filter(filter)
    sched = read_schedule(schedule, stdin=stdin, columns=schedule_columns)
    chosen = select_covering(sched, ra, dec, radius, filter=filter, after=after, limit=limit, sca=sca)
    params = {
        "PTMODE": ("schedule", "pointings: selected from a schedule"),
        "PTRA": (float(ra), "[deg] field centre, RA"),
        "PTDEC": (float(dec), "[deg] field centre, Dec"),
        "PTRADIUS": (float(radius), "[deg] pointing centres within this distance"),
        "PTFILTER": (filter or "any", "filter selected"),
        "PTLIMIT": (int(limit) if limit is not None else 0, "at most this many (0: no limit)"),
        "PTSCA": (int(sca), "detector written in every row (0: none)"),
        "PTCOVER": ("sca footprint" if sca else "boresight",
                    "kept: SCA footprint meets the field circle, or boresight in it"),
        "PTNSCHED": (len(sched), "exposures in the schedule"),
    }
    if after is not None:
        params["PTAFTER"] = (float(after), "[MJD] only exposures starting later")
    step = (f"pointings schedule ra={ra} dec={dec} radius={radius} filter={filter or 'any'} "
            f"{'sca=' + str(sca) + ' footprint' if sca else 'boresight'} selected={len(chosen)} of {len(sched)}")
    counts, params, inputs = _with_counts(chosen, catalog, sca, params, [("SCHED", schedule, sched.datasum)],
                                          columns=columns)
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params,
                    inputs=inputs, footprints=footprints, counts=counts)
    return chosen


def previous_exposures_file(dest: str, schedule: str, row: int, n: int, *, sca: int = 0, footprints: bool = False,
                            catalog: str | None = None, overwrite: bool = False, stdin=None, stdout=None,
                            columns=None, schedule_columns=None) -> list:
    """Check ``dest``, take the ``n`` exposures before ``row`` of the schedule file
    (:func:`previous_exposures`) and write them (with their SCA corners when ``footprints``, and the
    objects of ``catalog`` on each, as :func:`select_covering_file`)."""
    from ..io.output import check_output

    check_output(dest, overwrite=overwrite, inputs=[schedule, catalog])
    sched = read_schedule(schedule, stdin=stdin, columns=schedule_columns)
    chosen = previous_exposures(sched, row, n, sca=sca)
    params = {
        "PTMODE": ("before", "pointings: the exposures before a schedule row"),
        "PTBEFORE": (int(row), "schedule row whose earlier exposures these are"),
        "PTN": (int(n), "earlier exposures asked for"),
        "PTSCA": (int(sca), "detector written in every row (0: none)"),
        "PTNSCHED": (len(sched), "exposures in the schedule"),
    }
    step = f"pointings schedule before={row} n={n} found={len(chosen)}"
    counts, params, inputs = _with_counts(chosen, catalog, sca, params, [("SCHED", schedule, sched.datasum)],
                                          columns=columns)
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params,
                    inputs=inputs, footprints=footprints, counts=counts)
    return chosen


def plan_dithers_file(dest: str, ra: float, dec: float, n: int, *, dither: float = 10.0, filter: str = "J129",
                      start: float | None = None, exptime: float = WAS_EXPTIME, gap: float = WAS_GAP,
                      pa: float | None = None, sca: int = 0, seed: int = 1, footprints: bool = False,
                      catalog: str | None = None, overwrite: bool = False, stdout=None, columns=None) -> list:
    """Check ``dest``, plan a dithered sequence (:func:`plan_dithers`) and write it (with its SCA
    corners when ``footprints``, and the objects of ``catalog`` on each, as :func:`select_covering_file`).

    The header says how the start and the PA were chosen (PTSTFROM, PTPAFROM),
    with GalSim's best PA (PTBESTPA) and the Sun's angle (PTSUNANG) at the start.
    """
    from ..io.output import check_output

    check_output(dest, overwrite=overwrite, inputs=[catalog])
    chosen = plan_dithers(ra, dec, n, dither=dither, filter=filter, start=start, exptime=exptime, gap=gap,
                          pa=pa, sca=sca, seed=seed)
    first = chosen[0] if chosen else None
    first_mjd = first.mjd if first else (PLAN_REFERENCE_MJD if start is None else float(start))
    first_pa = first.pa if first else (0.0 if pa is None else float(pa) % 360.0)
    params = {
        "PTMODE": ("plan", "pointings: a planned dithered sequence"),
        "PTRA": (float(ra), "[deg] field centre, RA"),
        "PTDEC": (float(dec), "[deg] field centre, Dec"),
        "PTDITHER": (float(dither), "[arcsec] offsets uniform within +-this"),
        "PTFILTER": (check_filter(filter), "filter of every exposure"),
        "PTSTART": (float(first_mjd), "[MJD] start of the first exposure"),
        "PTSTFROM": ("given" if start is not None else f"first observable from MJD {PLAN_REFERENCE_MJD}",
                     "PTSTART: given, or searched in 1-day steps"),
        "PTEXPT": (float(exptime), "[s] exposure time"),
        "PTGAP": (float(gap), "[s] from the end of one exposure to the next"),
        "PTPA": (float(first_pa), "[deg] observatory position angle"),
        "PTPAFROM": ("given" if pa is not None else "galsim.roman.bestPA",
                     "PTPA: given, or best for exposure 0 at PTSTART"),
        "PTSCA": (int(sca), "detector written in every row (0: none)"),
    }
    if first is not None:
        best = best_pa(first.ra, first.dec, first.mjd)
        params["PTBESTPA"] = (float(best), "[deg] GalSim's best PA, exposure 0 at PTSTART")
        params["PTSUNANG"] = (round(sun_angle(first.ra, first.dec, first.mjd), 6),
                              "[deg] Sun to exposure 0 at PTSTART (54 to 126)")
    step = (f"pointings plan ra={ra} dec={dec} n={n} dither={dither} filter={check_filter(filter)} "
            f"start={first_mjd} pa={first_pa} seed={seed}")
    counts, params, inputs = _with_counts(chosen, catalog, sca, params, [], columns=columns)
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params, seed=seed,
                    footprints=footprints, counts=counts, inputs=inputs)
    return chosen
