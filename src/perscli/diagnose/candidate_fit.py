"""One candidate fitted beside the effects named so far: the threshold it must pass, its fit, its checks.

:func:`fit_candidate` fits one candidate's parameter (a Newton step when the
likelihood is quadratic over it, a scan and Brent's method when it is not)
with the model of its round held; :func:`threshold` is the improvement of
-2 ln L a name needs; :func:`_unphysical` says why a fitted value cannot be
named.  A named persistence frees its law's shape
(:func:`_free_persistence_shape`).  The search over rounds, pairs and sets
that uses them is :mod:`perscli.diagnose.search`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2

from .candidates import Candidate, by_name
from .joint import directions, joint_fit
from .likelihood import with_effect
from .noise import significance

log = logging.getLogger(__name__)

#: a named effect improves -2 ln L by at least this much: a likelihood-ratio test with a false-alarm
#: probability of 1e-3 per candidate for one parameter (chi^2 with one degree of freedom; 3.29 sigma).  It is
#: set by the two rates a detector team needs: an effect whose expected significance is 5 sigma passes it in
#: 96% of data sets (sqrt(10.83) = 3.29 = 5 - 1.71), and with ten candidates, several of them correlated, a
#: data set without any missing effect names one in fewer than 1%.  Both are measured by
#: tests/test_diagnose_calibrated.py on frames made by an independent detector chain.
MIN_DELTA_CHI2 = 10.83


def threshold(nparams: int = 1) -> float:
    """The improvement of -2 ln L a candidate with ``nparams`` free parameters needs: the same p-value
    (1e-3) as :data:`MIN_DELTA_CHI2` for one."""
    if nparams <= 1:
        return MIN_DELTA_CHI2
    return float(chi2.isf(chi2.sf(MIN_DELTA_CHI2, 1), nparams))


#: an effect on the signal must owe at least this share of its improvement to the expectation
MEAN_SHARE = 0.5
#: candidates within this much of the best one's improvement are reported as indistinguishable from it
MIN_DELTA_BIC = 10.0


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
    nparams: int = 1
    #: added to the threshold: the forward model's fidelity beside the strong effects named (see FIDELITY)
    floor: float = 0.0

    @property
    def significant(self) -> bool:
        return self.delta_chi2 > threshold(self.nparams) + self.floor

    def as_dict(self) -> dict:
        params = {self.candidate.param: self.value, **getattr(self, "extra", {})}
        errors = {self.candidate.param: self.error, **getattr(self, "extra_errors", {})}
        return {"effect": self.candidate.name, "params": params, "errors": errors, "model_value": self.start,
                "unit": self.candidate.unit, "delta_chi2": self.delta_chi2, "delta_bic": self.delta_bic,
                "significance_sigma": significance(self.delta_chi2, self.nparams), "significant": self.significant,
                "threshold_delta_chi2": threshold(self.nparams), "free_parameters": self.nparams, "note": self.note,
                **({"shape": self.shape} if getattr(self, "shape", None) else {})}


#: a Newton step is taken as the fit when the improvement it makes agrees with the quadratic prediction to
#: this share (plus :data:`NEWTON_SLACK`): the likelihood is then quadratic over the step, and its maximum is
#: where the step lands
NEWTON_AGREE = 0.02
NEWTON_SLACK = 0.05


def fit_candidate(problem, model, candidate: Candidate, m2lnl_base: float, npix: int, direction=None) -> Fit:
    """The candidate's parameter that minimises -2 ln L with everything else in ``model`` held.

    ``direction``: (score, Fisher information) of the candidate at ``model``
    (:func:`perscli.diagnose.joint.directions`).  One Newton step from the
    model's value is then tried first: when the improvement it makes agrees
    with the quadratic prediction ``g^2 / F`` (within :data:`NEWTON_AGREE`),
    its end is the fit and ``1 / sqrt(F)`` its error, at the cost of one
    evaluation.  Otherwise (a value far from the model's: a gain 40% off, a
    read noise 50% off) a coarse scan of the range and Brent's method find
    it.  ``fit.evaluation`` holds the evaluation at the value fitted when
    one was made.
    """
    start = candidate.get(model, problem.exposures)
    if candidate.fit is None and direction is not None:
        g, f = direction
        lo, hi = candidate.bounds
        if f > 0 and math.isfinite(g):
            value = min(max(start + g / f, lo), hi)
            predicted = g * (value - start) - 0.5 * f * (value - start) ** 2
            try:
                trial = candidate.put(model, value)
                ev = problem.evaluate(trial)
                m2 = ev.m2lnl()
            except (ValueError, FloatingPointError, ZeroDivisionError):
                m2 = math.inf
            gained = m2lnl_base - m2
            if math.isfinite(m2) and lo < value < hi and \
                    abs(gained - 2.0 * predicted) <= NEWTON_AGREE * abs(2.0 * predicted) + NEWTON_SLACK:
                fit = Fit(candidate, float(value), float(1.0 / math.sqrt(f)), start, m2)
                fit.delta_chi2 = gained
                fit.delta_bic = gained - math.log(max(npix, 2))
                fit.model = trial
                fit.evaluation = ev
                return fit
    if candidate.fit is not None:
        value, error, fitted, nparams, *more = candidate.fit(problem, model)
        more = more[0] if more else {}
        m2 = problem.evaluate(fitted).m2lnl()
        fit = Fit(candidate, float(value), float(error), start, m2, nparams=int(nparams))
        fit.delta_chi2 = float(more.get("delta_chi2", m2lnl_base - m2))
        fit.delta_bic = fit.delta_chi2 - nparams * math.log(max(npix, 2))
        fit.model = fitted
        if "extra" in more:
            fit.extra, fit.extra_errors = dict(more["extra"]), dict(more.get("extra_errors", {}))
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
    at_bound = grid[k] in (lo, hi)
    if at_bound:
        # the best grid point is a bound of the range: when the cost rises a step inside it, the minimum is
        # the bound itself (a value never named: see _unphysical), and Brent's method would only creep
        # towards it in some 25 golden-section steps
        inside = grid[k] + (tol * 10 if grid[k] == lo else -tol * 10)
        at_bound = lo < inside < hi and cost(inside) >= values[k]
    if at_bound:
        best = float(grid[k])
    elif b > a:
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


def _free_persistence_shape(problem, best: Fit, npix: int, progress=None) -> Fit:
    """Free gamma, x0, dx or alpha of a named persistence, one at a time, while the BIC supports it.

    The law's A and the parameters freed so far are the nuisance: the
    score test of the quadratic likelihood (:mod:`perscli.diagnose.joint`:
    the improvement ``g' F^-1 g`` predicts with the parameter freed, less
    that without) ranks the shape parameters; the best is fitted jointly
    with A and the freed ones (Fisher scoring) only when the prediction
    reaches :data:`SHAPE_SCREEN` of what the BIC asks, and kept when its
    exact improvement of -2 ln L exceeds ln n + :data:`MIN_DELTA_BIC`, its
    value is inside its range and x0 is below the full well.  Then the next.
    """
    need = math.log(max(npix, 2)) + MIN_DELTA_BIC
    amp = by_name("persistence")
    shapes = {name: _shape_candidate(name) for name, _, _ in PERSISTENCE_SHAPE}
    model, m2 = best.model, best.m2lnl
    start_m2 = m2
    freed = []
    well = model.value("saturation", "full_well", off=None)
    while len(freed) < len(shapes):
        cands = [amp] + [shapes[n] for n in freed]
        rest = [n for n in shapes if n not in freed]
        dirs = directions(problem, model, cands + [shapes[n] for n in rest])
        g, f = dirs.score, dirs.fisher

        def explained(idx):
            return float(g[idx] @ np.linalg.lstsq(f[np.ix_(idx, idx)], g[idx], rcond=1e-12)[0])

        base_idx = list(range(len(cands)))
        worth = {n: explained(base_idx + [len(cands) + k]) - explained(base_idx) for k, n in enumerate(rest)}
        if progress is not None:
            progress("persistence: freeing the law's shape would gain about "
                     + ", ".join(f"{n} {worth[n]:.3g}" for n in rest) + " in -2 ln L (score test)")
        name = max(rest, key=lambda n: worth[n])
        if not worth[name] >= SHAPE_SCREEN * need:
            break
        trial, values, cov, m2_trial = joint_fit(problem, model, cands + [shapes[name]])
        value = float(values[-1])
        lo, hi = shapes[name].bounds
        edge = shapes[name].scale * 1e-3
        if (m2 - m2_trial <= need or min(value - lo, hi - value) <= edge
                or (name == "x0" and well and value > well)):
            break
        if progress is not None:
            progress(f"persistence: {name} freed ({value:.4g}), -2 ln L down by {m2 - m2_trial:.1f}")
        freed.append(name)
        model, m2 = trial, m2_trial
        best.value, best.error = float(values[0]), float(math.sqrt(max(cov[0, 0], 0.0)))
        best.extra = {n: float(values[1 + k]) for k, n in enumerate(freed)}
        best.extra_errors = {n: float(math.sqrt(max(cov[1 + k, 1 + k], 0.0))) for k, n in enumerate(freed)}
    if freed:
        best.model, best.m2lnl = model, m2
        best.delta_chi2 += start_m2 - m2
        best.delta_bic += start_m2 - m2 - len(freed) * math.log(max(npix, 2))
        best.nparams = 1 + len(freed)
    return best


#: shape parameters of the Fermi law that a persistence fit may free: (name, bounds, typical size)
PERSISTENCE_SHAPE = (("gamma", (0.3, 3.0), 0.05), ("x0", (1.0e4, 3.0e5), 2.0e3), ("dx", (5.0e3, 2.0e5), 2.0e3),
                     ("alpha", (-0.5, 1.0), 0.01))
#: a shape parameter is fitted only when the score test predicts at least this share of the improvement the
#: BIC asks of it (a generous margin: the prediction is local, the fit is not)
SHAPE_SCREEN = 0.25


def _unphysical(fit: Fit, problem, ramp: bool) -> str:
    """Why a fitted value cannot be a detector's (empty when it can)."""
    name = fit.candidate.name
    lo, hi = fit.candidate.bounds
    edge = fit.candidate.scale * 1e-3
    if fit.candidate.fit is None and min(fit.value - lo, hi - fit.value) <= edge:
        return "at the edge of its range"
    if name == "ipc":
        kernel = np.asarray(fit.model.value("ipc", "kernel"), dtype=float) if fit.model is not None else None
        if fit.value < 0 or (kernel is not None and kernel.ndim == 2 and np.any(kernel[[0, 1, 1, 2], [1, 0, 2, 1]]
                                                                                 < -3 * max(fit.error, 1e-6))):
            return "a negative interpixel coupling"
        if kernel is not None and kernel.ndim == 2:
            # couplings to opposite neighbours differ by ~10% in real detectors (Roman's: 12%); a kernel
            # lopsided by more than half its mean moves light, as a shifted PSF does
            for a, b in ((kernel[1, 0], kernel[1, 2]), (kernel[0, 1], kernel[2, 1])):
                if abs(a - b) > 0.5 * abs(a + b) / 2.0 + 3.0 * max(fit.error, 1e-6) * 2.0:
                    return "a lopsided interpixel coupling (it would move the light: a shift, not IPC)"
    if name == "persistence":
        extra = getattr(fit, "extra", {})
        if extra.get("x0", 0.0) > 1.0e5:
            return "x0 above the full well"
    if name == "gain" and ramp:
        header = [e.gain for e in problem.exposures if e.counts == "DN" and e.gain]
        ptc = getattr(problem, "ptc_gain", None)
        if header and abs(fit.value / header[0] - 1.0) > 0.05:
            if ptc is None:
                return "far from the header's gain with no photon-transfer case in the data to support it"
            g, err = ptc
            if abs(fit.value - g) > 3 * err + 0.05 * g:
                return f"not the photon-transfer gain of the data ({g:.3g} +- {err:.2g})"
    return ""


