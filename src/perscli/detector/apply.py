"""Persistence of earlier exposures on a frame: add, subtract or predict it.

This is the frame-level driver behind ``perscli apply-persistence``: it
orders the earlier exposures by their timestamps, works out the exact
time factor of each (or GalSim's approximation), streams their fluence
through :func:`perscli.detector.persistence.accumulate` block of rows by
block of rows, all earlier frames side by side, and builds the output file
with the input's structure and units.  Memory is the output frame plus one
block per input, whatever the number of earlier frames.

Frames need not cover the same pixels: each is placed on the detector
through LTV1/LTV2 (detector pixel = image pixel - LTV, FITS 1-indexed; see
:meth:`perscli.io.frames.Frame.placement`), so a subarray and a full frame,
or two subarrays, share the detector pixels they both cover.  Persistence
flows only from the pixels an earlier frame saw light on to the pixels of
the current frame they coincide with; reference pixels (the 5-pixel border
of WFC3-IR raw/ima frames) neither give nor receive any.
The checks of earlier exposures and their placement (:func:`overlap`,
:func:`check_earlier`) live in :mod:`perscli.detector.earlier`.

Besides the science data, a correction carries its uncertainty and flags:
in subtract mode the ERR extension, when the input has one with data, grows
in quadrature by ``model_error`` times the persistence subtracted (in
predict mode ERR becomes that uncertainty), and with ``flag_above`` a DQ
bit marks the pixels whose persistence, averaged over the exposure,
exceeds that many electrons per second (WFC3's advice: 0.01 e-/s).
"""

from __future__ import annotations

import logging
import math
import re
import threading
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError, _kernels
from ..executor import thread_map
from ..io.cards import format_card
from ..io.checksum import ones_complement_add
from ..io.fitsfile import OutHDU
from ..io.frames import SECONDS_PER_DAY, UNITS, Frame, assign_sequence_timing, open_frame, require_timing
from ..io.output import add_provenance, check_output, write_hdus
from .persistence import (PersistenceModel, accumulate, beyond_lookback, exposure_time_factors, order_earlier,
                          round_charge)
from .settings import DEFAULT_DQ_BIT, DEFAULT_MODEL_ERROR, MODES, ApplyOptions

from .earlier import Overlap, _check_detector, _check_start, _detector, overlap

log = logging.getLogger(__name__)

#: keywords written by :func:`provenance`
_PROVENANCE_KEY = re.compile(r"^(PS(MODE|MODEL|KIND|TIME|COMB|MAXPRV|LOOKB|NPREV|UNIT|CUR|CURDS|MERR|FLAG|DQBIT"
                             r"|NFLAG)|PS_\w+|PSCOEF\d+|PSP\d+\w*)$")

#: rows per block: 64 rows of a 4088-pixel frame are 2 MB of float64, which stays in cache
BLOCK_ROWS = 64


@dataclass
class EarlierExposure:
    """What one earlier exposure contributed."""

    frame: Frame = field(repr=False)
    name: str
    recency: int          # 0 = most recent
    gap: float            # seconds from its end to the start of the current exposure
    factors: list         # time factor (s) or linear coefficient, one per output plane
    datasum: int = 0
    nonfinite: int = 0
    overlap: Overlap | None = None   # where it falls on the current frame (None: the same pixels)


@dataclass
class PersistencePlan:
    """Which earlier exposures count, and with which time factors."""

    current: Frame
    used: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    science: tuple | None = None   # the current frame's light-sensitive pixels (y0, y1, x0, x1); None: all


@dataclass
class PersistenceResult:
    """Summary of a run: the exposures used and the persistence added, in electrons."""

    used: list
    skipped: list
    max_electrons: float = 0.0     # largest persistence in the last plane
    total_electrons: float = 0.0   # sum over the last plane
    flagged: int = 0               # pixels flagged in DQ (with flag_above)


def _plane_ends(current: Frame) -> np.ndarray:
    """Seconds from the start of the current exposure to the end of each output plane."""
    if current.is_ramp:
        return np.asarray(current.read_times, dtype=np.float64)
    return np.array([(current.end - current.start) * SECONDS_PER_DAY])


