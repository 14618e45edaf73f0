"""Misspecification checks: what no candidate describes, said out loud rather than absorbed.

A likelihood fit of the most flexible candidate absorbs whatever the model
lacks: correlated noise and outliers raise the read noise, a flat-field
error tilts the gain, a shifted PSF inflates the read noise.  Each check
here looks for one such signature in the residuals of the final model with a
test statistic whose distribution when the model is right is known (a
chi^2, or a Poisson count), and fires when its p-value falls below
:data:`ALPHA`.  A check that fires goes to the report's ``unexplained`` list,
and the named effects it would be mistaken for (:attr:`Check.blocks`) are
withdrawn (:func:`perscli.diagnose.search.search`).

The checks:

- ``rows_columns``: the mean residual of each detector row and column of
  each exposure (every third pixel, so that interpixel capacitance leaves
  them independent; outliers left out) against the variance the model gives
  it (white noise, plus its ``correlated_read_noise``): row and column noise
  the model lacks.
- ``line_correlation``: neighbouring rows (and columns) offset alike, at
  lags 2-4 (Box-Pierce): 1/f noise, which independent row and column offsets
  do not describe.
- ``outliers``: pixels more than :data:`OUTLIER_SIGMA` sigma from their
  expectation, against what the noise gives, and pixels that are outliers in
  several exposures: hot pixels, cosmic rays, heavy tails.
- ``variance_shape``: the variance of the residuals in bins of the expected
  signal against a constant: noise that grows with the signal (a flat
  field, light changing during a ramp) rather than a read noise or a gain.
- ``flat_field``: in each of 8 x 8 blocks of the detector, the residual's
  slope against the expected signal, against their common value: a gain
  that varies over the detector.
- ``psf_shift``: each source's residual against its expectation's gradient
  (star by star, and all together): sources or the PSF displaced.
- ``psf_shape``: each source's residual against its expectation's
  Laplacian: sources wider or narrower than any named effect makes them.
- ``persistence_decay`` and ``persistence_fluence``: the persistence law
  split by how many exposures back the light came and by its fluence, each
  part's amplitude fitted: a persistence that decays otherwise in time than
  the law, or depends otherwise on the fluence (only saturated pixels).

Their false-alarm rates with the right model are measured on null
simulations from an independent detector chain by
tests/test_diagnose_calibrated.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize_scalar
from scipy.stats import norm, poisson

from ..stats.de_stats import chi2_sf
from .noise import counts_gain, dispersion, noise_correlation, significance

#: a check fires below this p-value: 8 checks at 1e-4 each keep the false alarms of a null case well
#: under 1% (measured: tests/test_diagnose_calibrated.py)
ALPHA = 1e-4
#: a pixel this many sigma from its expectation is an outlier (Gaussian noise: 2.6e-12 per pixel)
OUTLIER_SIGMA = 7.0


@dataclass
class Check:
    """One misspecification check's outcome."""

    name: str
    statistic: float
    dof: float
    p_value: float
    description: str
    blocks: tuple = ()
    detail: dict = field(default_factory=dict)
    #: why a fit it withdraws cannot stand, in a few words (the description when not given)
    why: str = ""

    @property
    def reason(self) -> str:
        return self.why or self.description

    @property
    def fired(self) -> bool:
        return self.p_value < ALPHA

    @property
    def sigma(self) -> float:
        """The p-value as a two-sided Gaussian significance (for a chi^2 statistic on the log scale, so that
        strong signals are not all cut at the 37 sigma of p = 1e-300)."""
        if self.name != "outliers" and self.dof and self.dof >= 1 and self.p_value < 1e-200:
            return significance(self.statistic, int(round(self.dof)))
        p = max(self.p_value, 1e-300)
        return float(norm.isf(p / 2.0))

    def as_dict(self) -> dict:
        return {"probe": self.name, "significance": self.sigma, "p_value": self.p_value,
                "statistic": self.statistic, "dof": self.dof, "description": self.description,
                "blocks": list(self.blocks), "fired": self.fired, **({"detail": self.detail} if self.detail else {})}


def _chi2_p(chi2: float, dof: float) -> float:
    # the one chi^2 survival function (exact for whole degrees of freedom); dof here are whole numbers
    return chi2_sf(chi2, int(round(max(dof, 1)))) if dof > 0 else 1.0


