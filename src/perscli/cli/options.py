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
--model           the detector model: roman, a YAML file or a     render, diagnose
                  rendered frame
--law             the persistence law: a preset or a file         apply-persistence (its --model until 0.3.0)
--seed            random seed (same seed, same output)            catalog, pointings, correlate, render
--workers         cores (processes, or threads for compiled       apply-persistence, render, measure,
                  loops and TreeCorr), default 1                  correlate, diagnose
--plot            also draw a figure into a PNG file              render, budget, correlate
--units           override BUNIT of the inputs                    apply-persistence
--gain            override GAIN/CCDGAIN (e-/DN)                   apply-persistence
--exptime         exposure time for inputs that lack EXPTIME      apply-persistence
--ra, --dec       a position: RA in [0, 360], Dec in [-90, 90]    catalog, pointings, render
                  degrees (ICRS); refused outside, never wrapped
--pa              position angle, degrees in [-360, 360]          pointings, render
--mjd, --start,   a date, MJD 0 to 100000 (1858 to 2132)          render (--mjd), pointings (--start,
--after                                                           --after)
--filter          Roman filter name (R062 ... K213, W146)         pointings
--sca             Roman detector 1-18 (0: none chosen)            pointings
--no-checksum     do not verify CHECKSUM/DATASUM of inputs        every command that reads FITS (and the group)
--columns         a table's column names (NAME=COL,...)           render, measure, catalog, pointings, correlate,
                                                                  budget
--compress        lossless tile compression of the output         apply-persistence, render
--set             KEY=VALUE overrides, repeatable, read by        render, study, apply-persistence
                  :func:`key_values`
================  ==============================================  ===========================================

