"""``perscli pointings``: the exposures that look at a field, from a schedule or planned."""

from __future__ import annotations

import logging

import click
from click.core import ParameterSource

from ..instrument import ROMAN_EXPTIME, ROMAN_N_SCA, ROMAN_WAS_GAP
from .helpers import FILE, PerscliCommand, check_outputs, report_errors
from .options import (columns_opt, dec_opt, filter_opt, no_checksum_opt, mjd_opt, output_opt, overwrite_opt, pa_opt, ra_opt, seed_opt,
                      verbosity_opts)

log = logging.getLogger("perscli")

#: options that belong to one mode only (--n is shared by --plan and --before)
SCHEDULE_ONLY = ("radius", "limit", "after")
PLAN_ONLY = ("dither", "start", "exptime", "gap", "pa", "seed")
#: what --before does not take: it needs no field
BEFORE_EXCLUDES = ("ra", "dec", "radius", "filter_name", "limit", "after")

#: where a plan without --start starts looking (perscli.scene.pointings.PLAN_REFERENCE_MJD, written here so that
#: --help does not import the library; tests check that they agree)
PLAN_REFERENCE_MJD = 61541.972429

sca_opt = click.option(
    "--sca", type=click.IntRange(0, ROMAN_N_SCA), default=0, show_default=True, metavar="N",
    help=f"Roman detector (SCA 1-{ROMAN_N_SCA}), written into every row; 0 for none chosen. With --schedule and "
         "--radius: keep the exposures whose SCA N footprint overlaps the field circle.")


@click.command("pointings", cls=PerscliCommand,
               short_help="Select exposures of a field from a schedule, or plan dithered ones.")
@click.option("--schedule", metavar="FILE", default=None, type=FILE,
              help="Survey schedule (FITS table: date, exptime, ra, dec, pa, filter; '-' for standard input): "
                   "select its exposures of the field.")
@click.option("--plan", is_flag=True, default=False, help="Plan a dithered sequence instead.")
@ra_opt("Field centre (--schedule --radius, --plan): right ascension")
@dec_opt("Field centre (--schedule --radius, --plan): declination")
@click.option("--radius", type=click.FloatRange(min=0, max=180, min_open=True), default=None, metavar="DEG",
              help="--schedule: radius of the field circle (great circle): pointing centres within it, or "
                   "with --sca N the exposures whose SCA N overlaps it.")
@filter_opt
@click.option("--limit", type=click.IntRange(min=1), default=None, metavar="N",
              help="--schedule: only the N earliest exposures selected.")
@mjd_opt("--after", "--schedule: only exposures that start after this MJD.")
@click.option("--before", type=click.IntRange(min=0), default=None, metavar="ROW",
              help="--schedule: the --n exposures that start last before schedule row ROW (from 0), "
                   "whatever their filter and pointing, in time order.")
@click.option("--n", "n", type=click.IntRange(min=1), default=None, metavar="N",
              help="--plan: number of exposures; --before: number of earlier exposures.")
@click.option("--dither", type=click.FloatRange(min=0, max=3600), default=10.0, show_default=True, metavar="ARCSEC",
              help="--plan: offsets uniform within +-ARCSEC east and north of the field centre.")
@mjd_opt("--start", "--plan: start of the first exposure; refused (with the first start after it that works) "
                    "if Roman cannot take every exposure of the plan  [default: the first date, from MJD "
                    f"{PLAN_REFERENCE_MJD} (the public Roman Wide Area Survey schedule's first exposure) in steps "
                    "of one day, at which Roman can take every exposure]")
@click.option("--exptime", type=click.FloatRange(min=0, min_open=True), default=ROMAN_EXPTIME, show_default=True,
              metavar="SECONDS", help=f"--plan: exposure time (Roman survey: {ROMAN_EXPTIME:g} s).")
@click.option("--gap", type=click.FloatRange(min=0), default=ROMAN_WAS_GAP, show_default=True, metavar="SECONDS",
              help=f"--plan: from the end of one exposure to the start of the next (Roman survey: "
                   f"~{ROMAN_WAS_GAP:g} s).")
@pa_opt("--plan: observatory position angle of every exposure, degrees (GalSim's convention; any roll is "
        "taken, as GalSim takes it)  [default: GalSim's best PA, galsim.roman.bestPA, for the first "
        "exposure at its start]")
