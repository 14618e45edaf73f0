"""What the detector chain carries besides the image, and the noise blocks its random streams are keyed on.

:class:`ChainContext` holds the exposure time, seed, sky rate and
persistence charge an effect needs; :data:`NOISE_BLOCK`, :func:`block_grid`,
:func:`block_streams`, :class:`BlockStack` and :func:`active_pixels` place
an image (a frame, a cutout or a stack of scattered blocks) on the
detector's grid of noise blocks, so that a pixel gets the same noise
whatever else is simulated.  See :mod:`perscli.detector.effects` for the
effects and the YAML model format.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

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
    #: draws that do not depend on the image, shared by the branches of one :func:`iter_chains` call (the same
    #: seed, origin and blocks): a read noise is drawn once for the reference and every persistence variant
    shared: dict | None = field(default=None, repr=False)

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

    def _whole(self, shape, at=(0, 0)):
        """The blocks wholly inside an image of ``shape`` whose [0, 0] is area pixel ``at`` (and inside the area).

        Returns
        -------
        (ndarray of bool, function)
            Per block of the stack: wholly inside; and a function giving the
            image's pixels as (block row, row, block column, column) indexed
            by the stack's blocks there (a view, no copy).
        """
        b = NOISE_BLOCK
        by0, bx0, _, _ = block_grid(self.origin, self.shape)
        oy, ox = int(at[0]), int(at[1])
        # block rows and columns [lo, hi) of the area whose pixels all lie in the image and in the area
        jlo, ilo = -(-oy // b), -(-ox // b)
        jhi = min((oy + shape[0]) // b, self.shape[0] // b)
        ihi = min((ox + shape[1]) // b, self.shape[1] // b)
        jj, ii = self.by - by0, self.bx - bx0
        whole = (jj >= jlo) & (jj < jhi) & (ii >= ilo) & (ii < ihi)

        def blocks(image):
            part = image[jlo * b - oy:jhi * b - oy, ilo * b - ox:ihi * b - ox]
            return part.reshape(max(jhi - jlo, 0), b, max(ihi - ilo, 0), b)[jj[whole] - jlo, :, ii[whole] - ilo, :]

        return whole, blocks

    def gather(self, image: np.ndarray, fill=np.nan, dtype=np.float64, at=(0, 0)) -> np.ndarray:
        """The blocks of ``image`` as a stack; ``fill`` beyond the area.

        ``image`` is the area, or with ``at`` a part of it whose [0, 0] is
        area pixel (row, column) ``at``: the area's pixels outside it are
        ``fill`` too (a frame inside its simulation area, gathered without
        padding it to the area first).
        """
        whole, blocks = self._whole(image.shape, at)
        out = np.empty((len(self), NOISE_BLOCK, NOISE_BLOCK), dtype=dtype)
        # the whole blocks in one gather; the few cut by the area's or the image's edges one at a time
        out[whole] = blocks(image)
        oy, ox = int(at[0]), int(at[1])
        for k in np.flatnonzero(~whole):
            rows, cols = self._place(k)
            out[k] = fill
            ya, yb = max(rows.start, oy), min(rows.stop, oy + image.shape[0])
            xa, xb = max(cols.start, ox), min(cols.stop, ox + image.shape[1])
            if ya < yb and xa < xb:
                out[k, ya - rows.start:yb - rows.start, xa - cols.start:xb - cols.start] = \
                    image[ya - oy:yb - oy, xa - ox:xb - ox]
        return out

    def scatter(self, stack: np.ndarray, fill=np.nan, dtype=np.float64) -> np.ndarray:
        """The stack back in the area, ``fill`` where no block was simulated."""
        whole, _ = self._whole(self.shape)
        out = np.full(self.shape, fill, dtype=dtype)
        b = NOISE_BLOCK
        by0, bx0, _, _ = block_grid(self.origin, self.shape)
        nby, nbx = self.shape[0] // b, self.shape[1] // b
        out[:nby * b, :nbx * b].reshape(nby, b, nbx, b)[self.by[whole] - by0, :, self.bx[whole] - bx0, :] = \
            stack[whole]
        for k in np.flatnonzero(~whole):
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
        out = np.empty((n, b + 2, b + 2))
        inner = out[:, 1:-1, 1:-1]
        inner[...] = stack
        for k in np.flatnonzero((self.h < b) | (self.w < b)):
            # beyond the area: zeros, as past the edge of a frame
            inner[k, self.h[k]:, :] = 0.0
            inner[k, :, self.w[k]:] = 0.0
        nb = self.neighbours

        def edge(values):
            # a neighbour's row, column or corner; index n: not simulated (NaN), n + 1: beyond the area (0)
            pad = np.empty((n + 2,) + values.shape[1:])
            pad[:n], pad[n], pad[n + 1] = values, np.nan, 0.0
            return pad

        out[:, 0, 1:-1] = edge(inner[:, -1, :])[nb[:, 0, 1]]
        out[:, -1, 1:-1] = edge(inner[:, 0, :])[nb[:, 2, 1]]
        out[:, 1:-1, 0] = edge(inner[:, :, -1])[nb[:, 1, 0]]
        out[:, 1:-1, -1] = edge(inner[:, :, 0])[nb[:, 1, 2]]
        out[:, 0, 0] = edge(inner[:, -1, -1])[nb[:, 0, 0]]
        out[:, 0, -1] = edge(inner[:, -1, 0])[nb[:, 0, 2]]
        out[:, -1, 0] = edge(inner[:, 0, -1])[nb[:, 2, 0]]
        out[:, -1, -1] = edge(inner[:, 0, 0])[nb[:, 2, 2]]
        return out

    def blank(self, stack: np.ndarray) -> np.ndarray:
        """``stack`` with the pixels beyond the area NaN."""
        for k in np.flatnonzero((self.h < NOISE_BLOCK) | (self.w < NOISE_BLOCK)):
            stack[k, self.h[k]:, :] = np.nan
            stack[k, :, self.w[k]:] = np.nan
        return stack


def blank_inactive(image: np.ndarray, active, origin) -> np.ndarray:
    """Set the pixels of the blocks ``active`` leaves out to NaN, in place: ``image[~active_pixels(...)] = nan``
    one block at a time, without a mask of the whole image."""
    if active is None:
        return image
    by0, bx0, nby, nbx = block_grid(origin, image.shape)
    x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
    for j, i in zip(*np.nonzero(~np.asarray(active, dtype=bool)[:nby, :nbx])):
        ya, yb = max((by0 + j) * NOISE_BLOCK, y0), min((by0 + j + 1) * NOISE_BLOCK, y0 + image.shape[0])
        xa, xb = max((bx0 + i) * NOISE_BLOCK, x0), min((bx0 + i + 1) * NOISE_BLOCK, x0 + image.shape[1])
        image[ya - y0:yb - y0, xa - x0:xb - x0] = np.nan
    return image


def active_pixels(active, origin, shape) -> np.ndarray:
    """The pixels of the blocks ``active`` marks, as a bool image of ``shape`` (all True for None)."""
    if active is None:
        return np.ones(shape, dtype=bool)
    by0, bx0, nby, nbx = block_grid(origin, shape)
    x0, y0 = int(origin[0]) - 1, int(origin[1]) - 1
    big = np.repeat(np.repeat(np.asarray(active, dtype=bool), NOISE_BLOCK, axis=0), NOISE_BLOCK, axis=1)
    oy, ox = y0 - by0 * NOISE_BLOCK, x0 - bx0 * NOISE_BLOCK
    return big[oy:oy + shape[0], ox:ox + shape[1]]
