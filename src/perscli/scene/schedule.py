"""Survey schedules: the exposures of a real schedule that look at a field, or that precede one.

A schedule (:func:`read_schedule`) is a FITS binary table with columns
``date`` (start, MJD), ``exptime`` (s), ``ra``, ``dec``, ``pa`` (degrees) and
``filter``, such as the public Roman Wide Area Survey sequence
``Roman_WAS_obseq_11_1_23.fits`` (16,956 exposures of 139.8 s that start
~169.8 s apart).

- :func:`select_covering`: the exposures whose pointing centre lies within
  a radius of the field centre (great-circle distance), in time order, each
  with its row number as ``expid``; with ``sca=N``, those whose SCA N
  footprint (:func:`perscli.scene.footprints.sca_footprint`) overlaps the
  field circle: the SCAs lie up to :data:`FPA_REACH_DEG` from the boresight;
- :func:`previous_exposures`: the exposures of a schedule that start before
  a given row, whatever their filter and pointing: on the same detector they
  are what leaves persistence in it.

Also :class:`Pointing` (one exposure) and :class:`Schedule` (a schedule as
columns).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..io.tables import read_table
from . import check_filter, check_position, separation
from .footprints import sca_footprint
from .regions import polygon_meets_circle

DAY = 86400.0

#: farthest any SCA corner lies from the boresight (the centre of the focal plane), degrees: GalSim's
#: Roman focal plane reaches 0.450 deg; 0.5 bounds it for the pre-selection of :func:`select_covering`
FPA_REACH_DEG = 0.5

#: the schedule's columns and what they must hold
SCHEDULE_COLUMNS = {"date": "number", "exptime": "number", "ra": "number", "dec": "number", "pa": "number",
                    "filter": "text"}

#: the name that stands for the schedule shipped with perscli (wherever a schedule file is asked for)
BUNDLED_SCHEDULE = "roman-was"
#: the bundled file: the public Roman Wide Area Survey observing sequence Roman_WAS_obseq_11_1_23.fits
#: (version of 2023-11-01: 16,956 exposures), gzipped, unchanged
BUNDLED_SCHEDULE_FILE = "Roman_WAS_obseq_11_1_23.fits.gz"


def schedule_path(name: str) -> str:
    """The file a schedule name stands for: :data:`BUNDLED_SCHEDULE` is the bundled one, anything else a path."""
    if name != BUNDLED_SCHEDULE:
        return name

    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", BUNDLED_SCHEDULE_FILE)


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
        FITS file (gzipped or not), '-' for standard input, or
        :data:`BUNDLED_SCHEDULE` for the public Roman WAS schedule shipped
        with perscli.
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
    path = schedule_path(path)
    table = read_table(path, what="schedule", stdin=stdin, columns=columns or {}, known=tuple(SCHEDULE_COLUMNS),
                       option="--schedule-columns")
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
                    after: float | None = None, limit: int | None = None, sca: int = 0, progress=None) -> list:
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
    progress : callable, optional
        ``progress(done, total, name)`` after each exposure whose SCA
        footprint is computed (GalSim's WCS: ~15 ms each, thousands for a
        wide field).

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

    chosen = []
    for k, i in enumerate(rows):
        if limit is not None and len(chosen) >= limit:
            break
        p = schedule_pointing(schedule, i, sca=sca)
        if polygon_meets_circle(*sca_footprint(p, sca), ra, dec, radius):
            chosen.append(p)
        if progress is not None:
            progress(k + 1, len(rows), f"{len(chosen)} on the field")
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
    check_sequence(schedule, [*picked.tolist(), row])
    return [schedule_pointing(schedule, i, sca=sca) for i in picked]


#: seconds by which one exposure may seem to run into the next: the rounding of an MJD (1e-11 day ~ 1 us)
OVERLAP_TOLERANCE = 1e-3


def check_sequence(schedule: Schedule, rows) -> None:
    """Refuse exposures of one detector whose times overlap: each must end before the next starts.

    Parameters
    ----------
    schedule : Schedule
    rows : sequence of int
        Schedule rows in time order (an exposure's history, then the exposure).

    Raises
    ------
    PerscliError
        One line naming the two rows, by how much they overlap, and the fix.
    """
    for a, b in zip(rows[:-1], rows[1:]):
        end = schedule.mjd[a] + schedule.exptime[a] / DAY
        overlap = (end - schedule.mjd[b]) * DAY
        if overlap > OVERLAP_TOLERANCE:
            where = f"{schedule.name}: " if schedule.name else ""
            raise PerscliError(f"{where}rows {a} and {b} overlap in time: row {a} (MJD {schedule.mjd[a]:.6f}, "
                               f"{schedule.exptime[a]:g} s) ends {overlap:.1f} s after row {b} starts; one "
                               "detector takes one exposure at a time: fix the dates or exposure times of the "
                               "schedule")
