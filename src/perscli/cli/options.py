"""Options shared by perscli commands.

Each decorator below is defined once and used by every command that takes
the option, so that names, metavars, units and help read the same everywhere
(a factory, such as ``workers_opt(what)``, only says what the option drives
in that command):

================  ==============================================  ===========================================
option            meaning                                         used by
================  ==============================================  ===========================================
-o/--output       output path, '-' for standard output            every command
--overwrite       replace an existing output (never an input)     every command
-v/-q             more/fewer messages; also after the command     every command (and the perscli group)
--model           the model to apply: a name or a file            apply-persistence (render: its own, for now)
--seed            random seed (same seed, same output)            catalog, pointings, correlate, render
--workers         cores (processes, or threads for compiled       apply-persistence, render, measure,
                  loops and TreeCorr), default 1                  correlate
--plot            also draw a figure into a PNG file              render, budget, correlate
--units           override BUNIT of the inputs                    apply-persistence
--gain            override GAIN/CCDGAIN (e-/DN)                   apply-persistence
--exptime         exposure time for inputs that lack EXPTIME      apply-persistence
--ra, --dec       field centre (degrees)                          catalog, pointings
--filter          Roman filter name (R062 ... K213, W146)         pointings
--sca             Roman detector 1-18 (0: none chosen)            pointings
--no-checksum     do not verify CHECKSUM/DATASUM of inputs        apply-persistence, render (and the group)
--compress        lossless tile compression of the output         apply-persistence, render
================  ==============================================  ===========================================

No output may replace an input: every file a command reads (FITS inputs,
--pointings, --psf, --catalog, --previous, --patch-centers, --schedule,
--gaia, model files) is passed to :func:`perscli.io.output.check_output`
with each output (-o and --plot), which refuses the command with one line and
exit status 1.
"""

import click

from ..instrument import ROMAN_FILTERS, ROMAN_N_SCA

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

def workers_opt(what: str):
    """``--workers N``: cores to use, ``what`` saying for what (processes or threads; see perscli.executor)."""
    return click.option(
        "--workers", type=click.IntRange(min=1), metavar="N", default=1, show_default=True,
        help=f"Cores to use: {what}.")


def model_opt(default: str, metavar: str, what: str):
    """``--model NAME|FILE``: the model a command applies, ``what`` listing the names and files it takes."""
    return click.option("--model", "model_spec", default=default, show_default=True, metavar=metavar,
                        help=f"Model to apply: {what}.")


def _png(ctx, param, value):
    if value is None:
        return None
    if value == "-":
        raise click.BadParameter("the figure cannot go to standard output: give a PNG file name")
    if not value.lower().endswith(".png"):
        raise click.BadParameter(f"{value}: needs a .png file name")
    return value


def plot_opt(what: str, metavar: str = "PNG"):
    """``--plot PNG``: also draw ``what`` into a PNG file (never over an input or the -o output)."""
    return click.option("--plot", metavar=metavar, default=None, callback=_png,
                        help=f"Also draw {what} into this PNG file.")

ra_opt = click.option(
    "--ra", type=float, required=True, metavar="DEG", help="Field centre: right ascension in degrees (ICRS).")

dec_opt = click.option(
    "--dec", type=click.FloatRange(-90, 90), required=True, metavar="DEG",
    help="Field centre: declination in degrees (ICRS).")

_SEED_HELP = "Random seed, written into the output: the same seed gives the same output."

seed_opt = click.option(
    "--seed", type=click.IntRange(min=0), default=1, show_default=True, metavar="N", help=_SEED_HELP)

#: --seed for commands where every run must choose one (render)
required_seed_opt = click.option(
    "--seed", type=click.IntRange(min=0), required=True, metavar="N", help=_SEED_HELP)


def _add_verbosity(sign: int):
    def callback(ctx, param, value):
        if value:
            from .helpers import configure_logging

            root = ctx.find_root()
            if root.obj is None:
                root.obj = {}
            root.obj["verbosity"] = root.obj.get("verbosity", 0) + sign * value
            configure_logging(root.obj["verbosity"])
        return value

    return callback


def verbosity_opts(func):
    """``-v/--verbose`` and ``-q/--quiet`` after the command name too (``perscli render ... -v``).

    They add to the counts given before it (``perscli -v render ... -v`` is -vv) and reconfigure logging.
    """
    func = click.option("-q", "--quiet", count=True, expose_value=False, callback=_add_verbosity(-1),
                        help="Fewer messages on stderr (errors only; no progress bars).")(func)
    func = click.option("-v", "--verbose", count=True, expose_value=False, callback=_add_verbosity(+1),
                        help="More messages on stderr (-vv: debug, with tracebacks).")(func)
    return func

# a plain string checked by the library (perscli.scene.check_filter), so that the command
# line does not import the filter table
filter_opt = click.option(
    "--filter", "filter_name", metavar="NAME", default=None,
    help=f"Roman filter: {', '.join(ROMAN_FILTERS[:-1])} or {ROMAN_FILTERS[-1]} (any case).")

sca_opt = click.option(
    "--sca", type=click.IntRange(0, ROMAN_N_SCA), default=0, show_default=True, metavar="N",
    help=f"Roman detector (SCA 1-{ROMAN_N_SCA}) to write into every row; 0 for none chosen.")


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
