"""The settings of ``perscli measure``, with their defaults written once.

:class:`MeasureOptions` is the one home of how measure fits shapes (in the
manner of :class:`perscli.stats.settings.CorrelateOptions`): the library
(:func:`perscli.measure.shapes.measure_files`,
:func:`perscli.measure.perframe.measure_frame`,
:func:`perscli.measure.joint.measure_joint`) takes one, the command's
options show and use its defaults, and a study's ``measure`` section starts
from them.  What to measure (frames, catalogue, output), the workers and
the progress callbacks stay parameters of the functions.  This module
imports nothing heavy, so that ``perscli measure --help`` stays fast.
"""

from __future__ import annotations

import dataclasses

from ..settings import setting

#: default cut on the predicted S/N (:func:`perscli.measure.noise.predicted_snr`).  Why 5: the fitted
#: flux S/N (flux / its error, what flag 2048 tests against 5) is ~0.6 of the predicted optimal S/N, so
#: a galaxy predicted below 5 is fitted at S/N ~3 and is flagged 2048 unless noise lifts it: on a full
#: J129 SCA at the paper's densities 921 of the 2242 galaxies lie below 5, and 4 of them (0.4%) came out
#: unflagged before the cut, at the cost of 86 model evaluations each (62% of all the fitting).  Their
#: shapes carry no information.
MIN_SNR_DEFAULT = 5.0


