"""``perscli measure``: galaxy shapes by exponential-profile fitting."""

from __future__ import annotations

import logging

import click

from ..executor import keep_freed_memory
from ..measure.settings import MeasureOptions
from .helpers import FILE, PerscliCommand, check_fits_name, check_outputs, progress_reporter, report_errors
from .options import (columns_opt, no_checksum_opt, output_opt, overwrite_opt, settings_options, verbosity_opts,
                      workers_opt)

log = logging.getLogger("perscli")

#: work below this many steps tells a log (stderr not a terminal) nothing: a full SCA's galaxies take minutes, a
#: cutout's few dozen seconds
PROGRESS_LEAST = 500


@click.command("measure", cls=PerscliCommand,
               short_help="Measure galaxy shapes on frames by exponential-profile fits.")
@click.argument("frames", nargs=-1, required=True, metavar="FRAME...", type=FILE)
@click.option("--catalog", required=True, metavar="CAT.fits", type=FILE,
              help="Objects to measure: id and ra/dec (degrees) or x/y (FITS pixels); hlr and mag_<FILTER> "
                   "columns, when present, give the starting point.  Checked as render checks it: unique ids, "
                   "RA/Dec on the sky, hlr >= 0 (> 0 for a galaxy), |e| < 1.")
@settings_options(MeasureOptions, "psf", "psf_pixel", "psf_oversampling", "allow_undersampled_psf")
@click.option("--write-psf", default=None, type=FILE, metavar="PSF.fits",
              help="Also write the PSF images used, one HDU per SCA and FILTER, readable as --psf (with "
                   "--psf roman: GalSim's Roman PSF drawn 4x oversampled without the pixel; PSFPIXEL = F, "
                   "OVERSAMP = 4, PIXSCALE, SCA, FILTER).")
@settings_options(MeasureOptions, "method", "stamp", "sky", "read_noise", "blend_radius", "kinds", "min_snr",
                  "all_rows", "joint")