def _planes(problem, evaluation, variance: bool = False):
    """Per piece: (exposure index, first row, residual image, expectation image, mask[, variance])."""
    res = evaluation.residuals()
    pieces = evaluation.pieces or [(k, slice(0, r.shape[0])) for k, r in enumerate(res)]
    for (i, rows), r, m, mask, v in zip(pieces, res, evaluation.mean, evaluation.mask, evaluation.variance):
        yield ((i, (rows.start or 0), r, m, mask, v) if variance else (i, (rows.start or 0), r, m, mask))


#: pixels further than this from their expectation are left out of row and column means (a hot pixel or a
#: cosmic ray would otherwise pass for a row's offset); Gaussian noise loses 6e-7 of its pixels
LINE_CLIP = 5.0


def line_means(problem, evaluation, model=None) -> dict:
    """The mean residual of each detector row and column of each exposure, with its white variance.

    Rows use every third pixel and columns every third row, so that
    interpixel capacitance leaves the pixels in a mean independent; pixels
    more than :data:`LINE_CLIP` sigma out are left out, and each exposure's
    mean residual is removed first (an offset is not a row's).  The white
    variance of a mean is the model's per-pixel variance less its row and
    column components (``correlated_read_noise``), divided by the pixels.

    Returns
    -------
    dict
        ``{'row': [...], 'column': [...]}``, each a list per exposure of
        ``(index, mean, white variance, modelled line variance)`` arrays in
        counts, sorted by index; plus ``'gain'``: e- per count per exposure.
    """
    row_sig = float(model.value("correlated_read_noise", "row", off=0.0)) if model is not None else 0.0
    col_sig = float(model.value("correlated_read_noise", "column", off=0.0)) if model is not None else 0.0
    acc = {}
    for i, r0, r, m, mask, v in _planes(problem, evaluation, variance=True):
        if r.ndim != 2 or r.shape[1] < 8:
            continue
        exp = problem.exposures[i] if i < len(problem.exposures) else None
        g = counts_gain(problem, model, exp) if exp is not None else 1.0
        line_var = (row_sig ** 2, col_sig ** 2)
        corr = (line_var[0] + line_var[1]) / g ** 2
        ok = mask & np.isfinite(r) & (np.abs(np.nan_to_num(r)) < LINE_CLIP)
        raw = np.where(ok, evaluation_raw(r, v), 0.0)
        white = np.where(ok, np.maximum(v - corr, 0.0), 0.0)
        a = acc.setdefault(i, {"g": g, "lv": (line_var[0] / g ** 2, line_var[1] / g ** 2), "rows": [], "cols": {}})
        # rows: every third pixel along the row
        sub = (slice(None), slice(None, None, 3))
        n = ok[sub].sum(axis=1)
        a["rows"].append((np.arange(r0, r0 + r.shape[0]), raw[sub].sum(axis=1), white[sub].sum(axis=1), n))
        # columns: every third row, counted from the detector's first row so stripes do not overlap in it
        keep = ((np.arange(r0, r0 + r.shape[0]) % 3) == 0)
        c = a["cols"]
        c["sum"] = c.get("sum", 0.0) + raw[keep].sum(axis=0)
        c["var"] = c.get("var", 0.0) + white[keep].sum(axis=0)
        c["n"] = c.get("n", 0) + ok[keep].sum(axis=0)
    out = {"row": [], "column": [], "gain": []}
    for i in sorted(acc):
        a = acc[i]
        idx = np.concatenate([x[0] for x in a["rows"]])
        s = np.concatenate([x[1] for x in a["rows"]])
        w = np.concatenate([x[2] for x in a["rows"]])
        n = np.concatenate([x[3] for x in a["rows"]])
        cs, cw, cn = a["cols"]["sum"], a["cols"]["var"], a["cols"]["n"]
        # the exposure's own mean residual out
        total = float(s.sum() + 0.0)
        count = float(n.sum())
        mu = total / count if count else 0.0
        for key, (ii, ss, ww, nn, lv) in (("row", (idx, s, w, n, a["lv"][0])),
                                        ("column", (np.arange(len(cs)), cs, cw, cn, a["lv"][1]))):
            good = nn >= 8
            order = np.argsort(ii[good], kind="stable")
            nn_ = nn[good][order].astype(float)
            out[key].append((ii[good][order], ss[good][order] / nn_ - mu, ww[good][order] / nn_ ** 2,
                             np.full(nn_.shape, lv)))
        out["gain"].append(a["g"])
    return out