#: the forward model's fidelity, as a share of the improvement of -2 ln L the named effects bring: what it
#: propagates to first order (the variance through nonlinearity and IPC, the Poisson noise of a dark current
#: before nonlinearity) leaves about this much of a strong effect's improvement for other candidates to take
#: (measured: a dark current of 0.4 e-/s improving -2 ln L by 1.05e6 on perscli's own renders leaves 50 that
#: an offset and read noise describe better; nonlinearity at 186 sigma on a full SCA left a read noise at
#: 3.4 sigma).  It is added to the threshold: beside an effect at 1000 sigma a candidate needs 100 more,
#: beside one at 50 sigma 0.25 more.
FIDELITY = 1e-4

#: candidates that act on the signal: named only when the expectation, not the noise alone, improves
MEAN_EFFECTS = ("persistence", "ipc", "nonlinearity", "reciprocity", "dark", "offset", "gain", "brighter_fatter")


def _mean_only_delta(problem, base, fitted_model, after=None) -> float:
    """-2 ln L improvement of the fitted model's expectation with the base model's variance held."""
    after = after if after is not None else problem.evaluate(fitted_model)
    total = 0.0
    for e0, v0, d, m, e1 in zip(base.mean, base.variance, base.data, base.mask, after.mean):
        r0, r1 = d[m] - e0[m], d[m] - e1[m]
        total += float(np.sum((r0 * r0 - r1 * r1) / v0[m]))
    return total


def _reset(model, original, name: str):
    """``model`` with effect ``name`` as ``original`` has it (its parameters and switch): the effect un-named."""
    eff = original.get(name)
    if eff is None:
        return with_effect(model, name, enabled=False)
    out = with_effect(model, name, enabled=eff.enabled)
    out.get(name).params = dict(eff.params)
    return out


def _shape_candidate(name: str):
    """One parameter of the persistence law's shape as a candidate of its own (for the joint fit of a named
    persistence whose shape was freed): A is fitted beside it, not profiled."""
    bounds, scale = next((b, sc) for n, b, sc in PERSISTENCE_SHAPE if n == name)

    def get(m, exposures):
        return float(getattr(m.persistence_model(), name))

    def put(m, value):
        return with_effect(m, "persistence", {name: float(value)})

    return Candidate("persistence", name, "", bounds, scale, "history", "", get, put)
