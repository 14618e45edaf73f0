"""Statistics of the shape changes De, without TreeCorr: the paper's summary, histogram and angle test.

- :func:`de_statistics`: N, the mean intrinsic ellipticity (the mean g of
  B), the mean De with its standard error, and the fraction of objects with
  |De| (and |Delta|e||) above thresholds (1e-8 and 1e-4 in the paper);
- :func:`de_histogram`: the histogram of |De| (the paper's figure hist_de);
- :func:`theta_distribution`: the |De|-weighted distribution of the position
  angle of De in bins of |De|, with bootstrap errors, and a chi2 test against
  uniform whose variance is the one under the uniform hypothesis (the
  paper's figure bin_theta), its p-value from :func:`chi2_sf` or from
  simulations; :func:`theta_summary` condenses it per |De| bin.
"""

from __future__ import annotations

import math

import numpy as np

from .settings import DEFAULT_THETA_EDGES, DEFAULT_THRESHOLDS

#: position-angle bins over [-90, 90) degrees
N_ANGLE = 18
#: histogram of |De|: log bins from HIST_LO to HIST_HI, HIST_PER_DECADE per decade, plus under/overflow
HIST_LO, HIST_HI, HIST_PER_DECADE = 1e-12, 1.0, 5
#: bootstrap over at most this many groups of objects (random groups of equal size above it)
MAX_BOOT_GROUPS = 2_000
#: the chi2 p-value of a |De| bin comes from the chi2 distribution when the expected (weighted)
#: count per angle bin, n_eff / nangle, is at least this (Pearson's rule of thumb); else from
#: NULL_DRAWS simulations under the uniform hypothesis (see :func:`theta_distribution`)
MIN_EXPECTED = 5.0
NULL_DRAWS = 2_000
#: above this many objects in a |De| bin the simulation would be slow: the chi2 distribution is used
MAX_NULL_OBJECTS = 200_000


# ------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------

