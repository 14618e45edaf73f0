"""A lone ramp, self-predicted: each pixel's later reads from its rate in the earliest reads.

Without a simulation the expectation comes from the data themselves: the
charge a pixel collected by an early reference read (reads minus the first,
so the bias drops out) gives its rate, and a linear accumulation at that rate
predicts every later read.  Effects that bend the ramp (nonlinearity), scale
its noise (gain) or add to it (read noise) then show in the later reads.  The
variance of each prediction is exact for a linear ramp: Poisson noise of the
charge between the reads, and the read noise and rounding of the three reads
involved (the read itself, the reference read and the first read).

Pixels whose ramps jump (a cosmic ray, or light that changes during the
exposure, as in grism time series) cannot be predicted from their early
reads; they are found once, with the starting model, as pixels with a read
more than :data:`JUMP_SIGMA` sigma from its prediction, and left out of every
fit and gap (their number is reported), as a pipeline's jump step would.
"""

from __future__ import annotations

import numpy as np

from .. import PerscliError
from ..detector.effects import DetectorModel, Effect, REGISTRY
from .likelihood import Evaluation

#: a read this many sigma from its self-prediction marks the pixel's ramp as jumping
JUMP_SIGMA = 10.0

#: effects a self-predicted ramp can constrain
RAMP_CANDIDATES = ("nonlinearity", "read_noise", "gain")


def ramp_model(exposures) -> DetectorModel:
    """The starting model of a self-predicted ramp: Poisson noise, no nonlinearity, read noise estimated from
    the first differences of the faintest pixels, the header's gain, rounding."""
    exp = next(e for e in exposures if e.is_ramp)
    gain = float(exp.gain) if exp.counts == "DN" and exp.gain else 1.0
    first, last = exp.data[0], exp.data[-1]
    # pixels faint over the whole ramp (chosen by their last read, so that the first difference's own
    # scatter is not truncated by the choice): read 1 minus read 0 is then the read noise of two reads.
    # Only pixels that see the sky: a WFC3-IR frame's reference pixels are quieter (7.9 e- against 13 e-
    # per read in ibh7a7lsq) and would be most of the faintest fifth
    valid = exp.valid if exp.valid is not None else np.ones(last.shape, dtype=bool)
    usable = valid & np.isfinite(first) & np.isfinite(last)
    faint = usable & (last <= np.nanquantile(np.where(usable, last, np.nan), 0.2))
    spread = 1.4826 * np.nanmedian(np.abs(first[faint] - np.nanmedian(first[faint]))) if faint.any() else 1.0
    sigma = max(float(spread) * gain / np.sqrt(2.0), 0.1)
    effects = [Effect("poisson", {}), Effect("nonlinearity", {"beta": 0.0}), Effect("read_noise", {"sigma": sigma}),
               Effect("gain", {"gain": gain}), Effect("quantize", {})]
    for eff in effects:
        eff.params = {**REGISTRY[eff.name].defaults(), **eff.params}
    return DetectorModel(effects, source="self-predicted ramp")


class RampProblem:
    """Self-predicted ramps: evaluates a model's nonlinearity, read noise and gain on later reads."""

    def __init__(self, exposures, *, fit_pixels: int = 1_000_000):
        self.exposures = [e for e in exposures if e.is_ramp]
        if not self.exposures:
            raise PerscliError("no ramp among the measured frames")
        for exp in self.exposures:
            if len(exp.read_times) < 3:
                raise PerscliError(f"{exp.label}: {len(exp.read_times) + 1} reads: a self-predicted ramp needs at "
                                   "least 4 (a reference read and later ones)")
        self.shape = self.exposures[0].data.shape[-2:]
        self.fit_pixels = fit_pixels
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
            rate = q_ref / tau[j]
            for k in range(j + 1, len(tau)):
                a = tau[k] / tau[j]
                q = rate * tau[k]
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
        from .probes import _neighbours

        for i, exp in enumerate(self.exposures):
            j = self._ref(exp)
            for k, piece in zip(range(j + 1, len(exp.read_times)), self._pieces(i)):
                mean = evaluation.mean[piece]
                out.append({"signal": mean, "read_time": np.full(mean.shape, exp.read_times[k]),
                            "position": block, "neighbours": _neighbours(mean)})
        return out
