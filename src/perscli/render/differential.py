"""A final exposure rendered only where persistence can change a galaxy: the differential study.

What persists of an earlier exposure, when star light persists (the paper's
setting), is its stars' light: the persistence of a final exposure can only
be non-zero on the pixels that some star of an earlier exposure lit, the
union of those stars' stamps (:func:`reach_mask`).  A galaxy whose measured
stamp (:func:`window_boxes`, one pixel wider for interpixel capacitance) does
not touch that union has exactly the same pixels with and without
persistence, hence exactly the same fit: De = 0.  Only the others
(:func:`candidate_rows`) need pixels, and only theirs are simulated
(:func:`render_final`): the detector's noise blocks that their stamps reach
(:data:`perscli.detector.effects.NOISE_BLOCK`), with every object whose light
reaches those blocks.  Because each pixel's noise is keyed on its block and
each pixel is the sum of the same stamps in the same order, those pixels are
the very bits a whole-frame render gives: the differential result is the full
result, not an approximation of it (tests/test_differential.py checks this
galaxy by galaxy).

The final's file holds the reference (no persistence) in SCI, and one image
per variant (persistence model and source) holding only the stamps it
changed, NaN elsewhere, with a CHANGED table of which galaxies changed in
which variant; :func:`perscli.measure.changes.measure_changes` fits those.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from .. import PerscliError
from ..detector.blocks import NOISE_BLOCK, BlockStack, active_pixels, block_grid
from ..detector.chain import run_chains
from ..detector.effects import Persistence
from ..detector.model import DetectorModel
from ..optics import Optics
from .exposure import Exposure, draw_sources, plan_objects, read_truth

log = logging.getLogger(__name__)

#: pixels added to each side of a measured stamp: the render places a galaxy with GalSim's WCS and
#: measure with the header's (astropy), which may round it to the neighbouring pixel
WINDOW_MARGIN = 1
#: interpixel capacitance brings each neighbour's signal into a pixel
IPC_REACH = 1


def _subset(cols: dict, rows: np.ndarray) -> dict:
    return {k: (v[rows] if isinstance(v, np.ndarray) and v.shape[:1] == cols["ra"].shape else v)
            for k, v in cols.items()}


#: a star's stamp holds its flux, with ringing of a fraction of it either way: a group of stars whose
#: fluxes sum to F cannot raise a pixel above F times this
FLUX_BOUND = 1.1


def persisting_stars(flux, boxes, floor: float, *, totals: bool = False):
    """Which stars' light can reach above ``floor`` electrons in some pixel (bool per star).

    A pixel's star light is the sum of the stamps that cover it, all of
    whose stars are linked by overlapping stamps: a group of overlapping
    stars whose fluxes sum to at most ``floor`` / :data:`FLUX_BOUND` lights
    no pixel above ``floor``, and leaves nothing; every star of any other
    group is kept (its light adds to its neighbours').

    Parameters
    ----------
    flux : ndarray
        Electrons of each star.
    boxes : ndarray, shape (k, 4)
        Each star's stamp [x0, x1, y0, y1] (inclusive pixels).
    floor : float
    totals : bool
        Also return each star's group's summed flux (electrons).
    """
    flux = np.asarray(flux, dtype=np.float64)
    n = len(flux)
    if floor <= 0 or n == 0:
        return (np.ones(n, dtype=bool), np.abs(flux)) if totals else np.ones(n, dtype=bool)
    parent = np.arange(n)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    b = np.asarray(boxes)
    order = np.argsort(b[:, 0], kind="stable")
    # sweep along x: a star's stamp can only overlap those that start before it ends
    for k, i in enumerate(order):
        for j in order[k + 1:]:
            if b[j, 0] > b[i, 1]:
                break
            if b[j, 2] <= b[i, 3] and b[i, 2] <= b[j, 3]:
                parent[root(j)] = root(i)
    roots = np.array([root(i) for i in range(n)])
    total = np.bincount(roots, weights=np.abs(flux), minlength=n)[roots]
    keep = total * FLUX_BOUND > floor
    return (keep, total) if totals else keep


#: how much brighter than the envelope of two drawn stamps any sub-pixel position of a star may be
ENVELOPE_SAFETY = 2.0
_ENVELOPES: dict = {}


def psf_envelope(sca: int, filter_name: str, n: int) -> np.ndarray:
    """How bright a star of unit flux can be at each distance from its pixel: E[d], d = 0 .. n // 2.

    E[d] bounds ``|stamp|`` at every pixel whose distance (the larger of
    |dx| and |dy|, in pixels) from the star's nearest pixel is at least d,
    for a stamp of side ``n`` drawn as :func:`perscli.render.exposure.draw_sources`
    draws it (its wrapped wings included): the most of two stamps (the star
    on a pixel centre and on a pixel corner) times :data:`ENVELOPE_SAFETY`.
    A star of flux F lights no pixel at distance d above floor when
    F E[d] <= floor.
    """
    from ..optics import stamp_drawer

    key = (int(sca), filter_name, int(n))
    if key not in _ENVELOPES:
        drawer = stamp_drawer(sca, filter_name)
        peak = np.maximum(np.abs(drawer.stamp(n, 0.0, 0.0, 1.0)), np.abs(drawer.stamp(n, 0.49, 0.49, 1.0)))
        c = n // 2
        j, i = np.indices(peak.shape)
        dist = np.maximum(np.abs(i - c), np.abs(j - c))
        best = np.zeros(dist.max() + 1)
        np.maximum.at(best, dist.ravel(), peak.ravel())
        # at distance d or more: the running maximum from the outside in
        _ENVELOPES[key] = np.maximum.accumulate(best[::-1])[::-1] * ENVELOPE_SAFETY
    return _ENVELOPES[key]


def star_boxes(cols: dict, exposure: Exposure, *, optics: Optics | None = None, floor: float = 0.0) -> np.ndarray:
    """The detector pixels each star's stamp covers on an exposure's frame: (k, 4) [x0, x1, y0, y1], inclusive.

    These are the pixels :func:`perscli.render.exposure.draw_sources` gives
    the star light (STARFLU), hence the only ones whose light can persist.

    Parameters
    ----------
    cols : dict
        The catalogue (:func:`perscli.render.exposure.read_truth`).
    exposure : Exposure
        The earlier exposure (its pointing, SCA and frame bounds).
    optics : Optics, optional
    floor : float
        Electrons: light at or below it does not persist: the stars of
        :func:`persisting_stars` only.

    Returns
    -------
    ndarray of int, shape (k, 4)
    """
    stars = np.flatnonzero(cols["kind"] == "star")
    if not len(stars):
        return np.zeros((0, 4), dtype=np.int64)
    optics = optics if optics is not None else Optics(exposure)
    sub = _subset(cols, stars)
    todo, x, y, flux, sizes = plan_objects(sub, optics, exposure.full_bounds)
    ix = np.floor(x[todo] + 0.5).astype(np.int64)
    iy = np.floor(y[todo] + 0.5).astype(np.int64)
    n = sizes[todo]
    boxes = np.stack([ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1], axis=1)
    keep, group_flux = persisting_stars(flux[todo], boxes, floor, totals=True)
    if floor > 0:
        # only where a star's light, with all its group's, can exceed the floor: a star's whole stamp
        # (2048 pixels for J < 10) would make the region most of the frame
        for k in np.flatnonzero(keep):
            env = psf_envelope(exposure.sca, exposure.filter, int(n[k]))
            above = np.flatnonzero(env * group_flux[k] * FLUX_BOUND > floor)
            reach = int(above.max()) if above.size else -1
            if reach < 0:
                keep[k] = False
                continue
            boxes[k] = [max(boxes[k, 0], ix[k] - reach), min(boxes[k, 1], ix[k] + reach),
                        max(boxes[k, 2], iy[k] - reach), min(boxes[k, 3], iy[k] + reach)]
    return _clip(boxes[keep], exposure.full_bounds)


def _clip(boxes: np.ndarray, bounds) -> np.ndarray:
    xmin, xmax, ymin, ymax = bounds
    out = boxes.copy()
    out[:, 0] = np.maximum(out[:, 0], xmin)
    out[:, 1] = np.minimum(out[:, 1], xmax)
    out[:, 2] = np.maximum(out[:, 2], ymin)
    out[:, 3] = np.minimum(out[:, 3], ymax)
    return out[(out[:, 0] <= out[:, 1]) & (out[:, 2] <= out[:, 3])]


def reach_mask(boxes, bounds) -> np.ndarray:
    """The frame's pixels inside any of ``boxes`` (detector pixels, inclusive): where persistence can be non-zero.

    Returns
    -------
    ndarray of bool, the frame's shape (ny, nx)
    """
    xmin, xmax, ymin, ymax = bounds
    mask = np.zeros((ymax - ymin + 1, xmax - xmin + 1), dtype=bool)
    for x0, x1, y0, y1 in _clip(np.asarray(boxes, dtype=np.int64).reshape(-1, 4), bounds):
        mask[y0 - ymin:y1 - ymin + 1, x0 - xmin:x1 - xmin + 1] = True
    return mask


def window_boxes(x, y, stamp, margin: int = WINDOW_MARGIN) -> np.ndarray:
    """The detector pixels of the stamps ``perscli measure`` cuts around positions (x, y), grown by ``margin``.

    ``perscli measure`` cuts a stamp of side n around the pixel nearest the
    galaxy (:func:`perscli.measure.shapes.cut_stamp`); a smaller stamp lies
    inside a larger one.

    Parameters
    ----------
    stamp : int or ndarray of int
        The side of each stamp (:func:`stamp_sides`), or one for all.

    Returns
    -------
    ndarray of int, shape (k, 4): [x0, x1, y0, y1], inclusive
    """
    ix = np.floor(np.asarray(x, dtype=np.float64) + 0.5).astype(np.int64)
    iy = np.floor(np.asarray(y, dtype=np.float64) + 0.5).astype(np.int64)
    n = np.broadcast_to(np.asarray(stamp, dtype=np.int64), ix.shape)
    h = n // 2
    return np.stack([ix - h - margin, ix - h + n - 1 + margin, iy - h - margin, iy - h + n - 1 + margin], axis=1)


#: the pixel scale :func:`stamp_sides` assumes, as a fraction of Roman's 0.11": ``perscli measure`` sizes
#: stamps with the frame's own (0.105-0.111" over the focal plane; a joint fit takes their mean), and a
#: smaller scale gives an equal or larger stamp
SIDE_SCALE = 0.95


def stamp_sides(cols: dict, rows, stamp: int) -> np.ndarray:
    """The stamp side ``perscli measure`` can cut for each galaxy (``rows`` of the catalogue), or larger.

    :func:`perscli.measure.shapes.stamp_side` with a pixel scale a little
    below any the frames have (:data:`SIDE_SCALE`), on the ladder of
    ``stamp``: a stamp sized for a galaxy's half-light radius, mostly 16 to
    32 pixels, rather than ``stamp`` for all.
    """
    from ..instrument import ROMAN_PIXEL_SCALE
    from ..measure.perframe import stamp_ladder, stamp_side

    ladder = stamp_ladder(stamp)
    hlr = {"hlr": np.asarray(cols["hlr"], dtype=np.float64)}
    return np.array([stamp_side(hlr, int(i), ROMAN_PIXEL_SCALE * SIDE_SCALE, ladder) for i in rows], dtype=np.int64)


def touches(mask: np.ndarray, boxes, bounds) -> np.ndarray:
    """Per box (detector pixels, inclusive): whether any pixel of ``mask`` (the frame at ``bounds``) lies in it."""
    xmin, xmax, ymin, ymax = bounds
    boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    if len(boxes) < 2000:
        # few boxes: look at each one rather than sum the whole frame
        out = np.zeros(len(boxes), dtype=bool)
        for k, (x0, x1, y0, y1) in enumerate(boxes):
            a, b = max(x0 - xmin, 0), min(x1 - xmin + 1, mask.shape[1])
            c, d = max(y0 - ymin, 0), min(y1 - ymin + 1, mask.shape[0])
            out[k] = a < b and c < d and bool(mask[c:d, a:b].any())
        return out
    # int32 holds the count of any frame (4088^2 < 2^31), at half the memory traffic of int64
    table = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=np.int32)
    np.cumsum(np.cumsum(mask, axis=0, dtype=np.int32), axis=1, out=table[1:, 1:])
    x0 = np.clip(boxes[:, 0] - xmin, 0, mask.shape[1])
    x1 = np.clip(boxes[:, 1] - xmin + 1, 0, mask.shape[1])
    y0 = np.clip(boxes[:, 2] - ymin, 0, mask.shape[0])
    y1 = np.clip(boxes[:, 3] - ymin + 1, 0, mask.shape[0])
    inside = (x0 < x1) & (y0 < y1)
    total = table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]
    return inside & (total > 0)


def galaxy_positions(cols: dict, optics: Optics, bounds, stamp: int):
    """Catalogue rows of the galaxies whose measured stamps reach the frame, and their detector positions."""
    xmin, xmax, ymin, ymax = bounds
    gal = np.flatnonzero(cols["kind"] == "galaxy")
    x, y = optics.positions(cols["ra"][gal], cols["dec"][gal])
    reach = stamp // 2 + WINDOW_MARGIN + IPC_REACH + 1
    with np.errstate(invalid="ignore"):
        near = (x >= xmin - reach) & (x <= xmax + reach) & (y >= ymin - reach) & (y <= ymax + reach)
    return gal[near], x[near], y[near]


def candidate_rows(cols: dict, final: Exposure, masks, *, stamp: int, optics: Optics | None = None) -> np.ndarray:
    """Per catalogue row: whether the galaxy's measured stamp on ``final`` touches where persistence can be.

    Parameters
    ----------
    cols : dict
        The catalogue.
    final : Exposure
    masks : ndarray of bool, or None
        :func:`reach_mask` of the final's earlier exposures (None: nothing reaches).
    stamp : int
        The largest stamp ``perscli measure`` cuts (its ``--stamp``).
    """
    out = np.zeros(len(cols["ra"]), dtype=bool)
    if masks is None or not masks.any():
        return out
    optics = optics if optics is not None else Optics(final)
    rows, x, y = galaxy_positions(cols, optics, final.full_bounds, stamp)
    boxes = window_boxes(x, y, stamp_sides(cols, rows, stamp), WINDOW_MARGIN + IPC_REACH)
    out[rows[touches(masks, boxes, final.full_bounds)]] = True
    return out


def on_final_rows(cols: dict, final: Exposure, *, stamp: int, optics: Optics | None = None) -> np.ndarray:
    """Per catalogue row: whether the galaxy's measured stamp reaches ``final``'s frame at all."""
    out = np.zeros(len(cols["ra"]), dtype=bool)
    optics = optics if optics is not None else Optics(final)
    rows, x, y = galaxy_positions(cols, optics, final.full_bounds, stamp)
    out[rows] = True
    return out


def _active_blocks(boxes, area) -> np.ndarray:
    """The noise blocks of ``area`` (block_grid of it) that any box (detector pixels, inclusive) reaches."""
    ax0, ax1, ay0, ay1 = area
    shape = (ay1 - ay0 + 1, ax1 - ax0 + 1)
    by0, bx0, nby, nbx = block_grid((ax0, ay0), shape)
    active = np.zeros((nby, nbx), dtype=bool)
    for x0, x1, y0, y1 in _clip(np.asarray(boxes, dtype=np.int64).reshape(-1, 4), area):
        active[(y0 - 1) // NOISE_BLOCK - by0:(y1 - 1) // NOISE_BLOCK - by0 + 1,
               (x0 - 1) // NOISE_BLOCK - bx0:(x1 - 1) // NOISE_BLOCK - bx0 + 1] = True
    return active


def _objects_reaching(plan, active, area) -> np.ndarray:
    """Per catalogue row: whether its stamp reaches an active noise block of ``area``."""
    todo, x, y, _, sizes = plan
    out = np.zeros(len(x), dtype=bool)
    if not active.any() or not len(todo):
        return out
    ax0, ax1, ay0, ay1 = area
    by0, bx0, nby, nbx = block_grid((ax0, ay0), (ay1 - ay0 + 1, ax1 - ax0 + 1))
    n = sizes[todo]
    ix = np.floor(x[todo] + 0.5).astype(np.int64)
    iy = np.floor(y[todo] + 0.5).astype(np.int64)
    boxes = np.stack([ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1], axis=1)
    table = np.zeros((nby + 1, nbx + 1), dtype=np.int64)
    np.cumsum(np.cumsum(active, axis=0, dtype=np.int64), axis=1, out=table[1:, 1:])
    c = np.clip(boxes, [ax0, ax0, ay0, ay0], [ax1, ax1, ay1, ay1])
    bxa = (c[:, 0] - 1) // NOISE_BLOCK - bx0
    bxb = (c[:, 1] - 1) // NOISE_BLOCK - bx0 + 1
    bya = (c[:, 2] - 1) // NOISE_BLOCK - by0
    byb = (c[:, 3] - 1) // NOISE_BLOCK - by0 + 1
    inside = (boxes[:, 0] <= ax1) & (boxes[:, 1] >= ax0) & (boxes[:, 2] <= ay1) & (boxes[:, 3] >= ay0)
    total = table[byb, bxb] - table[bya, bxb] - table[byb, bxa] + table[bya, bxa]
    out[todo[inside & (total > 0)]] = True
    return out


#: the stars' light of earlier exposures drawn by :func:`star_light`, kept for the next final of the same
#: detector (which shares all but one of its earlier exposures): key -> float32 image
_STAR_LIGHT: dict = {}
_STAR_LIGHT_SIZE = 12
_TRUTH: dict = {}


def _truth_columns(truth: str, filter_name: str) -> dict:
    """The catalogue's columns for a filter, read once per process and file (size and time keyed)."""
    import os

    st = os.stat(truth)
    key = (os.path.realpath(truth), st.st_size, st.st_mtime_ns, filter_name)
    if key not in _TRUTH:
        if len(_TRUTH) >= 4:
            _TRUTH.pop(next(iter(_TRUTH)))
        _TRUTH[key] = read_truth(truth, filter_name)
    return _TRUTH[key]


def star_light(truth: str, exposure: Exposure, floor: float = 0.0) -> np.ndarray:
    """The expected electrons of the catalogue's stars on an exposure's frame: its STARFLU, as render writes it.

    What an earlier exposure leaves when star light persists (the paper's
    setting): drawn here from the catalogue rather than read from a file, and
    kept for the next final (a study's earlier exposures would be most of its
    bytes).  The same stamps added in the same order as ``perscli render``
    adds them, in float32 as it writes them: the same bits as its STARFLU.
    With ``floor``, only the stars whose light can exceed it
    (:func:`persisting_stars`) are drawn: the same bits wherever the light
    exceeds ``floor``, what persists above it.
    """
    import os

    st = os.stat(truth)
    key = (os.path.realpath(truth), st.st_size, st.st_mtime_ns, exposure.sca, exposure.expid, exposure.mjd,
           exposure.filter, exposure.full_bounds, float(floor))
    if key in _STAR_LIGHT:
        _STAR_LIGHT[key] = _STAR_LIGHT.pop(key)        # most recently used last
        return _STAR_LIGHT[key]
    cols = _truth_columns(truth, exposure.filter)
    optics = Optics(exposure)
    plan = plan_objects(cols, optics, exposure.full_bounds)
    only = cols["kind"] == "star"
    if floor > 0:
        todo, x, y, flux, sizes = plan
        stars = todo[only[todo]]
        ix = np.floor(x[stars] + 0.5).astype(np.int64)
        iy = np.floor(y[stars] + 0.5).astype(np.int64)
        n = sizes[stars]
        boxes = np.stack([ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1], axis=1)
        only = np.zeros_like(only)
        only[stars[persisting_stars(flux[stars], boxes, floor)]] = True
    light = draw_sources(cols, exposure, stars=True, optics=optics, plan=plan, only=only,
                         image=False)[3].astype(np.float32)
    _STAR_LIGHT[key] = light
    while len(_STAR_LIGHT) > _STAR_LIGHT_SIZE:
        _STAR_LIGHT.pop(next(iter(_STAR_LIGHT)))
    return light


def star_persistence(truth: str, final: Exposure, histories, laws: dict, blocks=None, area=None) -> dict:
    """The persistence charge that the star light of ``histories`` leaves in ``final``, per law.

    The computation of ``perscli render --previous`` with the earlier
    frames' STARFLU (:func:`perscli.render.run.history_persistences`), on
    their light drawn here (:func:`star_light`).

    Parameters
    ----------
    laws : dict
        Name -> (PersistenceModel, threshold, cap, floor).
    blocks : perscli.detector.effects.BlockStack, optional
        Only these noise blocks of ``area`` (the simulation area around the
        final's frame): the charge as a stack of them.  The law is per pixel,
        so a block's values are the whole frame's there.
    area : (x0, x1, y0, y1)
        With ``blocks``.

    Returns
    -------
    dict
        Name -> electrons per pixel of the final's frame (or the stack of ``blocks``).
    """
    from ..detector.persistence import order_earlier, persistence_charge
    from ..io.frames import SECONDS_PER_DAY
    from .run import persisting_fluence

    histories = list(histories)
    for h in histories:
        if h.full_bounds != final.full_bounds or h.sca != final.sca:
            raise PerscliError(f"earlier exposure {h.expid}: not the frame of final {final.expid} (SCA {h.sca}, "
                               f"bounds {h.full_bounds})")
    ends = [(h.end - final.mjd) * SECONDS_PER_DAY for h in histories]
    window = (final.end - final.mjd) * SECONDS_PER_DAY
    names = [f"earlier exposure {h.expid}" for h in histories]
    from .run import pad_to

    bounds = final.full_bounds
    lights, charges = {}, {}

    def light(i, floor):
        if (i, floor) not in lights:
            value = star_light(truth, histories[i], floor)
            # only the blocks simulated: the law on a few per cent of the frame
            lights[(i, floor)] = value if blocks is None else \
                blocks.gather(pad_to(value, bounds, area), fill=0.0, dtype=np.float32)
        return lights[(i, floor)]

    def fluence(i, threshold, cap, floor, scratch):
        # made when the law uses it, in one scratch array: fresh frames cost more in page faults than the law
        return lambda: persisting_fluence(lights[(i, floor)], 1.0, threshold=threshold, cap=cap, floor=floor,
                                          out=scratch)

    for name, (pmodel, threshold, cap, floor) in laws.items():
        keep, _ = order_earlier(ends, 0.0, pmodel, names)
        if not histories:
            charges[name] = None
            continue
        for i in keep:
            light(i, floor)
        shape = next(iter(lights.values())).shape if lights else (1,)
        scratch = np.empty(shape, dtype=np.float32)
        # exposures beyond the law's look-back or count are left out by persistence_charge: never called
        fluences = [fluence(i, threshold, cap, floor, scratch) for i in range(len(histories))]
        charges[name] = persistence_charge(fluences, ends, 0.0, window, pmodel)[0] if keep else None
    return charges


#: below this fraction of active blocks the chain runs on the stack of them rather than on the whole area
STACK_FRACTION = 0.25


def _simulate(sources, models, charges, *, exposure, seed, sky_rate, active, area, blocks=None) -> dict:
    """Every model's SCI over ``area`` (NaN outside the active blocks).

    With ``blocks`` (few active blocks), the chain runs on the stack of them
    (:class:`perscli.detector.effects.BlockStack`; ``charges`` are stacks
    too) and the result is put back in the area; noise is keyed on blocks,
    so each pixel is the bits the whole area gives.
    """
    if blocks is None:
        results = run_chains(sources, models, exptime=exposure.exptime, seed=seed, sky_rate=sky_rate,
                             persistence=charges, origin=(area[0], area[2]), active=active)
        return {name: (r.sci, r.unit, r.sky_rate) for name, r in results.items()}
    results = run_chains(blocks.gather(sources), models, exptime=exposure.exptime, seed=seed, sky_rate=sky_rate,
                         persistence=charges, origin=(area[0], area[2]), blocks=blocks)
    return {name: (blocks.scatter(r.sci, dtype=np.float32), r.unit, r.sky_rate) for name, r in results.items()}


def render_final(truth: str, exposure: Exposure, dest: str, *, model: DetectorModel, variants: dict, seed: int,
                 histories=(), rows=None, stamp: int = 48, compress: str = "gzip", overwrite: bool = False,
                 pixels: dict | None = None) -> dict:
    """The reference and every variant of a final exposure, on the stamps of ``rows`` only; write ``dest``.

    Parameters
    ----------
    truth : str
        The truth catalogue.
    exposure : Exposure
        The final exposure (with its frame's bounds).
    dest : str
        Output file: SCI (the reference: ``model`` without earlier
        exposures) holding the pixels of the rows' stamps (NaN elsewhere);
        one image per variant (:func:`perscli.measure.changes.variant_extname`)
        holding the stamps it changed (NaN elsewhere); MODEL (the
        reference's detector model); CHANGED (id, and per variant whether
        it changed that galaxy's stamp).
    model : DetectorModel
        The reference's detector model.
    variants : dict
        Variant name -> DetectorModel: the model with its persistence law and
        source (only star light persists here: source 'stars').
    seed : int
        The frame's seed: the reference and every variant share its noise.
    histories : sequence of Exposure
        The earlier exposures of the same frame: their stars' light persists
        (:func:`star_persistence`).
    rows : ndarray of bool, optional
        Per catalogue row: the galaxies whose stamps to simulate (default: none).
    stamp : int
        The largest stamp ``perscli measure`` cuts.
    compress, overwrite
        As for :func:`perscli.render.run.render_file`.
    pixels : dict, optional
        Filled with the images and the CHANGED table as arrays (``SCI``, each
        variant's EXTNAME, ``CHANGED``) for a caller that measures them right
        away; ``dest`` then holds the reference, MODEL and CHANGED only.

    Returns
    -------
    dict
        rows simulated, objects drawn, active blocks and their fraction, and
        per variant the galaxies changed.
    """
    from ..io.cards import format_card
    from ..io.fitsfile import OutHDU, table_hdu
    from ..io.output import check_output, write_hdus
    from .run import _exposure_cards, _model_hdu, _provenance, _wcs_cards, crop, pad_to, simulation_area

    check_output(dest, overwrite=overwrite, inputs=[truth])
    cols = _truth_columns(truth, exposure.filter)
    for name, vm in variants.items():
        source = Persistence.fluence_input(vm)[0]
        if source != "stars":
            raise PerscliError(f"variant {name}: a differential render needs star light persisting "
                               f"(persistence.source stars), not {source}")
    optics = Optics(exposure)
    bounds = exposure.full_bounds
    xmin, xmax, ymin, ymax = bounds
    area = simulation_area(bounds)
    rows = np.zeros(len(cols["ra"]), dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
    gal, gx, gy = galaxy_positions(cols, optics, bounds, stamp)
    keep = rows[gal]
    gal, gx, gy = gal[keep], gx[keep], gy[keep]
    sides = stamp_sides(cols, gal, stamp)
    windows = _clip_keep(window_boxes(gx, gy, sides), bounds)
    active = _active_blocks(window_boxes(gx, gy, sides, WINDOW_MARGIN + IPC_REACH), area)
    plan = plan_objects(cols, optics, area)
    drawn = _objects_reaching(plan, active, area)
    sources = draw_sources(cols, exposure, optics=optics, plan=plan, bounds=area, only=drawn)[0] \
        if active.any() else np.zeros((area[3] - area[2] + 1, area[1] - area[0] + 1))
    charges = {}
    blocks = BlockStack.of(active, (area[0], area[2]), sources.shape) \
        if active.any() and active.mean() <= STACK_FRACTION else None
    if active.any() and histories:
        laws = {name: (vm.persistence_model(), *Persistence.fluence_input(vm)[1:], Persistence.floor(vm))
                for name, vm in variants.items()}
        charges = star_persistence(truth, exposure, histories, laws, blocks, area)
        if blocks is None:
            charges = {name: pad_to(charge, bounds, area) for name, charge in charges.items()}
    models = {"": model, **variants}
    results = _simulate(sources, models, charges, exposure=exposure, seed=seed, sky_rate=optics.sky_rate,
                        active=active, area=area, blocks=blocks)
    ref = crop(results[""][0], area, bounds)
    inside = np.zeros(ref.shape, dtype=bool)
    for x0, x1, y0, y1 in windows[1]:
        inside[y0 - ymin:y1 - ymin + 1, x0 - xmin:x1 - xmin + 1] = True
    if np.any(inside & ~np.isfinite(ref)):          # pragma: no cover - the blocks cover the windows
        raise PerscliError("render_final: a stamp reaches pixels that were not simulated")
    ref_out = np.where(inside, ref, np.nan).astype(np.float32)
    changed, var_out = {}, {}
    for name in variants:
        sci = crop(results[name][0], area, bounds).astype(np.float32)
        # a stamp changed when any of its pixels (as written: float32) differs from the reference's
        flags = touches(inside & (sci != ref_out), windows[1], bounds)
        keep = np.zeros(ref.shape, dtype=bool)
        for x0, x1, y0, y1 in windows[1][flags]:
            keep[y0 - ymin:y1 - ymin + 1, x0 - xmin:x1 - xmin + 1] = True
        changed[name], var_out[name] = flags, np.where(keep, sci, np.float32(np.nan))
    gain = model.value("gain", "gain", off=1.0)
    unit, sky_rate = results[""][1], results[""][2]
    common = _wcs_cards(optics, bounds)
    frame_cards = common + _exposure_cards(exposure, optics, seed, unit, gain) + [
        format_card("SKYRATE", sky_rate, "[e-/pixel/s] sky background used"),
        format_card("NOBJ", int(np.count_nonzero(drawn)), "objects drawn (those reaching the stamps)")]
    region = [format_card("REGION", "stamps", "only the stamps of galaxies persistence can reach"),
              format_card("NBLOCKS", int(active.sum()), f"noise blocks ({NOISE_BLOCK} px) simulated"),
              format_card("FBLOCKS", round(float(active.mean()) if active.size else 0.0, 6),
                          "fraction of the blocks simulated")]
    out = [OutHDU([format_card("SIMPLE", True), format_card("BITPIX", 8), format_card("NAXIS", 0),
                   format_card("EXTEND", True)])]
    out.append(OutHDU(frame_cards + region + [
        format_card("CONTENT", "reference: no persistence", "NaN outside the stamps simulated")],
        ref_out, extname="SCI"))
    from ..measure.changes import CHANGED_EXTNAME, variant_extname

    for name, vm in variants.items() if pixels is None else ():
        pm = vm.persistence_model()
        out.append(OutHDU(frame_cards + region + [
            format_card("CONTENT", f"variant {name}", "NaN where it equals SCI: only changed stamps"),
            format_card("VARIANT", name), format_card("PS_LAW", pm.name[-68:], "persistence law"),
            format_card("PS_FLOOR", Persistence.floor(vm), "[e-] fluence at or below leaves nothing"),
            format_card("NCHANGED", int(changed[name].sum()), "galaxies whose stamps changed")],
            var_out[name], extname=variant_extname(name)))
    out.append(_model_hdu(model))
    ids = np.asarray(cols["id"])[gal[windows[0]]].astype(np.int64)
    table = {"id": ids, **{variant_extname(n): changed[n].astype(np.int16) for n in variants}}
    out.append(table_hdu(table, CHANGED_EXTNAME, descriptions={"id": "catalogue id of a galaxy simulated"}))
    _provenance(out[0], truth, cols["datasum"], exposure, model, seed, [], [], {}, sky_rate,
                int(np.count_nonzero(drawn)), ("SCI", *[variant_extname(n) for n in variants]))
    out[0]["NPREV"] = (len(histories), "earlier exposures whose star light persists")
    for k, h in enumerate(histories, 1):
        if k <= 99:
            out[0][f"PRV{k:02d}ID"] = (int(h.expid), f"earlier exposure, ended MJD {h.end:.6f}")
    write_hdus(out, dest, overwrite=overwrite, compress=compress)
    if pixels is not None:
        pixels.update({"SCI": ref_out, "CHANGED": table,
                       **{variant_extname(n): var_out[n] for n in variants}})
    return {"rows": int(len(windows[0])), "objects": int(np.count_nonzero(drawn)), "blocks": int(active.sum()),
            "block_fraction": float(active.mean()) if active.size else 0.0,
            "changed": {n: int(c.sum()) for n, c in changed.items()}}


def _clip_keep(boxes: np.ndarray, bounds):
    """(indices of the boxes that reach ``bounds``, the boxes clipped to it)."""
    xmin, xmax, ymin, ymax = bounds
    c = boxes.copy()
    c[:, 0] = np.maximum(c[:, 0], xmin)
    c[:, 1] = np.minimum(c[:, 1], xmax)
    c[:, 2] = np.maximum(c[:, 2], ymin)
    c[:, 3] = np.minimum(c[:, 3], ymax)
    ok = (c[:, 0] <= c[:, 1]) & (c[:, 2] <= c[:, 3])
    return np.flatnonzero(ok), c[ok]


def final_candidates(cols: dict, final: Exposure, history, *, stamp: int = 48, floor: float = 0.0, cache=None):
    """Which galaxies' stamps on ``final`` the star light of its earlier exposures can reach.

    Parameters
    ----------
    cols : dict
        The truth catalogue.
    final : Exposure
    history : sequence of Exposure
        Its earlier exposures (same detector and frame).
    stamp : int
        The largest stamp ``perscli measure`` cuts.
    floor : float
        Electrons: star light at or below it does not persist.
    cache : dict, optional
        Earlier exposures' :func:`star_boxes`, kept between finals.

    Returns
    -------
    (ndarray of bool, ndarray of bool, float)
        Per catalogue row: reached; on the frame (the galaxy's stamp reaches
        it); and the fraction of the frame's pixels persistence can reach.
    """
    cache = {} if cache is None else cache
    parts = []
    for h in history:
        key = (h.sca, h.expid, h.full_bounds, float(floor))
        if key not in cache:
            cache[key] = star_boxes(cols, h, floor=floor)
        parts.append(cache[key])
    mask = reach_mask(np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.int64), final.full_bounds)
    optics = Optics(final)
    cand = candidate_rows(cols, final, mask, stamp=stamp, optics=optics)
    on = on_final_rows(cols, final, stamp=stamp, optics=optics)
    return cand, on, float(mask.mean())


def plan_regions(cols: dict, finals, *, stamp: int = 48, joint: bool = True, floor: float = 0.0):
    """Which galaxies of which finals a differential study simulates.

    Parameters
    ----------
    cols : dict
        The truth catalogue (:func:`perscli.render.exposure.read_truth`).
    finals : sequence of (Exposure, sequence of Exposure)
        Each final exposure with its earlier exposures (same detector).
    stamp : int
        The largest stamp ``perscli measure`` cuts.
    joint : bool
        Galaxies fitted over all their finals: a galaxy that persistence can
        reach on any final is simulated on every final it falls on.
    floor : float
        Electrons: star light at or below it does not persist (the smallest
        floor of the study's variants).

    Returns
    -------
    (dict, dict)
        The table (columns sca, expid, id: a galaxy to simulate on a final),
        and counts: on_frames (galaxy-final pairs with the stamp on the
        frame), galaxies_on, candidates (galaxies simulated), reached
        (galaxy-final pairs persistence can reach), pixel_fraction (of the
        finals' pixels persistence can reach, mean), floor.
    """
    boxes = {}
    per_final = []
    reached, on_frames, fractions = 0, 0, []
    n = len(cols["ra"]) if cols is not None else 0
    on_any = np.zeros(n, dtype=bool)
    reached_any = np.zeros(n, dtype=bool)
    for final, history in finals:
        cand, on, fraction = final_candidates(cols, final, history, stamp=stamp, floor=floor, cache=boxes)
        fractions.append(fraction)
        per_final.append((final, cand, on))
        on_any |= on
        reached_any |= cand
        reached += int(cand.sum())
        on_frames += int(on.sum())
    sca, expid, ids = [], [], []
    for final, cand, on in per_final:
        rows = np.flatnonzero((reached_any & on) if joint else cand)
        sca.append(np.full(len(rows), final.sca, dtype=np.int16))
        expid.append(np.full(len(rows), final.expid, dtype=np.int64))
        ids.append(np.asarray(cols["id"])[rows].astype(np.int64))
    cat = (lambda parts, dtype: np.concatenate(parts) if parts else np.zeros(0, dtype=dtype))
    table = {"sca": cat(sca, np.int16), "expid": cat(expid, np.int64), "id": cat(ids, np.int64)}
    counts = {"on_frames": on_frames, "galaxies_on": int(on_any.sum()), "candidates": int(reached_any.sum()),
              "reached": reached, "pixel_fraction": float(np.mean(fractions)) if fractions else 0.0,
              "floor": float(floor)}
    return table, counts
