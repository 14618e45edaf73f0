"""Name the effects the data ask for, as a set: forward rounds, backward elimination, a search over sets, checks.

Each round fits every candidate's parameter (one-dimensional: a Newton step
when the Gaussian likelihood, with the model's own variance so that effects
on the noise such as read noise count as much as effects on the mean, is
quadratic over it; a scan and Brent's method when it is not) with the effects
named so far held, and divides its improvement of -2 ln L by the share of its
Fisher information those do not carry (:mod:`perscli.diagnose.joint`): its
improvement with them refitted.  The best candidate is named when that passes
:func:`threshold` (a likelihood-ratio test at a false-alarm probability of
1e-3 per candidate), its value is physical and inside its range, an effect on
the signal owes its improvement to the expectation and not to the noise
alone, and refitted together with the named ones (:func:`_confirm`) it still
passes; when no single candidate does, two together may (:func:`_best_pair`).
A named persistence frees its law's shape when the BIC asks for it and is
checked at once against the law's decay and fluence dependence
(:func:`perscli.diagnose.checks.persistence_law`).

Then every named effect is retested beside all the others (backward
elimination), the named set is compared with every other set of one-parameter
candidates (:func:`_best_set`: a set the rounds did not build may describe the
data better), and one joint fit gives the values, marginal errors and
correlations.  Sets within :data:`MIN_DELTA_BIC` of the best are what the data
cannot tell apart: their members are listed as degenerate.  The
misspecification checks (:mod:`perscli.diagnose.checks`) run on the final
model: what fires is unexplained, the effects it could be mistaken for are
withdrawn, and the evidence (the checks, the withdrawn fits' significance and
reason) is kept.  The rates of false and missed names are measured by
tests/test_diagnose_calibrated.py.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from .candidates import CANDIDATES, Candidate

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
    from scipy.stats import chi2

    if nparams <= 1:
        return MIN_DELTA_CHI2
    return float(chi2.isf(chi2.sf(MIN_DELTA_CHI2, 1), nparams))


#: an effect on the signal must owe at least this share of its improvement to the expectation
MEAN_SHARE = 0.5
#: candidates within this much of the best one's improvement are reported as indistinguishable from it
MIN_DELTA_BIC = 10.0


def _sigma(delta_chi2: float, dof: int = 1) -> float:
    """The significance of a likelihood-ratio improvement, as a two-sided Gaussian number of sigma."""
    from scipy.special import ndtri_exp
    from scipy.stats import chi2

    if not delta_chi2 > 0:
        return 0.0
    if dof == 1:
        return math.sqrt(delta_chi2)       # exact, and no underflow for the strong effects
    # on the log scale: p underflows beyond ~37 sigma, its logarithm does not
    log_p = float(chi2.logsf(delta_chi2, dof))
    if not math.isfinite(log_p):
        # scipy's logsf underflows too: the upper incomplete gamma's asymptotic series, Q(a, h) ~
        # h^(a-1) e^-h / Gamma(a) (1 + (a-1)/h + (a-1)(a-2)/h^2), h = delta/2 >> a = dof/2
        from scipy.special import gammaln

        a, h = 0.5 * dof, 0.5 * delta_chi2
        log_p = (a - 1.0) * math.log(h) - h - float(gammaln(a)) + math.log1p((a - 1.0) / h
                                                                             + (a - 1.0) * (a - 2.0) / h ** 2)
    return float(-ndtri_exp(log_p - math.log(2.0)))


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
                "significance_sigma": _sigma(self.delta_chi2, self.nparams), "significant": self.significant,
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
    from scipy.optimize import minimize_scalar

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
    from .candidates import by_name
    from .joint import directions, joint_fit

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
    from scipy import signal as sps

    from .checks import _counts_gain

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
        g = _counts_gain(problem, model, problem.exposures[i])
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
    from scipy import ndimage

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


def _mean_only_delta(problem, base, fitted_model, after=None) -> float:
    """-2 ln L improvement of the fitted model's expectation with the base model's variance held."""
    after = after if after is not None else problem.evaluate(fitted_model)
    total = 0.0
    for e0, v0, d, m, e1 in zip(base.mean, base.variance, base.data, base.mask, after.mean):
        r0, r1 = d[m] - e0[m], d[m] - e1[m]
        total += float(np.sum((r0 * r0 - r1 * r1) / v0[m]))
    return total


@dataclass
class Result:
    """What the search found."""

    found: list                  # dicts: effect, params, errors, delta_chi2, significance, degenerate_with, ...
    candidates: list             # every candidate's fit in the first round (and later ones)
    model: object                # the model with the found effects
    rounds: list
    checks: list = field(default_factory=list)        # the misspecification checks on the final model
    unexplained: list = field(default_factory=list)   # checks that fired, withdrawn fits: the evidence kept
    correlations: dict = field(default_factory=dict)  # between the found effects' parameters (joint fit)
    withdrawn: list = field(default_factory=list)     # effects named, then withdrawn because a check fired
    eliminated: list = field(default_factory=list)    # effects named, then not significant beside the others
    set_aside: dict = field(default_factory=dict)     # fit pixels left out: a persistence no law describes
    alternatives: list = field(default_factory=list)  # sets the data cannot tell from the one named
    hints: list = field(default_factory=list)         # candidates below the naming threshold, above HINT_P


#: a candidate whose Fisher information the named effects carry all but this share of is a combination of
#: them (a correlation above 0.99): the data cannot tell it from them, and it is not tested on its own
DEGENERATE = 0.02
#: candidates tried, best first, for a round's name when the joint refit with the named effects takes the
#: improvement of the ones before below the threshold
CONFIRM_TRIES = 3
#: backward elimination: an effect whose Wald statistic in the final set is below this multiple of the
#: threshold is retested by refitting the others without it (above, the quadratic likelihood settles it)
RETEST_MARGIN = 3.0


def _reset(model, original, name: str):
    """``model`` with effect ``name`` as ``original`` has it (its parameters and switch): the effect un-named."""
    from .likelihood import with_effect

    eff = original.get(name)
    if eff is None:
        return with_effect(model, name, enabled=False)
    out = with_effect(model, name, enabled=eff.enabled)
    out.get(name).params = dict(eff.params)
    return out


def _shape_candidate(name: str):
    """One parameter of the persistence law's shape as a candidate of its own (for the joint fit of a named
    persistence whose shape was freed): A is fitted beside it, not profiled."""
    from .candidates import Candidate
    from .likelihood import with_effect

    bounds, scale = next((b, sc) for n, b, sc in PERSISTENCE_SHAPE if n == name)

    def get(m, exposures):
        return float(getattr(m.persistence_model(), name))

    def put(m, value):
        return with_effect(m, "persistence", {name: float(value)})

    return Candidate("persistence", name, "", bounds, scale, "history", "", get, put)


def _joint(problem, model, named, progress=None):
    """The named effects fitted by one parameter refitted together (:func:`perscli.diagnose.joint.joint_fit`),
    with the shape parameters a named persistence freed; each entry's values and marginal errors (scaled by
    its noise-correlation dispersion) updated in place.  Returns (model, -2 ln L, covariance, the candidates
    fitted: the named ones first, in order, then the shape parameters)."""
    from .joint import joint_fit

    cands = [c for _, c in named if c.fit is None]
    owners = [next(e for e, cc in named if cc is c) for c in cands]
    for entry, cand in named:
        if cand.name == "persistence" and cand.fit is None:
            for key in entry["params"]:
                if key != cand.param:
                    cands.append(_shape_candidate(key))
                    owners.append(entry)
    if not cands:
        return model, problem.evaluate(model).m2lnl(), np.zeros((0, 0)), cands
    model, values, cov, m2 = joint_fit(problem, model, cands, progress=progress)
    for k, (c, entry) in enumerate(zip(cands, owners)):
        entry["params"][c.param] = float(values[k])
        var = cov[k, k] * entry.get("dispersion", 1.0)
        entry["errors"][c.param] = float(math.sqrt(var)) if var > 0 else float("nan")
    return model, m2, cov, cands


def _retest(problem, model, original, named, entry, cand, m2, npix):
    """The improvement of -2 ln L that ``cand`` (named) brings beside all the other named effects: the
    others refitted without it (it reset to the original model's), divided by its dispersion."""
    without = _reset(model, original, cand.name)
    others = [(e, c) for e, c in named if c is not cand]
    if cand.fit is not None:
        # fitted its own way (its own likelihood): refitted on the model with the others as they are
        value, error, fitted, nparams, *more = cand.fit(problem, without)
        more = more[0] if more else {}
        return float(more.get("delta_chi2", problem.evaluate(without).m2lnl() - problem.evaluate(fitted).m2lnl()))
    saved = [(dict(e["params"]), dict(e["errors"])) for e, _ in others]
    _, m2_without, _, _ = _joint(problem, without, others)
    for (e, _), (p, er) in zip(others, saved):
        e["params"], e["errors"] = p, er
    return (m2_without - m2) / entry.get("dispersion", 1.0)


def _confirm(problem, current, named, fit, base, progress=None):
    """``fit``'s candidate refitted together with the named effects: (model, improvement over ``base``
    divided by its dispersion, its value, -2 ln L)."""
    from .joint import joint_fit

    cands = [c for _, c in named if c.fit is None] + [fit.candidate]
    model, values, cov, m2 = joint_fit(problem, fit.model, cands)
    return model, (base - m2) / getattr(fit, "dispersion", 1.0), float(values[-1]), m2


def search(problem, model, *, candidates=CANDIDATES, progress=None, max_rounds: int | None = None,
           ramp: bool = False) -> Result:
    """Name effects by likelihood, one set at a time: forward, backward, one joint refit; then check.

    Forward: each round fits every candidate not yet named with the named
    ones held (:func:`fit_candidate`), and divides its improvement by the
    share of its information the named effects do not carry (``1 - rho^2``,
    :func:`perscli.diagnose.joint.shared_information`): its improvement with
    them refitted, so that a weak effect beside a strong one is tested at its
    own significance.  The best candidate whose improvement passes
    :func:`threshold`, whose value is physical (:func:`_unphysical`) and
    which, if it acts on the signal, owes its improvement to the expectation
    (else it goes to ``unexplained`` as ``variance_only``), is refitted
    together with the named ones (:func:`perscli.diagnose.joint.joint_fit`);
    it is named when the joint improvement still passes.  Candidates within
    :data:`MIN_DELTA_BIC` of it are listed as its degenerate group, and stay
    candidates: a later round tests them beside it.  The rounds go on until
    no candidate passes.

    Backward: every named effect is retested beside all the others (its Wald
    statistic in the joint fit; a likelihood ratio with the others refitted
    when that is within :data:`RETEST_MARGIN` of the threshold); the weakest
    that no longer passes is eliminated, and again, until all pass.  One
    joint refit of the final set gives the values, marginal errors and
    correlations.

    Then the misspecification checks run on the final model: every check
    that fires goes to ``unexplained``, and the named effects it would be
    mistaken for (:attr:`~perscli.diagnose.checks.Check.blocks`) are
    withdrawn: listed under ``withdrawn`` and, with their significance and
    the check's reason, in ``unexplained``; the rest are refitted and checked
    again.  Evidence is never dropped: a check that fired before a withdrawal
    stays in ``unexplained`` whether or not it fires after.
    """
    from .checks import run_checks
    from .joint import directions, shared_information

    say = progress or (lambda text: None)
    usable = [c for c in candidates if c.applies(problem.exposures) and problem.allows(c.name)]
    named, rounds = [], []            # named: (entry, candidate)
    variance_only = {}
    disp_of = {}                      # each candidate's noise-correlation dispersion, from its latest fit
    current = model
    max_rounds = max_rounds if max_rounds is not None else len(usable)
    npix = 0
    for round_no in range(max_rounds):
        evaluation = problem.evaluate(current)
        base = evaluation.m2lnl()
        _, npix = evaluation.chi2()
        shared = noise_correlation(problem, current)
        taken = {c.name for _, c in named}
        remaining = [c for c in usable if c.name not in taken]
        if not remaining:
            break
        held_named = [c for _, c in named if c.fit is None]
        rho2 = {}
        others = [c for c in remaining if c.fit is None]
        # the directions of every candidate fitted by one parameter: the named effects' share of each one's
        # information (what holding them costs it), and the pairs' scores
        dirs = directions(problem, current, held_named + others, evaluation=evaluation)
        for c in others:
            rho2[c.name] = shared_information(dirs, c.name, [n.name for n in held_named])
        fits, after = [], {}
        floor = FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
        for cand in remaining:
            k = dirs.index(cand.name) if cand.fit is None else None
            f = fit_candidate(problem, current, cand, base, npix, None if k is None else
                              (dirs.score[k] / dirs.scales[k], dirs.fisher[k, k] / dirs.scales[k] ** 2))
            f.dispersion = 1.0
            if cand.name in MEAN_EFFECTS and f.delta_chi2 > 0.1 * threshold(f.nparams) and f.model is not None:
                # neighbours share noise: the improvement along this candidate's direction is that much larger
                after[cand.name] = getattr(f, "evaluation", None) or problem.evaluate(f.model)
                f.dispersion = dispersion(shared, evaluation, after[cand.name])
                f.delta_chi2 /= f.dispersion
                f.error *= math.sqrt(f.dispersion)
            f.held = f.delta_chi2
            f.floor = floor
            f.rho2 = rho2.get(cand.name, 0.0)
            if f.rho2 > 1.0 - DEGENERATE:
                most = max(held_named, key=lambda n: abs(dirs.fisher[dirs.index(n.name), dirs.index(cand.name)])
                           / math.sqrt(max(dirs.fisher[dirs.index(n.name), dirs.index(n.name)]
                                           * dirs.fisher[dirs.index(cand.name), dirs.index(cand.name)], 1e-300)))
                f.note = f"the named {most.name} carries its information (correlation above 0.99): not told apart"
                f.degenerate_with = most.name
            else:
                f.delta_chi2 = f.held / (1.0 - f.rho2)
            f.delta_bic = f.delta_chi2 - f.nparams * math.log(max(npix, 2))
            fits.append(f)
            disp_of[cand.name] = f.dispersion
            say(f"round {round_no + 1}: {cand.name} {cand.param}={f.value:.6g} delta chi2 {f.delta_chi2:.1f}"
                + (f" (held {f.held:.1f}, rho^2 {f.rho2:.2f})" if f.rho2 else ""))
        fits.sort(key=lambda f: -f.delta_chi2)
        best, tries = None, 0
        for f in fits:
            if not f.significant or f.note:
                continue
            why = _unphysical(f, problem, ramp)
            if not why and f.candidate.name in MEAN_EFFECTS:
                mean_delta = _mean_only_delta(problem, evaluation, f.model, after.get(f.candidate.name))
                if mean_delta / f.dispersion < MEAN_SHARE * f.held:
                    why = "improves the noise model only, not the expectation"
                    variance_only[f.candidate.name] = f.delta_chi2
            if not why and held_named and f.candidate.fit is None:
                if tries >= CONFIRM_TRIES:
                    break
                tries += 1
                joint_model, exact, value, m2j = _confirm(problem, current, named, f, base)
                say(f"round {round_no + 1}: {f.candidate.name} refitted with the named effects: delta chi2 "
                    f"{exact:.1f}")
                f.profile_estimate = f.delta_chi2
                f.delta_chi2 = exact
                f.delta_bic = exact - f.nparams * math.log(max(npix, 2))
                if not f.significant:
                    why = "not significant once the named effects are refitted with it"
                else:
                    f.model, f.value, f.m2lnl = joint_model, value, m2j
            f.note = why
            if not why:
                best = f
                break
        # no single candidate passes: two may, whose signals cancel in part (each weak with the other held)
        pair = None if best is not None else _best_pair(problem, current, named, fits, dirs, evaluation, shared,
                                                        base, npix, ramp, say, round_no)
        rounds.append([f.as_dict() for f in fits])
        if pair is not None:
            (fa, fb), groups = pair
            for f, other, group in ((fa, fb, groups[0]), (fb, fa, groups[1])):
                entry = f.as_dict()
                entry.update(degenerate_with=group, round=round_no + 1, dispersion=f.dispersion,
                             forward_delta_chi2=f.delta_chi2,
                             note=f"named together with {other.candidate.name}: the two improve -2 ln L by "
                                  f"{f.delta_chi2:.1f} (2 parameters), more than any one alone beside the named "
                                  "effects")
                named.append((entry, f.candidate))
            current, _, _, _ = _joint(problem, fa.model, named, progress)
            continue
        if best is None:
            break
        group = [f for f in fits if f.significant and not f.note and f is not best
                 and best.delta_chi2 - f.delta_chi2 < MIN_DELTA_BIC]
        if best.candidate.name == "persistence":
            best = _free_persistence_shape(problem, best, npix, progress)
            if hasattr(problem, "set_aside") and problem.aside is None:
                # the law's shape checked at once: a persistence it cannot describe leaves residuals that every
                # later round would try to explain with something else
                from .checks import persistence_law

                law = [c for c in persistence_law(problem, problem.evaluate(best.model), best.model) if c.fired]
                if law:
                    entry = best.as_dict()
                    entry.update(withdrawn_because=_because(law), checks=[c.name for c in law],
                                 degenerate_with=[], round=round_no + 1)
                    return _without_persistence(problem, model, candidates, law, [entry], best.model, progress,
                                                ramp, rounds)
        extra_note = ""
        if best.candidate.name == "ipc":
            best, extra_note = _ipc_shape(problem, best, progress)
        entry = best.as_dict()
        entry["degenerate_with"] = [f.candidate.name for f in group]
        entry["round"] = round_no + 1
        entry["dispersion"] = best.dispersion
        entry["forward_delta_chi2"] = best.delta_chi2
        if extra_note:
            entry["note"] = extra_note
        named.append((entry, best.candidate))
        current, _, _, _ = _joint(problem, best.model, named, progress)
    original = model
    # backward: every named effect beside all the others; the weakest that no longer passes goes
    eliminated = []
    while len(named) > 1:
        current, m2, cov, cands = _joint(problem, current, named)
        stats = []
        for entry, cand in named:
            if cand.fit is None:
                k = cands.index(cand)
                value, start = entry["params"][cand.param], entry["model_value"]
                wald = (value - start) ** 2 / cov[k, k] / entry.get("dispersion", 1.0) if cov[k, k] > 0 else 0.0
                # an effect whose other parameters were freed (persistence's law) is never judged on one alone
                if len(entry["params"]) > 1:
                    wald = min(wald, threshold(entry["free_parameters"]) * RETEST_MARGIN)
            else:
                wald = 0.0
            stats.append(wald)
        order = np.argsort(stats)
        weakest = None
        for k in order:
            entry, cand = named[k]
            need = threshold(entry["free_parameters"]) + FIDELITY * sum(
                max(e.get("forward_delta_chi2", 0.0), 0.0) for e, c in named if c is not cand)
            if stats[k] >= RETEST_MARGIN * need:
                break
            delta = _retest(problem, current, original, named, entry, cand, m2, npix)
            entry["retest_delta_chi2"] = delta
            say(f"backward: {cand.name} beside the others: delta chi2 {delta:.1f}")
            if delta < need:
                weakest = k
                break
        if weakest is None:
            break
        entry, cand = named.pop(weakest)
        others = ", ".join(c.name for _, c in named)
        eliminated.append({**entry, "eliminated_because": f"not significant beside {others} (delta chi2 "
                                                         f"{entry['retest_delta_chi2']:.1f})"})
        current = _reset(current, original, cand.name)
    # the set as a whole: another set of candidates may describe the data better than the one the rounds built
    # (a gain and reciprocity failure together, where one round took a dark current and the next nonlinearity)
    current, named, alternatives, hints = _best_set(problem, current, original, named, usable, variance_only,
                                                    disp_of, npix, ramp, say)
    current, _, cov, cands = _joint(problem, current, named, progress)
    # the checks on the final model: what they find is unexplained, and what it would pass for is withdrawn
    checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
    fired = {c.name: c for c in checks if c.fired}
    withdrawn = []
    if fired and named:
        keep = []
        for entry, cand in named:
            why = [c for c in fired.values() if cand.name in c.blocks]
            if why:
                withdrawn.append({**entry, "withdrawn_because": _because(why),
                                  "checks": [c.name for c in why]})
            else:
                keep.append((entry, cand))
        if withdrawn:
            named = keep
            current = original
            for entry, cand in named:
                current = _put_entry(current, entry, cand, problem)
            current, _, cov, cands = _joint(problem, current, named, progress)
            checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
            # what fired before stays as evidence; what fires now (the withdrawn fits' signal shows again) joins it
            for c in checks:
                if c.fired:
                    fired[c.name] = c
    law = [c for c in fired.values() if c.name in LAW_CHECKS]
    if law and hasattr(problem, "set_aside") and problem.aside is None:
        return _without_persistence(problem, model, candidates, law, withdrawn, current, progress, ramp, rounds)
    found = [e for e, _ in named]
    correlations = {}
    if len(cands) > 1:
        from .joint import correlations as corr

        rho = corr(cov)
        for a in range(len(cands)):
            for b in range(a + 1, len(cands)):
                correlations[f"{cands[a].name}.{cands[a].param}~{cands[b].name}.{cands[b].param}"] = \
                    float(rho[a, b])
    for entry, cand in named:
        _final_significance(entry, cand)
    unexplained = [{"probe": c.name, "significance": c.sigma, "description": c.description, "reason": c.reason}
                   for c in fired.values()]
    for w in withdrawn:
        unexplained.append({"probe": "withdrawn", "effect": w["effect"], "significance": w["significance_sigma"],
                            "reason": w["withdrawn_because"],
                            "description": f"{w['effect']} fitted at {w['significance_sigma']:.1f} sigma and "
                                           f"withdrawn: {w['withdrawn_because']}"})
    named_names = {e["effect"] for e in found}
    for name, delta in variance_only.items():
        if name not in named_names:
            unexplained.append({"probe": "variance_only", "effect": name, "significance": _sigma(delta),
                                "reason": "noise no candidate describes",
                                "description": f"{name} would improve the fit only through the noise it adds, not "
                                               "the expected signal: noise no candidate describes"})
    return Result(found=found, candidates=rounds[0] if rounds else [], model=current, rounds=rounds,
                  checks=[c.as_dict() for c in checks], unexplained=unexplained, correlations=correlations,
                  withdrawn=withdrawn, eliminated=eliminated, alternatives=alternatives,
                  hints=[h for h in hints if h["effect"] not in {e["effect"] for e in found}])


#: a pair of candidates is named together, when no single one passes, at this false-alarm probability (two
#: parameters: 21.6 in -2 ln L, twice the single threshold): with nine candidates fitted by one parameter, 36
#: pairs keep false pairs in data sets without a missing effect below 1e-3
PAIR_P = 2e-5
#: pairs refitted exactly, best score first
PAIR_TRIES = 2


def _best_pair(problem, current, named, fits, dirs, evaluation, shared, base, npix, ramp, say, round_no):
    """Two candidates named together when no single one passes: effects whose signals partly cancel
    (brighter-fatter and nonlinearity both lower a star's core; a gain and reciprocity failure both scale a
    star) each look weak beside the other held, and strong together.

    Every pair of candidates fitted by one parameter is scored with the
    named effects free: the improvement of -2 ln L the quadratic likelihood
    predicts (``g' F^-1 g`` over the named ones and the pair, less that over
    the named ones), divided by the larger dispersion of the two.  The best
    pairs whose score passes the threshold of two parameters at
    :data:`PAIR_P` are refitted exactly with the named effects
    (:func:`perscli.diagnose.joint.joint_fit`); the first whose exact
    improvement still passes, with physical values, is returned as
    ``((fit, fit), (group, group))``: each group the candidates that could
    replace that member (pairs with the other member scored within
    :data:`MIN_DELTA_BIC` of the best), or None.
    """
    from scipy.stats import chi2

    from .joint import joint_fit

    need = float(chi2.isf(PAIR_P, 2)) + FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
    by_name = {f.candidate.name: f for f in fits}
    names = [c.name for c in dirs.candidates]
    s_idx = [names.index(c.name) for _, c in named if c.fit is None]
    g, f = dirs.score, dirs.fisher

    def explained(idx):
        if not idx:
            return 0.0
        sub = f[np.ix_(idx, idx)]
        return float(g[idx] @ np.linalg.lstsq(sub, g[idx], rcond=1e-12)[0])

    base_s = explained(s_idx)
    pool = [k for k, n in enumerate(names) if k not in s_idx and n in by_name and not by_name[n].note]
    scored = []
    for a in range(len(pool)):
        for b in range(a + 1, len(pool)):
            i, j = pool[a], pool[b]
            disp = max(by_name[names[i]].dispersion, by_name[names[j]].dispersion)
            scored.append(((explained(s_idx + [i, j]) - base_s) / disp, i, j))
    scored.sort(reverse=True)
    for score, i, j in scored[:PAIR_TRIES]:
        if not score > need:
            break
        fa, fb = by_name[names[i]], by_name[names[j]]
        cands = [c for _, c in named if c.fit is None] + [fa.candidate, fb.candidate]
        model, values, cov, m2 = joint_fit(problem, current, cands)
        disp = dispersion(shared, evaluation, problem.evaluate(model))
        exact = (base - m2) / disp
        say(f"round {round_no + 1}: {fa.candidate.name} and {fb.candidate.name} together: delta chi2 {exact:.1f} "
            f"(score {score:.1f})")
        if not exact > need:
            continue
        out = []
        for k, fit in ((len(cands) - 2, fa), (len(cands) - 1, fb)):
            trial = Fit(fit.candidate, float(values[k]), float(math.sqrt(max(cov[k, k], 0.0) * disp)), fit.start, m2,
                        nparams=1)
            trial.model, trial.dispersion, trial.delta_chi2 = model, disp, exact
            trial.delta_bic = exact - 2 * math.log(max(npix, 2))
            if _unphysical(trial, problem, ramp):
                break
            out.append(trial)
        if len(out) != 2:
            continue
        groups = ([names[x] for sc, x, y in scored if y == j and x != i and score - sc < MIN_DELTA_BIC]
                  + [names[y] for sc, x, y in scored if x == j and y != i and score - sc < MIN_DELTA_BIC],
                  [names[x] for sc, x, y in scored if y == i and x != j and score - sc < MIN_DELTA_BIC]
                  + [names[y] for sc, x, y in scored if x == i and y != j and score - sc < MIN_DELTA_BIC])
        return tuple(out), groups
    return None


#: the search over sets looks at subsets of at most this many candidates fitted by one parameter (2^9 of them)
SET_SIZE = 9
#: and tries at most this many exact refits of a better set
SET_TRIES = 3
#: another set replaces the named one only when its score is lower by more than this: the rounds and the
#: backward elimination have settled each single addition and removal at the threshold already, and a set that
#: ties with the named one at the threshold's edge (an effect at 3.29 sigma, the dispersion counted a little
#: otherwise) is no better description
SET_MARGIN = 2.0


def _set_values(dirs, offsets, disp, pen):
    """For every subset T of the candidates of ``dirs``: the change of -2 ln L (from the model the directions
    were taken at) of fitting T with the others at the original model's values, by the quadratic likelihood,
    divided by the largest dispersion of the set's members, plus ``pen`` per member.  {frozenset: value}."""
    from itertools import combinations

    g, f = dirs.score, dirs.fisher
    n = len(g)
    out = {}
    for size in range(0, n + 1):
        for t in combinations(range(n), size):
            fixed = [k for k in range(n) if k not in t]
            d = -offsets[fixed]
            value = float(-2.0 * g[fixed] @ d + d @ f[np.ix_(fixed, fixed)] @ d)
            if t:
                t = list(t)
                rhs = g[t] - f[np.ix_(t, fixed)] @ d
                value -= float(rhs @ np.linalg.lstsq(f[np.ix_(t, t)], rhs, rcond=1e-10)[0])
            members = list(t) + [k for k in range(n) if offsets[k] != 0.0]
            scale = max([disp[k] for k in members] + [1.0])
            out[frozenset(t)] = value / scale + pen * len(t)
    return out


def _best_set(problem, current, original, named, usable, variance_only, disp_of, npix, ramp, say):
    """The set of candidates that describes the data best, searched over every subset of those fitted by one
    parameter, not only along the path the rounds took.

    At the current model the directions of every such candidate (but those
    found to act on the noise only) give the quadratic likelihood; each
    subset's best -2 ln L (its members free, the others back at the
    original model's values) plus :func:`threshold` per member, the price a
    round asks of each named effect, is its score (:func:`_set_values`).
    When another subset scores lower than the named one, it is fitted exactly
    (:func:`perscli.diagnose.joint.joint_fit`) and taken when its exact score
    is lower too and its values are physical; then again from there.

    Returns (model, named, alternatives): the sets whose score is within
    :data:`MIN_DELTA_BIC` of the best one's, which the data cannot tell
    from it ([[names], delta]); the members each alternative replaces are
    listed as degenerate with the named ones they replace.
    """
    from .joint import directions, joint_fit

    fixed_named = [(e, c) for e, c in named if c.fit is not None]
    pool = [c for c in usable if c.fit is None and c.name not in variance_only]
    if len(pool) > SET_SIZE or not pool:
        return current, named, [], []
    pen = threshold(1)
    alternatives = []
    dirs = None
    for _ in range(SET_TRIES):
        held = {c.name for _, c in named if c.fit is None}
        dirs = directions(problem, current, pool)
        # in units of each candidate's typical size, as the directions are
        offsets = np.array([c.get(current, problem.exposures) - c.get(original, problem.exposures) for c in pool]) \
            / dirs.scales
        disp = [disp_of.get(c.name, 1.0) for c in pool]
        scores = _set_values(dirs, offsets, disp, pen)
        mine = frozenset(k for k, c in enumerate(pool) if c.name in held)
        best = min(scores, key=scores.get)
        alternatives = sorted(((sorted(pool[k].name for k in t), v - scores[best]) for t, v in scores.items()
                               if t != best and v - scores[best] < MIN_DELTA_BIC and len(t) == len(best)),
                              key=lambda a: a[1])
        # the forward model's fidelity: a set that differs from the named one by less than that share of what
        # the named effects bring is no better description
        margin = SET_MARGIN + FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named)
        if best == mine or not scores[mine] - scores[best] > margin:
            break
        # the better set, fitted exactly from the original model's values of what it leaves out
        trial = current
        for c in pool:
            if c.name in held and pool.index(c) not in best:
                trial = _reset(trial, original, c.name)
        cands = [pool[k] for k in sorted(best)]
        base = problem.evaluate(current).m2lnl()
        model, values, cov, m2 = joint_fit(problem, trial, cands)
        worst = max([disp[k] for k in best] + [disp[k] for k in mine] + [1.0])
        exact = (m2 - base) / worst + pen * (len(best) - len(mine))
        names = [c.name for c in cands]
        say(f"sets: {', '.join(names) or 'none'} instead of {', '.join(sorted(held)) or 'none'}: score "
            f"{exact:+.1f} (quadratic {scores[best] - scores[mine]:+.1f})")
        if not exact < -margin:
            break
        entries = []
        physical = True
        for k, c in enumerate(cands):
            old = next((e for e, cc in named if cc is c), None)
            error = float(math.sqrt(max(cov[k, k], 0.0) * disp_of.get(c.name, 1.0)))
            if old is not None:
                old["params"][c.param], old["errors"][c.param] = float(values[k]), error
                entries.append((old, c))
                continue
            start = c.get(original, problem.exposures)
            fit = Fit(c, float(values[k]), error, start, m2)
            fit.model, fit.dispersion = model, disp_of.get(c.name, 1.0)
            fit.delta_chi2 = ((values[k] - start) / error) ** 2 if error > 0 else 0.0
            if _unphysical(fit, problem, ramp):
                physical = False
                break
            entry = fit.as_dict()
            entry.update(degenerate_with=[], round=0, dispersion=fit.dispersion, forward_delta_chi2=0.0,
                         note="named by the search over sets: the set with it describes the data better than "
                              f"the one the rounds built ({', '.join(sorted(held))})")
            entries.append((entry, c))
        if not physical:
            break
        named = entries + fixed_named
        current = model
        for e, c in fixed_named:
            current = _put_entry(current, e, c, problem)
        dirs = None
    if dirs is None:
        dirs = directions(problem, current, pool)
    hints = _hints(dirs, named, disp_of, FIDELITY * sum(max(e.get("forward_delta_chi2", 0.0), 0.0) for e, _ in named))
    by_entry = {c.name: e for e, c in named}
    # the degenerate groups of the rounds were judged beside part of the set: the whole set's alternatives replace
    # them
    for e, c in named:
        if c.fit is None:
            e["degenerate_with"] = []
    for names, _ in alternatives:
        chosen = {c.name for _, c in named if c.fit is None}
        out, into = chosen - set(names), set(names) - chosen
        for name in out:
            by_entry[name]["degenerate_with"] = sorted(set(by_entry[name]["degenerate_with"]) | into)
    return current, named, [[names, float(delta)] for names, delta in alternatives], hints