@sca_opt
@click.option("--footprints", is_flag=True, default=False,
              help="Add each row's SCA corners on the sky (columns corner_ra, corner_dec, 4 values each, "
                   "degrees; GalSim's Roman WCS); needs --sca N.")
@click.option("--catalog", "catalog", metavar="TRUTH.fits", default=None, type=FILE,
              help="With --footprints: also count the objects of this truth catalogue (perscli catalog) whose "
                   "centre lands on each row's SCA (columns n_star, n_galaxy).")
@columns_opt("--catalog", "ra=ALPHA_J2000,dec=DELTA_J2000,kind=CLASS")
@columns_opt("--schedule", "date=mjd_start,exptime=exp_time", name="--schedule-columns")
@no_checksum_opt
@seed_opt
@output_opt
@overwrite_opt
@verbosity_opts
@click.pass_context
@report_errors
def pointings(ctx, schedule, plan, ra, dec, radius, filter_name, limit, after, before, n, dither, start, exptime,
              gap, pa, sca, footprints, catalog, columns, schedule_columns, seed, output, overwrite):
    """Select the exposures of a field from a schedule, or plan a dithered sequence.

    With --schedule FILE: the exposures of a survey schedule (such as the
    public Roman Wide Area Survey sequence) that look at the field, the
    circle of --radius degrees about (--ra, --dec): without --sca, those
    whose pointing centre lies in it; with --sca N, those whose SCA N
    footprint on the sky (GalSim's Roman WCS for the pointing, position
    angle and date) overlaps it.  Optionally in one --filter, after an MJD,
    at most --limit of them, in time order; expid is the row in the
    schedule (from 0).

    With --schedule FILE --before ROW --n N: the N exposures that start last
    before row ROW starts, whatever their filter and wherever they point
    (on one detector, they are what leaves persistence in ROW), in time
    order (the most recent last).

    With --plan: --n exposures of --exptime seconds, each starting --gap
    seconds after the previous one ends, pointed at (--ra, --dec) offset by
    a random amount within +-(--dither) arcsec east and north (seeded by
    --seed), all at --pa, in --filter (default J129); expid 0 to N-1.
    Roman can take every exposure of a plan (GalSim's Roman module: 54 to
    126 degrees from the Sun).  Without --start the plan starts on the first
    date, from MJD 61541.972429 (2027-05-16, the first exposure of the public
    survey schedule) in steps of one day, at which it can (the same inputs
    give the same plan); without --pa, at GalSim's best PA for the first
    exposure then.  A --start at which Roman cannot take them is refused,
    naming the first start after it that works and the best PA there.  The
    header records the start and PA and how they were chosen (PTSTFROM,
    PTPAFROM), GalSim's best PA (PTBESTPA) and the Sun angle (PTSUNANG).

    The boresight (ra, dec) is the centre of the focal plane: SCAs lie up to
    0.45 degrees from it, so a field at the boresight is seen by no SCA in
    particular.  --footprints adds where SCA N lands; with --catalog
    TRUTH.fits, how many of its stars and galaxies land on it, row by row
    (perscli render --dry-run shows one frame in detail, and perscli
    catalog --footprints draws a catalogue where the SCA lands).

    The output is a FITS table 'POINTINGS': expid, mjd (start), exptime,
    ra, dec, pa, filter, sca (--sca, 0 when none is chosen), with
    --footprints corner_ra, corner_dec (the SCA's outer pixel edges at
    (0.5, 0.5), (4088.5, 0.5), (4088.5, 4088.5), (0.5, 4088.5)), with
    --catalog n_star, n_galaxy; the selection or plan and its inputs are
    in the header.

    \b
    Examples:
      perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --ra 10 --dec -44 --radius 1 --filter J129 \\
          -o was_j129.fits
      perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --ra 10 --dec -44 --radius 0.05 --sca 7 --footprints \\
          -o was_sca7.fits
      perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --before 4183 --n 10 --sca 7 -o was_prev.fits
      perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --ra 10 --dec -44 --radius 0.5 --limit 10 \\
          --after 61900 -o was_after.fits
      perscli pointings --plan --ra 10 --dec -44 --n 8 --dither 30 --seed 3 -o plan8.fits
      perscli pointings --plan --ra 10 --dec -44 --n 4 --start 61600.5 --pa 240 --sca 7 -o plan_given.fits
      perscli pointings --plan --ra 10 --dec -44 --n 4 --exptime 60 --gap 10 --sca 7 -o - | gzip > plan4.fits.gz
      perscli catalog --ra 10 --dec -44 --size 60 --galaxy-density 1 --star-density 0.5 -o wide_cat.fits
      perscli pointings --plan --ra 10 --dec -44 --n 2 --sca 7 --footprints --catalog wide_cat.fits -o plan_counts.fits
    """
    given = {name for name in ctx.params
             if ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)}
    if (schedule is None) == (not plan):
        raise click.UsageError("give either --schedule FILE or --plan", ctx)
    if plan:
        wrong = [name for name in (*SCHEDULE_ONLY, "before") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --schedule, not --plan", ctx)
        if n is None:
            raise click.UsageError("--plan needs --n N (the number of exposures)", ctx)
    elif before is not None:
        wrong = [name for name in (*PLAN_ONLY, *BEFORE_EXCLUDES) if name in given]
        if wrong:
            option = "--filter" if wrong[0] == "filter_name" else f"--{wrong[0]}"
            raise click.UsageError(f"{option} is not for --before (the earlier exposures of a schedule row, "
                                   "whatever their filter and pointing)", ctx)
        if n is None:
            raise click.UsageError("--before needs --n N (the number of earlier exposures)", ctx)
    else:
        wrong = [name for name in (*PLAN_ONLY, "n") if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --plan{' or --before' if wrong[0] == 'n' else ''}, "
                                   "not a field selection from --schedule", ctx)
        if radius is None:
            raise click.UsageError("--schedule needs --radius DEG (or --before ROW --n N)", ctx)
    if before is None:
        for name in ("ra", "dec"):
            if name not in given:
                raise click.UsageError(f"Missing option '--{name}': the field centre", ctx)
    if footprints and not sca:
        raise click.UsageError("--footprints needs --sca N (1-18): the detector whose corners to add", ctx)
    if catalog is not None and not footprints:
        raise click.UsageError("--catalog needs --footprints --sca N: the detector on which to count its objects",
                               ctx)

    from ..scene.pointings import plan_dithers_file, previous_exposures_file, select_covering_file

    check_outputs(output, inputs=[schedule, catalog], overwrite=overwrite)

    if plan:
        chosen = plan_dithers_file(output, ra, dec, n, dither=dither, filter=filter_name or "J129", start=start,
                                   exptime=exptime, gap=gap, pa=pa, sca=sca, seed=seed, footprints=footprints,
                                   catalog=catalog, overwrite=overwrite, columns=columns)
        if chosen:
            log.info("plan: start MJD %.6f (%s), PA %.4f (%s)", chosen[0].mjd,
                     "given" if start is not None else "the first observable", chosen[0].pa,
                     "given" if pa is not None else "GalSim's best")
    elif before is not None:
        chosen = previous_exposures_file(output, schedule, before, n, sca=sca, footprints=footprints,
                                         catalog=catalog, overwrite=overwrite, columns=columns,
                                         schedule_columns=schedule_columns)
        if len(chosen) < n:
            log.warning("%s: only %d exposure(s) start before row %d (asked for %d)", schedule, len(chosen),
                        before, n)
    else:
        chosen = select_covering_file(output, schedule, ra, dec, radius, filter=filter_name, after=after,
                                      limit=limit, sca=sca, footprints=footprints, catalog=catalog,
                                      overwrite=overwrite, columns=columns, schedule_columns=schedule_columns)
        if not chosen:
            what = f"whose SCA {sca} overlaps the circle of {radius:g} degrees" if sca else \
                f"within {radius:g} degrees"
            log.warning("%s: no exposure %s about (%g, %g)%s; the output table is empty",
                        schedule, what, ra, dec, f" in {filter_name}" if filter_name else "")
    # what was written, in one line on stderr (stdout may be the table itself), unless -q
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0)
    if verbosity >= 0:
        click.echo(f"{'stdout' if output == '-' else output}: {len(chosen)} rows written (exposures)", err=True)
