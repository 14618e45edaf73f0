"""Expectation, variance and Gaussian likelihood of measured frames under a detector model.

The expectation of a measured frame is the model's noise-free forward model
(:func:`perscli.detector.chain.forward`, the same effects render samples)
of the simulation's IDEAL (sources and sky, so the model's sky effect is not
applied again), with the persistence the earlier exposures' fluence leaves
in it; its variance is the model's noise carried through the effects that
follow each source of noise (Poisson, dark, read noise, quantisation; IPC
spreads it with the kernel squared, gain scales it).  Measured and simulated
noise are independent: the simulation's SCI is never used.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
from dataclasses import dataclass

import numpy as np

from .. import PerscliError
from ..detector.chain import ChargeCache, forward
from ..detector.effects import DEFAULTS, ORDER, REGISTRY
from ..detector.model import DetectorModel, Effect
from ..detector.persistence import persistence_charge
from ..executor import thread_map
from ..io.frames import SECONDS_PER_DAY
from .data import measured_fluence
from .probes import _neighbours
from .settings import DEFAULT_FIT_PIXELS


def with_effect(model: DetectorModel, name: str, params: dict | None = None, enabled: bool = True) -> DetectorModel:
    """A copy of ``model`` with effect ``name`` present, switched as given, its parameters updated."""
    out = DetectorModel([copy.deepcopy(e) for e in model.effects], source=model.source)
    eff = out.get(name)
    if eff is None:
        eff = Effect(name, copy.deepcopy(DEFAULTS[name]), enabled=False)
        out.effects.append(eff)
        out.effects.sort(key=lambda e: ORDER.index(e.name))
    if params:
        merged = dict(eff.params)
        merged.update(REGISTRY[name].validate(dict(params), f"diagnose: {name}"))
        eff.params = merged
    eff.enabled = enabled
    return out


@dataclass
class Evaluation:
    """Expectation, variance and data of the pixels used, for every exposure."""

    mean: list
    variance: list
    data: list
    mask: list
    #: per piece: (exposure index, rows of the frame it covers)
    pieces: list = None

    def chi2(self) -> tuple:
        """(chi^2, number of pixels) over the usable pixels."""
        total, n = 0.0, 0
        for e, v, d, m in zip(self.mean, self.variance, self.data, self.mask):
            r = (d[m] - e[m])
            total += float(np.sum(r * r / v[m]))
            n += int(m.sum())
        return total, n

    def m2lnl(self) -> float:
        """-2 ln L of the data, Gaussian with the model's variance (constants dropped)."""
        total = 0.0
        for e, v, d, m in zip(self.mean, self.variance, self.data, self.mask):
            r = d[m] - e[m]
            total += float(np.sum(r * r / v[m] + np.log(v[m])))
        return total

    def residuals(self) -> list:
        """(data - mean) / sqrt(variance), NaN where unusable."""
        out = []
        for e, v, d, m in zip(self.mean, self.variance, self.data, self.mask):
            r = np.full(d.shape, np.nan)
            r[m] = (d[m] - e[m]) / np.sqrt(v[m])
            out.append(r)
        return out


#: sets of the persistence law's parameters whose charges on the fit rows are kept
CHARGE_SETS = 8

#: pixels whose expected charge is within this many sigma (Poisson) of the full well are not fitted
NEAR_WELL_SIGMA = 5.0