def plan(current: Frame, previous, model: PersistenceModel) -> PersistencePlan:
    """Check the earlier exposures, place them, order them by time and work out their time factors.

    Parameters
    ----------
    current : Frame
        The exposure that receives persistence (an image or a ramp).
    previous : iterable of Frame
        Earlier exposures of the same detector, in any order, covering the
        same pixels or any others that overlap (placed with :func:`overlap`).
    model : PersistenceModel
        The law and its settings: time_model ('exact': the integral of the
        rate over the current exposure's own [start, end], or up to each read
        of a ramp, with t counted from the end of each earlier exposure;
        'middle': the rate at the middle of that window times its length, as
        STScI's WFC3 pipeline; 'galsim': GalSim's ``rate((0.5 + i) * 139.8 s)
        * 139.8 s`` for the i-th most recent one), max_previous (0: all) and
        lookback (hours; earlier exposures that ended longer before the
        current one starts are ignored, with a note at -v; 0: no limit);
        :meth:`~perscli.detector.persistence.PersistenceModel.with_settings`
        replaces them.

    Returns
    -------
    PersistencePlan
    """
    previous = list(previous)
    require_timing(current)
    if not current.is_ramp and previous and not current.end > current.start:
        # persistence is integrated over the current exposure: over 0 s it is 0, and the output would
        # silently be the input (EXPSTART = EXPEND, or MJDs so large that 100 s do not change them)
        raise PerscliError(f"{current.label}: the exposure lasts 0 s ({current.timing_source}: start = end = "
                           f"MJD {current.start!r}): no persistence can fall on it; fix the timing keywords, or "
                           "give --gap SECONDS (and --exptime SECONDS)")
    overlaps = []
    for prev in previous:
        require_timing(prev)
        _check_detector(prev, current.label, _detector(current), current.keyword("INSTRUME"))
        overlaps.append(overlap(prev, current))
        _check_start(prev, current.label, current.start)
    ends = [f.end for f in previous]
    keep, left = order_earlier(ends, current.start, model, [f.label for f in previous],
                               unit_seconds=SECONDS_PER_DAY)
    science = current.placement().science
    full = (0, current.shape[0], 0, current.shape[1])
    result = PersistencePlan(current=current, skipped=[previous[i].label for i in left],
                             science=None if science == full else science)
    old = set(beyond_lookback(ends, current.start, model, unit_seconds=SECONDS_PER_DAY))
    for i in left:
        if i in old:
            log.info("%s ended %.1f h before %s starts, beyond the %g h look-back: ignored", previous[i].label,
                     (current.start - ends[i]) * 24.0, current.label, model.lookback)
    capped = [previous[i].label for i in left if i not in old]
    if capped:
        log.info("only the %d most recent earlier exposures count; ignoring %s", len(keep), ", ".join(capped))
    if previous and not keep:
        log.warning("%s: no earlier exposure ended within the %g h look-back: no persistence", current.label,
                    model.lookback)
    plane_ends = _plane_ends(current)
    for recency, i in enumerate(keep):
        prev = previous[i]
        gap = (current.start - prev.end) * SECONDS_PER_DAY
        try:
            factors = exposure_time_factors(gap, plane_ends, recency, model, label=prev.label)
        except PerscliError as exc:
            raise PerscliError(f"{current.label}: {exc}" if not str(exc).startswith(prev.label) else str(exc)) from None
        if factors is None:
            log.info("%s: beyond the linear model's %d coefficients; ignored", prev.label, len(model.coefficients))
            result.skipped.append(prev.label)
            continue
        where = overlaps[i]
        if not where.same_pixels:
            y0, y1, x0, x1 = where.box
            log.info("%s lies on %s's pixels x %d-%d, y %d-%d (LTV1/LTV2: its pixel 1,1 is %s's %d,%d); "
                     "persistence flows there only", prev.label, current.label, x0 + 1, x1, y0 + 1, y1,
                     current.label, 1 - where.shift[1], 1 - where.shift[0])
        result.used.append(EarlierExposure(frame=prev, name=prev.name, recency=recency, gap=gap, factors=factors,
                                           overlap=where))
    return result


