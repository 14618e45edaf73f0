"""Fit every candidate by likelihood, name the significant ones in turn, refit them together.

Each round fits every candidate's parameter (a bounded one-dimensional
minimisation of -2 ln L, the Gaussian likelihood with the model's own
variance, so that effects on the noise such as read noise count as much as
effects on the mean) with the effects found so far in the model.  The best
candidate is named when it improves -2 ln L by more than
:func:`threshold` (a likelihood-ratio test at a false-alarm probability of
1e-3 per candidate; the rates of false and missed names are measured by
tests/test_diagnose_calibrated.py), its value is physical and inside its
range, an effect on the signal owes its improvement to the expectation and
not to the noise alone, and no misspecification check
(:mod:`perscli.diagnose.checks`) that fires says the candidate would only be
absorbing something else.  Every
effect named so far is then refitted together (:func:`joint_fit`), so that
correlated effects (a dark current and an offset, a gain and a
nonlinearity) share the disagreement as the data say; the report gives each
one's marginal error from the joint covariance and their correlations.
Candidates whose improvement is within :data:`MIN_DELTA_BIC` of the best
one's are what the data cannot tell apart: they are reported with it as one
degenerate group.
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

    @property
    def significant(self) -> bool:
        return self.delta_chi2 > threshold(self.nparams)

    def as_dict(self) -> dict:
        params = {self.candidate.param: self.value, **getattr(self, "extra", {})}
        errors = {self.candidate.param: self.error, **getattr(self, "extra_errors", {})}
        return {"effect": self.candidate.name, "params": params, "errors": errors, "model_value": self.start,
                "unit": self.candidate.unit, "delta_chi2": self.delta_chi2, "delta_bic": self.delta_bic,
                "significance_sigma": _sigma(self.delta_chi2, self.nparams), "significant": self.significant,
                "threshold_delta_chi2": threshold(self.nparams), "free_parameters": self.nparams, "note": self.note}


def fit_candidate(problem, model, candidate: Candidate, m2lnl_base: float, npix: int) -> Fit:
    """The candidate's parameter that minimises -2 ln L with everything else in ``model`` held."""
    from scipy.optimize import minimize_scalar

    start = candidate.get(model, problem.exposures)
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
    worth = _shape_screen(problem, model, m2)
    if progress is not None:
        progress("persistence: freeing the law's shape would gain about " + ", ".join(
            f"{name} {worth[name]:.3g}" for name, _, _ in PERSISTENCE_SHAPE) + " in -2 ln L (screen)")
    for name, bounds, scale in PERSISTENCE_SHAPE:
        if worth.get(name, math.inf) < SHAPE_SCREEN * (math.log(max(npix, 2)) + MIN_DELTA_BIC):
            # the local quadratic of -2 ln L (A profiled) says freeing it cannot pay: the profile fit, a
            # one-dimensional search whose every point is itself a fit of A, is not run
            continue
        def get(m, exposures, name=name):
            return float(getattr(m.persistence_model(), name))

        def put(m, value, name=name):
            # the profile likelihood: A (strongly correlated with the shape) re-fitted at every value
            return fit_candidate(problem, with_effect(m, "persistence", {name: float(value)}), amp, 0.0, npix).model

        free = Candidate(f"persistence.{name}", name, "", bounds, scale, "history", "", get, put)
        trial = fit_candidate(problem, model, free, m2, npix)
        if min(trial.value - bounds[0], bounds[1] - trial.value) <= scale * 1e-3:
            # at the edge of its range it measures nothing: the law's shape is held
            continue
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


#: a shape parameter is fitted only when the quadratic screen predicts at least this share of the improvement
#: the BIC asks of it (a generous margin: the screen is local, the fit is not)
SHAPE_SCREEN = 0.25
#: the screen's step, in units of each shape parameter's typical size: wide enough to see a curved likelihood
SHAPE_STEP = 5.0


