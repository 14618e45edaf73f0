"""xi+/- of De with TreeCorr (:func:`correlate_de`) and how its covariance was estimated (:class:`Errors`).

The shear-shear correlation function of De (TreeCorr's ``GGCorrelation``),
with a jackknife covariance over k-means patches (or given patch centres,
:mod:`perscli.stats.patches`), or shot-noise errors when a jackknife is
impossible; separation bins whose jackknife variance is zero to rounding get
their shot noise instead.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import treecorr

from .. import PerscliError
from ..executor import threads
from .shape_changes import ShapeChanges

log = logging.getLogger("perscli")

#: the jackknife needs objects in every patch: at least this many per patch on average
MIN_PER_PATCH = 10
SEP_UNITS = ("arcsec", "arcmin", "deg", "rad")
CROSS_PATCH_WEIGHTS = ("simple", "mean", "match")
#: covariance of xi: 'auto' is the jackknife when possible, else shot noise (with a warning)
VAR_METHODS = ("auto", "jackknife", "shot")


# ------------------------------------------------------------------------------------------------
# correlation
# ------------------------------------------------------------------------------------------------

def _treecorr_logger():
    """TreeCorr logs to stdout unless given a logger: send it to perscli's (stderr), quieter by one level."""
    logger = logging.getLogger("perscli.treecorr")
    logger.setLevel(logging.DEBUG if log.isEnabledFor(logging.DEBUG) else logging.WARNING)
    return logger


@dataclass
class Errors:
    """How the covariance of xi was estimated, and why.

    Attributes
    ----------
    method : {'jackknife', 'shot'}
        What TreeCorr's covariance is: the jackknife over patches, or shot
        noise (the variance of De over the pairs of each bin, every object
        independent: diagonal, and too small wherever De is spatially
        coherent).
    reason : str
        Why shot noise was used ('' for the jackknife).
    npatch : int
        Patches the jackknife used (0 for shot noise).
    asked : {'auto', 'jackknife', 'shot'}
        The ``var_method`` asked for.
    cov : ndarray or None
        The covariance written (xi+ bins, then xi- bins): TreeCorr's, with
        the rows and columns of ``shot_bins`` replaced by their shot noise.
    shot_bins : list of int
        Separation bins whose variance the jackknife could not estimate
        (zero to rounding, or not finite, though the bin has pairs: a bin
        with a pair or two at the edge of the range), given shot noise
        instead; empty when the whole covariance is one method.
    """

    method: str
    reason: str = ""
    npatch: int = 0
    asked: str = "auto"
    cov: np.ndarray | None = None
    shot_bins: list = field(default_factory=list)
    #: the typical width of a jackknife patch, in the separation unit (NaN without patches): a jackknife
    #: patch must be at least a separation for its removal to sample that separation's variance
    patch_size: float = float("nan")


def _too_few(n: int, wanted: int) -> tuple:
    """(why ``n`` objects cannot be cut into ``wanted`` jackknife patches, what would allow it or '')."""
    if n < 2 * MIN_PER_PATCH:
        return (f"only {n} object{'s' if n != 1 else ''}: too few for a jackknife over patches "
                f"(at least {2 * MIN_PER_PATCH} needed)"), ""
    return (f"only {n} objects for {wanted} jackknife patches (at least {MIN_PER_PATCH} per patch needed)",
            f"--npatch {max(2, n // MIN_PER_PATCH)} or fewer")