def map_blocks(the_plan: PersistencePlan, model: PersistenceModel, consume, *, block_rows: int = BLOCK_ROWS,
               workers: int = 1, progress=None) -> list:
    """Compute the persistence block of rows by block of rows and hand each block to ``consume``.

    Parameters
    ----------
    the_plan : PersistencePlan
    model : PersistenceModel
        Its ``combine`` setting adds up or takes the maximum over earlier exposures.
    consume : callable
        ``consume(r0, r1, electrons)`` with the persistence of rows ``r0:r1``
        in electrons, shape ``(nplanes, r1 - r0, nx)`` (one plane per read of
        a ramp; the array is reused afterwards); its return values are
        returned in block order.
    workers : int
        Threads, each taking whole blocks (reading, the compiled kernel and
        ``consume`` all release the GIL on large arrays).  Inputs that are read
        through CFITSIO (compressed, sections, ramps) are read in one thread.
    progress : callable, optional
        ``progress(done, total)``.

    Notes
    -----
    Every earlier frame that covers the current frame's pixels is read once,
    a block at a time, by the compiled kernel directly from its stored bytes
    where it can; the DATASUM of each is gathered on the way (in any order:
    the ones'-complement sum is commutative) and checked against its header
    at the end.  An earlier frame placed elsewhere on the detector gives
    only to the rows and columns it shares with the current frame (through a
    small buffer, then added or maxed in), and is checksummed whole at the
    end.  The current frame's reference pixels, if any, receive nothing.
    """
    current = the_plan.current
    ny, nx = current.shape
    nplanes = current.nreads
    starts = list(range(0, ny, block_rows))
    local = threading.local()
    nused = len(the_plan.used)
    use_max = model.combine == "max"

    def placed(rec, r0, r1, acc):
        """Add (or max) an earlier frame placed elsewhere on the detector into rows r0:r1 of ``acc``."""
        y0, y1, x0, x1 = rec.overlap.box
        a, b = max(r0, y0), min(r1, y1)
        if a >= b:
            return 0, 0
        dy, dx = rec.overlap.shift
        fluence, scale = rec.frame.fluence_rows(a + dy, b + dy, scratch=True)
        part = np.ascontiguousarray(fluence[:, x0 + dx:x1 + dx])
        own = np.zeros((nplanes, b - a, x1 - x0))
        bad, _ = accumulate(part, own, rec.factors, model, scale=scale, combine=model.combine)
        target = acc[:, a - r0:b - r0, x0:x1]
        if use_max:
            np.maximum(target, own, out=target)
        else:
            target += own
        return bad, 0

    def work(r0):
        r1 = min(ny, r0 + block_rows)
        storage = getattr(local, "storage", None)
        if storage is None:
            storage = local.storage = np.empty(nplanes * min(block_rows, ny) * nx, dtype=np.float64)
        acc = storage[:nplanes * (r1 - r0) * nx].reshape(nplanes, r1 - r0, nx)
        acc.fill(0.0)
        sums = []
        for rec in the_plan.used:
            if rec.overlap is None or rec.overlap.same_pixels:
                # the thread's scratch buffer: the rows are used at once, before the next read
                fluence, scale = rec.frame.fluence_rows(r0, r1, scratch=True)
                sums.append(accumulate(fluence, acc, rec.factors, model, scale=scale, combine=model.combine))
            else:
                sums.append(placed(rec, r0, r1, acc))
        # per pixel: rounding a block of rows is rounding the frame
        round_charge(acc, model.rounding)
        if the_plan.science is not None:
            # reference pixels see no light and hold no charge: they receive no persistence
            y0, y1, x0, x1 = the_plan.science
            acc[:, :max(0, min(r1, y0) - r0)] = 0.0
            acc[:, max(0, y1 - r0):] = 0.0
            acc[:, :, :x0] = 0.0
            acc[:, :, x1:] = 0.0
        return sums, consume(r0, r1, acc)

    threads_ok = all(rec.frame.fluence_is_raw for rec in the_plan.used)
    # threads, not processes: the compiled kernel releases the GIL and the blocks share one frame
    results = thread_map(work, starts, workers=workers if threads_ok else 1, progress=progress)
    for i, rec in enumerate(the_plan.used[:nused]):
        for sums, _ in results:
            bad, dsum = sums[i]
            rec.nonfinite += bad
            rec.datasum = ones_complement_add(rec.datasum, dsum)
        frame = rec.frame
        streamed = rec.overlap is None or rec.overlap.same_pixels
        if frame.fluence_is_raw and streamed:
            rec.datasum = frame.verify(frame.fluence_source, rec.datasum)
        else:
            rec.datasum = frame.datasum(frame.provenance_hdu)
        if rec.nonfinite:
            log.warning("%s: %d non-finite pixels counted as zero fluence", frame.label, rec.nonfinite)
    return [extra for _, extra in results]


def persistence_image(current: Frame, previous, model: PersistenceModel, *, workers: int = 1) -> np.ndarray:
    """The persistence that earlier exposures leave in ``current``, in electrons.

    Parameters are those of :func:`plan` and :func:`map_blocks`.

    Returns
    -------
    ndarray of float64, shape ``(nplanes, ny, nx)``
    """
    the_plan = plan(current, previous, model)
    out = np.zeros((current.nreads,) + current.shape)

    def keep(r0, r1, block):
        out[:, r0:r1] = block

    map_blocks(the_plan, model, keep, workers=workers)
    return out


