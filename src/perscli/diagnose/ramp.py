"""A lone ramp, self-predicted: each pixel's later reads from its rate in the earliest reads.

Without a simulation the expectation comes from the data themselves: the
charge a pixel collected by an early reference read (reads minus the first,
so the bias drops out) gives its rate, and a linear accumulation at that rate
predicts every later read.  Effects that bend the ramp (nonlinearity), scale
its noise (gain) or add to it (read noise) then show in the later reads.  The
variance of each prediction is exact for a linear ramp: Poisson noise of the
charge between the reads, and the read noise and rounding of the three reads
involved (the read itself, the reference read and the first read).

Persistence from an earlier ramp (its fluence, the last read times the
gain) arrives at the law's decaying rate rather than the pixel's own: the
prediction takes it out of the reference read and adds it back at each
read, so persistence is a candidate when several ramps are given.

The gain is the header's unless the ramps themselves refute it: a
photon-transfer curve (:func:`photon_transfer`: two ramps of one scene, or
one ramp's second differences) that Poisson noise of one gain describes and
that measures it to 5%.  Grism time series and other scenes whose light
changes hold no such case; diagnose then says so and keeps the header gain
(a gain fit would absorb the extra variance).  The read noise of the
starting model comes from the faintest pixels' second differences (pixels
that see the sky: a WFC3-IR frame's reference pixels are quieter).

Pixels whose ramps jump (a cosmic ray, or light that changes during the
exposure, as in grism time series) cannot be predicted from their early
reads; they are found once, with the starting model, as pixels with a read
more than :data:`JUMP_SIGMA` sigma from its prediction, and left out of every
fit and gap (their number is reported), as a pipeline's jump step would.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage
from scipy.stats import chi2

from .. import PerscliError
from ..detector.effects import REGISTRY
from ..detector.model import DetectorModel, Effect
from ..detector.persistence import persistence_charge
from ..io.frames import SECONDS_PER_DAY
from .data import measured_fluence
from .likelihood import Evaluation
from .probes import _neighbours
from .settings import DEFAULT_FIT_PIXELS

#: a read this many sigma from its self-prediction marks the pixel's ramp as jumping
JUMP_SIGMA = 10.0

#: effects a self-predicted ramp can constrain
RAMP_CANDIDATES = ("persistence", "nonlinearity", "read_noise", "gain")


#: a photon-transfer gain is trusted only when its estimates in the ranges of signal agree (chi^2 p-value
#: above this) and it is measured to :data:`PTC_PRECISION`: variance that grows faster than Poisson noise
#: (light that changes between or during exposures, pointing jitter across a spectrum, scenes that differ
#: between two exposures) makes them disagree
PTC_CONSISTENCY_P = 0.01
PTC_PRECISION = 0.05
#: a read this many sigma from its pixel's constant rate (its median interval) marks the pixel's light as
#: changing during the ramp: its second differences hold the change, not only noise
STEADY_SIGMA = 5.0
#: a variance that grows as the square of the signal (a scene that differs between two ramps by a share of
#: its light, light that changes) is found when the quadratic term of the curve exceeds this many errors
QUADRATIC_SIGMA = 4.0


def _clipped_variance(d: np.ndarray) -> float:
    """The variance of ``d`` with points beyond 4 sigma left out, iterated (hot pixels and jumps out)."""
    for _ in range(5):
        if d.size < 10:
            break
        m, sd = d.mean(), d.std()
        keep = np.abs(d - m) < 4.0 * sd
        if keep.all():
            break
        d = d[keep]
    return float(d.var(ddof=1)) if d.size > 1 else float("nan")


#: signal groups of a photon-transfer curve (spaced evenly in the logarithm of the signal), and the fewest
#: pixels (or pixel-intervals) a group needs
PTC_GROUPS = 8
PTC_MIN_GROUP = 200


def _equal_intervals(exp):
    """The ramp's first differences over its equally spaced reads: (intervals, ny, nx), and their spacing."""
    spacing = np.diff(np.concatenate([[0.0], exp.read_times]))
    usual = np.isclose(spacing, np.median(spacing), rtol=1e-3)
    d = np.diff(np.concatenate([np.zeros((1,) + exp.data.shape[1:]), exp.data]), axis=0)[usual]
    return d, float(np.median(spacing))


