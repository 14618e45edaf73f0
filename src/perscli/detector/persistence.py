"""Persistence: the charge that earlier exposures leave in later ones.

The model is the paper's (Lin et al., section 2.2): an earlier exposure with
fluence ``x`` electrons releases, ``t`` seconds after the end of that exposure,

    P(x, t) = F(x) * (t / 1000 s) ** (-gamma)          [e-/s]

with ``F`` the Fermi law ``A / (exp(-(x - x0)/dx) + 1) * (x / x0) ** alpha``
above ``half_well`` and a straight line through the origin below it.  The rate
separates into ``F(x)`` and a time factor, so the charge collected by a later
exposure is ``F(x) * T`` where ``T`` is the exact integral of the time factor
over that exposure's own window (:func:`time_factor`).  ``F`` is evaluated per
pixel once per earlier frame, by a compiled loop that streams the frame.

Three parameter sets are built in: the paper's Table 1 ('typical',
'pessimistic') and 'wfc3', STScI's parameters for HST WFC3-IR, which also
brings the WFC3 persistence pipeline's conventions (:func:`perscli.detector.settings.preset_settings`).

This module is the only place where persistence is computed: render,
apply-persistence and diagnose all call it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError, _kernels
from .settings import (COMBINES, DEFAULT_PRESET, FERMI_PARAMETERS, GALSIM_EXPTIME, GALSIM_LINEAR_COEFFICIENTS,
                       PERSISTENCE_SCHEMA, PRESETS, ROUNDINGS, SETTINGS, persistence_param, preset_settings)


@dataclass(frozen=True)
class PersistenceModel:
    """A persistence law: the paper's Fermi model or GalSim's linear one.

    Parameters
    ----------
    name : str
        Where the parameters came from ('typical', a YAML path, ...).
    kind : {'fermi', 'linear'}
        'fermi': the rate ``F(x) (t/1000)^-gamma``; 'linear': GalSim's
        ``coefficients[i] * x`` for the i-th most recent earlier exposure,
        independent of time.
    A, x0, dx, alpha, gamma, half_well : float
        Fermi parameters (see :data:`FERMI_PARAMETERS`).
    coefficients : tuple of float
        Linear coefficients, most recent exposure first.
    time_model : {'exact', 'middle', 'galsim'}
        How the rate becomes charge (see :data:`SETTINGS`).
    combine : {'sum', 'max'}
        How earlier exposures add up.
    max_previous : int
        Most recent earlier exposures that count (0: all).
    lookback : float
        Hours: earlier exposures that ended longer ago are ignored (0: no limit).
    rounding : {'none', 'round', 'floor'}
        The charge as computed, or rounded (truncated) to whole electrons
        (:func:`round_charge`).
    """

    name: str = DEFAULT_PRESET
    kind: str = "fermi"
    A: float = PRESETS[DEFAULT_PRESET]["A"]
    x0: float = PRESETS[DEFAULT_PRESET]["x0"]
    dx: float = PRESETS[DEFAULT_PRESET]["dx"]
    alpha: float = PRESETS[DEFAULT_PRESET]["alpha"]
    gamma: float = PRESETS[DEFAULT_PRESET]["gamma"]
    half_well: float = PRESETS[DEFAULT_PRESET]["half_well"]
    coefficients: tuple = field(default=GALSIM_LINEAR_COEFFICIENTS)
    time_model: str = preset_settings(DEFAULT_PRESET)["time_model"]
    combine: str = preset_settings(DEFAULT_PRESET)["combine"]
    max_previous: int = preset_settings(DEFAULT_PRESET)["max_previous"]
    lookback: float = preset_settings(DEFAULT_PRESET)["lookback"]
    rounding: str = persistence_param("rounding").default

    def __post_init__(self):
        # the one schema of a persistence model (perscli.detector.settings.PERSISTENCE_SCHEMA) checks a
        # model built here directly as it checks a model file or a --set
        where = f"persistence model {self.name!r}"
        for param in PERSISTENCE_SCHEMA:
            if hasattr(self, param.name):
                param.check("persistence", getattr(self, param.name), where)
        if self.kind == "fermi":
            for key in FERMI_PARAMETERS:
                if getattr(self, key) is None:
                    raise PerscliError(f"{where}: persistence.{key} is not given")

    @property
    def slope(self) -> float:
        """F(half_well) / half_well: the linear law's slope in (e-/s)/e- (0 without a linear branch)."""
        if self.half_well == 0:
            return 0.0
        return float(self.fermi(self.half_well) / self.half_well)

    def fermi(self, x):
        """The Fermi law alone (no linear branch), in e-/s at t = 1000 s."""
        x = np.asarray(x, dtype=np.float64)
        return self.A * (x / self.x0) ** self.alpha / (np.exp(-(x - self.x0) / self.dx) + 1.0)

    def F(self, x):
        """The rate at t = 1000 s per pixel, ``F(x)``, in e-/s (numpy, for reference use).

        Parameters
        ----------
        x : array_like
            Fluence of an earlier exposure in electrons.
        """
        x = np.asarray(x, dtype=np.float64)
        if self.kind == "linear":
            return x.copy()
        out = np.zeros_like(x)
        hi = x > self.half_well
        lo = (x > 0) & ~hi
        out[hi] = self.fermi(x[hi])
        out[lo] = self.slope * x[lo]
        return out

    def rate(self, x, t):
        """The persistence current ``P(x, t)`` in e-/s, ``t`` seconds after the earlier exposure."""
        if self.kind != "fermi":
            raise PerscliError("the linear model has no persistence current, only per-exposure fractions")
        return self.F(x) * (np.asarray(t, dtype=np.float64) / 1000.0) ** (-self.gamma)

    def with_settings(self, *, time_model=None, combine=None, max_previous=None,
                      lookback=None) -> "PersistenceModel":
        """This model with its settings replaced where given (command-line options over the model file).

        The name stays: the settings are recorded beside it (PSTIME, PSCOMB, PSMAXPRV, PSLOOKB).
        """
        changes = {k: v for k, v in (("time_model", time_model), ("combine", combine),
                                     ("max_previous", max_previous), ("lookback", lookback))
                   if v is not None and v != getattr(self, k)}
        return dataclasses.replace(self, **changes) if changes else self

    def params(self) -> dict:
        """The parameters and settings as a plain dict (for headers and YAML)."""
        if self.kind == "linear":
            out = {"kind": "linear", "coefficients": list(self.coefficients)}
        else:
            out = {key: getattr(self, key) for key in FERMI_PARAMETERS}
        out.update({key: getattr(self, key) for key in SETTINGS})
        if self.rounding != "none":
            out["rounding"] = self.rounding
        return out


