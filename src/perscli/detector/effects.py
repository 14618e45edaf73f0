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
"""

from __future__ import annotations

import copy
import json
import math
import os
import zlib
from dataclasses import dataclass, field
from typing import Callable, ClassVar

import numpy as np

from .. import PerscliError
from ..instrument import (ROMAN_DARK_CURRENT, ROMAN_FULL_WELL, ROMAN_GAIN, ROMAN_NONLINEARITY_BETA, ROMAN_READ_NOISE,
                          ROMAN_RECIPROCITY_ALPHA)

# -- parameter schemas ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Param:
    """One parameter of an effect: what it is and which values it may take.

    Attributes
    ----------
    name : str
    kind : {'float', 'int', 'choice', 'kernel', 'floats'}
        'float': a finite number; 'int': a whole number; 'choice': one of
        ``choices``; 'kernel': 'roman' or a 3x3 list of numbers; 'floats': a
        non-empty list of finite numbers.
    default
        The value when not given; None for a value taken from another
        parameter (``derived``).
    unit : str
    description : str
    lo, hi : float, optional
        Bounds (None: unbounded).
    lo_open, hi_open : bool
        The bound itself is excluded.
    choices : tuple of str
        Allowed words ('choice'), or words accepted besides numbers (e.g.
        'auto' for the sky level).
    derived : str
        For ``default=None``: where the value comes from (e.g. 'from base').
    """

    name: str
    kind: str
    default: object
    unit: str = ""
    description: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple = ()
    derived: str = ""

    def allowed(self, unit: bool = False) -> str:
        """The allowed values as text, e.g. '(0, inf)' or 'typical | pessimistic' (with the unit if asked)."""
        if self.kind == "choice":
            return " | ".join(self.choices)
        if self.kind == "kernel":
            return "roman | 3x3 list"
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        text = f"{left}{lo}, {hi}{right}"
        if self.kind == "int":
            text = f"integer {text}"
        if self.kind == "floats":
            text = f"list, each {text}"
        if unit and self.unit:
            text += f" {self.unit}"
        if self.choices:
            text += " | " + " | ".join(self.choices)
        return text

    def _requirement(self) -> str:
        if self.kind == "choice":
            return f"must be one of {', '.join(self.choices)}"
        if self.kind == "kernel":
            return "must be 'roman' or a 3x3 list of finite numbers"
        if self.lo == 0 and self.hi is None:
            return "must be positive" if self.lo_open else "must not be negative"
        if self.lo is None and self.hi is None:
            return "must be a finite number"
        return f"must be in {self.allowed()}"

    def check(self, effect: str, value, where: str):
        """``value`` converted to this parameter's type, or a PerscliError naming effect.param, value and range."""
        def fail(requirement):
            allowed = "" if self.kind in ("choice", "kernel") else f" (allowed: {self.allowed(unit=True)})"
            return PerscliError(f"{where}: {effect}.{self.name} {requirement}{allowed}, not {value!r}")

        if value is None and self.default is None:
            return None
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise fail(self._requirement())
            return value
        if self.kind == "kernel":
            if value == "roman":
                return value
            arr = np.asarray(value, dtype=float) if isinstance(value, (list, tuple)) and _numbers(value) else None
            if arr is None or arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
                raise fail(self._requirement())
            return [[float(v) for v in row] for row in value]
        if isinstance(value, str) and value in self.choices:
            return value
        if self.kind == "floats":
            if not isinstance(value, (list, tuple)) or not value:
                raise fail("must be a non-empty list of finite numbers")
            return [self._number(effect, v, where, fail) for v in value]
        return self._number(effect, value, where, fail)

    def _number(self, effect, value, where, fail):
        number = value
        if isinstance(number, str):
            # YAML 1.1 reads '-6e-7' (no decimal point) as text: accept any number Python can parse
            try:
                number = float(number)
            except ValueError:
                pass
        if isinstance(number, bool) or not isinstance(number, (int, float, np.integer, np.floating)) \
                or not math.isfinite(number):
            raise fail("must be a whole number" if self.kind == "int" else "must be a finite number")
        if self.kind == "int":
            if number != int(number):
                raise fail("must be a whole number")
            number = int(number)
        else:
            number = float(number)
        if self.lo is not None and (number < self.lo or (self.lo_open and number == self.lo)):
            raise fail(self._requirement())
        if self.hi is not None and (number > self.hi or (self.hi_open and number == self.hi)):
            raise fail(self._requirement())
        return number


def _numbers(rows) -> bool:
    try:
        return all(not isinstance(v, (bool, str)) and isinstance(v, (int, float))
                   for row in rows for v in row)
    except TypeError:
        return False


# -- what the chain carries --------------------------------------------------------------------


