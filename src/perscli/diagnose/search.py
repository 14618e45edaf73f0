"""Fit every candidate by likelihood, rank by delta chi^2 and delta BIC, add the significant ones in turn.

Each round fits every candidate's parameter (a bounded one-dimensional
minimisation of -2 ln L, the Gaussian likelihood with the model's own
variance, so that effects on the noise such as read noise count as much as
effects on the mean) with the effects found so far in the model.  The best
candidate is named when it improves -2 ln L by more than
:data:`MIN_DELTA_CHI2` and its BIC (``-2 ln L + k ln n``) by more than
:data:`MIN_DELTA_BIC` (strong evidence on Kass & Raftery's scale); it is then
added to the model and the next round starts.  Candidates whose improvement
is within :data:`MIN_DELTA_BIC` of the best one's are what the data cannot
tell apart: they are reported with it as one degenerate group.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from .candidates import CANDIDATES, Candidate

log = logging.getLogger(__name__)

#: a named effect improves -2 ln L by at least this much (5 sigma for one parameter) ...
MIN_DELTA_CHI2 = 25.0
#: ... and its BIC by at least this much
MIN_DELTA_BIC = 10.0
#: ... and it brings the gap at least this fraction of the way to 1
MIN_GAP_CLOSED = 0.01


def _gap(problem, model) -> float:
    """chi^2 per pixel over the fit's pixels (1 for pure noise)."""
    chi2, n = problem.evaluate(model).chi2()
    return chi2 / max(n, 1)


@dataclass
class Fit:
    """One candidate fitted with the model of its round."""

    candidate: Candidate
    value: float
    error: float
    start: float
    m2lnl: float
    delta_chi2: float = 0.0
    delta_bic: float = 0.0
    model: object = field(default=None, repr=False)
    note: str = ""

    @property
    def significant(self) -> bool:
        return self.delta_chi2 > MIN_DELTA_CHI2 and self.delta_bic > MIN_DELTA_BIC

    def as_dict(self) -> dict:
        params = {self.candidate.param: self.value, **getattr(self, "extra", {})}
        errors = {self.candidate.param: self.error, **getattr(self, "extra_errors", {})}
        return {"effect": self.candidate.name, "params": params, "errors": errors, "model_value": self.start,
                "unit": self.candidate.unit, "delta_chi2": self.delta_chi2, "delta_bic": self.delta_bic,
                "significant": self.significant, "note": self.note}


def fit_candidate(problem, model, candidate: Candidate, m2lnl_base: float, npix: int) -> Fit:
    """The candidate's parameter that minimises -2 ln L with everything else in ``model`` held."""
    from scipy.optimize import minimize_scalar

    start = candidate.get(model, problem.exposures)
    if candidate.fit is not None:
        value, error, fitted, nparams = candidate.fit(problem, model)
        m2 = problem.evaluate(fitted).m2lnl()
        fit = Fit(candidate, float(value), float(error), start, m2)
        fit.delta_chi2 = m2lnl_base - m2
        fit.delta_bic = fit.delta_chi2 - nparams * math.log(max(npix, 2))
        fit.model = fitted
        return fit
    lo, hi = candidate.bounds
    cache = {}

    def cost(value):
        value = float(value)
        if value not in cache:
            try:
                cache[value] = problem.evaluate(candidate.put(model, value)).m2lnl()
            except (ValueError, FloatingPointError, ZeroDivisionError):
                cache[value] = math.inf
        return cache[value]

    # a coarse scan first (the cost need not be unimodal over the whole range: gain and offset are
    # wide), then Brent's method in the best bracket
    grid = np.unique(np.concatenate([np.linspace(lo, hi, 9), [min(max(start, lo), hi)],
                                     np.clip(start + candidate.scale * np.array([-2.0, 2.0]), lo, hi)]))
    values = [cost(g) for g in grid]
    k = int(np.argmin(values))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    tol = candidate.scale * 1e-4
    if b > a:
        res = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": tol, "maxiter": 60})
        best = float(res.x) if res.fun <= values[k] else float(grid[k])
    else:
        best = float(grid[k])
    m2 = cost(best)
    error = _curvature_error(cost, best, max(abs(best) * 0.01, candidate.scale * 0.01), lo, hi)
    fit = Fit(candidate, best, error, start, m2)
    fit.delta_chi2 = m2lnl_base - m2
    fit.delta_bic = fit.delta_chi2 - math.log(max(npix, 2))
    fit.model = candidate.put(model, best)
    return fit


def _curvature_error(cost, x, h, lo, hi) -> float:
    """1 sigma from the curvature of -2 ln L (which rises by 1 at 1 sigma)."""
    a, b = max(lo, x - h), min(hi, x + h)
    if not b > a:
        return float("nan")
    fa, fx, fb = cost(a), cost(x), cost(b)
    # second derivative on a possibly uneven stencil
    d2 = 2.0 * ((fb - fx) / (b - x) - (fx - fa) / (x - a)) / (b - a) if x > a and b > x else float("nan")
    return float(math.sqrt(2.0 / d2)) if d2 > 0 else float("nan")