def _changing_light(exp, valid, gain):
    """Pixels whose light is constant during ``exp`` (every equally spaced interval within
    :data:`STEADY_SIGMA` of the pixel's median one, its noise from the faint pixels' second differences and
    Poisson noise at ``gain``), and the share of the illuminated pixels (above the median) that are not."""
    d, _ = _equal_intervals(exp)
    if d.shape[0] < 3:
        return valid, 0.0
    med = np.median(d, axis=0)
    dd = np.diff(d, axis=0)
    usable = valid & np.all(np.isfinite(dd), axis=0)
    faint = usable & (med <= np.nanquantile(np.where(usable, med, np.nan), 0.2))
    read2 = (1.4826 * np.median(np.abs(dd[:, faint]))) ** 2 / 2.0 if faint.any() else 1.0
    sigma = np.sqrt(read2 + np.clip(med, 0.0, None) / max(gain or 1.0, 1e-6))
    worst = np.max(np.abs(d - med), axis=0) / sigma
    steady = usable & (worst < STEADY_SIGMA)
    # the illuminated pixels by their mean interval (light that arrives in one interval leaves the median at 0)
    mean = d.mean(axis=0)
    lit = usable & (mean > np.median(mean[usable]) + 10.0 * np.sqrt(read2)) if usable.any() else usable
    share = float(1.0 - steady[lit].mean()) if lit.any() else 0.0
    return steady, share


#: two ramps hold one scene when fewer than this share of their pixels differ by more than
#: :data:`SCENE_SIGMA` times the noise Poisson noise at the header gain and the read noise give (a gain
#: off by a factor 2 would put 5e-4 of them there)
SCENE_SHARE = 0.01
SCENE_SIGMA = 5.0


def _scene_difference(a, b, valid, gain) -> dict:
    """Which share of the pixels differ between the last reads of two ramps by more than :data:`SCENE_SIGMA`
    times their noise (Poisson noise at ``gain``; the read noise from the faintest fifth's difference)."""
    both = valid & np.isfinite(a) & np.isfinite(b)
    if both.sum() < 100 or not gain:
        return {}
    diff = a - b
    mean = 0.5 * (a + b)
    faint = both & (mean <= np.quantile(mean[both], 0.2))
    if faint.sum() < 30:
        return {}
    spread = (1.4826 * np.median(np.abs(diff[faint] - np.median(diff[faint])))) ** 2
    read2 = max(spread - 2.0 * float(np.median(mean[faint])) / gain, 0.0)
    z = (diff - np.median(diff[both])) / np.sqrt(2.0 * np.clip(mean, 0.0, None) / gain + read2)
    return {"scene_share": float(np.mean(np.abs(z[both]) > SCENE_SIGMA))}