def correlate_de(sc: ShapeChanges, *, min_sep=1.0, max_sep=100.0, nbins=20, sep_units="arcmin", bin_slop=None,
                 npatch=20, patch_centers=None, cross_patch_weight="match", var_method="auto", seed=1, workers=1):
    """xi+/- of De with TreeCorr, and its covariance: the jackknife, or shot noise when that is impossible.

    Parameters
    ----------
    sc : ShapeChanges
        De and positions.
    min_sep, max_sep, nbins, sep_units, bin_slop
        TreeCorr's log binning (bin_slop None: TreeCorr's default,
        min(1, 0.1 / bin_size)).
    npatch : int
        k-means patches for the jackknife (ignored with ``patch_centers``).
    patch_centers : ndarray, optional
        Patch centres (see :func:`read_patch_centers`).
    cross_patch_weight : {'match', 'simple', 'mean'}
        TreeCorr's weight of pairs across a removed and a kept patch
        ('match': Mohammad & Percival 2022's, recommended for the jackknife).
    var_method : {'auto', 'jackknife', 'shot'}
        'jackknife' insists on it (an error when impossible); 'shot' asks for
        TreeCorr's shot noise; 'auto' (default) is the jackknife unless it is
        impossible, then shot noise with a warning that says why: fewer than
        :data:`MIN_PER_PATCH` objects per patch (a CI-sized study of a few
        dozen galaxies), fewer than 2 patches holding objects, or TreeCorr's
        jackknife failing.  A separation bin whose jackknife variance is
        zero to rounding (below 1e-6 of its shot noise) or not finite,
        though it has pairs (a pair or two at the edge of the range: too
        few per patch), gets its shot noise instead, with a warning: a zero
        error would make any value there significant.  'jackknife' keeps it
        (with the warning).
    seed : int
        Seed of the k-means initialisation (same seed, same patches).
    workers : int
        TreeCorr's OpenMP threads (:func:`perscli.executor.threads`: 1 when
        not given, never all cores unasked).

    Returns
    -------
    (treecorr.GGCorrelation, treecorr.Catalog, Errors)
        The catalogue has patches only when the jackknife was used; the
        covariance to use is ``Errors.cov`` (it differs from ``gg.cov`` in
        ``Errors.shot_bins``).

    Raises
    ------
    PerscliError
        Bad settings, the jackknife asked for and impossible, or TreeCorr failing.
    """
    if not 0 < min_sep < max_sep:
        raise PerscliError(f"--min-sep {min_sep} and --max-sep {max_sep}: need 0 < min-sep < max-sep")
    if sep_units not in SEP_UNITS:
        raise PerscliError(f"--sep-units {sep_units}: one of {', '.join(SEP_UNITS)}")
    if cross_patch_weight not in CROSS_PATCH_WEIGHTS:
        raise PerscliError(f"--cross-patch-weight {cross_patch_weight}: one of {', '.join(CROSS_PATCH_WEIGHTS)}")
    if var_method not in VAR_METHODS:
        raise PerscliError(f"--var-method {var_method}: one of {', '.join(VAR_METHODS)}")
    n = len(sc)
    if n == 0:
        raise PerscliError("no objects to correlate")
    wanted = len(patch_centers) if patch_centers is not None else npatch
    if var_method != "shot" and wanted < 2:
        raise PerscliError(f"{wanted} patch(es): the jackknife needs at least 2")
    logger = _treecorr_logger()
    nthreads = threads(workers)
    treecorr.set_omp_threads(nthreads, logger=logger)
    if sc.coords == "radec":
        where = dict(ra=sc.pos1, dec=sc.pos2, ra_units="deg", dec_units="deg")
    else:
        where = dict(x=sc.pos1, y=sc.pos2, x_units=sc.pos_units, y_units=sc.pos_units)
    binning = dict(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units=sep_units, bin_slop=bin_slop,
                   logger=logger)

    def run(method, patches):
        try:
            cat = treecorr.Catalog(g1=sc.de1, g2=sc.de2, rng=np.random.default_rng(seed), logger=logger,
                                   **where, **patches)
            extra = dict(cross_patch_weight=cross_patch_weight) if method == "jackknife" else {}
            gg = treecorr.GGCorrelation(var_method=method, **binning, **extra)
            gg.process(cat, num_threads=nthreads)
            gg.cov  # computed here so that a TreeCorr failure is reported as one
        except (ValueError, RuntimeError, ZeroDivisionError) as exc:
            raise PerscliError(f"TreeCorr failed on {n} objects ({method} errors): {exc}") from None
        return gg, cat

    errors = Errors("jackknife", npatch=wanted, asked=var_method)
    if var_method == "shot":
        errors = Errors("shot", reason="shot noise asked for (var_method 'shot')", asked=var_method)
    elif n < MIN_PER_PATCH * wanted:
        why, fix = _too_few(n, wanted)
        if var_method == "jackknife":
            raise PerscliError(f"{why}: use {fix}" if fix else why)
        errors = Errors("shot", reason=f"{why}; {fix} would allow one" if fix else why, asked=var_method)
    if errors.method == "jackknife":
        patches = dict(patch_centers=patch_centers) if patch_centers is not None else dict(npatch=npatch)
        try:
            gg, cat = run("jackknife", patches)
        except PerscliError as exc:
            if var_method == "jackknife":
                raise
            errors = Errors("shot", reason=f"the jackknife failed ({exc})", asked=var_method)
        else:
            used = int(np.count_nonzero(np.bincount(cat.patch, minlength=wanted)))
            errors.npatch = used
            if used < 2:
                if var_method == "jackknife":
                    raise PerscliError(f"only {used} of {wanted} patches hold objects: the jackknife needs 2")
                errors = Errors("shot", reason=f"only {used} of {wanted} patches hold objects (the jackknife "
                                "needs 2)", asked=var_method)
            else:
                if used < wanted:
                    log.warning("%d of %d patches hold no object: the jackknife uses %d", wanted - used, wanted,
                                used)
                errors.cov = np.array(gg.cov, dtype=np.float64)
                errors.patch_size = patch_size(cat, sc.coords, sep_units)
                _repair_bins(gg, errors, float(cat.varg), sep_units, keep=var_method == "jackknife")
    if errors.method == "shot":
        if var_method == "auto":
            log.warning("shot-noise errors for xi instead of a jackknife: %s (shot noise counts every object as "
                        "independent: too small where De is spatially coherent)", errors.reason)
        gg, cat = run("shot", {})
        errors.cov = np.array(gg.cov, dtype=np.float64)
    if np.any(gg.npairs == 0):
        empty = int(np.sum(gg.npairs == 0))
        if empty < nbins:
            log.warning("%d of %d separation bins hold no pair: widen the range or use fewer bins", empty, nbins)
        else:
            log.warning("no separation bin holds a pair: no two of the %d object(s) are %g to %g %s apart", n,
                        min_sep, max_sep, sep_units)
    return gg, cat, errors