#: a candidate whose improvement beside the named effects passes this false-alarm probability (2.58 sigma) but
#: not the naming threshold is reported below the threshold: never named, never written, said
HINT_P = 0.01


def _hints(dirs, named, disp_of, floor: float = 0.0) -> list:
    """Candidates below the naming threshold (plus ``floor``, :data:`FIDELITY`'s) whose improvement beside the
    named effects (the score test at the final model) still passes :data:`HINT_P`: where more data would look
    first."""
    from scipy.stats import chi2

    low, high = float(chi2.isf(HINT_P, 1)), threshold(1) + floor
    names = [c.name for c in dirs.candidates]
    held = [names.index(c.name) for _, c in named if c.fit is None and c.name in names]
    g, f = dirs.score, dirs.fisher

    def explained(idx):
        return float(g[idx] @ np.linalg.lstsq(f[np.ix_(idx, idx)], g[idx], rcond=1e-12)[0]) if idx else 0.0

    base = explained(held)
    out = []
    for k, c in enumerate(dirs.candidates):
        if k in held:
            continue
        delta = (explained(held + [k]) - base) / disp_of.get(c.name, 1.0)
        if low < delta <= high:
            step = np.linalg.lstsq(f[np.ix_(held + [k], held + [k])], g[held + [k]], rcond=1e-12)[0][-1]
            out.append({"effect": c.name, "param": c.param, "value": float(dirs.values[k] + step * dirs.scales[k]),
                        "delta_chi2": float(delta), "significance_sigma": _sigma(delta)})
    return sorted(out, key=lambda h: -h["delta_chi2"])