@dataclass
class ChainContext:
    """What effects need besides the image: exposure time, seed, sky and persistence.

    Parameters
    ----------
    exptime : float
        Seconds.
    seed : int
        Seed of every random stream.
    sky_rate : float or callable
        The automatic sky level in e-/pixel/s, or a function returning it
        (called at most once, and only if the sky effect asks for 'auto').
    persistence : ndarray or callable, optional
        The persistence charge in electrons (the image's shape), or a
        function returning it (called at most once, only when the
        persistence effect is on); None: no earlier exposures.
    """

    exptime: float
    seed: int = 0
    sky_rate: float | Callable[[], float] = 0.0
    persistence: np.ndarray | Callable[[], np.ndarray] | None = None
    #: detector pixel (x, y), 1-indexed, of the image's first element: places it on the noise blocks
    origin: tuple = (1, 1)
    #: which noise blocks to simulate (bool, :func:`block_grid` shape); None: all.  Pixels of the other
    #: blocks come out NaN
    active: np.ndarray | None = None
    #: the image is a stack of noise blocks (:class:`BlockStack`) rather than a piece of the detector
    blocks: "BlockStack | None" = None
    #: what the chain used: the sky rate (e-/pixel/s) and the persistence charge (electrons)
    used_sky_rate: float = field(default=0.0, init=False)
    used_persistence: np.ndarray | None = field(default=None, init=False)
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def sky(self) -> float:
        if "sky" not in self._cache:
            self._cache["sky"] = float(self.sky_rate() if callable(self.sky_rate) else self.sky_rate)
        return self._cache["sky"]

    def persistence_charge(self) -> np.ndarray | None:
        if self.persistence is None:
            return None
        if "persistence" not in self._cache:
            value = self.persistence() if callable(self.persistence) else self.persistence
            self._cache["persistence"] = np.asarray(value, dtype=np.float64)
        return self._cache["persistence"]


#: side, in detector pixels, of the square blocks that each have their own random stream per effect.
#: Blocks lie on the detector's grid (block (0, 0) starts at pixel (1, 1)), so a frame, a cutout or a
#: set of blocks all give a pixel the same noise.  32: a full 4088^2 SCA is 16,384 blocks, whose
#: streams cost ~0.05 s to key; smaller blocks would make regions tighter but keying slower
NOISE_BLOCK = 32


def block_grid(origin, shape) -> tuple:
    """The noise blocks an image covers: (first block row, first block column, rows, columns).

    Parameters
    ----------
    origin : (int, int)
        Detector pixel (x, y), 1-indexed, of ``image[0, 0]``.
    shape : (int, int)
        The image's (ny, nx).
    """
    x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
    bx0, by0 = x0 // NOISE_BLOCK, y0 // NOISE_BLOCK
    bx1 = (x0 + shape[1] - 1) // NOISE_BLOCK
    by1 = (y0 + shape[0] - 1) // NOISE_BLOCK
    return by0, bx0, by1 - by0 + 1, bx1 - bx0 + 1


def block_streams(seed: int, name: str, origin, shape, active=None):
    """Random streams of one effect over an image, one per noise block it covers.

    Each block's stream is a counter-based generator (Philox) keyed on the
    seed and the effect's name, its counter starting at the block's place on
    the detector: it depends on nothing else, so a pixel gets the same
    numbers whatever else is simulated.

    Parameters
    ----------
    seed : int
    name : str
        The effect's name.
    origin, shape
        As for :func:`block_grid`.
    active : ndarray of bool, optional
        Blocks to visit (the :func:`block_grid` shape); None: every block.

    Yields
    ------
    (numpy.random.Generator, tuple of slice, tuple of slice)
        The block's generator, the part of the image it covers, and that
        part's place within the whole block (NOISE_BLOCK x NOISE_BLOCK):
        draws that do not depend on the image's values are made for the whole
        block and cut, so that a block only partly on the image still gives
        its pixels the numbers the whole block would.
    """
    by0, bx0, nby, nbx = block_grid(origin, shape)
    x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
    bits = np.random.Philox(key=[int(seed) & 0xFFFFFFFFFFFFFFFF, zlib.crc32(name.encode())])
    gen = np.random.Generator(bits)
    state = bits.state
    for j in range(nby):
        by = by0 + j
        ya, yb = max(by * NOISE_BLOCK, y0), min((by + 1) * NOISE_BLOCK, y0 + shape[0])
        for i in range(nbx):
            if active is not None and not active[j, i]:
                continue
            bx = bx0 + i
            xa, xb = max(bx * NOISE_BLOCK, x0), min((bx + 1) * NOISE_BLOCK, x0 + shape[1])
            # the counter's high words name the block; the low word counts draws within it
            state["state"]["counter"][:] = (0, 0, by, bx)
            state["buffer_pos"] = 4
            state["has_uint32"] = 0
            bits.state = state
            yield (gen, (slice(ya - y0, yb - y0), slice(xa - x0, xb - x0)),
                   (slice(ya - by * NOISE_BLOCK, yb - by * NOISE_BLOCK),
                    slice(xa - bx * NOISE_BLOCK, xb - bx * NOISE_BLOCK)))


