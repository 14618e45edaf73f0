"""Running the detector chain: the effects of a model applied in order to an image of source electrons.

:func:`run_chain` draws a frame (each effect's ``sample``), :func:`run_chains`
draws several models of one exposure sharing their common steps, and
:func:`forward` propagates the mean and variance (each effect's
``expectation`` and ``variance``) for a likelihood.  The effects and the YAML
model format are documented in :mod:`perscli.detector.effects`; the noise
blocks in :mod:`perscli.detector.blocks`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .blocks import BlockStack, ChainContext
from .model import DetectorModel, Effect

# -- running the chain ---------------------------------------------------------------------------


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
              persistence: Callable[[], np.ndarray] | np.ndarray | None = None,
              origin=(1, 1), active=None) -> ChainResult:
    """Apply the detector chain to an image of source electrons: ``sample`` of each effect in order.

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
    persistence : ndarray or callable, optional
        The persistence in electrons (same shape), or a function returning
        it, called only when the persistence effect is on; None means no
        earlier exposures.
    origin : (int, int)
        Detector pixel (x, y), 1-indexed, of ``sources[0, 0]``: where the
        image lies on the noise blocks (:func:`block_streams`).  Every block
        the image covers should be covered whole (but at the detector's
        edges) for its pixels to get the noise of a whole-detector frame.
    active : ndarray of bool, optional
        Only these noise blocks (:func:`block_grid` shape) are simulated; the
        pixels of the others are NaN in SCI and FLUENCE.

    Returns
    -------
    ChainResult
        IDEAL is the image before the first effect after the 'scene' stage,
        FLUENCE before the first 'readout' effect (whether those are on or not).
    """
    return run_chains(sources, {"": model}, exptime=exptime, seed=seed, sky_rate=sky_rate,
                      persistence={"": persistence}, origin=origin, active=active)[""]


def _same_step(a: Effect, b: Effect) -> bool:
    return a.name == b.name and a.enabled == b.enabled and a.resolved() == b.resolved()


def run_chains(sources: np.ndarray, models: dict, *, exptime: float, seed: int,
               sky_rate: Callable[[], float] | float = 0.0, persistence: dict | None = None,
               origin=(1, 1), active=None, blocks: BlockStack | None = None) -> dict:
    """:func:`run_chain` for several models of one exposure, sharing the steps they have in common.

    The results of :func:`iter_chains`, all at once.
    """
    return dict(iter_chains(sources, models, exptime=exptime, seed=seed, sky_rate=sky_rate,
                            persistence=persistence, origin=origin, active=active, blocks=blocks))


def iter_chains(sources: np.ndarray, models: dict, *, exptime: float, seed: int,
                sky_rate: Callable[[], float] | float = 0.0, persistence: dict | None = None,
                origin=(1, 1), active=None, blocks: BlockStack | None = None, frames: bool = True):
    """:func:`run_chain` for several models of one exposure, sharing the steps they have in common.

    The same frame with and without persistence, or with two persistence
    laws, differs from the persistence step on: the steps before it (sky,
    Poisson noise, reciprocity, dark current) are taken once, and each model
    goes on from there.  Every effect draws from its own streams, so each
    result is the bits :func:`run_chain` gives for that model alone.

    Parameters
    ----------
    models : dict
        Name -> DetectorModel.
    persistence : dict, optional
        Name -> the persistence charge (or a function giving it, or None) of
        that model; missing names: None.
    blocks : BlockStack, optional
        ``sources`` and the charges are stacks of these noise blocks, and so
        are the results (:class:`BlockStack`).
    frames : bool
        False: the results' IDEAL and FLUENCE are None (not copied: a
        caller that keeps only SCI).
    Others as for :func:`run_chain`.

    Yields
    ------
    (name, ChainResult)
        In the order of ``models``, one at a time: a caller that keeps only
        what it needs of each holds one model's frames at a time (a study's
        final with twenty persistence variants).
    """
    persistence = persistence or {}
    names = list(models)
    chains = [models[n].effects for n in names]
    # the common prefix: the same effects with the same parameters, before any persistence charge differs
    shared = 0
    while len(names) > 1 and all(len(c) > shared for c in chains) \
            and all(_same_step(c[shared], chains[0][shared]) for c in chains) \
            and not (chains[0][shared].name == "persistence" and chains[0][shared].enabled):
        shared += 1
    ctx0 = ChainContext(exptime=exptime, seed=seed, sky_rate=sky_rate, origin=tuple(origin), active=active,
                        blocks=blocks)
    img = np.array(sources, dtype=np.float64)
    state = _Steps(frames)
    for eff in chains[0][:shared]:
        img = state.step(eff, img, ctx0)
    draws = {} if len(names) > 1 else None
    for n, chain in zip(names, chains):
        ctx = ChainContext(exptime=exptime, seed=seed, sky_rate=ctx0.sky, persistence=persistence.get(n),
                           origin=tuple(origin), active=active, blocks=blocks, shared=draws)
        ctx.used_sky_rate = ctx0.used_sky_rate
        branch = state.copy()
        mine = img.copy() if len(names) > 1 else img
        for eff in chain[shared:]:
            mine = branch.step(eff, mine, ctx)
        yield n, branch.result(mine, ctx)
        del mine, branch, ctx


class _Steps:
    """The running state of a chain: IDEAL and FLUENCE as they are passed, and the unit."""

    def __init__(self, frames: bool = True):
        self.unit, self.ideal, self.fluence = "electron", None, None
        self.frames = frames

    def copy(self) -> "_Steps":
        other = _Steps(self.frames)
        other.unit, other.ideal, other.fluence = self.unit, self.ideal, self.fluence
        return other

    def step(self, eff: Effect, img: np.ndarray, ctx: ChainContext) -> np.ndarray:
        cls = eff.cls
        if self.frames and self.ideal is None and cls.stage != "scene":
            self.ideal = img.copy()
        if self.frames and self.fluence is None and cls.stage == "readout":
            # the charge collected so far is what traps hold on to: it drives later persistence
            self.fluence = img.copy()
        if not eff.enabled:
            return img
        img = eff.instance().sample(img, ctx)
        self.unit = cls.unit_out or self.unit
        return img

    def result(self, img: np.ndarray, ctx: ChainContext) -> ChainResult:
        if not self.frames:
            return ChainResult(sci=img, unit=self.unit, ideal=None, fluence=None, persistence=ctx.used_persistence,
                               sky_rate=ctx.used_sky_rate)
        ideal = self.ideal if self.ideal is not None else img.copy()
        fluence = self.fluence if self.fluence is not None else img.copy()
        return ChainResult(sci=img, unit=self.unit, ideal=ideal, fluence=fluence, persistence=ctx.used_persistence,
                           sky_rate=ctx.used_sky_rate)


@dataclass
class Forward:
    """The noise-free forward model of a frame: mean and variance per pixel."""

    mean: np.ndarray         # expected SCI, in ``unit``
    variance: np.ndarray     # its variance per pixel (pixels taken as independent), ``unit`` squared
    unit: str
    fluence: np.ndarray      # expected collected charge, electrons
    sky_rate: float = 0.0


def _frozen(value):
    """A parameter value as a dictionary key (lists, e.g. a kernel, as tuples)."""
    if isinstance(value, dict):
        return tuple(sorted((k, _frozen(v)) for k, v in value.items()))
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(v) for v in value)
    return value


class ChargeCache:
    """The charge stage of :func:`forward` kept for the inputs a caller evaluates again and again.

    A likelihood fit of a readout effect (gain, read noise, nonlinearity, IPC,
    ...) evaluates the chain many times with the same charge stage (Poisson,
    reciprocity, dark, persistence, brighter-fatter, saturation): its mean,
    variance and fluence are kept here, keyed by the caller's name for the
    input (``key``: e.g. exposure and rows, the same sources and persistence
    charge each time) and every charge-stage effect's parameters, the last
    ``keep`` of each input.  The readout stage then starts from copies, so the
    result is the same bit for bit as without the cache.
    """

    def __init__(self, keep: int = 2):
        self.keep = keep
        self._entries = {}          # key -> {charge-stage parameters: (fluence, var, unit, sky rate)}
        self._lock = threading.Lock()

    def get(self, key, params):
        with self._lock:
            have = self._entries.get(key, {})
            hit = have.pop(params, None)
            if hit is not None:
                have[params] = hit                  # most recently used last
            return hit

    def put(self, key, params, value):
        with self._lock:
            have = self._entries.setdefault(key, {})
            have[params] = value
            while len(have) > self.keep:
                del have[next(iter(have))]


def forward(sources: np.ndarray, model: DetectorModel, *, exptime: float,
            sky_rate: Callable[[], float] | float = 0.0,
            persistence: Callable[[], np.ndarray] | np.ndarray | None = None,
            cache: ChargeCache | None = None, key=None) -> Forward:
    """Expectation and variance of a frame through the chain: what a likelihood of measured frames needs.

    Parameters are those of :func:`run_chain` (no seed: nothing is drawn).
    The mean is each effect's ``expectation`` of the previous mean; the
    variance is propagated with each effect's ``variance`` (first order in
    the noise: e.g. nonlinearity scales it by (1 + 2 beta x)^2).  With
    ``cache`` (a :class:`ChargeCache`) and ``key`` (what names ``sources``,
    ``persistence`` and ``sky_rate`` for the caller: the same key must mean
    the same inputs), the charge stage is taken from the cache when its
    effects' parameters are those of an earlier call.
    """
    effects = list(model.effects)
    first_readout = next((k for k, eff in enumerate(effects) if eff.cls.stage == "readout"), len(effects))
    params = None
    hit = None
    if cache is not None and key is not None:
        params = (float(exptime),) + tuple((eff.name, eff.enabled, _frozen(eff.params))
                                           for eff in effects[:first_readout])
        hit = cache.get(key, params)
    if hit is not None:
        fluence, var, unit, used_sky = hit        # the charge stage's mean is the fluence the readout starts from
        mean, var = fluence.copy(), var.copy()
        ctx = ChainContext(exptime=exptime, seed=0, sky_rate=sky_rate, persistence=persistence)
        rest = effects[first_readout:]
    else:
        ctx = ChainContext(exptime=exptime, seed=0, sky_rate=sky_rate, persistence=persistence)
        mean = np.array(sources, dtype=np.float64)
        var = np.zeros_like(mean)
        unit = "electron"
        fluence = None
        rest = effects
    for k, eff in enumerate(rest):
        if fluence is None and eff.cls.stage == "readout":
            fluence = mean.copy()
            if params is not None:
                kept = np.broadcast_to(var, mean.shape).copy()
                fluence.flags.writeable = kept.flags.writeable = False     # shared: nobody may change them
                cache.put(key, params, (fluence, kept, unit, ctx.used_sky_rate))
        if not eff.enabled:
            continue
        step = eff.instance()
        mean, var = step.moments(mean, var, ctx)
        unit = eff.cls.unit_out or unit
    if fluence is None:
        fluence = mean.copy()
    used_sky = hit[3] if hit is not None else ctx.used_sky_rate
    return Forward(mean=mean, variance=np.broadcast_to(var, mean.shape).copy(), unit=unit, fluence=fluence,
                   sky_rate=used_sky)

