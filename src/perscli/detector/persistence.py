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

This module is the only place where persistence is computed: render,
apply-persistence and diagnose all call it.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from .. import PerscliError

#: Parameter sets of the paper's Table 1 (GalSim's Roman module uses 'typical').
PRESETS = {
    "typical": dict(A=0.017, x0=6.0e4, dx=5.0e4, alpha=0.045, gamma=1.0, half_well=5.0e4),
    "pessimistic": dict(A=0.086, x0=1.37e5, dx=2.6e4, alpha=0.02, gamma=1.0, half_well=5.0e4),
}

#: GalSim's linear persistence coefficients (galsim.roman.persistence_coefficients):
#: the fraction of the i-th most recent earlier exposure added to the current one.
GALSIM_LINEAR_COEFFICIENTS = (
    4.5707683e-4, 1.4959818e-4, 9.115737e-5, 6.56769e-5,
    5.135571e-5, 4.217028e-5, 3.577534e-5, 3.106601e-5,
)

#: GalSim's Roman exposure time (galsim.roman.exptime), used by its 'fermi' method.
GALSIM_EXPTIME = 139.8

#: The schema of the Fermi parameters: name -> (description, unit).
FERMI_PARAMETERS = {
    "A": ("normalisation of the current at t = 1000 s", "e-/s"),
    "x0": ("fluence of the Fermi step", "e-"),
    "dx": ("width of the Fermi step", "e-"),
    "alpha": ("power-law index of the fluence dependence", ""),
    "gamma": ("power-law index of the decay in time", ""),
    "half_well": ("fluence below which the law is linear", "e-"),
}

TIME_MODELS = ("exact", "galsim")
COMBINES = ("sum", "max")


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
    """

    name: str = "typical"
    kind: str = "fermi"
    A: float = PRESETS["typical"]["A"]
    x0: float = PRESETS["typical"]["x0"]
    dx: float = PRESETS["typical"]["dx"]
    alpha: float = PRESETS["typical"]["alpha"]
    gamma: float = PRESETS["typical"]["gamma"]
    half_well: float = PRESETS["typical"]["half_well"]
    coefficients: tuple = field(default=GALSIM_LINEAR_COEFFICIENTS)

    def __post_init__(self):
        if self.kind not in ("fermi", "linear"):
            raise PerscliError(f"persistence model kind must be 'fermi' or 'linear', not {self.kind!r}")
        if self.kind == "fermi":
            for key in FERMI_PARAMETERS:
                value = getattr(self, key)
                if not (isinstance(value, (int, float)) and math.isfinite(value)):
                    raise PerscliError(f"persistence parameter {key}={value!r} is not a finite number")
            for key in ("x0", "dx", "half_well"):
                if getattr(self, key) <= 0:
                    raise PerscliError(
                        f"persistence parameter {key}={getattr(self, key)!r} must be positive (electrons)")
            if self.A < 0:
                raise PerscliError(f"persistence parameter A={self.A!r} must not be negative (e-/s)")
        else:
            if len(self.coefficients) == 0 or not all(math.isfinite(c) for c in self.coefficients):
                raise PerscliError("linear persistence model needs a list of finite coefficients")

    @property
    def slope(self) -> float:
        """F(half_well) / half_well: the linear law's slope in (e-/s)/e-."""
        return self.fermi(self.half_well) / self.half_well

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

    def params(self) -> dict:
        """The parameters as a plain dict (for headers and YAML)."""
        if self.kind == "linear":
            return {"coefficients": list(self.coefficients)}
        return {key: getattr(self, key) for key in FERMI_PARAMETERS}


def _number(key, value, source):
    try:
        return float(value)
    except (TypeError, ValueError):
        raise PerscliError(f"{source}: persistence parameter {key}={value!r} is not a number") from None


def load_model(spec: str = "typical", overrides: Mapping[str, object] | Sequence[str] = ()) -> PersistenceModel:
    """Build a persistence model from a name or a YAML file, with overrides.

    Parameters
    ----------
    spec : str
        'typical' or 'pessimistic' (the paper's Table 1), 'galsim-linear'
        (GalSim's 8 coefficients), or the path of a YAML file.  The YAML file
        holds either the parameters at top level or under a ``persistence:``
        key (so a detector-model file can be given), optionally with
        ``base: typical|pessimistic`` to start from a preset, ``kind:
        linear`` with ``coefficients: [...]`` for a linear model.
    overrides : mapping or sequence of 'KEY=VALUE'
        Values of A, x0, dx, alpha, gamma, half_well that replace those of
        ``spec``; unknown keys are an error.

    Returns
    -------
    PersistenceModel
    """
    if spec in PRESETS:
        model = PersistenceModel(name=spec, **PRESETS[spec])
    elif spec == "galsim-linear":
        model = PersistenceModel(name=spec, kind="linear")
    elif spec.endswith((".yaml", ".yml")) or os.path.exists(spec):
        model = _model_from_yaml(spec)
    else:
        raise PerscliError(
            f"unknown persistence model {spec!r}: use typical, pessimistic, galsim-linear or a YAML file")
    if isinstance(overrides, Mapping):
        items = list(overrides.items())
    else:
        items = []
        for text in overrides:
            if "=" not in text:
                raise PerscliError(f"--param {text!r} is not KEY=VALUE (e.g. --param gamma=1.1)")
            key, value = text.split("=", 1)
            items.append((key.strip(), value.strip()))
    if not items:
        return model
    if model.kind != "fermi":
        raise PerscliError(f"parameters cannot be overridden for the linear model {model.name!r}; "
                           "use --model typical|pessimistic|FILE.yaml to set Fermi parameters")
    changes = {}
    for key, value in items:
        if key not in FERMI_PARAMETERS:
            raise PerscliError(
                f"unknown persistence parameter {key!r}: valid are {', '.join(FERMI_PARAMETERS)}")
        changes[key] = _number(key, value, "--param")
    desc = ",".join(f"{k}={v:g}" for k, v in changes.items())
    return dataclasses.replace(model, name=f"{model.name}+{desc}", **changes)