@dataclass
class BlockStack:
    """Noise blocks of a detector area gathered into one array, shape (n, NOISE_BLOCK, NOISE_BLOCK).

    When persistence reaches a few scattered blocks of a frame, the chain
    need not touch the rest: the blocks are stacked and every effect works on
    the stack (each block's streams as in the frame, interpixel capacitance
    through each block's neighbours), at a cost that follows the blocks
    simulated.  The pixels of a block beyond the area (its last row and
    column of blocks may be partial) are NaN.

    Attributes
    ----------
    by, bx : ndarray of int
        Each block's place on the detector (block row and column).
    h, w : ndarray of int
        Its rows and columns inside the area.
    neighbours : ndarray of int, shape (n, 3, 3)
        For each block, its 3 x 3 neighbourhood as indices into the stack,
        ``n`` for a block of the area that is not simulated (NaN) and
        ``n + 1`` for one outside the area (zeros, as a frame's edge).
    origin, shape
        The area (detector pixel of its first element, and its shape).
    """

    by: np.ndarray
    bx: np.ndarray
    h: np.ndarray
    w: np.ndarray
    neighbours: np.ndarray
    origin: tuple
    shape: tuple

    def __len__(self) -> int:
        return len(self.by)

    @classmethod
    def of(cls, active, origin, shape) -> "BlockStack":
        """The stack of the blocks ``active`` marks in an area (:func:`block_grid` of ``origin``, ``shape``)."""
        if (int(origin[0]) - 1) % NOISE_BLOCK or (int(origin[1]) - 1) % NOISE_BLOCK:
            raise ValueError(f"a block stack's area starts on a block: {origin} does not")
        by0, bx0, nby, nbx = block_grid(origin, shape)
        jj, ii = np.nonzero(np.asarray(active, dtype=bool))
        n = len(jj)
        x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
        by, bx = by0 + jj, bx0 + ii
        h = np.minimum((by + 1) * NOISE_BLOCK, y0 + shape[0]) - by * NOISE_BLOCK
        w = np.minimum((bx + 1) * NOISE_BLOCK, x0 + shape[1]) - bx * NOISE_BLOCK
        index = np.full((nby + 2, nbx + 2), n + 1, dtype=np.int64)      # outside the area
        index[1:-1, 1:-1] = n                                               # in the area, not simulated
        index[jj + 1, ii + 1] = np.arange(n)
        neighbours = np.stack([index[jj + dj, ii + di] for dj in range(3) for di in range(3)],
                              axis=1).reshape(n, 3, 3)
        return cls(by, bx, h, w, neighbours, tuple(origin), tuple(shape))

    def _place(self, k):
        """Area-relative slices of block k."""
        x0, y0 = int(self.origin[0]) - 1, int(self.origin[1]) - 1
        ya, xa = self.by[k] * NOISE_BLOCK - y0, self.bx[k] * NOISE_BLOCK - x0
        return slice(ya, ya + self.h[k]), slice(xa, xa + self.w[k])

    def gather(self, image: np.ndarray, fill=np.nan, dtype=np.float64) -> np.ndarray:
        """The blocks of ``image`` (the area) as a stack; ``fill`` beyond the area."""
        out = np.full((len(self), NOISE_BLOCK, NOISE_BLOCK), fill, dtype=dtype)
        for k in range(len(self)):
            rows, cols = self._place(k)
            out[k, :self.h[k], :self.w[k]] = image[rows, cols]
        return out

    def scatter(self, stack: np.ndarray, fill=np.nan, dtype=np.float64) -> np.ndarray:
        """The stack back in the area, ``fill`` where no block was simulated."""
        out = np.full(self.shape, fill, dtype=dtype)
        for k in range(len(self)):
            rows, cols = self._place(k)
            out[rows, cols] = stack[k, :self.h[k], :self.w[k]]
        return out

    def streams(self, seed: int, name: str):
        """:func:`block_streams` for the stack: (generator, the block's part of the stack, its cut of a block)."""
        bits = np.random.Philox(key=[int(seed) & 0xFFFFFFFFFFFFFFFF, zlib.crc32(name.encode())])
        gen = np.random.Generator(bits)
        state = bits.state
        for k in range(len(self)):
            state["state"]["counter"][:] = (0, 0, int(self.by[k]), int(self.bx[k]))
            state["buffer_pos"] = 4
            state["has_uint32"] = 0
            bits.state = state
            h, w = int(self.h[k]), int(self.w[k])
            yield gen, (k, slice(0, h), slice(0, w)), (slice(0, h), slice(0, w))

    def edges(self, stack: np.ndarray) -> np.ndarray:
        """Each block with a one-pixel frame of its neighbours' pixels: shape (n, B + 2, B + 2).

        Neighbours not simulated give NaN, neighbours beyond the area zeros
        (a frame's edge), as the whole area would give them.
        """
        b = NOISE_BLOCK
        n = len(self)
        clean = stack.copy()
        for k in np.flatnonzero((self.h < b) | (self.w < b)):
            # beyond the area: zeros, as past the edge of a frame
            clean[k, self.h[k]:, :] = 0.0
            clean[k, :, self.w[k]:] = 0.0
        ext = np.concatenate([clean, np.full((1, b, b), np.nan), np.zeros((1, b, b))])
        out = np.empty((n, b + 2, b + 2))
        nb = self.neighbours
        out[:, 1:-1, 1:-1] = clean
        out[:, 0, 1:-1] = ext[nb[:, 0, 1], -1, :]
        out[:, -1, 1:-1] = ext[nb[:, 2, 1], 0, :]
        out[:, 1:-1, 0] = ext[nb[:, 1, 0], :, -1]
        out[:, 1:-1, -1] = ext[nb[:, 1, 2], :, 0]
        out[:, 0, 0] = ext[nb[:, 0, 0], -1, -1]
        out[:, 0, -1] = ext[nb[:, 0, 2], -1, 0]
        out[:, -1, 0] = ext[nb[:, 2, 0], 0, -1]
        out[:, -1, -1] = ext[nb[:, 2, 2], 0, 0]
        return out

    def blank(self, stack: np.ndarray) -> np.ndarray:
        """``stack`` with the pixels beyond the area NaN."""
        for k in np.flatnonzero((self.h < NOISE_BLOCK) | (self.w < NOISE_BLOCK)):
            stack[k, self.h[k]:, :] = np.nan
            stack[k, :, self.w[k]:] = np.nan
        return stack


