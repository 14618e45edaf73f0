"""The Roman additive shear budget as xi+(theta), and how a measured xi+ compares with it.

The High Latitude Imaging Survey requirement (Dore et al. 2018) limits the
additive shear systematics, per shear component, to an rms ``A_a`` in each of
four multipole bands, l = 31-99, 100-315, 316-999 and 1000-3161::

    dore2018    7.5e-5   9.9e-5   1.4e-4   1.9e-4   (RSS 2.7e-4)
    troxel2021  7.0e-5   9.9e-5   1.4e-4   1.9e-4   (Troxel et al. 2021)
    hirata      6.791e-5 9.697e-5 1.360e-4 1.855e-4 (Hirata's allocation)

Inside band ``a`` the budget's power spectrum is the template
``C_l = A_a^2 * 4 pi / (l (l+1)) / N_a`` with ``N_a = sum_band (2l+1) / (l (l+1))``,
zero outside the bands, so that ``sum_band (2l+1) / (4 pi) C_l = A_a^2``: each
band contributes its allowed variance.  The budget as a correlation function is
the direct sum over integer l (exact for a band-limited spectrum)::

    xi+(theta) = sum_l (2l+1) / (4 pi) C_l J0(l theta)

With the Dore numbers (E mode only) xi+ = 6.81e-8 at 1', 1.87e-8 at 10' and
8.4e-10 at 100'.  ``modes='EB'`` gives the B modes the same budget, which
doubles xi+.  The budget changes sign beyond ~170' (its spectrum is band
limited, so xi+ oscillates).

A measured xi+ (a ``perscli correlate`` table, TreeCorr's GG columns) is
compared bin by bin (:func:`compare`): ratio = xi+ / budget, its error
sigma_xip / |budget|, and a bin *exceeds* the budget when
``|xi+| - n_sigma * sigma_xip > |budget|``.  Magnitudes are compared because
the budget bounds the size of the systematic, whatever its sign, and the
budget itself is negative at large separations.  The verdict names the bin:
where the measurement exceeds, the bin furthest over its budget (its
separation, xi+, the budget, sigma and the ratio) and the separations of any
other bins that exceed; otherwise the bin closest to the budget.  When the
table's errors are shot noise (VAR_METH = 'shot': too few objects for a
jackknife), the verdict says so.
"""

from __future__ import annotations

import io
import math
import os
import textwrap
from dataclasses import dataclass, field

import numpy as np
from scipy.special import j0

from .. import PerscliError
from ..io.fitsfile import OutHDU, table_hdu
from ..io.output import add_provenance, atomic_output, check_output, write_hdus
from ..io.tables import read_table
from .settings import BudgetOptions

#: multipole bands of the HLIS requirement, inclusive
L_BANDS = ((31, 99), (100, 315), (316, 999), (1000, 3161))
LMAX = L_BANDS[-1][1]

#: additive shear rms per component in each of :data:`L_BANDS`, one entry for each of
#: :data:`perscli.stats.settings.BAND_NAMES` (the names the command line offers without importing this module)
BANDS = {
    "dore2018": (7.5e-5, 9.9e-5, 1.4e-4, 1.9e-4),
    "troxel2021": (7.0e-5, 9.9e-5, 1.4e-4, 1.9e-4),
    "hirata": (6.791e-5, 9.697e-5, 1.360e-4, 1.855e-4),
}

#: where each set of :data:`BANDS` comes from
BAND_SOURCES = {
    "dore2018": "Dore et al. 2018, WFIRST HLIS requirement",
    "troxel2021": "Troxel et al. 2021 (first band 7.0e-5, the rest as Dore et al. 2018)",
    "hirata": "Hirata's allocation of the HLIS additive budget",
}

#: how many of E and B share the budget: xi+ is multiplied by this
MODES = {"E": 1, "EB": 2}

#: separation units -> radians; the names TreeCorr's sep_units accepts, and common spellings
SEP_UNITS = {
    "arcmin": math.pi / 180 / 60, "arcmins": math.pi / 180 / 60, "arcminutes": math.pi / 180 / 60,
    "arcsec": math.pi / 180 / 3600, "arcsecs": math.pi / 180 / 3600, "arcseconds": math.pi / 180 / 3600,
    "deg": math.pi / 180, "degree": math.pi / 180, "degrees": math.pi / 180,
    "rad": 1.0, "radian": 1.0, "radians": 1.0,
}

#: the default separations when no measured xi+ is given: arcmin, log-spaced
DEFAULT_GRID = (BudgetOptions.theta_min, BudgetOptions.theta_max, BudgetOptions.nbins)