def _shape_screen(problem, model, m2: float) -> dict:
    """For each Fermi shape parameter, about how much freeing it would improve -2 ln L (A re-fitted).

    The profile of -2 ln L (A at its best for each value) is taken at the
    model's value and :data:`SHAPE_STEP` typical sizes either side: at each
    side A's best comes from a parabola through three values of A (the
    expectation is linear in A, so -2 ln L is close to quadratic in it).  A
    parabola through the three profile values gives the predicted
    improvement: its minimum when it is convex with its vertex within three
    steps, else the better side's improvement.  Where the stencil leaves
    the parameter's range the answer is infinite (the full fit decides).
    Twenty-four evaluations instead of the profile fits' hundreds.
    """
    from .candidates import _put_persistence
    from .likelihood import with_effect

    def cost(m):
        try:
            return problem.evaluate(m).m2lnl()
        except (ValueError, FloatingPointError, ZeroDivisionError):
            return math.inf

    pm = model.persistence_model()
    a = float(pm.A)
    ha = max(0.1 * a, 1e-3)

    def profile(m):
        """The minimum over A of -2 ln L, from a parabola through A - ha, A, A + ha (A kept >= 0)."""
        lo = max(a - ha, 0.0)
        xs = np.array([lo, lo + ha, lo + 2 * ha])
        fs = np.array([cost(_put_persistence(m, float(x))) for x in xs])
        if not np.all(np.isfinite(fs)):
            return float(np.min(fs))
        c2, c1, c0 = np.polyfit(xs - xs[1], fs, 2)
        if c2 <= 0:
            return float(fs.min())
        x = min(max(-c1 / (2 * c2), xs[0] - xs[1] - 3 * ha), 3 * ha)
        return float(min(fs.min(), c0 + c1 * x + c2 * x * x))

    out = {}
    for name, bounds, scale in PERSISTENCE_SHAPE:
        t = float(getattr(pm, name))
        h = SHAPE_STEP * scale
        if not (bounds[0] <= t - h and t + h <= bounds[1]):
            out[name] = math.inf
            continue
        fm, fp = profile(with_effect(model, "persistence", {name: t - h})), \
            profile(with_effect(model, "persistence", {name: t + h}))
        gain = m2 - min(fm, fp)
        curvature = fp - 2 * m2 + fm
        if curvature > 0:
            u = (fm - fp) / (2 * curvature)          # the vertex, in steps
            if abs(u) <= 3:
                gain = max(gain, curvature * u * u / 2)
        out[name] = float(gain) if math.isfinite(gain) else math.inf
    return out


@dataclass
class Result:
    """What the search found."""

    found: list                  # dicts: effect, params, errors, delta_chi2, significance, degenerate_with, ...
    candidates: list             # every candidate's fit in the first round (and later ones)
    model: object                # the model with the found effects
    rounds: list
    checks: list = field(default_factory=list)        # the misspecification checks on the final model
    unexplained: list = field(default_factory=list)   # those that fired
    correlations: dict = field(default_factory=dict)  # between the found effects' parameters (joint fit)
    withdrawn: list = field(default_factory=list)     # effects named, then withdrawn because a check fired


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


