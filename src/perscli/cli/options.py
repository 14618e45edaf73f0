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