#: columns of a correlate (TreeCorr GG) table that the comparison reads
XI_COLUMNS = ("meanr or r_nom", "xip", "sigma_xip")


def amplitudes(bands=BudgetOptions.bands) -> tuple:
    """The additive shear rms per component in each multipole band.

    Parameters
    ----------
    bands : str or sequence of 4 floats
        A name of :data:`BANDS`, or the four amplitudes themselves (zero
        switches a band off).

    Returns
    -------
    tuple of float
        One amplitude per band of :data:`L_BANDS`.

    Raises
    ------
    PerscliError
        Unknown name, or not four finite non-negative amplitudes.
    """
    if isinstance(bands, str):
        try:
            return BANDS[bands.lower()]
        except KeyError:
            raise PerscliError(f"unknown budget bands '{bands}': use one of {', '.join(BANDS)}") from None
    values = tuple(float(a) for a in bands)
    if len(values) != len(L_BANDS) or not all(math.isfinite(a) and a >= 0 for a in values):
        raise PerscliError(f"budget bands must be {len(L_BANDS)} finite amplitudes >= 0, got {values}")
    return values


def _modes_factor(modes: str) -> int:
    try:
        return MODES[modes.upper()]
    except (KeyError, AttributeError):
        raise PerscliError(f"unknown modes '{modes}': use E (E modes only) or EB (E and B modes)") from None


def power_spectrum(bands=BudgetOptions.bands) -> tuple:
    """The budget's angular power spectrum C_l (E mode), l = 0 ... :data:`LMAX`.

    Parameters
    ----------
    bands : str or sequence of 4 floats
        See :func:`amplitudes`.

    Returns
    -------
    ell : ndarray of int
        0 ... LMAX.
    cl : ndarray
        ``A_a^2 * 4 pi / (l (l+1)) / N_a`` inside band a, zero outside; so that
        ``sum_band (2l+1) / (4 pi) C_l = A_a^2``.
    """
    amps = amplitudes(bands)
    ell = np.arange(LMAX + 1)
    cl = np.zeros(LMAX + 1)
    for (lo, hi), amp in zip(L_BANDS, amps):
        band = ell[lo:hi + 1].astype(float)
        # a flat l(l+1) C_l inside the band, normalised so that the band carries variance A_a^2
        norm = np.sum((2 * band + 1) / (band * (band + 1)))
        cl[lo:hi + 1] = amp ** 2 * 4 * math.pi / (band * (band + 1)) / norm
    return ell, cl


def xi_plus(theta, bands=BudgetOptions.bands, modes: str = BudgetOptions.modes) -> np.ndarray:
    """The budget as xi+(theta): ``sum_l (2l+1) / (4 pi) C_l J0(l theta)``.

    Parameters
    ----------
    theta : float or array_like
        Separations in radians.
    bands : str or sequence of 4 floats
        See :func:`amplitudes`.
    modes : {'E', 'EB'}
        'EB' gives the B modes the same budget as the E modes, doubling xi+.

    Returns
    -------
    ndarray
        xi+ at each theta (same shape as ``theta``).
    """
    factor = _modes_factor(modes)
    ell, cl = power_spectrum(bands)
    keep = cl > 0
    ell, weight = ell[keep].astype(float), ((2 * ell + 1) / (4 * math.pi) * cl)[keep]
    theta = np.asarray(theta, dtype=float)
    flat = theta.ravel()
    out = np.empty(flat.shape)
    # rows of at most 1024 separations keep the (theta, l) matrix near 25 MB
    for start in range(0, flat.size, 1024):
        chunk = flat[start:start + 1024]
        out[start:start + 1024] = j0(np.outer(chunk, ell)) @ weight
    return factor * out.reshape(theta.shape)


def default_theta(grid=DEFAULT_GRID) -> np.ndarray:
    """Log-spaced separations (arcmin) for a budget without a measurement: ``(min, max, n)``."""
    lo, hi, n = grid
    if not (0 < lo < hi and math.isfinite(hi)) or int(n) < 1:
        raise PerscliError(f"separation grid {lo:g} to {hi:g} arcmin in {n} steps: need 0 < min < max and n >= 1")
    return np.geomspace(lo, hi, int(n)) if int(n) > 1 else np.array([float(lo)])


def sep_unit_radians(unit: str) -> float:
    """Radians per separation unit (a name of :data:`SEP_UNITS`, any case)."""
    try:
        return SEP_UNITS[str(unit).strip().lower()]
    except KeyError:
        raise PerscliError(f"unknown separation unit '{unit}': use arcmin, arcsec, deg or rad") from None


# -- a measured xi+ -----------------------------------------------------------------------------