def active_pixels(active, origin, shape) -> np.ndarray:
    """The pixels of the blocks ``active`` marks, as a bool image of ``shape`` (all True for None)."""
    if active is None:
        return np.ones(shape, dtype=bool)
    by0, bx0, nby, nbx = block_grid(origin, shape)
    x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
    big = np.repeat(np.repeat(np.asarray(active, dtype=bool), NOISE_BLOCK, axis=0), NOISE_BLOCK, axis=1)
    oy, ox = y0 - by0 * NOISE_BLOCK, x0 - bx0 * NOISE_BLOCK
    return big[oy:oy + shape[0], ox:ox + shape[1]]


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

    def streams(self, ctx: ChainContext, shape):
        """This effect's random streams over an image of ``shape``: :func:`block_streams`."""
        if ctx.blocks is not None:
            return ctx.blocks.streams(ctx.seed, self.name)
        return block_streams(ctx.seed, self.name, ctx.origin, shape, ctx.active)

    def fresh(self, ctx: ChainContext, image: np.ndarray) -> np.ndarray:
        """``image`` with the pixels of inactive blocks set to NaN (they are not simulated)."""
        if ctx.blocks is not None:
            return ctx.blocks.blank(image)
        if ctx.active is not None:
            image[~active_pixels(ctx.active, ctx.origin, image.shape)] = np.nan
        return image


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

    def _apply(self, img, t, out):
        # the empirical law itself, x (1 + alpha log10(x / (base_flux t))); GalSim's
        # Image.addReciprocityFailure uses its power-law approximation x (x/x0)^(alpha/ln 10),
        # 3e-4 apart at 1e6 e-.  Zero and negative pixels are left alone.
        pos = img > 0
        factor = np.log10(img, where=pos, out=np.zeros_like(img))
        factor -= np.log10(self.p["base_flux"] * t)
        factor *= self.p["alpha"]
        factor += 1.0
        np.multiply(img, factor, out=out, where=pos)
        return out

    def sample(self, image, ctx):
        return self._apply(image, ctx.exptime, image)

    def expectation(self, mean, ctx):
        mean = np.asarray(mean, dtype=np.float64)
        return self._apply(mean, ctx.exptime, mean.copy())

    def variance(self, mean, var, ctx):
        mean = np.asarray(mean, dtype=np.float64)
        pos = mean > 0
        slope = np.log10(mean, where=pos, out=np.zeros_like(mean))
        slope -= np.log10(self.p["base_flux"] * ctx.exptime)
        slope += 1.0 / math.log(10.0)
        slope *= self.p["alpha"]
        slope += 1.0
        return np.where(pos, var * slope * slope, var)


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


