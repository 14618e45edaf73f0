"""``perscli apply-persistence``: persistence of earlier exposures on a frame."""

from __future__ import annotations

import logging

import click

from .helpers import check_outputs, progress_reporter, report_errors
from .options import (compress_opt, exptime_opt, gain_opt, model_opt, no_checksum_opt, output_opt, overwrite_opt,
                      units_opt, verbosity_opts, workers_opt)

log = logging.getLogger("perscli")


@click.command("apply-persistence", short_help="Add, subtract or predict the persistence of earlier exposures.")
@click.argument("current", metavar="CURRENT")
@click.argument("previous", nargs=-1, required=True, metavar="PREVIOUS...")
@output_opt
@model_opt("typical", "NAME|MODEL.yaml|FRAME.fits",
           "the persistence law: typical or pessimistic (the paper's Table 1), galsim-linear (GalSim's 8 "
           "coefficients), a YAML file (persistence parameters, or a detector model as render takes), or a "
           "frame perscli rendered (the persistence of the model that made it)")
@click.option("--param", "params", multiple=True, metavar="KEY=VALUE",
              help="Override a model parameter (A, x0, dx, alpha, gamma, half_well) or setting (time_model, "
                   "combine, max_previous). Repeatable.")
@click.option("--mode", type=click.Choice(["add", "subtract", "predict"]), default="add", show_default=True,
              help="Add persistence, subtract it (a correction), or write the persistence alone.")
@click.option("--time-model", type=click.Choice(["exact", "galsim"]), default=None,
              help="exact: integral of the rate over the exposure from the real timestamps; "
                   "galsim: galsim.roman.applyPersistence(method='fermi')'s mid-exposure rate "
                   "[default: the model's time_model, exact].")
@click.option("--combine", type=click.Choice(["sum", "max"]), default=None,
              help="Sum over earlier exposures (the paper, GalSim) or per-pixel maximum (WFC3 pipeline) "
                   "[default: the model's combine, sum].")
@click.option("--max-previous", type=click.IntRange(min=0), default=None, metavar="N",
              help="Only the N most recent earlier exposures count (0: all) [default: the model's max_previous, 10].")
@click.option("--gap", type=click.FloatRange(min=0), default=None, metavar="SECONDS",
              help="Ignore header timestamps: PREVIOUS... then CURRENT, in command-line order, are consecutive "
                   "exposures separated by SECONDS.")
@units_opt
@gain_opt
@exptime_opt
@compress_opt
@no_checksum_opt
@overwrite_opt
@workers_opt("threads over blocks of rows (the output does not depend on N)")
@verbosity_opts
@report_errors
def apply_persistence(current, previous, output, model_spec, params, mode, time_model, combine,
                      max_previous, gap, units, gain, exptime, compress, overwrite, workers):
    """Add, subtract or predict the persistence of earlier exposures on CURRENT.

    Each earlier exposure (PREVIOUS...) with fluence x electrons releases
    P(x, t) = F(x) (t/1000 s)^-gamma e-/s, t counted from its end (the paper's
    Fermi model, linear below half_well).  The charge added to CURRENT is the
    exact integral of P over CURRENT's own exposure window, from EXPSTART/EXPEND,
    MJD-BEG/MJD-END or DATE-OBS + EXPTIME; for a ramp (WFC3-IR raw/ima, or a
    3-D cube with a READTIMES table) it is the integral up to each read.
    Earlier exposures are ordered by their timestamps, not by their order on
    the command line, and only the --max-previous most recent count.

    Fluence of an earlier exposure is its accumulated charge: rate x EXPTIME,
    DN x gain, or last read minus zeroth read for a ramp.  Non-finite pixels
    count as zero and are reported.  The output has CURRENT's structure and
    units, with provenance and checksums in its primary header.

    \b
    Examples:
      perscli apply-persistence exp4.fits exp1.fits exp2.fits exp3.fits -o exp4_pers.fits
      perscli apply-persistence exp4.fits exp3.fits --mode predict -o pers.fits
      perscli apply-persistence flt.fits prev_flt.fits --model pessimistic --param gamma=1.1 -o out.fits
      perscli apply-persistence raw.fits prev_raw.fits --combine max --mode subtract -o corrected.fits
      cat exp4.fits | perscli apply-persistence - exp3.fits -o - | perscli apply-persistence - exp2.fits -o out.fits
    """
    from ..detector.apply import apply_persistence_files
    from ..detector.persistence import load_model

    check_outputs(output, inputs=[current, *previous, model_spec], overwrite=overwrite)
    model = load_model(model_spec, params)
    result = apply_persistence_files(
        current, previous, output, model=model, mode=mode, time_model=time_model, combine=combine,
        max_previous=max_previous, units=units, gain=gain, exptime=exptime, gap=gap,
        overwrite=overwrite, workers=workers, progress=progress_reporter("rows"), compress=compress)
    log.info("%s: persistence from %d earlier exposure(s): max %.4g e-, total %.6g e- (last plane)",
             "stdout" if output == "-" else output, len(result.used), result.max_electrons,
             result.total_electrons)