def _unit_factor(current: Frame, plane: int) -> float:
    """Electrons per unit of the current frame's plane (0 for a read at time zero of a rate ramp)."""
    is_dn, is_rate = UNITS[current.unit]
    if is_rate:
        seconds = current.read_times[plane] if current.is_ramp else current.exptime
        if current.is_ramp and seconds == 0:
            return 0.0
        return current.electrons_per_unit(seconds=seconds)
    return current.electrons_per_unit()


def _check_corrections(model_error, flag_above, dq_bit) -> None:
    if not (isinstance(model_error, (int, float)) and math.isfinite(model_error) and model_error >= 0):
        raise PerscliError(f"--model-error must be a fraction >= 0 (e.g. 0.3 for 30%), not {model_error!r}")
    if flag_above is not None and not (isinstance(flag_above, (int, float)) and math.isfinite(flag_above)
                                       and flag_above >= 0):
        raise PerscliError(f"--flag-above must be a persistence rate >= 0 in e-/s (e.g. 0.01), not {flag_above!r}")
    if isinstance(dq_bit, bool) or not isinstance(dq_bit, (int, np.integer)) or dq_bit < 1 or dq_bit > 2 ** 31 \
            or dq_bit & (dq_bit - 1):
        raise PerscliError(f"--dq-bit must be one DQ flag value, a power of two from 1 to 2147483648 "
                           f"(e.g. 1024), not {dq_bit!r}")


def _section_of(current: Frame, array: np.ndarray) -> np.ndarray:
    """The current frame's image section (if any) of a companion array of the full stored image."""
    if current.section is None:
        return array
    rows, cols = current.section
    return array[..., rows, cols]


def _companion(current: Frame, name: str, ver: int):
    """The ERR or DQ HDU that goes with the science HDU of EXTVER ``ver``, or None."""
    return next((h for h in current.hdus if h.name == name and h.is_image and h.ver == ver), None)


def _err_planes(current: Frame, model_error: float, mode: str):
    """``(hdu index, stored data, plane)`` per output plane for the ERR arrays to update, or None per plane.

    ERR arrays without data (a WFC3 raw file's, where calwf3 has not yet
    computed them) are left as they are.
    """
    if mode == "add" or model_error == 0:
        return []
    full = current.stored_shape
    if current.layout == "cube":
        hdu = next((h for h in current.hdus if h.name == "ERR" and h.is_image), None)
        if hdu is None or not hdu.shape or 0 in hdu.shape:
            return []
        if tuple(hdu.shape) != (current.nreads,) + full:
            raise PerscliError(f"{current.label}: ERR has shape {tuple(hdu.shape)}, not the science cube's "
                               f"{(current.nreads,) + full}: cannot propagate the persistence uncertainty; give "
                               "--model-error 0 to leave ERR as it is")
        data = _section_of(current, hdu.read())
        return [(hdu.index, data, k) for k in range(current.nreads)]
    out = []
    for k in range(current.nreads):
        hdu = _companion(current, "ERR", current.hdus[current.sci[k]].ver)
        if hdu is None or not hdu.shape or 0 in hdu.shape:
            out.append(None)
            continue
        if tuple(hdu.shape) != full:
            raise PerscliError(f"{current.label}: {hdu.label} has shape {tuple(hdu.shape)}, not the science "
                               f"image's {full}: cannot propagate the persistence uncertainty; give "
                               "--model-error 0 to leave ERR as it is")
        out.append((hdu.index, _section_of(current, hdu.read()), None))
    return out


def _dq_targets(current: Frame, dq_bit: int):
    """``{hdu index or ('new', ver): (array, header cards)}``: the DQ arrays a flag goes into.

    Existing DQ arrays keep their integer type (the bit must fit in it); a
    DQ array without data (a WFC3 raw file's constant PIXVALUE) becomes a
    full array; a science HDU without DQ gets one (16-bit like HST's when the
    bit fits, else 32-bit), appended at the end of the file.
    """
    shape = current.shape
    vers = [current.hdus[i].ver for i in current.sci] if current.layout == "wfc3-ramp" \
        else [current.hdus[current.sci[0]].ver]
    targets = {}
    for ver in vers:
        if current.layout == "cube":
            hdu = next((h for h in current.hdus if h.name == "DQ" and h.is_image), None)
        else:
            hdu = _companion(current, "DQ", ver)
        if hdu is None:
            dtype = np.int16 if dq_bit <= 2 ** 14 else np.int32 if dq_bit <= 2 ** 30 else np.uint32
            cards = [format_card("EXTVER", ver, "extension version"),
                     format_card("COMMENT", "data quality flags, made by perscli apply-persistence --flag-above")]
            targets[("new", ver)] = (np.zeros(shape, dtype=dtype), cards)
            continue
        data, _ = hdu.read_copy()
        if data is None:
            value = hdu.header.get("PIXVALUE", 0)
            data = np.full(current.stored_shape, int(value or 0), dtype=hdu.dtype.newbyteorder("="))
        if data.dtype.kind not in "iu":
            raise PerscliError(f"{current.label}: {hdu.label} holds {data.dtype} values, not integer flags: "
                               "cannot set a DQ bit in it; drop --flag-above")
        if data.shape[-2:] != current.stored_shape:
            raise PerscliError(f"{current.label}: {hdu.label} has shape {data.shape}, not the science image's "
                               f"{current.stored_shape}; drop --flag-above")
        if dq_bit > np.iinfo(data.dtype).max:
            raise PerscliError(f"{current.label}: {hdu.label} holds {data.dtype} flags: --dq-bit {dq_bit} does not "
                               f"fit; choose a bit up to {(np.iinfo(data.dtype).max + 1) // 2}")
        cards = [c for c in hdu.header.cards if c[:8].rstrip() not in ("NPIX1", "NPIX2", "NPIX3", "PIXVALUE")]
        targets[hdu.index] = (np.array(_section_of(current, data)), cards)
        if current.layout == "cube":
            break
    return targets


