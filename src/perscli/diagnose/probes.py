"""Residual probes: normalised residuals against the covariates that separate detector effects.

Each probe bins ``r = (data - expectation) / sqrt(variance)`` against one
covariate and tests the bin means against zero (chi^2 with one degree of
freedom per bin); a probe *flags* a disagreement when that chi^2 has a
p-value below :data:`FLAG_P`.  Two probes are single numbers: the mean
residual (an offset) and the excess variance ``<r^2> - 1`` (noise the model
lacks).  Each probe also selects the pixels it is about (the brightest, the
ones beside bright pixels, the ones with a bright history) so that the gap
can be reported where an effect acts, not only over the whole frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..stats.de_stats import chi2_sf

#: a probe flags a disagreement below this p-value
FLAG_P = 1e-4

PROBES = {
    "signal": "the pixel's own expected signal",
    "neighbours": "its neighbours' signal minus its own (the 4 nearest)",
    "history": "the largest fluence of an earlier exposure at the pixel (electrons)",
    "time_since": "seconds since the end of the previous exposure",
    "exposure_time": "the exposure time",
    "read_time": "time within the ramp (seconds from the first read)",
    "position": "position on the detector (8 x 8 blocks)",
    "offset": "mean residual over all pixels",
    "excess_variance": "<r^2> - 1 over all pixels",
}


@dataclass
class Probe:
    """One probe's binned residuals."""

    name: str
    centres: np.ndarray
    means: np.ndarray
    errors: np.ndarray
    counts: np.ndarray
    chi2: float
    dof: int
    gap: float = float("nan")          # chi^2 / n of the residuals in the probe's own selection
    xlabel: str = ""
    log_x: bool = False
    symlog_x: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def p_value(self) -> float:
        return chi2_sf(self.chi2, int(max(self.dof, 1))) if self.dof else 1.0

    @property
    def flagged(self) -> bool:
        return self.dof > 0 and self.p_value < FLAG_P

    def as_dict(self) -> dict:
        return {"name": self.name, "covariate": PROBES[self.name], "chi2": self.chi2, "dof": self.dof,
                "p_value": self.p_value, "flagged": self.flagged, "gap": self.gap,
                "bins": [{"x": float(c), "mean_r": float(m), "error": float(e), "n": int(n)}
                         for c, m, e, n in zip(self.centres, self.means, self.errors, self.counts)]}


def _binned(name, x, r, *, nbins=12, log_x=False, edges=None, xlabel=""):
    ok = np.isfinite(x) & np.isfinite(r)
    x, r = x[ok], r[ok]
    if x.size < 10:
        return Probe(name, np.array([]), np.array([]), np.array([]), np.array([]), 0.0, 0, xlabel=xlabel)
    if edges is None and log_x and x.min() > 0:
        # logarithmic bins from the 1st percentile up: bright pixels are few but carry most effects
        lo, hi = float(np.quantile(x, 0.01)), float(x.max())
        edges = np.geomspace(lo, hi * (1 + 1e-9), nbins + 1) if hi > lo else np.array([lo, hi + 1e-9])
        edges[0] = x.min()
    elif edges is None:
        qs = np.unique(np.quantile(x, np.linspace(0, 1, nbins + 1)))
        edges = qs if len(qs) > 1 else np.array([x.min(), x.max() + 1e-9])
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(idx, minlength=len(edges) - 1).astype(float)
    sums = np.bincount(idx, weights=r, minlength=len(edges) - 1)
    sq = np.bincount(idx, weights=r * r, minlength=len(edges) - 1)
    xs = np.bincount(idx, weights=x, minlength=len(edges) - 1)
    good = counts > 1
    means = np.where(good, sums / np.maximum(counts, 1), np.nan)
    var = np.where(good, sq / np.maximum(counts, 1) - means ** 2, np.nan)
    # the error of a bin mean from the residuals' own scatter (at least that of unit-variance noise)
    errors = np.where(good, np.sqrt(np.maximum(var, 1.0) / np.maximum(counts, 1)), np.nan)
    centres = np.where(good, xs / np.maximum(counts, 1), np.nan)
    chi2 = float(np.nansum((means[good] / errors[good]) ** 2))
    return Probe(name, centres[good], means[good], errors[good], counts[good], chi2, int(good.sum()),
                 xlabel=xlabel, log_x=log_x)


def _neighbours(img):
    out = np.zeros_like(img)
    out[1:] += img[:-1]
    out[:-1] += img[1:]
    out[:, 1:] += img[:, :-1]
    out[:, :-1] += img[:, 1:]
    return out - 4.0 * img


def _gap(r, select=None):
    r = r if select is None else r[select]
    r = r[np.isfinite(r)]
    return float(np.mean(r * r)) if r.size else float("nan")