#: radians per separation unit
RADIANS_PER = {"arcsec": math.pi / 648000, "arcmin": math.pi / 10800, "deg": math.pi / 180, "rad": 1.0}


def patch_size(cat, coords: str, sep_units: str) -> float:
    """The typical width of the jackknife patches of a TreeCorr catalogue, in ``sep_units``.

    Each patch is taken as a disc holding its objects: for objects spread
    evenly over a disc of radius R, their rms distance from its centre is
    R / sqrt(2), so the disc's width is 2 sqrt(2) times the rms distance.
    The median over the patches that hold objects.
    """
    patch = np.asarray(cat.patch)
    if coords == "radec":
        ra, dec = np.radians(cat.ra), np.radians(cat.dec)
        xyz = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)
    else:
        # TreeCorr keeps x/y given with an angle unit in radians
        xyz = np.stack([cat.x, cat.y], axis=1)
    to_unit = 1.0 / RADIANS_PER[sep_units]
    widths = []
    for k in np.unique(patch[patch >= 0]):
        pts = xyz[patch == k]
        if len(pts) < 2:
            continue
        centre = pts.mean(axis=0)
        if coords == "radec":
            centre /= np.linalg.norm(centre)
            d = np.arccos(np.clip(pts @ centre, -1.0, 1.0))
        else:
            d = np.linalg.norm(pts - centre, axis=1)
        widths.append(2.0 * math.sqrt(2.0) * math.sqrt(float(np.mean(d * d))))
    return float(np.median(widths)) * to_unit if widths else float("nan")


def _repair_bins(gg, errors: Errors, varg: float, sep_units: str, *, keep: bool) -> None:
    """Give shot noise to the bins whose jackknife variance is zero to rounding though they have pairs.

    A bin holding a pair or two (at the edge of the range) leaves every
    jackknife sample with the same value, or none: its jackknife variance
    comes out as 0 or ~1e-30 of its shot noise, and an error of zero would
    make any xi there significant.  Such a bin's rows and columns of
    ``errors.cov`` (xi+ and xi-) become its shot-noise variance, listed in
    ``errors.shot_bins``; with ``keep`` (the jackknife insisted on) they are
    only reported.  With De zero everywhere (varg 0) zero variances are right.
    """
    nb = len(gg.npairs)
    has_pairs = np.asarray(gg.npairs) > 0
    var = np.diagonal(errors.cov)
    shot = np.asarray(gg.estimate_cov("shot"), dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(var) | ((varg > 0) & (var < 1e-6 * shot))
    bins = np.flatnonzero(has_pairs & (bad[:nb] | bad[nb:]))
    if not len(bins):
        return
    seps = ", ".join(f"{gg.rnom[k]:.3g}" for k in bins[:4]) + (", ..." if len(bins) > 4 else "")
    what = (f"the jackknife variance is zero to rounding (or not finite) in {len(bins)} of "
            f"{int(has_pairs.sum())} bins with pairs (theta = {seps} {sep_units}: too few pairs per patch)")
    if keep:
        log.warning("jackknife asked for, kept although %s", what)
        return
    for k in bins:
        for i in (k, nb + k):
            errors.cov[i, :] = 0.0
            errors.cov[:, i] = 0.0
            errors.cov[i, i] = shot[i]
    errors.shot_bins = [int(k) for k in bins]
    log.warning("%s: shot noise there instead", what)