def apply_to_frame(current: Frame, previous, model: PersistenceModel, *, mode: str = "add",
                   model_error: float = DEFAULT_MODEL_ERROR,
                   flag_above: float | None = None, dq_bit: int = DEFAULT_DQ_BIT, workers: int = 1,
                   progress=None):
    """Output HDUs: the current frame with persistence added, subtracted or alone.

    Parameters
    ----------
    current, previous, model, workers, progress
        See :func:`plan` and :func:`map_blocks`.
    mode : {'add', 'subtract', 'predict'}
        Data plus persistence, data minus persistence, or persistence alone;
        always in the current frame's units.  Integer data become float32;
        float data keep their precision.
    model_error : float
        Fractional uncertainty of the predicted persistence ``P`` (default
        :data:`DEFAULT_MODEL_ERROR`).  When the current frame has an ERR
        array with data (WFC3 flt/ima, JWST): in subtract mode each ERR
        value becomes ``sqrt(ERR^2 + (model_error * P)^2)``, in predict mode
        ``model_error * P``, per read of a ramp, in the frame's units; in add
        mode (a simulation: the persistence added is the truth) ERR is kept.
    flag_above : float, optional
        Flag the pixels whose persistence averaged over the exposure (the
        charge up to the last read, or over the exposure, divided by that
        time) exceeds this many electrons per second, whatever the frame's
        units: ``dq_bit`` is ORed into the DQ array that goes with each
        science array (every read of a ramp gets the exposure's flags).  A
        frame without DQ gets one.
    dq_bit : int
        The DQ value set (a power of two; default :data:`DEFAULT_DQ_BIT`).

    Returns
    -------
    (list of OutHDU, PersistenceResult)
        The output file's HDUs, in the input's structure (plus a DQ
        extension when one was made), with provenance in the primary header.
    """
    if mode not in MODES:
        raise PerscliError(f"--mode must be one of {', '.join(MODES)}, not {mode!r}")
    _check_corrections(model_error, flag_above, dq_bit)
    the_plan = plan(current, previous, model)
    factors = [_unit_factor(current, k) for k in range(current.nreads)]
    # the uncertainty and the flags: companions read whole before the blocks (they are small next to
    # the science data, and reading them here keeps CFITSIO out of the worker threads)
    err_in = _err_planes(current, model_error, mode)
    dq, flag_limit = _flag_targets(current, flag_above, dq_bit)
    done = _stream_corrections(the_plan, model, factors, err_in, flag_limit, mode=mode, model_error=model_error,
                               workers=workers, progress=progress)
    flagged = 0
    if done.flag_mask is not None:
        flagged = int(done.flag_mask.sum())
        for data, _ in dq.values():
            # every plane of a DQ cube gets the exposure's flags
            data |= (done.flag_mask * dq_bit).astype(data.dtype)
    hdus = _frame_hdus(current, done, dq)
    result = PersistenceResult(used=the_plan.used, skipped=the_plan.skipped, max_electrons=done.peak,
                               total_electrons=done.total, flagged=flagged)
    provenance(hdus[0], current, result, model, mode=mode, current_datasum=done.current_sum,
               model_error=model_error if done.err_out else None,
               flag=(flag_above, dq_bit) if done.flag_mask is not None else None)
    return hdus, result


