"""The detector model: a chain of effects in physical order, each switchable.

A detector model is a YAML file listing effects in the order they happen
physically, each with its parameters; every effect can be switched off with
``enabled: false``.  The defaults (:data:`DEFAULTS`) are GalSim's Roman
module (galsim.roman) and follow its order::

    effects:
      - sky:          {level: auto}        # zodiacal + thermal, e-/pixel/s ('auto': galsim.roman)
      - poisson:      {}                   # photon noise (integer electrons)
      - reciprocity:  {alpha: 0.0065, base_flux: 1.0}
      - dark:         {current: 0.015}     # e-/pixel/s, Poisson
      - persistence:  {base: typical}      # the Fermi model of earlier exposures (--previous)
      - nonlinearity: {beta: -6.0e-7}      # x + beta x^2
      - ipc:          {kernel: roman}      # 3x3 interpixel capacitance
      - read_noise:   {sigma: 8.5}         # e-, Gaussian
      - gain:         {gain: 1.0}          # e-/DN: the output is in DN
      - quantize:     {}                   # round to integers

Each effect draws its random numbers from its own stream, derived from the
seed and the effect's name, so switching one effect on or off leaves the
noise of every other effect unchanged: a frame rendered with persistence and
one without differ only by the persistence (what a paired measurement needs).

Persistence is not implemented here: the chain calls
:mod:`perscli.detector.persistence`, the one home of that model.
"""

from __future__ import annotations

import copy
import zlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import PerscliError

ORDER = ("sky", "poisson", "reciprocity", "dark", "persistence", "nonlinearity", "ipc",
         "read_noise", "gain", "quantize")

#: GalSim's Roman values (galsim.roman: reciprocity_alpha, dark_current, nonlinearity_beta,
#: ipc_kernel, read_noise, gain); persistence parameters are those of the paper's 'typical' set.
DEFAULTS = {
    "sky": {"level": "auto"},
    "poisson": {},
    "reciprocity": {"alpha": 0.0065, "base_flux": 1.0},
    "dark": {"current": 0.015},
    "persistence": {"base": "typical"},
    "nonlinearity": {"beta": -6.0e-7},
    "ipc": {"kernel": "roman"},
    "read_noise": {"sigma": 8.5},
    "gain": {"gain": 1.0},
    "quantize": {},
}

DESCRIPTIONS = {
    "sky": "zodiacal and thermal background, e-/pixel/s ('auto': galsim.roman.getSkyLevel + thermal)",
    "poisson": "Poisson noise of the collected charge",
    "reciprocity": "reciprocity failure x (1 + alpha log10(x / (base_flux t))) (GalSim: its power-law form)",
    "dark": "dark current (e-/pixel/s) with its Poisson noise",
    "persistence": "persistence of earlier exposures (perscli's Fermi model, exact time integral)",
    "nonlinearity": "classical nonlinearity x + beta x^2",
    "ipc": "interpixel capacitance, 3x3 kernel ('roman' or a 3x3 list)",
    "read_noise": "Gaussian read noise sigma (e-)",
    "gain": "conversion to DN with gain (e-/DN)",
    "quantize": "rounding to integer values",
}


@dataclass
class Effect:
    """One step of the chain."""

    name: str
    params: dict = field(default_factory=dict)
    enabled: bool = True


@dataclass
class DetectorModel:
    """An ordered list of effects."""

    effects: list
    source: str = "roman"

    def get(self, name: str) -> Effect | None:
        for eff in self.effects:
            if eff.name == name:
                return eff
        return None

    def enabled(self, name: str) -> bool:
        eff = self.get(name)
        return eff is not None and eff.enabled

    def describe(self) -> list:
        """[(name, enabled, params)] for headers and logs."""
        return [(e.name, e.enabled, dict(e.params)) for e in self.effects]

    def persistence_model(self):
        """The :class:`~perscli.detector.persistence.PersistenceModel` of the persistence step."""
        from .persistence import _model_from_mapping

        eff = self.get("persistence")
        return _model_from_mapping(dict(eff.params) if eff else {}, f"{self.source}: persistence")


def default_model() -> DetectorModel:
    """GalSim's Roman chain, every effect on."""
    return DetectorModel([Effect(name, copy.deepcopy(DEFAULTS[name])) for name in ORDER], source="roman")


