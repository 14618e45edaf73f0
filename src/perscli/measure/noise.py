"""The noise model of a frame and the S/N of catalogue objects predicted from the catalogue alone.

The background and variance per pixel come from the frame's headers and the
detector model that made it (:func:`noise_model`), or from its WHT/VAR/ERR
extension (:func:`_noise_and_weights`); never from its pixels.  The optimal
S/N of each object (:func:`predicted_snr`, through :class:`SnrTable`) uses
its catalogue magnitude and size, the PSF and that noise, and is what the
``--min-snr`` cut (:data:`MIN_SNR_DEFAULT`) compares against, so that the
cut is the same on frames with and without persistence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import galsim.roman as roman
import numpy as np

from .. import PerscliError
from ..detector.model import default_model, model_of_frame
from .fit import P_EXP, ExpModel
# the default cut (and why 5) lives with the other settings, in a module light enough for --help
from .settings import MIN_SNR_DEFAULT

#: mean of the mixture's second moment per axis in units of r_e^2: T = 2 r_e^2 * this
_MIXTURE_MOMENT = float(np.sum(P_EXP * (np.array([0.05072, 0.13756, 0.28781, 0.53195, 0.91209, 1.50157]) ** 2)))


@dataclass
class NoiseModel:
    """Background level and variance per pixel, in the frame's units."""

    background: float
    variance: float
    source: str
    detector: str = ""       # where read noise, dark current and gain came from


def frame_detector_model(frame):
    """The detector model that made ``frame`` (its MODEL table, written by ``perscli render``),
    else the default Roman model: ``(DetectorModel, 'MODEL' or 'roman')``."""
    model = model_of_frame(frame)
    return (model, "MODEL") if model is not None else (default_model(), "roman")


def noise_model(frame, *, sky=None, read_noise=None, dark=None) -> NoiseModel:
    """Background and variance from the frame's headers (never from its pixels).

    Read noise, dark current and gain come from the detector model that made
    the frame (:func:`frame_detector_model`): its read_noise.sigma,
    dark.current and gain.gain (0, 0 and the header's GAIN or 1 for effects
    that are off), or the default Roman model's for frames perscli did not
    render.

    Parameters
    ----------
    frame : perscli.io.frames.Frame
    sky : float, optional
        Background in the frame's units per pixel; default SKYRATE x EXPTIME
        (what ``perscli render`` writes) plus dark current.
    read_noise : float, optional
        Electrons; overrides the model's.
    dark : float, optional
        Dark current, e-/pixel/s; overrides the model's.
    """
    detector, where = frame_detector_model(frame)
    if read_noise is None:
        read_noise = detector.value("read_noise", "sigma", off=0.0)
    if dark is None:
        dark = detector.value("dark", "current", off=0.0)
    if where == "MODEL":
        gain = detector.value("gain", "gain", off=None) or frame.gain or 1.0
    else:
        gain = frame.gain or detector.value("gain", "gain", off=None) or 1.0
    exptime = frame.exptime
    is_dn = frame.unit in ("DN", "DN/s")
    to_units = 1.0 / gain if is_dn else 1.0
    if frame.unit.endswith("/s"):
        raise PerscliError(f"{frame.label}: measure needs a frame in electrons or DN, not a rate ({frame.unit})")
    rate = frame.keyword("SKYRATE")
    if sky is None:
        if rate is None or exptime is None:
            raise PerscliError(f"{frame.label}: no SKYRATE/EXPTIME in the header for the noise model; "
                               "give --sky LEVEL (frame units per pixel) or a WHT/VAR/ERR extension")
        sky_e = (float(rate) + dark) * exptime
        background = sky_e * to_units
        source = "SKYRATE"
    else:
        background = float(sky)
        sky_e = background / to_units
        source = "--sky"
    variance_e = max(sky_e, 0.0) + read_noise ** 2
    return NoiseModel(background=background, variance=variance_e * to_units ** 2, source=source, detector=where)


def _weight_hdu(frame):
    for hdu in frame.hdus:
        if hdu.name in ("WHT", "WEIGHT", "IVAR", "VAR", "VARIANCE", "ERR") and hdu.data_size:
            if hdu.shape[-2:] == frame.shape:
                return hdu
    return None


def _noise_and_weights(frame, *, sky, read_noise):
    """(NoiseModel, weight map or None, uniform inverse variance): the noise model of a frame."""
    weight_hdu = _weight_hdu(frame)
    if weight_hdu is None:
        noise = noise_model(frame, sky=sky, read_noise=read_noise)
        return noise, None, 1.0 / noise.variance
    w = np.asarray(weight_hdu.read(), dtype=np.float64)
    positive = w > 0
    if weight_hdu.name in ("VAR", "VARIANCE"):
        w = np.where(positive, 1.0 / np.where(positive, w, 1.0), 0.0)
    elif weight_hdu.name == "ERR":
        w = np.where(positive, 1.0 / np.where(positive, w, 1.0) ** 2, 0.0)
    if sky is None and frame.keyword("SKYRATE") is None:
        # a frame that carries its own weights and no sky model: taken as sky subtracted
        noise = NoiseModel(background=0.0, variance=float("nan"), source=weight_hdu.name)
    else:
        noise = noise_model(frame, sky=sky, read_noise=read_noise)
    return noise, w, float("nan")


