"""Persistence of earlier exposures on a frame: add, subtract or predict it.

This is the frame-level driver behind ``perscli apply-persistence``: it
orders the earlier exposures by their timestamps, works out the exact
time factor of each (or GalSim's approximation), streams their fluence
through :func:`perscli.detector.persistence.accumulate` block of rows by
block of rows, all earlier frames side by side, and builds the output file
with the input's structure and units.  Memory is the output frame plus one
block per input, whatever the number of earlier frames.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError, _kernels
from ..executor import thread_map
from ..io.fitsfile import OutHDU
from ..io.frames import SECONDS_PER_DAY, UNITS, Frame, require_timing
from ..io.output import add_provenance
from .persistence import GALSIM_EXPTIME, PersistenceModel, accumulate, ones_complement_add, time_factor

log = logging.getLogger(__name__)

MODES = ("add", "subtract", "predict")

#: keywords written by :func:`provenance`
_PROVENANCE_KEY = re.compile(r"^(PS(MODE|MODEL|KIND|TIME|COMB|MAXPRV|NPREV|UNIT|CUR|CURDS)|PS_\w+|PSCOEF\d+|PSP\d+\w*)$")

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


@dataclass
class PersistencePlan:
    """Which earlier exposures count, and with which time factors."""

    current: Frame
    used: list = field(default_factory=list)
    skipped: list = field(default_factory=list)


@dataclass
class PersistenceResult:
    """Summary of a run: the exposures used and the persistence added, in electrons."""

    used: list
    skipped: list
    max_electrons: float = 0.0     # largest persistence in the last plane
    total_electrons: float = 0.0   # sum over the last plane


def _plane_ends(current: Frame) -> np.ndarray:
    """Seconds from the start of the current exposure to the end of each output plane."""
    if current.is_ramp:
        return np.asarray(current.read_times, dtype=np.float64)
    return np.array([(current.end - current.start) * SECONDS_PER_DAY])


def with_settings(model: PersistenceModel, *, time_model=None, combine=None, max_previous=None) -> PersistenceModel:
    """``model`` with its settings replaced where given (command-line options over the model file)."""
    import dataclasses

    changes = {k: v for k, v in (("time_model", time_model), ("combine", combine), ("max_previous", max_previous))
               if v is not None and v != getattr(model, k)}
    return dataclasses.replace(model, **changes) if changes else model


def check_earlier(prev: Frame, *, label: str, shape: tuple, detector=None, offsets=(None, None),
                  start: float | None = None) -> None:
    """Refuse an earlier exposure that cannot leave persistence in the current one.

    Parameters
    ----------
    prev : Frame
        The earlier exposure.
    label : str
        The current exposure, for messages.
    shape : tuple
        The current exposure's image shape.
    detector : optional
        Its SCA/DETECTOR keyword, when known.
    offsets : (LTV1, LTV2)
        Its subarray offsets, when known.
    start : float, optional
        Its start (MJD).
    """
    require_timing(prev)
    if prev.shape != tuple(shape):
        raise PerscliError(f"{prev.label}: image shape {prev.shape} differs from {label}'s "
                           f"{tuple(shape)}; earlier exposures must be of the same detector area")
    theirs = prev.keyword("SCA", prev.keyword("DETECTOR"))
    if None not in (theirs, detector) and str(theirs).strip() != str(detector).strip():
        raise PerscliError(f"{prev.label}: detector SCA/DETECTOR={theirs} differs from "
                           f"{label}'s {detector}: persistence stays on the detector that saw "
                           "the light; give earlier exposures of the same detector")
    mine = (prev.keyword("LTV1"), prev.keyword("LTV2"))
    if None not in mine + tuple(offsets) and tuple(float(v) for v in mine) != tuple(float(v) for v in offsets):
        raise PerscliError(f"{prev.label}: subarray offset LTV1/LTV2={mine} differs from "
                           f"{label}'s {tuple(offsets)}: not the same pixels of the detector")
    if start is not None and prev.end > start:
        raise PerscliError(
            f"{prev.label} ends at MJD {prev.end:.8f}, after {label} starts "
            f"(MJD {start:.8f}): it is not an earlier exposure; check the order or the timestamps")


def plan(current: Frame, previous, model: PersistenceModel, *, time_model: str | None = None,
         max_previous: int | None = None) -> PersistencePlan:
    """Check the earlier exposures, order them by time and work out their time factors.

    Parameters
    ----------
    current : Frame
        The exposure that receives persistence (an image or a ramp).
    previous : iterable of Frame
        Earlier exposures of the same detector, in any order.
    model : PersistenceModel
        The law and its settings: time_model ('exact': the integral of the
        rate over the current exposure's own [start, end], or up to each read
        of a ramp, with t counted from the end of each earlier exposure;
        'galsim': GalSim's ``rate((0.5 + i) * 139.8 s) * 139.8 s`` for the
        i-th most recent one) and max_previous (0: all).
    time_model, max_previous : optional
        Override the model's settings.

    Returns
    -------
    PersistencePlan
    """
    from .persistence import exposure_time_factors, order_earlier

    model = with_settings(model, time_model=time_model, max_previous=max_previous)
    previous = list(previous)
    require_timing(current)
    for prev in previous:
        check_earlier(prev, label=current.label, shape=current.shape,
                      detector=current.keyword("SCA", current.keyword("DETECTOR")),
                      offsets=(current.keyword("LTV1"), current.keyword("LTV2")), start=current.start)
    keep, left = order_earlier([f.end for f in previous], current.start, model, [f.label for f in previous])
    result = PersistencePlan(current=current, skipped=[previous[i].label for i in left])
    if result.skipped:
        log.info("only the %d most recent earlier exposures count; ignoring %s", len(keep),
                 ", ".join(result.skipped))
    ends = _plane_ends(current)
    for recency, i in enumerate(keep):
        prev = previous[i]
        gap = (current.start - prev.end) * SECONDS_PER_DAY
        try:
            factors = exposure_time_factors(gap, ends, recency, model, label=prev.label)
        except PerscliError as exc:
            raise PerscliError(f"{current.label}: {exc}" if not str(exc).startswith(prev.label) else str(exc)) from None
        if factors is None:
            log.info("%s: beyond the linear model's %d coefficients; ignored", prev.label, len(model.coefficients))
            result.skipped.append(prev.label)
            continue
        result.used.append(EarlierExposure(frame=prev, name=prev.name, recency=recency, gap=gap, factors=factors))
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
    Every earlier frame is read once, a block at a time, by the compiled
    kernel directly from its stored bytes where it can; the DATASUM of each
    is gathered on the way (in any order: the ones'-complement sum is
    commutative) and checked against its header at the end.
    """
    import threading

    current = the_plan.current
    ny, nx = current.shape
    nplanes = current.nreads
    starts = list(range(0, ny, block_rows))
    local = threading.local()
    nused = len(the_plan.used)

    def work(r0):
        r1 = min(ny, r0 + block_rows)
        storage = getattr(local, "storage", None)
        if storage is None:
            storage = local.storage = np.empty(nplanes * min(block_rows, ny) * nx, dtype=np.float64)
        acc = storage[:nplanes * (r1 - r0) * nx].reshape(nplanes, r1 - r0, nx)
        acc.fill(0.0)
        sums = []
        for rec in the_plan.used:
            # the thread's scratch buffer: the rows are used at once, before the next read
            fluence, scale = rec.frame.fluence_rows(r0, r1, scratch=True)
            sums.append(accumulate(fluence, acc, rec.factors, model, scale=scale, combine=model.combine))
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
        if frame.fluence_is_raw:
            rec.datasum = frame.verify(frame.fluence_source, rec.datasum)
        else:
            rec.datasum = frame.datasum(frame.provenance_hdu)
        if rec.nonfinite:
            log.warning("%s: %d non-finite pixels counted as zero fluence", frame.label, rec.nonfinite)
    return [extra for _, extra in results]