#: the checks that find a persistence the law does not describe
LAW_CHECKS = ("persistence_decay", "persistence_fluence")
#: pixels where a persistence no law describes leaves more than this share of the read noise are set aside
ASIDE_READ_NOISE = 0.3


def _without_persistence(problem, model, candidates, law, withdrawn, current, progress, ramp, rounds=()) -> Result:
    """The search again without persistence and without the pixels where the persistence the law does not
    describe lies: what the first search named beside it may have absorbed it (a gain a little low makes a
    ghost's residual a little smaller), so everything is measured again on the pixels it leaves alone.

    The pixels set aside are those where the law, at the largest amplitude
    the persistence checks measured, leaves more than :data:`ASIDE_READ_NOISE`
    of the read noise.  The evidence stays: the persistence checks that fired
    and the withdrawn persistence fit go to ``unexplained`` before what the
    second search finds.
    """
    import dataclasses

    amplitude = max(max(c.detail.get("amplitude", [0.0]) + [0.0]) for c in law)
    pm = current.persistence_model()
    if pm.kind != "fermi" or not amplitude > 0:
        amplitude = max(pm.A, 1e-3)
    sigma = float(current.value("read_noise", "sigma", off=1.0) or 1.0)
    well = current.value("saturation", "full_well", off=None)
    count = problem.set_aside(dataclasses.replace(pm, A=float(amplitude)), ASIDE_READ_NOISE * sigma, well)
    say = progress or (lambda text: None)
    say(f"a persistence no law describes: {count} pixels of the fit rows set aside, the search again without "
        "persistence")
    inner = search(problem, model, candidates=[c for c in candidates if c.name != "persistence"],
                   progress=progress, ramp=ramp)
    evidence = [{"probe": c.name, "significance": c.sigma, "description": c.description, "reason": c.reason}
                for c in law]
    for w in withdrawn:
        if w["effect"] == "persistence":
            evidence.append({"probe": "withdrawn", "effect": "persistence", "significance": w["significance_sigma"],
                             "reason": w["withdrawn_because"],
                             "description": f"persistence fitted at {w['significance_sigma']:.1f} sigma and "
                                            f"withdrawn: {w['withdrawn_because']}"})
            inner.withdrawn.insert(0, w)
    seen = {u["probe"] for u in evidence}
    inner.unexplained = evidence + [u for u in inner.unexplained if u["probe"] not in seen or u["probe"] == "withdrawn"]
    inner.set_aside = {"pixels": count, "law_A": float(amplitude), "electrons": ASIDE_READ_NOISE * sigma}
    if rounds:
        # the rounds of the first search (with persistence) first: where the evidence came from
        inner.rounds = list(rounds) + inner.rounds
        inner.candidates = rounds[0]
    return inner


