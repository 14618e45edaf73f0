"""The settings of ``perscli correlate`` and ``perscli budget``, with their defaults written once.

:class:`CorrelateOptions` is the one home of correlate's analysis settings
(in the manner of TreeCorr's ``corr2_valid_params``): the library
(:func:`perscli.stats.correlate.correlate_files`) takes one, the command's
options show and use its defaults, and a study's ``correlate`` section
starts from them.  :class:`BudgetOptions` is budget's: the defaults of
:mod:`perscli.stats.budget`'s functions, of the command's options and of a
study's ``budget`` section.  This module imports nothing heavy, so that
``--help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from ..instrument import ROMAN_PIXEL_SCALE
from ..settings import setting

#: |De| thresholds of the paper's fractions
DEFAULT_THRESHOLDS = (1e-8, 1e-4)
#: |De| bin edges for the position-angle distribution (|g| <= 1, so |De| <= 2)
DEFAULT_THETA_EDGES = (1e-8, 1e-6, 1e-4, 1e-2, 2.0)


@dataclasses.dataclass(frozen=True)
class CorrelateOptions:
    """How ``perscli correlate`` reads shape changes and correlates them.

    Attributes
    ----------
    de_columns : (str, str) or None
        One table: the columns holding De1 and De2 (see
        :func:`~perscli.stats.shape_changes.load_shape_changes`).
    common_ids : bool
        Keep only the objects measured in both tables.
    positions : {'auto', 'radec', 'xy'}
        Which positions to correlate (auto: ra/dec when present).
    pixel_scale : float
        Arcsec per pixel for x/y positions in pixels (Roman's).
    columns : dict or None
        Column names (NAME=COL) of the tables.
    min_sep, max_sep : float
        The separation range, in ``sep_units``.
    nbins : int
        Logarithmic separation bins.
    sep_units : {'arcsec', 'arcmin', 'deg', 'rad'}
    bin_slop : float or None
        TreeCorr's bin_slop (None: its default).
    npatch : int
        Jackknife patches (k-means; 1: no jackknife).
    cross_patch_weight : {'match', 'simple', 'mean'}
        TreeCorr's weighting of pairs that cross patches.
    var_method : {'auto', 'jackknife', 'shot'}
        Covariance of xi: 'auto' falls back to shot noise, with a warning,
        when a jackknife is impossible.
    thresholds : tuple of float
        |De| thresholds of the fractions (:func:`~perscli.stats.de_stats.de_statistics`).
    theta_edges : tuple of float
        |De| bin edges of the position-angle distribution.
    nboot : int
        Bootstrap resamples of the position-angle test.
    seed : int
        Random seed (patches, bootstrap).
    flagged : {'drop', 'keep'}
        Objects whose fits carry a flag: left out (the command's default), or
        kept with their flags (a study's sample: every galaxy counts).
    within : (float, float, float) or None
        Only the objects within this circle: (ra, dec, radius), degrees (a
        study's field); None: all.
    """

    de_columns: tuple | None = None
    common_ids: bool = setting(False, "flag", "Correlate the ids A and B share, instead of refusing tables whose "
                                              "ids differ.")
    positions: str = setting("auto", "choice", "ra/dec in degrees (auto when present), or x/y (flat) in pixels or in "
                                               "their TUNIT angle.", choices=("auto", "radec", "xy"))
    pixel_scale: float = setting(ROMAN_PIXEL_SCALE, "float", "Arcsec per pixel for x/y positions in pixels (Roman's).",
                                 lo=0, lo_open=True, metavar="ARCSEC")
    columns: dict | None = None
    min_sep: float = setting(1.0, "float", "Smallest separation, in --sep-units.", lo=0, lo_open=True, metavar="SEP")
    max_sep: float = setting(100.0, "float", "Largest separation, in --sep-units.", lo=0, lo_open=True, metavar="SEP")
    nbins: int = setting(20, "int", "Logarithmic separation bins.", lo=1, metavar="N")
    sep_units: str = setting("arcmin", "choice", "Units of --min-sep, --max-sep and of the output separations.",
                             choices=("arcsec", "arcmin", "deg", "rad"))
    bin_slop: float | None = setting(None, "float", "TreeCorr's bin_slop [default: TreeCorr's, min(1, 0.1/bin size)]; "
                                                    "0 is exact but slow on large catalogues.",
                                     lo=0, metavar="X", show_default=False)
    npatch: int = setting(20, "int", "Jackknife patches, found by k-means on the positions (seeded by --seed).",
                          lo=2, metavar="N")
    cross_patch_weight: str = setting("match", "choice", "TreeCorr's weight of pairs across a removed and a kept patch "
                                                         "(match: Mohammad & Percival 2022, recommended for the "
                                                         "jackknife).", choices=("match", "simple", "mean"))
    var_method: str = setting("auto", "choice", "Errors of xi: the jackknife over patches, or shot noise; auto is the "
                                                "jackknife unless it is impossible (fewer than 10 objects per patch, "
                                                "fewer than 2 patches with objects), then shot noise with a warning; a "
                                                "bin whose jackknife variance is zero though it has pairs gets its shot "
                                                "noise (header SHOTBINS).", choices=("auto", "jackknife", "shot"))
    thresholds: tuple = setting(DEFAULT_THRESHOLDS, "numbers", "|De| thresholds: STATS gives the number and fraction "
                                                               "of objects at or above each.", metavar="T1,T2,...")
    theta_edges: tuple = setting(DEFAULT_THETA_EDGES, "numbers", "|De| bin edges of the position-angle distribution.",
                                 flag="--theta-bins", metavar="E0,E1,...")
    nboot: int = setting(200, "int", "Bootstrap resamples for the errors of the position-angle distribution.", lo=2,
                         metavar="N")
    seed: int = 1
    flagged: str = "drop"
    within: tuple | None = None


#: the additive shear budgets :mod:`perscli.stats.budget` knows (its ``BANDS`` holds their values)
BAND_NAMES = ("dore2018", "troxel2021", "hirata")


@dataclasses.dataclass(frozen=True)
class BudgetOptions:
    """How ``perscli budget`` draws the Roman additive shear budget and compares a measured xi+ with it.

    Attributes
    ----------
    bands : str
        The budget's rms per multipole band, one of :data:`BAND_NAMES`
        (dore2018: the HLIS requirement, Dore et al. 2018).
    modes : {'E', 'EB'}
        E: the budget is for E modes only; EB: B modes get the same budget.
    n_sigma : float
        A bin exceeds the budget when ``|xi+| - n_sigma sigma_xip > |budget|``.
    theta_min, theta_max : float
        Arcmin: the separations of the budget's table when no xi+ is given.
    nbins : int
        How many log-spaced separations that table has.
    """

    bands: str = setting("dore2018", "choice", "Additive shear rms per multipole band: dore2018 (HLIS requirement, "
                                               "Dore et al. 2018), troxel2021 (7.0e-5 in the first band) or hirata "
                                               "(Hirata's allocation).", choices=BAND_NAMES)
    modes: str = setting("E", "choice", "E: the budget is for E modes only; EB: B modes get the same budget, which "
                                        "doubles xi+.", choices=("E", "EB"), case_sensitive=False, metavar="E|EB")
    n_sigma: float = setting(2.0, "float", "A bin exceeds the budget when |xi+| - N sigma_xip > |budget|.",
                             flag="--sigma", lo=0, metavar="N")
    theta_min: float = 0.1
    theta_max: float = 300.0
    nbins: int = 50
