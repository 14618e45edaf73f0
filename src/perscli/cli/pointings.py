"""``perscli pointings``: the exposures that look at a field, from a schedule or planned.

A group of three subcommands, one job each: ``select`` (a schedule's
exposures of a field), ``before`` (a schedule's exposures before one of its
rows) and ``plan`` (a dithered sequence).  Until this release the three were
one command whose flags chose the job (``--schedule FILE``, ``--schedule FILE
--before ROW``, ``--plan``); that flag form still works until perscli 0.3.0, with a
deprecation warning (:class:`FlagFormGroup` hands it to :func:`pointings_flags`).
Both forms are built from the same option factories below and run the same
functions (:func:`run_select`, :func:`run_before`, :func:`run_plan`), so that
they write the same bytes for the same arguments.
"""

from __future__ import annotations

import logging

import click
from click.core import ParameterSource

from ..deprecation import deprecated
from ..instrument import ROMAN_EXPTIME, ROMAN_N_SCA, ROMAN_WAS_GAP
from ..scene.settings import PLAN_REFERENCE_MJD, PlanOptions, SelectOptions
from .helpers import FILE, PerscliCommand, PerscliGroup, check_outputs, file_or, progress_reporter, report_errors
from .options import (columns_opt, dec_opt, filter_opt, mjd_opt, no_checksum_opt, output_opt, overwrite_opt, pa_opt,
                      ra_opt, seed_opt, settings_option, verbosity_opts)


log = logging.getLogger("perscli")

#: footprints below this many tell a log (stderr not a terminal) nothing: ~15 ms each, so a few seconds
PROGRESS_LEAST = 300


# -- options: each defined once; ``help`` says what it does in the command that takes it ----------
# (no default=None where an option may be required: click (8.3+) does not enforce required=True on an option
# whose default is given, even as None)

def schedule_opt(help: str, *, default: str | None = None):
    """``--schedule roman-was|FILE``: a survey schedule, '-' for standard input; ``default``: the bundled one."""
    if default is None:
        return click.option("--schedule", metavar="FILE", type=FILE, help=help)
    return click.option("--schedule", metavar=f"{default}|FILE", default=default, show_default=True,
                        type=file_or(default), help=help)


def radius_opt(help: str, *, required: bool = False):
    """``--radius DEG``: the radius of the field circle."""
    return click.option("--radius", type=click.FloatRange(min=0, max=180, min_open=True), required=required,
                        metavar="DEG", help=help)


def limit_opt(help: str):
    """``--limit N``: at most N exposures selected (none given: all)."""
    return click.option("--limit", type=click.IntRange(min=1), default=None, metavar="N", help=help)


def row_opt(name: str, help: str, *, required: bool = False):
    """The schedule row whose earlier exposures to take: ``--row`` (before), ``--before`` (the flag form)."""
    return click.option(name, type=click.IntRange(min=0), required=required, metavar="ROW", help=help)


def n_opt(help: str, *, required: bool = False):
    """``--n N``: a number of exposures."""
    return click.option("--n", "n", type=click.IntRange(min=1), required=required, metavar="N", help=help)


def dither_opt(help: str):
    """``--dither ARCSEC``: a plan's offsets."""
    return settings_option(PlanOptions, "dither", help)


def plan_exptime_opt(help: str):
    """``--exptime SECONDS``: a plan's exposure time (options.exptime_opt is another: a fallback for inputs)."""
    return settings_option(PlanOptions, "exptime", help)


def gap_opt(help: str):
    """``--gap SECONDS``: from the end of one exposure of a plan to the start of the next."""
    return settings_option(PlanOptions, "gap", help)


def sca_opt(help: str):
    """``--sca N``: the detector written into every row (options.sca_opt's, with what it does here)."""
    return settings_option(SelectOptions, "sca", help)


def footprints_opt(func):
    return click.option("--footprints", is_flag=True, default=False,
                        help="Add each row's SCA corners on the sky (columns corner_ra, corner_dec, 4 values each, "
                             "degrees; GalSim's Roman WCS); needs --sca N.")(func)


def catalog_opt(func):
    return click.option("--catalog", "catalog", metavar="TRUTH.fits", default=None, type=FILE,
                        help="With --footprints: also count the objects of this truth catalogue (perscli catalog) "
                             "whose centre lands on each row's SCA (columns n_star, n_galaxy).")(func)