def time_factor(t_start, t_end, gamma: float) -> np.ndarray:
    """Exact integral of ``(t/1000)^-gamma`` over ``[t_start, t_end]`` seconds.

    Parameters
    ----------
    t_start, t_end : float or array_like
        Seconds since the end of the earlier exposure; ``t_end >= t_start``.
    gamma : float
        Decay index.

    Returns
    -------
    ndarray
        Seconds; multiplied by ``F(x)`` (e-/s) it gives the charge collected.

    Notes
    -----
    ``1000^gamma (t2^(1-gamma) - t1^(1-gamma)) / (1-gamma)``, written as
    ``1000^gamma t1^(1-gamma) expm1((1-gamma) ln(t2/t1)) / (1-gamma)`` so that
    it is accurate for gamma near 1 and tends to ``1000 ln(t2/t1)`` at gamma = 1.
    """
    t1 = np.asarray(t_start, dtype=np.float64)
    t2 = np.asarray(t_end, dtype=np.float64)
    if np.any(t2 < t1):
        raise ValueError("t_end must not precede t_start")
    if gamma == 1.0:
        with np.errstate(divide="ignore"):
            return np.where(t2 == t1, 0.0, 1000.0 * np.log(t2 / t1))
    if np.any(t1 <= 0):
        if gamma > 1.0:
            raise ValueError("the integral diverges at t = 0 for gamma >= 1")
        # 0 <= gamma < 1: the plain form is finite at t1 = 0
        return 1000.0 ** gamma * (t2 ** (1 - gamma) - t1 ** (1 - gamma)) / (1 - gamma)
    u = (1.0 - gamma) * np.log(t2 / t1)
    return 1000.0 ** gamma * t1 ** (1.0 - gamma) * np.expm1(u) / (1.0 - gamma)