def _ptc_points(exposures, gain=None):
    """Points of a photon-transfer curve: (mean signal, noise variance, its error) in counts, the method, the
    weight of the read noise in the intercept, and what was found about the light.

    Two ramps with the same reads (a pair of exposures of one scene): the
    pixels' difference between the ramps' last reads, whose variance over 2
    is the Poisson variance (signal / gain) plus twice the read noise's
    (reads minus the first).  One ramp: the second differences of its
    equally spaced reads, whose variance over 2 is one interval's Poisson
    variance plus three times the read noise's, over the pixels whose light
    is constant during the ramp (:func:`_changing_light`; where it changes,
    the second differences hold the change).  Pixels are grouped by signal
    (:data:`PTC_GROUPS` groups evenly spaced in its logarithm, from the sky
    to the brightest percent, each with at least :data:`PTC_MIN_GROUP`);
    each group's error comes from the spread between eight random subsets of
    its pixels.
    """
    ramps = [e for e in exposures if e.is_ramp]
    pair = next(((a, b) for i, a in enumerate(ramps) for b in ramps[i + 1:]
                 if a.data.shape == b.data.shape and np.allclose(a.read_times, b.read_times, rtol=1e-4)), None)
    info = {}
    if pair is not None:
        a, b = pair
        valid = np.ones(a.data.shape[-2:], dtype=bool)
        for e in pair:
            if e.valid is not None:
                valid &= e.valid
        valid &= np.all(np.isfinite(a.data), axis=0) & np.all(np.isfinite(b.data), axis=0)
        signal = 0.5 * (a.data[-1] + b.data[-1])
        # the sum and the difference of two equally noisy ramps are independent: grouping by the signal picks
        # no noise
        key = signal
        noise = (a.data[-1] - b.data[-1]) / np.sqrt(2.0)
        method, weight = "the difference of two ramps", 2.0
        info.update(_scene_difference(a.data[-1], b.data[-1], valid, gain))
    elif ramps:
        exp = ramps[0]
        d, _ = _equal_intervals(exp)
        if d.shape[0] < 4:
            return [], "second differences", 3.0, info
        dd = np.diff(d, axis=0)
        valid = (exp.valid if exp.valid is not None else np.ones(exp.data.shape[-2:], dtype=bool)) \
            & np.all(np.isfinite(dd), axis=0)
        steady, share = _changing_light(exp, valid, gain)
        info["changing_share"] = share
        info["steady_pixels"] = int(steady.sum())
        valid = steady
        own = d.mean(axis=0)
        signal = np.broadcast_to(own, dd.shape)
        # pixels are grouped by their neighbours' signal, not their own: a pixel's own mean interval shares its
        # first and last reads with its second differences, and grouping by it would pick pixels whose reads
        # are extreme (the faintest group's variance too high, the line too flat); the group's signal is still
        # the mean of its pixels' own, and the curve, a line, is unchanged by mixing rates in a group
        around = (ndimage.uniform_filter(np.where(valid, own, 0.0), 3, mode="constant") * 9.0 - np.where(valid, own, 0.0))
        count = ndimage.uniform_filter(valid.astype(float), 3, mode="constant") * 9.0 - valid
        key = np.broadcast_to(np.where(count > 0, around / np.maximum(count, 1), own), dd.shape)
        noise = dd / np.sqrt(2.0)
        valid = np.broadcast_to(valid, dd.shape)
        method, weight = "second differences of one ramp", 3.0
    else:
        return [], "none", 1.0, info
    sig, noi, keys = signal[valid], noise[valid], key[valid]
    if sig.size < PTC_MIN_GROUP * 3:
        return [], method, weight, info
    # groups spaced evenly in the logarithm of the signal, from the sky to the brightest percent (left out: the
    # well's nonlinearity): most pixels of a field see the sky alone, and the range the gain needs is in the few
    # that see sources
    lo = max(float(np.quantile(keys, 0.02)), 1.0)
    hi = float(np.quantile(keys, 0.99))
    cuts = np.geomspace(lo, hi, PTC_GROUPS + 1) if hi > 2.0 * lo else np.array([lo, hi])
    cuts[0] = float(keys.min())
    rng = np.random.default_rng(0)
    points = []
    for g in range(len(cuts) - 1):
        sel = (keys >= cuts[g]) & (keys <= cuts[g + 1])
        if sel.sum() < PTC_MIN_GROUP:
            continue
        x, y = sig[sel], noi[sel]
        y = y - np.median(y)
        var = _clipped_variance(y)
        parts = np.array_split(rng.permutation(y.size), 8)
        spread = np.std([_clipped_variance(y[k]) for k in parts], ddof=1) / np.sqrt(8.0)
        points.append((float(x.mean()), var, float(spread)))
    return points, method, weight, info


