"""Measured and simulated exposures for diagnose: read, put in time order, paired, in common units."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .. import PerscliError
from ..detector.model import model_of_frame
from ..io.frames import SECONDS_PER_DAY, UNITS, open_frame, require_timing

log = logging.getLogger(__name__)

#: simulated and measured exposures pair when their starts agree to this many seconds
PAIR_TOLERANCE = 1.0


@dataclass
class MeasuredExposure:
    """One measured exposure and what the forward model needs of it.

    Attributes
    ----------
    label : str
        The measured file.
    start, end : float
        MJD.
    exptime : float
        Seconds.
    data : ndarray
        The measured image in its own counts (DN or electrons; rates times
        the exposure time), float64.  For a ramp: reads minus the first read,
        shape ``(nreads - 1, ny, nx)``.
    counts : {'DN', 'electron'}
        What ``data`` counts.
    gain : float or None
        The header's e-/DN.
    read_times : ndarray or None
        Ramps: seconds from the first read to each read of ``data``.
    ideal : ndarray or None
        Noise-free electrons of sources and sky over the exposure (the
        simulation's IDEAL).
    fluence : ndarray
        Electrons collected: the history this exposure leaves for later
        ones (the simulation's FLUENCE, else the measured signal).
    sim : str or None
        The simulated file paired with it.
    offsets : tuple
        (LTV1, LTV2) of the measured frame, when present.
    valid : ndarray of bool, optional
        Pixels that see the sky: False for a WFC3-IR raw or ima frame's
        5-pixel border of reference pixels and for pixels with a DQ flag in
        any read (they are left out of every fit, gap and estimate).
    persist : ndarray, optional
        The persistence the simulation's own law added (its PERSIST), in
        electrons (float16): the part of FLUENCE a fitted law replaces by its
        own.
    """

    label: str
    start: float
    end: float
    exptime: float
    data: np.ndarray
    counts: str
    gain: float | None
    read_times: np.ndarray | None = None
    ideal: np.ndarray | None = None
    fluence: np.ndarray | None = None
    sim: str | None = None
    offsets: tuple = (None, None)
    datasum: int = 0
    extra: dict = field(default_factory=dict)
    valid: np.ndarray | None = None
    persist: np.ndarray | None = None

    @property
    def is_ramp(self) -> bool:
        return self.read_times is not None


def _counts(frame) -> tuple:
    """(stack of planes in DN or electrons, 'DN' or 'electron'), rates times the exposure (or read) time."""
    is_dn, is_rate = UNITS[frame.unit]
    # a 2-D frame is kept in float32 (its counts are float32 or 16-bit integers in the file): eleven full
    # SCAs with their IDEAL and FLUENCE are then 2.2 GB instead of 4.4
    dtype = np.float64 if frame.is_ramp else np.float32
    planes = [np.asarray(p, dtype=dtype) for p in frame.planes()]
    if is_rate:
        if frame.is_ramp:
            planes = [p * t for p, t in zip(planes, frame.read_times)]
        else:
            if not frame.exptime:
                raise PerscliError(f"{frame.label}: a rate image without EXPTIME; give --exptime")
            planes = [p * frame.exptime for p in planes]
    return np.stack(planes), ("DN" if is_dn else "electron")


def _valid_pixels(frame, shape) -> tuple:
    """(pixels that see the sky, number of reference pixels, number DQ-flagged) of a measured frame."""
    valid = np.ones(shape, dtype=bool)
    border = frame.reference_border if frame.section is None else 0
    if border:
        valid[:border] = valid[-border:] = False
        valid[:, :border] = valid[:, -border:] = False
    nref = int((~valid).sum())
    dq = [h for h in frame.hdus if h.name == "DQ" and h.is_image and h.shape and tuple(h.shape[-2:]) == tuple(shape)]
    flagged = np.zeros(shape, dtype=bool)
    for h in dq:
        flagged |= np.asarray(h.read()).reshape((-1,) + tuple(shape)).any(axis=0) != 0
    valid &= ~flagged
    return valid, nref, int((flagged & (valid | ~valid)).sum())


def read_measured(names, *, gain=None, exptime=None) -> list:
    """The measured exposures, in time order.

    Raises
    ------
    PerscliError
        Unreadable files, missing timing, exposures of different shapes or
        overlapping in time.
    """
    out = []
    for name in names:
        with open_frame(name, gain=gain, exptime=exptime) as frame:
            if frame.start is None or frame.end is None:
                raise PerscliError(f"{frame.label}: no exposure timing: diagnose puts exposures in time order and "
                                   "computes persistence from their times; add EXPSTART/EXPEND (MJD), "
                                   "MJD-BEG/MJD-END, or DATE-OBS with EXPTIME to the header")
            require_timing(frame)
            data, counts = _counts(frame)
            if counts == "DN" and frame.gain is None:
                raise PerscliError(f"{frame.label}: BUNIT is DN but the header has no GAIN or CCDGAIN; give --gain")
            read_times = None
            if frame.is_ramp:
                # reads minus the first: the bias and the charge before the first read drop out
                read_times = np.asarray(frame.read_times[1:] - frame.read_times[0], dtype=np.float64)
                data = data[1:] - data[0]
            bad = ~np.isfinite(data)
            if bad.all():
                raise PerscliError(f"{frame.label}: no finite pixel")
            valid, nref, ndq = _valid_pixels(frame, data.shape[-2:])
            if not valid.any():
                raise PerscliError(f"{frame.label}: every pixel is a reference pixel or flagged in DQ")
            exposure = MeasuredExposure(label=frame.label, start=frame.start, end=frame.end,
                                exptime=float(frame.exptime or (frame.end - frame.start) * SECONDS_PER_DAY),
                                data=data, counts=counts, gain=frame.gain, read_times=read_times,
                                offsets=(frame.keyword("LTV1"), frame.keyword("LTV2")),
                                datasum=frame.datasum(frame.sci[-1]), valid=valid)
            exposure.extra.update(reference_pixels=nref, dq_flagged=ndq,
                                  rendered=any(h.name == "IDEAL" for h in frame.hdus))
            out.append(exposure)
    out.sort(key=lambda e: e.start)
    shapes = {e.data.shape[-2:] for e in out}
    if len(shapes) > 1:
        raise PerscliError(f"measured frames differ in shape ({sorted(shapes)}): diagnose one detector area at a time")
    for a, b in zip(out, out[1:]):
        if b.start < a.end:
            sim = next((e for e in (a, b) if e.extra.get("rendered")), None)
            if sim is not None:
                # the usual cause: --simulated sim/*.fits, where the shell's glob passes only the first file
                # to --simulated and the others as measured frames
                raise PerscliError(f"{b.label} starts before {a.label} ends, and {sim.label} is a perscli render "
                                   "output (it has IDEAL): if it is a simulation, give it with --simulated (one "
                                   "--simulated per file: a shell glob after --simulated passes only the first)")
            raise PerscliError(f"{b.label} starts before {a.label} ends: exposures of one detector cannot overlap; "
                               "check their timestamps")
    for e in out:
        if not np.isfinite(e.data).any():
            raise PerscliError(f"{e.label}: no finite pixel")
        if e.is_ramp and (len(e.read_times) < 1 or not np.all(np.diff(np.concatenate([[0.0], e.read_times])) > 0)):
            raise PerscliError(f"{e.label}: its reads do not follow one another in time (SAMPTIME repeats or goes "
                               "back): a ramp's reads need increasing times")
    return out


def attach_simulations(exposures, sims) -> list:
    """Pair simulated frames (``perscli render`` outputs) with the measured exposures.

    Pairs by exposure start within :data:`PAIR_TOLERANCE` seconds when every
    frame has a start time, else by order (then the counts must match).

    Returns
    -------
    list of DetectorModel or None
        The model stored in each simulated frame (None where it has none).
    """
    opened = []
    for name in sims:
        frame = open_frame(name)
        opened.append(frame)
    try:
        for frame in opened:
            names = {h.name for h in frame.hdus}
            if "IDEAL" not in names:
                raise PerscliError(f"{frame.label}: no IDEAL extension: --simulated takes frames that perscli render "
                                   "wrote (SCI, IDEAL, FLUENCE)")
        timed = all(f.start is not None for f in opened)
        pairs = []
        if timed:
            for exp in exposures:
                match = [f for f in opened if abs(f.start - exp.start) * SECONDS_PER_DAY <= PAIR_TOLERANCE]
                if len(match) > 1:
                    raise PerscliError(f"{exp.label}: {len(match)} simulated frames start within "
                                       f"{PAIR_TOLERANCE:g} s of it; give one per exposure")
                pairs.append(match[0] if match else None)
            unused = [f.label for f in opened if all(f is not p for p in pairs)]
            if unused:
                raise PerscliError(f"{unused[0]}: no measured exposure starts within {PAIR_TOLERANCE:g} s of this "
                                   "simulated frame; check that both describe the same exposures")
        else:
            if len(opened) != len(exposures):
                raise PerscliError(f"{len(opened)} simulated frames for {len(exposures)} measured exposures: without "
                                   "start times they pair in order and their numbers must match")
            pairs = list(opened)
        models = []
        for exp, frame in zip(exposures, pairs):
            if frame is None:
                models.append(None)
                continue
            ideal_hdu = next(h for h in frame.hdus if h.name == "IDEAL")
            ideal = np.asarray(ideal_hdu.read(), dtype=np.float32)
            if ideal.shape != exp.data.shape[-2:]:
                raise PerscliError(f"{frame.label}: IDEAL is {ideal.shape}, the measured {exp.label} is "
                                   f"{exp.data.shape[-2:]}: pair frames of the same detector area")
            if not np.isfinite(ideal).any():
                raise PerscliError(f"{frame.label}: IDEAL has no finite pixel: the simulation of {exp.label} is "
                                   "empty or corrupt; render it again")
            exp.ideal = ideal
            exp.sim = frame.label
            flu = [h for h in frame.hdus if h.name == "FLUENCE"]
            if flu:
                exp.fluence = np.asarray(flu[0].read(), dtype=np.float32)
                pers = [h for h in frame.hdus if h.name == "PERSIST"]
                if pers and tuple(pers[0].shape[-2:]) == exp.fluence.shape:
                    # half precision (a thousandth of itself): it corrects the histories by a persistence's
                    # persistence, and a full SCA's PERSIST is 33 MB so, not 67
                    exp.persist = np.asarray(np.nan_to_num(pers[0].read()), dtype=np.float16)
            exp.extra["sky_rate"] = frame.keyword("SKYRATE")
            models.append(model_of_frame(frame))
        return models
    finally:
        for frame in opened:
            frame.close()


def measured_fluence(exp: MeasuredExposure) -> np.ndarray:
    """The electrons an exposure collected, from its measured counts (the history without a simulation)."""
    last = exp.data[-1]
    if exp.counts == "DN":
        return np.where(np.isfinite(last), last * np.float32(exp.gain), np.float32(0.0))
    return np.where(np.isfinite(last), last, np.float32(0.0))