class Problem:
    """Measured exposures, their simulations and history: evaluates any detector model on them.

    Parameters
    ----------
    exposures : list of perscli.diagnose.data.MeasuredExposure
        In time order, each with ``ideal`` (the simulation's noise-free electrons).
    fit_pixels : int
        About this many pixels, over all exposures, enter the fits and the
        probes: rows in stripes, one in each eighth of the frame, each with a
        row of margin for IPC, placed where the most pixels are bright in the
        simulation or in the earlier exposures' fluence (:func:`_stripes`);
        the gaps before and after are computed on every pixel, a block of
        rows at a time (:meth:`chi2_full`), so memory stays a few frames.
    workers : int
        Threads over the exposures in each evaluation (the forward model's
        compiled loops release the GIL); results do not depend on it.
    """

    def __init__(self, exposures, *, fit_pixels: int = DEFAULT_FIT_PIXELS, workers: int = 1):
        self.exposures = exposures
        for exp in exposures:
            if exp.ideal is None:
                raise PerscliError(f"{exp.label}: no simulated frame pairs with it; give --simulated frames for "
                                   "every measured exposure (or diagnose a lone ramp, self-predicted)")
        ny, nx = exposures[0].data.shape[-2:]
        self.shape = (ny, nx)
        self.workers = max(1, int(workers))
        self.stripes = _stripes(ny, nx, max(fit_pixels // len(exposures), 16 * nx), _bright_rows(exposures))
        #: the rows the fit stripes compute, in order: each stripe's rows are contiguous in it
        self.fit_rows = np.concatenate([np.arange(r.start or 0, r.stop) for r, _, _ in self.stripes])
        self._stripe_start = {}
        pos = 0
        for r, _, _ in self.stripes:
            self._stripe_start[(r.start, r.stop)] = pos
            pos += r.stop - (r.start or 0)
        self._charges = {}
        self._charge_sets = {}
        #: (index, well) -> (FLUENCE less PERSIST, the pixels the simulation saturated) on the fit rows: the
        #: part of a history no law changes, made once (it was a third of every history's time)
        self._history_base = {}
        #: the chain's charge stage on the fit stripes, per exposure and stripe (perscli.detector.chain.forward)
        self._charge_stage = ChargeCache()
        #: (persistence law, electrons): the fits leave out the pixels where that law leaves more (see
        #: :meth:`set_aside`); None: every pixel
        self.aside = None
        #: exposures whose fit pixels get a level of their own, profiled out in every evaluation (see
        #: :meth:`set_aside`)
        self.free_levels = frozenset()
        #: persisted charge persists again: the histories follow the law being fitted (:meth:`history`) when
        #: the simulated frames say how much of their FLUENCE their own law put in
        self._feedback = any(e.persist is not None for e in exposures[1:-1])
        #: per piece of rows, the pixels left out as near the full well (see :meth:`_pieces`)
        self._near_well = {}
        self._lock = threading.Lock()

    # -- persistence history ----------------------------------------------------------------------
    def charge(self, index: int, pmodel, region: str = "full", well=None):
        """The persistence that the earlier exposures leave in exposure ``index``: ``(array, scale)``, electrons
        ``array * scale``; None for the first.

        Without feedback (see :meth:`history`) the law is proportional to A:
        ``array`` is computed once for A = 1 and ``scale`` is A.  With it,
        the earlier exposures' histories depend on A too: ``array`` is the
        charge itself and ``scale`` 1.  ``region`` 'fit': only the rows of the
        fit stripes, stacked (:attr:`fit_rows`), so that a fit that frees the
        law's shape recomputes a few per cent of each frame; 'full': every
        row.  ``well``: the model's full well (the histories are clipped there).
        """
        if index == 0:
            return None
        feedback = self._feedback and pmodel.kind == "fermi"
        params = (pmodel.kind, pmodel.x0, pmodel.dx, pmodel.alpha, pmodel.gamma, pmodel.half_well,
                  pmodel.coefficients, pmodel.time_model, pmodel.combine, pmodel.max_previous,
                  (pmodel.A, well) if feedback else None)
        key = (region, index) + params
        with self._lock:
            have = self._charges.get(key)
        if have is None:
            # without feedback the law is proportional to A: computed once for A = 1 and scaled
            unit = dataclasses.replace(pmodel, A=1.0) if pmodel.kind == "fermi" and not feedback else pmodel
            cur = self.exposures[index]
            earlier = self.exposures[:index]
            ends = [(e.end - cur.start) * SECONDS_PER_DAY for e in earlier]
            window = (cur.end - cur.start) * SECONDS_PER_DAY
            # each history made when its exposure is used and dropped after (a frame at a time, not ten)
            fluences = [(lambda j=j: self.history(j, pmodel, region, well)) for j in range(index)]
            have = persistence_charge(fluences, ends, 0.0, window, unit)[0].astype(np.float32)
            with self._lock:
                # a few sets of the law's parameters for the fit rows (a fit that moves A or gamma goes back and
                # forth between nearby values), one for every row (each set is frames of charge): the charges
                # of other sets are dropped (the exposures' threads share the current set)
                sets = self._charge_sets.setdefault(region, [])
                if params in sets:
                    sets.remove(params)
                sets.append(params)
                keep = sets[-(CHARGE_SETS if region == "fit" else 1):]
                self._charge_sets[region] = keep
                self._charges = {k: v for k, v in self._charges.items() if k[0] != region or k[2:] in keep}
                self._charges[key] = have
        scale = pmodel.A if pmodel.kind == "fermi" and not feedback else 1.0
        return have, scale

    def history(self, index: int, pmodel, region: str = "full", well=None) -> np.ndarray:
        """The electrons exposure ``index`` collected (what its persistence is made of), as the persistence law
        ``pmodel`` of the earlier exposures makes it.

        The simulation's FLUENCE holds the persistence the simulation's own
        law put in (its PERSIST); the measured detector's holds its own.
        When the simulated frames carry PERSIST, the history is FLUENCE less
        PERSIST plus the persistence ``pmodel`` leaves (clipped at ``well``;
        pixels the simulation saturated stay saturated): persisted charge
        persists again, and a persistence several times the simulation's
        would otherwise leave too little of it two and more exposures later
        (7% at lag 2 for A = 0.3 against 0.017: the decay law's shape fitted
        wrong).  Without PERSIST (or from the measured frames) the history is
        FLUENCE as it is.
        """
        exp = self.exposures[index]
        base = exp.fluence if exp.fluence is not None else measured_fluence(exp)
        rows = self.fit_rows if region == "fit" else slice(None)
        base = base[rows]
        if not self._feedback or index == 0 or exp.persist is None or exp.fluence is None or pmodel.kind != "fermi":
            return base
        params = (pmodel.kind, pmodel.x0, pmodel.dx, pmodel.alpha, pmodel.gamma, pmodel.half_well,
                  pmodel.coefficients, pmodel.time_model, pmodel.combine, pmodel.max_previous, (pmodel.A, well))
        # kept with the charges of the same law on the fit rows (each later exposure's charge needs every
        # earlier history)
        key = (region, ("history", index)) + params
        with self._lock:
            have = self._charges.get(key)
        if have is not None:
            return have
        own = self.charge(index, pmodel, region, well)
        rest, saturated = self._history_rest(index, base, rows, region, well)
        # in place, one frame at a time (a full frame's history is 67 MB, and two threads make them at once):
        # the same values as rest + charge, clipped at the well where the simulation did not saturate, and at 0
        now = np.multiply(own[0], np.float32(own[1]), dtype=np.float32)
        now += rest
        if well:
            np.minimum(now, np.float32(well), out=now)
            np.copyto(now, base, where=saturated)
        have = np.maximum(now, np.float32(0.0), out=now)
        if region == "fit":
            # every pixel's histories would be frames more to hold: those are made again when asked (a few
            # elementwise passes each)
            with self._lock:
                if params in self._charge_sets.get(region, []):
                    self._charges[key] = have
        return have

    def _history_rest(self, index, base, rows, region, well):
        """(FLUENCE less PERSIST, pixels at the well or None) of exposure ``index``: kept for the fit rows."""
        key = (index, well)
        if region == "fit":
            with self._lock:
                have = self._history_base.get(key)
            if have is not None:
                return have
        exp = self.exposures[index]
        rest = exp.persist[rows].astype(np.float32)
        np.subtract(base, rest, out=rest)       # base - PERSIST, in the one new frame
        saturated = base >= np.float32(well * (1.0 - 1e-6)) if well else None
        if region == "fit":
            with self._lock:
                self._history_base[key] = (rest, saturated)
        return rest, saturated

    def set_aside(self, law, limit: float, well=None) -> int:
        """Leave out of every later fit (not of the gaps) the pixels where the persistence law ``law`` leaves more
        than ``limit`` electrons: where a persistence the model cannot describe lies, so that the other effects
        are measured on the pixels it leaves alone.  What it leaves on the rest, its pedestal from the sky's
        fluence (a fraction of an electron, the same over an exposure), is given a level of each later exposure's
        own, profiled out of every fit: a dark current or an offset is then measured by the first exposure,
        which no persistence reaches, and by none of the pedestals.  Returns how many pixels of the fit rows
        that sets aside."""
        self.aside = (law, float(limit))
        self.free_levels = frozenset(range(1, len(self.exposures)))
        count = 0
        for i in range(1, len(self.exposures)):
            unit = self.charge(i, law, "fit", well)
            count += int(np.count_nonzero(unit[0] * unit[1] > limit))
        return count

    def persistence_parts(self, model: DetectorModel, split) -> dict:
        """The persistence of the law in ``model`` at A = 1 split into parts: {part: {exposure index: electrons
        on the fit rows}}.

        ``split(j, i, fluence)`` gives, for earlier exposure ``j`` seen by
        exposure ``i``, {part: boolean mask of the earlier fluence}; a part
        is the charge those pixels of those earlier exposures leave (each
        earlier exposure keeps its place among the others, as the law's time
        model and its limit on earlier exposures count it).  The law must add
        up the earlier exposures (``combine: sum``) for the parts to add up to
        the whole.
        """
        pm = model.persistence_model()
        unit = dataclasses.replace(pm, A=1.0)
        well = model.value("saturation", "full_well", off=None)
        # the histories as the model makes them (no persistence in them when the model has none)
        lived = pm if model.enabled("persistence") else dataclasses.replace(pm, A=0.0)
        fluences = [self.history(j, lived, "fit", well) for j in range(len(self.exposures))]
        out = {}
        for i in range(1, len(self.exposures)):
            cur = self.exposures[i]
            ends = [(e.end - cur.start) * SECONDS_PER_DAY for e in self.exposures[:i]]
            window = (cur.end - cur.start) * SECONDS_PER_DAY
            masks = {j: split(j, i, fluences[j]) for j in range(i)}
            zero = np.zeros_like(fluences[0])
            for part in {p for m in masks.values() for p in m}:
                chosen = [np.where(masks[j][part], fluences[j], 0.0) if part in masks[j] else zero
                          for j in range(i)]
                if not any(np.any(c) for c in chosen):
                    continue
                charge = persistence_charge(chosen, ends, 0.0, window, unit)[0]
                if np.any(charge):
                    out.setdefault(part, {})[i] = charge
        return out

    def covariates(self, evaluation) -> list:
        return covariates_2d(self, evaluation)

    def allows(self, name: str) -> bool:
        return True

    # -- the forward model ---------------------------------------------------------------------------
    def _model_for(self, model: DetectorModel, exp) -> DetectorModel:
        """The model as it applies to IDEAL (no sky: IDEAL has it) and to the measured counts."""
        out = with_effect(model, "sky", enabled=False)
        if exp.counts == "electron":
            out = with_effect(out, "gain", enabled=False)
        elif not model.enabled("gain"):
            out = with_effect(out, "gain", {"gain": float(exp.gain)})
        return out

    def _prepared(self, model: DetectorModel) -> dict:
        """:meth:`_model_for` of ``model`` for each kind of exposure (counts, gain): one copy of the model for
        all the exposures that share it, made before the exposures' threads start."""
        out = {}
        for exp in self.exposures:
            key = (exp.counts, exp.gain)
            if key not in out:
                out[key] = self._model_for(model, exp)
        return out

    def _pieces(self, i, model, pieces, region: str = "full", prepared=None, extra=None):
        """(rows kept, mean, variance, data, mask) of exposure ``i`` for each (rows, keep0, keep1); ``region``
        'fit' when ``pieces`` are the fit stripes; ``prepared`` from :meth:`_prepared`; ``extra``: electrons
        added to the persistence charge (the fit rows, stacked as :attr:`fit_rows`), or None."""
        exp = self.exposures[i]
        pmodel = model.persistence_model() if model.enabled("persistence") else None
        m = prepared[(exp.counts, exp.gain)] if prepared is not None else self._model_for(model, exp)
        well = model.value("saturation", "full_well", off=None)
        charge = self.charge(i, pmodel, region, well) if pmodel is not None else None
        # a measured ramp is compared by its last read minus its first: the part of the exposure
        # between them (IDEAL spreads evenly over the exposure; the dark current accrues as long)
        exptime = float(exp.read_times[-1]) if exp.is_ramp else exp.exptime
        share = exptime / exp.exptime if exp.exptime else 1.0
        for rows, keep0, keep1 in pieces:
            ideal = exp.ideal[rows] if share == 1.0 else exp.ideal[rows] * share
            if charge is None:
                pers = None
            elif region == "fit":
                at = self._stripe_start[(rows.start, rows.stop)]
                pers = charge[0][at:at + (rows.stop - (rows.start or 0))] * charge[1]
            else:
                pers = charge[0][rows] * charge[1]
            if extra is not None:
                at = self._stripe_start[(rows.start, rows.stop)]
                add = extra[at:at + (rows.stop - (rows.start or 0))]
                pers = add if pers is None else pers + add
            # the fit stripes' charge stage is kept between evaluations that change only the readout (the
            # sources and the persistence charge are this exposure's and this law's: with an extra charge
            # nothing is kept)
            cached = region == "fit" and extra is None
            fw = forward(ideal, m, exptime=exptime, persistence=pers, cache=self._charge_stage if cached else None,
                         key=(i, rows.start, rows.stop, keep0, keep1, well, share) if cached else None)
            sl = slice(keep0, keep1)
            mean, var = fw.mean[sl], fw.variance[sl]
            data = exp.data[-1][rows][sl]
            mask = np.isfinite(data) & (var > 0) & np.isfinite(mean)
            if well:
                # within a few sigma of the full well the clipped signal's mean and variance are not the
                # first-order ones the chain gives: those pixels are left out.  Which pixels those are is
                # decided once, by the first model evaluated (the starting model): were it decided by each
                # model, a fit that moves charge (brighter-fatter, reciprocity, persistence) would move pixels
                # in and out of the likelihood, and -2 ln L would jump by their residuals
                key = (i, rows.start, rows.stop, keep0, keep1)
                with self._lock:
                    near = self._near_well.get(key)
                if near is None:
                    near = fw.fluence[sl] >= well - NEAR_WELL_SIGMA * math.sqrt(well)
                    with self._lock:
                        near = self._near_well.setdefault(key, near)
                mask &= ~near
            if exp.valid is not None:
                mask &= exp.valid[rows][sl]
            if region == "fit" and self.aside is not None and i > 0:
                # pixels where persistence no law describes lies are left out of the fits (never of the gaps)
                law, limit = self.aside
                at = self._stripe_start[(rows.start, rows.stop)]
                unit = self.charge(i, law, "fit", well)
                lying = unit[0][at:at + (rows.stop - (rows.start or 0))] * unit[1]
                mask &= ~(lying[sl] > limit)
            start = (rows.start or 0) + keep0
            yield slice(start, start + (keep1 - keep0)), mean, np.where(mask, var, 1.0), data, mask

    def evaluate(self, model: DetectorModel, *, full: bool = False, extra=None) -> Evaluation:
        """Expectation and variance of the fit stripes of every exposure (every pixel with ``full``:
        small frames only; :meth:`chi2_full` streams large ones).

        ``extra``: {exposure index: electrons on the fit rows} added to the
        persistence charge (the fit stripes only): how the chain passes a
        change of the persistence on to the measured counts."""
        out = Evaluation([], [], [], [], [])
        out.pieces = []
        pieces = [(slice(0, self.shape[0]), 0, self.shape[0])] if full else self.stripes
        region = "full" if full else "fit"
        if extra and full:
            raise ValueError("an extra persistence charge is given on the fit rows only")
        prepared = self._prepared(model)
        extra = extra or {}
        per_exposure = thread_map(lambda i: list(self._pieces(i, model, pieces, region, prepared, extra.get(i))),
                                  range(len(self.exposures)), workers=self.workers)
        for i, done in enumerate(per_exposure):
            if region == "fit" and i in self.free_levels and done:
                # a level of this exposure's own, profiled out: the weighted mean residual of its fit pixels
                num = sum(float(np.sum(((d - m) / v)[k])) for _, m, v, d, k in done)
                den = sum(float(np.sum((1.0 / v)[k])) for _, m, v, d, k in done)
                level = num / den if den > 0 else 0.0
                done = [(rows, mean + level, var, data, mask) for rows, mean, var, data, mask in done]
            for rows, mean, var, data, mask in done:
                out.mean.append(mean)
                out.variance.append(var)
                out.data.append(data)
                out.mask.append(mask)
                out.pieces.append((i, rows))
        return out

    def chi2_full(self, model: DetectorModel, *, block_rows: int = 512) -> tuple:
        """(chi^2, pixels) over every pixel of every exposure, a block of rows at a time."""
        ny = self.shape[0]
        blocks = []
        for r0 in range(0, ny, block_rows):
            r1 = min(ny, r0 + block_rows)
            a, b = max(0, r0 - 1), min(ny, r1 + 1)     # a row of margin each side for IPC
            blocks.append((slice(a, b), r0 - a, r0 - a + (r1 - r0)))

        prepared = self._prepared(model)
        if model.enabled("persistence"):
            # every exposure's persistence on every pixel made first, one exposure at a time (each needs the
            # earlier ones' histories, frames of their own): two threads making them at once held both sets of
            # frames besides the blocks the threads then go through
            pmodel, well = model.persistence_model(), model.value("saturation", "full_well", off=None)
            for i in range(1, len(self.exposures)):
                self.charge(i, pmodel, "full", well)

        def one(i):
            sums = []
            for _, mean, var, data, mask in self._pieces(i, model, blocks, prepared=prepared):
                r = data[mask] - mean[mask]
                sums.append((float(np.sum(r * r / var[mask])), int(mask.sum())))
            return sums

        total, n = 0.0, 0
        # summed in the same order whatever the number of threads: the same bytes
        for sums in thread_map(one, range(len(self.exposures)), workers=self.workers):
            for t, k in sums:
                total += t
                n += k
        return total, n


def covariates_2d(problem, evaluation) -> list:
    """Per piece of ``evaluation``: the probes' covariates (see :mod:`perscli.diagnose.probes`)."""
    out = []
    ny, nx = problem.shape
    for (i, rows), mean in zip(evaluation.pieces, evaluation.mean):
        exp = problem.exposures[i]
        yy = np.arange(rows.start, rows.stop)[:, None] * np.ones((1, nx), dtype=int)
        xx = np.ones((rows.stop - rows.start, 1), dtype=int) * np.arange(nx)[None, :]
        cov = {"signal": mean, "exposure_time": np.full(mean.shape, exp.exptime),
               "position": (yy * 8 // ny) * 8 + (xx * 8 // nx), "neighbours": _neighbours(mean)}
        history = np.zeros(mean.shape)
        for e in problem.exposures[:i]:
            flu = e.fluence if e.fluence is not None else measured_fluence(e)
            np.maximum(history, flu[rows], out=history)
        cov["history"] = history
        cov["time_since"] = np.full(mean.shape, (exp.start - problem.exposures[i - 1].end) * SECONDS_PER_DAY
                                    if i > 0 else np.nan)
        out.append(cov)
    return out


#: a pixel is bright, for the placing of the fit stripes, above this many electrons in the simulation of its
#: exposure or in an earlier exposure's fluence: 10% of an H4RG's well, where nonlinearity, brighter-fatter
#: and persistence (whose Fermi law turns on near half the well) carry most of their information
BRIGHT_ELECTRONS = 1.0e4


def _bright_rows(exposures) -> np.ndarray:
    """Per row, how many pixels are bright (:data:`BRIGHT_ELECTRONS`) in each exposure's IDEAL or in the
    FLUENCE it leaves for later ones, summed over the exposures.

    The selection uses the simulation only (never the measured noise), so it
    does not bias the fits; the fluence of the last exposure leaves no history
    in the data and is not counted.
    """
    ny = exposures[0].data.shape[-2]
    counts = np.zeros(ny, dtype=np.int64)
    for k, exp in enumerate(exposures):
        for image in (exp.ideal, exp.fluence if k < len(exposures) - 1 else None):
            if image is not None and image.shape[-2:] == exposures[0].data.shape[-2:]:
                counts += np.count_nonzero(np.asarray(image) > BRIGHT_ELECTRONS, axis=-1).reshape(-1, ny).sum(axis=0)
    return counts


def _stripes(ny: int, nx: int, fit_pixels: int, bright=None) -> list:
    """Row stripes covering about ``fit_pixels`` pixels: (rows to compute, first and last row kept).

    One stripe in each eighth of the frame (so that every part of the
    detector is sampled, as the probes of position need), at the offset that
    holds the most bright pixels (``bright``, per row: most of what
    nonlinearity, brighter-fatter and persistence leave is in a few per cent
    of the pixels, which evenly spaced stripes would mostly miss); evenly
    spaced where no offset holds more.
    """
    if ny * nx <= fit_pixels or ny < 64:
        return [(slice(0, ny), 0, ny)]
    nstripes = 8
    height = max(8, int(math.ceil(fit_pixels / nx / nstripes)))
    cum = np.concatenate([[0], np.cumsum(bright)]) if bright is not None and np.any(bright) else None
    out = []
    for k in range(nstripes):
        r0 = int((ny - height) * k / (nstripes - 1)) if nstripes > 1 else 0
        lo, hi = (ny * k) // nstripes, max((ny * (k + 1)) // nstripes - height, (ny * k) // nstripes)
        r0 = min(max(r0, lo), hi)
        if cum is not None:
            starts = np.arange(lo, hi + 1)
            held = cum[np.minimum(starts + height, ny)] - cum[starts]
            if held.max() > held[r0 - lo]:
                r0 = int(starts[np.argmax(held)])
        a, b = max(0, r0 - 1), min(ny, r0 + height + 1)
        out.append((slice(a, b), r0 - a, r0 - a + min(height, ny - r0)))
    return out
