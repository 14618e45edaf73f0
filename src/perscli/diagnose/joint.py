"""Effects fitted together: how each candidate moves the expectation and the variance, and what follows.

Near the best fit the Gaussian likelihood of the pixels is close to
quadratic in every candidate's parameter: the expectations of persistence,
dark current, offset, nonlinearity, reciprocity failure, interpixel
capacitance and brighter-fatter are linear in them, the variance of read
noise is quadratic, the gain nearly linear over a few per cent.  One
evaluation of the model a small step along each parameter gives its
*direction* (the change of every pixel's expectation and variance); their
inner products, weighted by the pixels' variance, are the Fisher matrix

    F_ij = sum_p dmu_i dmu_j / v + 1/2 sum_p dv_i dv_j / v^2

and the score ``g_i = sum_p dmu_i r / v + 1/2 sum_p dv_i (r^2 / v - 1) / v``
(``r`` the residual).  From them:

- :func:`joint_fit`: several effects fitted at once by Fisher scoring
  (Newton's method with the expected Hessian; a step is kept only when
  -2 ln L falls), the covariance ``F^-1`` (each error the marginal one,
  with the others free) and the correlations;
- :func:`shared_information`: the share of a candidate's information that
  effects already named carry (``rho^2 = F_cS F_SS^-1 F_Sc / F_cc``), so that
  its improvement with them refitted is its improvement with them held
  divided by ``1 - rho^2``: a weak effect beside a strong one is tested at
  its own significance, not at what the strong one's fit left of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: a direction's step, in units of the candidate's typical size (its ``scale``): small enough that the
#: variance of read noise (quadratic in sigma) is linear over it to a few 1e-3, large enough for float32 means
STEP = 0.1


@dataclass
class Directions:
    """The directions of some candidates at one model: whitened derivatives of the pixels' expectation
    (``a``: dmu / sqrt(v)) and variance (``b``: dv / (sqrt(2) v)), each over the usable pixels of the
    base evaluation, and the score and Fisher matrix they give.

    Derivatives, score and Fisher matrix are per each candidate's typical
    size (``scales``, its ``scale``): a nonlinearity's beta (1e-9) and a
    persistence's A (1e-2) differ by seven orders of magnitude in their own
    units, and a least-squares solve would take the small one's information
    for round-off.  ``values`` are in the candidates' own units.
    """

    candidates: list
    values: np.ndarray
    a: list
    b: list
    score: np.ndarray
    fisher: np.ndarray
    m2lnl: float
    scales: np.ndarray = None

    def index(self, name: str) -> int:
        return next(k for k, c in enumerate(self.candidates) if c.name == name)


def _step(cand, value: float) -> float:
    lo, hi = cand.bounds
    h = STEP * cand.scale
    # a step that would leave the range goes the other way
    return h if value + h <= hi else -h


def directions(problem, model, cands, *, evaluation=None) -> Directions:
    """The directions of ``cands`` (candidates with a ``put``) at ``model``: one evaluation each."""
    ev = evaluation if evaluation is not None else problem.evaluate(model)
    masks = ev.mask
    sv = [np.sqrt(v[m]) for v, m in zip(ev.variance, masks)]
    r = [(d[m] - e[m]) / s for d, e, m, s in zip(ev.data, ev.mean, masks, sv)]
    rr = np.concatenate(r) if r else np.zeros(0)
    inv = [1.0 / s for s in sv]
    values = np.array([c.get(model, problem.exposures) for c in cands], dtype=float)
    a_cols, b_cols = [], []
    scales = np.array([c.scale for c in cands], dtype=float)
    for cand, value, scale in zip(cands, values, scales):
        h = _step(cand, value)
        moved = problem.evaluate(cand.put(model, value + h))
        # per typical size of the parameter
        per = scale / h
        a = np.concatenate([((e1[m] - e0[m]) * per) * w for e1, e0, m, w in zip(moved.mean, ev.mean, masks, inv)])
        b = np.concatenate([((v1[m] - v0[m]) * per) * (w * w / math.sqrt(2.0))
                            for v1, v0, m, w in zip(moved.variance, ev.variance, masks, inv)])
        # pixels the step makes unusable (a NaN expectation) carry nothing along it
        a_cols.append(np.nan_to_num(a).astype(np.float32))
        b_cols.append(np.nan_to_num(b).astype(np.float32))
    n = len(cands)
    fisher = np.zeros((n, n))
    score = np.zeros(n)
    excess = (rr * rr - 1.0) / math.sqrt(2.0)
    # the columns are kept in float32; their products are summed in float64, a chunk of pixels at a time
    chunk = 1 << 20
    for cols, target in ((a_cols, rr), (b_cols, excess)):
        if not n:
            break
        for k in range(0, target.size, chunk):
            block = np.stack([c[k:k + chunk] for c in cols]).astype(np.float64)
            fisher += block @ block.T
            score += block @ target[k:k + chunk]
    return Directions(list(cands), values, a_cols, b_cols, score, fisher, ev.m2lnl(), scales)


def shared_information(dirs: Directions, name: str, named: list) -> float:
    """rho^2: the share of candidate ``name``'s information (its Fisher information) that the candidates
    ``named`` carry; 0 when none are named, near 1 when it is (nearly) a combination of them."""
    if not named:
        return 0.0
    c = dirs.index(name)
    s = [dirs.index(n) for n in named]
    f = dirs.fisher
    if not f[c, c] > 0:
        return 1.0
    fss = f[np.ix_(s, s)]
    fsc = f[s, c]
    try:
        x = np.linalg.lstsq(fss, fsc, rcond=1e-10)[0]
    except np.linalg.LinAlgError:
        return 1.0
    return float(min(max(fsc @ x / f[c, c], 0.0), 1.0))


def correlations(cov: np.ndarray) -> np.ndarray:
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = cov / np.outer(sd, sd)
    return np.where(np.isfinite(out), out, 0.0)


def joint_fit(problem, model, cands, *, max_iter: int = 8, progress=None):
    """The parameters of ``cands`` fitted together by Fisher scoring: (model, values, covariance, -2 ln L).

    Each iteration takes the directions at the current values and the step
    ``F^-1 g`` (clipped into each candidate's range; a parameter held at a
    bound the step would cross is held there), halved up to five times until
    -2 ln L falls.  Iterations stop when the predicted improvement is below
    1e-3.  The covariance is ``F^-1`` at the end (parameters held at a bound:
    zero variance), in each candidate's units.
    """
    if not cands:
        return model, np.zeros(0), np.zeros((0, 0)), problem.evaluate(model).m2lnl()
    lo = np.array([c.bounds[0] for c in cands], dtype=float)
    hi = np.array([c.bounds[1] for c in cands], dtype=float)

    def put(m, values):
        for c, v in zip(cands, values):
            m = c.put(m, float(v))
        return m

    def cost(m):
        try:
            value = problem.evaluate(m).m2lnl()
        except (ValueError, FloatingPointError, ZeroDivisionError):
            return math.inf
        return value if math.isfinite(value) else math.inf

    current = model
    ev = problem.evaluate(current)
    dirs = directions(problem, current, cands, evaluation=ev)
    values, m2 = dirs.values.copy(), dirs.m2lnl
    free = np.ones(len(cands), dtype=bool)
    for _ in range(max_iter):
        f, g = dirs.fisher, dirs.score
        # parameters at a bound whose score pushes out of the range are held there (an active set)
        free = ~(((values <= lo) & (g < 0)) | ((values >= hi) & (g > 0)))
        step = np.zeros(len(cands))
        if free.any():
            idx = np.nonzero(free)[0]
            step[idx] = np.linalg.lstsq(f[np.ix_(idx, idx)], g[idx], rcond=1e-12)[0]
        predicted = float(step @ g)
        step = step * dirs.scales           # from typical sizes to the candidates' own units
        if not predicted > 1e-3:
            break
        accepted = False
        for _half in range(6):
            trial = np.clip(values + step, lo, hi)
            m_trial = put(current, trial)
            m2_trial = cost(m_trial)
            if m2_trial < m2:
                accepted = True
                break
            step = step / 2.0
        if not accepted:
            break
        current, values, improvement, m2 = m_trial, trial, m2 - m2_trial, m2_trial
        dirs = directions(problem, current, cands)
        if improvement < 1e-3:
            break
    f = dirs.fisher
    cov = np.zeros((len(cands), len(cands)))
    idx = np.nonzero(free)[0]
    if idx.size:
        try:
            cov[np.ix_(idx, idx)] = np.linalg.inv(f[np.ix_(idx, idx)])
        except np.linalg.LinAlgError:
            cov[np.ix_(idx, idx)] = np.linalg.pinv(f[np.ix_(idx, idx)])
    cov = cov * np.outer(dirs.scales, dirs.scales)
    if progress is not None:
        progress("joint fit: " + ", ".join(f"{c.name} {v:.5g}" for c, v in zip(cands, values)))
    return current, values, cov, m2