def _persistence_schema():
    from .persistence import COMBINES, FERMI_PARAMETERS, GALSIM_LINEAR_COEFFICIENTS, PRESETS, TIME_MODELS

    bounds = {"A": dict(lo=0.0), "x0": dict(lo=0.0, lo_open=True), "dx": dict(lo=0.0, lo_open=True),
              "half_well": dict(lo=0.0)}
    law = tuple(Param(key, "float", None, unit, f"{text} (default: from base)", derived="base", **bounds.get(key, {}))
                for key, (text, unit) in FERMI_PARAMETERS.items())
    return (
        Param("base", "choice", "typical", "", "the paper's parameter set (Table 1) the law starts from",
              choices=tuple(PRESETS)),
        Param("kind", "choice", "fermi", "", "fermi: the paper's rate F(x) (t/1000 s)^-gamma; linear: GalSim's "
              "coefficients x fluence", choices=("fermi", "linear")),
        *law,
        Param("coefficients", "floats", list(GALSIM_LINEAR_COEFFICIENTS), "",
              "kind linear: fraction of each earlier exposure's fluence, most recent first (galsim.roman)"),
        Param("time_model", "choice", "exact", "", "exact: the rate integrated over the exposure; middle: the "
              "rate at its middle x its length (the WFC3 pipeline); galsim: GalSim's mid-exposure rate x 139.8 s",
              choices=TIME_MODELS),
        Param("combine", "choice", "sum", "", "sum over earlier exposures (the paper, GalSim) or per-pixel max "
              "(WFC3 pipeline)", choices=COMBINES),
        Param("max_previous", "int", 10, "", "only the N most recent earlier exposures count (0: all)", lo=0),
        Param("source", "float", "stars", "e-", "what of an earlier exposure persists: stars (its STARFLU: the "
              "light of stars only; the paper's setting and the study's), all (its FLUENCE: every photon, sky and "
              "galaxies too), or a number: only pixels whose FLUENCE exceeds that many electrons", lo=0.0,
              choices=("all", "stars")),
        Param("floor", "float", 0.0, "e-", "pixels of an earlier exposure whose persisting fluence (STARFLU or "
              "FLUENCE) is at or below this leave nothing: how far faint light persists (0: all of it, the linear "
              "law down to zero; the paper does not say)", lo=0.0),
        Param("fluence_cap", "float", "well", "e-", "the fluence fed to the law is at most this: well = "
              "saturation.full_well (no cap with saturation off), none = no cap (STARFLU beyond the well "
              "persists: the law extrapolated)", lo=0.0, lo_open=True, choices=("well", "none")),
    )


@register
class Persistence(DetectorEffect):
    name = "persistence"
    description = ("charge released by earlier exposures (--previous), from their FLUENCE or STARFLU "
                   "(source, fluence_cap) (perscli.detector.persistence; added as its expectation)")
    schema = _persistence_schema()

    @classmethod
    def resolve(cls, params):
        from .persistence import PRESETS

        out = super().resolve(params)
        for key, value in PRESETS[out["base"]].items():
            if out.get(key) is None:
                out[key] = float(value)
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
        import dataclasses

        from .persistence import FERMI_PARAMETERS, PersistenceModel

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
    def floor(model: "DetectorModel") -> float:
        """Electrons: earlier pixels at or below this leave no persistence in ``model`` (0: none left out)."""
        eff = model.get("persistence")
        return float((eff.resolved() if eff is not None else Persistence.resolve({}))["floor"])

    @staticmethod
    def fluence_input(model: "DetectorModel") -> tuple:
        """What of an earlier exposure feeds the law in ``model``: (source, threshold, cap).

        Returns
        -------
        source : {'all', 'stars', 'threshold'}
            Which image of the earlier frame: FLUENCE ('all', 'threshold') or STARFLU ('stars').
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
        image += self.p["beta"] * image * image
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
            from scipy import ndimage

            framed = ctx.blocks.edges(image)
            out = ndimage.correlate(framed, self.kernel()[None, :, :], mode="constant", cval=0.0)
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
        for gen, part, cut in self.streams(ctx, image.shape):
            image[part] += gen.normal(0.0, self.p["sigma"], size=(NOISE_BLOCK, NOISE_BLOCK))[cut]
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
    LINES = 4096

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
        return np.round(image)

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


# -- the model -----------------------------------------------------------------------------------


@dataclass
class Effect:
    """One step of a detector model: an effect's name, its parameters and whether it is on."""

    name: str
    params: dict = field(default_factory=dict)
    enabled: bool = True

    @property
    def cls(self):
        return REGISTRY[self.name]

    def resolved(self) -> dict:
        """Every parameter with the value it acts with."""
        return self.cls.resolve(self.params)

    def instance(self) -> DetectorEffect:
        return self.cls(self.resolved())


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

    def value(self, name: str, key: str, off=None):
        """A parameter's resolved value, or ``off`` when the effect is absent or switched off."""
        eff = self.get(name)
        if eff is None or not eff.enabled:
            return off
        return eff.resolved()[key]

    def describe(self) -> list:
        """[(name, enabled, resolved params)], in order: the model as it acts (two equal models describe equal)."""
        return [(e.name, e.enabled, e.resolved()) for e in self.effects]

    def persistence_model(self):
        """The :class:`~perscli.detector.persistence.PersistenceModel` of the persistence step."""
        eff = self.get("persistence")
        return Persistence.model(dict(eff.params) if eff else {}, f"{os.path.basename(self.source)}: persistence")