def middle_time_factor(gap, ends, gamma: float) -> np.ndarray:
    """The WFC3 pipeline's time factor: ``(t_mid/1000)^-gamma`` times the window, ``t_mid`` its middle.

    Parameters
    ----------
    gap : float
        Seconds from the end of the earlier exposure to the start of the current one.
    ends : float or array_like
        Seconds from the start of the current exposure to the end of each
        window (the exposure, or each read of a ramp: the window is then
        ``[0, read time]`` and ``t_mid`` its own middle).
    gamma : float

    Returns
    -------
    ndarray
        Seconds: ``e ((gap + e/2)/1000)^-gamma`` for each window length ``e``
        (0 for an empty window).

    Notes
    -----
    STScI's WFC3-IR persistence estimate counts time from EXPEND of the
    earlier exposure to the middle of the later one.  The
    decay is convex, so this falls below the exact integral
    (:func:`time_factor`): for gamma = 1 and a 300 s exposure by 30% when it
    starts 30 s after the earlier one ends, by 1.4% 600 s after, and by
    parts per million after 10 h (the difference is of second order in the
    window over the delay).
    """
    e = np.atleast_1d(np.asarray(ends, dtype=np.float64))
    mid = float(gap) + 0.5 * e
    out = np.zeros_like(e)
    live = e > 0
    out[live] = e[live] * (mid[live] / 1000.0) ** (-gamma)
    return out


def accumulate(fluence, acc, time_factors, model: PersistenceModel, *, scale: float = 1.0,
               combine: str = "sum", span=None):
    """Add ``T_k * F(scale * fluence)`` into ``acc[k]`` for every time factor, in one pass.

    Parameters
    ----------
    fluence : ndarray
        An earlier frame (or a block of its rows), float32 or float64,
        native or big-endian (the bytes of a FITS file can be passed as they
        are), C-contiguous.
    acc : ndarray of float64
        Accumulator of shape ``(len(time_factors),) + fluence.shape``, updated in place.
    time_factors : sequence of float
        ``T_k`` in seconds for each output plane (one per read of a ramp).
        For the linear model, the coefficient of this exposure.
    model : PersistenceModel
    scale : float
        Converts fluence values to electrons (gain, exposure time).
    combine : {'sum', 'max'}
        Add the contributions or keep the per-pixel maximum.
    span : (int, int), optional
        Only the flat pixel range ``[start, stop)`` (the compiled loop releases
        the GIL: threads may work on disjoint spans).

    Returns
    -------
    (int, int)
        Number of non-finite fluence pixels (counted as zero), and the FITS
        DATASUM of ``fluence``'s values written big-endian.
    """
    fluence = np.asarray(fluence)
    if fluence.dtype.kind != "f" or fluence.dtype.itemsize not in (4, 8):
        fluence = fluence.astype(np.float64)
    if not fluence.flags.c_contiguous:
        fluence = np.ascontiguousarray(fluence)
    if acc.dtype != np.float64 or not acc.flags.c_contiguous:
        raise TypeError("accumulator must be a C-contiguous float64 array")
    tf = [float(t) for t in time_factors]
    if acc.size != len(tf) * fluence.size:
        raise ValueError(f"accumulator has {acc.size} values, expected {len(tf)} x {fluence.size}")
    if combine not in COMBINES:
        raise PerscliError(f"--combine must be one of {', '.join(COMBINES)}, not {combine!r}")
    linear = model.kind == "linear"
    args = (tf, float(scale), combine == "max", int(linear), model.A, model.x0, model.dx,
            model.alpha, model.half_well, 0.0 if linear else model.slope)
    n = fluence.size
    return _kernels.accumulate(fluence, acc, *args, tuple(span) if span is not None else (0, n))


# -- persistence on arrays ------------------------------------------------------------------------