catalog_columns_opt = columns_opt("--catalog", "ra=ALPHA_J2000,dec=DELTA_J2000,kind=CLASS")
schedule_columns_opt = columns_opt("--schedule", "date=mjd_start,exptime=exp_time", name="--schedule-columns")


def _flag(mode: str, text: str) -> str:
    """The help of a subcommand's option in the flag form, which says for which mode it is."""
    return f"{mode}: {text[0].lower()}{text[1:]}"


# the help of each option, written once: the subcommand's, and (through _flag) the flag form's
SCHEDULE_HELP = "Survey schedule (FITS table: date, exptime, ra, dec, pa, filter; '-' for standard input)"
#: the subcommands' --schedule: the bundled public schedule by default (perscli.scene.schedule.BUNDLED_SCHEDULE)
BUNDLED_HELP = ("Survey schedule: roman-was, the Roman project's public Wide Area Survey observing sequence "
                "(Roman_WAS_obseq_11_1_23.fits of 2023-11-01, 16,956 exposures) shipped with perscli, or a FITS "
                "table (date, exptime, ra, dec, pa, filter; '-' for standard input)")
BUNDLED = "roman-was"
RADIUS_HELP = ("Radius of the field circle (great circle): pointing centres within it, or with --sca N the "
               "exposures whose SCA N overlaps it.")
LIMIT_HELP = "Only the N earliest exposures selected."
AFTER_HELP = "Only exposures that start after this MJD."
DITHER_HELP = "Offsets uniform within +-ARCSEC east and north of the field centre."
START_HELP = ("Start of the first exposure; refused (with the first start after it that works) if Roman cannot "
              "take every exposure of the plan  [default: the first date, from MJD "
              f"{PLAN_REFERENCE_MJD} (the public Roman Wide Area Survey schedule's first exposure) in steps of one "
              "day, at which Roman can take every exposure]")
EXPTIME_HELP = f"Exposure time (Roman survey: {ROMAN_EXPTIME:g} s)."
GAP_HELP = f"From the end of one exposure to the start of the next (Roman survey: ~{ROMAN_WAS_GAP:g} s)."
PA_HELP = ("Observatory position angle of every exposure, degrees (GalSim's convention; any roll is taken, as "
           "GalSim takes it)  [default: GalSim's best PA, galsim.roman.bestPA, for the first exposure at its start]")
SCA_HELP = f"Roman detector (SCA 1-{ROMAN_N_SCA}), written into every row; 0 for none chosen."


def row_outputs(func):
    """The options of what each row carries besides its exposure: SCA corners, catalogue counts."""
    for decorate in reversed((footprints_opt, catalog_opt, catalog_columns_opt)):
        func = decorate(func)
    return func


def output_opts(func):
    """-o, --overwrite, -v/-q: the end of every form's options."""
    for decorate in reversed((output_opt, overwrite_opt, verbosity_opts)):
        func = decorate(func)
    return func


def schedule_tail(func):
    """What the subcommands that read a schedule end with: the rows' outputs, the schedule's columns,
    --no-checksum, -o/--overwrite/-v/-q, and the context and error handling."""
    for decorate in reversed((row_outputs, schedule_columns_opt, no_checksum_opt, output_opts, click.pass_context,
                              report_errors)):
        func = decorate(func)
    return func


# -- the jobs, shared by the subcommands and the flag form ---------------------------------------

def check_rows(ctx, sca, footprints, catalog) -> None:
    """Refuse --footprints without --sca, and --catalog without --footprints (usage errors)."""
    if footprints and not sca:
        raise click.UsageError("--footprints needs --sca N (1-18): the detector whose corners to add", ctx)
    if catalog is not None and not footprints:
        raise click.UsageError("--catalog needs --footprints --sca N: the detector on which to count its objects",
                               ctx)


def plan_options(filter_name, **values) -> PlanOptions:
    """The settings of a plan from the command line's values (``filter_name``: --filter, None when not given)."""
    # --filter is options.filter_opt, without a default of its own (in select, none means any filter)
    return PlanOptions(filter=filter_name or PlanOptions().filter, **values)


def select_options(filter_name, **values) -> SelectOptions:
    """The settings of a selection from the command line's values (``filter_name``: --filter, None for any)."""
    return SelectOptions(filter=filter_name, **values)