def _model_from_yaml(path: str) -> PersistenceModel:
    from ..io.config import load_yaml

    doc = load_yaml(path, "persistence model")
    if isinstance(doc, Mapping) and isinstance(doc.get("persistence"), Mapping):
        doc = doc["persistence"]
    if isinstance(doc, Mapping) and isinstance(doc.get("effects"), list):
        # a detector model: take its persistence step
        steps = [e["persistence"] for e in doc["effects"] if isinstance(e, Mapping) and "persistence" in e]
        doc = steps[0] if steps else None
    if not isinstance(doc, Mapping):
        raise PerscliError(f"{path}: expected a mapping of persistence parameters (A, x0, dx, alpha, gamma, half_well)")
    return _model_from_mapping(dict(doc), path)


def _model_from_mapping(doc: dict, path: str) -> PersistenceModel:
    """A model from parsed parameters (a YAML file's, or a detector model's persistence step)."""
    doc = dict(doc)
    kind = doc.pop("kind", doc.pop("model", "fermi"))
    base = doc.pop("base", None)
    doc.pop("enabled", None)
    if kind == "linear":
        coeffs = doc.pop("coefficients", GALSIM_LINEAR_COEFFICIENTS)
        if doc:
            raise PerscliError(f"{path}: unknown keys for a linear model: {', '.join(map(str, doc))}")
        if not isinstance(coeffs, (list, tuple)):
            raise PerscliError(f"{path}: coefficients must be a list of numbers")
        return PersistenceModel(name=path, kind="linear",
                                coefficients=tuple(_number("coefficients", c, path) for c in coeffs))
    if kind != "fermi":
        raise PerscliError(f"{path}: kind must be 'fermi' or 'linear', not {kind!r}")
    if base is not None and base not in PRESETS:
        raise PerscliError(f"{path}: base must be one of {', '.join(PRESETS)}, not {base!r}")
    params = dict(PRESETS[base or "typical"])
    unknown = [k for k in doc if k not in FERMI_PARAMETERS]
    if unknown:
        raise PerscliError(
            f"{path}: unknown persistence parameter(s) {', '.join(map(str, unknown))}; "
            f"valid are {', '.join(FERMI_PARAMETERS)}")
    missing = [k for k in FERMI_PARAMETERS if k not in doc] if base is None else []
    if missing:
        raise PerscliError(f"{path}: missing {', '.join(missing)} (or give 'base: typical' to start from a preset)")
    params.update({k: _number(k, v, path) for k, v in doc.items()})
    name = base if base and not doc else path
    return PersistenceModel(name=name, **params)


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


def ones_complement_add(a: int, b: int) -> int:
    """Add two 32-bit ones'-complement sums (how FITS DATASUMs of pieces combine)."""
    s = a + b
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


def accumulate(fluence, acc, time_factors, model: PersistenceModel, *, scale: float = 1.0,
               combine: str = "sum", pool=None, workers: int = 1):
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
    pool : concurrent.futures.Executor, optional
        Threads to split the pixels across (the compiled loop releases the GIL).
    workers : int
        Number of pieces to split into when ``pool`` is given.

    Returns
    -------
    (int, int)
        Number of non-finite fluence pixels (counted as zero), and the FITS
        DATASUM of ``fluence``'s values written big-endian.
    """
    from .. import _kernels

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
    if pool is None or workers <= 1 or n < 1 << 16:
        return _kernels.accumulate(fluence, acc, *args, (0, n))
    edges = np.linspace(0, n, workers + 1).astype(np.int64)
    futures = [pool.submit(_kernels.accumulate, fluence, acc, *args, (int(a), int(b)))
               for a, b in zip(edges[:-1], edges[1:])]
    nonfinite, datasum = 0, 0
    for future in futures:
        bad, part = future.result()
        nonfinite += bad
        datasum = ones_complement_add(datasum, part)
    return nonfinite, datasum
