"""The HDUs of the ``perscli correlate`` output file, and xi as a table of TreeCorr's columns.

:func:`build_hdus` lays out the file: the primary HDU with the provenance and
settings, XI (:func:`xi_table`), COV, STATS, HIST_DE, THETA_DE, PATCHES and,
for pooled pairs, PAIRS (:func:`_pairs_hdu`) or, for pooled De columns,
INPUTS.
"""

from __future__ import annotations

import os
import textwrap

import numpy as np
import treecorr

from ..io.fitsfile import OutHDU, table_hdu
from ..io.output import add_provenance
from .de_stats import MIN_EXPECTED, N_ANGLE, NULL_DRAWS
from .shape_changes import ShapeChanges
from .xi import Errors


# ------------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------------

XI_COLUMNS = ("r_nom", "meanr", "meanlogr", "xip", "xim", "xip_im", "xim_im", "sigma_xip", "sigma_xim",
              "weight", "npairs")


def xi_table(gg, cov=None) -> dict:
    """TreeCorr's output columns of a GGCorrelation (:data:`XI_COLUMNS`), by name.

    With ``cov`` (xi+ bins then xi- bins, e.g. :attr:`Errors.cov`) the
    errors are the square roots of its diagonal instead of TreeCorr's.
    """
    if cov is None:
        sigp, sigm = np.sqrt(gg.varxip), np.sqrt(gg.varxim)
    else:
        diag = np.sqrt(np.diagonal(cov))
        sigp, sigm = diag[:len(gg.xip)], diag[len(gg.xip):]
    return dict(zip(XI_COLUMNS, (gg.rnom, gg.meanr, gg.meanlogr, gg.xip, gg.xim, gg.xip_im, gg.xim_im,
                                 sigp, sigm, gg.weight, gg.npairs)))


def _comment(hdu, text: str) -> None:
    """COMMENT cards holding ``text``, wrapped at 72 characters (a card holds no more)."""
    for line in textwrap.wrap(text, 72):
        hdu.header.add_comment(line)


def _table_hdu(columns: dict, name: str, units: dict | None = None):
    return table_hdu(columns, name, units=units)


_AXES_COMMENTS = {
    "pixel": "De is in the pixel axes of the frames measured. xi+ is unchanged by a rotation of those axes "
             "common to the catalogue; xi- is not (it mixes with xim_im).",
    "as given": "De is correlated in the axes it is given in. xi+ is unchanged by a rotation of those axes "
                "common to the catalogue; xi- is not (it mixes with xim_im).",
    "sky": "De is in sky axes (g of joint fits): xi+ and xi- are defined on the sky.",
}


def build_hdus(sc: ShapeChanges, gg, cat, stats: dict, hist: dict, theta: dict, *, settings: dict, seed: int,
               patch_source: str, errors: Errors | None = None):
    """The output file: provenance, XI, COV, STATS, HIST_DE, THETA_DE, PATCHES and, for pooled pairs, PAIRS.

    Parameters
    ----------
    sc : ShapeChanges
        The De correlated, with their inputs and counts.
    gg : treecorr.GGCorrelation
        The correlation, processed.
    cat : treecorr.Catalog
        Its catalogue (the jackknife's patches).
    stats, hist, theta : dict
        The one-point statistics, the |De| histogram and the position-angle
        distribution (:mod:`perscli.stats.de_stats`).
    settings : dict
        The binning and error settings used (:mod:`perscli.stats.settings`).
    seed : int
    patch_source : str
        Where the patches came from: k-means, or the --patch-centers file.
    errors : Errors, optional
        The covariance of xi (default: TreeCorr's, of ``gg``).

    Returns
    -------
    list of OutHDU
    """
    if errors is None:
        errors = Errors(str(gg.var_method), npatch=int(cat.npatch) if gg.var_method == "jackknife" else 0)
    jackknife = errors.method == "jackknife"
    primary = _primary_hdu(sc, gg, stats, settings=settings, seed=seed, patch_source=patch_source, errors=errors)
    cov_matrix = errors.cov if errors.cov is not None else np.asarray(gg.cov, dtype=np.float64)
    hdus = [primary, _xi_hdu(sc, gg, cov_matrix, settings, errors), _cov_hdu(cov_matrix, settings, errors),
            _stats_hdu(sc, stats), _hist_hdu(hist), _theta_hdu(theta, settings), _patches_hdu(sc, cat, jackknife)]
    if sc.pairs:
        hdus.append(_pairs_hdu(sc.pairs, sc.g_axes))
    if sc.tables:
        hdus.append(_inputs_hdu(sc.tables))
    return hdus


