"""A final exposure rendered only where persistence can change a galaxy: the differential study.

What persists of an earlier exposure is light drawn from the catalogue:
every object's (persistence source 'drawn', the paper's pipeline) or the
stars' alone ('stars').  A galaxy whose measured stamp (:func:`window_boxes`,
one pixel wider for interpixel capacitance) no such light reaches has exactly
the same pixels with and without persistence, hence exactly the same fit:
De = 0.  With star light persisting, the persistence of a final can only be
non-zero on the pixels that some star of an earlier exposure lit, the union
of those stars' stamps (:func:`reach_mask`), and only the galaxies there
(:func:`candidate_rows`) need pixels; with every object's light persisting,
nearly every galaxy's stamp is reached and all of them are simulated.  Only
their pixels are simulated (:func:`render_final`): the detector's noise
blocks that their stamps reach (:data:`perscli.detector.blocks.NOISE_BLOCK`),
with every object whose light reaches those blocks.  Because each pixel's
noise is keyed on its block and each pixel is the sum of the same stamps in
the same order, those pixels are the very bits a whole-frame render gives:
the differential result is the full result, not an approximation of it
(tests/test_differential.py checks this galaxy by galaxy).

The final's file holds the reference (no persistence) in SCI, and one image
per variant (persistence model and source) holding only the stamps it
changed, NaN elsewhere, with a CHANGED table of which galaxies changed in
which variant; :func:`perscli.study.changes.measure_changes` fits those.
"""

from __future__ import annotations

import functools
import hashlib

import logging
import os
from dataclasses import dataclass, field

import fitsio
import numpy as np

from .. import PerscliError
from ..detector.blocks import NOISE_BLOCK, BlockStack
from ..detector.chain import iter_chains
from ..detector.effects import Persistence
from ..detector.model import DetectorModel
from ..detector.persistence import order_earlier, persistence_charge
from ..io.cards import format_card
from ..io.fitsfile import OutHDU, table_hdu
from ..io.frames import SECONDS_PER_DAY
from ..io.output import check_output, write_hdus
from ..io.tables import read_table
from ..measure.settings import MeasureOptions
from ..optics import Optics
from ..render.cards import _exposure_cards, _model_hdu, _provenance, _wcs_cards
from ..render.exposure import Exposure, draw_sources, plan_objects, read_truth
from ..render.run import crop, pad_to, persisting_fluence, simulation_area
from .reach import (IPC_REACH, WINDOW_MARGIN, _active_blocks, _clip_keep, _objects_reaching, galaxy_positions,
                    persisting_stars, stamp_sides, window_boxes)

log = logging.getLogger(__name__)


#: the light of earlier exposures drawn by :func:`object_light`, kept for the next final of the same detector
#: (which shares all but one of its earlier exposures): key -> float32 image
_LIGHT: dict = {}
_LIGHT_SIZE = 12
_TRUTH: dict = {}

#: the persistence sources a differential study can draw from the catalogue, and the image of a frame each is
LIGHT_SOURCES = {"drawn": "DRAWN", "stars": "STARFLU"}


def _truth_columns(truth: str, filter_name: str) -> dict:
    """The catalogue's columns for a filter, read once per process and file (size and time keyed)."""
    st = os.stat(truth)
    key = (os.path.realpath(truth), st.st_size, st.st_mtime_ns, filter_name)
    if key not in _TRUTH:
        if len(_TRUTH) >= 4:
            _TRUTH.pop(next(iter(_TRUTH)))
        _TRUTH[key] = read_truth(truth, filter_name)
    return _TRUTH[key]


def _light_key(truth: str, exposure: Exposure, source: str, floor: float, region=None):
    st = os.stat(truth)
    where = None if region is None else (region.area, hashlib.sha1(region.blocks.tobytes()).hexdigest())
    return (os.path.realpath(truth), st.st_size, st.st_mtime_ns, exposure.sca, exposure.expid, exposure.mjd,
            exposure.filter, exposure.full_bounds, source, float(floor) if source == "stars" else 0.0, where)