@dataclass
class XiTable:
    """The xi+ of a correlate table, as the comparison needs it.

    Attributes
    ----------
    label : str
        File name for messages ('stdin' for '-').
    name : str
        The path as given.
    theta : ndarray
        Separation of each bin (meanr where finite, else r_nom), in ``unit``.
    unit : str
        Separation unit: arcmin, arcsec, deg or rad.
    xip, sigma_xip : ndarray
        xi+ and its error; NaN allowed only in empty bins.
    empty : ndarray of bool
        Bins without pairs (weight or npairs 0): not compared.
    datasum : int
        DATASUM of the table as read (provenance).
    var_method : str
        What sigma_xip is, from the header's VAR_METH ('jackknife', 'shot'),
        '' when the table does not say.
    shot_bins : tuple of int
        Rows whose error is shot noise inside a jackknife (header SHOTBINS:
        too few pairs there for the jackknife).
    """

    label: str
    name: str
    theta: np.ndarray
    unit: str
    xip: np.ndarray
    sigma_xip: np.ndarray
    empty: np.ndarray
    datasum: int = 0
    var_method: str = ""
    shot_bins: tuple = ()
    #: the width of the jackknife's patches (header PATCHSIZ, in ``unit``; NaN when not given)
    patch_size: float = float("nan")


#: what read_xi reads (for --columns)
XI_READS = ("meanr", "r_nom", "xip", "sigma_xip", "weight", "npairs")


def read_xi(path: str, *, stdin=None, columns=None) -> XiTable:
    """Read xi+ from a ``perscli correlate`` output (TreeCorr GG column names).

    The first binary table (EXTNAME 'XI') is read: the separation from meanr
    where it is finite and positive, else r_nom, in the unit of the header's
    SEP_UNIT (or TreeCorr's SEP_UNITS, or the column's TUNIT; arcmin when none
    is given); xip and sigma_xip.  Bins with weight (or npairs) 0 hold no
    pairs and are marked empty: they may hold NaN and are not compared.

    Parameters
    ----------
    path : str
        The table ('-' for standard input).
    stdin : binary file, optional
        Stream read for '-'.
    columns : dict, optional
        Column mapping {perscli name: table column} for a table written by
        another tool; the names are those of :data:`XI_READS`.

    Raises
    ------
    PerscliError
        Unreadable file, a column missing or of the wrong type, no rows, an
        unknown separation unit, or a NaN, infinite or negative value where a
        bin has pairs.
    """
    what = "correlation table (perscli correlate output)"
    table = read_table(path, what=what, stdin=stdin, columns=columns or {}, known=XI_READS)
    where = f"{table.label}: HDU {table.index}"
    names = {n.lower() for n in table.names}
    if len(table) == 0:
        raise PerscliError(f"{where} has no rows: the correlation has no separation bins")
    if "meanr" not in names and "r_nom" not in names:
        raise PerscliError(f"{where} has no column 'meanr' or 'r_nom'; a {what} needs the columns "
                           f"{', '.join(XI_COLUMNS)}: check that this is a {what}, or name its columns with "
                           "--columns meanr=COLUMN,xip=COLUMN,sigma_xip=COLUMN")
    xip = table.column("xip", needed=XI_COLUMNS).astype(float)
    sigma = table.column("sigma_xip", needed=XI_COLUMNS).astype(float)
    nominal = table.column("r_nom").astype(float) if "r_nom" in names else None
    theta = table.column("meanr").astype(float) if "meanr" in names else nominal.copy()
    if nominal is not None:
        # TreeCorr leaves meanr undefined (or at r_nom) in a bin without pairs
        bad = ~(np.isfinite(theta) & (theta > 0))
        theta[bad] = nominal[bad]
    if "weight" in names:
        empty = table.column("weight").astype(float) == 0
    elif "npairs" in names:
        empty = table.column("npairs").astype(float) == 0
    else:
        empty = np.zeros(len(table), bool)

    unit = _xi_unit(table, "meanr" if "meanr" in names else "r_nom")
    for k in range(len(table)):
        if not (np.isfinite(theta[k]) and theta[k] > 0):
            raise PerscliError(f"{where}: bin {k} has separation {theta[k]} {unit}; separations must be finite "
                               "and positive: check the meanr and r_nom columns")
        if empty[k]:
            continue
        for col, values in (("xip", xip), ("sigma_xip", sigma)):
            if not np.isfinite(values[k]):
                raise PerscliError(f"{where}: column '{col}' is {values[k]} in bin {k} (theta = {theta[k]:.4g} "
                                   f"{unit}), which has pairs: recompute the correlation")
        if sigma[k] < 0:
            raise PerscliError(f"{where}: column 'sigma_xip' is negative ({sigma[k]:.3g}) in bin {k}: "
                               "an error must be >= 0; check the correlation table")
    var_method = str(table.header.get("VAR_METH", table.header.get("VARMETHD", "")) or "").strip().lower()
    listed = str(table.header.get("SHOTBINS", "") or "")
    shot_bins = tuple(int(k) for k in listed.split(",") if k.strip().isdigit())
    size = table.header.get("PATCHSIZ")
    size = float(size) if isinstance(size, (int, float)) and not isinstance(size, bool) and size > 0 else math.nan
    return XiTable(label=table.label, name=path, theta=theta, unit=unit, xip=xip, sigma_xip=sigma, empty=empty,
                   datasum=table.datasum, var_method=var_method, shot_bins=shot_bins, patch_size=size)