@dataclasses.dataclass(frozen=True)
class MeasureOptions:
    """How ``perscli measure`` selects objects and fits their shapes.

    Attributes
    ----------
    psf : str
        'roman' (GalSim's Roman PSF for each frame's SCA and FILTER) or a PSF
        image, ``file.fits[EXT]`` (:func:`perscli.measure.psf.psf_model`).
    psf_pixel : {'included', 'excluded'} or None
        Whether the PSF image includes the detector pixel response (None: its
        PSFPIXEL keyword, else inferred with a warning).  Only with a PSF image.
    psf_oversampling : float or None
        PSF pixels per frame pixel of the PSF image (None: its header).  Only
        with a PSF image.
    allow_undersampled_psf : bool
        Fit through an undersampled PSF image, with a warning, instead of
        refusing it.  Only with a PSF image.
    method : {'exp', 'hsm'}
        exp: the exponential-mixture fit; hsm: GalSim's REGAUSS.
    stamp : int
        Largest stamp side in pixels (even, >= 16); an exp fit uses the
        smallest side on the ladder 16, 24, ... that holds the galaxy, hsm
        this one.
    sky : float or None
        Background per pixel in the frame's units (None: SKYRATE x EXPTIME +
        dark, from the header and detector model).
    read_noise : float or None
        Read noise in electrons of the noise model, for frames without a
        weight HDU (None: the frame's detector model's, else Roman's).
    blend_radius : float
        Flag objects with another catalogue object this close, in pixels (0:
        never).
    kinds : None, 'all', str or sequence of str
        Catalogue kinds to fit (:func:`perscli.measure.selection.select_kinds`):
        None the galaxies, or every row of a catalogue without a kind column.
    min_snr : float
        Fit only objects whose S/N predicted from the catalogue reaches this
        (0: no cut; a catalogue without a magnitude column for the frame's filter: every object fitted).
    all_rows : bool
        Also write rows, without a fit, for selected objects off the frame
        (flag 256) and below ``min_snr`` (flag 4096).
    joint : bool
        One fit per galaxy over all the frames, on the sky (only
        :func:`~perscli.measure.shapes.measure_files` reads it: it chooses
        between measure_frame and measure_joint).
    columns : dict or None
        Column names {perscli name: catalogue column} of a catalogue another
        tool wrote (:func:`perscli.measure.selection.read_positions`; only
        measure_files reads the catalogue).
    """

    psf: str = setting("roman", "file_or", "roman: GalSim's Roman PSF for the frame's SCA and FILTER.  Or a PSF "
                       "image (file.fits[EXT] picks an HDU; of several, each frame takes the one of its SCA and "
                       "FILTER) sampled finer than the frame, 4x ideally: its sampling from --psf-oversampling, "
                       "OVERSAMP (PSF pixels per detector pixel), PSF_SAMP (PSFEx: 1/that), PIXSCALE or PIXELSCL "
                       "(arcsec) or CDELT1 (deg); refused if undersampled (coarser than 1.5x, R062 2.4x, Z087 1.7x, "
                       "for a Roman filter; or with power beyond its own Nyquist frequency).",
                       choices=("roman",), metavar="roman|PSF.fits")
    psf_pixel: str | None = setting(None, "choice", "Whether the PSF image includes the detector pixel response (then "
                                    "the fit does not apply it again), overriding its PSFPIXEL keyword (T/F).  "
                                    "Without either: included for STPSF's DET_SAMP/DET_DIST extensions and PSFEx "
                                    "models (PSF_SAMP), else excluded (an optical PSF), with a warning.",
                                    choices=("included", "excluded"), show_default=False)
    psf_oversampling: float | None = setting(None, "float", "PSF pixels per frame pixel of the PSF image, overriding "
                                             "its header.", lo=0, lo_open=True, metavar="N", show_default=False)
    allow_undersampled_psf: bool = setting(False, "flag", "Fit with an undersampled PSF image instead of refusing it, "
                                           "with a warning giving the expected shape error (Roman's PSF at the "
                                           "frame's own sampling: 4e-4 to 5e-3 in g with the pixel response, up to "
                                           "6e-2 without).")
    method: str = setting("exp", "choice", "exp: exponential-mixture fit (exact PSF, analytic Jacobian); hsm: GalSim "
                          "REGAUSS.", choices=("exp", "hsm"))
    stamp: int = setting(48, "int", "Largest stamp side.  An exp fit uses the smallest of 16, 24, 32, ... up to it "
                         "that holds 4 catalogue half-light radii + 3 pixels each side of the centre (smaller "
                         "galaxies, smaller FFTs, fewer neighbours); --method hsm uses this side.", metavar="PIXELS")
    sky: float | None = setting(None, "float", "Background per pixel in the frame's units [default: SKYRATE x EXPTIME "
                                "+ dark].", metavar="LEVEL", show_default=False)
    read_noise: float | None = setting(None, "float", "Read noise (electrons) of the noise model, when the frame has "
                                       "no weight HDU [default: read_noise.sigma of the frame's detector model (MODEL "
                                       "table), else Roman's 8.5].", lo=0, metavar="E", show_default=False)
    blend_radius: float = setting(4.0, "float", "Flag objects with another catalogue object this close (0: never).",
                                  lo=0, metavar="PIXELS")
    kinds: str | tuple | None = setting(None, "text", "Catalogue kinds to fit (its kind column: galaxy, star), "
                                        "comma-separated, or all [default: galaxy; every row of a catalogue without "
                                        "a kind column].", metavar="galaxy|LIST|all", show_default=False)
    min_snr: float = setting(MIN_SNR_DEFAULT, "float", "Fit only objects whose S/N predicted from the catalogue "
                             "(magnitude through ZPT_AB, hlr, PSF, sky + dark + read noise; never the pixels) is at "
                             "least X; 0: no cut.  The objects of a catalogue without a magnitude column for the "
                             "frame's filter are always fitted (a magnitude that is not a number is refused).",
                             metavar="X")
    all_rows: bool = setting(False, "flag", "Also write rows, without a fit, for selected objects off the frame (flag "
                             "256) and below --min-snr (flag 4096).")
    joint: bool = setting(False, "flag", "One fit per galaxy over all the FRAMEs it falls on (one filter; WCS and "
                          "EXPTIME needed), with g, T, flux and position on the sky: a JOINT table.")
    columns: dict | None = None

    def psf_options(self):
        """A new :class:`perscli.measure.psf.PsfOptions` of the PSF image settings.

        New on each call because a PsfOptions records the warnings it has
        given: one per run, shared by its frames, says each once.
        """
        from .psf import PsfOptions  # lazy: --help reads MeasureOptions; measure.psf imports galsim

        return PsfOptions(pixel=self.psf_pixel, oversampling=self.psf_oversampling,
                          allow_undersampled=self.allow_undersampled_psf)
