"""Planned dithered sequences: N exposures on a field that Roman can take.

:func:`plan_dithers`: N exposures of ``exptime`` seconds, each starting
``gap`` seconds after the previous one ends (defaults 139.8 s and 30 s, the
survey's cadence, :data:`WAS_EXPTIME`, :data:`WAS_GAP`), pointed at the
field centre offset by a random amount uniform in [-dither, +dither] arcsec
along east and north on the tangent plane, all at the same PA.  Every
exposure of a plan is one Roman can take (GalSim's Sun-angle limits,
:func:`perscli.scene.observability.observable`): without a start, the plan
starts at the first observable date on or after :data:`PLAN_REFERENCE_MJD`
(the first exposure of the public survey schedule), searched in steps of one
day (:func:`perscli.scene.observability.first_observable_start`); without a
PA, at GalSim's best PA (:func:`perscli.scene.observability.best_pa`) at
that start.  A start given is checked, and refused with the first observable
date after it.
"""

from __future__ import annotations

import math

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_EXPTIME, ROMAN_WAS_GAP
from . import check_filter, check_mjd, check_pa, deproject, mjd_datetime
from .observability import (OBSERVABLE_SEARCH_DAYS, _first_unobservable, _never_observable, _when, best_pa,
                            first_observable_start, sun_angle, sun_limits)
from .schedule import DAY, Pointing, _check_centre, _check_sca
from .settings import PLAN_REFERENCE_MJD, PlanOptions

#: Roman Wide Area Survey cadence (the public WAS schedule, Roman_WAS_obseq_11_1_23.fits): exposure time and gap between exposures, s
WAS_EXPTIME = ROMAN_EXPTIME
WAS_GAP = ROMAN_WAS_GAP


#: the defaults of a plan, written once (perscli.scene.settings)
_D = PlanOptions()


def plan_dithers(ra: float, dec: float, n: int, *, dither: float = _D.dither, filter: str = _D.filter,
                 start: float | None = _D.start, exptime: float = _D.exptime, gap: float = _D.gap,
                 pa: float | None = _D.pa, sca: int = _D.sca, seed: int = _D.seed,
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