def photon_transfer(exposures, header_gain=None) -> dict:
    """The gain and read noise the measured ramps themselves give, or why they cannot give them.

    The noise variance against the signal (:func:`_ptc_points`) is a line of
    slope 1 / gain and intercept w x read noise^2 (w = 2 or 3, by method).
    The gain is *trusted* only when the data hold a photon-transfer case:

    - one ramp: pixels whose light is constant during the ramp span a range
      of signal (where the light changes, as in a spatial scan or a grism
      time series, the reads hold the change, not only noise);
    - the variance does not grow as the square of the signal (a term
      :data:`QUADRATIC_SIGMA` errors from zero: two ramps whose scenes differ
      by a share of their light, light that changes);
    - the line describes every group (chi^2 p-value above
      :data:`PTC_CONSISTENCY_P`) and measures the gain to :data:`PTC_PRECISION`.

    Otherwise the verdict says which of these fails, and the header's gain
    is kept; no gain is given (a line through points it does not describe
    is no measurement: on the WFC3-IR grism ramps it said 0.3 e-/DN for one
    ramp and 2.07 for the pair, against 2.46).

    Returns
    -------
    dict
        ``gain``, ``gain_error`` (e-/count; None unless trusted),
        ``read_noise`` (counts per read), ``trusted`` (bool), ``method``,
        ``points``, ``reason`` (why not, empty when trusted) and a
        one-line ``verdict``.
    """
    points, method, weight, info = _ptc_points(exposures, header_gain)
    out = {"method": method, "trusted": False, "gain": None, "gain_error": None, "read_noise": None,
           "points": [list(p) for p in points], **info}
    kept = f"the header gain ({header_gain:.3g}) is kept" if header_gain else "no gain is measured"

    def refuse(reason):
        out["reason"] = reason
        out["verdict"] = f"no photon-transfer case: {reason}; {kept}"
        return out

    changing = info.get("changing_share", 0.0)
    if changing > 0.05:
        # the first thing to say: the brighter pixels' reads hold the change of their light
        light = (f"the light of {100 * changing:.0f}% of the illuminated pixels changes during the ramp (a "
                 "spatial scan, a grism time series, a source that varies), and the pixels whose light is "
                 "constant ")
    else:
        light = "the pixels "
    scene = info.get("scene_share")
    if scene is not None and scene > SCENE_SHARE:
        return refuse(f"the two ramps' scenes differ: {100 * scene:.2g}% of the pixels differ by more than "
                      f"{SCENE_SIGMA:g} times the noise Poisson noise at the header gain and the read noise give "
                      "(light that moved or changed between them), so their difference is not noise")
    if len(points) < 3:
        return refuse(light + "are too few")
    m = np.array([p[0] for p in points])
    v = np.array([p[1] for p in points])
    e = np.array([p[2] for p in points])
    ok = np.isfinite(v) & (e > 0)
    if ok.sum() < 3 or np.ptp(m[ok]) <= 0:
        return refuse(light + "span no range of signal")
    a = np.stack([m[ok], np.ones(ok.sum())], axis=1) / e[ok, None]
    coef, *_ = np.linalg.lstsq(a, v[ok] / e[ok], rcond=None)
    cov = np.linalg.inv(a.T @ a)
    slope, intercept = float(coef[0]), float(coef[1])
    fit_chi2 = float(np.sum(((v[ok] - (slope * m[ok] + intercept)) / e[ok]) ** 2))
    consistency = float(chi2.sf(fit_chi2, ok.sum() - 2))
    out["consistency_p"] = consistency

    def read_noise(g):
        # from the faintest group, its small Poisson part taken out with gain g: the intercept of a line
        # through groups that hold more than Poisson noise would be misplaced
        return float(np.sqrt(max(v[0] - m[0] / g, 0.0) / weight)) if g else float(np.sqrt(max(v[0], 0.0) / weight))

    out["read_noise"] = read_noise(header_gain)
    if ok.sum() >= 4:
        q = np.stack([m[ok] ** 2, m[ok], np.ones(ok.sum())], axis=1) / e[ok, None]
        qc, *_ = np.linalg.lstsq(q, v[ok] / e[ok], rcond=None)
        qerr = float(np.sqrt(np.linalg.inv(q.T @ q)[0, 0]))
        out["quadratic"] = [float(qc[0]), qerr]
        if qc[0] > QUADRATIC_SIGMA * qerr:
            what = ("the two ramps' scenes differ by a share of their light" if method.startswith("the difference")
                    else "their light changes between reads")
            return refuse(f"{light}hold noise that grows as the square of the signal ({qc[0] / qerr:.0f} sigma "
                          f"from none): {what}, not only Poisson noise")
    if not slope > 0:
        return refuse(light + "hold noise that does not grow with the signal")
    gain = 1.0 / slope
    err = float(np.sqrt(cov[0, 0])) / slope ** 2
    if consistency < PTC_CONSISTENCY_P:
        return refuse(f"{light}hold noise that does not grow as Poisson noise of one gain (chi^2 p = "
                      f"{consistency:.2g} over {int(ok.sum())} ranges of signal)")
    if err > PTC_PRECISION * gain:
        return refuse(f"{light}span {m[ok].min():.3g}-{m[ok].max():.3g} counts: they measure the gain to "
                      f"{100 * err / gain:.0f}% only")
    out.update(trusted=True, gain=gain, gain_error=err, reason="")
    out["read_noise"] = read_noise(gain)
    if header_gain:
        agree = abs(gain - header_gain) <= 3.0 * err + 0.05 * header_gain
        out["verdict"] = (f"{gain:.3g} +- {err:.2g} e-/count from {method}: "
                          + ("supports the header gain" if agree else f"refutes the header gain of {header_gain:.3g}"))
    else:
        out["verdict"] = f"{gain:.3g} +- {err:.2g} e-/count from {method}"
    return out