def run_select(ctx, schedule, ra, dec, radius, options: SelectOptions, catalog, output, overwrite) -> None:
    """``perscli pointings select``: the exposures of a schedule that look at the field."""
    from ..scene.pointings import select_covering_file

    check_outputs(output, inputs=[schedule, catalog], overwrite=overwrite)
    # with --sca, each exposure near the field has its footprint computed (~15 ms): a wide field takes minutes
    chosen = select_covering_file(output, schedule, ra, dec, radius, options, catalog=catalog, overwrite=overwrite,
                                  progress=progress_reporter("footprints", least=PROGRESS_LEAST))
    if not chosen:
        sca = options.sca
        what = f"whose SCA {sca} overlaps the circle of {radius:g} degrees" if sca else f"within {radius:g} degrees"
        log.warning("%s: no exposure %s about (%g, %g)%s; the output table is empty",
                    schedule, what, ra, dec, f" in {options.filter}" if options.filter else "")
    _say_rows(ctx, output, chosen)


def run_before(ctx, schedule, row, n, *, sca, footprints, catalog, columns, schedule_columns, output,
               overwrite) -> None:
    """``perscli pointings before``: the ``n`` exposures of a schedule that start last before ``row``."""
    from ..scene.pointings import previous_exposures_file

    check_outputs(output, inputs=[schedule, catalog], overwrite=overwrite)
    chosen = previous_exposures_file(output, schedule, row, n, sca=sca, footprints=footprints, catalog=catalog,
                                     overwrite=overwrite, columns=columns, schedule_columns=schedule_columns)
    if len(chosen) < n:
        log.warning("%s: only %d exposure(s) start before row %d (asked for %d)", schedule, len(chosen), row, n)
    _say_rows(ctx, output, chosen)


def run_plan(ctx, ra, dec, n, options: PlanOptions, catalog, output, overwrite) -> None:
    """``perscli pointings plan``: a dithered sequence of ``n`` exposures on the field."""
    from ..scene.pointings import plan_dithers_file

    check_outputs(output, inputs=[catalog], overwrite=overwrite)
    chosen = plan_dithers_file(output, ra, dec, n, options, catalog=catalog, overwrite=overwrite)
    if chosen:
        log.info("plan: start MJD %.6f (%s), PA %.4f (%s)", chosen[0].mjd,
                 "given" if options.start is not None else "the first observable", chosen[0].pa,
                 "given" if options.pa is not None else "GalSim's best")
    _say_rows(ctx, output, chosen)


def _say_rows(ctx, output, chosen) -> None:
    # what was written, in one line on stderr (stdout may be the table itself), unless -q
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0)
    if verbosity >= 0:
        click.echo(f"{'stdout' if output == '-' else output}: {len(chosen)} rows written (exposures)", err=True)


# -- the group ------------------------------------------------------------------------------------

class FlagFormGroup(PerscliGroup):
    """A group that still runs the flag form of the command it replaced, as a deprecated alias.

    Arguments whose first word, after the group's own options (-v, -q),
    is another option (``perscli pointings --plan ...``) are parsed and run
    by ``legacy``, a command of the same name, exactly as before; anything
    else (a subcommand, the help option, nothing) is the group's.

    Parameters
    ----------
    legacy : click.Command
        The flag form.

    """

    def __init__(self, *args, legacy: click.Command, **kwargs):
        super().__init__(*args, **kwargs)
        self.legacy = legacy

    def _is_flag_form(self, args, parent, extra) -> bool:
        names = extra.get("help_option_names") or self.context_settings.get("help_option_names")
        if names is None and parent is not None:
            names = parent.help_option_names
        names = set(names or ["--help"])
        own = {opt for p in self.params for opt in (*p.opts, *p.secondary_opts)}
        for word in args:
            # the group's own options take no value: -v, --quiet, -vv
            if word in own or (word[:1] == "-" and word[1:2] not in ("", "-")
                               and all(f"-{c}" in own for c in word[1:])):
                continue
            return word.startswith("-") and word not in names
        return False

    def make_context(self, info_name, args, parent=None, **extra):
        if self._is_flag_form(args, parent, extra):
            return self.legacy.make_context(info_name, args, parent=parent, **extra)
        return super().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx):
        # the group run on its own (main) with a flag-form context: run the legacy command
        if ctx.command is not self:
            return ctx.command.invoke(ctx)
        return super().invoke(ctx)


@click.command("pointings", cls=PerscliCommand,
               short_help="Deprecated flag form of perscli pointings select, before and plan.")
