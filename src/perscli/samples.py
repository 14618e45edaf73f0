"""Small sample exposures for the demo, the docs' examples and the tests.

:func:`make_sample_sequence` draws a short dithered sequence of Roman-like
exposures of one star field with GalSim: the Roman PSF of one SCA and
filter, bright (saturating) stars whose fluence leaves persistence in later
exposures, a flat sky, and headers such as a real frame carries (WCS,
EXPSTART/EXPEND from the Roman Wide Area Survey cadence, EXPTIME, BUNIT,
GAIN, SCA, FILTER).  The frames hold the charge collected in electrons and
no persistence, so ``perscli apply-persistence`` has something to add.
"""

from __future__ import annotations

import datetime as _dt
import os

import galsim
import galsim.roman as roman
import numpy as np
from astropy.io import fits

from . import __version__
from .instrument import ROMAN_EXPTIME, ROMAN_WAS_CADENCE
from .optics import bandpasses, quick_roman_psf

#: Roman WAS cadence: 139.8 s exposures starting ~169.8 s apart (a ~30 s gap).
EXPTIME = ROMAN_EXPTIME
CADENCE = ROMAN_WAS_CADENCE


def make_sample_sequence(outdir: str, *, n: int = 4, size: int = 256, seed: int = 20231101,
                         sca: int = 7, filter_name: str = "J129", start_mjd: float = 61541.972429,
                         ra: float = 10.0, dec: float = -44.0, nstars: int = 12) -> list:
    """Write ``n`` exposures ``exp1.fits`` ... ``expN.fits`` to ``outdir``.

    Parameters
    ----------
    outdir : str
        Destination folder (created if needed).
    n : int
        Number of exposures, in time order.
    size : int
        Side of the square cutout in pixels.
    seed : int
        Seed of the star field and the dithers; same seed, same pixels.
    sca, filter_name : int, str
        Roman SCA and filter whose PSF, WCS and zeropoint are used.
    start_mjd : float
        Start of the first exposure (default: the first exposure of the
        public Roman WAS schedule).
    ra, dec : float
        Field centre in degrees.
    nstars : int
        Stars in the field; magnitudes 12.5-18.5 so that the brightest exceed the full well.

    Returns
    -------
    list of str
        The paths written.
    """
    rng = np.random.default_rng(seed)
    os.makedirs(outdir, exist_ok=True)
    bandpass = bandpasses()[filter_name]
    psf = quick_roman_psf(sca, filter_name)
    centre = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
    scale = roman.pixel_scale
    # stars on a field a little larger than the cutout, so dithers move them in and out
    half = 0.55 * size * scale
    star_dx = rng.uniform(-half, half, nstars)
    star_dy = rng.uniform(-half, half, nstars)
    star_mag = rng.uniform(12.5, 18.5, nstars)
    sky_rate = 0.9  # e-/s/pixel, a typical Roman J129 zodiacal level
    paths = []
    for k in range(n):
        start = start_mjd + k * CADENCE / 86400.0
        dither = rng.uniform(-8, 8, 2) * scale  # arcsec
        image = galsim.ImageF(size, size, scale=scale)
        image.fill(sky_rate * EXPTIME)
        for dx, dy, mag in zip(star_dx, star_dy, star_mag):
            flux = 10 ** (-0.4 * (mag - bandpass.zeropoint)) * roman.collecting_area * EXPTIME
            pos = galsim.PositionD((dx + dither[0]) / scale + size / 2 + 0.5,
                                   (dy + dither[1]) / scale + size / 2 + 0.5)
            stamp_size = int(min(256, max(64, 16 * np.sqrt(flux / 1e5))))
            stamp = galsim.Convolve(psf, galsim.DeltaFunction(flux=flux)).drawImage(
                nx=stamp_size, ny=stamp_size, scale=scale, center=pos.round(),
                offset=pos - pos.round(), method="auto")
            bounds = stamp.bounds & image.bounds
            if bounds.isDefined():
                image[bounds] += stamp[bounds]
        pointing = centre.deproject(dither[0] * galsim.arcsec, dither[1] * galsim.arcsec)
        wcs = galsim.TanWCS(galsim.AffineTransform(-scale, 0, 0, scale,
                                                   origin=image.true_center),
                            world_origin=pointing, units=galsim.arcsec)
        header = {}
        wcs.writeToFitsHeader(header, image.bounds)
        hdr = fits.Header()
        for key, value in header.items():
            hdr[key] = value
        date_obs = _dt.datetime(1858, 11, 17) + _dt.timedelta(days=start)
        hdr["BUNIT"] = ("electron", "charge collected during the exposure")
        hdr["GAIN"] = (roman.gain, "[e-/DN]")
        hdr["EXPTIME"] = (EXPTIME, "[s] exposure time")
        hdr["EXPSTART"] = (start, "[MJD] exposure start")
        hdr["EXPEND"] = (start + EXPTIME / 86400.0, "[MJD] exposure end")
        hdr["DATE-OBS"] = (date_obs.isoformat(timespec="milliseconds"), "UTC start of the exposure")
        hdr["TELESCOP"] = "ROMAN"
        hdr["INSTRUME"] = "WFI"
        hdr["SCA"] = (sca, "sensor chip assembly")
        hdr["FILTER"] = filter_name
        hdr["RA_TARG"] = (pointing.ra.deg, "[deg] pointing")
        hdr["DEC_TARG"] = (pointing.dec.deg, "[deg] pointing")
        hdr["CREATOR"] = (f"perscli {__version__}", "software that made this file")
        hdr["SEED"] = (seed, "random seed of the star field")
        hdr.add_history("perscli sample frame: GalSim Roman PSF stars on a flat sky; no noise, no persistence")
        path = os.path.join(outdir, f"exp{k + 1}.fits")
        hdul = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(image.array.astype(np.float32), hdr, name="SCI")])
        hdul.writeto(path, overwrite=True, checksum=True)
        paths.append(path)
    return paths