def load_detector_model(spec: str | None = None, overrides=()) -> DetectorModel:
    """Read a detector model and apply ``EFFECT.KEY=VALUE`` overrides.

    Parameters
    ----------
    spec : str, optional
        'roman' (or None) for :func:`default_model`, or a YAML file: either a
        list under ``effects:`` (in physical order) of ``{name: {params}}``
        mappings, or a mapping ``name: {params}``.  Effects not listed are
        off; parameters not given take the Roman defaults.
    overrides : sequence of str
        'EFFECT.KEY=VALUE' (e.g. 'read_noise.sigma=5'), 'EFFECT=off' or
        'EFFECT=on'.

    Returns
    -------
    DetectorModel
    """
    if spec in (None, "roman", "default"):
        model = default_model()
    else:
        model = _from_yaml(spec)
    for text in overrides:
        _override(model, text)
    return model


def _from_yaml(path: str) -> DetectorModel:
    from ..io.config import load_yaml

    doc = load_yaml(path, "detector model")
    if isinstance(doc, dict) and "effects" in doc:
        doc = doc["effects"]
    if isinstance(doc, dict):
        items = list(doc.items())
    elif isinstance(doc, list):
        items = []
        for entry in doc:
            if isinstance(entry, str):
                items.append((entry, {}))
            elif isinstance(entry, dict) and len(entry) == 1:
                items.append(next(iter(entry.items())))
            else:
                raise PerscliError(f"{path}: each effect must be a name or a one-key mapping, not {entry!r}")
    else:
        raise PerscliError(f"{path}: expected 'effects:' with a list of effects in physical order")
    effects, seen = [], set()
    for name, params in items:
        if name not in DEFAULTS:
            raise PerscliError(f"{path}: unknown effect {name!r}; known: {', '.join(ORDER)}")
        if name in seen:
            raise PerscliError(f"{path}: effect {name!r} is listed twice")
        seen.add(name)
        params = dict(params or {})
        enabled = params.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise PerscliError(f"{path}: {name}.enabled must be true or false, not {enabled!r}")
        merged = copy.deepcopy(DEFAULTS[name])
        merged.update(params)
        eff = Effect(name, merged, enabled)
        _validate(eff, path)
        effects.append(eff)
    order = [ORDER.index(e.name) for e in effects]
    if order != sorted(order):
        raise PerscliError(f"{path}: effects must be listed in physical order: {', '.join(ORDER)}")
    return DetectorModel(effects, source=path)


def _override(model: DetectorModel, text: str) -> None:
    if "=" not in text:
        raise PerscliError(f"--set {text!r} is not EFFECT.KEY=VALUE or EFFECT=on|off")
    key, value = (s.strip() for s in text.split("=", 1))
    name, _, param = key.partition(".")
    if name not in DEFAULTS:
        raise PerscliError(f"--set {text!r}: unknown effect {name!r}; known: {', '.join(ORDER)}")
    eff = model.get(name)
    if eff is None:
        eff = Effect(name, copy.deepcopy(DEFAULTS[name]), enabled=False)
        model.effects.append(eff)
        model.effects.sort(key=lambda e: ORDER.index(e.name))
    if not param:
        if value.lower() not in ("on", "off", "true", "false"):
            raise PerscliError(f"--set {text!r}: use {name}=on or {name}=off")
        eff.enabled = value.lower() in ("on", "true")
        return
    import yaml

    eff.params[param] = yaml.safe_load(value)
    eff.enabled = True
    _validate(eff, "--set")


def _validate(eff: Effect, where: str) -> None:
    """Reject unknown parameters and values of the wrong kind."""
    if eff.name == "persistence":
        eff.params.pop("enabled", None)
        from .persistence import _model_from_mapping

        _model_from_mapping(dict(eff.params), f"{where}: persistence")
        return
    allowed = set(DEFAULTS[eff.name])
    unknown = set(eff.params) - allowed
    if unknown:
        raise PerscliError(f"{where}: unknown parameter(s) {', '.join(sorted(unknown))} for effect "
                           f"{eff.name!r}; valid: {', '.join(sorted(allowed)) or 'none'}")
    for key, value in eff.params.items():
        if eff.name == "sky" and key == "level" and value == "auto":
            continue
        if eff.name == "ipc" and key == "kernel":
            if value == "roman":
                continue
            arr = np.asarray(value, dtype=float) if isinstance(value, list) else None
            if arr is None or arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
                raise PerscliError(f"{where}: ipc.kernel must be 'roman' or a 3x3 list of numbers")
            continue
        if isinstance(value, str):
            # YAML 1.1 reads '-6e-7' (no decimal point) as text: accept any number Python can parse
            try:
                value = eff.params[key] = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise PerscliError(f"{where}: {eff.name}.{key}={value!r} must be a finite number")
        if key in ("gain", "base_flux") and value <= 0:
            raise PerscliError(f"{where}: {eff.name}.{key}={value!r} must be positive")
        if key in ("current", "sigma", "level") and value < 0:
            raise PerscliError(f"{where}: {eff.name}.{key}={value!r} must not be negative")