@schedule_opt(f"{SCHEDULE_HELP}: select its exposures of the field.")
@click.option("--plan", is_flag=True, default=False, help="Plan a dithered sequence instead.")
@ra_opt("Field centre (--schedule --radius, --plan): right ascension")
@dec_opt("Field centre (--schedule --radius, --plan): declination")
@radius_opt(_flag("--schedule", RADIUS_HELP))
@filter_opt
@limit_opt(_flag("--schedule", LIMIT_HELP))
@mjd_opt("--after", _flag("--schedule", AFTER_HELP))
@row_opt("--before", "--schedule: the --n exposures that start last before schedule row ROW (from 0), whatever "
                     "their filter and pointing, in time order.")
@n_opt("--plan: number of exposures; --before: number of earlier exposures.")
@dither_opt(_flag("--plan", DITHER_HELP))
@mjd_opt("--start", _flag("--plan", START_HELP))
@plan_exptime_opt(_flag("--plan", EXPTIME_HELP))
@gap_opt(_flag("--plan", GAP_HELP))
@pa_opt(_flag("--plan", PA_HELP))
@sca_opt(f"{SCA_HELP} With --schedule and --radius: keep the exposures whose SCA N footprint overlaps the field "
         "circle.")
@row_outputs
@schedule_columns_opt
@no_checksum_opt
@seed_opt
@output_opts
@click.pass_context
@report_errors
def pointings_flags(ctx, schedule, plan, ra, dec, radius, filter_name, limit, after, before, n, dither, start,
                    exptime, gap, pa, sca, footprints, catalog, columns, schedule_columns, seed, output, overwrite):
    """Deprecated: the flag form of perscli pointings select, before and plan.

    It works, with a warning, until perscli 0.3.0; it takes the options it
    took before and writes the same bytes as the subcommand it stands for:

    \b
      perscli pointings --schedule FILE ...             perscli pointings select --schedule FILE ...
      perscli pointings --schedule FILE --before ROW    perscli pointings before --schedule FILE --row ROW
      perscli pointings --plan ...                      perscli pointings plan ...

    See perscli pointings --help and the help of each subcommand.
    """
    given = {name for name in ctx.params
             if ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)}
    if (schedule is None) == (not plan):
        raise click.UsageError("give either --schedule FILE or --plan", ctx)
    # the options of one job only (--n is shared by --plan and --before); what --before takes no field
    schedule_only = ("radius", "limit", "after")
    plan_only = ("dither", "start", "exptime", "gap", "pa", "seed")
    before_excludes = ("ra", "dec", "radius", "filter_name", "limit", "after")
    if plan:
        wrong = [name for name in (*schedule_only, "before") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --schedule, not --plan", ctx)
        if n is None:
            raise click.UsageError("--plan needs --n N (the number of exposures)", ctx)
    elif before is not None:
        wrong = [name for name in (*plan_only, *before_excludes) if name in given]
        if wrong:
            option = "--filter" if wrong[0] == "filter_name" else f"--{wrong[0]}"
            raise click.UsageError(f"{option} is not for --before (the earlier exposures of a schedule row, "
                                   "whatever their filter and pointing)", ctx)
        if n is None:
            raise click.UsageError("--before needs --n N (the number of earlier exposures)", ctx)
    else:
        wrong = [name for name in (*plan_only, "n") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --plan{' or --before' if wrong[0] == 'n' else ''}, "
                                   "not a field selection from --schedule", ctx)
        if radius is None:
            raise click.UsageError("--schedule needs --radius DEG (or --before ROW --n N)", ctx)
    if before is None:
        for name in ("ra", "dec"):
            if name not in given:
                raise click.UsageError(f"Missing option '--{name}': the field centre", ctx)
    check_rows(ctx, sca, footprints, catalog)
    if plan:
        deprecated("perscli pointings --plan ...", "perscli pointings plan ...")
    elif before is not None:
        deprecated("perscli pointings --schedule FILE --before ROW ...",
                   "perscli pointings before --schedule FILE --row ROW ...")
    else:
        deprecated("perscli pointings --schedule FILE ...", "perscli pointings select --schedule FILE ...")
    if plan:
        options = plan_options(filter_name, dither=dither, start=start, exptime=exptime, gap=gap, pa=pa, sca=sca,
                               seed=seed, footprints=footprints, columns=columns)
        run_plan(ctx, ra, dec, n, options, catalog, output, overwrite)
    elif before is not None:
        run_before(ctx, schedule, before, n, sca=sca, footprints=footprints, catalog=catalog, columns=columns,
                   schedule_columns=schedule_columns, output=output, overwrite=overwrite)
    else:
        options = select_options(filter_name, after=after, limit=limit, sca=sca, footprints=footprints,
                                 columns=columns, schedule_columns=schedule_columns)
        run_select(ctx, schedule, ra, dec, radius, options, catalog, output, overwrite)


@click.group("pointings", cls=FlagFormGroup, legacy=pointings_flags,
             short_help="Select exposures of a field from a schedule, or plan dithered ones.")
@verbosity_opts
def pointings():
    """The exposures that look at a field: selected from a survey schedule, or planned.

    Each subcommand writes a FITS table 'POINTINGS' (expid, mjd (start),
    exptime, ra, dec, pa, filter, sca; with --footprints the SCA's corners
    on the sky, with --catalog how many objects of a truth catalogue land
    on it): select takes the exposures of a schedule (by default roman-was,
    the public Roman Wide Area Survey sequence shipped with perscli) that
    look at a field, before takes the
    exposures of a schedule that start last before one of its rows (what
    leaves persistence in it), and plan lays out a dithered sequence that
    Roman can take (by default from the first date, from MJD 61541.972429,
    at which it can).  perscli pointings COMMAND --help says more.

    \b
    Examples:
      perscli pointings select --ra 10 --dec -44 --radius 1 -o was_1deg.fits
      perscli pointings before --row 4183 --n 3 -o was_prev3.fits
      perscli pointings plan --ra 10 --dec -44 --n 3 -o plan3.fits
    """


_BORESIGHT = """

    The boresight (ra, dec) is the centre of the focal plane: SCAs lie up to
    0.45 degrees from it, so a field at the boresight is seen by no SCA in
    particular.  --footprints adds where SCA N lands (the SCA's outer pixel
    edges at (0.5, 0.5), (4088.5, 0.5), (4088.5, 4088.5), (0.5, 4088.5):
    columns corner_ra, corner_dec); with --catalog TRUTH.fits, how many of
    its stars and galaxies land on it, row by row (columns n_star,
    n_galaxy).  perscli render --dry-run shows one frame in detail, and
    perscli catalog --pointings draws a catalogue where the SCA lands."""


SELECT_DOC = """The exposures of a survey schedule that look at a field.

    The exposures of --schedule (the public Roman Wide Area Survey sequence
    shipped with perscli, roman-was, unless a FITS file is given) that look
    at the field, the circle of --radius degrees
    about (--ra, --dec): without --sca, those whose pointing centre lies in
    it; with --sca N, those whose SCA N footprint on the sky (GalSim's Roman
    WCS for the pointing, position angle and date) overlaps it.  Optionally
    in one --filter, after an MJD, at most --limit of them, in time order;
    expid is the row in the schedule (from 0), and the header holds the
    selection and its inputs.""" + _BORESIGHT + """

    \b
    Examples:
      perscli pointings select --ra 10 --dec -44 --radius 1 --filter J129 \\
          -o was_j129.fits
      perscli pointings select --ra 10 --dec -44 --radius 0.05 --sca 7 \\
          --footprints -o was_sca7.fits
      perscli pointings select --ra 10 --dec -44 --radius 0.5 --limit 10 \\
          --after 61900 -o was_after.fits
    """


@pointings.command("select", cls=PerscliCommand, help=SELECT_DOC,
                    short_help="The exposures of a schedule that look at a field.")
@schedule_opt(f"{BUNDLED_HELP}.", default=BUNDLED)
@ra_opt(required=True)
@dec_opt(required=True)
@radius_opt(RADIUS_HELP, required=True)
@filter_opt
@limit_opt(LIMIT_HELP)
@mjd_opt("--after", AFTER_HELP)
@sca_opt(f"{SCA_HELP} Keeps the exposures whose SCA N footprint overlaps the field circle (without: those whose "
         "pointing centre lies in it).")
@schedule_tail
def select(ctx, schedule, ra, dec, radius, filter_name, limit, after, sca, footprints, catalog, columns,
           schedule_columns, output, overwrite):
    check_rows(ctx, sca, footprints, catalog)
    options = select_options(filter_name, after=after, limit=limit, sca=sca, footprints=footprints, columns=columns,
                             schedule_columns=schedule_columns)
    run_select(ctx, schedule, ra, dec, radius, options, catalog, output, overwrite)


@pointings.command("before", cls=PerscliCommand,
                   short_help="The exposures of a schedule that start last before one of its rows.")
@schedule_opt(f"{BUNDLED_HELP}.", default=BUNDLED)
@row_opt("--row", "The schedule row (from 0) whose earlier exposures to take.", required=True)
@n_opt("Number of earlier exposures.", required=True)
@sca_opt(SCA_HELP)
@schedule_tail
def before(ctx, schedule, row, n, sca, footprints, catalog, columns, schedule_columns, output, overwrite):
    """The exposures of a schedule that start last before one of its rows.

    The --n exposures of --schedule (roman-was, the public Roman Wide Area
    Survey sequence shipped with perscli, unless a FITS file is given) that
    start last before row --row starts (rows from 0), whatever their filter and wherever they point: on
    one detector, they are what leaves persistence in that row.  In time
    order (the most recent last); fewer, with a warning, when the schedule
    starts sooner.  expid is the row in the schedule, and the header holds
    the row, the number asked for and the inputs.  --footprints adds where
    SCA N lands in each (columns corner_ra, corner_dec); with --catalog
    TRUTH.fits, how many of its stars and galaxies land on it (n_star,
    n_galaxy).

    \b
    Examples:
      perscli pointings before --row 4183 --n 10 --sca 7 -o was_prev.fits
      perscli pointings before --row 4183 --n 2 --sca 7 --footprints \\
          -o was_prev_sca7.fits
    """
    check_rows(ctx, sca, footprints, catalog)
    run_before(ctx, schedule, row, n, sca=sca, footprints=footprints, catalog=catalog, columns=columns,
               schedule_columns=schedule_columns, output=output, overwrite=overwrite)


PLAN_DOC = f"""A dithered sequence of exposures that Roman can take.

    --n exposures of --exptime seconds, each starting --gap seconds after the
    previous one ends, pointed at (--ra, --dec) offset by a random amount
    within +-(--dither) arcsec east and north (seeded by --seed), all at
    --pa, in --filter (default J129); expid 0 to N-1.  Roman can take every
    exposure of a plan (GalSim's Roman module: 54 to 126 degrees from the
    Sun).  Without --start the plan starts on the first date, from MJD
    {PLAN_REFERENCE_MJD} (2027-05-16, the first exposure of the public survey
    schedule) in steps of one day, at which it can (the same inputs give
    the same plan); without --pa, at GalSim's best PA for the first exposure
    then.  A --start at which Roman cannot take them is refused, naming the
    first start after it that works and the best PA there.  The header
    records the plan, the start and PA and how they were chosen (PTSTFROM,
    PTPAFROM), GalSim's best PA (PTBESTPA) and the Sun angle
    (PTSUNANG).""" + _BORESIGHT + """

    \b
    Examples:
      perscli pointings plan --ra 10 --dec -44 --n 8 --dither 30 --seed 3 -o plan8.fits
      perscli pointings plan --ra 10 --dec -44 --n 4 --start 61600.5 --pa 240 --sca 7 -o plan_given.fits
      perscli pointings plan --ra 10 --dec -44 --n 4 --exptime 60 --gap 10 --sca 7 -o - | gzip > plan4.fits.gz
      perscli catalog --ra 10 --dec -44 --size 60 --galaxy-density 1 --star-density 0.5 -o wide_cat.fits
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 --footprints --catalog wide_cat.fits -o plan_counts.fits
    """


@pointings.command("plan", cls=PerscliCommand, help=PLAN_DOC,
                   short_help="A dithered sequence of exposures Roman can take.")
@ra_opt(required=True)
@dec_opt(required=True)
@n_opt("Number of exposures.", required=True)
@dither_opt(DITHER_HELP)
@filter_opt
@mjd_opt("--start", START_HELP)
@plan_exptime_opt(EXPTIME_HELP)
@gap_opt(GAP_HELP)
@pa_opt(PA_HELP)
@sca_opt(SCA_HELP)
@row_outputs
@no_checksum_opt
@seed_opt
@output_opts
@click.pass_context
@report_errors
def plan(ctx, ra, dec, n, dither, filter_name, start, exptime, gap, pa, sca, footprints, catalog, columns, seed,
         output, overwrite):
    check_rows(ctx, sca, footprints, catalog)
    options = plan_options(filter_name, dither=dither, start=start, exptime=exptime, gap=gap, pa=pa, sca=sca,
                           seed=seed, footprints=footprints, columns=columns)
    run_plan(ctx, ra, dec, n, options, catalog, output, overwrite)
