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

The code lives in one module per job:
:mod:`perscli.scene.schedule` (schedules, :class:`Pointing`),
:mod:`perscli.scene.observability`, :mod:`perscli.scene.footprints`
(detectors on the sky) and :mod:`perscli.scene.dithers` (planned sequences);
this module holds the pointings table and the commands that write it.
"""

from __future__ import annotations

import logging

import numpy as np

from .. import PerscliError
from ..instrument import ROMAN_SCA_SIZE
from ..io.cards import format_card
from ..io.fitsfile import OutHDU, table_hdu
from ..io.output import add_provenance, check_output, write_hdus
from ..io.tables import read_table
from . import check_filter, check_positions

from .dithers import plan_dithers
from .footprints import count_on_sca, sca_footprint
from .observability import best_pa, sun_angle
from .schedule import (SCHEDULE_COLUMNS, Pointing, _check_sca, check_exptimes, previous_exposures, read_schedule,
                       select_covering)
from .settings import PLAN_REFERENCE_MJD, PlanOptions, SelectOptions

log = logging.getLogger(__name__)

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
    "corner_ra": ("4D", "deg", "SCA corners (pixel edges) (0.5,0.5) ({e},0.5) ({e},{e}) (0.5,{e}): RA".format(
        e=ROMAN_SCA_SIZE + 0.5)),
    "corner_dec": ("4D", "deg", "SCA corners, same order: Dec"),
}

#: the optional columns of :func:`pointings_hdulist` with ``counts``: catalogue objects on each row's SCA
COUNT_COLUMNS = {
    "n_star": ("K", None, "catalogue stars whose centre lands on the SCA"),
    "n_galaxy": ("K", None, "catalogue galaxies whose centre lands on the SCA"),
}


def pointings_hdulist(pointings, *, step: str, params: dict | None = None, inputs=(), seed: int | None = None,
                      footprints: bool = False, counts: dict | None = None):
    """The FITS file of ``pointings``: an empty primary HDU and the 'POINTINGS' table with provenance.

    ``step``, ``params``, ``inputs`` and ``seed`` are those of
    :func:`perscli.io.output.add_provenance`.  With ``footprints`` the table
    also has the columns of :data:`FOOTPRINT_COLUMNS`: each row's SCA
    corners (:func:`sca_footprint` of its ``sca``, which must be 1-18);
    with ``counts`` (:func:`count_on_sca`) those of :data:`COUNT_COLUMNS`.
    """
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
                    "where the SCA lands: perscli catalog --pointings POINTINGS.fits --sca N)", catalog,
                    sca or "of each row", len(chosen))
    elif chosen:
        log.info("%s: objects on the SCA in %d of %d rows (at most %d stars, %d galaxies in one)", catalog, covered,
                 len(chosen), int(counts["star"].max()), int(counts["galaxy"].max()))
    params = dict(params)
    params["PTNCAT"] = (len(ra), "objects in the catalogue counted")
    params["PTNSTAR"] = (int(counts["star"].sum()), "stars on the SCA, summed over rows")
    params["PTNGAL"] = (int(counts["galaxy"].sum()), "galaxies on the SCA, summed over rows")
    return counts, params, [*inputs, ("TRUTH", catalog, datasum)]


def select_covering_file(dest: str, schedule: str, ra: float, dec: float, radius: float,
                         options: SelectOptions | None = None, *, catalog: str | None = None,
                         overwrite: bool = False, stdin=None, stdout=None, progress=None) -> list:
    """``perscli pointings select`` as a function: the exposures of a schedule file that look at a field.

    Checks ``dest``, selects from the schedule (:func:`select_covering`) and
    writes the pointings (:func:`write_pointings`), with each row's SCA
    corners when ``options.footprints``, and how many objects of the truth
    catalogue ``catalog`` land on each row's SCA (:func:`count_on_sca`).

    Parameters
    ----------
    dest : str
        Output path, '-' for standard output.
    schedule : str
        The schedule file ('-': ``stdin``).
    ra, dec, radius : float
        The field: the circle of ``radius`` degrees about (ra, dec).
    options : SelectOptions, optional
        The settings (:class:`~perscli.scene.settings.SelectOptions`, where
        their defaults are written): filter, after, limit, the SCA, its
        footprints, the column names of the catalogue and of the schedule.
    catalog : str, optional
        A truth catalogue whose objects are counted on each row's SCA.
    overwrite, stdin, stdout
        Replace an existing output; the streams read and written for '-'.
    progress : callable, optional
        ``progress(done, total, name)`` over the exposures whose SCA footprint is computed (with an SCA).

    Returns
    -------
    list of Pointing
        The exposures selected, in time order.
    """
    o = options if options is not None else SelectOptions()
    filter, after, limit, sca = o.filter, o.after, o.limit, o.sca
    check_output(dest, overwrite=overwrite, inputs=[schedule, catalog])
    if filter is not None:
        filter = check_filter(filter)
    sched = read_schedule(schedule, stdin=stdin, columns=o.schedule_columns)
    chosen = select_covering(sched, ra, dec, radius, filter=filter, after=after, limit=limit, sca=sca,
                             progress=progress)
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
                                          columns=o.columns)
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params,
                    inputs=inputs, footprints=o.footprints, counts=counts)
    return chosen


def previous_exposures_file(dest: str, schedule: str, row: int, n: int, *, sca: int = 0, footprints: bool = False,
                            catalog: str | None = None, overwrite: bool = False, stdin=None, stdout=None,
                            columns=None, schedule_columns=None) -> list:
    """Check ``dest``, take the ``n`` exposures before ``row`` of the schedule file
    (:func:`previous_exposures`) and write them (with their SCA corners when ``footprints``, and the
    objects of ``catalog`` on each, as :func:`select_covering_file`)."""
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


def plan_dithers_file(dest: str, ra: float, dec: float, n: int, options: PlanOptions | None = None, *,
                      catalog: str | None = None, overwrite: bool = False, stdout=None) -> list:
    """``perscli pointings plan`` as a function: plan a dithered sequence and write it.

    Checks ``dest``, plans the sequence (:func:`plan_dithers`) and writes it
    (:func:`write_pointings`), with its SCA corners when
    ``options.footprints``, and the objects of ``catalog`` on each row's SCA,
    as :func:`select_covering_file`.  The header says how the start and the
    PA were chosen (PTSTFROM, PTPAFROM), with GalSim's best PA (PTBESTPA)
    and the Sun's angle (PTSUNANG) at the start.

    Parameters
    ----------
    dest : str
        Output path, '-' for standard output.
    ra, dec : float
        Field centre, degrees.
    n : int
        Number of exposures.
    options : PlanOptions, optional
        The settings (:class:`~perscli.scene.settings.PlanOptions`, where
        their defaults are written): dither, filter, start, exposure time,
        gap, PA, seed, the SCA, its footprints, the catalogue's column names.
    catalog : str, optional
        A truth catalogue whose objects are counted on each row's SCA.
    overwrite, stdout
        Replace an existing output; the stream written for '-'.

    Returns
    -------
    list of Pointing
        The plan, ``expid`` 0 to n-1.
    """
    o = options if options is not None else PlanOptions()
    dither, filter, start, exptime, gap, pa, sca, seed = (o.dither, o.filter, o.start, o.exptime, o.gap, o.pa,
                                                          o.sca, o.seed)
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
    counts, params, inputs = _with_counts(chosen, catalog, sca, params, [], columns=o.columns)
    write_pointings(chosen, dest, overwrite=overwrite, stdout=stdout, step=step, params=params, seed=seed,
                    footprints=o.footprints, counts=counts, inputs=inputs)
    return chosen