def _flag_targets(current: Frame, flag_above, dq_bit: int) -> tuple:
    """The DQ arrays a flag goes into (:func:`_dq_targets`) and the charge, in electrons, above which it is set.

    Returns
    -------
    (dict, float or None)
        ``({}, None)`` without ``flag_above``.
    """
    if flag_above is None:
        return {}, None
    dq = _dq_targets(current, dq_bit)
    seconds = float(_plane_ends(current)[-1])
    if seconds <= 0:
        raise PerscliError(f"{current.label}: the exposure lasts 0 s: a persistence rate cannot be flagged; "
                           "drop --flag-above or fix the timing")
    return dq, flag_above * seconds


@dataclass
class _Corrected:
    """The corrected frame of :func:`apply_to_frame`, as streamed block by block (:func:`_stream_corrections`)."""

    out: np.ndarray        # (nplanes, ny, nx), the science planes in the output's stored (big-endian) type
    plane_sums: list       # DATASUM of each plane of ``out``
    current_sum: int       # the current frame's DATASUM, checked against its header where it was streamed
    peak: float            # largest persistence in the last plane, electrons
    total: float           # sum of the last plane's persistence, electrons
    err_out: dict          # hdu index -> the updated ERR array
    flag_mask: np.ndarray | None   # (ny, nx) pixels above the flag's charge; None without flags


def _stream_corrections(the_plan: PersistencePlan, model: PersistenceModel, factors, err_in, flag_limit, *,
                        mode: str, model_error: float, workers: int = 1, progress=None) -> _Corrected:
    """Compute the persistence block by block (:func:`map_blocks`) and the corrected planes, ERR and flags from it.

    Parameters
    ----------
    the_plan, model, workers, progress
        As :func:`map_blocks`.
    factors : list of float
        Electrons per unit of each output plane (:func:`_unit_factor`).
    err_in : list
        The ERR planes to update (:func:`_err_planes`).
    flag_limit : float or None
        The charge above which a pixel is flagged; None: no flags.
    mode, model_error
        As :func:`apply_to_frame`.

    Returns
    -------
    _Corrected
    """
    current = the_plan.current
    ny, nx = current.shape
    sci = current.hdus[current.sci[0]]
    # stored (big-endian) order: each block is converted and its DATASUM summed in the thread that made it
    dtype = np.dtype(">f8") if sci.dtype == np.dtype(">f8") and sci.is_plain_float else np.dtype(">f4")
    out = np.empty((current.nreads, ny, nx), dtype=dtype)
    # the fast path: the current frame's stored bytes are checksummed as they are used
    fold_current = current.rows_are_raw
    err_out = {}
    for entry in err_in:
        if entry is not None and entry[0] not in err_out:
            err_out[entry[0]] = np.empty_like(entry[1])
    flag_mask = None if flag_limit is None else np.zeros((ny, nx), dtype=bool)
    consume = _block_consumer(current, out, factors, err_in, err_out, flag_mask, flag_limit, mode=mode,
                              model_error=model_error, fold_current=fold_current)
    threads = workers if (fold_current or mode == "predict") else 1  # CFITSIO reads stay in one thread
    parts = map_blocks(the_plan, model, consume, workers=threads, progress=progress)
    current_sum = 0
    plane_sums = [0] * current.nreads
    for part, _, _, sums in parts:
        current_sum = ones_complement_add(current_sum, part)
        plane_sums = [ones_complement_add(a, b) for a, b in zip(plane_sums, sums)]
    peak = max((p for _, p, _, _ in parts), default=0.0)
    total = float(sum(t for _, _, t, _ in parts))
    if fold_current and mode != "predict":
        current_sum = current.verify(current.sci[0], current_sum)
    else:
        current_sum = current.datasum(current.provenance_hdu)
    return _Corrected(out=out, plane_sums=plane_sums, current_sum=current_sum, peak=peak, total=total,
                      err_out=err_out, flag_mask=flag_mask)