def _xi_unit(table, column: str) -> str:
    """The separation unit: SEP_UNIT, TreeCorr's sep_units, the column's TUNIT, else arcmin."""
    for key in ("SEP_UNIT", "SEP_UNITS"):
        if key in table.header:
            unit = str(table.header[key]).strip()
            if unit.lower() not in SEP_UNITS:
                raise PerscliError(f"{table.label}: HDU {table.index} keyword {key} = '{unit}' is not a "
                                   "separation unit: set it to arcmin, arcsec, deg or rad")
            return _canonical_unit(unit)
    tunit = table.unit(column)
    if tunit.lower() in SEP_UNITS:
        return _canonical_unit(tunit)
    return "arcmin"


def _canonical_unit(unit: str) -> str:
    scale = sep_unit_radians(unit)
    return {SEP_UNITS["arcmin"]: "arcmin", SEP_UNITS["arcsec"]: "arcsec", SEP_UNITS["deg"]: "deg",
            1.0: "rad"}[scale]


# -- comparison ---------------------------------------------------------------------------------

@dataclass
class Comparison:
    """The budget at a set of separations, and a measured xi+ against it.

    Attributes
    ----------
    theta : ndarray
        Separations, in ``unit``.
    unit : str
        arcmin, arcsec, deg or rad.
    budget : ndarray
        The budget's xi+ at ``theta``.
    bands, modes : str
        Which budget (a name of :data:`BANDS`, or 'custom') and 'E' or 'EB'.
    n_sigma : float
        A bin exceeds when ``|xip| - n_sigma * sigma_xip > |budget|``.
    xip, sigma_xip, ratio, sigma_ratio : ndarray or None
        The measurement, ``xip / budget`` and ``sigma_xip / |budget|`` (NaN in
        empty bins); None without a measurement.
    exceeds, empty : ndarray of bool or None
        Bins over the budget by more than their errors allow; bins without pairs.
    orders : float
        min over compared bins of ``log10(|budget| / |xip|)``: how far below the
        budget the measurement is at worst (inf when xip is 0 everywhere, nan
        without a comparison).
    verdict : str
        One line: 'below budget by 1.8 orders of magnitude at worst (...)',
        or, naming the bin, 'exceeds the budget at 2.5 arcmin (xi+ = ... >
        ... + 2 sigma, ...)'.
    worst : int or None
        The bin the verdict names: among the bins that exceed, the one
        furthest over its budget (largest |ratio|); otherwise the compared
        bin closest to its budget in orders of magnitude.  None without a
        compared bin.
    var_method : str
        What the errors of xi+ are ('jackknife', 'shot'; '' when unknown).
    shot_bins : tuple of int
        Bins whose error is shot noise inside a jackknife (the XI table's SHOTBINS).
    """

    theta: np.ndarray
    unit: str
    budget: np.ndarray
    bands: str
    modes: str
    n_sigma: float = BudgetOptions.n_sigma
    xip: np.ndarray | None = None
    sigma_xip: np.ndarray | None = None
    ratio: np.ndarray | None = None
    sigma_ratio: np.ndarray | None = None
    exceeds: np.ndarray | None = None
    empty: np.ndarray | None = None
    orders: float = float("nan")
    verdict: str = ""
    amplitudes: tuple = field(default_factory=tuple)
    worst: int | None = None
    var_method: str = ""
    shot_bins: tuple = ()
    #: per bin: 'below', 'above' or 'cannot tell' (:func:`bin_verdicts`); '' for an empty bin
    verdicts: np.ndarray | None = None
    #: per bin: whether its error can be trusted (a jackknife needs patches at least the separation)
    supported: np.ndarray | None = None
    patch_size: float = float("nan")

    @property
    def n_exceeding(self) -> int:
        """Number of bins over the budget (0 without a measurement)."""
        return int(np.count_nonzero(self.exceeds)) if self.exceeds is not None else 0

    def exceeding(self) -> list:
        """The bins over the budget, worst first: dicts of bin, theta, xip, sigma_xip, budget, ratio, sigma_ratio."""
        if self.exceeds is None:
            return []
        idx = np.flatnonzero(self.exceeds)
        idx = idx[np.argsort(-np.abs(self.ratio[idx]), kind="stable")]
        return [{"bin": int(k), "theta": float(self.theta[k]), "xip": float(self.xip[k]),
                 "sigma_xip": float(self.sigma_xip[k]), "budget": float(self.budget[k]),
                 "ratio": float(self.ratio[k]), "sigma_ratio": float(self.sigma_ratio[k])} for k in idx]


