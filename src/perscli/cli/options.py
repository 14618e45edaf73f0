"""Options shared by perscli commands.

Each decorator below is defined once and used by every command that takes
the option, so that names, metavars, units and help read the same everywhere:

================  ============================================  ==================
option            meaning                                       used by
================  ============================================  ==================
-o/--output       output path, '-' for standard output          apply-persistence
--overwrite       replace an existing output                    apply-persistence
--units           override BUNIT of the inputs                  apply-persistence
--gain            override GAIN/CCDGAIN (e-/DN)                 apply-persistence
--exptime         exposure time for inputs that lack EXPTIME    apply-persistence
--workers         threads or processes to use                   apply-persistence
--ra, --dec       field centre (degrees)                        catalog, pointings
--seed            random seed (same seed, same output)          catalog, pointings
--filter          Roman filter name (R062 ... K213, W146)       pointings
--sca             Roman detector 1-18 (0: none chosen)          pointings
================  ============================================  ==================
"""

import click

output_opt = click.option(
    "-o", "--output", "output", required=True, metavar="PATH",
    help="Output FITS file, or '-' for standard output.")

overwrite_opt = click.option(
    "--overwrite", is_flag=True, default=False, help="Replace the output if it exists.")

units_opt = click.option(
    "--units", metavar="UNIT", default=None,
    help="Units of every input, overriding BUNIT: electron, electron/s, DN or DN/s.")

gain_opt = click.option(
    "--gain", type=click.FloatRange(min=0, min_open=True), metavar="E_PER_DN", default=None,
    help="Gain in e-/DN, overriding GAIN/CCDGAIN (needed for DN inputs without them).")

exptime_opt = click.option(
    "--exptime", type=click.FloatRange(min=0), metavar="SECONDS", default=None,
    help="Exposure time for inputs whose header has no EXPTIME or XPOSURE.")

workers_opt = click.option(
    "--workers", type=click.IntRange(min=1), metavar="N", default=1, show_default=True,
    help="Number of cores to use.")

ra_opt = click.option(
    "--ra", type=float, required=True, metavar="DEG", help="Field centre: right ascension in degrees (ICRS).")

dec_opt = click.option(
    "--dec", type=click.FloatRange(-90, 90), required=True, metavar="DEG",
    help="Field centre: declination in degrees (ICRS).")

seed_opt = click.option(
    "--seed", type=click.IntRange(min=0), default=1, show_default=True, metavar="N",
    help="Random seed, written into the output: the same seed gives the same output.")

# a plain string checked by the library (perscli.scene.check_filter), so that the command
# line does not import the filter table
filter_opt = click.option(
    "--filter", "filter_name", metavar="NAME", default=None,
    help="Roman filter: R062, Z087, Y106, J129, H158, F184, K213 or W146 (any case).")

sca_opt = click.option(
    "--sca", type=click.IntRange(0, 18), default=0, show_default=True, metavar="N",
    help="Roman detector (SCA 1-18) to write into every row; 0 for none chosen.")


def _no_checksum(ctx, param, value):
    if value:
        from ..io.fitsfile import set_checksum_verification

        set_checksum_verification(False)


# eager, so that it is in force before any input is opened; it also reaches worker processes
no_checksum_opt = click.option(
    "--no-checksum", is_flag=True, default=False, expose_value=False, is_eager=True, callback=_no_checksum,
    help="Do not verify the CHECKSUM/DATASUM of inputs (for files edited on purpose; "
         "astropy's `fitscheck --force FILE` updates them instead).")

compress_opt = click.option(
    "--compress", type=click.Choice(["none", "gzip", "rice"]), default="none", show_default=True,
    help="Tile-compress the output's images, losslessly: gzip (GZIP_2, any data) or rice (integer data "
         "only). An output named *.fits.gz is gzip-compressed as a whole instead.")