def _block_consumer(current: Frame, out, factors, err_in, err_out, flag_mask, flag_limit, *, mode: str,
                    model_error: float, fold_current: bool):
    """The ``consume`` of :func:`map_blocks` for :func:`_stream_corrections`: one block of rows into ``out``.

    It converts the block's persistence to the frame's units, updates the
    ERR rows in ``err_out`` and the flags in ``flag_mask``, adds it to or
    subtracts it from the current frame's rows (unless predicting), and
    returns ``(the current rows' DATASUM part, peak, total, [DATASUM of each
    output plane's rows])``.
    """
    nx = current.shape[1]

    def consume(r0, r1, electrons):
        peak_total = (float(electrons[-1].max()), float(electrons[-1].sum()))
        if flag_mask is not None:
            np.greater(electrons[-1], flag_limit, out=flag_mask[r0:r1])
        scratch = np.empty((r1 - r0, nx))
        part = 0
        out_sums = []
        for k in range(current.nreads):
            if factors[k] == 0.0:
                work = scratch
                work.fill(0.0)
            elif factors[k] == 1.0:
                work = electrons[k]          # a frame in electrons: no conversion (this block is not read again)
            else:
                work = scratch
                np.divide(electrons[k], factors[k], out=work)
            entry = err_in[k] if k < len(err_in) else None
            if entry is not None:
                index, err, plane = entry
                rows_in = err[plane, r0:r1] if plane is not None else err[r0:r1]
                rows_out = err_out[index][plane, r0:r1] if plane is not None else err_out[index][r0:r1]
                if mode == "subtract":
                    rows_out[...] = np.hypot(rows_in, model_error * work)
                else:
                    rows_out[...] = model_error * np.abs(work)
            if mode != "predict":
                rows = current.raw_rows(r0, r1, scratch=True) if fold_current else current.rows(k, r0, r1)
                if fold_current:
                    part = ones_complement_add(part, _kernels.datasum(rows))
                if mode == "add":
                    np.add(rows, work, out=work)
                else:
                    np.subtract(rows, work, out=work)
            # values beyond the output's floats (a current frame scaled by BZERO = 1E300, stored as
            # 32-bit) would be written as infinities with exit 0: numpy raises instead (no extra pass)
            with np.errstate(over="raise"):
                try:
                    out[k, r0:r1] = work
                except FloatingPointError:
                    raise PerscliError(
                        f"{current.label}: values up to {np.nanmax(np.abs(work)):.3g} do not fit in the output's "
                        f"{8 * out.dtype.itemsize}-bit floats: the data or their scaling (BSCALE/BZERO) are "
                        "corrupt; check the frame") from None
            out_sums.append(_kernels.datasum(out[k, r0:r1]))
        return (part,) + peak_total + (out_sums,)

    return consume


def _frame_hdus(current: Frame, done: _Corrected, dq: dict) -> list:
    """The output file's HDUs: the current frame's, in its order, with the corrected science, ERR and DQ data.

    Parameters
    ----------
    current : Frame
    done : _Corrected
        The corrected planes (:func:`_stream_corrections`).
    dq : dict
        The flagged DQ arrays (:func:`_dq_targets`; empty without flags):
        existing ones replace theirs, new ones are appended at the end.

    Returns
    -------
    list of OutHDU
    """
    hdus = []
    for hdu in current.hdus:
        if hdu.index in current.sci:
            if current.layout == "cube":
                data, datasum = done.out, 0
                for s in done.plane_sums:
                    datasum = ones_complement_add(datasum, s)
            else:
                k = current.sci.index(hdu.index)
                data, datasum = done.out[k], done.plane_sums[k]
            extname = hdu.header.get("EXTNAME") if "EXTNAME" in hdu.header else None
            hdus.append(OutHDU(list(hdu.header.cards), data, extname=extname, datasum=datasum))
        elif hdu.index in done.err_out:
            hdus.append(OutHDU(list(hdu.header.cards), done.err_out[hdu.index], extname="ERR"))
        elif hdu.index in dq:
            data, cards = dq[hdu.index]
            hdus.append(OutHDU(cards, data, extname="DQ"))
        else:
            data, units = hdu.read_copy()
            hdus.append(OutHDU(list(hdu.header.cards), data, units=units))
    for key, (data, cards) in dq.items():
        if isinstance(key, tuple):
            hdus.append(OutHDU(cards, data, extname="DQ"))
    return hdus