def default_model() -> DetectorModel:
    """GalSim's Roman chain with saturation at :data:`FULL_WELL`: every registered effect on, except those
    not in the Roman model (``offset``), which are left out."""
    return DetectorModel([Effect(name, copy.deepcopy(DEFAULTS[name])) for name in ORDER
                          if REGISTRY[name].default_enabled], source="roman")


def _plain(value):
    """A parameter value as plain Python (YAML cannot write numpy scalars and arrays)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def model_to_yaml(model: DetectorModel, header: str = "") -> str:
    """The model as the YAML that :func:`load_detector_model` reads back (every parameter resolved).

    Parameters
    ----------
    model : DetectorModel
    header : str
        Comment lines to put first (without '#').
    """
    import yaml

    effects = []
    for name, enabled, params in model.describe():
        entry = {k: _plain(v) for k, v in params.items()}
        if not enabled:
            entry["enabled"] = False
        effects.append({name: entry})
    text = yaml.safe_dump({"effects": effects}, sort_keys=False, default_flow_style=None, width=100)
    lines = "".join(f"# {line}\n" for line in header.splitlines()) if header else ""
    return lines + text


def load_detector_model(spec: str | None = None, overrides=()) -> DetectorModel:
    """Read a detector model and apply ``EFFECT.KEY=VALUE`` overrides.

    Parameters
    ----------
    spec : str, optional
        'roman' (or None) for :func:`default_model`; a YAML file: either a
        list under ``effects:`` (in physical order) of ``{name: {params}}``
        mappings, or a mapping ``name: {params}``, effects not listed are
        off, parameters not given take the defaults; or a FITS frame that
        ``perscli render`` wrote: the model that made it (its MODEL table).
    overrides : sequence of str
        'EFFECT.KEY=VALUE' (e.g. 'read_noise.sigma=5'), 'EFFECT=off' or
        'EFFECT=on'.

    Returns
    -------
    DetectorModel
    """
    if spec in (None, "roman", "default"):
        model = default_model()
    elif _is_fits(spec):
        model = _from_fits(spec)
    else:
        model = _from_yaml(spec)
    for text in overrides:
        _override(model, text)
    return model


def _is_fits(spec: str) -> bool:
    name = spec.split("[", 1)[0]
    if name.lower().endswith((".fits", ".fit", ".fts", ".fits.gz", ".fit.gz", ".fz")):
        return True
    try:
        with open(name, "rb") as fh:
            head = fh.read(9)
    except OSError:
        return False
    return head == b"SIMPLE  =" or head[:2] == b"\x1f\x8b"


def _from_yaml(path: str) -> DetectorModel:
    from ..io.config import load_yaml

    doc = load_yaml(path, "detector model")
    if isinstance(doc, dict) and "effects" in doc:
        others = [str(k) for k in doc if k != "effects"]
        if others:
            # a misspelt section would otherwise be ignored in silence
            raise PerscliError(f"{path}: unknown key(s) {', '.join(others)} beside 'effects:'; a detector model "
                               "file holds only 'effects:' (a list of effects in physical order)")
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
    for name, params in items:
        if params is not None and not isinstance(params, dict):
            raise PerscliError(f"{path}: the parameters of {name!r} must be a mapping, not {params!r}")
    return _build([(name, dict(params or {})) for name, params in items], path)


def _build(items, where: str) -> DetectorModel:
    """A model from [(name, {params, optionally 'enabled'})] in the order given, checked."""
    effects, seen = [], set()
    for name, params in items:
        if name not in REGISTRY:
            raise PerscliError(f"{where}: unknown effect {name!r}; known: {', '.join(ORDER)}")
        if name in seen:
            raise PerscliError(f"{where}: effect {name!r} is listed twice")
        seen.add(name)
        params = dict(params)
        enabled = params.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise PerscliError(f"{where}: {name}.enabled must be true or false, not {enabled!r}")
        merged = copy.deepcopy(DEFAULTS[name])
        merged.update(REGISTRY[name].validate(params, where))
        effects.append(Effect(name, merged, enabled))
    order = [ORDER.index(e.name) for e in effects]
    if order != sorted(order):
        raise PerscliError(f"{where}: effects must be listed in physical order: {', '.join(ORDER)}")
    return DetectorModel(effects, source=where)


def _override(model: DetectorModel, text: str) -> None:
    if "=" not in text:
        raise PerscliError(f"--set {text!r} is not EFFECT.KEY=VALUE or EFFECT=on|off")
    key, value = (s.strip() for s in text.split("=", 1))
    name, _, param = key.partition(".")
    if name not in REGISTRY:
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

    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError:
        parsed = value
    params = dict(eff.params)
    params.update(eff.cls.validate({param: parsed}, "--set"))
    eff.cls.validate(params, "--set")
    eff.params = params
    eff.enabled = True


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
    Others as for :func:`run_chain`.

    Returns
    -------
    dict
        Name -> ChainResult.
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
    state = _Steps()
    for eff in chains[0][:shared]:
        img = state.step(eff, img, ctx0)
    out = {}
    for n, chain in zip(names, chains):
        ctx = ChainContext(exptime=exptime, seed=seed, sky_rate=ctx0.sky, persistence=persistence.get(n),
                           origin=tuple(origin), active=active, blocks=blocks)
        ctx.used_sky_rate = ctx0.used_sky_rate
        branch = state.copy()
        mine = img.copy() if len(names) > 1 else img
        for eff in chain[shared:]:
            mine = branch.step(eff, mine, ctx)
        out[n] = branch.result(mine, ctx)
    return out


class _Steps:
    """The running state of a chain: IDEAL and FLUENCE as they are passed, and the unit."""

    def __init__(self):
        self.unit, self.ideal, self.fluence = "electron", None, None

    def copy(self) -> "_Steps":
        other = _Steps()
        other.unit, other.ideal, other.fluence = self.unit, self.ideal, self.fluence
        return other

    def step(self, eff: Effect, img: np.ndarray, ctx: ChainContext) -> np.ndarray:
        cls = eff.cls
        if self.ideal is None and cls.stage != "scene":
            self.ideal = img.copy()
        if self.fluence is None and cls.stage == "readout":
            # the charge collected so far is what traps hold on to: it drives later persistence
            self.fluence = img.copy()
        if not eff.enabled:
            return img
        img = eff.instance().sample(img, ctx)
        self.unit = cls.unit_out or self.unit
        return img

    def result(self, img: np.ndarray, ctx: ChainContext) -> ChainResult:
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


def forward(sources: np.ndarray, model: DetectorModel, *, exptime: float,
            sky_rate: Callable[[], float] | float = 0.0,
            persistence: Callable[[], np.ndarray] | np.ndarray | None = None) -> Forward:
    """Expectation and variance of a frame through the chain: what a likelihood of measured frames needs.

    Parameters are those of :func:`run_chain` (no seed: nothing is drawn).
    The mean is each effect's ``expectation`` of the previous mean; the
    variance is propagated with each effect's ``variance`` (first order in
    the noise: e.g. nonlinearity scales it by (1 + 2 beta x)^2).
    """
    ctx = ChainContext(exptime=exptime, seed=0, sky_rate=sky_rate, persistence=persistence)
    mean = np.array(sources, dtype=np.float64)
    var = np.zeros_like(mean)
    unit = "electron"
    fluence = None
    for eff in model.effects:
        if fluence is None and eff.cls.stage == "readout":
            fluence = mean.copy()
        if not eff.enabled:
            continue
        step = eff.instance()
        var = step.variance(mean, var, ctx)
        mean = step.expectation(mean, ctx)
        unit = eff.cls.unit_out or unit
    if fluence is None:
        fluence = mean.copy()
    return Forward(mean=mean, variance=np.broadcast_to(var, mean.shape).copy(), unit=unit, fluence=fluence,
                   sky_rate=ctx.used_sky_rate)


# -- the schema as a table, and the model in a FITS file ---------------------------------------

def _show(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return f"[{len(value)} values]" if len(value) > 3 else json.dumps(value)
    return str(value)


def schema_rows() -> list:
    """(effect, parameter, type, unit, default, allowed, description) for every effect and parameter.

    An effect's own row has an empty parameter, 'on' as default and its description.
    """
    rows = []
    for name, cls in REGISTRY.items():
        rows.append((name, "", "", "", "on", "", cls.description))
        for p in cls.schema:
            default = f"({p.derived})" if p.default is None else _show(p.default)
            kind = {"choice": "str", "kernel": "str|3x3", "floats": "list"}.get(p.kind, p.kind)
            rows.append(("", p.name, kind, p.unit, default, p.allowed(), p.description))
    return rows


def format_schema(width: int = 120) -> str:
    """The schema as a plain-text table, in physical order (``perscli render --list-effects``)."""
    import textwrap

    head = ("EFFECT", "PARAMETER", "TYPE", "UNIT", "DEFAULT", "ALLOWED", "DESCRIPTION")
    rows = schema_rows()
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(6)]
    indent = sum(widths) + 2 * 6
    desc_width = max(30, width - indent)
    lines = []
    for row in [head] + rows:
        cells = "  ".join(c.ljust(w) for c, w in zip(row[:6], widths))
        wrapped = textwrap.wrap(row[6], desc_width) or [""]
        lines.append(f"{cells}  {wrapped[0]}".rstrip())
        lines.extend((" " * indent + more).rstrip() for more in wrapped[1:])
    lines.append("")
    lines.append("Effects act in this order; --set EFFECT=off|on, --set EFFECT.PARAMETER=VALUE, or a YAML "
                 "model file (--model).")
    return "\n".join(lines) + "\n"


#: columns of the MODEL table: name, numpy type
MODEL_COLUMNS = ("EFFECT", "ENABLED", "PARAM", "VALUE", "UNIT")


def model_rows(model: DetectorModel) -> list:
    """(effect, enabled, parameter, value as JSON, unit) for every resolved parameter, in order.

    An effect without parameters has one row with an empty parameter, so
    that its place and its on/off state are recorded too.
    """
    rows = []
    for name, enabled, params in model.describe():
        cls = REGISTRY[name]
        if not cls.schema:
            rows.append((name, enabled, "", "", ""))
        for p in cls.schema:
            rows.append((name, enabled, p.name, json.dumps(params[p.name]), p.unit))
    return rows


def model_table(model: DetectorModel) -> tuple:
    """The MODEL binary table of a rendered frame: (structured array, column units)."""
    rows = model_rows(model)

    def width(i):
        return max([1] + [len(r[i]) for r in rows])

    dtype = [("EFFECT", f"S{width(0)}"), ("ENABLED", "?"), ("PARAM", f"S{width(2)}"),
             ("VALUE", f"S{width(3)}"), ("UNIT", f"S{width(4)}")]
    data = np.array([(r[0].encode(), bool(r[1]), r[2].encode(), r[3].encode(), r[4].encode()) for r in rows],
                    dtype=dtype)
    return data, ["", "", "", "", ""]


def model_from_table(columns: dict, where: str) -> DetectorModel:
    """The detector model of a MODEL table's columns (EFFECT, ENABLED, PARAM, VALUE), checked."""
    missing = [c for c in ("EFFECT", "ENABLED", "PARAM", "VALUE") if c not in columns]
    if missing:
        raise PerscliError(f"{where}: the MODEL table lacks column(s) {', '.join(missing)}")

    def text(v):
        return (v.decode("ascii", "replace") if isinstance(v, bytes) else str(v)).strip()

    items, index = [], {}
    for i, (name, enabled, param, value) in enumerate(zip(*(columns[c] for c in ("EFFECT", "ENABLED", "PARAM",
                                                                                   "VALUE"))), 1):
        name, param, value = text(name), text(param), text(value)
        if name not in index:
            index[name] = len(items)
            items.append((name, {"enabled": bool(enabled)}))
        params = items[index[name]][1]
        if params["enabled"] != bool(enabled):
            raise PerscliError(f"{where}: MODEL row {i}: {name} is both on and off")
        if not param:
            continue
        try:
            params[param] = json.loads(value)
        except ValueError:
            raise PerscliError(f"{where}: MODEL row {i}: the value {value!r} of {name}.{param} is not valid JSON; "
                               "the table is corrupt") from None
    return _build(items, where)


def _from_fits(path: str) -> DetectorModel:
    from ..io.fitsfile import open_fits

    with open_fits(path) as f:
        tables = [h for h in f.hdus if h.name == "MODEL" and h.kind == "table"]
        if not tables:
            raise PerscliError(f"{path}: no MODEL table: not a frame perscli render wrote (or one written before "
                               "models were stored); give 'roman' or a YAML model file")
        hdu = tables[0]
        columns = {name.upper(): hdu.read_column(name) for name in hdu.colnames}
        return model_from_table(columns, path)


def model_of_frame(frame) -> DetectorModel | None:
    """The detector model stored in an opened frame (:class:`perscli.io.frames.Frame`), or None."""
    tables = [h for h in getattr(frame, "hdus", []) or [] if h.name == "MODEL" and h.kind == "table"
              and {"EFFECT", "ENABLED", "PARAM", "VALUE"} <= {c.upper() for c in h.colnames}]
    if not tables:
        return None          # not rendered by perscli (another program's MODEL table is not ours)
    hdu = tables[0]
    columns = {name.upper(): hdu.read_column(name) for name in hdu.colnames}
    return model_from_table(columns, frame.label)