def _because(checks) -> str:
    """Why a fit is withdrawn, in a few words: the reasons of the checks that say what the data hold instead
    (the persistence law's), and the names of the others (their descriptions are in ``unexplained``)."""
    said = [c.why for c in checks if c.why]
    others = [c.name for c in checks if not c.why]
    if others:
        said.append(f"the {', '.join(others)} check{'s' if len(others) > 1 else ''} fire{'' if len(others) > 1 else 's'}"
                    ": the fit may only absorb what they find")
    return "; ".join(said)


def _put_entry(model, entry, cand, problem):
    """``model`` with a found effect put in at its reported values (all its parameters)."""
    from .likelihood import with_effect

    if cand.fit is not None:
        return cand.fit(problem, model)[2]
    if cand.name == "ipc" and "kernel" in entry.get("shape", {}):
        # the freed kernel's shape, at the strength the joint fit gave it
        model = with_effect(model, "ipc", {"kernel": entry["shape"]["kernel"], "alpha": None})
    out = cand.put(model, entry["params"][cand.param])
    extra = {k: v for k, v in entry["params"].items() if k != cand.param}
    return with_effect(out, cand.name, extra) if extra else out


def _final_significance(entry, cand):
    """The entry's significance as it stands in the final set: its value against the model's, over its
    marginal error (the Wald statistic of the joint fit), or its retest's likelihood ratio when one ran."""
    if "retest_delta_chi2" in entry:
        delta = entry["retest_delta_chi2"]
    elif cand.fit is None and len(entry["params"]) == 1:
        err = entry["errors"].get(cand.param)
        delta = ((entry["params"][cand.param] - entry["model_value"]) / err) ** 2 if err and err > 0 else \
            entry["delta_chi2"]
    else:
        delta = entry["delta_chi2"]
    entry["delta_chi2"] = float(delta)
    entry["significance_sigma"] = _sigma(delta, entry["free_parameters"])
    entry["significant"] = delta > threshold(entry["free_parameters"])