def ramp_model(exposures) -> DetectorModel:
    """The starting model of a self-predicted ramp: Poisson noise, no nonlinearity, the read noise of the
    faint pixels' second differences, the header's gain, rounding."""
    exp = next(e for e in exposures if e.is_ramp)
    gain = float(exp.gain) if exp.counts == "DN" and exp.gain else 1.0
    # only pixels that see the sky: a WFC3-IR frame's reference pixels are quieter (7.9 e- against 13 e-
    # per read in ibh7a7lsq) and would be most of the faintest; and second differences, which hold
    # neither the rate nor the ramp's curvature, rather than the first read's difference
    # the read noise from one ramp's second differences: a pair of exposures also differs by the scene
    read = photon_transfer([exp], gain)["read_noise"]
    if read is None or not read > 0:
        first, last = exp.data[0], exp.data[-1]
        valid = exp.valid if exp.valid is not None else np.ones(last.shape, dtype=bool)
        usable = valid & np.isfinite(first) & np.isfinite(last)
        faint = usable & (last <= np.nanquantile(np.where(usable, last, np.nan), 0.2))
        read = 1.4826 * np.nanmedian(np.abs(first[faint] - np.nanmedian(first[faint]))) / np.sqrt(2.0) \
            if faint.any() else 1.0
    sigma = max(float(read) * gain, 0.1)
    effects = [Effect("poisson", {}), Effect("nonlinearity", {"beta": 0.0}), Effect("read_noise", {"sigma": sigma}),
               Effect("gain", {"gain": gain}), Effect("quantize", {})]
    for eff in effects:
        eff.params = {**REGISTRY[eff.name].defaults(), **eff.params}
    return DetectorModel(effects, source="self-predicted ramp")