def exposure_time_factors(gap: float, ends, recency: int, model: PersistenceModel, *, label: str = "an earlier "
                          "exposure"):
    """What one earlier exposure contributes per unit of ``F(x)``, for each output plane.

    Parameters
    ----------
    gap : float
        Seconds from the end of the earlier exposure to the start of the current one.
    ends : sequence of float
        Seconds from the start of the current exposure to the end of each
        output plane: ``[exptime]`` for an image, the read times of a ramp.
    recency : int
        0 for the most recent earlier exposure (GalSim's time model and the
        linear model depend on it).
    model : PersistenceModel

    Returns
    -------
    list of float or None
        Seconds (the time integral of ``(t/1000)^-gamma``; with
        ``time_model='middle'`` its value at the middle of the window times
        the window, :func:`middle_time_factor`; GalSim's
        ``rate((0.5 + i) 139.8 s) 139.8 s`` with ``time_model='galsim'``), or
        the linear coefficient; None when the exposure is beyond the linear
        model's coefficients.
    """
    ends = np.atleast_1d(np.asarray(ends, dtype=np.float64))
    if model.kind == "linear":
        if len(ends) > 1:
            raise PerscliError("the linear model has no time dependence and cannot be applied read by read; "
                               "use a Fermi model (typical, pessimistic) for ramps")
        return [model.coefficients[recency]] if recency < len(model.coefficients) else None
    if model.time_model == "galsim":
        if len(ends) > 1:
            raise PerscliError("time_model galsim has no notion of reads; use time_model exact for ramps")
        mid = (0.5 + recency) * GALSIM_EXPTIME
        return [GALSIM_EXPTIME * (mid / 1000.0) ** (-model.gamma)]
    if model.time_model == "middle":
        return [float(v) for v in middle_time_factor(gap, ends, model.gamma)]
    if gap <= 0 and model.gamma >= 1:
        raise PerscliError(f"{label} ends exactly when the current exposure starts: with gamma={model.gamma:g} the "
                           "persistence integral diverges at zero delay; check the timestamps (a reset takes time)")
    try:
        return [float(v) for v in time_factor(np.full_like(ends, gap), gap + ends, model.gamma)]
    except ValueError as exc:
        raise PerscliError(f"{label}: {exc}") from None


def beyond_lookback(ends, start: float, model: PersistenceModel, *, unit_seconds: float = 1.0) -> list:
    """Indices of the earlier exposures that ended more than ``model.lookback`` hours before ``start``.

    Parameters
    ----------
    ends : sequence of float
        End of each earlier exposure, on the clock of ``start``.
    start : float
        Start of the current exposure.
    unit_seconds : float
        Seconds per unit of that clock (1 for seconds, 86400 for MJD).
    """
    if not model.lookback:
        return []
    limit = model.lookback * 3600.0
    return [i for i, end in enumerate(ends) if (float(start) - float(end)) * unit_seconds > limit]


def order_earlier(ends, start: float, model: PersistenceModel, names=None, *, unit_seconds: float = 1.0):
    """Which earlier exposures count, most recent first, after checking their times.

    Parameters
    ----------
    ends : sequence of float
        End of each earlier exposure (any clock, seconds or days, as ``start``).
    start : float
        Start of the current exposure, same clock.
    names : sequence of str, optional
        For messages.
    unit_seconds : float
        Seconds per unit of the clock (1 for seconds, 86400 for MJD): the
        model's look-back is in hours.

    Returns
    -------
    (list of int, list of int)
        Indices used (most recent first, those within ``model.lookback``
        hours unless 0, at most ``model.max_previous`` unless 0) and indices
        left out (beyond the look-back, then beyond max_previous).

    Raises
    ------
    PerscliError
        An exposure that does not end before ``start``, or one given twice
        (two earlier exposures of one detector cannot end at the same moment).
    """
    ends = [float(e) for e in ends]
    names = list(names) if names is not None else [f"earlier exposure {i + 1}" for i in range(len(ends))]
    for i, end in enumerate(ends):
        if end > start:
            raise PerscliError(f"{names[i]} ends after the current exposure starts: it is not an earlier exposure; "
                               "check the order or the timestamps")
    order = sorted(range(len(ends)), key=lambda i: ends[i], reverse=True)
    for a, b in zip(order, order[1:]):
        if ends[a] == ends[b]:
            raise PerscliError(f"{names[b]} and {names[a]} end at the same moment: the same earlier exposure is "
                               "given twice; give each earlier exposure once")
    old = set(beyond_lookback(ends, start, model, unit_seconds=unit_seconds))
    recent = [i for i in order if i not in old]
    keep = recent if model.max_previous == 0 else recent[:model.max_previous]
    return keep, [i for i in order if i in old] + recent[len(keep):]