def persistence_image(current: Frame, previous, model: PersistenceModel, *, time_model: str | None = None,
                      combine: str | None = None, max_previous: int | None = None, workers: int = 1) -> np.ndarray:
    """The persistence that earlier exposures leave in ``current``, in electrons.

    Parameters are those of :func:`plan` and :func:`map_blocks`.

    Returns
    -------
    ndarray of float64, shape ``(nplanes, ny, nx)``
    """
    model = with_settings(model, time_model=time_model, combine=combine, max_previous=max_previous)
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


def apply_to_frame(current: Frame, previous, model: PersistenceModel, *, mode: str = "add",
                   time_model: str | None = None, combine: str | None = None, max_previous: int | None = None,
                   workers: int = 1, progress=None):
    """Output HDUs: the current frame with persistence added, subtracted or alone.

    Parameters
    ----------
    current, previous, model, time_model, combine, max_previous, workers, progress
        See :func:`plan` and :func:`map_blocks`.
    mode : {'add', 'subtract', 'predict'}
        Data plus persistence, data minus persistence, or persistence alone;
        always in the current frame's units.  Integer data become float32;
        float data keep their precision.

    Returns
    -------
    (list of OutHDU, PersistenceResult)
        The output file's HDUs, in the input's structure, with provenance in
        the primary header.
    """
    if mode not in MODES:
        raise PerscliError(f"--mode must be one of {', '.join(MODES)}, not {mode!r}")
    model = with_settings(model, time_model=time_model, combine=combine, max_previous=max_previous)
    time_model, combine, max_previous = model.time_model, model.combine, model.max_previous
    the_plan = plan(current, previous, model)
    ny, nx = current.shape
    nplanes = current.nreads
    sci_hdus = [current.hdus[i] for i in current.sci]
    # stored (big-endian) order: each block is converted and its DATASUM summed in the thread that made it
    dtype = np.dtype(">f8") if sci_hdus[0].dtype == np.dtype(">f8") and sci_hdus[0].is_plain_float else np.dtype(">f4")
    out = np.empty((nplanes, ny, nx), dtype=dtype)
    factors = [_unit_factor(current, k) for k in range(nplanes)]
    # the fast path: the current frame's stored bytes are checksummed as they are used
    fold_current = current.rows_are_raw

    def consume(r0, r1, electrons):
        peak_total = (float(electrons[-1].max()), float(electrons[-1].sum()))
        scratch = np.empty((r1 - r0, nx))
        part = 0
        out_sums = []
        for k in range(nplanes):
            if factors[k] == 0.0:
                work = scratch
                work.fill(0.0)
            elif factors[k] == 1.0:
                work = electrons[k]          # a frame in electrons: no conversion (this block is not read again)
            else:
                work = scratch
                np.divide(electrons[k], factors[k], out=work)
            if mode != "predict":
                rows = current.raw_rows(r0, r1, scratch=True) if fold_current else current.rows(k, r0, r1)
                if fold_current:
                    part = ones_complement_add(part, _kernels.datasum(rows))
                if mode == "add":
                    np.add(rows, work, out=work)
                else:
                    np.subtract(rows, work, out=work)
            out[k, r0:r1] = work
            out_sums.append(_kernels.datasum(out[k, r0:r1]))
        return (part,) + peak_total + (out_sums,)

    threads = workers if (fold_current or mode == "predict") else 1  # CFITSIO reads stay in one thread
    parts = map_blocks(the_plan, model, consume, workers=threads, progress=progress)
    current_sum = 0
    plane_sums = [0] * nplanes
    for part, _, _, sums in parts:
        current_sum = ones_complement_add(current_sum, part)
        plane_sums = [ones_complement_add(a, b) for a, b in zip(plane_sums, sums)]
    peak = max((p for _, p, _, _ in parts), default=0.0)
    total = float(sum(t for _, _, t, _ in parts))
    if fold_current and mode != "predict":
        current_sum = current.verify(current.sci[0], current_sum)
    else:
        current_sum = current.datasum(current.provenance_hdu)

    hdus = []
    for hdu in current.hdus:
        if hdu.index in current.sci:
            if current.layout == "cube":
                data, datasum = out, 0
                for s in plane_sums:
                    datasum = ones_complement_add(datasum, s)
            else:
                k = current.sci.index(hdu.index)
                data, datasum = out[k], plane_sums[k]
            extname = hdu.header.get("EXTNAME") if "EXTNAME" in hdu.header else None
            hdus.append(OutHDU(list(hdu.header.cards), data, extname=extname, datasum=datasum))
        else:
            data, units = hdu.read_copy()
            hdus.append(OutHDU(list(hdu.header.cards), data, units=units))
    result = PersistenceResult(used=the_plan.used, skipped=the_plan.skipped, max_electrons=peak,
                               total_electrons=total)
    provenance(hdus[0], current, result, model, mode=mode, time_model=time_model, combine=combine,
               max_previous=max_previous, current_datasum=current_sum)
    return hdus, result