def budget_at(theta, unit: str = "arcmin", *, bands=BudgetOptions.bands,
              modes: str = BudgetOptions.modes) -> Comparison:
    """The budget alone at separations ``theta`` (in ``unit``), as a :class:`Comparison` without a measurement."""
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    unit = _canonical_unit(unit)
    amps = amplitudes(bands)
    modes = modes.upper()
    values = xi_plus(theta * sep_unit_radians(unit), amps, modes)
    return Comparison(theta=theta, unit=unit, budget=values, bands=_bands_name(bands), modes=modes,
                      amplitudes=amps)


def bin_verdicts(xip, sigma, budget, n_sigma: float = BudgetOptions.n_sigma, supported=None) -> np.ndarray:
    """Per separation bin: 'below' the budget, 'above' it, or 'cannot tell'.

    The budget bounds the size of a systematic whatever its sign, so a bin is
    'below' when ``|xi+| + n_sigma sigma < |budget|`` (a strongly negative
    xi+ is no better than a positive one), 'above' when
    ``|xi+| - n_sigma sigma > |budget|``, and 'cannot tell' when that
    interval straddles the budget, or where the error itself cannot be
    trusted (``supported`` False: a jackknife over patches smaller than the
    separation, or no error at all).
    """
    xip, sigma, budget = (np.asarray(v, dtype=float) for v in (xip, sigma, budget))
    ok = np.isfinite(xip) & np.isfinite(sigma)
    if supported is not None:
        ok &= np.asarray(supported, dtype=bool)
    out = np.full(xip.shape, "cannot tell", dtype=object)
    with np.errstate(invalid="ignore"):
        out[ok & (np.abs(xip) + n_sigma * sigma < np.abs(budget))] = "below"
        out[ok & (np.abs(xip) - n_sigma * sigma > np.abs(budget))] = "above"
    return out


def compare(xi: XiTable, *, bands=BudgetOptions.bands, modes: str = BudgetOptions.modes,
            n_sigma: float = BudgetOptions.n_sigma) -> Comparison:
    """Compare a measured xi+ with the budget at its separations.

    Parameters
    ----------
    xi : XiTable
        From :func:`read_xi`.
    bands, modes
        See :func:`xi_plus`.
    n_sigma : float
        A bin exceeds the budget when ``|xip| - n_sigma * sigma_xip > |budget|``:
        over it by more than ``n_sigma`` errors.

    Returns
    -------
    Comparison
        With ratio, sigma_ratio, exceeds, orders and verdict filled in.
    """
    if not (math.isfinite(n_sigma) and n_sigma >= 0):
        raise PerscliError(f"n_sigma must be finite and >= 0, got {n_sigma}")
    result = budget_at(xi.theta, xi.unit, bands=bands, modes=modes)
    used = ~xi.empty
    # a jackknife estimates the variance at a separation only from patches at least that wide
    supported = np.ones(len(xi.theta), dtype=bool)
    if xi.var_method == "jackknife" and math.isfinite(xi.patch_size):
        supported = xi.theta <= xi.patch_size
    verdicts = bin_verdicts(xi.xip, xi.sigma_xip, result.budget, n_sigma, supported)
    verdicts[~used] = ""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(used, xi.xip / result.budget, np.nan)
        sigma_ratio = np.where(used, xi.sigma_xip / np.abs(result.budget), np.nan)
        exceeds = used & (verdicts == "above")
        # how far below the budget the bin's upper bound (|xi+| + n_sigma sigma) lies
        orders_per_bin = np.log10(np.abs(result.budget) / (np.abs(xi.xip) + n_sigma * xi.sigma_xip))
    result.xip, result.sigma_xip = xi.xip, xi.sigma_xip
    result.ratio, result.sigma_ratio, result.exceeds, result.empty = ratio, sigma_ratio, exceeds, xi.empty.copy()
    result.n_sigma = float(n_sigma)
    result.orders = float(np.min(orders_per_bin[used])) if used.any() else float("nan")
    result.var_method = xi.var_method
    result.shot_bins = tuple(xi.shot_bins)
    result.verdicts, result.supported, result.patch_size = verdicts, supported, xi.patch_size
    result.verdict = _verdict(result, orders_per_bin)
    return result


