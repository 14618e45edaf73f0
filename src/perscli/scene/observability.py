"""Observability: when Roman can point at a position, and at what roll.

GalSim's Roman module, ``galsim.roman.allowedPos`` and ``bestPA``: Roman
looks at positions 54 to 126 degrees from the Sun (90 +-
``galsim.roman.max_sun_angle``, :func:`sun_limits`, :func:`sun_angle`,
:func:`observable`); GalSim does not limit the roll about the boresight
(``getWCS`` takes any PA), and neither does perscli: the public schedule's
PAs lie far from ``bestPA`` (:func:`best_pa`, another convention), so a roll
limit would refuse the real survey.

:func:`first_observable_start` finds the first start at which Roman can take
every exposure of a sequence (planned sequences,
:func:`perscli.scene.dithers.plan_dithers`); :func:`unobservable_message`
says in one line why a position cannot be observed and when it can.
"""

from __future__ import annotations

import math

import coord
import galsim
import galsim.roman as roman
import numpy as np

from . import check_mjd, check_position, mjd_datetime

#: [days] how far after its earliest date a start is searched for (every position is observable at some
#: time of a year), and in what steps
OBSERVABLE_SEARCH_DAYS = 366
OBSERVABLE_SEARCH_STEP = 1.0


def _date(mjd: float):
    return mjd_datetime(mjd)


def _when(mjd: float) -> str:
    return f"MJD {mjd:.5f} ({mjd_datetime(mjd):%Y-%m-%d %H:%M} UTC)"


def sun_limits() -> tuple:
    """GalSim's limits on the angle between a Roman pointing and the Sun, degrees: (54, 126)."""
    return 90.0 - roman.max_sun_angle, 90.0 + roman.max_sun_angle


def sun_angle(ra: float, dec: float, mjd: float) -> float:
    """Degrees between (ra, dec) and the Sun at ``mjd``, computed as ``galsim.roman.allowedPos`` does."""
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
    ra, dec = check_position(ra, dec, "pointing")
    mjd = check_mjd(mjd)
    return bool(roman.allowedPos(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees),
                                 mjd_datetime(mjd)))


def best_pa(ra: float, dec: float, mjd: float) -> float | None:
    """GalSim's best observatory position angle at (ra, dec) on ``mjd``, degrees in [0, 360).

    ``galsim.roman.bestPA``: the solar panels face the Sun as directly as
    possible.  None when Roman cannot point there then.
    """
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