def _primary_hdu(sc: ShapeChanges, gg, stats: dict, *, settings: dict, seed: int, patch_source: str,
                 errors: Errors) -> OutHDU:
    """The primary HDU: the provenance, the settings and counts, and COMMENT cards on the axes and errors."""
    jackknife = errors.method == "jackknife"
    sep = settings["sep_units"]
    primary = OutHDU([])
    params = {"NOBJ": (len(sc), "objects correlated (entries, pooled pairs)")}
    params.update(sc.params)
    if sc.ids is not None and sc.pair is not None:
        params["NIDS"] = (int(len(np.unique(sc.ids))), "distinct ids over the pooled pairs")
    params.update({
        "GFRAME": (sc.g_axes, "axes of De: pixel, sky or as given (De columns)"),
        "MINSEP": (settings["min_sep"], f"[{sep}] --min-sep"), "MAXSEP": (settings["max_sep"], f"[{sep}] --max-sep"),
        "NBINS": (settings["nbins"], "--nbins (log bins)"), "SEPUNIT": (sep, "--sep-units"),
        "BINSLOP": (float(gg.bin_slop), "TreeCorr bin_slop used"),
        "VARMETHD": (errors.method, "covariance of xi: jackknife or shot"),
        "VARASKED": (errors.asked, "--var-method asked for"),
        "NPATCH": (errors.npatch, "jackknife patches used (0: shot noise)")})
    if errors.reason:
        params["VARWHY"] = (errors.reason, "why shot noise")
    if errors.shot_bins:
        params["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "bins whose jackknife variance was 0")
    if jackknife:
        params["PATCHSRC"] = (patch_source[:68], "k-means, or the --patch-centers file")
        params["CPW"] = (settings["cross_patch_weight"], "TreeCorr cross_patch_weight")
    params.update({
        "NBOOT": (settings["nboot"], "bootstrap resamples of THETA_DE"),
        "TREECORR": (treecorr.__version__, "TreeCorr version")})
    for k, t in enumerate(stats["threshold"], 1):
        params[f"THRESH{k}"] = (float(t), "|De| threshold of STATS frac_ge")
    header = add_provenance(primary.header, step=f"correlate {sc.source}", params=params, inputs=sc.inputs,
                            seed=seed)
    if sc.pairs and not sc.inputs:
        header.add_history(f"  inputs: {len(sc.pairs)} pairs, listed with their DATASUMs in the PAIRS table")
    if sc.tables:
        header.add_history(f"  inputs: {len(sc.tables)} tables, listed with their DATASUMs in the INPUTS table")
    _comment(primary, _AXES_COMMENTS.get(sc.g_axes, _AXES_COMMENTS["as given"]))
    if not jackknife:
        _comment(primary, "Errors of xi are shot noise (VARWHY): every object independent, so too small where "
                          "De is spatially coherent; COV is diagonal.")
    elif errors.shot_bins:
        _comment(primary, "SHOTBINS: separation bins (0-based) with pairs whose jackknife variance was zero to "
                          "rounding (too few pairs per patch); their xi+ and xi- have shot-noise errors and no "
                          "covariance with other bins.")
    return primary


def _xi_hdu(sc: ShapeChanges, gg, cov_matrix, settings: dict, errors: Errors) -> OutHDU:
    """XI: :func:`xi_table` with the errors of ``cov_matrix``, and the binning in its header."""
    sep = settings["sep_units"]
    xi = _table_hdu(xi_table(gg, cov_matrix), "XI", units={"r_nom": sep, "meanr": sep, "meanlogr": f"log({sep})"})
    xh = xi.header
    xh["SEP_UNIT"] = (sep, "units of r_nom and meanr")
    xh["COORDS"] = (sc.coords, "radec (spherical) or xy (flat)")
    xh["MIN_SEP"] = (settings["min_sep"], f"[{sep}]")
    xh["MAX_SEP"] = (settings["max_sep"], f"[{sep}]")
    xh["NBINS"] = settings["nbins"]
    xh["BIN_SIZE"] = (float(gg.bin_size), "ln(max_sep/min_sep)/nbins")
    xh["BIN_SLOP"] = float(gg.bin_slop)
    xh["VAR_METH"] = (errors.method, "sigma_xip, sigma_xim: jackknife or shot")
    xh["NPATCH"] = errors.npatch
    if errors.method == "jackknife" and np.isfinite(errors.patch_size):
        # a jackknife supports separations up to the width of its patches
        xh["PATCHSIZ"] = (round(float(errors.patch_size), 6), f"[{sep}] typical width of a patch")
    if errors.shot_bins:
        xh["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "rows with shot-noise errors")
    xh["NOBJ"] = len(sc)
    return xi


def _cov_hdu(cov_matrix, settings: dict, errors: Errors) -> OutHDU:
    """COV: the covariance of xi+ then xi- over the bins."""
    cov = OutHDU([], cov_matrix, extname="COV")
    cov.header["ORDER"] = ("xip,xim", "rows/columns: xi+ of every bin, then xi-")
    cov.header["NBINS"] = settings["nbins"]
    cov.header["VAR_METH"] = errors.method
    cov.header["NPATCH"] = errors.npatch
    if errors.shot_bins:
        cov.header["SHOTBINS"] = (",".join(str(k) for k in errors.shot_bins), "bins (xi+ and xi-) with shot noise")
    return cov


def _stats_hdu(sc: ShapeChanges, stats: dict) -> OutHDU:
    """STATS: the one-point statistics of De, one row, with the counts of the objects read."""
    scols = {"n": np.array([stats["n"]])}
    for key in ("e1_mean", "e1_err", "e2_mean", "e2_err", "de1_mean", "de1_err", "de2_mean", "de2_err",
                "de_abs_mean", "de_abs_max"):
        scols[key] = np.array([stats[key]])
    scols["threshold"] = stats["threshold"][None, :]
    scols["n_ge"] = stats["n_ge"][None, :].astype(np.int64)
    scols["frac_ge"] = stats["frac_ge"][None, :]
    if "n_dabs_ge" in stats:
        scols["n_dabs_ge"] = stats["n_dabs_ge"][None, :].astype(np.int64)
        scols["frac_dabs_ge"] = stats["frac_dabs_ge"][None, :]
    if "n_clean_ge" in stats:
        scols["n_clean"] = np.array([stats["n_clean"]], dtype=np.int64)
        scols["n_clean_ge"] = stats["n_clean_ge"][None, :].astype(np.int64)
    for key in ("rows_a", "rows_b", "matched", "flagged", "nonfinite", "outside"):
        scols[key] = np.array([sc.counts.get(key, 0)], dtype=np.int64)
    stats_hdu = _table_hdu(scols, "STATS")
    _comment(stats_hdu, "e1/e2: mean g of B (the reference frame); NaN when De was given as columns. "
                        "errors: standard errors of the means; frac_ge: fraction with |De| >= threshold. "
                        "flagged: objects left out for a flag; with flagged objects kept, n_clean and n_clean_ge "
                        "count the objects whose fits carry none; outside: objects outside the field.")
    if sc.pairs:
        stats_hdu.header["NPAIRS"] = (len(sc.pairs), "pairs pooled: counts are sums over them")
        _comment(stats_hdu, "pooled pairs: an object measured in several pairs counts once per pair.")
    return stats_hdu


def _hist_hdu(hist: dict) -> OutHDU:
    """HIST_DE: the |De| histogram."""
    hist_hdu = _table_hdu(hist, "HIST_DE")
    _comment(hist_hdu, "|De| histogram: log bins; first row [0, lo) underflow, last [hi, inf) overflow.")
    return hist_hdu


def _theta_hdu(theta: dict, settings: dict) -> OutHDU:
    """THETA_DE: the distribution of De's position angle per |De| bin, and its test against uniform."""
    tcols = {k: v for k, v in theta.items() if k not in ("ngroups", "p_method")}
    theta_hdu = _table_hdu(tcols, "THETA_DE", units={"theta_lo": "deg", "theta_hi": "deg"})
    th = theta_hdu.header
    th["NANGLE"] = (N_ANGLE, "position-angle bins per |De| bin")
    th["NDOF"] = (N_ANGLE - 1, "degrees of freedom of chi2_uniform")
    th["NBOOT"] = (settings["nboot"], "bootstrap resamples (frac_err)")
    th["NULLSIMS"] = (NULL_DRAWS, "simulations under uniform for p_uniform (null-sim)")
    th["MINEXPEC"] = (MIN_EXPECTED, "chi2 p-value when n_eff/NANGLE >= this")
    for k, (g, method) in enumerate(zip(theta["ngroups"], theta["p_method"]), 1):
        th[f"NGROUP{k}"] = (int(g), f"groups resampled in |De| bin {k}")
        th[f"PMETHOD{k}"] = (method or "none", f"p_uniform of |De| bin {k}: chi2 or null-sim")
    _comment(theta_hdu, "frac: |De|-weighted fraction of the |De| bin with position angle in the bin; angle "
                        "0.5 atan2(De2, De1) from axis 1 towards axis 2; uniform: 1/NANGLE. frac_err: bootstrap "
                        "error of frac. The test against uniform uses the variance under uniform angles: "
                        "frac_err_null = sqrt(p(1-p)/n_eff), p = 1/NANGLE, n_eff = (sum |De|)^2 / sum |De|^2; "
                        "chi2_uniform = n_eff sum (frac - p)^2 / p with dof_uniform = NANGLE - 1; p_uniform from "
                        "the chi2 distribution (PMETHODk = chi2) or, for few objects, from NULLSIMS simulations "
                        "with uniform angles (null-sim).")
    return theta_hdu


def _patches_hdu(sc: ShapeChanges, cat, jackknife: bool) -> OutHDU:
    """PATCHES: the jackknife's patch centres (none for shot-noise errors) and their objects."""
    if jackknife:
        centers = np.asarray(cat.patch_centers, dtype=np.float64)
        counts = np.bincount(cat.patch, minlength=len(centers)).astype(np.int64)
    else:
        centers = np.zeros((0, 3 if sc.coords == "radec" else 2))
        counts = np.zeros(0, dtype=np.int64)
    pcols = {"patch": np.arange(len(centers), dtype=np.int64), "x": centers[:, 0], "y": centers[:, 1]}
    if centers.shape[1] == 3:
        pcols["z"] = centers[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            pcols["ra"] = np.degrees(np.arctan2(centers[:, 1], centers[:, 0])) % 360.0
            pcols["dec"] = np.degrees(np.arcsin(np.clip(centers[:, 2] / np.linalg.norm(centers, axis=1), -1, 1)))
    pcols["nobj"] = counts
    patches = _table_hdu(pcols, "PATCHES", units={"ra": "deg", "dec": "deg"})
    patches.header["NPATCH"] = (len(centers), "patches (0: shot-noise errors, no jackknife)")
    _comment(patches, "TreeCorr's patch centres (x, y[, z]); reuse with --patch-centers THIS_FILE.")
    return patches


def _inputs_hdu(tables: list) -> OutHDU:
    """INPUTS: one row per table of De pooled, with its DATASUM and the objects it gave."""
    return table_hdu({"name": np.array([os.path.basename(r["name"]) for r in tables]),
                      "datasum": np.array([r["datasum"] for r in tables], dtype=np.int64),
                      "rows": np.array([r["rows"] for r in tables], dtype=np.int64),
                      "used": np.array([r["used"] for r in tables], dtype=np.int64)}, "INPUTS",
                     descriptions={"name": "table pooled (file[EXT])", "used": "objects pooled from it"})


def _pairs_hdu(records: list, g_axes: str):
    """PAIRS: one row per pooled pair, its files with their DATASUMs and what it contributed."""
    cols = {"pair": np.arange(1, len(records) + 1, dtype=np.int64),
            "a": np.array([os.path.basename(r["a"]) if r["a"] != "-" else "stdin" for r in records]),
            "b": np.array([os.path.basename(r["b"]) if r["b"] != "-" else "stdin" for r in records]),
            "a_datasum": np.array([r["a_datasum"] for r in records], dtype=np.int64),
            "b_datasum": np.array([r["b_datasum"] for r in records], dtype=np.int64)}
    for key in ("rows_a", "rows_b", "matched", "flagged", "nonfinite", "used"):
        cols[key] = np.array([r[key] for r in records], dtype=np.int64)
    for key in ("de1_mean", "de2_mean", "de_abs_mean", "de_abs_max"):
        cols[key] = np.array([r[key] for r in records], dtype=np.float64)
    descriptions = {"pair": "1-based, as listed", "a": "SHAPES table with persistence", "b": "reference",
                    "used": "objects pooled from this pair"}

    hdu = table_hdu(cols, "PAIRS", descriptions=descriptions)
    hdu.header["NPAIRS"] = (len(records), "pairs pooled")
    hdu.header["GFRAME"] = (g_axes, "axes of g in every pair")
    _comment(hdu, "used = 0: the pair had no usable object (a table without rows, or every match flagged); "
                  "its means are NaN.")
    return hdu
