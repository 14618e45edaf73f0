"""Where persistence can reach on a final, and which galaxies a differential study simulates.

What persists of an earlier exposure is light drawn from the catalogue: the
stamps :func:`perscli.render.exposure.draw_sources` draws (:func:`light_boxes`:
every object's for the source 'drawn', the stars' for 'stars', only the part a
star's light can keep above a fluence floor).  A galaxy whose measured stamp
(:func:`window_boxes`, grown by a pixel for interpixel capacitance) none of
them reaches has the same pixels with and without persistence: its De is 0
exactly (:func:`candidate_rows`).  :func:`plan_regions` lists, per final, the
galaxies of the study's sample (:func:`in_field`) to simulate;
:mod:`perscli.study.differential` renders them.
"""

from __future__ import annotations

import numpy as np

from ..detector.blocks import NOISE_BLOCK, block_grid
from ..instrument import ROMAN_PIXEL_SCALE
from ..measure.perframe import stamp_ladder, stamp_side
from ..measure.settings import MeasureOptions
from ..optics import Optics, stamp_drawer
from ..render.exposure import Exposure, plan_objects
from ..scene import separation

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


def light_boxes(cols: dict, exposure: Exposure, source: str = "drawn", *, optics: Optics | None = None,
                floor: float = 0.0) -> np.ndarray:
    """The detector pixels whose light can persist on an exposure's frame: (k, 4) [x0, x1, y0, y1], inclusive.

    The stamps :func:`perscli.render.exposure.draw_sources` draws: of every
    object for the source 'drawn' (the frame's DRAWN), of the stars for
    'stars' (STARFLU); light can persist nowhere else.

    Parameters
    ----------
    cols : dict
        The catalogue (:func:`perscli.render.exposure.read_truth`).
    exposure : Exposure
        The earlier exposure (its pointing, SCA and frame bounds).
    source : {'drawn', 'stars'}
    optics : Optics, optional
    floor : float
        Electrons: light at or below it does not persist: only the objects
        of :func:`persisting_stars` (groups of overlapping stamps bright
        enough), and for stars only the part of the stamp within which the
        PSF can keep the light above the floor.

    Returns
    -------
    ndarray of int, shape (k, 4)
    """
    rows = np.flatnonzero(cols["kind"] == "star") if source == "stars" else np.arange(len(cols["ra"]))
    if not len(rows):
        return np.zeros((0, 4), dtype=np.int64)
    optics = optics if optics is not None else Optics(exposure)
    sub = _subset(cols, rows)
    todo, x, y, flux, sizes = plan_objects(sub, optics, exposure.full_bounds)
    ix = np.floor(x[todo] + 0.5).astype(np.int64)
    iy = np.floor(y[todo] + 0.5).astype(np.int64)
    n = sizes[todo]
    boxes = np.stack([ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1], axis=1)
    keep, group_flux = persisting_stars(flux[todo], boxes, floor, totals=True)
    if floor > 0 and source == "stars":
        # only where a star's light, with all its group's, can exceed the floor: a star's whole stamp
        # (2048 pixels for J < 10) would make the region most of the frame (a galaxy's light is spread
        # over its profile, which the point source's envelope does not bound: its whole stamp is kept)
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
    galaxy (:func:`perscli.measure.perframe.cut_stamp`); a smaller stamp lies
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

    :func:`perscli.measure.perframe.stamp_side` with a pixel scale a little
    below any the frames have (:data:`SIDE_SCALE`), on the ladder of
    ``stamp``: a stamp sized for a galaxy's half-light radius, mostly 16 to
    32 pixels, rather than ``stamp`` for all.
    """
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


def final_candidates(cols: dict, final: Exposure, history, *, stamp: int = MeasureOptions.stamp, sources=("drawn",), floor: float = 0.0,
                     sample=None, cache=None):
    """Which galaxies' stamps on ``final`` the light of its earlier exposures can reach.

    Parameters
    ----------
    cols : dict
        The truth catalogue.
    final : Exposure
    history : sequence of Exposure
        Its earlier exposures (same detector and frame).
    stamp : int
        The largest stamp ``perscli measure`` cuts.
    sources : sequence of {'drawn', 'stars'}
        What persists (the study's variants: the union of what they reach).
    floor : float
        Electrons: light at or below it does not persist (the smallest floor of the variants).
    sample : ndarray of bool, optional
        Per catalogue row: the galaxies of the study's sample (default: all).
    cache : dict, optional
        Earlier exposures' :func:`light_boxes`, kept between finals.

    Returns
    -------
    (ndarray of bool, ndarray of bool, float)
        Per catalogue row: reached; on the frame (the galaxy's stamp reaches
        it); and the fraction of the frame's pixels persistence can reach
        (NaN for the source 'drawn', which reaches every galaxy on the frame).
    """
    if "drawn" in sources:
        # every object's light persists: its stamps (64 pixels and more for each galaxy) reach nearly every
        # galaxy of the frame, and simulating the few they miss only finds De = 0 there: all are candidates
        on = on_final_rows(cols, final, stamp=stamp)
        if sample is not None:
            on &= sample
        return on.copy(), on, float("nan")
    cache = {} if cache is None else cache
    parts = []
    for h in history:
        for source in sorted(set(sources)):
            key = (h.sca, h.expid, h.full_bounds, source, float(floor))
            if key not in cache:
                cache[key] = light_boxes(cols, h, source, floor=floor)
            parts.append(cache[key])
    mask = reach_mask(np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.int64), final.full_bounds)
    optics = Optics(final)
    cand = candidate_rows(cols, final, mask, stamp=stamp, optics=optics)
    on = on_final_rows(cols, final, stamp=stamp, optics=optics)
    if sample is not None:
        cand &= sample
        on &= sample
    return cand, on, float(mask.mean())


def in_field(cols: dict, field: dict) -> np.ndarray:
    """Per catalogue row: a galaxy within ``field['radius']`` degrees of the field's centre (the study's sample).

    Every exposure that covers such a galaxy reaches the field, hence is a
    final of a study whose finals are all the exposures reaching it: the
    galaxy is measured on all of its exposures, as in a survey.
    """
    dist = separation(field["ra"], field["dec"], np.asarray(cols["ra"]), np.asarray(cols["dec"]))
    return (np.asarray(cols["kind"]) == "galaxy") & (dist <= field["radius"])


def plan_regions(cols: dict, finals, *, stamp: int = MeasureOptions.stamp, joint: bool = True, sources=("drawn",), floor: float = 0.0,
                 sample=None):
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
    sources : sequence of {'drawn', 'stars'}
        What persists in the study's variants.
    floor : float
        Electrons: light at or below it does not persist (the smallest
        floor of the study's variants).
    sample : ndarray of bool, optional
        Per catalogue row: the study's sample (:func:`in_field`); None: every galaxy.

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
        cand, on, fraction = final_candidates(cols, final, history, stamp=stamp, sources=sources, floor=floor,
                                              sample=sample, cache=boxes)
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