#: how many separations of exceeding bins the verdict lists before '...'
VERDICT_LIST = 5


def _verdict(c: Comparison, orders_per_bin: np.ndarray) -> str:
    """The one-line verdict; sets ``c.worst`` to the bin it names."""
    text = _verdict_text(c, orders_per_bin)
    if c.worst is not None and c.var_method != "shot" and c.worst in c.shot_bins:
        text += "; that bin's error is shot noise (too few pairs there for the jackknife)"
    return text


def _verdict_text(c: Comparison, orders_per_bin: np.ndarray) -> str:
    used = ~c.empty
    m = int(np.count_nonzero(used))
    skipped = int(np.count_nonzero(c.empty))
    tail = f"; {skipped} empty bin{'s' if skipped != 1 else ''} skipped" if skipped else ""
    if m == 0:
        c.worst = None
        return f"no bin with pairs: nothing to compare with the budget{tail}"
    if c.var_method == "shot":
        # shot noise ignores any spatial coherence of De: errors too small, a finding too easy
        tail += "; errors are shot noise (no jackknife)"
    idx = np.flatnonzero(used)
    if c.n_exceeding:
        over = c.exceeding()
        k = over[0]["bin"]
        c.worst = k
        at = f"{c.theta[k]:.3g} {c.unit}"
        return f"exceeds the budget at {at} ({_excess(c, k)}){_others(c, over, m)}{tail}"
    if not np.isfinite(c.orders):
        c.worst = int(idx[0])
        return f"below budget at every separation (xi+ = 0 in all {m} bins){tail}"
    unsupported = idx[~c.supported[idx]] if c.supported is not None else idx[:0]
    if len(unsupported):
        tail += (f"; {len(unsupported)} bin{'s' if len(unsupported) != 1 else ''} beyond the jackknife patches' "
                 f"width ({c.patch_size:.3g} {c.unit}): cannot tell there")
    told = idx[c.verdicts[idx] != "cannot tell"] if c.verdicts is not None else idx
    if not len(told):
        c.worst = int(idx[0])
        return f"cannot tell at any of {m} bins: |xi+| +- {c.n_sigma:g} sigma straddles the budget{tail}"
    worst = int(told[np.argmin(orders_per_bin[told])])
    c.worst = worst
    where = f"theta = {c.theta[worst]:.3g} {c.unit}"
    open_bins = [int(k) for k in idx if c.verdicts[k] == "cannot tell" and c.supported[k]]
    if open_bins:
        seps = ", ".join(f"{c.theta[k]:.3g}" for k in open_bins[:VERDICT_LIST]) + \
            (", ..." if len(open_bins) > VERDICT_LIST else "")
        tail = f"; cannot tell at {seps} {c.unit} (|xi+| +- {c.n_sigma:g} sigma straddles the budget)" + tail
    median = float(np.median(orders_per_bin[told]))
    return (f"below budget at {len(told)} of {m} bins (|xi+| + {c.n_sigma:g} sigma), by {orders_per_bin[worst]:.1f} "
            f"orders of magnitude at worst ({where}), {median:.1f} at the median{tail}")


def _excess(c: Comparison, k: int) -> str:
    """'xi+ = 2.04e-07 > 6.81e-08 + 2 sigma (sigma 6.8e-11): 3 x the budget' for bin k."""
    x, s, b = float(c.xip[k]), float(c.sigma_xip[k]), float(c.budget[k])
    # magnitudes are compared (the budget bounds the size of a systematic, and turns negative at large
    # separations): say so when a sign makes the plain inequality read wrong
    plain = x >= 0 and b > 0
    lhs = f"xi+ = {x:.3g}" if plain else f"|xi+| = {abs(x):.3g}"
    rhs = f"{b:.3g}" if plain else f"|budget| {abs(b):.3g}"
    return (f"{lhs} > {rhs} + {c.n_sigma:g} sigma, sigma = {s:.2g}: "
            f"{float(c.ratio[k]):.3g} +- {float(c.sigma_ratio[k]):.2g} x the budget")


def _others(c: Comparison, over: list, m: int) -> str:
    """'; 1 of 12 bins' or '; 3 of 12 bins exceed, at 2.5, 5.1, 10 arcmin'."""
    if len(over) == 1:
        return f"; 1 of {m} bins"
    seps = sorted(row["theta"] for row in over)
    listed = ", ".join(f"{t:.3g}" for t in seps[:VERDICT_LIST]) + (", ..." if len(seps) > VERDICT_LIST else "")
    return f"; {len(over)} of {m} bins exceed, at {listed} {c.unit}"