def _signed_log_edges(x, nbins: int = 12, core: float = 1.0):
    """Bin edges for a covariate of either sign piled up near zero: one bin for |x| < ``core`` and
    logarithmic bins out to the extremes on each side."""
    x = x[np.isfinite(x)]
    half = max(nbins // 2 - 1, 1)
    edges = [-core, core]
    neg, pos = -x[x < -core], x[x > core]
    if neg.size:
        edges = list(-np.geomspace(core, neg.max() * (1 + 1e-9), half + 1)[::-1]) + edges[1:]
    if pos.size:
        edges = edges[:-1] + list(np.geomspace(core, pos.max() * (1 + 1e-9), half + 1))
    if not neg.size:
        edges = [min(float(x.min()), -core) - 1e-9] + edges
    if not pos.size:
        edges = edges + [max(float(x.max()), core) + 1e-9]
    return np.unique(np.asarray(edges, dtype=float))


def run_probes(problem, evaluation, reference=None) -> dict:
    """Every probe that the data allow, on the pixels of ``evaluation``.

    Parameters
    ----------
    problem : Problem or RampProblem
        Its ``covariates(evaluation)`` gives per-plane covariate arrays.
    evaluation : perscli.diagnose.likelihood.Evaluation
        On the fit stripes (a few per exposure): the probes bin those pixels.
    reference : Evaluation, optional
        Take the covariates (and so the bins) from this evaluation instead:
        the probes of a model before and after a fit then share their x.
    """
    res = evaluation.residuals()
    cov = problem.covariates(reference if reference is not None else evaluation)
    r = np.concatenate([x.ravel() for x in res])
    out = {}
    counts = getattr(problem.exposures[0], "counts", "DN")
    unit = "DN" if counts == "DN" else "e-"

    def cat(key):
        return np.concatenate([c[key].ravel() for c in cov]) if all(key in c for c in cov) else None

    signal = cat("signal")
    if signal is not None:
        positive = signal > 0
        p = _binned("signal", np.where(positive, signal, np.nan), r, log_x=True,
                    xlabel=f"expected signal ({unit})")
        top = signal >= np.nanquantile(signal, 0.9)
        p.gap = _gap(r, top)
        out["signal"] = p
    neigh = cat("neighbours")
    if neigh is not None:
        # most pixels see sky, whose neighbours match it: one bin around zero, logarithmic bins beyond
        p = _binned("neighbours", neigh, r, edges=_signed_log_edges(neigh),
                    xlabel=f"neighbours' signal - 4 x own ({unit})")
        p.symlog_x = True
        strong = np.abs(neigh) >= np.nanquantile(np.abs(neigh), 0.95)
        p.gap = _gap(r, strong)
        out["neighbours"] = p
    hist = cat("history")
    if hist is not None and np.nanmax(hist) > 0:
        some = hist > 0
        p = _binned("history", np.where(some, hist, np.nan), r, log_x=True, xlabel="earlier fluence (e-)")
        # the gap where the history is bright; where no pixel is, where there is any
        p.gap = _gap(r, hist > 1e3) if np.any(hist > 1e3) else _gap(r, some)
        out["history"] = p
    for key, label in (("time_since", "seconds since the previous exposure"), ("exposure_time", "exposure time (s)"),
                       ("read_time", "seconds since the first read")):
        x = cat(key)
        if x is not None and len(np.unique(x[np.isfinite(x)])) > 1:
            values = np.unique(x[np.isfinite(x)])
            edges = np.concatenate([values - 1e-6, [values[-1] + 1e-6]])
            p = _binned(key, x, r, edges=edges, xlabel=label)
            p.gap = _gap(r)
            out[key] = p
    pos = cat("position")
    if pos is not None:
        p = _binned("position", pos, r, edges=np.arange(65) - 0.5, xlabel="block (8 x 8 over the detector)")
        p.gap = _gap(r)
        out["position"] = p
    finite = r[np.isfinite(r)]
    n = finite.size
    mean = float(finite.mean()) if n else 0.0
    out["offset"] = Probe("offset", np.array([0.0]), np.array([mean]), np.array([1.0 / math.sqrt(max(n, 1))]),
                          np.array([n]), float(mean ** 2 * n), 1, gap=_gap(r))
    excess = float(np.mean(finite ** 2) - 1.0) if n else 0.0
    out["excess_variance"] = Probe("excess_variance", np.array([0.0]), np.array([excess]),
                                   np.array([math.sqrt(2.0 / max(n, 1))]), np.array([n]),
                                   float(excess ** 2 * n / 2.0), 1, gap=_gap(r))
    return out