def _stream(seed: int, name: str) -> np.random.Generator:
    """The random stream of one effect: depends on the seed and the effect's name only."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), zlib.crc32(name.encode())])))


def roman_ipc_kernel() -> np.ndarray:
    import galsim.roman

    return np.asarray(galsim.roman.ipc_kernel.array, dtype=np.float64)


def apply_ipc(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Interpixel capacitance with a 3x3 kernel, as GalSim's ``Image.applyIPC(edge_treatment='extend')``.

    ``kernel[j, i]`` is the fraction of the signal of the neighbour at offset
    (i - 1, j - 1) that appears in a pixel (GalSim's definition, so the
    asymmetric Roman kernel is applied as GalSim applies it); outside the
    image there is no charge (zero padding).
    """
    from scipy import ndimage

    # one compiled pass: a correlation (not a convolution) is GalSim's definition of the kernel
    return ndimage.correlate(np.asarray(image, dtype=np.float64), np.asarray(kernel, dtype=np.float64),
                             mode="constant", cval=0.0)


@dataclass
class ChainResult:
    """What the chain produced."""

    sci: np.ndarray          # the final frame
    unit: str                # 'DN' after gain, else 'electron'
    ideal: np.ndarray        # sources + sky, noise-free, electrons
    fluence: np.ndarray      # charge collected (drives later persistence), electrons
    persistence: np.ndarray | None = None   # electrons added by earlier exposures
    sky_rate: float = 0.0    # e-/pixel/s used


def run_chain(sources: np.ndarray, model: DetectorModel, *, exptime: float, seed: int,
              sky_rate: Callable[[], float] | float = 0.0,
              persistence: Callable[[], np.ndarray] | None = None) -> ChainResult:
    """Apply the detector chain to an image of source electrons.

    Parameters
    ----------
    sources : ndarray
        Expected electrons from astronomical sources over the exposure.
    model : DetectorModel
    exptime : float
        Seconds.
    seed : int
        Seed of every random stream.
    sky_rate : float or callable
        The automatic sky level in e-/pixel/s (called only if the sky effect
        is on with level 'auto').
    persistence : callable, optional
        Returns the persistence in electrons (same shape) when the
        persistence effect is on; None means no earlier exposures.

    Returns
    -------
    ChainResult
    """
    img = np.array(sources, dtype=np.float64)
    unit = "electron"
    rate = 0.0
    pers = None
    ideal = None
    fluence = None
    after_persistence = ORDER.index("persistence")
    for eff in model.effects:
        if fluence is None and ORDER.index(eff.name) > after_persistence:
            # the charge collected so far is what traps hold on to: it drives later persistence
            fluence = img.copy()
        if not eff.enabled:
            continue
        p = eff.params
        if eff.name == "sky":
            rate = float(sky_rate() if callable(sky_rate) else sky_rate) if p["level"] == "auto" else float(p["level"])
            img += rate * exptime
        elif eff.name == "poisson":
            if ideal is None:
                ideal = img.copy()
            img = _stream(seed, "poisson").poisson(np.clip(img, 0.0, None)).astype(np.float64)
        elif eff.name == "reciprocity":
            # the empirical law itself, x (1 + alpha log10(x / (base_flux t))); GalSim's
            # Image.addReciprocityFailure uses its power-law approximation x (x/x0)^(alpha/ln 10),
            # 3e-4 apart at 1e6 e-.  Zero and negative pixels are left alone.
            pos = img > 0
            factor = np.log10(img, where=pos, out=np.zeros_like(img))
            factor -= np.log10(p["base_flux"] * exptime)
            factor *= p["alpha"]
            factor += 1.0
            np.multiply(img, factor, out=img, where=pos)
        elif eff.name == "dark":
            img += _stream(seed, "dark").poisson(p["current"] * exptime, size=img.shape)
        elif eff.name == "persistence":
            if persistence is not None:
                pers = np.asarray(persistence(), dtype=np.float64)
                img += pers
        elif eff.name == "nonlinearity":
            img += p["beta"] * img * img
        elif eff.name == "ipc":
            kernel = roman_ipc_kernel() if p["kernel"] == "roman" else np.asarray(p["kernel"], dtype=float)
            img = apply_ipc(img, kernel)
        elif eff.name == "read_noise":
            img += _stream(seed, "read_noise").normal(0.0, p["sigma"], size=img.shape)
        elif eff.name == "gain":
            img /= p["gain"]
            unit = "DN"
        elif eff.name == "quantize":
            img = np.round(img)
    if ideal is None:
        ideal = np.array(sources, dtype=np.float64) + rate * exptime
    if fluence is None:
        fluence = img.copy()
    return ChainResult(sci=img, unit=unit, ideal=ideal, fluence=fluence, persistence=pers, sky_rate=rate)
