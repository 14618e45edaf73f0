"""Shape changes De between two measurements: their correlation function and statistics.

The paper measures every galaxy twice, on an exposure with persistence (A)
and on the same exposure without it (B), and studies De = g(A) - g(B):

- the shear-shear correlation function xi+/- of De (TreeCorr's
  ``GGCorrelation``), with a jackknife covariance over k-means patches, or
  shot-noise errors when a jackknife is impossible (:func:`correlate_de`);
- N, the mean intrinsic ellipticity (the mean g of B), the mean De with its
  standard error, and the fraction of objects with |De| above thresholds
  (1e-8 and 1e-4 in the paper);
- the histogram of |De| (the paper's figure hist_de);
- the |De|-weighted distribution of the position angle of De in bins of
  |De|, with bootstrap errors, and a chi2 test against uniform whose
  variance is the one under the uniform hypothesis (the paper's figure
  bin_theta; :func:`theta_distribution`).

:func:`load_shape_changes` reads De from one or two SHAPES tables
(``perscli measure``), :func:`load_pairs` pools the De of many pairs (each
final exposure against its reference) into one catalogue,
:func:`de_statistics`, :func:`de_histogram`, :func:`theta_distribution` and
:func:`correlate_de` compute the pieces, and :func:`correlate_files` is
``perscli correlate`` as a function.

Pooling: every pair contributes one entry per object it measures, so an
object measured in several pairs (several final exposures of the same
galaxy) appears once per pair, at its ra/dec: xi+/- then counts the pairs
of entries, the statistics count entries, and the jackknife puts all of an
object's entries in the same patch.

Orientation: g in a SHAPES table is in the frame's pixel axes unless the
table's header says otherwise (GAXES or GFRAME = 'sky': a joint fit, one row
per galaxy, whose g is in sky axes); De is correlated in the axes it is
given in.  xi+ does not depend on those axes when one rotation takes them to
the local sky axes over the whole catalogue (one detector, one pointing): a
rotation by phi multiplies every De by exp(2i phi) and leaves De De*
unchanged.  If the pixel axes are also mirrored with respect to the sky, xi+
is unchanged in flat geometry and to within the parallel transport between
the two objects' local frames on the sky (well under 1 % at these
separations).  xi- does depend on the orientation: a rotation turns it into
xi- exp(4i phi), mixing its real and imaginary parts.  Catalogues that
combine detectors or pointings with different orientations need g in sky
axes (a joint fit), or De rotated to the sky first (given with --de1/--de2).

This module holds the driver, :func:`correlate_files` (checks of its
options, the figures' file names, writing everything or nothing); De is read
by :mod:`perscli.stats.shape_changes` and :mod:`perscli.stats.pairs`, its
statistics are in :mod:`perscli.stats.de_stats`, xi+/- in
:mod:`perscli.stats.xi` and the output's HDUs in
:mod:`perscli.stats.correlate_hdus`.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass

from .. import PerscliError
from ..io.output import check_output, write_hdus
from ..io.tempfiles import make_temp_file
from ..scene import separation
from . import plots
from .settings import CorrelateOptions

from .correlate_hdus import build_hdus, xi_table
from .de_stats import _abs, de_histogram, de_statistics, theta_distribution, theta_summary
from .pairs import _check_pairs, load_pairs
from .patches import patch_center_vectors, read_patch_center_columns
from .shape_changes import load_shape_changes
from .xi import VAR_METHODS, Errors, correlate_de

log = logging.getLogger("perscli")


# ------------------------------------------------------------------------------------------------
# the driver: perscli correlate as a function
# ------------------------------------------------------------------------------------------------

def _png_targets(plot, plots_dir, overwrite):
    """{kind: path} of the figures to write, checked before any work."""
    targets = {}
    if plot is not None:
        if not plot.lower().endswith(".png"):
            raise PerscliError(f"--plot {plot}: needs a .png file name")
        targets["xi"] = plot
    if plots_dir is not None:
        if os.path.exists(plots_dir) and not os.path.isdir(plots_dir):
            raise PerscliError(f"--plots {plots_dir}: is a file, not a folder")
        parent = os.path.dirname(os.path.abspath(plots_dir))
        if not os.path.isdir(parent):
            raise PerscliError(f"--plots {plots_dir}: folder {parent} does not exist")
        for kind in ("xi", "hist_de", "bin_theta"):
            targets[f"dir:{kind}"] = os.path.join(plots_dir, f"{kind}.png")
    for path in targets.values():
        folder = os.path.dirname(os.path.abspath(path))
        if path == plot and not os.path.isdir(folder):
            raise PerscliError(f"{path}: folder {folder} does not exist; create it or choose another file")
        if os.path.exists(path) and not overwrite:
            raise PerscliError(f"{path}: already exists; use --overwrite to replace it")
    return targets


def _within(sc, ra, dec, radius):
    """The objects of ``sc`` within ``radius`` degrees of (ra, dec) (a study's field)."""
    if sc.coords != "radec":
        raise PerscliError("a circle on the sky needs ra/dec positions, not x/y")
    keep = separation(ra, dec, sc.pos1, sc.pos2) <= radius
    if not keep.any():
        raise PerscliError(f"no object within {radius} deg of ra={ra} dec={dec}: nothing to correlate")
    return sc.select(keep, "outside")


def correlate_files(catalogs, dest: str, options: CorrelateOptions | None = None, *, pairs=None, frames=None,
                    patch_centers=None, workers=1, plot=None, plots_dir=None, overwrite=False, stdin=None) -> dict:
    """``perscli correlate`` as a function: xi+/- of De, its covariance and the De statistics.

    Writes ``dest`` (FITS; '-' for standard output) with the HDUs XI
    (TreeCorr's columns), COV (covariance, [xi+, xi-]), STATS, HIST_DE,
    THETA_DE, PATCHES and, for pooled pairs, PAIRS; and optionally the
    figures: ``plot`` (xi alone) and ``plots_dir``/{xi,hist_de,bin_theta}.png.
    Nothing is written unless everything succeeds.

    Parameters
    ----------
    catalogs : sequence of str
        One or two SHAPES tables (:func:`load_shape_changes`); empty when
        ``pairs`` is given.
    dest : str
        Output path, '-' for standard output.
    pairs : sequence of (str, str), or str, optional
        Many pairs pooled into one catalogue (:func:`load_pairs`): (A, B)
        paths, or the path of a pairs file.  Not with ``catalogs`` or
        ``de_columns``.
    options : CorrelateOptions, optional
        The analysis settings (:class:`~perscli.stats.settings.CorrelateOptions`,
        where their defaults are written): columns and positions, the
        separation bins, patches and covariance, thresholds, the
        position-angle bins and bootstrap, the seed.
    frames
        See :func:`load_shape_changes`.
    patch_centers, workers
        See :func:`correlate_de` (``patch_centers`` is a file here).
    plot, plots_dir, overwrite, stdin
        Figures, replacing existing outputs, the stream read for '-'.

    Returns
    -------
    dict
        n (objects; entries when pairs are pooled), npairs (0 without
        ``pairs``), counts, stats, the xi table, npatch, var_method and
        var_reason (why shot noise, '' for the jackknife), shot_bins
        (separation bins given shot noise inside a jackknife), theta (per
        |De| bin: de_lo, de_hi, n, n_eff, chi2, dof, p, p_method), figures
        and source.
    """
    o = options if options is not None else CorrelateOptions()
    catalogs = list(catalogs or ())
    pairs, thresholds, theta_edges = _checked_options(o, catalogs, pairs, frames)
    inputs = [*catalogs, *(name for pair in (pairs or ()) for name in pair), patch_centers]
    pngs = _checked_outputs(dest, inputs, plot=plot, plots_dir=plots_dir, overwrite=overwrite)
    sc, centers = _read_de(o, catalogs, pairs, frames=frames, patch_centers=patch_centers, stdin=stdin)
    found = _correlate(sc, o, centers, thresholds=thresholds, theta_edges=theta_edges, workers=workers)
    settings = dict(min_sep=float(o.min_sep), max_sep=float(o.max_sep), nbins=int(o.nbins), sep_units=o.sep_units,
                    cross_patch_weight=o.cross_patch_weight, nboot=int(o.nboot))
    source = os.path.basename(patch_centers) if patch_centers is not None else f"kmeans npatch={o.npatch}"
    errors = found.errors
    hdul = build_hdus(sc, found.gg, found.cat, found.stats, found.hist, found.theta, settings=settings, seed=o.seed,
                      patch_source=source, errors=errors)
    xi = xi_table(found.gg, errors.cov)
    errs = "jackknife errors" if errors.method == "jackknife" else "shot-noise errors"
    figures = {"xi": lambda p: plots.xi_figure(xi, p, sep_units=o.sep_units, title=sc.source, errors=errs),
               "hist_de": lambda p: plots.hist_de_figure(found.hist, p, thresholds=thresholds, n=len(sc)),
               "bin_theta": lambda p: plots.theta_figure(found.theta, p)}
    _write_all(hdul, dest, pngs, figures, plots_dir=plots_dir, overwrite=overwrite)
    return {"n": len(sc), "npairs": len(sc.pairs), "counts": sc.counts, "stats": found.stats, "xi": xi,
            "npatch": errors.npatch, "var_method": errors.method, "var_reason": errors.reason,
            "shot_bins": list(errors.shot_bins),
            "theta": theta_summary(found.theta), "figures": list(pngs.values()), "source": sc.source}


def _checked_options(o: CorrelateOptions, catalogs: list, pairs, frames) -> tuple:
    """Check :func:`correlate_files`' inputs and settings before anything is read.

    Returns
    -------
    (list or None, tuple of float, tuple of float)
        The pairs (:func:`perscli.stats.pairs._check_pairs`), the |De|
        thresholds and the position-angle bins' edges.

    Raises
    ------
    PerscliError
        Tables and pairs both, or a setting out of range.
    """
    if pairs is not None:
        if catalogs:
            raise PerscliError("give SHAPES tables or pairs, not both")
        if o.de_columns is not None:
            raise PerscliError("--de1/--de2 name the De columns of one table; they do not go with pairs")
        pairs = _check_pairs(pairs, frames)
    if o.var_method not in VAR_METHODS:
        raise PerscliError(f"--var-method {o.var_method}: one of {', '.join(VAR_METHODS)}")
    thresholds = tuple(float(t) for t in o.thresholds)
    if not thresholds or any(not (t > 0 and math.isfinite(t)) for t in thresholds):
        raise PerscliError(f"--thresholds {thresholds}: need one or more positive numbers")
    theta_edges = tuple(float(t) for t in o.theta_edges)
    if len(theta_edges) < 2 or any(b <= a for a, b in zip(theta_edges[:-1], theta_edges[1:])) or theta_edges[0] < 0:
        raise PerscliError(f"--theta-bins {theta_edges}: need two or more increasing edges >= 0")
    if o.nboot < 2:
        raise PerscliError(f"--nboot {o.nboot}: need at least 2 resamples")
    if not 0 < o.min_sep < o.max_sep:
        raise PerscliError(f"--min-sep {o.min_sep} and --max-sep {o.max_sep}: need 0 < min-sep < max-sep")
    return pairs, thresholds, theta_edges


def _checked_outputs(dest: str, inputs: list, *, plot, plots_dir, overwrite: bool) -> dict:
    """Check the output file and the figures' (:func:`_png_targets`); returns {kind: path} of the figures."""
    check_output(dest, overwrite=overwrite, inputs=inputs)
    pngs = _png_targets(plot, plots_dir, overwrite)
    for path in pngs.values():
        if os.path.exists(path):
            check_output(path, overwrite=overwrite, inputs=inputs)
        if dest != "-" and os.path.abspath(path) == os.path.abspath(dest):
            raise PerscliError(f"{path}: a figure and the -o output name the same file: choose another name")
    return pngs


def _read_de(o: CorrelateOptions, catalogs: list, pairs, *, frames, patch_centers, stdin):
    """The De to correlate (:func:`load_pairs` or :func:`load_shape_changes`) and the patch centres given.

    Returns
    -------
    (ShapeChanges, ndarray or None)
        De (within ``o.within`` when set), and the patch centres as vectors
        (:func:`perscli.stats.patches.patch_center_vectors`) or None.
    """
    # the patch centres are read first: a bad --patch-centers (a FIFO without a writer, /dev/zero, a folder)
    # is one line before any table is read, never a hang or a traceback after it
    centre_columns = read_patch_center_columns(patch_centers) if patch_centers is not None else None
    if o.flagged not in ("drop", "keep"):
        raise PerscliError(f"flagged {o.flagged!r}: drop or keep")
    if pairs is not None:
        sc = load_pairs(pairs, frames=frames, common_ids=o.common_ids, positions=o.positions,
                        pixel_scale=o.pixel_scale, stdin=stdin, columns=o.columns, flagged=o.flagged)
    else:
        sc = load_shape_changes(catalogs, frames=frames, de_columns=o.de_columns, common_ids=o.common_ids,
                                positions=o.positions, pixel_scale=o.pixel_scale, stdin=stdin, columns=o.columns,
                                flagged=o.flagged)
    if o.within is not None:
        sc = _within(sc, *o.within)
    centers = patch_center_vectors(centre_columns, sc.coords, patch_centers) if patch_centers is not None else None
    log.info("%s: %d objects (%d matched, %d flagged, %d not finite)", sc.source, len(sc), sc.counts["matched"],
             sc.counts["flagged"], sc.counts["nonfinite"])
    return sc, centers


@dataclass
class _Correlation:
    """What :func:`_correlate` finds: xi+/- of De and the statistics of De."""

    gg: object          # treecorr.GGCorrelation, processed
    cat: object         # its treecorr.Catalog (the jackknife's patches)
    errors: Errors      # the covariance of xi
    stats: dict         # de_statistics
    hist: dict          # de_histogram of |De|
    theta: dict         # theta_distribution


def _correlate(sc, o: CorrelateOptions, centers, *, thresholds, theta_edges, workers: int = 1) -> _Correlation:
    """xi+/- of De (:func:`correlate_de`), its statistics, the |De| histogram and the position angles' distribution."""
    gg, cat, errors = correlate_de(sc, min_sep=o.min_sep, max_sep=o.max_sep, nbins=o.nbins, sep_units=o.sep_units,
                                   bin_slop=o.bin_slop, npatch=o.npatch, patch_centers=centers,
                                   cross_patch_weight=o.cross_patch_weight, var_method=o.var_method, seed=o.seed,
                                   workers=workers)
    stats = de_statistics(sc.de1, sc.de2, e1=sc.e1, e2=sc.e2, thresholds=thresholds, dabs=sc.dabs,
                          flags=sc.flags if o.flagged == "keep" else None)
    hist = de_histogram(_abs(sc.de1, sc.de2))
    theta = theta_distribution(sc.de1, sc.de2, edges=theta_edges, nboot=o.nboot, seed=o.seed)
    return _Correlation(gg=gg, cat=cat, errors=errors, stats=stats, hist=hist, theta=theta)


def _write_all(hdul: list, dest: str, pngs: dict, figures: dict, *, plots_dir, overwrite: bool) -> None:
    """Write the figures and the FITS file, everything or nothing.

    The figures first, into temporary files beside their targets, renamed
    once the FITS file is in place; ``figures``: kind -> a function drawing
    it into a path.
    """
    temps, made_dir = {}, None
    try:
        if pngs:
            if plots_dir is not None and not os.path.isdir(plots_dir):
                os.mkdir(plots_dir)
                made_dir = plots_dir
            for key, path in pngs.items():
                # a new file's permissions (0666 less the umask), as for every output
                fd, tmp = make_temp_file(os.path.dirname(os.path.abspath(path)),
                                         prefix=f".{os.path.basename(path)}.", suffix=".png")
                os.close(fd)
                temps[tmp] = path
                figures[key.removeprefix("dir:")](tmp)
        write_hdus(hdul, dest, overwrite=overwrite)
        for tmp, path in temps.items():
            os.replace(tmp, path)
        temps.clear()
        made_dir = None
    finally:
        for tmp in temps:
            if os.path.exists(tmp):
                os.unlink(tmp)
        if made_dir is not None:
            os.rmdir(made_dir)