def provenance(header, current: Frame, result: PersistenceResult, model: PersistenceModel, *,
               mode: str, time_model: str, combine: str, max_previous: int, current_datasum: int) -> None:
    """Write the settings and inputs of an apply-persistence run into the primary header."""
    params = {
        "PSMODE": (mode, "persistence: add, subtract or predict"),
        "PSMODEL": (model.name[-68:], "persistence model"),
        "PSKIND": (model.kind, "fermi or linear"),
        "PSTIME": (time_model if model.kind == "fermi" else "none", "time model: exact integral or galsim"),
        "PSCOMB": (combine, "combination over earlier exposures"),
        "PSMAXPRV": (max_previous, "most recent earlier exposures counted (0: all)"),
        "PSNPREV": (len(result.used), "earlier exposures used"),
        "PSUNIT": (current.unit, "units of the science data"),
    }
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
    add_provenance(header, step=f"apply-persistence mode={mode} model={model.name} "
                                f"time-model={params['PSTIME'][0]} combine={combine} "
                                f"previous={len(result.used)}",
                   params=params, inputs=inputs)


def apply_persistence_files(current: str, previous, dest: str, *, model: PersistenceModel,
                            mode: str = "add", time_model: str | None = None, combine: str | None = None,
                            max_previous: int | None = None, units: str | None = None, gain: float | None = None,
                            exptime: float | None = None, gap: float | None = None, overwrite: bool = False,
                            workers: int = 1, progress=None, stdin=None, stdout=None,
                            compress: str = "none") -> PersistenceResult:
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
    mode, time_model, combine, max_previous, workers, progress
        See :func:`apply_to_frame`.
    units, gain, exptime : optional
        Override BUNIT, GAIN/CCDGAIN and supply EXPTIME for every input.
    gap : float, optional
        Ignore header timestamps: the inputs form a regular sequence in the
        order ``previous..., current`` with ``gap`` seconds between exposures.
    overwrite : bool
        Replace an existing output.
    compress : {'none', 'gzip', 'rice'}
        Lossless tile compression of the output's images.

    Returns
    -------
    PersistenceResult
    """
    from ..io.frames import assign_sequence_timing, open_frame
    from ..io.output import check_output, write_hdus

    names = [current, *previous]
    if names.count("-") > 1:
        raise PerscliError("only one input can be read from standard input ('-')")
    check_output(dest, overwrite=overwrite, inputs=names)
    opened = []
    try:
        for name in names:
            opened.append(open_frame(name, units=units, gain=gain, exptime=exptime, stdin=stdin))
        cur, prevs = opened[0], opened[1:]
        if gap is not None:
            if gap < 0:
                raise PerscliError(f"--gap must be >= 0 seconds, not {gap}")
            assign_sequence_timing(prevs + [cur], gap, exptime)
        hdus, result = apply_to_frame(cur, prevs, model, mode=mode, time_model=time_model, combine=combine,
                                      max_previous=max_previous, workers=workers, progress=progress)
        write_hdus(hdus, dest, overwrite=overwrite, stdout=stdout, compress=compress)
        return result
    finally:
        for frame in opened:
            frame.close()