No output may replace an input: every file a command reads (FITS inputs,
--pointings, --psf, --catalog, --previous, --patch-centers, --schedule,
--gaia, model files) is passed to :func:`perscli.io.output.check_output`
with each output (-o, --plot, and render --dry-run's --regions), which refuses
the command with one line and exit status 1.
"""

import math

import click

from .. import PerscliError
from ..executor import MAX_WORKERS
from ..instrument import ROMAN_FILTERS, ROMAN_N_SCA
from ..io.config import split_key_value
from ..scene import DEC_RANGE, MJD_RANGE, PA_RANGE, RA_RANGE
from ..settings import default_text, option_fields
from .helpers import FILE, OUTPUT, DataError, configure_logging, file_or

def output_option(required: bool = True):
    """``-o/--output PATH``: required, or (``required=False``) checked by a command that can run without one
    (render --dry-run)."""
    return click.option("-o", "--output", "output", required=required, metavar="PATH", type=OUTPUT,
                        help="Output FITS file, or '-' (or /dev/stdout) for standard output.")


output_opt = output_option()

overwrite_opt = click.option(
    "--overwrite", is_flag=True, default=False, help="Replace the output if it exists.")

units_opt = click.option(
    "--units", metavar="UNIT", default=None,
    help="Units of every input, overriding BUNIT: electron, electron/s, DN or DN/s.")

class FiniteRange(click.FloatRange):
    """A range of floats that refuses 'nan' and 'inf' too (click's FloatRange lets NaN through, and
    'inf' through a range without an upper bound): ``--exptime inf`` would make any charge infinite."""

    def convert(self, value, param, ctx):
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number in the range {self._describe_range()}.", param, ctx)
        return rv


# the ranges of perscli.io.frames (GAIN_RANGE, MAX_EXPTIME), written here again so that --help does not
# import numpy: a gain no detector has, or an exposure time of 0 s, would silently give no persistence
gain_opt = click.option(
    "--gain", type=FiniteRange(min=1e-3, max=1e3), metavar="E_PER_DN", default=None,
    help="Gain in e-/DN (0.001 to 1000), overriding GAIN/CCDGAIN (needed for DN inputs without them).")

exptime_opt = click.option(
    "--exptime", type=FiniteRange(min=0, min_open=True, max=1e7), metavar="SECONDS", default=None,
    help="Exposure time (more than 0 s) for inputs whose header has no EXPTIME or XPOSURE.")

def workers_opt(what: str):
    """``--workers N``: cores to use, ``what`` saying for what (processes or threads; see perscli.executor),
    1 to :data:`perscli.executor.MAX_WORKERS` (a million threads crash TreeCorr's OpenMP pool)."""
    return click.option(
        "--workers", type=click.IntRange(min=1, max=MAX_WORKERS), metavar="N", default=1, show_default=True,
        help=f"Cores to use: {what}.")


def model_opt(default: str, metavar: str, what: str, names=()):
    """``--model NAME|FILE``: the detector model (one meaning in every command; apply-persistence's persistence
    law is ``--law``), ``what`` listing the names and files it takes (``names`` complete in the shell)."""
    return click.option("--model", "model_spec", default=default, show_default=True, metavar=metavar,
                        type=file_or(*names), help=f"Detector model: {what}.")


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
    return click.option("--plot", metavar=metavar, default=None, callback=_png, type=FILE,
                        help=f"Also draw {what} into this PNG file.")

class _Range(click.FloatRange):
    """A closed range of floats that also refuses 'nan' (click's FloatRange lets NaN through).

    ``hint(value)`` may add a suggestion to the message of a value out of range.
    """

    def __init__(self, low: float, high: float, hint=None):
        super().__init__(low, high)
        self.hint = hint

    def convert(self, value, param, ctx):
        try:
            rv = super().convert(value, param, ctx)
        except click.BadParameter as exc:
            number = _float(value)
            extra = self.hint(number) if self.hint and number is not None and math.isfinite(number) else ""
            if extra:
                raise click.BadParameter(f"{exc.message.rstrip('.')}{extra}.", ctx, param) from None
            raise
        if math.isnan(rv):
            self.fail(f"{value!r} is not a number in the range {self._describe_range()}.", param, ctx)
        return rv


def _float(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _ra_hint(value: float) -> str:
    return f" (the same direction as {value % 360.0:g}: give that)"


def _mjd_hint(value: float) -> str:
    return f" (a Julian Date? MJD = JD - 2400000.5 = {value - 2400000.5:.5f})" if value > 2400000.5 else ""


# the ranges of perscli.scene, where they are written (a light import: numpy waits for the functions that use it)
RA_TYPE = _Range(*RA_RANGE, hint=_ra_hint)
DEC_TYPE = _Range(*DEC_RANGE)
PA_TYPE = _Range(*PA_RANGE)
MJD_TYPE = _Range(*MJD_RANGE, hint=_mjd_hint)


def ra_opt(help: str = "Field centre: right ascension", *, required: bool = False):
    """``--ra DEG``: a right ascension in [0, 360] degrees; ``help`` says what position it is."""
    # no default=None: click (8.3+) does not enforce required=True on an option given a default, even None
    return click.option("--ra", type=RA_TYPE, required=required, metavar="DEG",
                        help=f"{help}, degrees (ICRS).")


def dec_opt(help: str = "Field centre: declination", *, required: bool = False):
    """``--dec DEG``: a declination in [-90, 90] degrees; ``help`` says what position it is."""
    return click.option("--dec", type=DEC_TYPE, required=required, metavar="DEG",
                        help=f"{help}, degrees (ICRS).")


def pa_opt(help: str):
    """``--pa DEG``: an observatory position angle (GalSim's convention) in [-360, 360] degrees."""
    return click.option("--pa", type=PA_TYPE, default=None, metavar="DEG", help=help)


def mjd_opt(name: str, help: str):
    """A date option (``--mjd``, ``--start``, ``--after``): an MJD in [0, 100000] (1858-11-17 to 2132-09-01)."""
    return click.option(name, type=MJD_TYPE, default=None, metavar="MJD", help=help)

_SEED_HELP = "Random seed, written into the output: the same seed gives the same output."

seed_opt = click.option(
    "--seed", type=click.IntRange(min=0), default=1, show_default=True, metavar="N", help=_SEED_HELP)

def chosen_seed_option(required: bool = True):
    """``--seed N`` with no default: every run chooses one (render); ``required=False`` for a command that
    checks it itself (render --dry-run needs none)."""
    return click.option("--seed", type=click.IntRange(min=0), required=required, metavar="N", help=_SEED_HELP)



def _add_verbosity(sign: int):
    def callback(ctx, param, value):
        if value:
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
        from ..io.checksum import read_options      # io.checksum imports numpy: only when the flag is given

        # in force until the command's context closes (passed down, like rasterio.Env; the executor
        # carries it to worker threads, processes and Dask tasks)
        ctx.with_resource(read_options(verify_checksums=False))


# eager, so that it is in force before any input is opened
no_checksum_opt = click.option(
    "--no-checksum", is_flag=True, default=False, expose_value=False, is_eager=True, callback=_no_checksum,
    help="Do not verify the CHECKSUM/DATASUM of inputs (for files edited on purpose; "
         "astropy's `fitscheck --force FILE` updates them instead).")

def compress_option(default: str = "none"):
    """``--compress none|gzip|rice``, with the command's own default (render's is RenderOptions')."""
    return click.option(
        "--compress", type=click.Choice(["none", "gzip", "rice"]), default=default, show_default=True,
        help="Tile-compress the output's images, losslessly: gzip (GZIP_2, any data) or rice (integer data "
             "only). An output named *.fits.gz is gzip-compressed as a whole instead.")


compress_opt = compress_option()


def _columns(ctx, param, value):
    from ..io.tables import parse_column_mapping    # io.tables imports fitsio: only when a command runs

    try:
        return parse_column_mapping(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def columns_opt(what: str, example: str = "ra=ALPHA_J2000,dec=DELTA_J2000", name: str = "--columns"):
    """``--columns NAME=COLUMN,...``: read a table whose columns another tool named.

    Parameters
    ----------
    what : str
        The table the mapping applies to ('the catalogue', '--schedule').
    example : str
        An example mapping for the help.
    name : str
        The option's name, for a command reading two kinds of table
        (pointings: ``--columns`` for the catalogue, ``--schedule-columns``).
    """
    return click.option(
        name, name.lstrip("-").replace("-", "_"), multiple=True, metavar="NAME=COL,...", callback=_columns,
        help=f"Column names of {what} when they differ from perscli's: NAME=COL pairs, comma-separated or "
             f"repeated (e.g. {example}); NAME is the column perscli reads, COL the file's.")


def key_values(item: dict | None = None, *, effect: str | None = None):
    """A click callback for a repeatable ``--set KEY=VALUE`` (rasterio's ``_cb_key_val``): each item read by
    :func:`perscli.io.config.split_key_value`, the library's one reading, as the command line parses it.

    Parameters
    ----------
    item : dict, optional
        How the library names the items (:data:`perscli.io.config.DETECTOR_ITEM`,
        :data:`~perscli.io.config.STUDY_ITEM`): an item without '=' is
        refused with the library's own line, exit status 1.  The items go on
        as given: the library types each value and checks it against its
        schema, once.
    effect : str, optional
        The one effect the command applies ('persistence' for
        apply-persistence): items are ``EFFECT.KEY=VALUE`` and go on as
        ``KEY=VALUE``; another effect, or no dotted path, is a usage error
        (exit status 2).
    """
    def callback(ctx, param, value):
        out = []
        for text in value:
            try:
                key, raw = split_key_value(text, **(item or {}))
            except PerscliError as exc:
                if effect is None:
                    raise DataError(str(exc)) from None
                key, raw = "", None
            if effect is None:
                out.append(text)
                continue
            name, dot, sub = key.partition(".")
            if raw is None or not dot or not sub:
                raise click.BadParameter(f"{text!r}: give {effect}.KEY=VALUE, e.g. {effect}.gamma=1.1", ctx, param)
            if name != effect:
                raise click.BadParameter(f"{text!r}: apply-persistence applies {effect} only (give "
                                         f"{effect}.{sub}=...); render's --set takes the other effects", ctx, param)
            out.append(f"{sub}={raw}")
        return tuple(out)

    return callback


def numbers(ctx, param, value):
    """A click callback: comma-separated numbers (``1e-8,1e-4``) as a tuple of floats."""
    if value is None:
        return None
    try:
        values = tuple(float(v) for v in value.replace(" ", "").split(",") if v)
    except ValueError:
        raise click.BadParameter(f"{value!r}: give numbers separated by commas, e.g. 1e-8,1e-4") from None
    if not values:
        raise click.BadParameter("give at least one number")
    return values


def _click_type(spec):
    """The click type of a setting's :class:`perscli.settings.OptionSpec`."""
    v = spec.values
    if spec.kind == "choice":
        return click.Choice(list(v.choices), case_sensitive=spec.case_sensitive)
    if spec.kind == "file_or":
        return file_or(*(v.choices if v else ()))
    if spec.kind in ("float", "int"):
        if v is None or (v.lo is None and v.hi is None):
            return float if spec.kind == "float" else int
        if spec.kind == "int":
            return click.IntRange(min=v.lo, max=v.hi, min_open=v.lo_open, max_open=v.hi_open)
        return click.FloatRange(min=v.lo, max=v.hi, min_open=v.lo_open, max_open=v.hi_open)
    return None


def settings_option(cls, name: str, help: str | None = None):
    """The click option of field ``name`` of a settings dataclass, made from the field (:func:`perscli.settings.setting`).

    Its default is the dataclass's, its parameter the field's name: a
    command passes ``**{name: value}`` on to the dataclass as it comes.
    ``help`` replaces the field's where one option does different things in
    different commands (pointings' --sca).
    """
    fields = option_fields(cls)
    if name not in fields:
        raise KeyError(f"{cls.__name__}.{name} has no option (declare it with perscli.settings.setting)")
    default, spec = fields[name]
    flag = spec.flag or "--" + name.replace("_", "-")
    kwargs = {"help": spec.help if help is None else help, "show_default": spec.show_default}
    if spec.metavar:
        kwargs["metavar"] = spec.metavar
    if spec.kind == "flag":
        return click.option(flag, name, is_flag=True, default=bool(default), help=kwargs["help"])
    if spec.kind == "numbers":
        return click.option(flag, name, callback=numbers, default=default_text(default), **kwargs)
    if spec.check is not None:
        kwargs["callback"] = _checked(spec.check)
    return click.option(flag, name, type=_click_type(spec), default=default, **kwargs)


def _checked(check):
    """A click callback running the library's check of a value (:attr:`perscli.settings.OptionSpec.check`)."""
    def callback(ctx, param, value):
        try:
            return check(value)
        except PerscliError as exc:
            raise click.BadParameter(str(exc)) from None
    return callback


def settings_options(cls, *names):
    """The click options of several fields of a settings dataclass, in the order given (:func:`settings_option`)."""
    made = [settings_option(cls, n) for n in names]

    def decorate(func):
        for opt in reversed(made):
            func = opt(func)
        return func

    return decorate