def joint_fit(problem, model, named: list, *, progress=None):
    """Every named effect's parameter fitted together: (model, values, covariance).

    ``named`` holds :class:`~perscli.diagnose.candidates.Candidate` objects;
    each is put into the model at a value (its ``put``) and -2 ln L is
    minimised over all of them at once (L-BFGS-B in units of each one's
    scale, within its range).  The covariance is twice the inverse of the
    Hessian of -2 ln L at the minimum (finite differences), so each error is
    the marginal one, with the others free.
    """
    from scipy.optimize import minimize

    if not named:
        return model, np.zeros(0), np.zeros((0, 0))
    exposures = problem.exposures
    scale = np.array([c.scale for c in named])
    lo = np.array([c.bounds[0] for c in named]) / scale
    hi = np.array([c.bounds[1] for c in named]) / scale
    x0 = np.clip(np.array([c.get(model, exposures) for c in named]) / scale, lo, hi)

    def put(x):
        m = model
        for c, v in zip(named, x * scale):
            m = c.put(m, float(v))
        return m

    cache = {}

    def cost(x):
        key = tuple(np.round(x, 12))
        if key not in cache:
            try:
                cache[key] = problem.evaluate(put(np.asarray(x))).m2lnl()
            except (ValueError, FloatingPointError, ZeroDivisionError):
                cache[key] = math.inf
        return cache[key]

    if len(named) == 1:
        best = x0
    else:
        res = minimize(cost, x0, method="L-BFGS-B", bounds=list(zip(lo, hi)),
                       options={"eps": 1e-4, "ftol": 1e-12, "gtol": 1e-6, "maxiter": 200})
        best = res.x if res.fun <= cost(x0) else x0
    # the Hessian of -2 ln L by central differences, in units of the scales
    n = len(named)
    h = np.full(n, 1e-2)
    f0 = cost(best)
    hess = np.zeros((n, n))
    for a in range(n):
        for b in range(a, n):
            def at(da, db):
                x = best.copy()
                x[a] += da * h[a]
                x[b] += db * h[b]
                return cost(np.clip(x, lo, hi))
            if a == b:
                hess[a, a] = (at(1, 0) - 2 * f0 + at(-1, 0)) / h[a] ** 2
            else:
                hess[a, b] = hess[b, a] = (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)) / (4 * h[a] * h[b])
    try:
        cov = 2.0 * np.linalg.inv(hess) if np.all(np.isfinite(hess)) else np.full((n, n), np.nan)
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.nan)
    cov = cov * np.outer(scale, scale)
    if progress is not None:
        progress("joint fit: " + ", ".join(f"{c.name} {v:.5g}" for c, v in zip(named, best * scale)))
    return put(best), best * scale, cov


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


def _refit_named(problem, model, found: list, named: list, progress=None):
    """``model`` with the effects of ``found`` put in at their values, those fitted by one parameter refitted
    together; updates ``found``'s values and errors.  Returns the model."""
    current = model
    for entry, cand in zip(found, named):
        if cand.fit is not None:
            current = cand.fit(problem, current)[2]
        else:
            current = cand.put(current, entry["params"][cand.param])
            extra = {k: v for k, v in entry["params"].items() if k != cand.param}
            if extra:
                from .likelihood import with_effect

                current = with_effect(current, cand.name, extra)
    return _refit_jointly(problem, current, named, found, progress)


def _refit_jointly(problem, current, named, found, progress=None):
    """The named effects refitted together: each shares the disagreement as the data say; ``found``'s
    values and marginal errors (scaled by each effect's noise-correlation dispersion) updated in place."""
    joint = [c for c in named if c.fit is None]
    if len(joint) > 1:
        current, values, cov = joint_fit(problem, current, joint, progress=progress)
        for k, (c, v) in enumerate(zip(joint, values)):
            e = next(x for x in found if x["effect"] == c.name)
            e["params"][c.param] = float(v)
            e["errors"][c.param] = (float(math.sqrt(cov[k, k] * e.get("dispersion", 1.0))) if cov[k, k] > 0
                                    else float("nan"))
    return current