def _ivar_at(weights, ivar, x, y) -> np.ndarray:
    """Inverse variance at FITS positions: the uniform value, or the median positive weight within 2 pixels."""
    if weights is None:
        return np.full(len(x), ivar)
    ny, nx = weights.shape
    out = np.zeros(len(x))
    for k, (xx, yy) in enumerate(zip(x, y)):
        ix, iy = int(math.floor(xx - 0.5)), int(math.floor(yy - 0.5))
        box = weights[max(iy - 2, 0):min(iy + 3, ny), max(ix - 2, 0):min(ix + 3, nx)]
        box = box[box > 0]
        out[k] = float(np.median(box)) if box.size else 0.0
    return out


def _start_size(cat, i, pixel_scale):
    """T of the start, pixel^2 (arcsec^2 for pixel_scale 1): from the catalogue hlr, else 0.3\"."""
    hlr = float(cat["hlr"][i]) if "hlr" in cat and np.isfinite(cat["hlr"][i]) and cat["hlr"][i] > 0 else 0.3
    return 2.0 * (hlr / pixel_scale) ** 2 * _MIXTURE_MOMENT


def catalogue_rate(cat, i, frame) -> float:
    """The object's flux in e-/s from its catalogue magnitude in the frame's FILTER through ZPT_AB (NaN without)."""
    zpt, filt = frame.keyword("ZPT_AB"), frame.keyword("FILTER")
    mag_col = f"mag_{str(filt).strip().lower()}" if filt else None
    if zpt is None or mag_col not in cat:
        return float("nan")

    rate = 10 ** (-0.4 * (float(cat[mag_col][i]) - float(zpt))) * roman.collecting_area
    return float(rate) if np.isfinite(rate) else float("nan")


def frame_units_per_rate(frame) -> float | None:
    """Frame units per e-/s of source: the exposure time (divided by the gain for a frame in DN)."""
    if not frame.exptime:
        return None
    return frame.exptime / (frame.gain or 1.0) if frame.unit == "DN" else frame.exptime


def _snr_table(model):
    """The :class:`SnrTable` of a model, made once."""
    table = getattr(model, "_snr_table", None)
    if table is None:
        table = model._snr_table = SnrTable(model)
    return table


class SnrTable:
    """sum(p^2) of a round, centred exponential of size T through one PSF, for :func:`predicted_snr`.

    The optimal S/N of a galaxy of flux F on a background of variance V per
    pixel is F sqrt(sum(p^2) / V), p its normalised image; sum(p^2) depends
    on T only (for a round galaxy) and is tabulated once per PSF, 0.005-20000
    pixel^2, interpolated in log-log.
    """

    def __init__(self, model: ExpModel):
        self.logT = np.linspace(np.log(5e-3), np.log(2e4), 121)
        c = float(model.n // 2)
        values = []
        for T in np.exp(self.logT):
            img = model.image((c, c, 0.0, 0.0, float(T), 1.0))
            values.append(float(np.sum(img * img)))
        self.logS = np.log(np.maximum(values, 1e-300))

    def __call__(self, T) -> np.ndarray:
        logT = np.log(np.clip(np.asarray(T, dtype=np.float64), 5e-3, 2e4))
        return np.exp(np.interp(logT, self.logT, self.logS))


def predicted_snr(cat, rows, frame, pixel_scale, table: SnrTable, ivar) -> np.ndarray:
    """The optimal S/N of catalogue rows on a frame, predicted without looking at its pixels.

    F sqrt(sum(p^2) ivar): F the catalogue magnitude in the frame's FILTER
    through ZPT_AB and the exposure time (frame units), p the normalised
    image of the round exponential of the catalogue's hlr (0.3" without
    one) through the frame's PSF (:class:`SnrTable`), ivar the inverse
    variance per pixel: sky, dark current and read noise of the noise model
    (:func:`noise_model`), or the frame's weight map at the object.  The
    source's own Poisson noise is left out (it matters only far above any
    cut).  NaN where the catalogue has no magnitude (or the frame no
    ZPT_AB/EXPTIME): such objects are not cut.
    """
    rows = np.asarray(rows, dtype=np.int64)
    per_rate = frame_units_per_rate(frame)
    out = np.full(len(rows), np.nan)
    if not per_rate:
        return out
    T = np.array([_start_size(cat, i, pixel_scale) for i in rows])
    rate = np.array([catalogue_rate(cat, i, frame) for i in rows])
    flux = rate * per_rate
    with np.errstate(invalid="ignore"):
        out = flux * np.sqrt(table(T) * np.asarray(ivar, dtype=np.float64))
    return np.where(np.isfinite(out), np.maximum(out, 0.0), np.nan)


def _check_min_snr(min_snr):
    if min_snr is None:
        return MIN_SNR_DEFAULT
    try:
        value = float(min_snr)
    except (TypeError, ValueError):
        raise PerscliError(f"--min-snr {min_snr!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise PerscliError(f"--min-snr {min_snr} must be a finite number >= 0 (0: fit every object on the frame)")
    return value