def round_charge(charge: np.ndarray, rounding: str) -> np.ndarray:
    """The persistence charge as a frame receives it: as computed, or in whole electrons (in place).

    Parameters
    ----------
    charge : ndarray of float
        Electrons.
    rounding : {'none', 'round', 'floor'}
        'round': to the nearest whole electron (halves to even, numpy's
        rule); 'floor': truncated, as storing the charge in an integer image
        does (the charge is never negative, so truncation is the floor).

    Notes
    -----
    A persistence image kept in whole electrons drops every pixel below one
    electron (half an electron when rounded): only earlier pixels whose
    charge reaches that leave anything, a floor on the fluence that rises with
    the time since the earlier exposure.
    """
    if rounding == "round":
        np.round(charge, out=charge)
    elif rounding == "floor":
        np.floor(charge, out=charge)
    elif rounding != "none":
        raise PerscliError(f"persistence.rounding {rounding!r}: use one of {', '.join(ROUNDINGS)}")
    return charge


def persistence_charge(fluences, ends, start: float, plane_ends, model: PersistenceModel, *, scales=None):
    """The persistence charge that earlier exposures leave in the current one: arrays in, array out.

    The file-free core of ``perscli apply-persistence`` (which streams the
    same computation block by block from files) and of ``perscli render``.

    Parameters
    ----------
    fluences : sequence of ndarray, or of functions returning one
        Fluence of each earlier exposure, all of one shape (electrons, or
        times ``scales``).  Non-finite values count as zero.  A function is
        called when its exposure is used and its array dropped right after
        (so it may hand back the same scratch array each time).
    ends : sequence of float
        End of each earlier exposure, in seconds on the clock of ``start``.
    start : float
        Start of the current exposure, seconds.
    plane_ends : float or sequence of float
        Seconds from ``start`` to the end of the exposure (an image), or to
        each read (a ramp: one output plane per read).
    model : PersistenceModel
        The law and its settings (time_model, combine, max_previous).
    scales : sequence of float, optional
        Multiply each fluence into electrons (gain, exposure time).

    Returns
    -------
    ndarray of float64, shape ``(nplanes,) + fluence shape``
        Electrons (rounded as ``model.rounding`` says, :func:`round_charge`).
    """
    fluences = [f if callable(f) else np.asarray(f) for f in fluences]
    if len(fluences) != len(ends):
        raise ValueError("one end time per fluence array")
    plane_ends = np.atleast_1d(np.asarray(plane_ends, dtype=np.float64))
    if not fluences:
        raise PerscliError("no earlier exposure: persistence needs at least one")
    arrays = [f for f in fluences if not callable(f)]
    shape = arrays[0].shape if arrays else fluences[0]().shape
    for f in arrays:
        if f.shape != shape:
            raise PerscliError(f"earlier exposures differ in shape ({f.shape} and {shape}): they must cover the same "
                               "detector pixels")
    scales = [1.0] * len(fluences) if scales is None else [float(s) for s in scales]
    keep, _ = order_earlier(ends, start, model)
    acc = np.zeros((len(plane_ends),) + shape)
    for recency, i in enumerate(keep):
        factors = exposure_time_factors(start - float(ends[i]), plane_ends, recency, model,
                                        label=f"earlier exposure {i + 1}")
        if factors is None:
            continue
        fluence = fluences[i]() if callable(fluences[i]) else fluences[i]
        accumulate(np.ascontiguousarray(fluence), acc, factors, model, scale=scales[i], combine=model.combine)
    return round_charge(acc, model.rounding)
