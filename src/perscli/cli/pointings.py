"""``perscli pointings``: the exposures that look at a field, from a schedule or planned."""

from __future__ import annotations

import logging

import click
from click.core import ParameterSource

from ..instrument import ROMAN_EXPTIME, ROMAN_WAS_GAP
from .helpers import check_outputs, report_errors
from .options import dec_opt, filter_opt, output_opt, overwrite_opt, ra_opt, sca_opt, seed_opt, verbosity_opts

log = logging.getLogger("perscli")

#: options that belong to one mode only
SCHEDULE_ONLY = ("radius", "limit", "after")
PLAN_ONLY = ("n", "dither", "start", "exptime", "gap", "pa", "seed")


@click.command("pointings", short_help="Select exposures of a field from a schedule, or plan dithered ones.")
@click.option("--schedule", metavar="FILE", default=None,
              help="Survey schedule (FITS table: date, exptime, ra, dec, pa, filter; '-' for standard input): "
                   "select its exposures of the field.")
@click.option("--plan", is_flag=True, default=False, help="Plan a dithered sequence instead.")
@ra_opt
@dec_opt
@click.option("--radius", type=click.FloatRange(min=0, min_open=True), default=None, metavar="DEG",
              help="--schedule: pointing centres within this great-circle distance of the field centre.")
@filter_opt
@click.option("--limit", type=click.IntRange(min=1), default=None, metavar="N",
              help="--schedule: only the N earliest exposures selected.")
@click.option("--after", type=float, default=None, metavar="MJD",
              help="--schedule: only exposures that start after this MJD.")
@click.option("--n", "n", type=click.IntRange(min=1), default=None, metavar="N",
              help="--plan: number of exposures.")
@click.option("--dither", type=click.FloatRange(min=0), default=10.0, show_default=True, metavar="ARCSEC",
              help="--plan: offsets uniform within +-ARCSEC east and north of the field centre.")
@click.option("--start", type=float, default=60000.0, show_default=True, metavar="MJD",
              help="--plan: start of the first exposure.")
@click.option("--exptime", type=click.FloatRange(min=0, min_open=True), default=ROMAN_EXPTIME, show_default=True,
              metavar="SECONDS", help=f"--plan: exposure time (Roman survey: {ROMAN_EXPTIME:g} s).")
@click.option("--gap", type=click.FloatRange(min=0), default=ROMAN_WAS_GAP, show_default=True, metavar="SECONDS",
              help=f"--plan: from the end of one exposure to the start of the next (Roman survey: "
                   f"~{ROMAN_WAS_GAP:g} s).")
@click.option("--pa", type=float, default=0.0, show_default=True, metavar="DEG",
              help="--plan: position angle of every exposure.")
@sca_opt
@seed_opt
@output_opt
@overwrite_opt
@verbosity_opts
@click.pass_context
@report_errors
def pointings(ctx, schedule, plan, ra, dec, radius, filter_name, limit, after, n, dither, start, exptime, gap,
              pa, sca, seed, output, overwrite):
    """Select the exposures of a field from a schedule, or plan a dithered sequence.

    With --schedule FILE: the exposures of a survey schedule (such as the
    public Roman Wide Area Survey sequence) whose pointing centre lies within
    --radius degrees of (--ra, --dec), optionally in one --filter, after an
    MJD, at most --limit of them, in time order; expid is the row in the
    schedule (from 0).

    With --plan: --n exposures of --exptime seconds, each starting --gap
    seconds after the previous one ends, pointed at (--ra, --dec) offset by
    a random amount within +-(--dither) arcsec east and north (seeded by
    --seed), all at --pa, in --filter (default J129); expid 0 to N-1.

    The output is a FITS table 'POINTINGS': expid, mjd (start), exptime,
    ra, dec, pa, filter, sca (--sca, 0 when none is chosen), with the
    selection or plan and its inputs in the header.

    \b
    Examples:
      perscli pointings --schedule Roman_WAS_obseq_11_1_23.fits --ra 10 --dec -44 --radius 1 --filter J129 -o p.fits
      perscli pointings --schedule obseq.fits --ra 10 --dec -44 --radius 0.5 --limit 10 --after 61900 -o p.fits
      perscli pointings --plan --ra 10 --dec -44 --n 8 --dither 30 --seed 3 -o plan.fits
      perscli pointings --plan --ra 10 --dec -44 --n 4 --exptime 60 --gap 10 --sca 7 -o - | gzip > plan.fits.gz
    """
    given = {name for name in ctx.params
             if ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)}
    if (schedule is None) == (not plan):
        raise click.UsageError("give either --schedule FILE or --plan", ctx)
    if plan:
        wrong = [name for name in SCHEDULE_ONLY if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --schedule, not --plan", ctx)
        if n is None:
            raise click.UsageError("--plan needs --n N (the number of exposures)", ctx)
    else:
        wrong = [name for name in PLAN_ONLY if name in given]
        if wrong:
            raise click.UsageError(f"--{wrong[0]} is for --plan, not --schedule", ctx)
        if radius is None:
            raise click.UsageError("--schedule needs --radius DEG", ctx)

    from ..scene.pointings import plan_dithers_file, select_covering_file

    check_outputs(output, inputs=[schedule], overwrite=overwrite)

    if plan:
        chosen = plan_dithers_file(output, ra, dec, n, dither=dither, filter=filter_name or "J129", start=start,
                                   exptime=exptime, gap=gap, pa=pa, sca=sca, seed=seed, overwrite=overwrite)
    else:
        chosen = select_covering_file(output, schedule, ra, dec, radius, filter=filter_name, after=after,
                                      limit=limit, sca=sca, overwrite=overwrite)
        if not chosen:
            log.warning("%s: no exposure within %g degrees of (%g, %g)%s; the output table is empty",
                        schedule, radius, ra, dec, f" in {filter_name}" if filter_name else "")
    log.info("%s: %d exposures", "stdout" if output == "-" else output, len(chosen))
