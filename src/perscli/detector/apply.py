"""Persistence of earlier exposures on a frame: add, subtract or predict it.

This is the frame-level driver behind ``perscli apply-persistence``: it
orders the earlier exposures by their timestamps, works out the exact
time factor of each (or GalSim's approximation), streams their fluence
through :func:`perscli.detector.persistence.accumulate` one frame at a time,
and builds the output file with the input's structure and units.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits

from .. import PerscliError
from ..io.frames import SECONDS_PER_DAY, UNITS, Frame, require_timing
from ..io.output import add_provenance
from .persistence import GALSIM_EXPTIME, PersistenceModel, accumulate, time_factor

log = logging.getLogger(__name__)

MODES = ("add", "subtract", "predict")


@dataclass
class EarlierExposure:
    """What one earlier exposure contributed."""

    name: str
    recency: int          # 0 = most recent
    gap: float            # seconds from its end to the start of the current exposure
    factors: list         # time factor (s) or linear coefficient, one per output plane
    datasum: int = 0
    nonfinite: int = 0


@dataclass
class PersistenceResult:
    """Persistence in electrons on the current frame, plane by plane."""

    electrons: np.ndarray             # (nplanes, ny, nx), float64
    used: list = field(default_factory=list)
    skipped: list = field(default_factory=list)


def _label(frame: Frame) -> str:
    return "stdin" if frame.name == "-" else frame.name


def _time_factors(current: Frame, prev: Frame, recency: int, model: PersistenceModel, time_model: str):
    gap = (current.start - prev.end) * SECONDS_PER_DAY
    if model.kind == "linear":
        if current.is_ramp:
            raise PerscliError(f"{_label(current)}: the linear model has no time dependence and cannot be "
                               "applied read by read; use a Fermi model (typical, pessimistic) for ramps")
        if recency >= len(model.coefficients):
            return gap, None
        return gap, [model.coefficients[recency]]
    if time_model == "galsim":
        if current.is_ramp:
            raise PerscliError(f"{_label(current)}: --time-model galsim has no notion of reads; "
                               "use --time-model exact for ramps")
        mid = (0.5 + recency) * GALSIM_EXPTIME
        return gap, [GALSIM_EXPTIME * (mid / 1000.0) ** (-model.gamma)]
    if current.is_ramp:
        ends = gap + np.asarray(current.read_times, dtype=np.float64)
    else:
        ends = np.array([gap + (current.end - current.start) * SECONDS_PER_DAY])
    if gap <= 0 and model.gamma >= 1:
        raise PerscliError(
            f"{_label(prev)} ends exactly when {_label(current)} starts: with gamma={model.gamma:g} the "
            "persistence integral diverges at zero delay; check the timestamps (a reset takes time)")
    try:
        return gap, [float(v) for v in time_factor(np.full_like(ends, gap), ends, model.gamma)]
    except ValueError as exc:
        raise PerscliError(f"{_label(prev)}: {exc}") from None


def persistence_on(current: Frame, previous, model: PersistenceModel, *, time_model: str = "exact",
                   combine: str = "sum", max_previous: int = 10, workers: int = 1,
                   progress=None) -> PersistenceResult:
    """The persistence that earlier exposures leave in ``current``, in electrons.

    Parameters
    ----------
    current : Frame
        The exposure that receives persistence (an image or a ramp).
    previous : iterable of Frame
        Earlier exposures of the same detector, in any order.  Each is
        closed after use, so only one earlier frame is in memory at a time.
    model : PersistenceModel
    time_model : {'exact', 'galsim'}
        'exact': the integral of the rate over the current exposure's own
        [start, end] (or up to each read's time for a ramp), with t counted
        from the end of each earlier exposure.  'galsim': GalSim's
        ``rate((0.5 + i) * 139.8 s) * 139.8 s`` for the i-th most recent one.
    combine : {'sum', 'max'}
        Sum over earlier exposures (the paper, GalSim) or per-pixel maximum
        (the WFC3 pipeline).
    max_previous : int
        Only the most recent ``max_previous`` earlier exposures count (0: all).
    workers : int
        Threads per frame.
    progress : callable, optional
        Called as ``progress(done, total, name)`` after each earlier frame.

    Returns
    -------
    PersistenceResult
    """
    previous = list(previous)
    require_timing(current)
    for prev in previous:
        require_timing(prev)
        if prev.shape != current.shape:
            raise PerscliError(f"{_label(prev)}: image shape {prev.shape} differs from {_label(current)}'s "
                               f"{current.shape}; earlier exposures must be of the same detector area")
        offsets = [(f.keyword("LTV1"), f.keyword("LTV2")) for f in (prev, current)]
        if None not in offsets[0] + offsets[1] and offsets[0] != offsets[1]:
            raise PerscliError(f"{_label(prev)}: subarray offset LTV1/LTV2={offsets[0]} differs from "
                               f"{_label(current)}'s {offsets[1]}: not the same pixels of the detector")
        if prev.end > current.start:
            raise PerscliError(
                f"{_label(prev)} ends at MJD {prev.end:.8f}, after {_label(current)} starts "
                f"(MJD {current.start:.8f}): it is not an earlier exposure; check the order or the timestamps")
    if max_previous < 0:
        raise PerscliError(f"--max-previous must be >= 0 (0 for all), not {max_previous}")
    ordered = sorted(previous, key=lambda f: f.end, reverse=True)
    keep = ordered if max_previous == 0 else ordered[:max_previous]
    skipped = [_label(f) for f in ordered[len(keep):]]
    for frame in ordered[len(keep):]:
        frame.close()
    if skipped:
        log.info("only the %d most recent earlier exposures count; ignoring %s", len(keep), ", ".join(skipped))

    nplanes = current.nreads
    acc = np.zeros((nplanes,) + current.shape, dtype=np.float64)
    result = PersistenceResult(electrons=acc, skipped=skipped)
    for recency, prev in enumerate(keep):
        gap, factors = _time_factors(current, prev, recency, model, time_model)
        record = EarlierExposure(name=prev.name, recency=recency, gap=gap, factors=factors or [])
        record.datasum = prev.datasum(prev.sci[-1] if prev.layout == "wfc3-ramp" else prev.sci[0])
        if factors is None:
            log.info("%s: beyond the linear model's %d coefficients; ignored", _label(prev),
                     len(model.coefficients))
        else:
            fluence, scale = prev.fluence()
            record.nonfinite = accumulate(fluence, acc, factors, model, scale=scale,
                                          combine=combine, workers=workers)
            del fluence
            if record.nonfinite:
                log.warning("%s: %d non-finite pixels counted as zero fluence", _label(prev), record.nonfinite)
        prev.close()
        result.used.append(record)
        if progress is not None:
            progress(recency + 1, len(keep), _label(prev))
    return result


def _to_units(current: Frame, electrons: np.ndarray, plane: int) -> np.ndarray:
    """Persistence electrons of one plane in the current frame's units."""
    is_dn, is_rate = UNITS[current.unit]
    if not (is_dn or is_rate):
        return electrons
    if is_rate:
        seconds = current.read_times[plane] if current.is_ramp else current.exptime
        if current.is_ramp and seconds == 0:
            return np.zeros_like(electrons)
        factor = current.electrons_per_unit(seconds=seconds)
    else:
        factor = current.electrons_per_unit()
    return electrons / factor


def _science_header(header: fits.Header) -> fits.Header:
    header = header.copy()
    # the output is float: integer scaling keywords no longer apply
    for key in ("BZERO", "BSCALE", "BLANK", "CHECKSUM", "DATASUM"):
        header.remove(key, ignore_missing=True)
    return header


def build_output(current: Frame, result: PersistenceResult, *, mode: str = "add") -> fits.HDUList:
    """The output file: the current frame's HDUs with its science data replaced.

    Parameters
    ----------
    current : Frame
    result : PersistenceResult
        From :func:`persistence_on`.
    mode : {'add', 'subtract', 'predict'}
        Data plus persistence, data minus persistence, or persistence alone;
        always in the current frame's units.  Integer data become float32;
        float data keep their precision.
    """
    if mode not in MODES:
        raise PerscliError(f"--mode must be one of {', '.join(MODES)}, not {mode!r}")
    planes = current.planes()
    new = []
    for k, data in enumerate(planes):
        dtype = data.dtype.newbyteorder("=") if data.dtype.kind == "f" else np.dtype(np.float32)
        pers = _to_units(current, result.electrons[k], k)
        if mode == "predict":
            out = pers.astype(dtype)
        else:
            out = np.array(data, dtype=dtype)
            if mode == "add":
                np.add(out, pers, out=out, casting="unsafe")
            else:
                np.subtract(out, pers, out=out, casting="unsafe")
        new.append(out)

    hdus = []
    for i, hdu in enumerate(current.hdul):
        if i in current.sci:
            if current.layout == "cube":
                data = np.stack(new)
            else:
                data = new[current.sci.index(i)]
            header = _science_header(hdu.header)
            cls = fits.PrimaryHDU if i == 0 else fits.ImageHDU
            hdus.append(cls(data=data, header=header))
        elif i == 0:
            hdus.append(fits.PrimaryHDU(data=hdu.data, header=hdu.header.copy()))
        else:
            hdus.append(hdu)
    return fits.HDUList(hdus)


def provenance(hdul: fits.HDUList, current: Frame, result: PersistenceResult, model: PersistenceModel, *,
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
    inputs = [("PSCUR", current.name, current_datasum)]
    for i, rec in enumerate(result.used, 1):
        stem = f"PSP{i:02d}"
        inputs.append((stem, rec.name, rec.datasum))
        params[f"{stem}DT"] = (round(rec.gap, 6), f"[s] from end of {stem} to start of PSCUR")
        if rec.factors:
            params[f"{stem}TF"] = (rec.factors[-1], "[s] time factor (or coefficient), last plane")
    header = hdul[0].header
    add_provenance(header, step=f"apply-persistence mode={mode} model={model.name} "
                                f"time-model={params['PSTIME'][0]} combine={combine} "
                                f"previous={len(result.used)}",
                   params=params, inputs=inputs)


def apply_persistence_files(current: str, previous, dest: str, *, model: PersistenceModel,
                            mode: str = "add", time_model: str = "exact", combine: str = "sum",
                            max_previous: int = 10, units: str | None = None, gain: float | None = None,
                            exptime: float | None = None, gap: float | None = None, overwrite: bool = False,
                            workers: int = 1, progress=None, stdin=None, stdout=None) -> PersistenceResult:
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
        See :func:`persistence_on` and :func:`build_output`.
    units, gain, exptime : optional
        Override BUNIT, GAIN/CCDGAIN and supply EXPTIME for every input.
    gap : float, optional
        Ignore header timestamps: the inputs form a regular sequence in the
        order ``previous..., current`` with ``gap`` seconds between exposures.
    overwrite : bool
        Replace an existing output.

    Returns
    -------
    PersistenceResult
    """
    from ..io.frames import assign_sequence_timing, open_frame
    from ..io.output import check_output, write_fits

    if time_model not in ("exact", "galsim"):
        raise PerscliError(f"--time-model must be exact or galsim, not {time_model!r}")
    if combine not in ("sum", "max"):
        raise PerscliError(f"--combine must be sum or max, not {combine!r}")
    if mode not in MODES:
        raise PerscliError(f"--mode must be one of {', '.join(MODES)}, not {mode!r}")
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
        result = persistence_on(cur, prevs, model, time_model=time_model, combine=combine,
                                max_previous=max_previous, workers=workers, progress=progress)
        hdul = build_output(cur, result, mode=mode)
        cur_sum = cur.datasum(cur.sci[-1] if cur.layout == "wfc3-ramp" else cur.sci[0])
        provenance(hdul, cur, result, model, mode=mode, time_model=time_model, combine=combine,
                   max_previous=max_previous, current_datasum=cur_sum)
        write_fits(hdul, dest, overwrite=overwrite, stdout=stdout)
        return result
    finally:
        for frame in opened:
            frame.close()