def evaluation_raw(r, v):
    """data - expectation, from the normalised residual and the variance."""
    return np.nan_to_num(r) * np.sqrt(v)


def line_variance_fit(means: list) -> tuple:
    """The variance common to every line (row or column) beyond white noise, by maximum likelihood.

    Parameters
    ----------
    means : list of (index, mean, white variance, modelled) arrays, as :func:`line_means` gives.

    Returns
    -------
    (float, float, float)
        The extra variance in counts^2 (>= 0), the improvement of -2 ln L
        over none, and the error of its square root (from the curvature).
    """
    m = np.concatenate([x[1] for x in means]) if means else np.zeros(0)
    w = np.concatenate([x[2] for x in means]) if means else np.zeros(0)
    if m.size < 8:
        return 0.0, 0.0, float("nan")
    ok = w > 0
    m, w = m[ok], w[ok]

    def cost(rho):
        s = w + rho * rho
        return float(np.sum(m * m / s + np.log(s)))

    hi = max(float(np.sqrt(max(np.mean(m * m) * 4.0, 1e-12))), 1e-6)
    res = minimize_scalar(cost, bounds=(0.0, hi), method="bounded", options={"xatol": hi * 1e-6})
    rho = float(res.x) if res.fun < cost(0.0) else 0.0
    delta = cost(0.0) - cost(rho)
    h = max(rho * 1e-2, hi * 1e-4)
    a, b = max(rho - h, 0.0), rho + h
    d2 = (cost(b) - 2 * cost(rho) + cost(a)) / ((b - a) / 2.0) ** 2 if rho > h else float("nan")
    err = float(math.sqrt(2.0 / d2)) if d2 == d2 and d2 > 0 else float("nan")
    return rho * rho, max(delta, 0.0), err


def rows_columns(problem, evaluation, model=None) -> Check:
    lines = line_means(problem, evaluation, model)
    chi2, dof, worst = 0.0, 0, 0.0
    for key in ("row", "column"):
        for _, m, w, lv in lines[key]:
            z = m / np.sqrt(w + lv)
            chi2 += float(np.sum(z * z))
            dof += int(z.size)
            if z.size:
                worst = max(worst, float(np.max(np.abs(z))))
    p = _chi2_p(chi2, dof)
    return Check("rows_columns", chi2, dof, p, "rows or columns offset from each other beyond the model's noise "
                 "(correlated read noise, 1/f noise, bias drifts)",
                 blocks=("read_noise", "offset", "dark"), detail={"worst_z": worst})


def line_correlation(problem, evaluation, model=None, lags=(2, 3, 4)) -> Check:
    """Neighbouring rows (and columns) offset alike: 1/f noise rather than independent row and column offsets.

    The Box-Pierce statistic of each exposure's standardised row and column
    means at ``lags`` (interpixel capacitance and brighter-fatter couple
    adjacent lines only, so lag 1 is left out), against chi^2.
    """
    lines = line_means(problem, evaluation, model)
    chi2, dof = 0.0, 0
    for key in ("row", "column"):
        for idx, m, w, lv in lines[key]:
            z = m / np.sqrt(w + lv)
            for lag in lags:
                # pairs of lines ``lag`` apart, both present
                pos = {int(k): j for j, k in enumerate(idx)}
                pairs = [(j, pos[int(k) + lag]) for j, k in enumerate(idx) if int(k) + lag in pos]
                if len(pairs) < 30:
                    continue
                a = np.array([z[j] for j, _ in pairs])
                b = np.array([z[k] for _, k in pairs])
                rho = float(np.sum(a * b) / len(pairs))
                chi2 += len(pairs) * rho * rho
                dof += 1
    return Check("line_correlation", chi2, dof, _chi2_p(chi2, dof),
                 "neighbouring rows or columns offset alike (1/f noise: no independent row and column offsets)",
                 blocks=("correlated_read_noise", "read_noise", "offset", "dark"))