@columns_opt("the --catalog", "id=NUMBER,ra=ALPHA_J2000,dec=DELTA_J2000")
@no_checksum_opt
@output_opt
@overwrite_opt
@workers_opt("processes fitting the objects (the output does not depend on N)")
@verbosity_opts
@report_errors
def measure(frames, catalog, psf, psf_pixel, psf_oversampling, allow_undersampled_psf, write_psf, method, stamp,
            sky, read_noise, blend_radius, kinds, min_snr, all_rows, joint, columns, output, overwrite, workers):
    """Measure the shapes of the catalogue's galaxies on each FRAME, or jointly over all of them.

    Which objects: the catalogue rows of --kinds (the galaxies, by the truth
    catalogue's kind column; every row of a catalogue without one) whose
    position falls on the frame, and whose S/N predicted from the catalogue
    alone is at least --min-snr (default 5: below it the fitted S/N is ~3
    and the shape is noise).  The prediction uses the magnitude in the frame's
    FILTER through ZPT_AB, the catalogue hlr, the PSF and the noise model,
    never the pixels, so frames with and without persistence fit the same
    objects.

    The exponential profile is the 6-Gaussian mixture of Hogg & Lang, with
    parameters (x, y, g1, g2, T, flux); it is convolved with the PSF exactly,
    in Fourier space (the PSF's transform times the pixel response, folded
    above Nyquist), and fitted by a damped Newton method (Levenberg-Marquardt
    on the full Hessian: the analytic Jacobian and the residual's
    second-order term, from the same compiled pass) in float64 to 1e-10, in
    about 10 model evaluations.  The start (catalogue position, round, the
    catalogue's size and flux) and the weights (WHT/VAR/ERR HDU, else the sky
    from the header, and the dark current, read noise and gain of the detector
    model that rendered the frame, or Roman's) never depend on its pixel noise,
    so shape changes between two frames that differ by a small pattern are
    that pattern's alone (linear down to ~1e-10).  Only when the catalogue has
    no magnitude for the frame's FILTER is the start flux solved from the data.

    The PSF: GalSim's Roman PSF for the frame's SCA and FILTER (--psf roman),
    or an image.  An image is an optical PSF, without the detector pixel
    response (PSFPIXEL = F: GalSim's drawImage(method='no_pixel'), STPSF's
    OVERSAMP extension, what --write-psf writes), which the fit multiplies by
    the pixel's response; or an effective PSF that includes it (PSFPIXEL = T:
    PSFEx models, STPSF's DET_SAMP extension, images of stars), which the fit
    must not give it again.  Say which with PSFPIXEL or --psf-pixel; without
    either a warning states the assumption.  The image is interpolated, which
    is accurate only for an image sampled finer than the frame: Roman's PSF
    at the frame's own sampling (PSFEx, DET_SAMP) is aliased, and shapes
    measured through it are off by 4e-4 to 5e-3 in g (more without the
    pixel), so an image coarser than the frame's filter needs, or whose own
    Fourier transform holds power beyond its Nyquist frequency, is refused
    (exit 1) unless --allow-undersampled-psf.  Through a 4x oversampled image
    (STPSF's OVERSAMP, or --write-psf's of --psf roman) shapes are those of
    --psf roman to ~1e-4.

    Output: a SHAPES table, one row per object fitted per frame (frame = its
    index): id, frame, x, y (FITS pixels), ra, dec, g1, g2 (the frame's pixel
    axes), T (pixel^2), flux, their errors, s2n (fitted), snr_pred
    (predicted), chi2, nfev and flags (1 no convergence, 2 stamp off the frame
    edge, 4 T <= 0, 8 flux <= 0, 16 too few pixels, 32 |g| reached 1, 64 no
    errors, 128 HSM failed, 256 object off the frame, 512 a catalogue
    neighbour within --blend-radius, 1024 centre moved > 3 pixels from the
    catalogue position, 2048 S/N below 5, 4096 predicted S/N below
    --min-snr; rows with 256 or 4096 are written only with --all-rows); with
    several frames a COMBINED table: per object the inverse-variance weighted
    mean g over the frames where its fit has no flag.

    With --joint: a JOINT table instead, one row per galaxy fitted on all
    the frames it falls on at once (each frame with its own PSF for its SCA
    and its own WCS): id, ra, dec (fitted), g1, g2 on the sky (u West, v
    North: +g1 elongated East-West, +g2 North-West/South-East; the axes of
    the truth catalogue's e1, e2), T (arcsec^2), flux (e-/s), errors (ra_err,
    dec_err in arcsec), s2n, snr_pred (combined: sqrt of the sum of squares),
    nframes, chi2, nfev, flags (as above; 2 if any frame's stamp runs off its
    edge).

    \b
    Examples:
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o pair.fits
      perscli catalog --pointings pair.fits --bounds 1 512 1 512 -o truth.fits
      perscli render truth.fits --pointings pair.fits --row 0 --bounds 1 512 1 512 --seed 1 -o frame0.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 512 1 512 --seed 2 \\
          --previous frame0.fits -o frame.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 512 1 512 --seed 2 \\
          --set persistence=off -o frame_nop.fits
      perscli measure frame.fits --catalog truth.fits -o shapes.fits
      perscli measure frame_nop.fits --catalog truth.fits -o shapes_nop.fits
      perscli measure frame.fits frame_nop.fits --catalog truth.fits -o both.fits
      perscli measure frame.fits --catalog truth.fits --write-psf psf_x4.fits -o shapes_roman.fits
      perscli measure frame.fits --catalog truth.fits --psf psf_x4.fits --method hsm -o hsm.fits
      perscli measure frame.fits --catalog truth.fits --psf 'psf_x4.fits[PSF]' --psf-pixel excluded \\
          --psf-oversampling 4 -o shapes_x4.fits
      perscli measure frame0.fits frame.fits --catalog truth.fits --joint -o joint.fits
      perscli measure frame.fits --catalog truth.fits --kinds all --min-snr 0 --all-rows -o everything.fits

    (The first five make the inputs: two exposures of a 512 x 512 cutout
    of SCA 7, the second with and without the persistence of the first.
    --write-psf writes GalSim's Roman PSF for the frame's SCA and filter,
    4x oversampled, which --psf then reads; --psf-pixel and
    --psf-oversampling say what a PSF image's header does not, as for
    STPSF's 'psf.fits[OVERSAMP]' or a PSFEx model.)
    """
    from ..measure.shapes import measure_files

    check_outputs(output, inputs=[catalog, *frames, psf], overwrite=overwrite)
    # whole frames made and dropped over and over: kept for reuse rather than mapped afresh each time
    keep_freed_memory()
    if write_psf is not None:
        check_fits_name(write_psf, "--write-psf")
        check_outputs(write_psf, inputs=[catalog, *frames, psf], overwrite=overwrite)
    options = MeasureOptions(
        psf=psf, psf_pixel=psf_pixel, psf_oversampling=psf_oversampling,
        allow_undersampled_psf=allow_undersampled_psf, method=method, stamp=stamp, sky=sky, read_noise=read_noise,
        blend_radius=blend_radius, kinds=kinds, min_snr=min_snr, all_rows=all_rows, joint=joint, columns=columns)
    summary = measure_files(frames, catalog, output, options=options, write_psf=write_psf, workers=workers,
                            overwrite=overwrite,
                            progress=progress_reporter("galaxies" if joint else "objects", least=PROGRESS_LEAST))
    log.info("%s: %d rows (%d without flags) from %d frame(s); %d fitted, %d below --min-snr",
             "stdout" if output == "-" else output, summary["rows"], summary["good"], summary["frames"],
             summary["fitted"], summary["cut"])