def _mean_err(values):
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    mean = float(np.mean(values))
    err = float(np.std(values, ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return mean, err


def _abs(de1, de2) -> np.ndarray:
    out = np.multiply(de1, de1)
    out += np.multiply(de2, de2)
    return np.sqrt(out, out=out)


def de_statistics(de1, de2, *, e1=None, e2=None, thresholds=DEFAULT_THRESHOLDS, dabs=None, flags=None) -> dict:
    """The paper's summary of De.

    Parameters
    ----------
    de1, de2 : ndarray
        Shape changes.
    e1, e2 : ndarray, optional
        Intrinsic shapes (g of the reference frame); NaN means when absent.
    thresholds : sequence of float
        |De| thresholds.
    dabs : ndarray, optional
        Delta|e| = |g(A)| - |g(B)| per object (the paper's text says both
        |De| and Delta|e|): then also n_dabs_ge and frac_dabs_ge, objects
        with |Delta|e|| >= threshold.
    flags : ndarray, optional
        Per object, the flags of its fits (flagged objects kept): then also
        n_clean (objects without a flag) and n_clean_ge (of them, those with
        |De| >= threshold).

    Returns
    -------
    dict
        n; e1_mean, e1_err, e2_mean, e2_err (standard errors); de1_mean,
        de1_err, de2_mean, de2_err; de_abs_mean, de_abs_max; threshold,
        n_ge and frac_ge (arrays: objects with |De| >= threshold, and their
        fraction of n); with ``dabs``, n_dabs_ge and frac_dabs_ge.
    """
    de1, de2 = np.asarray(de1, dtype=np.float64), np.asarray(de2, dtype=np.float64)
    absde = _abs(de1, de2)
    n = len(absde)
    out = {"n": n}
    for key, values in (("e1", e1), ("e2", e2), ("de1", de1), ("de2", de2)):
        stem = f"{key}_mean"
        mean, err = _mean_err(values) if values is not None else (math.nan, math.nan)
        out[stem], out[f"{key}_err"] = mean, err
    out["de_abs_mean"] = float(absde.mean()) if n else math.nan
    out["de_abs_max"] = float(absde.max()) if n else math.nan
    thresholds = np.asarray(sorted(thresholds), dtype=np.float64)
    out["threshold"] = thresholds
    out["n_ge"] = np.array([np.count_nonzero(absde >= t) for t in thresholds], dtype=np.int64)
    out["frac_ge"] = out["n_ge"] / n if n else np.full(len(thresholds), math.nan)
    if flags is not None:
        clean = np.asarray(flags) == 0
        out["n_clean"] = int(clean.sum())
        out["n_clean_ge"] = np.array([np.count_nonzero(clean & (absde >= t)) for t in thresholds], dtype=np.int64)
    if dabs is not None:
        a = np.abs(np.asarray(dabs, dtype=np.float64))
        out["n_dabs_ge"] = np.array([np.count_nonzero(a >= t) for t in thresholds], dtype=np.int64)
        out["frac_dabs_ge"] = out["n_dabs_ge"] / n if n else np.full(len(thresholds), math.nan)
    return out


def de_histogram(absde, *, lo=HIST_LO, hi=HIST_HI, per_decade=HIST_PER_DECADE) -> dict:
    """Counts of |De| in log bins, with an underflow bin [0, lo) and an overflow bin [hi, inf).

    Returns
    -------
    dict
        de_lo, de_hi (bin edges), count, frac (of all objects).
    """
    nbin = int(round(math.log10(hi / lo) * per_decade))
    edges = np.logspace(math.log10(lo), math.log10(hi), nbin + 1)
    index = np.searchsorted(edges, np.asarray(absde), side="right")
    count = np.bincount(index, minlength=nbin + 2)
    total = max(len(absde), 1)
    return {"de_lo": np.concatenate([[0.0], edges]), "de_hi": np.concatenate([edges, [np.inf]]),
            "count": count.astype(np.int64), "frac": count / total}


def position_angle(de1, de2) -> np.ndarray:
    """Position angle of De in degrees in [-90, 90), from the first axis towards the second."""
    theta = 0.5 * np.degrees(np.arctan2(de2, de1))
    return np.where(theta >= 90.0, theta - 180.0, theta)


def theta_distribution(de1, de2, *, edges=DEFAULT_THETA_EDGES, nangle=N_ANGLE, nboot=200, seed=1,
                       max_groups=MAX_BOOT_GROUPS, null_draws=NULL_DRAWS) -> dict:
    """|De|-weighted distribution of De's position angle in bins of |De|, and its test against uniform.

    In each |De| bin, ``frac[k]`` = sum of |De| over objects whose angle is
    in angle bin k / sum of |De| over the bin's objects (1/nangle each when
    the angle is uniform).

    Errors of the measured fractions (``frac_err``, drawn in the figure):
    standard deviation over ``nboot`` bootstrap resamples of the bin's
    objects.  When a bin holds more than ``max_groups`` objects, each object
    is first put into one of ``max_groups`` groups at random and the groups
    are resampled: for independent objects the group sums are independent
    too, so this has the same expected variance, at a cost O(nboot x
    max_groups) instead of O(nboot x n).

    The test against uniform uses the variance under the uniform hypothesis,
    not the bootstrap's (which is that of the observed fractions and would
    shrink with any excess).  Under the hypothesis the angles are
    independent of |De| and uniform, so given the weights w_i = |De_i| the
    indicator of object i in angle bin k is Bernoulli(p), p = 1/nangle, and
    ``frac[k] = sum_i w_i I_ik / W`` (W = sum w_i) has mean p and covariance
    ``(p delta_kl - p^2) / n_eff`` with ``n_eff = W^2 / sum w_i^2`` (Kish's
    effective number; n_eff = n for equal weights): the multinomial's, with
    n_eff in place of n.  ``frac_err_null`` is ``sqrt(p (1 - p) / n_eff)``
    and the chi2 is the Mahalanobis distance of frac from p in that
    (singular) covariance::

        chi2 = n_eff * sum_k (frac[k] - p)^2 / p,   nangle - 1 degrees of freedom

    (Pearson's statistic when the weights are equal).  Its p-value comes
    from the chi2 distribution when n_eff p >= :data:`MIN_EXPECTED` (the
    expected weighted count per angle bin); for fewer objects, where that
    approximation fails, from ``null_draws`` simulations of the statistic
    with the same weights and uniform angles (p = (1 + number of simulated
    chi2 >= the observed) / (1 + null_draws)).  Both assume independent
    objects: De of neighbours touched by one ghost, or of one object in
    several pooled pairs, are not, and then the test is too liberal.

    Returns
    -------
    dict
        Arrays with one entry per (|De| bin, angle bin): de_lo, de_hi, n
        (objects in the |De| bin), n_eff, theta_lo, theta_hi (degrees),
        frac, frac_err (bootstrap), frac_err_null (under uniform),
        chi2_uniform, dof_uniform and p_uniform (of the |De| bin; NaN when it
        is empty); and, per |De| bin, ``ngroups`` and ``p_method`` ('chi2' or
        'null-sim', '' when empty).
    """
    de1, de2 = np.asarray(de1, dtype=np.float64), np.asarray(de2, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    absde = _abs(de1, de2)
    inside = (absde >= edges[0]) & (absde < edges[-1])
    if not inside.all():
        absde, de1, de2 = absde[inside], de1[inside], de2[inside]
    # angle bin from atan2 in (-pi, pi]: position angle 0.5 atan2 + 90 deg over the bin width;
    # computed in place, as these arrays can hold millions of objects
    phase = np.arctan2(de2, de1)
    phase += math.pi
    phase *= nangle / (2 * math.pi)
    abin = phase.astype(np.intp)
    del phase
    abin %= nangle          # atan2 = pi (position angle 90) is -90
    debin = np.searchsorted(edges, absde, side="right")
    debin -= 1
    rng = np.random.default_rng(seed)
    # its own stream, so that the bootstrap draws do not depend on which bins were simulated
    null_rng = np.random.default_rng([int(seed), 2])
    width = 180.0 / nangle
    p0 = 1.0 / nangle
    keys = ("de_lo", "de_hi", "n", "n_eff", "theta_lo", "theta_hi", "frac", "frac_err", "frac_err_null",
            "chi2_uniform", "dof_uniform", "p_uniform")
    rows = {k: [] for k in keys}
    ngroups, methods = [], []
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = debin == j
        n = int(np.count_nonzero(sel))
        frac = np.full(nangle, np.nan)
        err = np.full(nangle, np.nan)
        groups = min(n, max_groups)
        neff, chi2, pvalue, method = 0.0, math.nan, math.nan, ""
        if n:
            w, a = absde[sel], abin[sel]
            sums = np.bincount(a, weights=w, minlength=nangle)
            total = float(sums.sum())
            if total > 0:
                frac = sums / total
                neff = total ** 2 / float(np.dot(w, w))
                chi2 = float(neff * np.sum((frac - p0) ** 2) / p0)
                if neff * p0 >= MIN_EXPECTED or n > MAX_NULL_OBJECTS:
                    pvalue, method = chi2_sf(chi2, nangle - 1), "chi2"
                else:
                    pvalue, method = _null_pvalue(chi2, w, nangle, null_draws, null_rng), "null-sim"
                err = _bootstrap_errors(w, a, nangle, groups, nboot, rng)
        ngroups.append(groups)
        methods.append(method)
        rows["de_lo"].append(np.full(nangle, lo))
        rows["de_hi"].append(np.full(nangle, hi))
        rows["n"].append(np.full(nangle, n, dtype=np.int64))
        rows["n_eff"].append(np.full(nangle, neff))
        rows["theta_lo"].append(-90.0 + width * np.arange(nangle))
        rows["theta_hi"].append(-90.0 + width * np.arange(1, nangle + 1))
        rows["frac"].append(frac)
        rows["frac_err"].append(err)
        rows["frac_err_null"].append(np.full(nangle, math.sqrt(p0 * (1 - p0) / neff) if neff > 0 else np.nan))
        rows["chi2_uniform"].append(np.full(nangle, chi2))
        rows["dof_uniform"].append(np.full(nangle, nangle - 1, dtype=np.int64))
        rows["p_uniform"].append(np.full(nangle, pvalue))
    out = {k: np.concatenate(v) for k, v in rows.items()}
    out["ngroups"] = ngroups
    out["p_method"] = methods
    return out


def chi2_sf(x: float, dof: int) -> float:
    """P(X >= x) for X ~ chi2 with an integer number of degrees of freedom.

    Exact closed form, Q(dof/2, x/2) from Q(1/2, h) = erfc(sqrt(h)) or
    Q(1, h) = exp(-h) and Q(a + 1, h) = Q(a, h) + h^a exp(-h) / Gamma(a + 1):
    a sum of positive terms, so accurate to rounding; scipy.special would
    add ~0.1 s of import to every ``perscli correlate``.
    """
    if math.isnan(x):
        return math.nan
    if x <= 0:
        return 1.0
    h = 0.5 * x
    a, q = (0.5, math.erfc(math.sqrt(h))) if dof % 2 else (1.0, math.exp(-h))
    while a < 0.5 * dof - 1e-9:
        q += math.exp(a * math.log(h) - h - math.lgamma(a + 1))
        a += 1.0
    return min(q, 1.0)


def _bootstrap_errors(w, a, nangle, groups, nboot, rng) -> np.ndarray:
    """Standard deviation of the weighted angle fractions over bootstrap resamples of (groups of) objects."""
    n = len(w)
    index = np.arange(n) if groups == n else rng.integers(0, groups, n)
    index *= nangle
    index += a
    per_group = np.bincount(index, weights=w, minlength=groups * nangle).reshape(groups, nangle)
    del index
    draws = rng.integers(0, groups, size=(nboot, groups), dtype=np.intp)
    draws += np.arange(nboot)[:, None] * groups
    times = np.bincount(draws.ravel(), minlength=nboot * groups).reshape(nboot, groups)
    boot = times.astype(np.float64) @ per_group
    total = boot.sum(axis=1, keepdims=True)
    boot = boot[total[:, 0] > 0] / total[total[:, 0] > 0]
    return boot.std(axis=0, ddof=1) if len(boot) > 1 else np.full(nangle, np.nan)


def _null_pvalue(chi2: float, w: np.ndarray, nangle: int, draws: int, rng) -> float:
    """P(chi2 >= observed) under uniform angles with the same weights, by simulation."""
    n = len(w)
    total = float(w.sum())
    neff = total ** 2 / float(np.dot(w, w))
    p0 = 1.0 / nangle
    # chunks of at most ~4 million simulated angles keep memory flat for any n
    chunk = max(1, min(draws, 4_000_000 // max(n, 1)))
    hits = done = 0
    offsets = None
    while done < draws:
        m = min(chunk, draws - done)
        sim = rng.integers(0, nangle, size=(m, n), dtype=np.intp)
        if offsets is None or len(offsets) != m:
            offsets = (np.arange(m) * nangle)[:, None]
        sim += offsets
        sums = np.bincount(sim.ravel(), weights=np.broadcast_to(w, (m, n)).ravel(),
                           minlength=m * nangle).reshape(m, nangle)
        t = neff * np.sum((sums / total - p0) ** 2, axis=1) / p0
        # ties are common with few objects: count them as at least as extreme (rounding aside)
        hits += int(np.count_nonzero(t >= chi2 * (1 - 1e-9) - 1e-12))
        done += m
    return (1 + hits) / (1 + draws)


def theta_summary(theta: dict) -> list:
    """Per |De| bin of a :func:`theta_distribution`: de_lo, de_hi, n, n_eff, chi2, dof, p, p_method."""
    nangle = len(theta["p_method"]) and len(theta["de_lo"]) // len(theta["p_method"])
    out = []
    for k, method in enumerate(theta["p_method"]):
        i = k * nangle
        out.append({"de_lo": float(theta["de_lo"][i]), "de_hi": float(theta["de_hi"][i]), "n": int(theta["n"][i]),
                    "n_eff": float(theta["n_eff"][i]), "chi2": float(theta["chi2_uniform"][i]),
                    "dof": int(theta["dof_uniform"][i]), "p": float(theta["p_uniform"][i]), "p_method": method})
    return out
