"""Instrument constants: the one place where Roman's and WFC3-IR's numbers are written.

Everything else imports them from here, so that a number such as the Roman
exposure time is written once.  The Roman values are those of GalSim's Roman
module (``galsim.roman``) and of the public Roman Wide Area Survey schedule;
the WFC3-IR values those of the HST data handbook and STScI's persistence
pipeline.

Roman Wide-Field Instrument
---------------------------
=========================  ==========  ================================================
name                       value       meaning
=========================  ==========  ================================================
ROMAN_EXPTIME              139.8 s     exposure time of the Wide Area Survey
                                       (``galsim.roman.exptime``; GalSim used 140.25 s
                                       before 2023, the value the paper quotes)
ROMAN_WAS_GAP              30.0 s      from the end of one survey exposure to the
                                       start of the next (reset and slew)
ROMAN_WAS_CADENCE          169.8 s     exposure starts: ROMAN_EXPTIME + ROMAN_WAS_GAP
ROMAN_PIXEL_SCALE          0.11"       arcsec per pixel
ROMAN_SCA_SIZE             4088        active pixels per side of an SCA
ROMAN_DETECTOR_SIZE        4096        pixels per side of the H4RG-10, reference pixels included
ROMAN_N_SCA                18          SCAs in the focal plane, numbered 1-18
ROMAN_GAIN                 1.0         e-/DN
ROMAN_READ_NOISE           8.5 e-      per pixel, Gaussian
ROMAN_DARK_CURRENT         0.015       e-/pixel/s
ROMAN_NONLINEARITY_BETA    -6e-7       classical nonlinearity: f(x) = x + beta x^2
ROMAN_RECIPROCITY_ALPHA    0.0065      reciprocity failure per decade of flux
ROMAN_FULL_WELL            1.0e5 e-    charge a pixel holds before saturating (H4RG-10;
                                       twice the paper's half_well of 5e4 e-)
ROMAN_FILTERS              R062 ...    the imaging filters, in order of wavelength
=========================  ==========  ================================================

HST WFC3-IR
-----------
WFC3_IR_CCDGAIN (2.5 e-/DN) is the gain of raw (DN) ramps.  (STScI's own
persistence model for WFC3-IR is not used by perscli: its parameters are in
the project's field notes, section 1.)
"""

from __future__ import annotations

#: [s] exposure time of the Roman Wide Area Survey (``galsim.roman.exptime``).
ROMAN_EXPTIME = 139.8

#: [e-] full well of Roman's H4RG-10 detectors: collected charge saturates here (twice the
#: paper's half_well, 5e4 e-; romanisim's 55,000 DN saturation flag is a pipeline threshold, not the well).
ROMAN_FULL_WELL = 1.0e5

#: [s] GalSim's Roman exposure time before 2023 (and the paper's): for comparisons only.
GALSIM_OLD_EXPTIME = 140.25

#: [s] from the end of one Wide Area Survey exposure to the start of the next.
ROMAN_WAS_GAP = 30.0

#: [s] between the starts of consecutive Wide Area Survey exposures.
ROMAN_WAS_CADENCE = ROMAN_EXPTIME + ROMAN_WAS_GAP

#: [arcsec] per pixel (``galsim.roman.pixel_scale``).
ROMAN_PIXEL_SCALE = 0.11

#: Active pixels per side of an SCA (``galsim.roman.n_pix``).
ROMAN_SCA_SIZE = 4088

#: Pixels per side of the H4RG-10 detector, its 4-pixel border of reference pixels included.
ROMAN_DETECTOR_SIZE = 4096

#: SCAs in the focal plane, numbered 1 to ROMAN_N_SCA (``galsim.roman.n_sca``).
ROMAN_N_SCA = 18

#: [e-/DN] (``galsim.roman.gain``).
ROMAN_GAIN = 1.0

#: [e-] per pixel (``galsim.roman.read_noise``).
ROMAN_READ_NOISE = 8.5

#: [e-/pixel/s] (``galsim.roman.dark_current``).
ROMAN_DARK_CURRENT = 0.015

#: Classical nonlinearity, f(x) = x + beta x^2 in electrons (``galsim.roman.nonlinearity_beta``).
ROMAN_NONLINEARITY_BETA = -6.0e-7

#: Reciprocity failure per decade of flux (``galsim.roman.reciprocity_alpha``).
ROMAN_RECIPROCITY_ALPHA = 0.0065

#: The imaging filters (``galsim.roman.getBandpasses``), in order of wavelength; W146 is the wide one.
ROMAN_FILTERS = ("R062", "Z087", "Y106", "J129", "H158", "F184", "K213", "W146")

#: [e-/DN] gain of HST WFC3-IR raw ramps (the CCDGAIN keyword).
WFC3_IR_CCDGAIN = 2.5

