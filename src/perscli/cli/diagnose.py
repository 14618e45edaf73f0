"""``perscli diagnose``: where simulated and measured frames disagree, and which effect is missing."""

from __future__ import annotations

import logging
import os

import click

from .. import PerscliError
from ..diagnose.settings import DiagnoseOptions
from ..io.output import check_output_folder
from .helpers import FILE, FOLDER, PerscliCommand, report_errors, verbosity
from .options import (FiniteRange, model_opt, no_checksum_opt, overwrite_opt, settings_options, verbosity_opts,
                      workers_opt)

log = logging.getLogger("perscli")

#: the defaults, written once (perscli.diagnose.settings)
D = DiagnoseOptions()


@click.command("diagnose", cls=PerscliCommand,
               short_help="Find the detector effect a simulation lacks, fit it, show the gap shrink.")
@click.argument("measured", nargs=-1, required=True, metavar="MEASURED...", type=FILE)
@click.option("--simulated", "simulated", multiple=True, metavar="SIM.fits", type=FILE,
              help="The same exposures rendered by perscli render (SCI, IDEAL, FLUENCE, MODEL); repeatable. "
                   "Paired with MEASURED by start time (within 1 s), else in order. Without them, a lone "
                   "ramp is predicted from its own earliest reads.")
@model_opt(None, "MODEL.yaml|FRAME.fits",
           "the one to test, a YAML list of effects or a frame perscli rendered [default: the one stored in the "
           "simulated frames]")
@click.option("-o", "--output", "outdir", required=True, metavar="OUTDIR", type=FOLDER,
              help="Folder to write: model.yaml, report.json, report.md and PNG figures.")
@settings_options(DiagnoseOptions, "fit_pixels")
@click.option("--gain", type=FiniteRange(min=1e-3, max=1e3), default=None, metavar="E_PER_DN",
              help="Gain of measured DN frames whose header has no GAIN or CCDGAIN.")
@click.option("--exptime", type=FiniteRange(min=0, min_open=True, max=1e7), default=None, metavar="SECONDS",
              help="Exposure time of measured frames whose header has none.")
@workers_opt("threads over the exposures of each likelihood evaluation (the same result with any number)")
@no_checksum_opt
@overwrite_opt
@verbosity_opts
@report_errors
def diagnose(measured, simulated, model_spec, outdir, fit_pixels, gain, exptime, workers, overwrite):
    """Find where MEASURED frames and their simulation disagree, and which detector effect is missing.

    The expectation and variance of every measured pixel come from the
    detector model's forward model (the same effects render samples) of the
    simulation's IDEAL, with the persistence of the earlier exposures; the
    residuals are examined against the pixel's signal, its neighbours', the
    fluence of earlier exposures, exposure and read times and position.  Each
    candidate (persistence A, ipc alpha, brighter_fatter coefficient,
    nonlinearity beta, reciprocity alpha, dark current, offset level,
    read_noise sigma, correlated_read_noise row and column, gain) is fitted
    by likelihood beside the effects already named; the best is named when
    its likelihood-ratio improvement passes a test with a false-alarm
    probability of 1e-3 and its value is physical, and the search repeats;
    then every named effect is retested beside the others, the set is
    compared with every other set of candidates, and one joint fit gives
    marginal errors and correlations.  Sets the data cannot tell apart are
    listed as such.  Misspecification checks (row and column noise, 1/f
    noise, outliers and hot pixels, noise that grows with the signal, a
    flat field, displaced or reshaped sources, a persistence whose decay or
    dependence on fluence is not the law's) then run on the final model:
    what they find is reported as "unexplained", and the effects it could be
    mistaken for are withdrawn, their significance and the reason kept.  The
    gap (chi^2 per pixel) is given with its noise sqrt(2/N).

    OUTDIR gets model.yaml (the simulation's model with the effects found at
    their fitted values: perscli render --model OUTDIR/model.yaml), report.json,
    report.md and PNG figures; it appears whole or not at all.

    \b
    Examples:
      perscli pointings plan --ra 10 --dec -44 --n 2 --sca 7 -o seq.fits
      perscli catalog --pointings seq.fits --bounds 1 256 1 256 -o seq_truth.fits
      perscli render seq_truth.fits --pointings seq.fits --row 0 --bounds 1 256 1 256 --seed 1 -o e0.fits
      perscli render seq_truth.fits --pointings seq.fits --row 1 --bounds 1 256 1 256 --seed 2 \\
          --previous e0.fits -o e1.fits
      perscli render seq_truth.fits --pointings seq.fits --row 0 --bounds 1 256 1 256 --seed 21 \\
          --set dark.current=0.3 -o meas0.fits
      perscli render seq_truth.fits --pointings seq.fits --row 1 --bounds 1 256 1 256 --seed 22 \\
          --set dark.current=0.3 --previous meas0.fits -o meas1.fits
      perscli diagnose meas0.fits meas1.fits --simulated e0.fits --simulated e1.fits -o diag
      perscli diagnose meas0.fits meas1.fits --simulated e0.fits --simulated e1.fits \\
          --model sample_data/roman_detector.yaml -o diag_model
      perscli diagnose ibh7a7lsq_raw.fits -o wfc3_diag

    (e0 and e1 are two exposures of a 256 x 256 cutout of SCA 7 rendered
    with the Roman model, the second with the persistence of the first;
    meas0 and meas1 the same exposures "measured": with a dark current 20
    times Roman's.  ibh7a7lsq_raw.fits is an HST WFC3-IR raw ramp as MAST
    serves it (XO-1, a 138 x 138 subarray), downloaded into the current
    folder: a lone ramp is predicted from its own earliest reads.)
    """
    from ..diagnose.report import diagnose as run, write_report

    inputs = list(measured) + list(simulated) + ([model_spec] if model_spec and os.path.exists(model_spec) else [])
    # diagnose writes its folder beside it and renames it into place: the folder it goes in must exist
    parent = os.path.dirname(os.path.abspath(outdir)) if outdir != "-" else "."
    if not os.path.isdir(parent):
        raise PerscliError(f"{parent}: folder does not exist; create it or choose another output")
    check_output_folder(outdir, overwrite=overwrite, inputs=inputs)
    # a search takes tens of seconds to minutes: one line per step (each candidate fitted in each round, the
    # gaps) on stderr, at a terminal or in a log alike; none with -q
    quiet = verbosity() < 0

    def progress(text):
        if not quiet:
            click.echo(f"diagnose: {text}", err=True)

    options = DiagnoseOptions(fit_pixels=fit_pixels, gain=gain, exptime=exptime, workers=workers)
    outcome = run(measured, simulated=simulated, model_spec=model_spec, options=options, progress=progress)
    write_report(outcome, outdir, overwrite=overwrite)
    report = outcome["report"]
    if not quiet:
        click.echo(f"{report['verdict']}; gap {report['gap_before']:.4g} -> {report['gap_after']:.4g} "
                   f"+- {report['gap_noise']:.2g} (report in {outdir}/report.md)", err=True)