def search(problem, model, *, candidates=CANDIDATES, progress=None, max_rounds: int = 8, ramp: bool = False) -> Result:
    """Name significant effects one at a time, refitting all named ones together after each; then check.

    A candidate is named when it improves -2 ln L by more than
    :func:`threshold` of its free parameters, its value is physical
    (:func:`_unphysical`), and an effect on the signal owes its improvement
    to the expectation, not to the noise alone (else the improvement goes to
    ``unexplained`` as ``variance_only``).  When no candidate is left, the
    misspecification checks run on the final model: every check that fires
    goes to ``unexplained``, and the named effects it would be mistaken for
    (:attr:`~perscli.diagnose.checks.Check.blocks`) are withdrawn (their fits
    may only be absorbing what it found; the report lists them under
    ``withdrawn`` with the reason) and the rest refitted without them.
    """
    from .checks import run_checks

    usable = [c for c in candidates if c.applies(problem.exposures) and problem.allows(c.name)]
    found, rounds, named = [], [], []
    variance_only = {}
    current = model
    remaining = list(usable)
    for round_no in range(max_rounds):
        evaluation = problem.evaluate(current)
        base = evaluation.m2lnl()
        _, npix = evaluation.chi2()
        shared = noise_correlation(problem, current)
        fits, after = [], {}
        for cand in remaining:
            f = fit_candidate(problem, current, cand, base, npix)
            if cand.name in MEAN_EFFECTS and f.delta_chi2 > 0.3 * threshold(f.nparams) and f.model is not None:
                # neighbours share noise: the improvement along this candidate's direction is that much larger
                after[cand.name] = problem.evaluate(f.model)
                f.dispersion = dispersion(shared, evaluation, after[cand.name])
                f.delta_chi2 /= f.dispersion
                f.delta_bic = f.delta_chi2 - f.nparams * math.log(max(npix, 2))
                f.error *= math.sqrt(f.dispersion)
            fits.append(f)
            if progress is not None:
                progress(f"round {round_no + 1}: {cand.name} {cand.param}={f.value:.6g} delta chi2 {f.delta_chi2:.1f}")
        fits.sort(key=lambda f: -f.delta_chi2)
        best = None
        for f in fits:
            if not f.significant:
                continue
            why = _unphysical(f, problem, ramp)
            if not why and f.candidate.name in MEAN_EFFECTS:
                mean_delta = _mean_only_delta(problem, evaluation, f.model, after.get(f.candidate.name))
                if mean_delta / getattr(f, "dispersion", 1.0) < MEAN_SHARE * f.delta_chi2:
                    why = "improves the noise model only, not the expectation"
                    variance_only[f.candidate.name] = f.delta_chi2
            f.note = why
            if not why:
                best = f
                break
        rounds.append([f.as_dict() for f in fits])
        if best is None:
            break
        group = [f for f in fits if f.significant and not f.note and f is not best
                 and best.delta_chi2 - f.delta_chi2 < MIN_DELTA_BIC]
        if best.candidate.name == "persistence":
            best = _free_persistence_shape(problem, best, npix, progress)
        entry = best.as_dict()
        entry["degenerate_with"] = [f.candidate.name for f in group]
        entry["round"] = round_no + 1
        entry["dispersion"] = getattr(best, "dispersion", 1.0)
        found.append(entry)
        named.append(best.candidate)
        current = best.model
        current = _refit_jointly(problem, current, named, found, progress)
        taken = {best.candidate.name, *entry["degenerate_with"]}
        remaining = [c for c in remaining if c.name not in taken]
        if not remaining:
            break
    # the checks on the final model: what they find is unexplained, and what it would pass for is withdrawn
    checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
    fired = [c for c in checks if c.fired]
    withdrawn = []
    if fired and found:
        keep = []
        for entry, cand in zip(found, named):
            why = [c.name for c in fired if cand.name in c.blocks]
            if why:
                withdrawn.append({**entry, "withdrawn_because": f"the {', '.join(why)} check fires: the fit may only "
                                                               f"absorb what it finds"})
            else:
                keep.append((entry, cand))
        if withdrawn:
            found = [e for e, _ in keep]
            named = [c for _, c in keep]
            current = _refit_named(problem, model, found, named, progress=progress)
            checks = run_checks(problem, problem.evaluate(current), current, ramp=ramp, final=True)
            # what the withdrawn fits absorbed shows again: every check that fires now is reported
            fired = [c for c in checks if c.fired]
    correlations = {}
    joint = [c for c in named if c.fit is None]
    if len(joint) > 1:
        _, _, cov = joint_fit(problem, current, joint)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        for a in range(len(joint)):
            for b in range(a + 1, len(joint)):
                if sd[a] > 0 and sd[b] > 0:
                    correlations[f"{joint[a].name}.{joint[a].param}~{joint[b].name}.{joint[b].param}"] = \
                        float(cov[a, b] / (sd[a] * sd[b]))
    unexplained = [{"probe": c.name, "significance": c.sigma, "description": c.description} for c in fired]
    named_names = {e["effect"] for e in found}
    for name, delta in variance_only.items():
        if name not in named_names:
            unexplained.append({"probe": "variance_only", "significance": _sigma(delta),
                                "description": f"{name} would improve the fit only through the noise it adds, not "
                                               "the expected signal: noise no candidate describes"})
    return Result(found=found, candidates=rounds[0] if rounds else [], model=current, rounds=rounds,
                  checks=[c.as_dict() for c in checks], unexplained=unexplained, correlations=correlations,
                  withdrawn=withdrawn)
