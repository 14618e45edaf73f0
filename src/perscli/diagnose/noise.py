"""What diagnose's likelihood leaves out: pixels whose noise is shared, and significances in sigma.

The likelihood (:mod:`perscli.diagnose.likelihood`) takes pixels as
independent.  Interpixel capacitance spreads the charge noise of a pixel to
its neighbours and correlated read noise moves whole rows and columns, so a
candidate's improvement of -2 ln L is divided by its :func:`dispersion` (a
quasi-likelihood correction) before the search (:mod:`perscli.diagnose.search`)
and the checks (:mod:`perscli.diagnose.checks`) compare it with their
thresholds; :func:`significance` turns an improvement into sigma for both.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage, signal as sps
from scipy.special import gammaln, ndtri_exp
from scipy.stats import chi2


def significance(delta_chi2: float, dof: int = 1) -> float:
    """The significance of a likelihood-ratio improvement, as a two-sided Gaussian number of sigma."""
    if not delta_chi2 > 0:
        return 0.0
    if dof == 1:
        return math.sqrt(delta_chi2)       # exact, and no underflow for the strong effects
    # on the log scale: p underflows beyond ~37 sigma, its logarithm does not
    log_p = float(chi2.logsf(delta_chi2, dof))
    if not math.isfinite(log_p):
        # scipy's logsf underflows too: the upper incomplete gamma's asymptotic series, Q(a, h) ~
        # h^(a-1) e^-h / Gamma(a) (1 + (a-1)/h + (a-1)(a-2)/h^2), h = delta/2 >> a = dof/2
        a, h = 0.5 * dof, 0.5 * delta_chi2
        log_p = (a - 1.0) * math.log(h) - h - float(gammaln(a)) + math.log1p((a - 1.0) / h
                                                                             + (a - 1.0) * (a - 2.0) / h ** 2)
    return float(-ndtri_exp(log_p - math.log(2.0)))


def counts_gain(problem, model, exp) -> float:
    """e- per count of the model's expectation of ``exp`` (as the problem compares it)."""
    if exp.counts != "DN":
        return 1.0
    if model is not None and model.enabled("gain"):
        return float(model.value("gain", "gain"))
    return float(exp.gain or 1.0)


def noise_correlation(problem, model):
    """How the model's noise is shared between pixels: (normalised IPC kernel or None, per piece the share of
    each pixel's variance that interpixel capacitance spreads, per piece the shares of row and of column read
    noise, per piece its exposure), or None when nothing is shared.

    Noise that exists before the charge is read (Poisson, dark, persistence)
    passes through the IPC kernel K, so two pixels a lag apart share
    ``v_pre * (K * K)(lag)``; read noise and rounding come after it and are
    not spread; correlated read noise is shared by every pixel of a row (its
    row part) or of a column (its column part) of one exposure.  The
    likelihood takes pixels as independent; :func:`dispersion` uses this to
    correct its improvements.
    """
    ipc = model.enabled("ipc")
    row = float(model.value("correlated_read_noise", "row", off=0.0)) ** 2
    col = float(model.value("correlated_read_noise", "column", off=0.0)) ** 2
    if not hasattr(problem, "stripes") or not (ipc or row or col):
        return None
    auto = None
    if ipc:
        k = model.get("ipc").instance().kernel()
        auto = sps.correlate2d(k, k, mode="full")           # 5 x 5: lags up to 2
        auto = auto / auto[2, 2]
    read = float(model.value("read_noise", "sigma", off=0.0)) ** 2 + row + col
    quant = 1.0 / 12.0 if model.enabled("quantize") else 0.0
    ev = problem.evaluate(model)
    shares, lines, which = [], [], []
    for (i, _), v, mask in zip(ev.pieces, ev.variance, ev.mask):
        g = counts_gain(problem, model, problem.exposures[i])
        post = read / g ** 2 + quant
        vv = np.where(mask, v, np.inf)
        shares.append(np.where(mask, np.clip((v - post) / v, 0.0, 1.0), 0.0) if ipc else None)
        lines.append((np.where(mask, row / g ** 2 / vv, 0.0), np.where(mask, col / g ** 2 / vv, 0.0)))
        which.append(i)
    return auto, shares, lines, which


def dispersion(shared, base, after) -> float:
    """How much more the residuals vary along the change from ``base`` to ``after`` (the candidate's
    direction ``a``) than independent pixels would: a' C a / a'a, C the noise correlation ``shared``
    (:func:`noise_correlation`) gives.

    A candidate's likelihood-ratio improvement is divided by it and its
    squared error multiplied (a quasi-likelihood correction): ~1.1 for smooth
    directions in Roman frames, whose charge noise neighbours share; much more
    for a level (dark, offset) when row and column read noise move whole lines.
    """
    if shared is None:
        return 1.0
    auto, shares, lines, which = shared
    num = den = 0.0
    columns = {}
    for m0, v0, m1, mask, f, (rs, cs), i in zip(base.mean, base.variance, after.mean, base.mask, shares, lines,
                                                 which):
        a = np.where(mask, (m1 - m0) / np.sqrt(v0), 0.0)
        if auto is not None:
            b = a * np.sqrt(f)
            num += float(np.sum(a * a * (1.0 - f)) + np.sum(b * ndimage.correlate(b, auto, mode="constant")))
        else:
            num += float(np.sum(a * a))
        den += float(np.sum(a * a))
        if a.ndim == 2:
            # a row's read noise is one value for the whole row: its pixels' residuals move together
            r = a * np.sqrt(rs)
            num += float(np.sum(np.sum(r, axis=1) ** 2) - np.sum(r * r))
            c = a * np.sqrt(cs)
            columns.setdefault(i, [np.zeros(a.shape[1]), 0.0])
            columns[i][0] += np.sum(c, axis=0)
            columns[i][1] += float(np.sum(c * c))
    for total, diagonal in columns.values():
        # a column's spans every piece of its exposure
        num += float(np.sum(total ** 2) - diagonal)
    return min(max(num / den, 0.5), 50.0) if den > 0 else 1.0