#: shape parameters of the Fermi law that a persistence fit may free: (name, bounds, typical size)
PERSISTENCE_SHAPE = (("gamma", (0.3, 3.0), 0.05), ("x0", (1.0e4, 3.0e5), 2.0e3), ("dx", (5.0e3, 2.0e5), 2.0e3),
                     ("alpha", (-0.5, 1.0), 0.01))


def _free_persistence_shape(problem, best: Fit, npix: int, progress=None) -> Fit:
    """Free gamma, x0, dx and alpha of a named persistence one at a time (A re-fitted with each), keeping
    each only when the BIC supports it (its -2 ln L improves by more than ln n + MIN_DELTA_BIC)."""
    from .candidates import Candidate, _get_persistence, _put_persistence
    from .likelihood import with_effect

    model, m2 = best.model, best.m2lnl
    start_m2 = m2
    extra, errors = {}, {}
    amp = Candidate("persistence", "A", "e-/s", (0.0, 2.0), 0.02, "history", "", _get_persistence,
                    _put_persistence)
    for name, bounds, scale in PERSISTENCE_SHAPE:
        def get(m, exposures, name=name):
            return float(getattr(m.persistence_model(), name))

        def put(m, value, name=name):
            # the profile likelihood: A (strongly correlated with the shape) re-fitted at every value
            return fit_candidate(problem, with_effect(m, "persistence", {name: float(value)}), amp, 0.0, npix).model

        free = Candidate(f"persistence.{name}", name, "", bounds, scale, "history", "", get, put)
        trial = fit_candidate(problem, model, free, m2, npix)
        refit = fit_candidate(problem, trial.model, amp, m2, npix)
        if m2 - refit.m2lnl > math.log(max(npix, 2)) + MIN_DELTA_BIC:
            if progress is not None:
                progress(f"persistence: {name} freed ({trial.value:.4g}), -2 ln L down by {m2 - refit.m2lnl:.1f}")
            model, m2 = refit.model, refit.m2lnl
            extra[name], errors[name] = trial.value, trial.error
            best.value, best.error = refit.value, refit.error
    if extra:
        best.model, best.m2lnl = model, m2
        best.delta_chi2 += start_m2 - m2
        best.delta_bic += start_m2 - m2 - len(extra) * math.log(max(npix, 2))
        best.extra, best.extra_errors = extra, errors
    return best


@dataclass
class Result:
    """What the search found."""

    found: list                  # dicts: effect, params, errors, delta_chi2, delta_bic, degenerate_with
    candidates: list             # every candidate's fit in the first round (and later ones)
    model: object                # the model with the found effects
    rounds: list


def search(problem, model, *, candidates=CANDIDATES, progress=None, max_rounds: int = 8) -> Result:
    """Add significant effects to ``model`` one at a time until no candidate improves it significantly."""
    exposures = problem.exposures
    usable = [c for c in candidates if c.applies(exposures) and problem.allows(c.name)]
    found, rounds, first = [], [], None
    current = model
    remaining = list(usable)
    for round_no in range(max_rounds):
        evaluation = problem.evaluate(current)
        base = evaluation.m2lnl()
        _, npix = evaluation.chi2()
        fits = []
        for k, cand in enumerate(remaining, 1):
            fits.append(fit_candidate(problem, current, cand, base, npix))
            if progress is not None:
                progress(f"round {round_no + 1}: {cand.name} {cand.param}={fits[-1].value:.6g} "
                         f"delta chi2 {fits[-1].delta_chi2:.1f}")
        fits.sort(key=lambda f: -f.delta_chi2)
        rounds.append([f.as_dict() for f in fits])
        if first is None:
            first = fits
        significant = [f for f in fits if f.significant]
        best = None
        gap_now = _gap(problem, current)
        for f in significant:
            # a value pinned at the edge of its range measures nothing, and an effect that does not bring
            # the gap (chi^2 per pixel) closer to 1 explains nothing: neither is named
            lo, hi = f.candidate.bounds
            edge = f.candidate.scale * 1e-3      # well inside the fit's own tolerance of the bound
            at_bound = f.candidate.fit is None and min(f.value - lo, hi - f.value) <= edge
            gap_with = _gap(problem, f.model)
            closes = abs(gap_now - 1.0) - abs(gap_with - 1.0) >= MIN_GAP_CLOSED * abs(gap_now - 1.0)
            f.note = "at the edge of its range" if at_bound else ("does not close the gap" if not closes else "")
            if not at_bound and closes:
                best = f
                break
        rounds[-1] = [f.as_dict() for f in fits]
        if best is None:
            break
        group = [f for f in significant if f is not best and not f.note
                 and best.delta_chi2 - f.delta_chi2 < MIN_DELTA_BIC]
        if best.candidate.name == "persistence":
            best = _free_persistence_shape(problem, best, npix, progress)
        entry = best.as_dict()
        entry["degenerate_with"] = [f.candidate.name for f in group]
        entry["round"] = round_no + 1
        found.append(entry)
        current = best.model
        taken = {best.candidate.name, *entry["degenerate_with"]}
        remaining = [c for c in remaining if c.name not in taken]
        if not remaining:
            break
    return Result(found=found, candidates=rounds[0] if rounds else [], model=current, rounds=rounds)
