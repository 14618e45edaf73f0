"""The PSF of a shape fit: GalSim's Roman PSF, or an image read with its sampling and pixel response.

A PSF image is one of two things, and the fit must know which:

- an *optical* PSF, without the detector's pixel response (GalSim's
  ``drawImage(method='no_pixel')``, STPSF's OVERSAMP extension, what
  ``perscli measure --write-psf`` writes): the model multiplies its Fourier
  transform by the pixel's;
- an *effective* PSF, which includes it (PSFEx models, STPSF's DET_SAMP
  extension, images of stars): its transform holds the pixel's already, and
  applying it a second time widens the PSF by a pixel's variance (noiseless
  exponentials through Roman's J129 PSF given 4x oversampled with the pixel:
  mean |g error| 3e-3 with the pixel applied twice, 5e-6 without).

Header keywords of a PSF image (``--psf-pixel`` and ``--psf-oversampling``
override them):

========  =======  ==============================================================
keyword   value    meaning
========  =======  ==============================================================
PSFPIXEL  T/F      the image includes the detector pixel response (T) or not (F)
OVERSAMP  N        PSF pixels per detector pixel (STPSF; what --write-psf writes)
PSF_SAMP  s        PSF pixel in detector pixels (PSFEx): N = 1/s
PIXSCALE  arcsec   PSF pixel on the sky (PIXELSCL, STPSF's; CDELT1 in degrees):
                   N = the frame's pixel scale / it
SCA       1-18     with FILTER: which frames the image is for; in a file of several
FILTER    name     PSF images, each frame takes the one of its SCA and FILTER
========  =======  ==============================================================

The sampling is taken from the first of OVERSAMP, PSF_SAMP, PIXSCALE,
PIXELSCL, CDELT1 present: the keywords relative to the detector's pixels
first, because a PSF in the detector frame is fixed to its pixels, whatever
the sky scale of the frame's WCS (Roman's varies by a few percent over the
focal plane).  Without PSFPIXEL the pixel response is inferred, and the
assumption said on stderr: included for STPSF's detector-sampled extensions
(EXTNAME DET_SAMP, DET_DIST) and PSFEx models (PSF_SAMP), excluded otherwise
(an oversampled image is most often an optical model's).

Sampling.  The image is interpolated (quintic), which is exact only for an
image sampled finely enough that its Fourier transform vanishes before the
image's own Nyquist frequency.  Roman's PSF reaches D/lambda = 0.98 cycles per
0.11" pixel at J129: at the frame's own sampling (native, as PSFEx and STPSF's
DET_SAMP give) it is aliased, and no interpolation recovers it.  Noiseless
exponentials (hlr 0.15-0.45", |g| <= 0.3) measured through Roman's PSF given
at native sampling are off by a mean |g error| of 4e-4 (K213) to 5e-3 (Y106,
Z087) with the pixel included and up to 6e-2 without; given 2x oversampled
with the pixel, or 4x without, by 5e-5 or less for Z087 and redder filters
(3e-4 at R062).  So an image is refused
(:func:`check_sampling`) when

- its declared sampling is coarser than the frame's Roman filter needs:
  at least :data:`MIN_OVERSAMPLING` PSF pixels per frame pixel, and a Nyquist
  frequency of at least :data:`NYQUIST_FRACTION` of the optics' cutoff D/lambda
  at the filter's effective wavelength (R062: 2.4x, Z087: 1.7x, others 1.5x);
- or, whatever it declares, the image itself holds more than
  :data:`MAX_ALIASED_POWER` of its Fourier power beyond its Nyquist
  frequency (:func:`aliased_power`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import galsim
import galsim.roman as roman
import numpy as np
from scipy.signal.windows import tukey

from .. import PerscliError
from ..instrument import ROMAN_PIXEL_SCALE
from ..io.fitsfile import OutHDU
from ..io.fitsreader import open_fits
# GalSim's Roman PSF and filters: the ones render draws with
from ..optics import roman_psf, roman_wavelength, to_pixels

log = logging.getLogger(__name__)

#: PSF pixels per frame pixel of the images ``--write-psf`` writes, and their side (pixels): 512 at 4x
#: is 64 frame pixels, wider than the largest stamp's FFT grid, so that the PSF's wings that the fits
#: fold into a stamp are the same as --psf roman's (written 256 wide, shapes differ from --psf roman's
#: by up to 2e-4; 512 wide, by 4e-5 at J129)
WRITE_OVERSAMPLING = 4
WRITE_SIZE = 512
#: least PSF pixels per frame pixel accepted for a frame in a Roman filter
MIN_OVERSAMPLING = 1.5
#: least ratio of the image's Nyquist frequency 1/(2 PSF pixel) to the optics' cutoff D/lambda for a
#: Roman filter.  Why not 1 (Nyquist): the transfer function of Roman's obscured pupil is small
#: beyond 0.6 of the cutoff, and noiseless exponentials through images sampled at 0.6 to 0.65 of it
#: are within 2.4e-4 of their g on average (R062 2.5x, Y106 1.5x); Z087 at 1.5x (0.52) misses by 2.4e-3.
NYQUIST_FRACTION = 0.6
#: largest fraction of an image's Fourier power beyond its Nyquist frequency (in the corners of its
#: transform, |k| above the Nyquist frequency, after a cosine taper of its outer quarters that keeps
#: the edges from counting).  Roman's PSF at the frame's sampling, 1.5" to 7" images, any centring:
#: 2e-3 to 0.2 (all filters but K213, whose 9e-4 to 3e-3 goes with mean |g errors| of 4e-4, and which
#: the declared sampling catches); 2x oversampled with the pixel: < 1e-7 for J129 and redder filters,
#: 4e-4 at Z087; 4x, with or without the pixel: < 4e-5, and up to 7e-4 with Gaussian noise of 1e-3 of
#: the peak on a 3.5" image (noise counts too: a noisy image is interpolated no better).
MAX_ALIASED_POWER = 1e-3
#: mean |g error| of noiseless exponentials (hlr 0.15-0.45", |g| <= 0.3, 40 of them) measured through
#: Roman's PSF given at the frame's own sampling: (with the pixel response, without it), per filter.
#: The expected error with --allow-undersampled-psf (finer sampling errs less).
UNDERSAMPLED_ERRORS = {"R062": (3e-3, 8e-3), "Z087": (5e-3, 6e-2), "Y106": (5e-3, 2e-2), "J129": (2e-3, 8e-3),
                       "W146": (9e-4, 2e-3), "H158": (6e-4, 8e-4), "F184": (4e-4, 4e-4), "K213": (4e-4, 4e-4)}

_PIXEL_CHOICES = ("included", "excluded")


@dataclass
class PsfOptions:
    """How to read a PSF image: what the command line says, overriding its header.

    Attributes
    ----------
    pixel : {'included', 'excluded'} or None
        Whether the image includes the detector pixel response (None: from
        PSFPIXEL, else inferred with a warning).
    oversampling : float or None
        PSF pixels per frame pixel (None: from the header).
    allow_undersampled : bool
        Use an undersampled image anyway, with a warning giving the expected
        error, instead of refusing it.
    """

    pixel: str | None = None
    oversampling: float | None = None
    allow_undersampled: bool = False
    said: set = field(default_factory=set, repr=False, compare=False)

    def __post_init__(self):
        if self.pixel is not None and self.pixel not in _PIXEL_CHOICES:
            raise PerscliError(f"--psf-pixel {self.pixel!r}: give included or excluded")
        if self.oversampling is not None:
            try:
                value = float(self.oversampling)
            except (TypeError, ValueError):
                raise PerscliError(f"--psf-oversampling {self.oversampling!r} is not a number") from None
            if not (math.isfinite(value) and value > 0):
                raise PerscliError(f"--psf-oversampling {self.oversampling} must be a positive number "
                                   "(PSF pixels per frame pixel)")
            self.oversampling = value

    def warn(self, message: str):
        """A warning on stderr, once per run (several frames share a PSF)."""
        if message not in self.said:
            self.said.add(message)
            log.warning("%s", message)


@dataclass
class PsfModel:
    """The PSF a frame's fits use.

    Attributes
    ----------
    profile : galsim.GSObject
        In the frame's pixel units, flux 1.
    pixel_included : bool
        The profile includes the pixel response (the model must not apply it).
    source : str
        'roman' or the image's file name (with its HDU).
    image : ndarray or None
        The image as read (None for 'roman' until :meth:`written_image`).
    oversampling : float or None
        PSF pixels per frame pixel of ``image``.
    sca, filter : str
        Of the frame (for --write-psf and the selection of PSF images).
    pixel_scale : float
        The frame's pixel scale, arcsec.
    wavelength : float or None
        nm, for 'roman'.
    aliased_power : float or None
        :func:`aliased_power` of the image.
    """

    profile: object
    pixel_included: bool
    source: str
    image: np.ndarray | None = None
    oversampling: float | None = None
    sca: str = ""
    filter: str = ""
    pixel_scale: float = ROMAN_PIXEL_SCALE
    wavelength: float | None = None
    aliased_power: float | None = None
    arcsec_profile: object = field(default=None, repr=False)

    def written_image(self):
        """(image, PSF pixels per frame pixel, pixel included) for --write-psf.

        For 'roman': GalSim's PSF drawn :data:`WRITE_OVERSAMPLING` x finer
        than Roman's pixels, :data:`WRITE_SIZE` wide, without the pixel,
        from its Fourier transform (GalSim's FFT drawing: samples of the
        band-limited profile the fits use, so that the image interpolated
        back gives the same shapes to ~4e-5; drawn in real space, the
        interpolation of GalSim's own interpolated profile would add up to
        2e-4 at R062).
        """
        if self.image is not None:
            return self.image, self.oversampling, self.pixel_included

        scale = roman.pixel_scale / WRITE_OVERSAMPLING
        drawn = galsim.Convolve(self.arcsec_profile, galsim.DeltaFunction()).drawImage(
            nx=WRITE_SIZE, ny=WRITE_SIZE, scale=scale, method="no_pixel")
        return np.asarray(drawn.array, dtype=np.float64), float(WRITE_OVERSAMPLING), False


def frame_roman_psf(frame) -> PsfModel:
    """galsim.roman.getPSF for the frame's SCA and FILTER, at the SCA centre and the filter's effective
    wavelength (:func:`perscli.optics.roman_psf`, what ``perscli render`` draws with), in Roman pixels (0.11")."""
    sca, filt = frame.keyword("SCA"), frame.keyword("FILTER")
    if sca is None or filt is None:
        raise PerscliError(f"{frame.label}: --psf roman needs SCA and FILTER in the header; give --psf PSF.fits")
    name = str(filt).strip()
    wavelength = roman_wavelength(name)
    if wavelength is None:
        raise PerscliError(f"{frame.label}: FILTER={filt!r} is not a Roman filter; give --psf PSF.fits")
    try:
        sca_number = int(sca)
    except (TypeError, ValueError):
        raise PerscliError(f"{frame.label}: SCA={sca!r} is not a Roman SCA number (1-18)") from None
    psf = roman_psf(sca_number, name)
    return PsfModel(profile=to_pixels(psf), pixel_included=False, source="roman",
                    sca=str(sca_number), filter=name, pixel_scale=roman.pixel_scale, wavelength=wavelength,
                    arcsec_profile=psf)


def aliased_power(image) -> float:
    """Fraction of an image's Fourier power beyond its Nyquist frequency: in the corners of its discrete
    transform, |k| > pi per image pixel.

    A PSF sampled finely enough has a transform that vanishes before the
    Nyquist frequency, so its corners hold ~nothing; an undersampled one
    is aliased, and the folded power fills them, wherever the PSF's centre
    falls on the pixel grid (which the power along the Nyquist lines alone
    depends on).  The image, normalised to unit sum, is tapered (Tukey
    window, cosine over the outer quarter of each side) so that a PSF cut
    off at the image's edge does not count as high frequencies.
    """
    data = np.asarray(image, dtype=np.float64)
    data = data / data.sum()
    ny, nx = data.shape
    tapered = data * tukey(ny, 0.5)[:, None] * tukey(nx, 0.5)[None, :]
    power = np.abs(np.fft.fft2(tapered)) ** 2
    ky = 2.0 * np.fft.fftfreq(ny)[:, None]     # units of the Nyquist frequency
    kx = 2.0 * np.fft.fftfreq(nx)[None, :]
    total = float(power.sum())
    return float(power[np.hypot(kx, ky) > 1.0].sum() / total) if total > 0 else 0.0


def required_oversampling(filt, pixel_scale: float) -> float | None:
    """Least PSF pixels per frame pixel for a frame in a Roman filter (None for other filters).

    max(:data:`MIN_OVERSAMPLING`, 2 NYQUIST_FRACTION x pixel / (lambda/D)):
    the image's Nyquist frequency at least NYQUIST_FRACTION of the cutoff
    D/lambda at the filter's effective wavelength.
    """
    wavelength = roman_wavelength(filt)
    if wavelength is None:
        return None
    lambda_over_d = wavelength * 1e-9 / roman.diameter * 180.0 / math.pi * 3600.0
    return max(MIN_OVERSAMPLING, 2.0 * NYQUIST_FRACTION * pixel_scale / lambda_over_d)


def _number(value, key, label, signed: bool = False) -> float:
    """A positive header value (its absolute value with ``signed``)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise PerscliError(f"{label}: {key} = {value!r} is not a number") from None
    if signed:
        number = abs(number)
    if not (math.isfinite(number) and number > 0):
        raise PerscliError(f"{label}: {key} = {value!r} must be a positive number")
    return number


def psf_sampling(keyword, label: str, pixel_scale: float, options: PsfOptions, warn=None):
    """PSF pixels per frame pixel, and where that came from.

    ``keyword(name)`` reads the PSF image's header.  Order: --psf-oversampling,
    OVERSAMP, PSF_SAMP, PIXSCALE, PIXELSCL, CDELT1 (see the module's docstring).
    ``warn(message)`` (default ``options.warn``) takes a doubt about them.
    """
    warn = warn if warn is not None else options.warn
    angular = None
    for key, factor in (("PIXSCALE", 1.0), ("PIXELSCL", 1.0), ("CDELT1", 3600.0)):
        if keyword(key) is not None:
            # CDELT1 is negative on a sky image whose RA grows to the left
            angular = (key, _number(keyword(key), key, label, signed=True) * factor)
            break
    if options.oversampling is not None:
        return options.oversampling, f"--psf-oversampling {options.oversampling:g}"
    relative = None
    if keyword("OVERSAMP") is not None:
        relative = (_number(keyword("OVERSAMP"), "OVERSAMP", label), f"OVERSAMP = {keyword('OVERSAMP')}")
    elif keyword("PSF_SAMP") is not None:
        relative = (1.0 / _number(keyword("PSF_SAMP"), "PSF_SAMP", label), f"PSF_SAMP = {keyword('PSF_SAMP')}")
    if relative is not None:
        if angular is not None:
            detector = angular[1] * relative[0]
            if abs(detector / pixel_scale - 1.0) > 0.1:
                warn(f"{label}: {relative[1]} with {angular[0]} = {angular[1]:.4g}\" describes a detector "
                     f"of {detector:.3g}\" pixels, the frame's are {pixel_scale:.3g}\": is the PSF for "
                     f"this instrument? ({relative[1].split(' =')[0]} used)")
        return relative
    if angular is not None:
        return pixel_scale / angular[1], f"{angular[0]} = {angular[1]:.4g}\""
    raise PerscliError(f"{label}: no PIXSCALE (arcsec), CDELT1 (deg), OVERSAMP or PSF_SAMP keyword: the PSF "
                       "image's sampling is needed; give --psf-oversampling N (PSF pixels per frame pixel)")


def psf_includes_pixel(keyword, label: str, options: PsfOptions, warn=None) -> bool:
    """Whether the PSF image includes the pixel response: --psf-pixel, PSFPIXEL, else inferred and
    the assumption given to ``warn`` (default ``options.warn``)."""
    warn = warn if warn is not None else options.warn
    if options.pixel is not None:
        return options.pixel == "included"
    declared = keyword("PSFPIXEL")
    if declared is not None:
        if isinstance(declared, bool):
            return declared
        text = str(declared).strip().upper()
        if text in ("T", "TRUE", "1", "Y", "YES"):
            return True
        if text in ("F", "FALSE", "0", "N", "NO"):
            return False
        raise PerscliError(f"{label}: PSFPIXEL = {declared!r}: it must be T (the image includes the detector "
                           "pixel response) or F; or give --psf-pixel included|excluded")
    extname = str(keyword("EXTNAME") or "").strip().upper()
    hint = "give --psf-pixel included|excluded (or PSFPIXEL = T/F in its header) to say which"
    if extname.startswith("DET_"):
        warn(f"{label}: no PSFPIXEL keyword; taken to include the pixel response, as STPSF's "
             f"detector-sampled EXTNAME {extname} does; {hint}")
        return True
    if keyword("PSF_SAMP") is not None:
        warn(f"{label}: no PSFPIXEL keyword; taken to include the pixel response, as a PSFEx model "
             f"(PSF_SAMP), made from images of stars, does; {hint}")
        return True
    warn(f"{label}: no PSFPIXEL keyword; taken as an optical PSF without the pixel response (as "
         "GalSim's drawImage(method='no_pixel') and STPSF's OVERSAMP extension give); if it includes "
         f"it (PSFEx, STPSF's DET_SAMP, images of stars) the shapes will be wrong: {hint}")
    return False


def _roman_number(name) -> str:
    """'129' for J129 or F129 (GalSim's and STPSF's names of one Roman filter), else the name."""
    text = str(name or "").strip().upper()
    return text[1:] if len(text) == 4 and text[0].isalpha() and text[1:].isdigit() else text


def _same_detector(header_get, frame) -> bool:
    """False when the PSF image's SCA or FILTER keyword names another than the frame's (both present)."""
    for key, norm in (("SCA", _sca_number), ("FILTER", _roman_number)):
        mine, theirs = header_get(key), frame.keyword(key)
        if mine is not None and theirs is not None and norm(mine) != norm(theirs):
            return False
    return True


def _sca_number(value) -> str:
    text = str(value).strip()
    return str(int(text)) if text.isdigit() else text.upper()


def _describe(header_get) -> str:
    parts = []
    if header_get("SCA") is not None:
        parts.append(f"SCA {header_get('SCA')}")
    if header_get("FILTER") is not None:
        parts.append(str(header_get("FILTER")).strip())
    return " ".join(parts) or "no SCA/FILTER"


def read_psf_image(spec: str, frame, warn=log.warning):
    """The PSF image of a file for a frame: (data float64, keyword(name) getter, label).

    A file with one image (or ``file.fits[EXT]``): that image.  With several:
    the one whose SCA and FILTER keywords match the frame's.  ``warn(message)``
    takes the warning for an image whose SCA or FILTER is not the frame's.
    """
    try:
        source = open_fits(spec)
    except PerscliError as exc:
        raise PerscliError(f"--psf: {exc}") from None
    try:
        hdus = source.hdus
        if source.selected is not None:
            images = [hdus[source.selected]]
        else:
            images = [h for h in hdus if h.is_image and h.shape and 0 not in h.shape]
        primary = hdus[0].header

        def getter(hdu):
            def get(key):
                for header in (hdu.header, primary):
                    if key in header and header[key] not in (None, ""):
                        return header[key]
                return None
            return get

        if not images:
            raise PerscliError(f"{source.label}: no image: --psf needs a FITS image of the PSF")
        if len(images) > 1:
            tagged = [h for h in images if "SCA" in h.header or "FILTER" in h.header]
            if not tagged:
                names = ", ".join(h.name or f"HDU {h.index}" for h in images)
                raise PerscliError(f"{source.label}: holds {len(images)} images ({names}) without SCA/FILTER "
                                   f"keywords: select one, e.g. '{spec}[{images[0].name or images[0].index}]'")
            matches = [h for h in tagged if _same_detector(getter(h), frame)]
            if len(matches) != 1:
                have = "; ".join(_describe(getter(h)) for h in tagged)
                want = f"SCA {frame.keyword('SCA')} {str(frame.keyword('FILTER') or '').strip()}"
                if not matches:
                    raise PerscliError(f"{source.label}: none of its PSF images is for {frame.label}'s {want} "
                                       f"(it has {have}); give a PSF for it, e.g. with --psf roman --write-psf")
                raise PerscliError(f"{source.label}: {len(matches)} PSF images are for {want}: select one with "
                                   f"'{spec}[EXT]'")
            images = matches
        hdu = images[0]
        get = getter(hdu)
        label = source.label
        if source.selected is None and hdu.index != 0:
            name = f"{hdu.name},{hdu.ver}" if hdu.name and hdu.ver > 1 else (hdu.name or str(hdu.index))
            label = f"{source.label}[{name}]"
        if len(hdu.shape) != 2:
            raise PerscliError(f"{label}: the PSF image has {len(hdu.shape)} axes; expected 2 (select one plane)")
        if not _same_detector(get, frame):
            frame_says = f"SCA {frame.keyword('SCA')} {str(frame.keyword('FILTER') or '').strip()}"
            warn(f"{label}: the PSF is for {_describe(get)}, {frame.label} is {frame_says}")
        data = np.array(hdu.read(), dtype=np.float64)
        if source.section is not None:
            data = data[source.section]          # file.fits[EXT][x1:x2,y1:y2]: the PSF in that box
        # the header as a plain dict: the file is closed before the keywords are used
        keys = ("PSFPIXEL", "OVERSAMP", "PSF_SAMP", "PIXSCALE", "PIXELSCL", "CDELT1", "SCA", "FILTER")
        values = {key: get(key) for key in keys}
        values["EXTNAME"] = hdu.name or None      # this HDU's own: the primary's names another image
    finally:
        source.close()
    if data.shape[0] < 4 or data.shape[1] < 4:
        raise PerscliError(f"{label}: a PSF image of {data.shape[1]}x{data.shape[0]} pixels is too small")
    if not np.all(np.isfinite(data)) or data.sum() <= 0:
        raise PerscliError(f"{label}: the PSF image has non-finite values or no positive flux")
    return data, values.get, label


def check_sampling(label: str, oversampling: float, where: str, power: float, frame, pixel_scale: float,
                   pixel_included: bool, options: PsfOptions, warn=None) -> None:
    """Refuse (PerscliError) an undersampled PSF image, or with ``allow_undersampled`` warn with the expected error.

    Undersampled: coarser than :func:`required_oversampling` for the frame's
    Roman filter, or more than :data:`MAX_ALIASED_POWER` of its Fourier
    power beyond its Nyquist frequency.
    """
    filt = str(frame.keyword("FILTER") or "").strip()
    need = required_oversampling(filt, pixel_scale)
    remedy = ("give an image sampled 4x finer than the frame (perscli measure --psf roman --write-psf PSF.fits "
              "writes GalSim's Roman PSF so) or --psf roman")
    reason = None
    if need is not None and oversampling < need * (1.0 - 1e-6):
        reason = (f"undersampled for {filt}: {oversampling:.3g} PSF pixels per frame pixel of {pixel_scale:.3g}\" "
                  f"({where}), while interpolating Roman's PSF at {roman_wavelength(filt):.0f} nm needs "
                  f"{need:.3g} or more (PSF pixels of {pixel_scale / need:.3g}\" or less)")
    elif power > MAX_ALIASED_POWER:
        reason = (f"undersampled: {100 * power:.2g}% of its Fourier power lies beyond its Nyquist frequency "
                  f"({oversampling:.3g} PSF pixels per frame pixel, {where}), where a PSF image sampled "
                  f"finely enough, and not noisy, has almost none (at most {100 * MAX_ALIASED_POWER:.2g}%), "
                  "so it cannot be interpolated accurately")
    if reason is None:
        return
    if not options.allow_undersampled:
        raise PerscliError(f"{label}: {reason}; {remedy}")
    errors = UNDERSAMPLED_ERRORS.get(filt)
    form = "with" if pixel_included else "without"
    if errors is not None:
        expected = errors[0] if pixel_included else errors[1]
        basis = (f"the mean |g error| of noiseless exponentials measured through Roman's {filt} PSF given at "
                 f"the frame's own sampling {form} the pixel response")
    else:
        column = [v[0] if pixel_included else v[1] for v in UNDERSAMPLED_ERRORS.values()]
        expected = max(column)
        basis = (f"mean |g errors| of {min(column):.0e} to {max(column):.0e} for Roman's PSFs R062-K213 given at "
                 f"the frame's own sampling {form} the pixel response")
    warn = warn if warn is not None else options.warn
    warn(f"--allow-undersampled-psf: {label} is {reason}; expect shape errors of ~{expected:.0e} in g ({basis}), "
         "against < 1e-4 with an image sampled 4x finer than the frame")


def psf_model(spec: str, frame, *, pixel_scale: float, options: PsfOptions | None = None) -> PsfModel:
    """The PSF of a frame's fits: 'roman' (:func:`frame_roman_psf`) or a FITS image.

    Parameters
    ----------
    spec : str
        'roman', or a PSF image (``file.fits`` or ``file.fits[EXT]``) with
        the keywords of the module's docstring.
    frame : perscli.io.frames.Frame
    pixel_scale : float
        The frame's pixel scale, arcsec.
    options : PsfOptions
        --psf-pixel, --psf-oversampling, --allow-undersampled-psf.

    Raises
    ------
    PerscliError
        No sampling keyword, an unreadable or empty image, or an undersampled
        one (:func:`check_sampling`).
    """
    options = options if options is not None else PsfOptions()
    if spec == "roman":
        return frame_roman_psf(frame)
    # warnings wait until the image is accepted: a refusal is one line
    notes = []
    data, keyword, label = read_psf_image(spec, frame, warn=notes.append)
    oversampling, where = psf_sampling(keyword, label, pixel_scale, options, warn=notes.append)
    pixel_included = psf_includes_pixel(keyword, label, options, warn=notes.append)
    power = aliased_power(data)
    check_sampling(label, oversampling, where, power, frame, pixel_scale, pixel_included, options, warn=notes.append)
    for note in notes:
        options.warn(note)
    log.info("%s: PSF image %dx%d, %.3g PSF pixels per frame pixel (%s), pixel response %s, %.2g of its "
             "Fourier power beyond Nyquist", label, data.shape[1], data.shape[0], oversampling, where,
             "included" if pixel_included else "excluded", power)
    profile = galsim.InterpolatedImage(galsim.Image(data, scale=1.0 / oversampling), x_interpolant="quintic",
                                       normalization="flux")
    return PsfModel(profile=profile, pixel_included=pixel_included, source=label, image=data,
                    oversampling=oversampling, sca=str(frame.keyword("SCA") or "").strip(),
                    filter=str(frame.keyword("FILTER") or "").strip(), pixel_scale=pixel_scale,
                    aliased_power=power)


def psf_hdus(models) -> list:
    """--write-psf: one image HDU per PSF (EXTNAME PSF, EXTVER 1, 2, ...) with the keywords that read it back."""
    hdus = []
    for k, model in enumerate(models, 1):
        image, oversampling, pixel_included = model.written_image()
        hdu = OutHDU([], data=np.ascontiguousarray(image, dtype=np.float64), extname="PSF")
        hdu["EXTVER"] = (k, "one PSF per SCA and FILTER")
        hdu["PSFPIXEL"] = (bool(pixel_included), "image includes the detector pixel response")
        hdu["OVERSAMP"] = (float(oversampling), "PSF pixels per detector pixel")
        hdu["PIXSCALE"] = (model.pixel_scale / float(oversampling), "[arcsec] PSF pixel")
        if model.sca:
            hdu["SCA"] = (int(model.sca) if model.sca.isdigit() else model.sca, "detector the PSF is for")
        if model.filter:
            hdu["FILTER"] = (model.filter, "filter the PSF is for")
        if model.wavelength is not None:
            hdu["WAVELEN"] = (round(model.wavelength, 3), "[nm] wavelength of the PSF")
        hdu["PSFSRC"] = ("galsim.roman.getPSF" if model.source == "roman" else model.source.split("/")[-1][:68],
                         "where the PSF came from")
        hdu["PSFNORM"] = ("flux", "the fits normalise the image to unit sum")
        hdus.append(hdu)
    return hdus

