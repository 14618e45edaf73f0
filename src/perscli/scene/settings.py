"""The settings of ``perscli pointings`` and ``perscli catalog``, with their defaults written once.

:class:`PlanOptions` (``perscli pointings plan``) and :class:`SelectOptions`
(``perscli pointings select``) are the one home of the pointings commands'
settings, in the manner of :class:`perscli.stats.settings.CorrelateOptions`:
the library (:func:`perscli.scene.pointings.plan_dithers_file`,
:func:`perscli.scene.pointings.select_covering_file`, and the defaults of
:func:`perscli.scene.dithers.plan_dithers`) takes one, and the command's
options show and use its defaults.  What each row of the table carries
besides its exposure (the detector, its corners, the catalogue's columns) is
common to both: :class:`RowOptions`.  :class:`CatalogOptions` holds the
defaults of a truth catalogue (``perscli catalog``,
:func:`perscli.scene.catalog.make_truth_catalog` and a study's ``catalog``
section).

This module, and its package's ``__init__``, import nothing heavy: it is read
when the command line is built, and ``--help`` must stay fast.
"""

from __future__ import annotations

import dataclasses

from ..instrument import ROMAN_EXPTIME, ROMAN_N_SCA, ROMAN_WAS_GAP
from ..settings import setting

#: [MJD] where a plan without a start looks for its first observable date: the start of the first exposure
#: of the public Roman Wide Area Survey schedule (Roman_WAS_obseq_11_1_23.fits), 2027-05-16 23:20:18 UTC.
#: A fixed date, not today's, so that the same inputs give the same plan
PLAN_REFERENCE_MJD = 61541.972429


@dataclasses.dataclass(frozen=True, kw_only=True)
class RowOptions:
    """What each row of a pointings table carries besides its exposure.

    Attributes
    ----------
    sca : int
        Roman detector (SCA 1-18) written into every row; 0: none chosen.
        A selection from a schedule with an SCA keeps the exposures whose
        SCA footprint overlaps the field circle.
    footprints : bool
        Add each row's SCA corners on the sky (columns corner_ra,
        corner_dec); needs ``sca``.
    columns : dict or None
        Column names (NAME=COL) of the truth catalogue whose objects are
        counted on each row's SCA, when they differ from perscli's.
    """

    sca: int = setting(0, "int", "The detector written into every row (0: none chosen).", lo=0, hi=ROMAN_N_SCA,
                       metavar="N")
    footprints: bool = False
    columns: dict | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class SelectOptions(RowOptions):
    """How ``perscli pointings select`` picks the exposures of a field from a schedule.

    Attributes
    ----------
    filter : str or None
        Only the exposures in this Roman filter (any case); None: any.
    after : float or None
        Only the exposures that start after this MJD.
    limit : int or None
        At most this many exposures, the earliest; None: all.
    schedule_columns : dict or None
        Column names (NAME=COL) of the schedule, when they differ from
        perscli's (date, exptime, ra, dec, pa, filter).
    sca, footprints, columns
        See :class:`RowOptions`.
    """

    filter: str | None = None
    after: float | None = None
    limit: int | None = None
    schedule_columns: dict | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlanOptions(RowOptions):
    """How ``perscli pointings plan`` lays out a dithered sequence.

    Attributes
    ----------
    dither : float
        Arcsec: offsets uniform within +-dither east and north of the field
        centre, independently per exposure.
    filter : str
        Roman filter of every exposure.
    start : float or None
        MJD at which the first exposure starts; None: the first date from
        :data:`perscli.scene.settings.PLAN_REFERENCE_MJD`, in steps of one
        day, at which Roman can take every exposure.
    exptime : float
        Seconds each exposure lasts (the Roman Wide Area Survey's).
    gap : float
        Seconds from the end of one exposure to the start of the next (the
        survey's).
    pa : float or None
        Observatory position angle of every exposure, degrees (GalSim's
        convention); None: GalSim's best PA for the first exposure at its
        start.
    seed : int
        Random seed of the offsets.
    sca, footprints, columns
        See :class:`RowOptions`.
    """

    dither: float = setting(10.0, "float", "A plan's offsets, arcsec.", lo=0, hi=3600, metavar="ARCSEC")
    filter: str = "J129"
    start: float | None = None
    exptime: float = setting(ROMAN_EXPTIME, "float", "A plan's exposure time.", lo=0, lo_open=True,
                             metavar="SECONDS")
    gap: float = setting(ROMAN_WAS_GAP, "float", "From the end of one exposure of a plan to the start of the next.",
                         lo=0, metavar="SECONDS")
    pa: float | None = None
    seed: int = 1


@dataclasses.dataclass(frozen=True)
class CatalogOptions:
    """The defaults of a truth catalogue's field and galaxies.

    Attributes
    ----------
    size : float
        Arcmin: the side of a square field.
    margin_arcsec : float
        Arcsec: how much each detector footprint is grown, the half-width of
        the stamp of a J = 14 star (28") and of the largest galaxy (14"), so
        that every object whose light render would draw on a detector at a
        level that matters is in the catalogue.
    galaxy_density : float
        Galaxies per arcmin^2 (Poisson): the paper's.
    """

    size: float = 10.0
    margin_arcsec: float = 30.0
    galaxy_density: float = setting(40.0, "float", "Mean number of galaxies per arcmin^2 (Poisson).", lo=0,
                                    metavar="PER_ARCMIN2")