def _bands_name(bands) -> str:
    if isinstance(bands, str):
        return bands.lower()
    amps = amplitudes(bands)
    for name, values in BANDS.items():
        if values == amps:
            return name
    return "custom"


# -- output -------------------------------------------------------------------------------------

def budget_hdulist(result: Comparison, *, inputs=()):
    """The 'BUDGET' table of a :class:`Comparison`, with its parameters and provenance in the header.

    Columns: theta (unit), xip_budget; with a measurement also xip, sigma_xip,
    ratio, sigma_ratio and exceeds (logical).
    """
    cols = {"theta": result.theta, "xip_budget": result.budget}
    if result.xip is not None:
        cols.update({"xip": result.xip, "sigma_xip": result.sigma_xip, "ratio": result.ratio,
                     "sigma_ratio": result.sigma_ratio, "exceeds": np.asarray(result.exceeds, dtype=bool),
                     "verdict": np.array([str(v) for v in result.verdicts]),
                     "supported": np.asarray(result.supported, dtype=bool)})
    descriptions = {"theta": "separation (meanr of the XI table, else r_nom)",
                    "xip_budget": "xi+ of the additive shear budget",
                    "xip": "measured xi+ (XI table)", "sigma_xip": "error of xip (XI table)",
                    "ratio": "xip / xip_budget (NaN: empty bin)", "sigma_ratio": "sigma_xip / |xip_budget|",
                    "exceeds": "|xip| - BUDSIGMA sigma_xip > |xip_budget|",
                    "verdict": "below (|xip| + BUDSIGMA sigma < |budget|), above, or cannot tell",
                    "supported": "the error holds: jackknife patches at least this separation wide"}
    hdu = table_hdu(cols, "BUDGET", units={"theta": result.unit}, descriptions=descriptions)
    params = {
        "BUDBANDS": (result.bands, "additive budget: HLIS requirement bands"),
        "BUDMODES": (result.modes, "E: budget for E modes; EB: E and B (xi+ x 2)"),
        "SEP_UNIT": (result.unit, "unit of theta"),
    }
    for k, ((lo, hi), amp) in enumerate(zip(L_BANDS, result.amplitudes), start=1):
        params[f"BUDA{k}"] = (amp, f"additive shear rms per component, l={lo}-{hi}")
    step = f"budget bands={result.bands} modes={result.modes}"
    if result.xip is not None:
        params["BUDSIGMA"] = (result.n_sigma, "exceeds: |xip| - BUDSIGMA sigma > |budget|")
        params["BUDNBIN"] = (int(np.count_nonzero(~result.empty)), "bins compared (with pairs)")
        params["BUDNEXC"] = (result.n_exceeding, "bins exceeding the budget")
        if np.isfinite(result.orders):
            params["BUDWORST"] = (round(result.orders, 4), "min log10(|budget|/(|xip| + BUDSIGMA sigma))")
        for key, name in (("BUDNBEL", "below"), ("BUDNCNT", "cannot tell")):
            params[key] = (int(np.count_nonzero(result.verdicts == name)), f"bins with verdict {name}")
        if math.isfinite(result.patch_size):
            params["BUDPATCH"] = (float(result.patch_size), f"[{result.unit}] width of the jackknife patches")
        if result.worst is not None:
            k = result.worst
            params["BUDWBIN"] = (int(k), "row of the bin the verdict names (0-based)")
            params["BUDWSEP"] = (float(result.theta[k]), f"[{result.unit}] separation of that bin")
            if np.isfinite(result.ratio[k]):
                params["BUDWRAT"] = (float(result.ratio[k]), "xip / budget in that bin")
        if result.var_method:
            params["BUDVARM"] = (result.var_method, "errors of xip (XI VAR_METH)")
        params["VERDICT"] = result.verdict
        step += f" sigma={result.n_sigma:g}: {result.verdict}"
    add_provenance(hdu, step=step, params=params, inputs=inputs)
    return [OutHDU([]), hdu]