def outliers(problem, evaluation) -> Check:
    n, count, repeated = 0, 0, 0
    per_exposure = {}
    for i, r0, r, _, mask in _planes(problem, evaluation):
        big = mask & (np.abs(np.nan_to_num(r)) > OUTLIER_SIGMA)
        n += int(mask.sum())
        count += int(big.sum())
        if r.ndim == 2:
            per_exposure.setdefault(i, []).append((r0, big))
    # the same pixel an outlier in two or more exposures: a hot pixel, not a passing cosmic ray
    if len(per_exposure) > 1:
        maps = {}
        for i, parts in per_exposure.items():
            for r0, big in parts:
                for y, x in zip(*np.nonzero(big)):
                    maps.setdefault((r0 + y, x), set()).add(i)
        repeated = sum(1 for v in maps.values() if len(v) > 1)
    rate = 2.0 * norm.sf(OUTLIER_SIGMA)
    # Poisson noise of small counts has heavier tails than Gaussian noise: 100 times the Gaussian rate
    expected = max(n * rate * 100.0, 1e-3)
    p = float(poisson.sf(count - 1, expected)) if count else 1.0
    return Check("outliers", float(count), expected, p,
                 f"pixels more than {OUTLIER_SIGMA:g} sigma from the model ({count}; {repeated} in several "
                 "exposures: hot pixels; in one: cosmic rays or other outliers)",
                 blocks=("read_noise", "dark", "offset", "correlated_read_noise"), detail={"count": count, "repeated": repeated, "pixels": n})