class RampProblem:
    """Self-predicted ramps: evaluates a model's nonlinearity, read noise and gain on later reads."""

    def __init__(self, exposures, *, fit_pixels: int = DEFAULT_FIT_PIXELS):
        self.exposures = [e for e in exposures if e.is_ramp]
        if not self.exposures:
            raise PerscliError("no ramp among the measured frames")
        for exp in self.exposures:
            if len(exp.read_times) < 3:
                raise PerscliError(f"{exp.label}: {len(exp.read_times) + 1} reads: a self-predicted ramp needs at "
                                   "least 4 (a reference read and later ones)")
        self.shape = self.exposures[0].data.shape[-2:]
        self.fit_pixels = fit_pixels
        # the gain the reads themselves give, when they hold a photon-transfer case (else the header's is kept)
        header = self.exposures[0].gain if self.exposures[0].counts == "DN" else None
        self.photon_transfer = photon_transfer(self.exposures, header)
        pt = self.photon_transfer
        self.ptc_gain = (pt["gain"], pt["gain_error"]) if pt["trusted"] and header else None
        self.masks = [e.valid.copy() if e.valid is not None else np.ones(self.shape, dtype=bool)
                      for e in self.exposures]
        start = ramp_model(self.exposures)
        ev = self.evaluate(start, full=True)
        self.jumps = 0
        for i, exp in enumerate(self.exposures):
            r = [np.abs(ev.data[k] - ev.mean[k]) / np.sqrt(ev.variance[k]) for k in self._pieces(i)]
            worst = np.max(np.stack(r), axis=0)
            jump = ~(worst < JUMP_SIGMA) & self.masks[i]
            self.masks[i] &= ~jump & np.all(np.isfinite(exp.data), axis=0)
            self.jumps += int(jump.sum())

    def _pieces(self, i):
        """Indices in an evaluation's lists of exposure ``i``'s predicted reads."""
        start = sum(len(e.read_times) - self._ref(e) - 1 for e in self.exposures[:i])
        return range(start, start + len(self.exposures[i].read_times) - self._ref(self.exposures[i]) - 1)

    @staticmethod
    def _ref(exp) -> int:
        """Index (in ``data``) of the reference read: the third after the first, or earlier for short ramps."""
        return min(2, len(exp.read_times) - 2)

    def allows(self, name: str) -> bool:
        return name in RAMP_CANDIDATES

    def persistence(self, index: int, model: DetectorModel):
        """Electrons of persistence in each read (minus the first) of ramp ``index`` that the earlier ramps'
        fluence leaves, shape (reads, ny, nx); None for the first ramp or without persistence in ``model``."""
        if index == 0 or not model.enabled("persistence"):
            return None
        pm = model.persistence_model()
        key = (index, pm.kind, pm.x0, pm.dx, pm.alpha, pm.gamma, pm.half_well, pm.coefficients, pm.time_model,
               pm.combine, pm.max_previous)
        cache = self.__dict__.setdefault("_persistence", {})
        if key not in cache:
            # one set of shape parameters at a time; the law is proportional to A, computed for A = 1
            cache.clear()
            unit = dataclasses.replace(pm, A=1.0) if pm.kind == "fermi" else pm
            cur = self.exposures[index]
            earlier = self.exposures[:index]
            ends = [(e.end - cur.start) * SECONDS_PER_DAY for e in earlier]
            cache[key] = persistence_charge([measured_fluence(e) for e in earlier], ends, 0.0, cur.read_times, unit)
        return cache[key] * (pm.A if pm.kind == "fermi" else 1.0)

    def evaluate(self, model: DetectorModel, *, full: bool = False) -> Evaluation:
        beta = float(model.value("nonlinearity", "beta", off=0.0))
        sigma = float(model.value("read_noise", "sigma", off=0.0))
        quant = 1.0 / 12.0 if model.enabled("quantize") else 0.0
        means, variances, datas, masks = [], [], [], []
        for i, exp in enumerate(self.exposures):
            gain = float(model.value("gain", "gain", off=1.0)) if exp.counts == "DN" else 1.0
            j = self._ref(exp)
            tau = exp.read_times
            ref = exp.data[j] * gain                       # electrons by the reference read
            if beta != 0.0:
                # the charge before nonlinearity: x + beta x^2 = ref, the root that is x at beta = 0
                disc = np.maximum(1.0 + 4.0 * beta * ref, 0.0)
                q_ref = 2.0 * ref / (1.0 + np.sqrt(disc))
            else:
                q_ref = ref
            # persistence: charge that arrives at the law's decaying rate, not the pixel's own
            pers = self.persistence(i, model)
            rate = (q_ref - (pers[j] if pers is not None else 0.0)) / tau[j]
            for k in range(j + 1, len(tau)):
                a = tau[k] / tau[j]
                q = rate * tau[k] + (pers[k] if pers is not None else 0.0)
                mean = (q + beta * q * q) / gain
                poisson = np.maximum(q - q_ref, 0.0) + (1.0 - a) ** 2 * np.maximum(q_ref, 0.0)
                reads = 1.0 + a * a + (a - 1.0) ** 2
                var = (poisson + sigma * sigma * reads) / gain ** 2 + quant * reads
                data = exp.data[k]
                mask = self.masks[i] & np.isfinite(data) & (var > 0)
                means.append(mean)
                variances.append(np.where(mask, var, 1.0))
                datas.append(data)
                masks.append(mask)
        return Evaluation(means, variances, datas, masks)

    def chi2_full(self, model: DetectorModel) -> tuple:
        """(chi^2, pixels) over every predicted read of every pixel."""
        return self.evaluate(model, full=True).chi2()

    def covariates(self, evaluation) -> list:
        out = []
        ny, nx = self.shape
        yy, xx = np.mgrid[0:ny, 0:nx]
        block = (yy * 8 // ny) * 8 + (xx * 8 // nx)

        for i, exp in enumerate(self.exposures):
            j = self._ref(exp)
            for k, piece in zip(range(j + 1, len(exp.read_times)), self._pieces(i)):
                mean = evaluation.mean[piece]
                out.append({"signal": mean, "read_time": np.full(mean.shape, exp.read_times[k]),
                            "position": block, "neighbours": _neighbours(mean)})
        return out