def budget_figure(result: Comparison, *, linthresh: float | None = None) -> bytes:
    """The paper's comparison figure as PNG bytes.

    xi+ of the measurement with error bars (bins over the budget in red)
    against the budget's curve, log separation, symlog xi+; the linear range
    ``|xi+| < linthresh`` is shaded grey.  The legend sits below the axes, so
    that it hides no point.

    Parameters
    ----------
    result : Comparison
        From :func:`compare` or :func:`budget_at`.
    linthresh : float, optional
        Half-width of the symlog's linear range.  Default: the smallest
        positive sigma_xip of a compared bin, but at most 1e-10 (the budget's
        scale at the largest separations), so that both stay on the log part.

    Returns
    -------
    bytes
        A PNG image.
    """
    import matplotlib  # lazy: figures only for --plot; matplotlib.use is process-wide

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen

    measured = result.xip is not None
    used = ~result.empty if measured else np.zeros(0, bool)
    if linthresh is None:
        linthresh = 1e-10
        if measured:
            sig = result.sigma_xip[used]
            sig = sig[np.isfinite(sig) & (sig > 0)]
            if sig.size:
                linthresh = min(linthresh, float(sig.min()))
    lo, hi = float(result.theta.min()), float(result.theta.max())
    fine = np.geomspace(lo / 1.3, hi * 1.3, 600)
    curve = xi_plus(fine * sep_unit_radians(result.unit), result.amplitudes, result.modes)

    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    label = f"additive budget ({result.bands}, {'E and B' if result.modes == 'EB' else 'E'} modes)"
    ax.plot(fine, curve, color="black", lw=1.5, label=label)
    if measured:
        ok = used & ~result.exceeds
        ax.errorbar(result.theta[ok], result.xip[ok], yerr=result.sigma_xip[ok], fmt="o", ms=4, capsize=2,
                    color="tab:blue", label=r"$\xi_+$ of the shape changes")
        bad = used & result.exceeds
        if bad.any():
            ax.errorbar(result.theta[bad], result.xip[bad], yerr=result.sigma_xip[bad], fmt="s", ms=4, capsize=2,
                        color="tab:red", label=f"over budget by > {result.n_sigma:g} sigma")
        # 80 characters: at 95 a long verdict ran past the right edge of the figure
        ax.set_title(textwrap.fill(result.verdict, 80), fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("symlog", linthresh=linthresh)
    ax.axhspan(-linthresh, linthresh, color="0.85", zorder=0, label=f"linear range |y| < {linthresh:.1g}")
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_xlim(fine[0], fine[-1])
    ax.set_xlabel(rf"$\theta$ ({result.unit})")
    ax.set_ylabel(r"$\xi_+(\theta)$")
    # below the axes, never over them: loc="best" put the legend on the points at 4-6 arcmin (the
    # budget's curve fills the top, the points the middle, and no corner of the axes is free)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    return buffer.getvalue()


def budget_file(dest: str, xi_path: str | None = None, *, bands: str = BudgetOptions.bands,
                modes: str = BudgetOptions.modes, n_sigma: float = BudgetOptions.n_sigma, grid=DEFAULT_GRID,
                plot: str | None = None, overwrite: bool = False, stdin=None, stdout=None, columns=None) -> Comparison:
    """Check the outputs, compute the budget (and the comparison), write the table and the figure.

    Parameters
    ----------
    dest : str
        Output FITS path, or '-' for standard output.
    xi_path : str, optional
        A correlate output ('-' for standard input).  Without it the budget
        alone is tabulated on ``grid`` (arcmin: min, max, n log-spaced).
    bands, modes, n_sigma
        See :func:`compare`.
    plot : str, optional
        PNG path for :func:`budget_figure`.
    overwrite : bool
        Replace existing outputs.
    columns : dict, optional
        Column mapping of the xi table (:func:`read_xi`).

    Returns
    -------
    Comparison
        What was written.  Nothing is written when an error is raised.
    """
    inputs = [xi_path] if xi_path else []
    check_output(dest, overwrite=overwrite, inputs=inputs)
    if plot is not None:
        if plot == "-":
            raise PerscliError("the plot cannot go to standard output: give a PNG file name")
        check_output(plot, overwrite=overwrite, inputs=inputs)
        if dest != "-" and _same_path(plot, dest):
            raise PerscliError(f"{plot}: the plot and the table would be the same file: choose another name")
    # a typo in bands or modes is reported before the input is read
    amplitudes(bands)
    _modes_factor(modes)
    if xi_path:
        xi = read_xi(xi_path, stdin=stdin, columns=columns)
        result = compare(xi, bands=bands, modes=modes, n_sigma=n_sigma)
        provenance = [("XI", xi_path, xi.datasum)]
    else:
        result = budget_at(default_theta(grid), "arcmin", bands=bands, modes=modes)
        provenance = []
    # drawn before anything is written, so that a failing figure leaves no table behind
    png = budget_figure(result) if plot is not None else None
    write_hdus(budget_hdulist(result, inputs=provenance), dest, overwrite=overwrite, stdout=stdout)
    if png is not None:
        with atomic_output(plot, overwrite=overwrite) as stream:
            stream.write(png)
    return result


def _same_path(a: str, b: str) -> bool:
    return os.path.abspath(a) == os.path.abspath(b)