def variance_shape(problem, evaluation, *, nbins: int = 10, blocks=("read_noise",)) -> Check:
    rs, ms = [], []
    for _, _, r, m, mask in _planes(problem, evaluation):
        rs.append(r[mask])
        ms.append(m[mask])
    if not rs:
        return Check("variance_shape", 0.0, 0, 1.0, "noise that grows with the signal", blocks=blocks)
    r, m = np.concatenate(rs), np.concatenate(ms)
    ok = np.isfinite(r) & np.isfinite(m)
    r, m = r[ok], m[ok]
    if r.size < 200:
        return Check("variance_shape", 0.0, 0, 1.0, "noise that grows with the signal", blocks=blocks)
    # the brightest 1% out: the model's variance is first order there (saturation, nonlinearity)
    cut = m <= np.quantile(m, 0.99)
    r, m = r[cut], m[cut]
    edges = np.unique(np.quantile(m, np.linspace(0, 1, nbins + 1)))
    idx = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, len(edges) - 2)
    v, w, centre = [], [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        k = int(sel.sum())
        if k < 30:
            continue
        x = r[sel]
        v.append(float(np.var(x)))
        w.append(k / 2.0)             # 1 / variance of a sample variance of unit Gaussian noise
        centre.append(float(np.mean(m[sel])))
    v, w = np.array(v), np.array(w)
    if v.size < 3:
        return Check("variance_shape", 0.0, 0, 1.0, "noise that grows with the signal", blocks=blocks)
    vbar = float(np.sum(w * v) / np.sum(w))
    chi2 = float(np.sum(w * (v - vbar) ** 2))
    dof = v.size - 1
    return Check("variance_shape", chi2, dof, _chi2_p(chi2, dof),
                 "the residuals' variance changes with the signal (noise a read noise or one gain does not make)",
                 blocks=blocks, detail={"signal": centre, "variance": v.tolist()})


#: what a flat-field error can pass for: it multiplies every source's light, so anything that acts on the signal
#: (and persistence, whose ghosts sit where the sources were when pointings repeat)
FLAT_FIELD_BLOCKS = ("gain", "nonlinearity", "reciprocity", "persistence", "brighter_fatter", "ipc")


def flat_field(problem, evaluation) -> Check:
    ny, nx = problem.shape
    num = np.zeros(64)
    den = np.zeros(64)
    for _, r0, r, m, mask, v in _planes(problem, evaluation, variance=True):
        if r.ndim != 2:
            continue
        yy = (np.arange(r0, r0 + r.shape[0])[:, None] * 8 // ny) * 8 + (np.arange(nx)[None, :] * 8 // nx)
        # a gain error eps in a block shows as r = eps * m / sigma
        g = np.where(mask, m / np.sqrt(v), 0.0)
        rr = np.where(mask, np.nan_to_num(r), 0.0)
        num += np.bincount(yy.ravel(), weights=(g * rr).ravel(), minlength=64)
        den += np.bincount(yy.ravel(), weights=(g * g).ravel(), minlength=64)
    ok = den > 0
    if ok.sum() < 4:
        return Check("flat_field", 0.0, 0, 1.0, "a gain that varies over the detector",
                     blocks=FLAT_FIELD_BLOCKS)
    eps = num[ok] / den[ok]
    err2 = 1.0 / den[ok]
    mean = float(np.sum(eps / err2) / np.sum(1.0 / err2))
    chi2 = float(np.sum((eps - mean) ** 2 / err2))
    dof = int(ok.sum()) - 1
    return Check("flat_field", chi2, dof, _chi2_p(chi2, dof),
                 "the response differs from block to block of the detector (a flat-field error)",
                 blocks=FLAT_FIELD_BLOCKS,
                 detail={"rms": float(np.std(eps)), "mean": mean})


#: a source, for the star-by-star checks: pixels whose expectation is this many sigma above the frame's median
SOURCE_SIGMA = 20.0


def _sources(problem, evaluation):
    """Per source: (design columns, normalised residuals) of its pixels, columns the expectation's x and y
    gradients and its Laplacian over sigma (a shift moves light along the gradient, a wider or narrower PSF
    along the Laplacian)."""
    for _, _, r, m, mask, v in _planes(problem, evaluation, variance=True):
        if r.ndim != 2 or min(r.shape) < 5:
            continue
        m = np.asarray(m, dtype=np.float64)
        sigma = np.sqrt(v)
        ok = mask & np.isfinite(r)
        if not ok.any():
            continue
        level = np.median(m[ok])
        bright = ok & (m - level > SOURCE_SIGMA * sigma)
        if not bright.any():
            continue
        labels, n = ndimage.label(ndimage.binary_dilation(bright, iterations=2))
        gy, gx = np.gradient(m)
        lap = ndimage.laplace(m)
        cols = np.stack([gx / sigma, gy / sigma, lap / sigma])
        for k, sl in enumerate(ndimage.find_objects(labels), start=1):
            if sl is None:
                continue
            sel = (labels[sl] == k) & ok[sl]
            if sel.sum() < 6:
                continue
            yield cols[(slice(None),) + sl][:, sel], np.nan_to_num(r[sl][sel])


def _regression_chi2(a, b):
    """chi^2 of the least-squares coefficients of b on the rows of a (unit-variance b): b'A (A'A)^-1 A'b."""
    ata = a @ a.T
    atb = a @ b
    if not np.all(np.isfinite(ata)) or np.linalg.cond(ata) > 1e12:
        return None, None
    coef = np.linalg.solve(ata, atb)
    return float(coef @ atb), coef


def psf_shift(problem, evaluation) -> Check:
    """Sources displaced from where the model puts them: the residual of each source against its
    expectation's gradient (2 degrees of freedom a source), and of all of them together (a common shift)."""
    per_star, dof, n = 0.0, 0, 0
    ata, atb = np.zeros((2, 2)), np.zeros(2)
    for cols, r in _sources(problem, evaluation):
        a = cols[:2]
        c2, _ = _regression_chi2(a, r)
        if c2 is None:
            continue
        per_star += c2
        dof += 2
        n += 1
        ata += a @ a.T
        atb += a @ r
    blocks = ("read_noise", "ipc", "brighter_fatter", "nonlinearity", "reciprocity")
    if n == 0 or np.linalg.det(ata) <= 0:
        return Check("psf_shift", 0.0, 0, 1.0, "sources displaced from where the model puts them", blocks=blocks)
    shift = np.linalg.solve(ata, atb)
    common = float(shift @ atb)
    # the smaller p-value of the two statistics, Bonferroni-corrected for the pair
    p = min(1.0, 2.0 * min(_chi2_p(common, 2), _chi2_p(per_star, dof)))
    return Check("psf_shift", per_star, dof, p,
                 "sources displaced from where the model puts them (a shifted PSF or wrong positions)",
                 blocks=blocks, detail={"shift_x": float(shift[0]), "shift_y": float(shift[1]),
                                        "common_chi2": common, "sources": n})


def psf_shape(problem, evaluation) -> Check:
    """Sources wider or narrower than the model's, star by star (their residual along the expectation's
    Laplacian, the shift fitted with it): run on the final model, it blocks nothing."""
    chi2, dof = 0.0, 0
    for cols, r in _sources(problem, evaluation):
        c3, coef = _regression_chi2(cols, r)
        c2, _ = _regression_chi2(cols[:2], r)
        if c3 is None or c2 is None:
            continue
        chi2 += max(c3 - c2, 0.0)
        dof += 1
    return Check("psf_shape", chi2, dof, _chi2_p(chi2, dof) if dof else 1.0,
                 "sources wider or narrower than the model makes them (a PSF, charge spreading or "
                 "interpixel coupling no candidate describes)")


#: the earlier exposures' lags (1, 2, 3 and more back) whose persistence the decay check compares
LAG_GROUPS = 3
#: fluences below this share of the law's half well leave a persistence indistinguishable from an offset (the
#: sky's ~0.05 e- pedestal): the fluence check leaves them as the law has them
FAINT_SHARE = 0.02
#: a pixel at this share of the full well or above is saturated
SATURATED_SHARE = 0.999


def persistence_law(problem, evaluation, model) -> list:
    """Whether the persistence in the data has the law's shape: its decay with time, its dependence on fluence.

    The law of ``model`` (at A = 1; its parameters as the model has them,
    freed ones included, whether or not persistence is on) is split into
    parts by the earlier exposure's lag (1, 2, 3 or more exposures back)
    and by its fluence (from 2% of the half well to the half well: the
    linear branch; to the full well; saturated).  Each part passes through
    the chain of ``model`` (:meth:`~perscli.diagnose.likelihood.Problem.evaluate`
    with the part added to the persistence) and its amplitude is fitted to
    the residuals by weighted least squares, in units of the law's A.  With
    the law's shape right every part has the same amplitude (the model's A
    fitted, or not, leaves a common one), so:

    - ``persistence_decay``: the amplitudes per lag (the fluence ranges
      summed as the law has them) against one common value, chi^2 with one
      degree of freedom less than lags: persistence that decays otherwise in
      time than the law (an exponential, another power);
    - ``persistence_fluence``: the amplitudes per fluence range against one
      value: persistence that depends otherwise on the earlier fluence
      (only saturated pixels persisting, another turn-on).

    Their chi^2 are divided by the noise correlation's dispersion along the
    law's direction (:func:`perscli.diagnose.noise.dispersion`).  Each check
    blocks persistence: a fitted A would only absorb it.  Returns the checks
    the data allow (none for one exposure, a law that is not the Fermi law,
    or earlier exposures combined by their maximum).
    """
    if len(problem.exposures) < 2 or not hasattr(problem, "persistence_parts"):
        return []
    pm = model.persistence_model()
    if pm.kind != "fermi" or pm.combine != "sum":
        return []
    well = model.value("saturation", "full_well", off=None)
    faint = FAINT_SHARE * pm.half_well

    def split(j, i, fluence):
        lag = min(i - j, LAG_GROUPS)
        bins = {0: (fluence > faint) & (fluence <= pm.half_well)}
        if well:
            bins[1] = (fluence > pm.half_well) & (fluence < SATURATED_SHARE * well)
            bins[2] = fluence >= SATURATED_SHARE * well
        else:
            bins[1] = fluence > pm.half_well
        return {(lag, b): m for b, m in bins.items() if m.any()}

    parts = problem.persistence_parts(model, split)
    if not parts:
        return []
    keys = sorted(parts)
    # each part through the chain: a small amplitude (the chain is linear over it), per unit of A
    eps = 0.01
    cols = []
    masks = evaluation.mask
    for key in keys:
        moved = problem.evaluate(model, extra={i: eps * c for i, c in parts[key].items()})
        cols.append([((m1 - m0) / eps).astype(np.float32) for m1, m0 in zip(moved.mean, evaluation.mean)])
    k = len(keys)
    ata, atb = np.zeros((k, k)), np.zeros(k)
    for piece, (e, v, d, m) in enumerate(zip(evaluation.mean, evaluation.variance, evaluation.data, masks)):
        x = np.stack([c[piece][m] for c in cols]).astype(np.float64)
        if not np.any(x):
            continue
        w = 1.0 / v[m]
        ata += (x * w) @ x.T
        atb += x @ (w * (d[m] - e[m]))
    keep = np.diag(ata) > 0
    keys = [kk for kk, ok in zip(keys, keep) if ok]
    ata, atb = ata[np.ix_(keep, keep)], atb[keep]
    cols = [c for c, ok in zip(cols, keep) if ok]
    if not keys:
        return []
    # the noise neighbouring pixels share, along the law's whole direction
    whole = SimpleNamespace(mean=[e + sum(c[p] for c in cols) * max(pm.A, 0.01) for p, e in
                                  enumerate(evaluation.mean)])
    disp = dispersion(noise_correlation(problem, model), evaluation, whole)
    base_a = pm.A if model.enabled("persistence") else 0.0
    out = []
    for name, index, labels in (("persistence_decay", 0, {1: "1", 2: "2", LAG_GROUPS: f">={LAG_GROUPS}"}),
                                ("persistence_fluence", 1, {0: "below half the well", 1: "half the well to the well",
                                                             2: "saturated"})):
        groups = sorted({kk[index] for kk in keys})
        if len(groups) < 2:
            continue
        # the parts summed within each group: the law's own shape along the other axis
        s = np.array([[1.0 if kk[index] == g else 0.0 for kk in keys] for g in groups])
        f = s @ ata @ s.T
        b = s @ atb
        try:
            cov = np.linalg.inv(f)
        except np.linalg.LinAlgError:
            continue
        amp = cov @ b
        ones = np.ones(len(groups))
        w = np.linalg.solve(cov, ones)
        common = float(w @ amp / (w @ ones))
        diff = amp - common
        chi2 = float(diff @ np.linalg.solve(cov, diff)) / disp
        signal = float(amp @ np.linalg.solve(cov, amp)) / disp
        dof = len(groups) - 1
        err = np.sqrt(np.clip(np.diag(cov) * disp, 0.0, None))
        total = base_a + amp
        detail = {"groups": [labels.get(g, str(g)) for g in groups], "amplitude": total.tolist(),
                  "error": err.tolist(), "law_A": base_a, "gamma": pm.gamma,
                  "signal_sigma": significance(signal, len(groups)), "dispersion": disp}
        shown = ", ".join(f"{labels.get(g, g)}: {t:.3g} +- {e:.2g}" for g, t, e in zip(groups, total, err))
        detail["shown"] = shown
        if name == "persistence_decay":
            why = f"persistence-like signal whose decay is not the model's law (t^-{pm.gamma:.3g})"
            description = (f"{why}: its amplitude, in units of the law's A, by how many exposures back the light "
                           f"came: {shown}")
        else:
            saturated_only = (groups[-1] == 2 and total[-1] > 5 * err[-1]
                              and all(abs(t) < 3 * e or abs(t) < 0.1 * total[-1]
                                      for t, e in zip(total[:-1], err[:-1])))
            why = ("persistence from saturated pixels only" if saturated_only
                   else "persistence whose dependence on the earlier fluence is not the law's")
            description = f"{why}: its amplitude, in units of the law's A, by earlier fluence: {shown}"
        out.append(Check(name, chi2, dof, _chi2_p(chi2, dof), description, blocks=("persistence",),
                         detail=detail, why=why))
    return out


def run_checks(problem, evaluation, model=None, *, ramp: bool = False, final: bool = False) -> list:
    """Every check the data allow, on ``evaluation`` (the current model's residuals on the fit pixels).

    ``final``: the model the search ends with; the checks that block
    nothing (the sources' shape) are added.
    """
    out = [rows_columns(problem, evaluation, model), line_correlation(problem, evaluation, model),
           outliers(problem, evaluation),
           variance_shape(problem, evaluation, blocks=("read_noise", "gain") if ramp else ("read_noise",))]
    if not ramp:
        out += [flat_field(problem, evaluation), psf_shift(problem, evaluation)]
        if model is not None:
            out += persistence_law(problem, evaluation, model)
        if final:
            out.append(psf_shape(problem, evaluation))
    return out