#: the free 8-coupling IPC kernel replaces the one-parameter template when its improvement passes the
#: threshold for its 7 extra parameters
def _ipc_shape(problem, best: Fit, progress=None):
    """A named IPC: its kernel's 8 couplings freed when the data ask for another shape than the model's
    (:func:`perscli.diagnose.candidates.ipc_free_shape`), and the free kernel physical; (fit, note)."""
    from .candidates import ipc_free_shape

    shape = ipc_free_shape(problem, best.model)
    delta = shape["delta_chi2"] / best.dispersion
    if delta <= threshold(7):
        return best, ""
    trial = Fit(best.candidate, shape["alpha"], shape["error"] * math.sqrt(best.dispersion), best.start,
                best.m2lnl, nparams=8)
    trial.model = shape["model"]
    why = _unphysical(trial, problem, False)
    if why:
        return best, (f"another kernel shape improves -2 ln L by {delta:.1f} (7 parameters) but is {why}: the "
                      "model's shape is kept")
    if progress is not None:
        progress(f"ipc: the 8 couplings freed (delta chi2 {delta:.1f} over the template)")
    best.model, best.value, best.error = shape["model"], shape["alpha"], trial.error
    best.delta_chi2 += delta
    best.nparams = 8
    best.shape = {"kernel": shape["kernel"], "delta_chi2": delta}
    return best, f"kernel shape freed: its 8 couplings improve -2 ln L by {delta:.1f} over the model's shape"