@dataclass(frozen=True)
class Region:
    """Where a task needs the light of its exposures: noise blocks (:func:`perscli.detector.blocks.block_grid`
    of ``area``) that some final's simulated stamps reach; the light is exact there, 0 where no object
    reaching them is drawn."""

    area: tuple
    blocks: np.ndarray = field(compare=False)


def final_blocks(cols: dict, exposure: Exposure, rows, stamp: int):
    """The noise blocks a final's simulation needs: (simulation area, active blocks of it, windows, galaxies)."""
    optics = Optics(exposure)
    bounds = exposure.full_bounds
    area = simulation_area(bounds)
    rows = np.zeros(len(cols["ra"]), dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
    gal, gx, gy = galaxy_positions(cols, optics, bounds, stamp)
    keep = rows[gal]
    gal, gx, gy = gal[keep], gx[keep], gy[keep]
    sides = stamp_sides(cols, gal, stamp)
    windows = _clip_keep(window_boxes(gx, gy, sides), bounds)
    active = _active_blocks(window_boxes(gx, gy, sides, WINDOW_MARGIN + IPC_REACH), area)
    return area, active, windows, gal


def _keep(key, light) -> None:
    _LIGHT[key] = light
    while len(_LIGHT) > _LIGHT_SIZE:
        _LIGHT.pop(next(iter(_LIGHT)))


def remember_light(truth: str, exposure: Exposure, source: str, light: np.ndarray, region=None) -> None:
    """Keep a frame's drawn light, drawn elsewhere, as :func:`object_light` would return it."""
    _keep(_light_key(truth, exposure, source, 0.0, region), light)


def object_light(truth: str, exposure: Exposure, source: str = "drawn", floor: float = 0.0,
                 region: Region | None = None) -> np.ndarray:
    """The expected electrons of the catalogue's objects on an exposure's frame, as render writes them.

    What an earlier exposure leaves, drawn here from the catalogue rather
    than read from a file, and kept for the next final (a study's earlier
    exposures would be most of its bytes): for ``source`` 'drawn' every
    object (the frame's DRAWN), for 'stars' the stars alone (its STARFLU).
    The same stamps added in the same order as ``perscli render`` adds them,
    in float32 as it writes them: the same bits.  With ``floor`` and the
    stars, only the stars whose light can exceed it (:func:`persisting_stars`)
    are drawn: the same bits wherever the light exceeds ``floor``, what
    persists above it.

    Parameters
    ----------
    truth : str
    exposure : Exposure
    source : {'drawn', 'stars'}
    floor : float
        Electrons (the persistence effect's floor).
    region : Region, optional
        Only the objects whose stamps reach these blocks: the light there is
        the frame's, bit for bit (each pixel the sum of the same stamps in the
        same order); elsewhere it may lack the light of objects that do not
        reach them.  None: the whole frame.
    """
    if source not in LIGHT_SOURCES:
        raise PerscliError(f"persistence source {source!r}: a differential study draws {' or '.join(LIGHT_SOURCES)}")
    key = _light_key(truth, exposure, source, floor, region)
    if key in _LIGHT:
        _LIGHT[key] = _LIGHT.pop(key)        # most recently used last
        return _LIGHT[key]
    cols = _truth_columns(truth, exposure.filter)
    optics = Optics(exposure)
    known = {}          # the catalogue's positions on this frame, worked out once for both plans
    plan = plan_objects(cols, optics, exposure.full_bounds, known)
    reaching = None
    if region is not None:
        reaching = _objects_reaching(plan_objects(cols, optics, region.area, known), region.blocks, region.area)
    if source == "drawn":
        light = draw_sources(cols, exposure, optics=optics, plan=plan, only=reaching)[0].astype(np.float32)
    else:
        only = cols["kind"] == "star"
        if reaching is not None:
            only = only & reaching
        if floor > 0:
            todo, x, y, flux, sizes = plan
            stars = todo[only[todo]]
            ix = np.floor(x[stars] + 0.5).astype(np.int64)
            iy = np.floor(y[stars] + 0.5).astype(np.int64)
            n = sizes[stars]
            boxes = np.stack([ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1], axis=1)
            keep = np.zeros_like(only)
            keep[stars[persisting_stars(flux[stars], boxes, floor)]] = True
            only = keep
        light = draw_sources(cols, exposure, stars=True, optics=optics, plan=plan, only=only,
                             image=False)[3].astype(np.float32)
    _keep(key, light)
    return light


def history_charges(truth: str, final: Exposure, histories, laws: dict, blocks=None, area=None,
                    region: Region | None = None, lazy: bool = False) -> dict:
    """The persistence charge that the light of ``histories`` leaves in ``final``, per law.

    The computation of ``perscli render --previous`` with the earlier
    frames' DRAWN or STARFLU (:func:`perscli.render.run.history_persistences`),
    on their light drawn here (:func:`object_light`).

    Parameters
    ----------
    laws : dict
        Name -> (PersistenceModel, source, threshold, cap, floor); source 'drawn' or 'stars'.
    blocks : perscli.detector.blocks.BlockStack, optional
        Only these noise blocks of ``area`` (the simulation area around the
        final's frame): the charge as a stack of them.  The law is per pixel,
        so a block's values are the whole frame's there.
    area : (x0, x1, y0, y1)
        With ``blocks``.
    region : Region, optional
        The earlier exposures' light drawn only where the task's finals need it
        (:func:`object_light`): it must cover ``blocks``.
    lazy : bool
        Each law's charge as a function computing it when called (the
        earlier exposures' light drawn once for all): a caller running the
        laws one after the other then holds one charge at a time.

    Returns
    -------
    dict
        Name -> electrons per pixel of the final's frame (or the stack of
        ``blocks``), or None when no earlier exposure counts for that law;
        with ``lazy``, a function returning it.
    """
    histories = list(histories)
    for h in histories:
        if h.full_bounds != final.full_bounds or h.sca != final.sca:
            raise PerscliError(f"earlier exposure {h.expid}: not the frame of final {final.expid} (SCA {h.sca}, "
                               f"bounds {h.full_bounds})")
    ends = [(h.end - final.mjd) * SECONDS_PER_DAY for h in histories]
    window = (final.end - final.mjd) * SECONDS_PER_DAY
    names = [f"earlier exposure {h.expid}" for h in histories]
    bounds = final.full_bounds
    lights, charges = {}, {}

    def light(i, source, floor):
        key = (i, source, floor if source == "stars" else 0.0)
        if key not in lights:
            value = object_light(truth, histories[i], source, floor, region)
            # only the blocks simulated: the law on a few per cent of the frame
            lights[key] = value if blocks is None else \
                blocks.gather(value, fill=0.0, dtype=np.float32, at=(bounds[2] - area[2], bounds[0] - area[0]))
        return lights[key]

    def fluence(i, source, threshold, cap, floor, scratch):
        # made when the law uses it, in one scratch array: fresh frames cost more in page faults than the law
        return lambda: persisting_fluence(light(i, source, floor), 1.0, threshold=threshold, cap=cap, floor=floor,
                                          out=scratch)

    def charge(pmodel, source, threshold, cap, floor, keep):
        shape = light(keep[0], source, floor).shape
        scratch = np.empty(shape, dtype=np.float32)
        # exposures beyond the law's look-back or count are left out by persistence_charge: never called
        fluences = [fluence(i, source, threshold, cap, floor, scratch) for i in range(len(histories))]
        return persistence_charge(fluences, ends, 0.0, window, pmodel)[0]

    for name, (pmodel, source, threshold, cap, floor) in laws.items():
        keep, _ = order_earlier(ends, 0.0, pmodel, names)
        if not histories or not keep:
            charges[name] = None
        elif lazy:
            charges[name] = functools.partial(charge, pmodel, source, threshold, cap, floor, keep)
        else:
            charges[name] = charge(pmodel, source, threshold, cap, floor, keep)
    return charges


#: below this fraction of active blocks the chain runs on the stack of them rather than on the whole area
STACK_FRACTION = 0.6


def _simulate(sources, models, charges, *, exposure, seed, sky_rate, active, area, blocks=None):
    """Every model's SCI over ``area`` (NaN outside the active blocks), one model at a time.

    With ``blocks`` (few active blocks), the chain runs on the stack of them
    (:class:`perscli.detector.blocks.BlockStack`; ``charges`` are stacks
    too) and the result is put back in the area; noise is keyed on blocks,
    so each pixel is the bits the whole area gives.

    Yields
    ------
    (name, (sci, unit, sky_rate))
        In the order of ``models``.
    """
    if blocks is None:
        for name, r in iter_chains(sources, models, exptime=exposure.exptime, seed=seed, sky_rate=sky_rate,
                                   persistence=charges, origin=(area[0], area[2]), active=active, frames=False):
            yield name, (r.sci, r.unit, r.sky_rate)
            del r
        return
    for name, r in iter_chains(blocks.gather(sources), models, exptime=exposure.exptime, seed=seed,
                               sky_rate=sky_rate, persistence=charges, origin=(area[0], area[2]), blocks=blocks,
                               frames=False):
        yield name, (blocks.scatter(r.sci, dtype=np.float32), r.unit, r.sky_rate)
        del r


def render_final(truth: str, exposure: Exposure, dest: str, *, model: DetectorModel, variants: dict, seed: int,
                 histories=(), rows=None, stamp: int = MeasureOptions.stamp, compress: str = "gzip", overwrite: bool = False,
                 pixels: dict | None = None, keep_light: bool = False, region: Region | None = None) -> dict:
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
        one image per variant (:func:`variant_extname`)
        holding the stamps it changed (NaN elsewhere); MODEL (the
        reference's detector model); CHANGED (id, and per variant whether
        it changed that galaxy's stamp).
    model : DetectorModel
        The reference's detector model.
    variants : dict
        Variant name -> DetectorModel: the model with its persistence law and
        source (:data:`LIGHT_SOURCES`: light drawn from the catalogue).
    seed : int
        The frame's seed: the reference and every variant share its noise.
    histories : sequence of Exposure
        The earlier exposures of the same frame: their light persists
        (:func:`history_charges`).
    rows : ndarray of bool, optional
        Per catalogue row: the galaxies whose stamps to simulate (default: none).
    stamp : int
        The largest stamp ``perscli measure`` cuts.
    compress, overwrite
        As for :func:`perscli.render.run.render_file`.
    pixels : dict, optional
        Filled with the images and the CHANGED table as arrays (``SCI``, each
        variant's EXTNAME, ``CHANGED``) for a caller that measures them right
        away.
    keep_light : bool
        Draw every object of ``region`` and keep its drawn light
        (:func:`object_light`'s cache) for later finals of the same detector:
        when this final is an earlier exposure of others to come.
    region : Region, optional
        Where the task's finals need light (:func:`final_blocks` of each,
        joined): earlier exposures are drawn there only.  None: the whole frame.

    Returns
    -------
    dict
        rows simulated, objects drawn, active blocks and their fraction, and
        per variant the galaxies changed.
    """
    check_output(dest, overwrite=overwrite, inputs=[truth])
    cols = _truth_columns(truth, exposure.filter)
    _check_light_sources(variants)
    optics = Optics(exposure)
    area, active, windows, gal = final_blocks(cols, exposure, rows, stamp)
    if region is not None and (region.area != area or np.any(active & ~region.blocks)):
        raise PerscliError("render_final: the region does not cover the final's stamps")
    drawn, sources = _draw_final(truth, exposure, cols, optics, area, active, keep_light=keep_light, region=region)
    charges, blocks = _final_charges(truth, exposure, histories, variants, active, sources.shape, area, region)
    final = _final_pixels(sources, {"": model, **variants}, charges, exposure=exposure, seed=seed,
                          sky_rate=optics.sky_rate, active=active, area=area, blocks=blocks, windows=windows[1],
                          keep_frames=pixels is not None)
    ids = np.asarray(cols["id"])[gal[windows[0]]].astype(np.int64)
    nobj = int(np.count_nonzero(drawn))
    out = _final_hdus(final, ids, exposure, optics, model, variants, seed=seed, active=active, nobj=nobj)
    _final_provenance(out[0], truth, cols["datasum"], exposure, model, seed, final.sky_rate, nobj, histories)
    write_hdus(out, dest, overwrite=overwrite, compress=compress)
    if pixels is not None:
        ref_full = np.where(final.inside, final.ref32, np.float32(np.nan))
        changed = {"id": ids, **{variant_extname(n): final.changed[n] for n in variants}}
        pixels.update({"SCI": ref_full, "CHANGED": changed,
                       **{variant_extname(n): final.var_full[n] for n in variants}})
    return {"rows": int(len(windows[0])), "objects": nobj, "blocks": int(active.sum()),
            "block_fraction": float(active.mean()) if active.size else 0.0,
            "changed": {n: int(c.sum()) for n, c in final.changed.items()}}


def _check_light_sources(variants: dict) -> None:
    """Refuse a variant whose persistence source is not light drawn from the catalogue (:data:`LIGHT_SOURCES`)."""
    for name, vm in variants.items():
        source = Persistence.fluence_input(vm)[0]
        if source not in LIGHT_SOURCES:
            raise PerscliError(f"variant {name}: a differential render draws what persists from the catalogue: "
                               f"persistence.source {' or '.join(LIGHT_SOURCES)}, not {source}")


def _draw_final(truth: str, exposure: Exposure, cols: dict, optics, area, active, *, keep_light: bool,
                region: Region | None) -> tuple:
    """The objects of a final drawn over ``area``: those whose light reaches the ``active`` blocks.

    With ``keep_light``, every object of ``region`` (or of the frame) is
    drawn and the frame's light kept (:func:`remember_light`).

    Returns
    -------
    (ndarray of bool, ndarray)
        Per catalogue row: drawn; and the electrons of the objects over ``area``.
    """
    plan = plan_objects(cols, optics, area)
    drawn = _objects_reaching(plan, active, area)
    if keep_light:
        # every object of the region drawn, not only those reaching the stamps: the frame's DRAWN is then a
        # crop of the same sums there, kept for the later finals whose earlier exposure this one is
        drawn = _objects_reaching(plan, region.blocks, area) if region is not None else np.isin(
            np.arange(len(drawn)), plan[0])
    sources = draw_sources(cols, exposure, optics=optics, plan=plan, bounds=area, only=drawn)[0] \
        if active.any() or keep_light else np.zeros((area[3] - area[2] + 1, area[1] - area[0] + 1))
    if keep_light:
        remember_light(truth, exposure, "drawn", crop(sources, area, exposure.full_bounds).astype(np.float32), region)
    return drawn, sources


def _final_charges(truth: str, exposure: Exposure, histories, variants: dict, active, shape, area,
                   region: Region | None) -> tuple:
    """Each variant's persistence charge from ``histories`` (:func:`history_charges`), made lazily.

    Returns
    -------
    (dict, BlockStack or None)
        Variant -> a callable giving its charge (or None), empty without
        histories or active blocks; and the stack of the active blocks the
        chain runs on (None: the whole area, :data:`STACK_FRACTION`).
    """
    charges = {}
    blocks = BlockStack.of(active, (area[0], area[2]), shape) \
        if active.any() and active.mean() <= STACK_FRACTION else None
    if active.any() and histories:
        laws = {name: (vm.persistence_model(), *Persistence.fluence_input(vm), Persistence.floor(vm))
                for name, vm in variants.items()}
        # each law's charge made when its chain needs it, and dropped with its frame: one at a time in memory
        charges = history_charges(truth, exposure, histories, laws, blocks, area, region, lazy=True)
        if blocks is None:
            bounds = exposure.full_bounds
            charges = {name: charge if charge is None else
                       (lambda charge=charge: pad_to(charge(), bounds, area)) for name, charge in charges.items()}
    return charges, blocks


@dataclass
class _FinalPixels:
    """A final's reference and variants on its galaxies' windows (:func:`_final_pixels`)."""

    unit: str               # of the frame's pixels
    sky_rate: float         # [e-/pixel/s] the sky background used
    inside: np.ndarray      # (ny, nx) bool: the frame's pixels inside a window
    ref32: np.ndarray       # (ny, nx) the reference frame, float32 (as written)
    windows: np.ndarray     # (n, 4) each galaxy's window: x0, x1, y0, y1 (detector pixels, inclusive)
    wx0: np.ndarray         # first column of each window (0-indexed, frame array)
    wy0: np.ndarray         # first row of each window
    wnx: np.ndarray         # columns of each window
    wny: np.ndarray         # rows of each window
    offsets: np.ndarray     # (n + 1) first pixel of each window in ``ref_pix``, then their total
    ref_pix: np.ndarray     # the reference's pixels of the windows, one window after the other, row by row
    changed: dict           # variant -> per window: whether the variant changed a pixel of it
    deltas: dict            # variant -> its pixels of the windows minus the reference's (float32 when exact)
    var_full: dict          # variant -> its frame, NaN outside the windows it changed (with ``keep_frames``)


def _final_pixels(sources, models: dict, charges: dict, *, exposure: Exposure, seed: int, sky_rate, active, area,
                  blocks, windows, keep_frames: bool) -> _FinalPixels:
    """Simulate the reference (``models['']``) and every variant, and compare them on the windows.

    Parameters
    ----------
    sources, charges, seed, sky_rate, active, area, blocks
        As :func:`_simulate`.
    models : dict
        '' -> the reference's model, then variant -> its model.
    windows : ndarray
        (n, 4): each galaxy's window, x0, x1, y0, y1 (:func:`final_blocks`).
    keep_frames : bool
        Also keep each variant's frame (``var_full``).

    Returns
    -------
    _FinalPixels
    """
    bounds = exposure.full_bounds
    xmin, _, ymin, _ = bounds
    results = _simulate(sources, models, charges, exposure=exposure, seed=seed, sky_rate=sky_rate,
                        active=active, area=area, blocks=blocks)
    name, (ref, unit, frame_sky) = next(results)
    assert name == ""
    ref = crop(ref, area, bounds)
    inside = np.zeros(ref.shape, dtype=bool)
    for x0, x1, y0, y1 in windows:
        inside[y0 - ymin:y1 - ymin + 1, x0 - xmin:x1 - xmin + 1] = True
    if np.any(inside & ~np.isfinite(ref)):          # pragma: no cover - the blocks cover the windows
        raise PerscliError("render_final: a stamp reaches pixels that were not simulated")
    ref32 = ref.astype(np.float32)
    # each galaxy's window of the frame (0-indexed array coordinates), one after the other
    win = windows
    wx0, wy0 = win[:, 0] - xmin, win[:, 2] - ymin
    wnx, wny = win[:, 1] - win[:, 0] + 1, win[:, 3] - win[:, 2] + 1
    offsets = np.concatenate([[0], np.cumsum(wnx * wny)]).astype(np.int64)

    def cut(image):
        if not len(win):
            return np.zeros(0, dtype=image.dtype)
        return np.concatenate([image[y:y + h, x:x + w].ravel() for x, y, w, h in zip(wx0, wy0, wnx, wny)])

    ref_pix = cut(ref32)
    changed, deltas, var_full = {}, {}, {}
    for name, (sci, _, _) in results:
        sci = crop(sci, area, bounds)
        # only the windows' pixels are converted (as written: float32), not the frame's
        pix = cut(sci).astype(np.float32)
        # a stamp changed when any of its pixels differs from the reference's (every window holds a pixel)
        flags = np.logical_or.reduceat(pix != ref_pix, offsets[:-1]) if len(win) else np.zeros(0, dtype=bool)
        d = pix.astype(np.float64) - ref_pix.astype(np.float64)
        d32 = d.astype(np.float32)
        changed[name], deltas[name] = flags, d32 if np.array_equal(d32, d) else d
        if keep_frames:
            keep = np.zeros(ref.shape, dtype=bool)
            for x0, x1, y0, y1 in win[flags]:
                keep[y0 - ymin:y1 - ymin + 1, x0 - xmin:x1 - xmin + 1] = True
            var_full[name] = np.where(keep, sci.astype(np.float32), np.float32(np.nan))
        del sci, pix
    return _FinalPixels(unit=unit, sky_rate=frame_sky, inside=inside, ref32=ref32, windows=win, wx0=wx0, wy0=wy0,
                        wnx=wnx, wny=wny, offsets=offsets, ref_pix=ref_pix, changed=changed, deltas=deltas,
                        var_full=var_full)


def _final_hdus(final: _FinalPixels, ids, exposure: Exposure, optics, model: DetectorModel, variants: dict, *,
                seed: int, active, nobj: int) -> list:
    """A final's file: primary, SCI (the reference's header), MODEL, STAMPS, REFPIX and one D_ image per variant.

    ``ids``: the catalogue id of each window's galaxy; ``nobj``: the objects drawn.
    """
    xmin, xmax, ymin, ymax = exposure.full_bounds
    gain = model.value("gain", "gain", off=1.0)
    common = _wcs_cards(optics, exposure.full_bounds)
    frame_cards = common + _exposure_cards(exposure, optics, seed, final.unit, gain) + [
        format_card("SKYRATE", final.sky_rate, "[e-/pixel/s] sky background used"),
        format_card("NOBJ", nobj, "objects drawn (those reaching the stamps)")]
    region = [format_card("REGION", "stamps", "only the stamps of galaxies persistence can reach"),
              format_card("NBLOCKS", int(active.sum()), f"noise blocks ({NOISE_BLOCK} px) simulated"),
              format_card("FBLOCKS", round(float(active.mean()) if active.size else 0.0, 6),
                          "fraction of the blocks simulated"),
              format_card("FRAMENX", int(xmax - xmin + 1), "[pixel] columns of the frame (pixels in REFPIX)"),
              format_card("FRAMENY", int(ymax - ymin + 1), "[pixel] rows of the frame")]
    out = [OutHDU([format_card("SIMPLE", True), format_card("BITPIX", 8), format_card("NAXIS", 0),
                   format_card("EXTEND", True)])]
    out.append(OutHDU(frame_cards + region + [
        format_card("CONTENT", "the reference's header", "pixels: REFPIX at the STAMPS windows")],
        None, extname="SCI"))
    out.append(_model_hdu(model))
    table = {"id": ids, "x0": final.wx0.astype(np.int32), "y0": final.wy0.astype(np.int32),
             "nx": final.wnx.astype(np.int32), "ny": final.wny.astype(np.int32), "offset": final.offsets[:-1],
             **{variant_extname(n): final.changed[n].astype(np.int16) for n in variants}}
    out.append(table_hdu(table, STAMPS_EXTNAME, descriptions={
        "id": "catalogue id of a galaxy simulated", "x0": "first column of its window (0-indexed, frame array)",
        "y0": "first row of its window", "nx": "columns of the window", "ny": "rows of the window",
        "offset": "first pixel of the window in REFPIX and the D_ images (row by row)",
        **{variant_extname(n): f"1: variant {n} changed a pixel of the window" for n in variants}}))
    out.append(OutHDU([format_card("BUNIT", final.unit),
                       format_card("CONTENT", "reference pixels of the STAMPS windows", "no persistence")],
                      final.ref_pix, extname=REF_EXTNAME))
    for name, vm in variants.items():
        pm = vm.persistence_model()
        out.append(OutHDU([format_card("BUNIT", final.unit),
                           format_card("CONTENT", f"variant {name} minus the reference", "STAMPS windows"),
                           format_card("VARIANT", name), format_card("PS_LAW", pm.name[-68:], "persistence law"),
                           format_card("PS_FLOOR", Persistence.floor(vm), "[e-] fluence at or below leaves nothing"),
                           format_card("NCHANGED", int(final.changed[name].sum()), "galaxies whose stamps changed")],
                          final.deltas[name], extname=delta_extname(name)))
    return out


def _final_provenance(primary: OutHDU, truth: str, truth_datasum, exposure: Exposure, model: DetectorModel,
                      seed: int, sky_rate, nobj: int, histories) -> None:
    """A final's provenance (:func:`perscli.render.cards._provenance`) and its earlier exposures (NPREV, PRVnnID)."""
    _provenance(primary, truth, truth_datasum, exposure, model, seed, [], [], {}, sky_rate, nobj, ("SCI",))
    primary["NPREV"] = (len(histories), "earlier exposures whose light persists")
    for k, h in enumerate(histories, 1):
        if k <= 99:
            primary[f"PRV{k:02d}ID"] = (int(h.expid), f"earlier exposure, ended MJD {h.end:.6f}")


#: a final's table of the galaxies' windows, and its 1-D images of their pixels
STAMPS_EXTNAME = "STAMPS"
REF_EXTNAME = "REFPIX"


def variant_extname(variant: str) -> str:
    """The image HDU of a final's file that holds a variant ('stars-typical' -> 'STARS-TYPICAL')."""
    return variant.upper()


def delta_extname(variant: str) -> str:
    """The 1-D image of a final's file holding a variant's change in the windows: 'D_DRAWN-TYPICAL'."""
    return "D_" + variant_extname(variant)


def read_stamps(path: str, variants=(), pixels: bool = True) -> dict:
    """A final's windows (:func:`render_final`): their table, the reference's pixels, each variant's change.

    With ``pixels`` False only the table is read (which galaxies each
    variant changed), and 'path' says where the pixels are.

    Returns
    -------
    dict
        'table' (column arrays of STAMPS), 'ref' (1-D), 'deltas' (variant -> 1-D), as stored; 'path'.
    """
    table = read_table(f"{path}[{STAMPS_EXTNAME}]", what="the windows of a study's final")
    names = {n.upper(): n for n in table.names}
    cols = {k: table.column(k, kind="integer") for k in ("id", "x0", "y0", "nx", "ny", "offset")}
    for v in variants:
        if variant_extname(v) not in names:
            raise PerscliError(f"{path}: its {STAMPS_EXTNAME} table has no column {variant_extname(v)} (variant {v})")
        cols[variant_extname(v)] = table.column(names[variant_extname(v)], kind="integer")
    out = {"table": cols, "deltas": {}, "path": path}
    if not pixels:
        return out

    with fitsio.FITS(path) as f:
        out["ref"] = f[REF_EXTNAME].read() if len(cols["id"]) else np.zeros(0, dtype=np.float32)
        for v in variants:
            out["deltas"][v] = f[delta_extname(v)].read() if len(cols["id"]) else np.zeros(0, dtype=np.float32)
    return out


def stamp_windows(stored: dict, key: str, wanted: dict):
    """Sub-windows of a final's stored windows: {galaxy id: (b0, b1, a0, a1)} -> {(b0, b1, a0, a1): pixels}.

    ``key`` is 'ref' or a variant.  Each wanted window must lie inside its
    galaxy's stored one (render's windows are measure's stamps grown by a
    margin).
    """
    t = stored["table"]
    flat = stored["ref"] if key == "ref" else stored["deltas"][key]
    where = {int(i): k for k, i in enumerate(t["id"])}
    out = {}
    for gid, (b0, b1, a0, a1) in wanted.items():
        k = where.get(int(gid))
        if k is None:
            raise PerscliError(f"galaxy {gid}: no window of it in the final's {STAMPS_EXTNAME} table")
        x0, y0, nx, ny, off = (int(t[c][k]) for c in ("x0", "y0", "nx", "ny", "offset"))
        if a0 < x0 or a1 > x0 + nx or b0 < y0 or b1 > y0 + ny:
            raise PerscliError(f"galaxy {gid}: measure's stamp [{a0}:{a1}, {b0}:{b1}] is not inside the window the "
                               f"final kept [{x0}:{x0 + nx}, {y0}:{y0 + ny}]")
        block = flat[off:off + nx * ny].reshape(ny, nx)
        out[(b0, b1, a0, a1)] = block[b0 - y0:b1 - y0, a0 - x0:a1 - x0]
    return out
