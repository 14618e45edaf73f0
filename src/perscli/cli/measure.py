"""``perscli measure``: galaxy shapes by exponential-profile fitting."""

from __future__ import annotations

import logging

import click

from .helpers import check_outputs, progress_reporter, report_errors
from .options import output_opt, overwrite_opt, verbosity_opts, workers_opt

log = logging.getLogger("perscli")


@click.command("measure", short_help="Measure galaxy shapes on frames by exponential-profile fits.")
@click.argument("frames", nargs=-1, required=True, metavar="FRAME...")
@click.option("--catalog", required=True, metavar="CAT.fits",
              help="Objects to measure: id and ra/dec (degrees) or x/y (FITS pixels); hlr and mag_<FILTER> "
                   "columns, when present, give the starting point.")
@click.option("--psf", default="roman", show_default=True, metavar="roman|PSF.fits",
              help="roman: GalSim's Roman PSF for the frame's SCA and FILTER; or an image of the optical PSF "
                   "with PIXSCALE (arcsec), sampled 2x or finer.")
@click.option("--method", type=click.Choice(["exp", "hsm"]), default="exp", show_default=True,
              help="exp: exponential-mixture fit (exact PSF, analytic Jacobian); hsm: GalSim REGAUSS.")
@click.option("--stamp", type=int, default=48, show_default=True, metavar="PIXELS", help="Stamp side.")
@click.option("--sky", type=float, default=None, metavar="LEVEL",
              help="Background per pixel in the frame's units [default: SKYRATE x EXPTIME + dark].")
@click.option("--read-noise", type=click.FloatRange(min=0), default=None, metavar="E",
              help="Read noise (electrons) of the noise model, when the frame has no weight HDU [default: "
                   "read_noise.sigma of the frame's detector model (MODEL table), else Roman's 8.5].")
@click.option("--blend-radius", type=click.FloatRange(min=0), default=4.0, show_default=True, metavar="PIXELS",
              help="Flag objects with another catalogue object this close (0: never).")
@output_opt
@overwrite_opt
@workers_opt("processes fitting the objects (the output does not depend on N)")
@verbosity_opts
@report_errors
def measure(frames, catalog, psf, method, stamp, sky, read_noise, blend_radius, output, overwrite, workers):
    """Measure the shapes of the catalogue's objects on each FRAME.

    The exponential profile is the 6-Gaussian mixture of Hogg & Lang, with
    parameters (x, y, g1, g2, T, flux); it is convolved with the PSF exactly,
    in Fourier space (the PSF's transform times the pixel response, folded
    above Nyquist), and fitted by Levenberg-Marquardt with the analytic
    Jacobian in float64 to 1e-10.  The start (catalogue position, round, the
    catalogue's size and flux) and the weights (WHT/VAR/ERR HDU, else the sky
    from the header, and the dark current, read noise and gain of the detector
    model that rendered the frame, or Roman's) never depend on its pixel noise,
    so shape changes between two frames that differ by a small pattern are
    that pattern's alone (linear down to ~1e-10).  Only when the catalogue has
    no magnitude for the frame's FILTER is the start flux solved from the data.

    Output: a SHAPES table, one row per object per frame (frame = its index):
    id, frame, x, y (FITS pixels), ra, dec, g1, g2, T (pixel^2), flux, their
    errors, s2n, chi2, nfev and flags (1 no convergence, 2 stamp off the frame
    edge, 4 T <= 0, 8 flux <= 0, 16 too few pixels, 32 |g| reached 1, 64 no
    errors, 128 HSM failed, 256 object off the frame, 512 a catalogue neighbour
    within --blend-radius, 1024 centre moved > 3 pixels from the catalogue
    position, 2048 S/N below 5); with several frames a
    COMBINED table: per object the inverse-variance weighted mean g over the
    frames where its fit has no flag.

    \b
    Examples:
      perscli measure exp3.fits --catalog truth.fits -o shapes.fits
      perscli measure exp3.fits exp3_nopersist.fits --catalog truth.fits -o both.fits
      perscli measure frame.fits --catalog cat.fits --psf psf_x4.fits --method hsm -o hsm.fits
    """
    from ..measure.shapes import measure_files

    check_outputs(output, inputs=[catalog, *frames, psf], overwrite=overwrite)
    summary = measure_files(frames, catalog, output, psf=psf, method=method, stamp=stamp, sky=sky,
                            read_noise=read_noise, blend_radius=blend_radius, workers=workers, overwrite=overwrite,
                            progress=progress_reporter("objects"))
    log.info("%s: %d rows (%d without flags) from %d frame(s)", "stdout" if output == "-" else output,
             summary["rows"], summary["good"], summary["frames"])