def provenance(header, current: Frame, result: PersistenceResult, model: PersistenceModel, *,
               mode: str, current_datasum: int,
               model_error: float | None = None, flag: tuple | None = None) -> None:
    """Write the settings and inputs of an apply-persistence run into the primary header.

    ``model_error`` when ERR was updated; ``flag`` = (rate in e-/s, DQ bit) when DQ was.
    """
    params = {
        "PSMODE": (mode, "persistence: add, subtract or predict"),
        "PSMODEL": (model.name[-68:], "persistence model"),
        "PSKIND": (model.kind, "fermi or linear"),
        "PSTIME": (model.time_model if model.kind == "fermi" else "none", "time model: exact, middle or galsim"),
        "PSCOMB": (model.combine, "combination over earlier exposures"),
        "PSMAXPRV": (model.max_previous, "most recent earlier exposures counted (0: all)"),
        "PSLOOKB": (float(model.lookback), "[h] earlier exposures older are ignored (0: none)"),
        "PSNPREV": (len(result.used), "earlier exposures used"),
        "PSUNIT": (current.unit, "units of the science data"),
    }
    if model_error is not None:
        params["PSMERR"] = (float(model_error), "fractional uncertainty of persistence, in ERR")
    if flag is not None:
        params["PSFLAG"] = (float(flag[0]), "[e-/s] DQ flag where persistence rate exceeds")
        params["PSDQBIT"] = (int(flag[1]), "DQ value set for persistence")
        params["PSNFLAG"] = (int(result.flagged), "pixels flagged for persistence")
    if model.kind == "fermi":
        params.update({
            "PS_A": (model.A, "[e-/s] Fermi normalisation at t=1000 s"),
            "PS_X0": (model.x0, "[e-] Fermi step fluence"),
            "PS_DX": (model.dx, "[e-] Fermi step width"),
            "PS_ALPHA": (model.alpha, "fluence power-law index"),
            "PS_GAMMA": (model.gamma, "time power-law index"),
            "PS_HWELL": (model.half_well, "[e-] linear below this fluence"),
        })
    else:
        for i, c in enumerate(model.coefficients, 1):
            params[f"PSCOEF{i:02d}"] = (c, f"linear coefficient, exposure {i} back")
    if isinstance(header, OutHDU):
        # a chained run (apply-persistence on an earlier output) replaces the earlier run's
        # settings; its HISTORY cards stay
        header.remove(matching=lambda key: _PROVENANCE_KEY.match(key) is not None)
    inputs = [("PSCUR", current.name, current_datasum)]
    for i, rec in enumerate(result.used, 1):
        stem = f"PSP{i:02d}"
        inputs.append((stem, rec.name, rec.datasum))
        params[f"{stem}DT"] = (round(rec.gap, 6), f"[s] from end of {stem} to start of PSCUR")
        params[f"{stem}TF"] = (rec.factors[-1], "[s] time factor (or coefficient), last plane")
        if rec.overlap is not None and not rec.overlap.same_pixels:
            params[f"{stem}SX"] = (rec.overlap.shift[1], f"[pix] {stem} x of PSCUR pixel x=0")
            params[f"{stem}SY"] = (rec.overlap.shift[0], f"[pix] {stem} y of PSCUR pixel y=0")
    extra = f" lookback={model.lookback:g}h" if model.lookback else ""
    if model_error is not None:
        extra += f" model-error={model_error:g}"
    if flag is not None:
        extra += f" flag-above={flag[0]:g} dq-bit={flag[1]}"
    add_provenance(header, step=f"apply-persistence mode={mode} model={model.name} "
                                f"time-model={params['PSTIME'][0]} combine={model.combine} "
                                f"previous={len(result.used)}{extra}",
                   params=params, inputs=inputs)


def apply_persistence_files(current: str, previous, dest: str, *, model: PersistenceModel,
                            options: ApplyOptions = ApplyOptions(), overwrite: bool = False, workers: int = 1,
                            progress=None, stdin=None, stdout=None) -> PersistenceResult:
    """Read frames, apply persistence and write the result: the whole command as a function.

    Parameters
    ----------
    current : str
        Path of the frame that receives persistence, or '-' for stdin.
    previous : sequence of str
        Paths of earlier exposures (at most one may be '-').
    dest : str
        Output path, or '-' for stdout.
    model : PersistenceModel
        The law and its settings (time_model, combine, max_previous, lookback).
    options : ApplyOptions
        The mode, the corrections of ERR and DQ, what overrides the inputs'
        headers, and the output's compression.
    overwrite : bool
        Replace an existing output.
    workers, progress
        See :func:`map_blocks`.

    Returns
    -------
    PersistenceResult
    """
    o = options
    names = [current, *previous]
    if names.count("-") > 1:
        raise PerscliError("only one input can be read from standard input ('-')")
    _check_corrections(o.model_error, o.flag_above, o.dq_bit)
    check_output(dest, overwrite=overwrite, inputs=names)
    opened = []
    try:
        for name in names:
            opened.append(open_frame(name, units=o.units, gain=o.gain, exptime=o.exptime, stdin=stdin))
        cur, prevs = opened[0], opened[1:]
        if o.gap is not None:
            if o.gap < 0:
                raise PerscliError(f"--gap must be >= 0 seconds, not {o.gap}")
            assign_sequence_timing(prevs + [cur], o.gap, o.exptime)
        hdus, result = apply_to_frame(cur, prevs, model, mode=o.mode, model_error=o.model_error,
                                      flag_above=o.flag_above, dq_bit=o.dq_bit, workers=workers, progress=progress)
        write_hdus(hdus, dest, overwrite=overwrite, stdout=stdout, compress=o.compress)
        return result
    finally:
        for frame in opened:
            frame.close()
