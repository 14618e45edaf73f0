"""The detector model: a registry of effects, applied in physical order, each switchable.

Every effect is one class registered by name (:data:`REGISTRY`, in physical
order) with a parameter schema (:class:`Param`: type, unit, default, allowed
range, description) and three methods:

``sample(image, ctx)``
    what ``perscli render`` does to a frame, drawing from the effect's own
    random stream;
``expectation(mean, ctx)``
    the noise-free forward model of the mean signal;
``variance(mean, var, ctx)``
    how the effect changes the variance per pixel of a signal whose mean
    (before the effect) is ``mean``.

Expectation and variance are what a likelihood needs (``perscli diagnose``);
:func:`forward` chains them, :func:`run_chain` chains ``sample``.  ``ctx``
(:class:`ChainContext`) carries the exposure time, the seed, the sky rate and
the persistence charge supplied by the caller.

A detector model is a YAML file listing effects in the order they happen
physically, each with its parameters; every effect can be switched off with
``enabled: false``.  The default (:func:`default_model`) is GalSim's Roman
chain (galsim.roman) in its order, with saturation added::

    effects:
      - sky:          {level: auto}        # zodiacal + thermal, e-/pixel/s ('auto': galsim.roman)
      - poisson:      {}                   # photon noise (integer electrons)
      - reciprocity:  {alpha: 0.0065, base_flux: 1.0}
      - dark:         {current: 0.015}     # e-/pixel/s, Poisson
      - persistence:  {base: typical}      # the Fermi model of earlier exposures (--previous)
      - saturation:   {full_well: 1.0e5}   # e-: collected charge is clipped here
      - nonlinearity: {beta: -6.0e-7}      # x + beta x^2
      - ipc:          {kernel: roman}      # 3x3 interpixel capacitance
      - read_noise:   {sigma: 8.5}         # e-, Gaussian
      - gain:         {gain: 1.0}          # e-/DN: the output is in DN
      - quantize:     {}                   # round to integers

Each effect draws its random numbers from its own streams, keyed on the
seed, the effect's name and the block of detector pixels (:data:`NOISE_BLOCK`
pixels square, on the detector's own grid: :func:`block_streams`), so that

- switching one effect on or off leaves the noise of every other effect
  unchanged: a frame rendered with persistence and one without differ only
  by the persistence (what a paired measurement needs);
- a pixel's noise is the same whether the whole detector, a cutout or a
  scattered set of blocks is simulated (``ChainContext.origin`` and
  ``active``): a study can render only the regions that persistence reaches
  and get the very pixels of the whole frame there.

Stages: 'scene' effects (sky) make the IDEAL frame with the sources;
'charge' effects (up to saturation) make the FLUENCE, the charge collected in
the pixels that drives later persistence; 'readout' effects act on the
signal after the charge is collected.

A rendered frame carries its resolved model in a MODEL table
(:func:`model_table`); :func:`load_detector_model` reads it back from the
frame, so that ``perscli render --model FRAME.fits`` reproduces the model.

Persistence is not implemented here: the chain calls
:mod:`perscli.detector.persistence`, the one home of that model.

This module holds the registry of effects and the effect classes; the rest
of the detector model lives beside it: the parameter schema in
:mod:`perscli.settings`, the chain's context and noise blocks in
:mod:`perscli.detector.blocks`, models (YAML, MODEL tables) in
:mod:`perscli.detector.model` and the chain in :mod:`perscli.detector.chain`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import zlib
from typing import ClassVar

import galsim.roman
import numpy as np

from .. import PerscliError, _kernels
from ..instrument import (ROMAN_DARK_CURRENT, ROMAN_DETECTOR_SIZE, ROMAN_FULL_WELL, ROMAN_GAIN,
                          ROMAN_NONLINEARITY_BETA, ROMAN_READ_NOISE, ROMAN_RECIPROCITY_ALPHA)
from .blocks import NOISE_BLOCK, ChainContext, blank_inactive, block_streams
from ..settings import Param
from .persistence import PersistenceModel
from .settings import FERMI_PARAMETERS, PERSISTENCE_SCHEMA, PRESETS, preset_settings

# -- interpixel capacitance ----------------------------------------------------------------------


def roman_ipc_kernel() -> np.ndarray:
    return np.asarray(galsim.roman.ipc_kernel.array, dtype=np.float64)


def apply_ipc(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Interpixel capacitance with a 3x3 kernel, as GalSim's ``Image.applyIPC(edge_treatment='extend')``.

    ``kernel[j, i]`` is the fraction of the signal of the neighbour at offset
    (i - 1, j - 1) that appears in a pixel (GalSim's definition, so the
    asymmetric Roman kernel is applied as GalSim applies it); outside the
    image there is no charge (zero padding).  ``image`` may be a stack of
    planes (..., ny, nx): each is correlated on its own.

    Returns
    -------
    numpy.ndarray
        float64, the shape of ``image``: ``scipy.ndimage.correlate(image,
        kernel, mode='constant')`` bit for bit, from one compiled pass that
        releases the GIL (so diagnose's threads over exposures run at once;
        ndimage holds the GIL and took most of a likelihood evaluation).
    """
    x = np.ascontiguousarray(image, dtype=np.float64)
    k = np.ascontiguousarray(kernel, dtype=np.float64)
    if k.shape != (3, 3) or x.ndim < 2:
        raise ValueError(f"apply_ipc: a 3x3 kernel over planes (..., ny, nx), not {k.shape} over {x.shape}")
    out = np.empty_like(x)
    ny, nx = x.shape[-2:]
    _kernels.correlate3x3(x, out, k, (x.size // max(ny * nx, 1), ny, nx))
    return out


# -- the effects ---------------------------------------------------------------------------------

#: name -> effect class, in physical order
REGISTRY: dict = {}


def register(cls):
    """Add an effect class to :data:`REGISTRY` (registration order is the physical order)."""
    if cls.name in REGISTRY:
        raise ValueError(f"effect {cls.name!r} registered twice")
    names = [p.name for p in cls.schema]
    if len(set(names)) != len(names) or "enabled" in names:
        raise ValueError(f"effect {cls.name!r}: parameter names must be unique and not 'enabled'")
    REGISTRY[cls.name] = cls
    return cls


class DetectorEffect:
    """Base class of the effects: a schema, ``sample``, ``expectation`` and ``variance``.

    An instance holds resolved, checked parameters (``self.p``).
    """

    name: ClassVar[str] = ""
    stage: ClassVar[str] = "charge"          # 'scene', 'charge' or 'readout'
    unit_out: ClassVar[str | None] = None    # the units after this effect, if it changes them
    default_enabled: ClassVar[bool] = True   # on in the default (Roman) model
    description: ClassVar[str] = ""
    schema: ClassVar[tuple] = ()

    def __init__(self, params: dict):
        self.p = dict(params)

    @classmethod
    def param(cls, key: str) -> Param:
        return next(p for p in cls.schema if p.name == key)

    @classmethod
    def defaults(cls) -> dict:
        return {p.name: copy.deepcopy(p.default) for p in cls.schema}

    @classmethod
    def resolve(cls, params: dict) -> dict:
        """Every parameter with its value (derived ones worked out): the model as it acts."""
        out = cls.defaults()
        out.update(params)
        return out

    @classmethod
    def validate(cls, params: dict, where: str) -> dict:
        """Checked and converted parameters; unknown names, wrong types and values out of range are errors."""
        known = {p.name for p in cls.schema}
        unknown = [k for k in params if k not in known]
        if unknown:
            raise PerscliError(f"{where}: unknown parameter(s) {', '.join(map(str, unknown))} for effect "
                               f"{cls.name!r}; valid: {', '.join(p.name for p in cls.schema) or 'none'}")
        return {k: cls.param(k).check(cls.name, v, where) for k, v in params.items()}

    def sample(self, image: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """The image after this effect, drawn from the effect's own stream (may work in place)."""
        raise NotImplementedError

    def expectation(self, mean: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """The noise-free forward model: the mean signal after this effect."""
        return mean

    def variance(self, mean: np.ndarray, var: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """The variance after this effect, for a signal of mean ``mean`` and variance ``var`` before it."""
        return var

    def moments(self, mean: np.ndarray, var: np.ndarray, ctx: ChainContext) -> tuple:
        """(:meth:`expectation`, :meth:`variance`) at once: what :func:`perscli.detector.chain.forward` calls.

        An effect whose two share an expensive part (reciprocity's logarithm) computes it once here.
        """
        var = self.variance(mean, var, ctx)       # first: an expectation may work in place on ``mean``
        return self.expectation(mean, ctx), var

    def streams(self, ctx: ChainContext, shape):
        """This effect's random streams over an image of ``shape``: :func:`block_streams`."""
        if ctx.blocks is not None:
            return ctx.blocks.streams(ctx.seed, self.name)
        return block_streams(ctx.seed, self.name, ctx.origin, shape, ctx.active)

    def fresh(self, ctx: ChainContext, image: np.ndarray) -> np.ndarray:
        """``image`` with the pixels of inactive blocks set to NaN (they are not simulated)."""
        if ctx.blocks is not None:
            return ctx.blocks.blank(image)
        return blank_inactive(image, ctx.active, ctx.origin)


@register
class Sky(DetectorEffect):
    name = "sky"
    stage = "scene"
    description = "zodiacal and thermal background, added to the sources (noise-free: Poisson comes next)"
    schema = (Param("level", "float", "auto", "e-/pixel/s", "background rate; 'auto': galsim.roman.getSkyLevel "
                    "(zodiacal) + thermal at the pointing", lo=0.0, choices=("auto",)),)

    def rate(self, ctx):
        rate = ctx.sky() if self.p["level"] == "auto" else float(self.p["level"])
        ctx.used_sky_rate = rate
        return rate

    def sample(self, image, ctx):
        image += self.rate(ctx) * ctx.exptime
        return image

    def expectation(self, mean, ctx):
        return mean + self.rate(ctx) * ctx.exptime


@register
class Poisson(DetectorEffect):
    name = "poisson"
    description = "Poisson noise of the collected charge (integer electrons; negative expectations count as 0)"

    def sample(self, image, ctx):
        # the number of draws Poisson sampling takes depends on the means, so a block's pixels are only
        # reproducible when the whole block is simulated: render simulates whole blocks
        out = self.fresh(ctx, np.empty_like(image, dtype=np.float64))
        for gen, part, _ in self.streams(ctx, image.shape):
            out[part] = gen.poisson(np.clip(image[part], 0.0, None))
        return out

    def expectation(self, mean, ctx):
        return np.clip(mean, 0.0, None)

    def variance(self, mean, var, ctx):
        return var + np.clip(mean, 0.0, None)


@register
class Reciprocity(DetectorEffect):
    name = "reciprocity"
    description = ("reciprocity failure x (1 + alpha log10(x / (base_flux t))) on positive pixels "
                   "(GalSim uses its power-law form)")
    schema = (Param("alpha", "float", ROMAN_RECIPROCITY_ALPHA, "", "fractional change per decade of flux (galsim.roman: 0.0065)",
                    lo=0.0),
              Param("base_flux", "float", 1.0, "e-/s", "flux at which the response is unchanged", lo=0.0,
                    lo_open=True))

    def _log_ratio(self, img, t):
        """log10(x / (base_flux t)) where x > 0 (0 elsewhere), and the mask x > 0."""
        pos = img > 0
        ratio = np.log10(img, where=pos, out=np.zeros_like(img))
        ratio -= np.log10(self.p["base_flux"] * t)
        return ratio, pos

    def _apply(self, img, t, out, ratio=None):
        # the empirical law itself, x (1 + alpha log10(x / (base_flux t))); GalSim's
        # Image.addReciprocityFailure uses its power-law approximation x (x/x0)^(alpha/ln 10),
        # 3e-4 apart at 1e6 e-.  Zero and negative pixels are left alone.
        factor, pos = self._log_ratio(img, t) if ratio is None else (ratio[0].copy(), ratio[1])
        factor *= self.p["alpha"]
        factor += 1.0
        np.multiply(img, factor, out=out, where=pos)
        return out

    def sample(self, image, ctx):
        return self._apply(image, ctx.exptime, image)

    def expectation(self, mean, ctx):
        mean = np.asarray(mean, dtype=np.float64)
        return self._apply(mean, ctx.exptime, mean.copy())

    def _variance(self, var, ratio):
        slope, pos = ratio
        slope += 1.0 / math.log(10.0)
        slope *= self.p["alpha"]
        slope += 1.0
        return np.where(pos, var * slope * slope, var)

    def variance(self, mean, var, ctx):
        return self._variance(var, self._log_ratio(np.asarray(mean, dtype=np.float64), ctx.exptime))

    def moments(self, mean, var, ctx):
        # the logarithm once for both (it was a fifth of diagnose's likelihood evaluations)
        mean = np.asarray(mean, dtype=np.float64)
        ratio = self._log_ratio(mean, ctx.exptime)
        out = self._apply(mean, ctx.exptime, mean.copy(), ratio)
        return out, self._variance(var, ratio)


@register
class Dark(DetectorEffect):
    name = "dark"
    description = "dark current, with its Poisson noise"
    schema = (Param("current", "float", ROMAN_DARK_CURRENT, "e-/pixel/s", "dark current (galsim.roman: 0.015)", lo=0.0),)

    def sample(self, image, ctx):
        mean = self.p["current"] * ctx.exptime
        for gen, part, cut in self.streams(ctx, image.shape):
            image[part] += gen.poisson(mean, size=(NOISE_BLOCK, NOISE_BLOCK))[cut]
        return self.fresh(ctx, image)

    def expectation(self, mean, ctx):
        return mean + self.p["current"] * ctx.exptime

    def variance(self, mean, var, ctx):
        return var + self.p["current"] * ctx.exptime


@register
class Persistence(DetectorEffect):
    name = "persistence"
    description = ("charge released by earlier exposures (--previous), from their DRAWN, STARFLU or FLUENCE "
                   "(source, fluence_cap) (perscli.detector.persistence; added as its expectation)")
    schema = PERSISTENCE_SCHEMA

    @classmethod
    def resolve(cls, params):
        out = super().resolve(params)
        for key, value in PRESETS[out["base"]].items():
            if out.get(key) is None:
                out[key] = float(value)
        for key, value in preset_settings(out["base"]).items():
            if out.get(key) is None:
                out[key] = value
        out["coefficients"] = [float(c) for c in out["coefficients"]]
        return out

    @classmethod
    def validate(cls, params, where):
        if "model" in params and "kind" not in params:
            # the spelling perscli.detector.persistence files accept
            params = {("kind" if k == "model" else k): v for k, v in params.items()}
        out = super().validate(params, where)
        cls.model(out, where)          # the law's own checks (e.g. its combination of parameters)
        return out

    @classmethod
    def model(cls, params: dict, name: str = "persistence"):
        """The :class:`~perscli.detector.persistence.PersistenceModel` of these parameters."""
        p = cls.resolve(params)
        explicit = [k for k in FERMI_PARAMETERS if params.get(k) is not None] or p["kind"] != "fermi"
        fields = {f.name for f in dataclasses.fields(PersistenceModel)}
        kwargs = {k: v for k, v in p.items() if k in fields and k not in ("name",)}
        kwargs["coefficients"] = tuple(p["coefficients"])
        return PersistenceModel(name=name if explicit else p["base"], **kwargs)

    def sample(self, image, ctx):
        charge = ctx.persistence_charge()
        if charge is not None:
            ctx.used_persistence = charge
            image += charge
        return image

    def expectation(self, mean, ctx):
        charge = ctx.persistence_charge()
        return mean if charge is None else mean + charge

    @staticmethod
    def floor(model) -> float:
        """Electrons: earlier pixels at or below this leave no persistence in ``model`` (0: none left out).

        ``model`` is a :class:`perscli.detector.model.DetectorModel` (model.py imports this module).
        """
        eff = model.get("persistence")
        return float((eff.resolved() if eff is not None else Persistence.resolve({}))["floor"])

    @staticmethod
    def fluence_input(model) -> tuple:
        """What of an earlier exposure feeds the law in ``model``: (source, threshold, cap).

        Parameters
        ----------
        model : perscli.detector.model.DetectorModel
            The detector model (model.py imports this module, hence no annotation).

        Returns
        -------
        source : {'drawn', 'stars', 'all', 'threshold'}
            Which image of the earlier frame: DRAWN ('drawn'), STARFLU ('stars') or FLUENCE ('all',
            'threshold'): :data:`perscli.render.settings.SOURCE_HDU`.
        threshold : float or None
            Electrons: only pixels whose FLUENCE exceeds it persist ('threshold').
        cap : float or None
            The fluence is clipped at this many electrons (None: no cap).
            'well' is the saturation effect's full well when saturation is on,
            else no cap: a model without a well has nothing to clip at.
        """
        eff = model.get("persistence")
        p = eff.resolved() if eff is not None else Persistence.resolve({})
        source, threshold = p["source"], None
        if not isinstance(source, str):
            source, threshold = "threshold", float(p["source"])
        cap = p["fluence_cap"]
        if cap == "well":
            cap = model.value("saturation", "full_well")
        elif cap == "none":
            cap = None
        return source, threshold, None if cap is None else float(cap)


def _framed(image: np.ndarray, ctx: "ChainContext") -> np.ndarray:
    """The image (or each block of a stack) with a one-pixel frame of its neighbours (zeros past the area)."""
    if ctx.blocks is not None:
        return ctx.blocks.edges(image)
    return np.pad(np.asarray(image, dtype=np.float64), 1)


def brighter_fatter_flow(framed: np.ndarray, coefficient: float) -> np.ndarray:
    """The charge each pixel gains from its four neighbours under the brighter-fatter effect.

    Charge already collected repels what follows, so the boundary between
    two pixels moves towards the fainter one by an amount proportional to
    their difference, and the charge crossing it is proportional to that
    shift times their mean: ``coefficient / 2 * (q_j^2 - q_i^2)`` flows
    from pixel j into pixel i (first order in the charge; conserves charge
    inside the area).

    Parameters
    ----------
    framed : ndarray, shape (..., ny + 2, nx + 2)
        Collected electrons with a one-pixel frame of neighbours.
    coefficient : float
        Per electron.

    Returns
    -------
    ndarray, shape (..., ny, nx)
    """
    sq = np.square(np.nan_to_num(framed, nan=0.0))
    centre = sq[..., 1:-1, 1:-1]
    flow = (sq[..., :-2, 1:-1] + sq[..., 2:, 1:-1] + sq[..., 1:-1, :-2] + sq[..., 1:-1, 2:]) - 4.0 * centre
    return 0.5 * coefficient * flow


@register
class BrighterFatter(DetectorEffect):
    name = "brighter_fatter"
    default_enabled = False
    description = ("the brighter-fatter effect: collected charge pushes later charge to the neighbours, "
                   "coefficient/2 (q_j^2 - q_i^2) between nearest neighbours; off in the Roman model")
    schema = (Param("coefficient", "float", 0.0, "1/e-", "boundary shift per electron of difference (H2RG/H4RG: "
                    "a few 1e-8 gives ~1% of a 1e5 e- peak)", lo=0.0),)

    def _apply(self, image, ctx):
        flow = brighter_fatter_flow(_framed(image, ctx), self.p["coefficient"])
        out = image + flow
        return ctx.blocks.blank(out) if ctx.blocks is not None else out

    def sample(self, image, ctx):
        return self._apply(image, ctx)

    def expectation(self, mean, ctx):
        return self._apply(np.asarray(mean, dtype=np.float64), ctx)

    # the variance: the flow moves a few per cent of the charge, its noise with it; first order unchanged


#: the full well of Roman's H4RG-10 pixels, electrons (see README: detector model)
FULL_WELL = ROMAN_FULL_WELL


@register
class Saturation(DetectorEffect):
    name = "saturation"
    description = ("the pixel's full well: collected charge above it is lost (clipped), so FLUENCE, "
                   "what drives later persistence, never exceeds it (persistence.fluence_cap: well)")
    schema = (Param("full_well", "float", FULL_WELL, "e-", "charge a pixel holds (H4RG-10: ~1e5; the paper's "
                    "half_well is half of it)", lo=0.0, lo_open=True),)

    def sample(self, image, ctx):
        np.minimum(image, self.p["full_well"], out=image)
        return image

    def expectation(self, mean, ctx):
        # the deterministic limit; near the well the mean of a clipped noisy signal is slightly lower
        return np.minimum(mean, self.p["full_well"])

    def variance(self, mean, var, ctx):
        # a saturated pixel carries no noise (and no information)
        return np.where(np.asarray(mean) >= self.p["full_well"], 0.0, var)


@register
class Nonlinearity(DetectorEffect):
    name = "nonlinearity"
    stage = "readout"
    description = "classical nonlinearity x + beta x^2 of the collected charge"
    schema = (Param("beta", "float", ROMAN_NONLINEARITY_BETA, "1/e-", "quadratic coefficient (galsim.roman: -6e-7)"),)

    def sample(self, image, ctx):
        # (beta x) x, then added: the bits of ``image += beta * image * image`` with one temporary, not two
        term = np.multiply(self.p["beta"], image)
        term *= image
        image += term
        return image

    def expectation(self, mean, ctx):
        return mean + self.p["beta"] * mean * mean

    def variance(self, mean, var, ctx):
        slope = 1.0 + 2.0 * self.p["beta"] * np.asarray(mean, dtype=np.float64)
        return var * slope * slope


@register
class IPC(DetectorEffect):
    name = "ipc"
    stage = "readout"
    description = "interpixel capacitance: each pixel receives fractions of its neighbours' signal"
    schema = (Param("kernel", "kernel", "roman", "", "3x3 kernel: 'roman' (galsim.roman.ipc_kernel) or a list; "
                    "kernel[j][i] is what a pixel receives from its neighbour at (i-1, j-1)"),
              Param("alpha", "float", None, "", "mean coupling to the 4 nearest neighbours (what diagnose reports): "
                    "the kernel's couplings scaled to it, charge conserved", lo=0.0, hi=0.2,
                    derived="the kernel's own"))

    def kernel(self) -> np.ndarray:
        k = self.p["kernel"]
        k = roman_ipc_kernel() if k == "roman" else np.asarray(k, dtype=float)
        alpha = self.p.get("alpha")
        if alpha is not None:
            off = k.copy()
            off[1, 1] = 0.0
            nn = (off[0, 1] + off[1, 0] + off[1, 2] + off[2, 1]) / 4.0
            if nn <= 0:
                raise PerscliError("ipc.alpha: the kernel has no nearest-neighbour coupling to scale; give "
                                   "ipc.kernel as a list instead")
            off *= alpha / nn
            k = off
            k[1, 1] = 1.0 - off.sum()
        return k

    def sample(self, image, ctx):
        if ctx.blocks is not None:
            # each block with its neighbours' edge pixels, correlated as the whole area would be
            out = apply_ipc(ctx.blocks.edges(image), self.kernel())
            return ctx.blocks.blank(np.ascontiguousarray(out[:, 1:-1, 1:-1]))
        return apply_ipc(image, self.kernel())

    def expectation(self, mean, ctx):
        return apply_ipc(mean, self.kernel())

    def variance(self, mean, var, ctx):
        # independent pixels: each neighbour's variance enters with its weight squared
        return apply_ipc(var, self.kernel() ** 2)


@register
class ReadNoise(DetectorEffect):
    name = "read_noise"
    stage = "readout"
    description = "Gaussian read noise"
    schema = (Param("sigma", "float", ROMAN_READ_NOISE, "e-", "standard deviation (galsim.roman: 8.5)", lo=0.0),)

    def sample(self, image, ctx):
        if ctx.shared is None:
            for gen, part, cut in self.streams(ctx, image.shape):
                image[part] += gen.normal(0.0, self.p["sigma"], size=(NOISE_BLOCK, NOISE_BLOCK))[cut]
            return self.fresh(ctx, image)
        # several branches of one frame: the noise drawn once (each pixel the same sum as above, bit for bit)
        key = (self.name, self.p["sigma"], image.shape)
        noise = ctx.shared.get(key)
        if noise is None:
            noise = ctx.shared[key] = np.zeros(image.shape)
            for gen, part, cut in self.streams(ctx, image.shape):
                noise[part] = gen.normal(0.0, self.p["sigma"], size=(NOISE_BLOCK, NOISE_BLOCK))[cut]
        image += noise
        return self.fresh(ctx, image)

    def variance(self, mean, var, ctx):
        return var + self.p["sigma"] ** 2


@register
class CorrelatedReadNoise(DetectorEffect):
    name = "correlated_read_noise"
    stage = "readout"
    default_enabled = False
    description = ("read noise shared by whole rows and by whole columns (the white row and column components "
                   "of correlated noise, bias drifts); off in the Roman model")
    schema = (Param("row", "float", 0.0, "e-", "rms of the offset common to a detector row", lo=0.0),
              Param("column", "float", 0.0, "e-", "rms of the offset common to a detector column", lo=0.0))

    #: offsets are drawn for this many rows and columns from the detector's first, whatever the area:
    #: a pixel gets its row's and column's offsets whether a frame, a cutout or blocks are simulated
    LINES = ROMAN_DETECTOR_SIZE

    def _offsets(self, ctx, which: int, sigma: float, needed: int) -> np.ndarray:
        bits = np.random.Philox(key=[int(ctx.seed) & 0xFFFFFFFFFFFFFFFF, zlib.crc32(self.name.encode())])
        bits.state = {**bits.state, "state": {**bits.state["state"],
                                              "counter": np.array([0, 0, which, 0], dtype=np.uint64)}}
        # draws of one stream: the first n of a longer draw are the draw of n
        return np.random.Generator(bits).normal(0.0, sigma, size=max(self.LINES, needed))

    def sample(self, image, ctx):
        if self.p["row"] <= 0 and self.p["column"] <= 0:
            return image
        if ctx.blocks is not None:
            st = ctx.blocks
            rows = st.by[:, None] * NOISE_BLOCK + np.arange(NOISE_BLOCK)[None, :]
            cols = st.bx[:, None] * NOISE_BLOCK + np.arange(NOISE_BLOCK)[None, :]
            r = self._offsets(ctx, 1, self.p["row"], int(rows.max()) + 1)[rows]
            c = self._offsets(ctx, 2, self.p["column"], int(cols.max()) + 1)[cols]
            image += r[:, :, None] + c[:, None, :]
            return image
        x0, y0 = int(ctx.origin[0]) - 1, int(ctx.origin[1]) - 1
        ny, nx = image.shape
        r = self._offsets(ctx, 1, self.p["row"], y0 + ny)[y0:y0 + ny]
        c = self._offsets(ctx, 2, self.p["column"], x0 + nx)[x0:x0 + nx]
        image += r[:, None] + c[None, :]
        return image

    def variance(self, mean, var, ctx):
        # the marginal variance of one pixel; the covariance along rows and columns is what
        # diagnose's row and column statistics test
        return var + self.p["row"] ** 2 + self.p["column"] ** 2


@register
class Offset(DetectorEffect):
    name = "offset"
    stage = "readout"
    default_enabled = False
    description = ("a noiseless level added to every exposure (a bias or pedestal), independent of the "
                   "exposure time; off in the Roman model")
    schema = (Param("level", "float", 0.0, "e-", "electrons per pixel added to every read"),)

    def sample(self, image, ctx):
        image += self.p["level"]
        return image

    def expectation(self, mean, ctx):
        return mean + self.p["level"]


@register
class Gain(DetectorEffect):
    name = "gain"
    stage = "readout"
    unit_out = "DN"
    description = "conversion of electrons to DN"
    schema = (Param("gain", "float", ROMAN_GAIN, "e-/DN", "electrons per DN (galsim.roman: 1.0)", lo=0.0, lo_open=True),)

    def sample(self, image, ctx):
        image /= self.p["gain"]
        return image

    def expectation(self, mean, ctx):
        return mean / self.p["gain"]

    def variance(self, mean, var, ctx):
        return var / self.p["gain"] ** 2


@register
class Quantize(DetectorEffect):
    name = "quantize"
    stage = "readout"
    description = "rounding to integer values (the A/D converter); adds 1/12 unit^2 of variance"

    def sample(self, image, ctx):
        return np.round(image, out=image)

    def variance(self, mean, var, ctx):
        # uniform rounding error: exact when the noise before it is well above one unit
        return var + 1.0 / 12.0


#: effect names in physical order
ORDER = tuple(REGISTRY)

#: the effects of the default (Roman) model, in physical order
ROMAN_ORDER = tuple(name for name, cls in REGISTRY.items() if cls.default_enabled)

#: default parameters of each effect (None: derived, e.g. from the persistence base)
DEFAULTS = {name: cls.defaults() for name, cls in REGISTRY.items()}

DESCRIPTIONS = {name: cls.description for name, cls in REGISTRY.items()}
