"""``perscli budget``: the Roman additive shear budget as xi+(theta), and a measured xi+ against it."""

from __future__ import annotations

import logging

import click

from ..stats.settings import BudgetOptions
from .helpers import FILE, PerscliCommand, check_outputs, report_errors
from .options import (columns_opt, no_checksum_opt, output_opt, overwrite_opt, plot_opt, settings_options,
                      verbosity_opts)

#: ``--check``'s exit status when a bin exceeds the budget (1 is an error, 2 a usage error)
EXIT_OVER_BUDGET = 3

log = logging.getLogger("perscli")

#: the defaults, written once (perscli.stats.settings)
D = BudgetOptions()


@click.command("budget", cls=PerscliCommand,
               short_help="Compare a measured xi+ with the Roman additive shear budget.")
@click.argument("xi", required=False, metavar="[XI.fits]", type=FILE)
@settings_options(BudgetOptions, "bands", "modes", "n_sigma")
@click.option("--theta-range", type=(click.FloatRange(min=0, min_open=True), click.FloatRange(min=0, min_open=True)),
              default=None, metavar="ARCMIN ARCMIN",
              help=f"Without XI: smallest and largest separation of the table [default: {D.theta_min:g} "
                   f"{D.theta_max:g}].")
@click.option("--nbins", type=click.IntRange(min=1), default=None, metavar="N",
              help=f"Without XI: number of log-spaced separations [default: {D.nbins}].")
@plot_opt("xi+ with error bars against the budget (log theta, symlog xi+, linear range shaded)")
@columns_opt("XI", "meanr=theta,xip=xi_plus,sigma_xip=sigma")
@no_checksum_opt
@click.option("--check", is_flag=True, default=False,
              help="Exit with status 3 (after writing the outputs) if any bin exceeds the budget (1 stays an "
                   "error).")
@output_opt
@overwrite_opt
@verbosity_opts
@click.pass_context
@report_errors
def budget(ctx, xi, bands, modes, n_sigma, theta_range, nbins, plot, columns, check, output, overwrite):
    """The Roman additive shear budget as xi+(theta), and a measured xi+ against it.

    The HLIS requirement (Dore et al. 2018) allows an additive shear rms per
    component of 7.5e-5, 9.9e-5, 1.4e-4 and 1.9e-4 in the multipole bands
    31-99, 100-315, 316-999 and 1000-3161.  Inside band a the budget's
    spectrum is C_l = A_a^2 4pi / (l(l+1)) / N_a, N_a = sum over the band of
    (2l+1)/(l(l+1)), and xi+(theta) = sum over integer l of (2l+1)/(4pi) C_l
    J0(l theta): 6.81e-8 at 1', 1.87e-8 at 10', 8.4e-10 at 100' (E modes;
    --modes EB doubles it).  The budget changes sign beyond ~170'.

    Without XI: the budget on log-spaced separations (--theta-range, --nbins).

    With XI, a `perscli correlate` table (TreeCorr's GG columns; separation
    meanr, else r_nom, in SEP_UNIT, default arcmin; '-' for standard input):
    the budget at its separations, ratio = xip / budget and its error
    sigma_xip / |budget|, and per bin whether |xip| - N sigma_xip > |budget|
    (--sigma N).  Bins without pairs (weight 0) are skipped.  A one-line
    verdict goes to stderr, e.g. 'below budget by 1.8 orders of magnitude at
    worst (theta = 0.5 arcmin)', and into the header (VERDICT).  When bins
    exceed, it names the one furthest over its budget, e.g. 'exceeds the
    budget at 2.5 arcmin (xi+ = 1.2e-07 > 5.45e-08 + 2 sigma, sigma = 3e-09:
    2.2 +- 0.055 x the budget); 1 of 20 bins', and the header gives that
    bin (BUDWBIN, BUDWSEP, BUDWRAT).  Errors that are shot noise (correlate
    without a jackknife) are said in the verdict.

    Output: a FITS table 'BUDGET': theta, xip_budget, and with XI also xip,
    sigma_xip, ratio, sigma_ratio, exceeds; the bands, modes and --sigma in
    the header (BUDBANDS, BUDMODES, BUDSIGMA, BUDA1-4).  --check: exit status
    3 if any bin exceeds the budget, after writing the outputs (a finding,
    not an error: errors exit 1).

    \b
    Examples:
      perscli budget -o budget.fits --plot budget.png
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o pair.fits
      perscli catalog --pointings pair.fits --bounds 1 256 1 256 -o truth.fits
      perscli render truth.fits --pointings pair.fits --row 0 --bounds 1 256 1 256 --seed 1 -o frame0.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 256 1 256 --seed 2 \\
          --previous frame0.fits -o frame.fits
      perscli render truth.fits --pointings pair.fits --row 1 --bounds 1 256 1 256 --seed 2 \\
          --set persistence=off -o frame_nop.fits
      perscli measure frame.fits frame_nop.fits --catalog truth.fits -o both.fits
      perscli correlate both.fits --frames 0 1 --min-sep 0.05 --max-sep 2 --nbins 5 -o xi.fits
      perscli budget xi.fits -o cmp.fits --plot xi_vs_budget.png
      perscli budget xi.fits --bands hirata --modes EB --sigma 3 -o cmp_hirata.fits
      perscli correlate both.fits --frames 0 1 --min-sep 0.05 --max-sep 2 --nbins 5 -o - | perscli budget - -o cmp_pipe.fits
      perscli budget xi.fits --check -o cmp_check.fits || [ $? -eq 3 ]   # 3: xi+ exceeds the budget

    (The second to the eighth make a measured xi+, as perscli correlate
    --help does: the shape changes De of the galaxies of a 256 x 256 cutout
    of SCA 7 between an exposure with and without the persistence of the
    one before.)
    """
    if xi is not None and (theta_range is not None or nbins is not None):
        raise click.UsageError("--theta-range and --nbins are for the budget alone; with XI the separations "
                               "are the table's", ctx)
    if theta_range is not None and not theta_range[0] < theta_range[1]:
        raise click.BadParameter(f"the smallest separation must come first: {theta_range[0]:g} >= "
                                 f"{theta_range[1]:g}", ctx, param_hint="'--theta-range'")

    from ..stats.budget import budget_file

    check_outputs(output, inputs=[xi], plot=plot, overwrite=overwrite)
    lo, hi = theta_range if theta_range is not None else (D.theta_min, D.theta_max)
    grid = (lo, hi, nbins if nbins is not None else D.nbins)
    result = budget_file(output, xi, bands=bands, modes=modes.upper(), n_sigma=n_sigma, grid=grid, plot=plot,
                         overwrite=overwrite, columns=columns)
    where = "stdout" if output == "-" else output
    if result.xip is None:
        log.info("%s: budget (%s, %s) at %d separations, %.3g to %.3g arcmin", where, result.bands, result.modes,
                 len(result.theta), result.theta[0], result.theta[-1])
        return
    verbosity = (ctx.find_root().obj or {}).get("verbosity", 0)
    if verbosity >= 0:
        # stderr: standard output may carry the FITS table (-o -)
        click.echo(f"{'stdin' if xi == '-' else xi}: {result.verdict}", err=True)
    if check and result.n_exceeding:
        # a verdict, not a failure: scripts tell "over budget" (3) from "could not tell" (1)
        ctx.exit(EXIT_OVER_BUDGET)
